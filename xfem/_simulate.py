"""Trajectories across cuts: a schedule of cuts on an ``XFEMModel`` and the rollouts between them, differentiable
with respect to the material, the initial state and the forces through the cut events.

A cut changes the DOFs by the duplication of eq. 16-18 (Algorithm 1 line 7): each new DOF copies the x and v of
one old DOF, ``x_new = x_old[dof_source]`` (``CutReport.dof_source``), a gather, so reverse mode passes through
it. Which pieces exist, and so every segment's ``FEMSystem`` and copy map, is decided on the host by the model's
own cuts, once; they are constants for the gradient (the cut solids are placed in the rest configuration, so
they do not depend on the state).

The host phase (``_segments``) yields one ``_Segment`` per cut frame, made by ``_after_cuts``: the system after
the frame's cuts and the map from the previous segment's DOFs. A segment whose system is a JAX function of
parameters (a plane cut placed by a traced point and normal) fits the same ``_run``.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from xfem._backward_euler import FEMSystem, State
from xfem._material import Material
from xfem._rollout import rollout
from xfem._xfem import XFEMModel


class _Segment(NamedTuple):
    """The frames between two cut frames: they start at ``frame`` (1-based), after the cuts of that frame, and
    step ``system``; ``source`` (n,) maps the previous segment's DOFs to this one's (None: the first segment)."""

    frame: int
    system: FEMSystem
    source: np.ndarray | None


# the host phase of the schedules already run, per model: (schedule key, the model's system after them, the
# state the model had before them, the segments); a later call with the same schedule reuses them while the model
# has not been cut since (its cached system is the same object)
_DONE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _after_cuts(model: XFEMModel, solids: Sequence) -> tuple[FEMSystem, np.ndarray]:
    """Cut ``model`` by ``solids`` (one frame's cuts, in order): its system after them, and for each of its DOFs
    the DOF before the first cut it copies (the cuts' ``dof_source`` maps composed)."""
    source = np.arange(len(model.dof_sid))
    for solid in solids:
        report = model.cut(solid)
        if report.dof_source is not None:
            source = source[report.dof_source]
    return model.system(), source


def _segments(model: XFEMModel, schedule, steps: int) -> tuple[list[_Segment], State]:
    """The segments of the schedule (host; cuts the model unless this schedule was run on it already) and the
    model's state before its cuts."""
    frames = sorted({frame for frame, _ in schedule})
    key = (steps, tuple((frame, id(solid)) for frame, solid in schedule))
    done = _DONE.get(model)
    if done is not None and done[0] == key and done[1] is model.system():
        return done[3], done[2]
    segments = [_Segment(1, model.system(), None)]  # pending background cuts take effect first
    start = State(np.array(model.state.x), np.array(model.state.v))
    for frame in frames:
        system, source = _after_cuts(model, [solid for f, solid in schedule if f == frame])
        segments.append(_Segment(frame, system, source))
    _DONE[model] = (key, segments[-1].system, start, segments)
    return segments, start


def simulate(model: XFEMModel, schedule: Sequence[tuple[int, object]], material: Material, h, steps: int, *,
             newton_iterations: int = 1, tolerance: float | None = None, line_search: bool = True,
             forces: Callable[[int, FEMSystem], jax.Array] | None = None, state: State | None = None) -> list[State]:
    """``steps`` frames of a cutting simulation (Algorithm 1 with the cuts given in advance), every frame's state
    returned; differentiable (reverse mode) with respect to ``material``, ``state`` and ``forces``, across the cuts
    (module docstring; each segment's gradient as ``rollout``'s: exact for converged steps, with one Newton
    iteration the converged step's formula at the executed iterate).

    Frame f (1..steps) makes the cuts scheduled at f, then one backward Euler step, as ``run_scene`` and
    ``XFEMModel.step`` do. The model's cuts run on the host: ``simulate`` CUTS ``model`` (afterwards it holds the
    last segment's pieces; its own ``state`` is carried through the cuts but not stepped). Called again with the
    same model and schedule (the same solid objects; e.g. by ``jax.grad`` or an optimizer's iterations), it reuses
    those cuts while the model has not been cut since.

    Args:
        model: the ``XFEMModel``, with the cuts made before the schedule's.
        schedule: ``(frame, solid)`` pairs, 1 <= frame <= steps, solids as ``XFEMModel.cut`` takes them; the cuts
            of one frame are made in the order given.
        material: the ``Material`` (scalars or one value per element of every segment's system).
        h: the positive time step.
        steps: python int >= 1, the number of frames.
        newton_iterations, tolerance, line_search: as ``backward_euler_step``.
        forces: None (each segment's system force, e.g. gravity on its pieces), or a function ``(k, system)`` of a
            segment's index and ``FEMSystem`` returning its forces, (n_k, 3) or (frames_k, n_k, 3) per frame, as
            ``rollout`` takes them; it may close over traced parameters.
        state: the ``State`` at frame 0 on the DOFs before the schedule's cuts; None: the model's state then.
    Returns:
        One ``State`` per segment (the frames before the first cut frame, then from each cut frame to the next),
        x and v of shape (frames_k, n_k, 3), n_k the DOFs after that segment's cuts; the segments' frames concatenated
        are frames 1..steps. A segment starting at frame 1 (a cut at frame 1) leaves the first one with 0 frames.
    """
    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel (xfem_model), got {type(model).__name__}")
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    schedule = list(schedule)
    for entry in schedule:
        if (not isinstance(entry, tuple) or len(entry) != 2 or not isinstance(entry[0], int)
                or isinstance(entry[0], bool) or not 1 <= entry[0] <= steps):
            raise ValueError(f"schedule: expected (frame, solid) pairs with an int frame in [1, {steps}], got {entry!r}")
    if forces is not None and not callable(forces):
        raise ValueError("forces: expected None or a function (segment index, FEMSystem) -> forces")
    with jax.ensure_compile_time_eval():  # host work, also when simulate is traced (jit, grad)
        segments, start = _segments(model, schedule, steps)
    if state is None:
        state = start
    elif not isinstance(state, State):
        raise ValueError(f"state: expected None or a State, got {type(state).__name__}")
    return _run(segments, state, material, h, steps, newton_iterations, tolerance, line_search, forces)


def _run(segments: list[_Segment], state: State, material: Material, h, steps: int, newton_iterations: int,
         tolerance, line_search: bool, forces) -> list[State]:
    """The JAX phase: each segment's rollout from the previous one's last state, mapped by its copy map."""
    trajectory = []
    for k, segment in enumerate(segments):
        if segment.source is not None:  # Algorithm 1 line 7: the new DOFs copy their source's x and v
            source = jnp.asarray(segment.source)
            state = State(state.x[source], state.v[source])
        end = segments[k + 1].frame if k + 1 < len(segments) else steps + 1
        frames = rollout(segment.system, state, material, h, end - segment.frame, newton_iterations=newton_iterations,
                         tolerance=tolerance, line_search=line_search,
                         forces=None if forces is None else forces(k, segment.system))
        trajectory.append(frames)
        if end > segment.frame:
            state = State(frames.x[-1], frames.v[-1])
    return trajectory
