"""Trajectories across cuts: a schedule of cuts on an ``XFEMModel`` and the rollouts between them, differentiable
with respect to the material, the initial state and the forces through the cut events, and with respect to the
planes of plane cuts.

A cut changes the DOFs by the duplication of eq. 16-18 (Algorithm 1 line 7): each new DOF copies the x and v of
one old DOF, ``x_new = x_old[dof_source]`` (``CutReport.dof_source``), a gather, so reverse mode passes through
it. Which pieces exist, and so every segment's ``FEMSystem`` and copy map, is decided on the host by the model's
own cuts, once; they are constants for the gradient (the cut solids are placed in the rest configuration, so
they do not depend on the state).

Plane cuts (``plane_cuts=[(frame, point, normal, epsilon), ...]``, slabs as ``plane_cut_solid`` makes them) are
placed by parameters: the pieces they make are found on the host at the given (concrete) planes by
``xfem.plane_cuts`` on a copy of the model, together with the schedule's solids in time order, and each segment's
system is then ``PlaneCuts.systems(points, normals)``, a JAX function of every plane so far; the gradient with
respect to each point and normal is exact for the combinatorics found (``xfem._cut_system``).

The host phase (``_segments``, ``_plane_segments``) yields one ``_Segment`` per cut frame: the system after the
frame's cuts (for plane cuts, the index of the frame's last cut in ``PlaneCuts.systems``) and the map from the
previous segment's DOFs; ``_run`` rolls them out. With plane cuts the two phases are split in the open:
``plane_cut_simulation`` runs the host phase at concrete planes and returns a ``PlaneCutSimulation``, whose call
is the JAX phase alone (planes in, trajectory out), so it can be jitted and vmapped over the planes; its pieces
are checked to hold at the planes (``PlaneCuts.holds``): concrete planes where they do not are cut anew, traced
ones raise a runtime error (``require``). ``simulate`` with plane cuts keeps one per model and schedule.

Every segment's steps converge by default (``rollout``), so the implicit gradients are the derivatives of the
trajectory computed; ``newton_iterations=1, tolerance=None`` is the paper's step.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import concrete_or_error
from jaxtyping import Array, ArrayLike, Bool, Float

from _jaxcga_shared.checks import require
from xfem._backward_euler import _NEWTON_ITERATIONS, FEMSystem, State
from xfem._cut_system import PlaneCuts, _concrete, _plane, plane_cuts
from xfem._material import Material
from xfem._rollout import rollout
from xfem._xfem import XFEMModel


class _Segment(NamedTuple):
    """The frames between two cut frames: they start at ``frame`` (1-based), after the cuts of that frame, and
    step ``system`` (an ``FEMSystem``; with plane cuts, the index of the frame's last cut in
    ``PlaneCuts.systems``, or None before the first cut: the model's system); ``source`` (n,) maps the previous
    segment's DOFs to this one's (None: the same DOFs)."""

    frame: int
    system: FEMSystem | int | None
    source: np.ndarray | None


# the host phase of the schedules already run, per model: (schedule key, the model's system after them, the
# state the model had before them, the segments); a later call with the same schedule reuses them while the model
# has not been cut since (its cached system is the same object)
_DONE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
# with plane cuts, per model: (schedule key, its PlaneCutSimulation); a later call reuses it while the model has not
# been cut (it finds the pieces again where they do not hold at the planes)
_PLANES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


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


def _plane_segments(model: XFEMModel, schedule, planes) -> tuple[list[_Segment], PlaneCuts]:
    """The segments of a schedule with plane cuts at the concrete planes ``planes`` ((frame, point, normal,
    epsilon), numpy, sorted by frame) and the ``PlaneCuts`` (host; the model is left uncut). A frame's solids are
    cut before its planes."""
    frames = sorted({frame for frame, _ in schedule} | {frame for frame, *_ in planes})
    entries, ends = [], []  # plane_cuts' entries in time order; the index of each frame's last cut
    for frame in frames:
        entries += [solid for f, solid in schedule if f == frame]
        entries += [(point, normal, epsilon) for f, point, normal, epsilon in planes if f == frame]
        ends.append(len(entries) - 1)
    cuts = plane_cuts(model, entries)
    segments, first = [_Segment(1, None, None)], 0
    for frame, end in zip(frames, ends):
        source = None  # the frame's cuts' DOF copy maps composed
        for report in cuts.reports[first : end + 1]:
            if report.dof_source is not None:
                source = report.dof_source if source is None else source[report.dof_source]
        segments.append(_Segment(frame, end, source))
        first = end + 1
    return segments, cuts


_CHANGED = (
    "planes: they moved past a node or a piece's vertex since the pieces were found (PlaneCuts.holds is False), "
    "so the prepared cuts no longer describe them; call the simulation with concrete planes (it cuts again) or "
    "prepare a new one there (plane_cut_simulation)"
)


class PlaneCutSimulation:
    """``simulate`` with plane cuts, its host phase done once (``plane_cut_simulation`` makes it): calling it with
    the planes runs the JAX phase only, so it can be jitted, vmapped over planes and differentiated in them.

    The pieces (which elements the slabs split, the enrichment, the DOF copy maps) are those found at the planes
    it was prepared or last cut at, ``points`` and ``normals``; the systems are the ``PlaneCuts`` replay, a JAX
    function of the planes, exact while ``holds`` is True (no node or piece vertex crossed a slab's face). Called
    with concrete planes (also under eager ``jax.grad``) where it does not hold, it cuts again at them; with
    traced planes (jit, vmap) it cannot, and raises a runtime error naming the planes instead of returning a
    trajectory of other pieces.

    Attributes:
        frames: (k,) the frame of each plane cut, in the order given.
        epsilons: (k,) their slab thicknesses.
        points, normals: (k, 3) the planes the pieces were found at (numpy), in the order given.
        cuts: the ``PlaneCuts`` found there (its ``model``: the copy cut by every cut; ``systems``), the cuts in time
            order (the plane cuts by frame).
        steps: the number of frames.
    """

    def __init__(self, model: XFEMModel, schedule: list, planes: list, steps: int):
        self._model, self._schedule, self.steps = model, schedule, steps
        self.frames = np.array([frame for frame, *_ in planes], np.int64)
        self.epsilons = np.array([epsilon for *_, epsilon in planes], np.float64)
        self._order = np.argsort(self.frames, kind="stable")  # the cuts' time order
        self._system = model.system()  # pending background cuts take effect first
        self._start = State(np.array(model.state.x), np.array(model.state.v))
        self._cut(np.stack([p[1] for p in planes]), np.stack([p[2] for p in planes]))

    def _cut(self, points: np.ndarray, normals: np.ndarray) -> None:
        """Find the pieces at these concrete planes (given order; host)."""
        if self._model.system() is not self._system:
            raise ValueError("model: cut since the plane cut simulation was prepared; prepare a new one")
        o = self._order
        planes = [(int(self.frames[k]), points[k], normals[k], float(self.epsilons[k])) for k in o]
        self._segments, self.cuts = _plane_segments(self._model, self._schedule, planes)
        self.points, self.normals = points, normals

    def _planes(self, points, normals):
        """The checked planes (given order) and, when concrete, their numpy values (else None)."""
        k = len(self.frames)
        if jnp.shape(points) != (k, 3) or jnp.shape(normals) != (k, 3):
            raise ValueError(
                f"points, normals: expected shape ({k}, 3) (one plane per plane cut), got {jnp.shape(points)} and "
                f"{jnp.shape(normals)}"
            )
        try:
            concrete = [
                np.asarray(concrete_or_error(None, a, name), np.float64)
                for a, name in ((points, "points"), (normals, "normals"))
            ]
        except jax.errors.ConcretizationTypeError:
            return points, normals, None
        for j in range(k):  # ValueErrors naming the plane
            _plane(concrete[0][j], concrete[1][j], self.epsilons[j], f" (plane_cuts[{j}])")
        return points, normals, concrete

    def holds(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> Bool[Array, ""]:
        """Whether the pieces found describe these planes (``PlaneCuts.holds``; a JAX bool, jit- and vmap-able).

        Args:
            points: (k, 3) the planes' points, in the order of the plane cuts given.
            normals: (k, 3) their unit normals.
        """
        points, normals, _ = self._planes(points, normals)
        o = jnp.asarray(self._order)
        return self.cuts.holds(jnp.asarray(points)[o], jnp.asarray(normals)[o])

    def __call__(
        self,
        points: Float[ArrayLike, "k 3"],
        normals: Float[ArrayLike, "k 3"],
        material: Material,
        h: float | Float[Array, ""],
        *,
        newton_iterations: int = _NEWTON_ITERATIONS,
        tolerance: float | Literal["auto"] | None = "auto",
        line_search: bool = True,
        forces: Callable[[int, FEMSystem], Float[Array, "n 3"] | Float[Array, "frames n 3"]] | None = None,
        state: State | None = None,
    ) -> list[State]:
        """The trajectory at these planes (``simulate``'s result); jit-, vmap- and grad-able in the planes and
        the other arguments.

        Args:
            points: (k, 3) the planes' points, in the order of the plane cuts given (JAX values to differentiate).
            normals: (k, 3) their unit normals (the gradient with respect to a normal is tangent to the sphere).
            material: as ``simulate``; state None:
                the model's state when the simulation was prepared.
            h: see ``material``.
            newton_iterations: see ``material``.
            tolerance: see ``material``.
            line_search: see ``material``.
            forces: see ``material``.
            state: see ``material``.
        Returns:
            One ``State`` per segment, as ``simulate``.
        """
        points, normals, concrete = self._planes(points, normals)
        o = jnp.asarray(self._order)
        if concrete is not None:
            with jax.ensure_compile_time_eval():  # host work, also under eager jax.grad
                if not bool(self.cuts.holds(concrete[0][self._order], concrete[1][self._order])):
                    self._cut(*concrete)
            points, normals = jnp.asarray(points)[o], jnp.asarray(normals)[o]
        else:
            points, normals = jnp.asarray(points)[o], jnp.asarray(normals)[o]
            points = require(points, (~self.cuts.holds(points, normals), _CHANGED))
        systems = self.cuts.systems(points, normals)
        segments = [  # a plane segment's system is the index of its cut (_plane_segments)
            s._replace(system=self._system if s.system is None else systems[s.system])  # pyright: ignore[reportCallIssue, reportArgumentType]
            for s in self._segments
        ]
        if state is None:
            state = self._start
        elif not isinstance(state, State):
            raise ValueError(f"state: expected None or a State, got {type(state).__name__}")
        return _run(segments, state, material, h, self.steps, newton_iterations, tolerance, line_search, forces)


def plane_cut_simulation(
    model: XFEMModel,
    schedule: Sequence[tuple[int, object]],
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]],
    steps: int,
) -> PlaneCutSimulation:
    """Prepare ``simulate(model, schedule, ..., plane_cuts=plane_cuts)`` for calls under ``jax.jit`` and
    ``jax.vmap`` over the planes: the pieces are found on the host at these (concrete) planes, once; the returned
    ``PlaneCutSimulation`` maps planes (points, normals) to the trajectory in JAX (``jax.jit(jax.vmap(jax.grad(
    loss)))`` over a batch of planes works), raising where the planes moved past the pieces found.

    Args:
        model: the ``XFEMModel``, left uncut (its cuts so far and its state are the simulation's start).
        schedule: ``(frame, solid)`` pairs as ``simulate`` takes them.
        plane_cuts: ``(frame, point, normal, epsilon)`` as ``simulate`` takes them, point and normal concrete.
        steps: python int >= 1, the number of frames.
    Returns:
        The ``PlaneCutSimulation``.
    """
    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel (xfem_model), got {type(model).__name__}")
    _check_steps(steps)
    schedule = _check_schedule(schedule, steps)
    planes = _check_planes(list(plane_cuts), steps, _PREPARE)
    if not planes:
        raise ValueError("plane_cuts: expected at least one (frame, point, normal, epsilon)")
    return PlaneCutSimulation(model, schedule, [(f, *c) for f, _, _, c in planes], steps)


def _scheduled(entry, size: int, steps: int) -> bool:
    """Whether ``entry`` is a tuple of ``size`` items whose first is an int frame in [1, steps]."""
    return (
        isinstance(entry, tuple)
        and len(entry) == size
        and isinstance(entry[0], int)
        and not isinstance(entry[0], bool)
        and 1 <= entry[0] <= steps
    )


def _check_planes(planes, steps: int, advice: str) -> list:
    """The checked ``plane_cuts``: (frame, point, normal, epsilon) in the order given, the point and normal as given
    (possibly traced) and their concrete values (a ValueError with ``advice`` where they have none)."""
    checked = []
    for k, entry in enumerate(planes):
        if not _scheduled(entry, 4, steps):
            raise ValueError(
                f"plane_cuts: expected (frame, point, normal, epsilon) with an int frame in [1, {steps}], got {entry!r}"
            )
        frame, point, normal, epsilon = entry
        name = f" (plane_cuts[{k}])"
        concrete = _plane(
            _concrete("point" + name, point, advice), _concrete("normal" + name, normal, advice), epsilon, name
        )
        checked.append((frame, point, normal, concrete))
    return checked


def _check_steps(steps) -> None:
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")


def _check_schedule(schedule, steps: int) -> list:
    schedule = list(schedule)
    for entry in schedule:
        if not _scheduled(entry, 2, steps):
            raise ValueError(
                f"schedule: expected (frame, solid) pairs with an int frame in [1, {steps}], got {entry!r}"
            )
    return schedule


_UNDER_JIT = (
    "simulate finds the pieces of plane cuts on the host at concrete planes: prepare them once with "
    "xfem.plane_cut_simulation and call its result under jax.jit or jax.vmap, or differentiate simulate by eager "
    "jax.grad"
)
_PREPARE = "plane_cut_simulation finds the pieces at concrete planes: call it outside jax.jit and jax.vmap"


def simulate(
    model: XFEMModel,
    schedule: Sequence[tuple[int, object]],
    material: Material,
    h: float | Float[Array, ""],
    steps: int,
    *,
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]] = (),
    newton_iterations: int = _NEWTON_ITERATIONS,
    tolerance: float | Literal["auto"] | None = "auto",
    line_search: bool = True,
    forces: Callable[[int, FEMSystem], Float[Array, "n 3"] | Float[Array, "frames n 3"]] | None = None,
    state: State | None = None,
) -> list[State]:
    """``steps`` frames of a cutting simulation (Algorithm 1 with the cuts given in advance), every frame's state
    returned; differentiable (reverse mode) with respect to ``material``, ``state``, ``forces`` and the points and
    normals of ``plane_cuts``, across the cuts (module docstring; each segment's gradient as ``rollout``'s: exact
    for converged steps, the default; with the paper's one Newton iteration the converged step's formula at the
    executed iterate; a plane's exact for the pieces found at it).

    Frame f (1..steps) makes the cuts scheduled at f (the solids of ``schedule``, then the slabs of
    ``plane_cuts``, each in the order given), then one backward Euler step, as ``run_scene`` and
    ``XFEMModel.step`` do. Without plane cuts the model's cuts run on the host: ``simulate`` CUTS ``model``
    (afterwards it holds the last segment's pieces; its own ``state`` is carried through the cuts but not
    stepped); called again with the same model and schedule (the same solid objects; e.g. by ``jax.grad`` or an
    optimizer's iterations), it reuses those cuts while the model has not been cut since. With plane cuts, every
    cut of the schedule is made on a copy (``xfem.plane_cuts``) and ``model`` is left uncut: each call finds the
    pieces at its concrete planes (a point and normal traced by eager ``jax.grad`` have concrete values; under
    ``jax.jit`` or ``jax.vmap`` use ``plane_cut_simulation``), or reuses the previous call's while they still hold
    there (``PlaneCuts.holds``: the planes moved without crossing a node or a piece's vertex); which pieces exist is
    a constant of the gradient.

    Args:
        model: the ``XFEMModel``, with the cuts made before the schedule's.
        schedule: ``(frame, solid)`` pairs, 1 <= frame <= steps, solids as ``XFEMModel.cut`` takes them; the cuts
            of one frame are made in the order given.
        material: the ``Material`` (scalars or one value per element of every segment's system).
        h: the positive time step.
        steps: python int >= 1, the number of frames.
        plane_cuts: ``(frame, point, normal, epsilon)``: a slab of thickness epsilon > 0 across the whole body
            about the plane through point (3,) with the unit normal (3,) (``plane_cut_solid`` with an extent
            covering the body), made at that frame after the frame's solids; point and normal may be JAX values
            to differentiate (the gradient with respect to a normal is tangent to the unit sphere).
        newton_iterations: as ``backward_euler_step`` (by default every step converges;
            ``newton_iterations=1, tolerance=None`` is the paper's single iteration, approximate for gradients).
        tolerance: see ``newton_iterations``.
        line_search: see ``newton_iterations``.
        forces: None (each segment's system force, e.g. gravity on its pieces), or a function ``(k, system)`` of a
            segment's index and ``FEMSystem`` returning its forces, (n_k, 3) or (frames_k, n_k, 3) per frame, as
            ``rollout`` takes them; it may close over traced parameters.
        state: the ``State`` at frame 0 on the DOFs before the schedule's cuts; None: the model's state then.
    Returns:
        One ``State`` per segment (the frames before the first cut frame, then from each cut frame to the next),
        x and v of shape (frames_k, n_k, 3), n_k the DOFs after that segment's cuts, and its steps' ``SolveStats``
        (frames_k,); the segments' frames concatenated are frames 1..steps. A segment starting at frame 1 (a cut at
        frame 1) leaves the first one with 0 frames.
    """
    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel (xfem_model), got {type(model).__name__}")
    _check_steps(steps)
    schedule = _check_schedule(schedule, steps)
    planes = _check_planes(list(plane_cuts), steps, _UNDER_JIT)
    options = dict(
        newton_iterations=newton_iterations, tolerance=tolerance, line_search=line_search, forces=forces, state=state
    )
    if planes:
        with jax.ensure_compile_time_eval():  # host work, also when simulate is traced (eager grad)
            simulation = _simulation(model, schedule, planes, steps)
        points = jnp.stack([jnp.asarray(p) for _, p, _, _ in planes])
        normals = jnp.stack([jnp.asarray(n) for _, _, n, _ in planes])
        return simulation(points, normals, material, h, **options)  # pyright: ignore[reportArgumentType]
    with jax.ensure_compile_time_eval():  # host work, also when simulate is traced (jit, grad)
        segments, start = _segments(model, schedule, steps)
    if state is None:
        state = start
    elif not isinstance(state, State):
        raise ValueError(f"state: expected None or a State, got {type(state).__name__}")
    return _run(segments, state, material, h, steps, newton_iterations, tolerance, line_search, forces)


def _simulation(model: XFEMModel, schedule: list, planes: list, steps: int) -> PlaneCutSimulation:
    """The ``PlaneCutSimulation`` of this model, schedule and plane cuts: the previous call's while the model has
    not been cut since (it cuts again where its pieces do not hold at the planes), else a new one."""
    key = (
        steps,
        tuple((frame, id(solid)) for frame, solid in schedule),
        tuple((frame, concrete[2]) for frame, _, _, concrete in planes),
    )
    done = _PLANES.get(model)
    if done is not None and done[0] == key and done[1]._system is model.system():
        return done[1]
    simulation = PlaneCutSimulation(model, schedule, [(f, *c) for f, _, _, c in planes], steps)
    _PLANES[model] = (key, simulation)
    return simulation


def _run(
    segments: list[_Segment],
    state: State,
    material: Material,
    h,
    steps: int,
    newton_iterations: int,
    tolerance,
    line_search: bool,
    forces: Callable[[int, FEMSystem], Array] | None,
) -> list[State]:
    """The JAX phase: each segment's rollout from the previous one's last state, mapped by its copy map."""
    if forces is not None and not callable(forces):
        raise ValueError("forces: expected None or a function (segment index, FEMSystem) -> forces")
    trajectory = []
    state = State(jnp.asarray(state.x), jnp.asarray(state.v))  # numpy's indexing cannot take a traced map
    for k, segment in enumerate(segments):
        if segment.source is not None:  # Algorithm 1 line 7: the new DOFs copy their source's x and v
            source = jnp.asarray(segment.source)
            state = State(state.x[source], state.v[source])
        end = segments[k + 1].frame if k + 1 < len(segments) else steps + 1
        system = segment.system
        assert isinstance(system, FEMSystem)  # simulate and PlaneCutSimulation resolved every segment's system
        frames = rollout(
            system,
            state,
            material,
            h,
            end - segment.frame,
            newton_iterations=newton_iterations,
            tolerance=tolerance,
            line_search=line_search,
            forces=None if forces is None else forces(k, system),
        )
        trajectory.append(frames)
        if end > segment.frame:
            state = State(frames.x[-1], frames.v[-1])
    return trajectory
