"""Trajectories across cuts: a schedule of cuts on an ``XFEMModel`` and the rollouts between them, differentiable
with respect to the material, the initial state and the forces through the cut events, and with respect to the
planes of plane cuts.

A cut changes the DOFs by the duplication of eq. 16-18 (Algorithm 1 line 7): each new DOF copies the x and v of
one old DOF, ``x_new = x_old[dof_source]`` (``CutReport.dof_source``), a gather, so reverse mode passes through
it. Which pieces exist, and so every segment's ``FEMSystem`` and copy map, is decided on the host by the model's
own cuts; they are constants for the gradient (the cut solids are placed in the rest configuration, so they do
not depend on the state).

Plane cuts (``plane_cuts=[(frame, point, normal, epsilon), ...]``, slabs as ``plane_cut_solid`` makes them) are
placed by parameters: the pieces they make are found on the host at the given (concrete) planes by
``xfem.plane_cuts`` on a copy of the model, together with the schedule's solids in time order, and each segment's
system is then ``PlaneCuts.systems(points, normals)``, a JAX function of every plane so far; the gradient with
respect to each point and normal is exact for the combinatorics found (``xfem._cut_system``).

The two phases are split in the open. The host phase, ``plan_cuts``, returns a ``CutPlan``: one ``_Segment`` per cut
frame (the system after the frame's cuts, for plane cuts the index of the frame's last cut in ``PlaneCuts.systems``,
and the map from the previous segment's DOFs). The JAX phase, ``simulate(..., plan=plan)`` (``_run``), rolls the
segments out. The caller holds the plan and passes it to every call of one schedule (a loss under ``jax.grad``, an
optimizer's iterations), so the Booleans run once; nothing in this module keeps a plan or a model, and a plan keeps
the model and the solids it was made from, so it is checked against the call's by identity and cannot go stale.
Every cut is made on a copy of the model (``xfem._cut_system._copy``), which the plan keeps (``CutPlan.model``): the
caller's model is never cut, so ``simulate`` is a function of its arguments. ``simulate`` without a plan makes one
for the call. With plane cuts the plan's pieces are checked to hold at the call's planes (``PlaneCuts.holds``):
concrete planes where they do not are refused (make a new plan there), traced ones raise a runtime error
(``require``). ``plane_cut_simulation`` wraps a plan in a ``PlaneCutSimulation``, a function of the planes alone
that makes a new plan where concrete planes moved past its pieces.

Every segment's steps converge by default (``rollout``), so the implicit gradients are the derivatives of the
trajectory computed; ``newton_iterations=1, tolerance=None`` is the paper's step.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.extend.core import concrete_or_error
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from _jaxcga_shared.checks import require
from xfem._backward_euler import _NEWTON_ITERATIONS, FEMSystem, State
from xfem._cut_system import PlaneCuts, _copy, _plane, plane_cuts
from xfem._cuts import _positive
from xfem._material import Material
from xfem._rollout import rollout
from xfem._xfem import XFEMModel


class _Segment(NamedTuple):
    """The frames between two cut frames: they start at ``frame`` (1-based), after the cuts of that frame, and
    step ``system`` (an ``FEMSystem``; with plane cuts, the index of the frame's last cut in
    ``PlaneCuts.systems``; None before the first cut: the model's system before the schedule); ``source`` (n,)
    maps the previous segment's DOFs to this one's (None: the same DOFs)."""

    frame: int
    system: FEMSystem | int | None
    source: np.ndarray | None


@dataclasses.dataclass(frozen=True, eq=False)
class CutPlan:
    """The host phase of ``simulate`` for one model, schedule, step count and set of plane cuts (``plan_cuts``
    makes it): the pieces each cut frame makes (the Booleans, run once), each segment's ``FEMSystem`` and the DOF
    copy maps between segments. ``simulate(..., plan=plan)`` runs the JAX phase alone on it, so a loss evaluated
    many times (``jax.grad``, an optimizer's iterations) cuts once. The caller owns it: nothing else keeps it, and
    dropping it frees its systems.

    The cuts are made on a copy of the model, which the plan keeps (``model``); the model it was made for
    (``made_for``) is left uncut. It keeps that model and the schedule's solids; ``simulate`` refuses it (a
    ValueError naming ``plan``) for another model (compared by identity), schedule (frames, and solids by
    identity), step count or set of plane cuts (frames and thicknesses). Make a new plan when the schedule
    changes, when the model was cut since (``simulate`` refuses the plan then, naming ``model``), and, with plane
    cuts, when the planes move past the pieces found (``holds`` is False: ``simulate`` refuses such concrete
    planes, and raises a runtime error for traced ones, rather than return a trajectory of other pieces).

    Attributes:
        made_for: the caller's ``XFEMModel`` it was made for (compared by identity; never cut by the plan).
        model: the copy of ``made_for`` cut by every cut of the plan, in time order (the schedule's solids and the
            slabs at ``points``, ``normals``): the last segment's pieces and DOF numbering (``dof_node``,
            ``components``, ``piece_surfaces``) for host queries of a trajectory; its state is ``start`` carried
            through the cuts, not stepped. Closed (``XFEMModel.close``: its Boolean threads ended), so it neither
            cuts in parallel nor steps. With plane cuts it is ``cuts.model``.
        schedule: the ``(frame, solid)`` pairs, as given.
        steps: the number of frames.
        frames: (k,) int64 the frame of each plane cut, in the order given (k = 0 without plane cuts).
        epsilons: (k,) float64 their slab thicknesses.
        points: (k, 3) float64 the planes the pieces were found at, in the order given.
        normals: (k, 3) float64 their unit normals.
        cuts: the ``PlaneCuts`` found there (its ``model``: the copy cut by every cut; ``systems``: the system after
            each cut as a JAX function of the planes), the cuts in time order (a frame's solids, then its planes);
            None without plane cuts.
        start: the model's ``State`` before the schedule's cuts (numpy), ``simulate``'s start by default.
        initial: the model's ``FEMSystem`` before the schedule's cuts (the segment before the first cut frame).
        segments: one ``(frame, system, source)`` per segment: its first frame; its ``FEMSystem`` (with plane cuts,
            the index of its frame's last cut in ``cuts.systems``; None for the first segment: ``initial``); the
            (n_k,) int64 map from the previous segment's DOFs to its own (None: the same DOFs).
        model_cuts: the number of cuts of ``made_for`` (``len(made_for.cuts)``) when planned: a model cut since is
            refused.
    """

    made_for: XFEMModel
    model: XFEMModel
    schedule: tuple[tuple[int, object], ...]
    steps: int
    frames: Int[np.ndarray, " k"]
    epsilons: Float[np.ndarray, " k"]
    points: Float[np.ndarray, "k 3"]
    normals: Float[np.ndarray, "k 3"]
    cuts: PlaneCuts | None
    start: State
    initial: FEMSystem
    segments: tuple[_Segment, ...]
    model_cuts: int

    def holds(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> Bool[Array, ""]:
        """Whether the plan's pieces describe these planes (``PlaneCuts.holds``; a JAX bool, jit- and
        vmap-able); True without plane cuts (k = 0).

        Args:
            points: (k, 3) the planes' points, in the order of the plane cuts given.
            normals: (k, 3) their unit normals.
        Returns:
            A JAX bool: no node or vertex of a piece crossed a slab's face since the pieces were found.
        """
        points, normals, _ = _checked_planes(self, points, normals)
        if self.cuts is None:
            return jnp.asarray(True)
        o = jnp.asarray(_time_order(self.frames))
        return self.cuts.holds(jnp.asarray(points)[o], jnp.asarray(normals)[o])


def _time_order(frames: np.ndarray) -> np.ndarray:
    """The plane cuts' order in time (by frame; a frame's in the order given)."""
    return np.argsort(frames, kind="stable")


def _checked_planes(plan: CutPlan, points, normals):
    """The plan's planes given as (k, 3) arrays, checked, and, when concrete, their numpy values (else None)."""
    k = len(plan.frames)
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
        _plane(concrete[0][j], concrete[1][j], plan.epsilons[j], f" (plane_cuts[{j}])")
    return points, normals, concrete


def _after_cuts(model: XFEMModel, solids: Sequence) -> tuple[FEMSystem, np.ndarray]:
    """Cut ``model`` by ``solids`` (one frame's cuts, in order): its system after them, and for each of its DOFs
    the DOF before the first cut it copies (the cuts' ``dof_source`` maps composed)."""
    source = np.arange(len(model.dof_sid))
    for solid in solids:
        report = model.cut(solid)
        if report.dof_source is not None:
            source = source[report.dof_source]
    return model.system(), source


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


def _plan(model: XFEMModel, schedule: list, steps: int, planes: list, start: State | None = None) -> CutPlan:
    """The ``CutPlan`` of checked arguments: ``planes`` (frame, point, normal, epsilon), concrete numpy, in the
    order given; ``start``: the state before the cuts (None: the model's now). Host work, also when traced; the
    cuts are made on a copy, ``model`` is left as it is."""
    with jax.ensure_compile_time_eval():  # the systems' arrays are constants, also when simulate is traced
        if start is None:
            start = State(np.array(model.state.x), np.array(model.state.v))
        initial = model.system()
        frames = np.array([frame for frame, *_ in planes], np.int64)
        epsilons = np.array([epsilon for *_, epsilon in planes], np.float64)
        points = np.array([point for _, point, _, _ in planes], np.float64).reshape(-1, 3)
        normals = np.array([normal for _, _, normal, _ in planes], np.float64).reshape(-1, 3)
        cuts = None
        if planes:
            in_time = [planes[k] for k in _time_order(frames)]
            segments, cuts = _plane_segments(model, schedule, in_time)
            copy = cuts.model
        else:
            segments = [_Segment(1, None, None)]
            # its Boolean threads end with the cuts; the plan keeps its pieces for host queries
            with _copy(model) as copy:
                for frame in sorted({frame for frame, _ in schedule}):
                    system, source = _after_cuts(copy, [solid for f, solid in schedule if f == frame])
                    segments.append(_Segment(frame, system, source))
    return CutPlan(
        made_for=model,
        model=copy,
        schedule=tuple(schedule),
        steps=steps,
        frames=frames,
        epsilons=epsilons,
        points=points,
        normals=normals,
        cuts=cuts,
        start=start,
        initial=initial,
        segments=tuple(segments),
        model_cuts=len(model.cuts),
    )


def plan_cuts(
    model: XFEMModel,
    schedule: Sequence[tuple[int, object]],
    steps: int,
    *,
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]] = (),
) -> CutPlan:
    """The host phase of ``simulate(model, schedule, ..., steps, plane_cuts=plane_cuts)``, done once: the cuts'
    Booleans, each segment's system and the DOF copy maps, for ``simulate(..., plan=plan)`` to run on as often as
    needed (``CutPlan``: what it holds and when to make a new one).

    Every cut is made on a copy of ``model`` (the schedule's solids in frame order, with plane cuts by
    ``xfem.plane_cuts`` at these concrete planes), and ``model`` is left uncut: the cut copy is the plan's
    ``model`` (the last segment's pieces and DOFs, for host queries).

    Args:
        model: the ``XFEMModel``, with the cuts made before the schedule's (made again on the copy); its state is
            the plan's ``start``.
        schedule: ``(frame, solid)`` pairs, 1 <= frame <= steps, solids as ``XFEMModel.cut`` takes them; the cuts
            of one frame are made in the order given.
        steps: python int >= 1, the number of frames.
        plane_cuts: ``(frame, point, normal, epsilon)`` as ``simulate`` takes them, point (3,) and normal (3,)
            concrete (the planes the pieces are found at; ``simulate`` may then take other planes where the pieces
            hold).
    Returns:
        The ``CutPlan``.
    """
    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel (xfem_model), got {type(model).__name__}")
    _check_steps(steps)
    schedule = _check_schedule(schedule, steps)
    planes = _check_planes(list(plane_cuts), steps, _PREPARE)
    return _plan(model, schedule, steps, [(f, *c) for f, _, _, c in planes])


_CHANGED = (
    "planes: they moved past a node or a piece's vertex since the pieces were found (PlaneCuts.holds is False), "
    "so the plan's cuts no longer describe them; make a new plan at concrete planes there (xfem.plan_cuts, "
    "xfem.plane_cut_simulation)"
)


class PlaneCutSimulation:
    """``simulate`` with plane cuts as a function of the planes, on a ``CutPlan`` (``plane_cut_simulation`` makes
    it): calling it with the planes runs the JAX phase only, so it can be jitted, vmapped over planes and
    differentiated in them.

    The pieces (which elements the slabs split, the enrichment, the DOF copy maps) are its ``plan``'s, found at
    ``points`` and ``normals``; the systems are the ``PlaneCuts`` replay, a JAX function of the planes, exact while
    ``holds`` is True (no node or piece vertex crossed a slab's face). Called with concrete planes (also under
    eager ``jax.grad``) where it does not hold, it makes a new plan at them (on the host; it replaces ``plan``);
    with traced planes (jit, vmap) it cannot, and raises a runtime error naming the planes instead of returning a
    trajectory of other pieces.

    Attributes:
        plan: the ``CutPlan`` it runs on.
        frames: (k,) the frame of each plane cut, in the order given.
        epsilons: (k,) their slab thicknesses.
        points, normals: (k, 3) the planes the pieces were found at (numpy), in the order given.
        cuts: the ``PlaneCuts`` found there (its ``model``: the copy cut by every cut; ``systems``), the cuts in time
            order (the plane cuts by frame).
        steps: the number of frames.
    """

    def __init__(self, plan: CutPlan):
        if not isinstance(plan, CutPlan) or plan.cuts is None:
            raise ValueError("plan: expected a CutPlan with plane cuts (xfem.plan_cuts(..., plane_cuts=...))")
        self.plan = plan

    @property
    def frames(self) -> Int[np.ndarray, " k"]:
        """(k,) the frame of each plane cut, in the order given."""
        return self.plan.frames

    @property
    def epsilons(self) -> Float[np.ndarray, " k"]:
        """(k,) their slab thicknesses."""
        return self.plan.epsilons

    @property
    def points(self) -> Float[np.ndarray, "k 3"]:
        """(k, 3) the planes the pieces were found at (numpy), in the order given."""
        return self.plan.points

    @property
    def normals(self) -> Float[np.ndarray, "k 3"]:
        """(k, 3) their unit normals."""
        return self.plan.normals

    @property
    def cuts(self) -> PlaneCuts:
        """The ``PlaneCuts`` found there."""
        assert self.plan.cuts is not None  # a plan with plane cuts (__init__)
        return self.plan.cuts

    @property
    def steps(self) -> int:
        """The number of frames."""
        return self.plan.steps

    def holds(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> Bool[Array, ""]:
        """Whether the pieces found describe these planes (``CutPlan.holds``; a JAX bool, jit- and vmap-able).

        Args:
            points: (k, 3) the planes' points, in the order of the plane cuts given.
            normals: (k, 3) their unit normals.
        Returns:
            A JAX bool.
        """
        return self.plan.holds(points, normals)

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
        plan = self.plan
        points, normals, concrete = _checked_planes(plan, points, normals)
        if concrete is not None:
            with jax.ensure_compile_time_eval():  # host work, also under eager jax.grad
                if not bool(plan.holds(*concrete)):
                    self.plan = plan = _replan(plan, *concrete)
        options = dict(
            newton_iterations=newton_iterations,
            tolerance=tolerance,
            line_search=line_search,
            forces=forces,
            state=state,
        )
        return _run_plan(plan, points, normals, concrete is None, material, h, options)


def _replan(plan: CutPlan, points: np.ndarray, normals: np.ndarray) -> CutPlan:
    """The plan of the same model, schedule and plane cuts at other concrete planes (given order), from the same
    start."""
    _check_model(plan, plan.made_for)
    planes = [(int(f), points[k], normals[k], float(e)) for k, (f, e) in enumerate(zip(plan.frames, plan.epsilons))]
    return _plan(plan.made_for, list(plan.schedule), plan.steps, planes, plan.start)


def plane_cut_simulation(
    model: XFEMModel,
    schedule: Sequence[tuple[int, object]],
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]],
    steps: int,
) -> PlaneCutSimulation:
    """Prepare ``simulate(model, schedule, ..., plane_cuts=plane_cuts)`` for calls under ``jax.jit`` and
    ``jax.vmap`` over the planes: the pieces are found on the host at these (concrete) planes, once
    (``plan_cuts``); the returned ``PlaneCutSimulation`` maps planes (points, normals) to the trajectory in JAX
    (``jax.jit(jax.vmap(jax.grad(loss)))`` over a batch of planes works), raising where the planes moved past the
    pieces found.

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
    if not list(plane_cuts):
        raise ValueError("plane_cuts: expected at least one (frame, point, normal, epsilon)")
    return PlaneCutSimulation(plan_cuts(model, schedule, steps, plane_cuts=plane_cuts))


def _scheduled(entry, size: int, steps: int) -> bool:
    """Whether ``entry`` is a tuple of ``size`` items whose first is an int frame in [1, steps]."""
    return (
        isinstance(entry, tuple)
        and len(entry) == size
        and isinstance(entry[0], int)
        and not isinstance(entry[0], bool)
        and 1 <= entry[0] <= steps
    )


def _check_planes(planes, steps: int, advice: str | None) -> list:
    """The checked ``plane_cuts``: (frame, point, normal, epsilon) in the order given, the point and normal as given
    (possibly traced) and their concrete values (point, normal, epsilon). A traced point or normal (jit, vmap) is a
    ValueError with ``advice``, or, with ``advice`` None, gives (None, None, epsilon)."""
    checked = []
    for k, entry in enumerate(planes):
        if not _scheduled(entry, 4, steps):
            raise ValueError(
                f"plane_cuts: expected (frame, point, normal, epsilon) with an int frame in [1, {steps}], got {entry!r}"
            )
        frame, point, normal, epsilon = entry
        name = f" (plane_cuts[{k}])"
        values = []
        for what, x in (("point", point), ("normal", normal)):
            try:
                values.append(np.asarray(concrete_or_error(None, x, what + name)))
            except jax.errors.ConcretizationTypeError:
                if advice is not None:
                    raise ValueError(f"{what}{name}: {advice}") from None
        if len(values) == 2:
            concrete = _plane(values[0], values[1], epsilon, name)
        else:
            concrete = (None, None, _positive("epsilon" + name, epsilon, "slab thickness"))
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


def _check_model(plan: CutPlan, model: XFEMModel) -> None:
    """ValueError where the plan was made for another model, or the model was cut since."""
    if plan.made_for is not model:
        raise ValueError("plan: made for another model; make one for this model (xfem.plan_cuts(model, ...))")
    if len(model.cuts) != plan.model_cuts:
        raise ValueError(
            f"model: cut since the plan was made ({len(model.cuts)} cuts, {plan.model_cuts} then); make a new plan "
            "(xfem.plan_cuts)"
        )


def _check_plan(plan, model: XFEMModel, schedule: list, steps: int, planes: list) -> CutPlan:
    """The plan, checked to be made for this model, schedule, step count and plane cuts (ValueError naming it)."""
    if not isinstance(plan, CutPlan):
        raise ValueError(f"plan: expected None or a CutPlan (xfem.plan_cuts), got {type(plan).__name__}")
    _check_model(plan, model)
    if plan.steps != steps:
        raise ValueError(f"plan: made for steps={plan.steps}, got steps={steps}; make a new plan (xfem.plan_cuts)")
    # the solids by identity: the plan keeps them, so an equal id is the same solid
    same = len(plan.schedule) == len(schedule) and all(
        f == g and a is b for (f, a), (g, b) in zip(plan.schedule, schedule)
    )
    if not same:
        raise ValueError(
            "plan: made for another schedule (the same (frame, solid) pairs, the same solid objects, in order, "
            "expected); make a new plan (xfem.plan_cuts)"
        )
    frames = np.array([frame for frame, *_ in planes], np.int64)
    epsilons = np.array([c[2] for *_, c in planes], np.float64)
    if not (np.array_equal(frames, plan.frames) and np.array_equal(epsilons, plan.epsilons)):
        raise ValueError(
            f"plan: made for plane cuts at frames {plan.frames.tolist()} with thicknesses {plan.epsilons.tolist()}, "
            f"got frames {frames.tolist()} with {epsilons.tolist()}; make a new plan (xfem.plan_cuts)"
        )
    return plan


_UNDER_JIT = (
    "simulate finds the pieces of plane cuts on the host at concrete planes: make a plan once with "
    "xfem.plan_cuts (or xfem.plane_cut_simulation) and pass it (simulate(..., plan=plan)) under jax.jit or "
    "jax.vmap, or differentiate simulate by eager jax.grad"
)
_PREPARE = "plan_cuts finds the pieces at concrete planes: call it outside jax.jit and jax.vmap"
_MOVED = (
    "plan: its pieces were found at other planes and do not hold at these (CutPlan.holds is False: a slab's face "
    "crossed a node or a piece's vertex); make a new plan at these planes (xfem.plan_cuts)"
)


def simulate(
    model: XFEMModel,
    schedule: Sequence[tuple[int, object]],
    material: Material,
    h: float | Float[Array, ""],
    steps: int,
    *,
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]] = (),
    plan: CutPlan | None = None,
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
    ``XFEMModel.step`` do. The cuts are the host phase (``plan_cuts``: the Booleans), the steps the JAX phase.
    Pass the ``plan`` of this model and schedule to run the JAX phase alone: a loss evaluated many times (by
    ``jax.grad``, an optimizer's iterations) then cuts once. Without a plan each call makes one (as ``plan_cuts``
    does) and drops it. Either way the cuts are made on a copy and ``model`` is left as it is (its pieces, DOFs
    and state), so equal calls give equal trajectories; the cut model (the last segment's DOFs, for host queries)
    is the plan's ``model``. With plane cuts a plan's pieces are used at other planes while they hold there
    (``CutPlan.holds``: the planes moved without crossing a node or a piece's vertex); which pieces exist is a
    constant of the gradient. Points and normals traced by ``jax.jit`` or ``jax.vmap`` need a plan;
    eager ``jax.grad`` gives concrete values, and works without one.

    Args:
        model: the ``XFEMModel``, with the cuts made before the schedule's (left uncut).
        schedule: ``(frame, solid)`` pairs, 1 <= frame <= steps, solids as ``XFEMModel.cut`` takes them; the cuts
            of one frame are made in the order given.
        material: the ``Material`` (scalars or one value per element of every segment's system).
        h: the positive time step.
        steps: python int >= 1, the number of frames.
        plane_cuts: ``(frame, point, normal, epsilon)``: a slab of thickness epsilon > 0 across the whole body
            about the plane through point (3,) with the unit normal (3,) (``plane_cut_solid`` with an extent
            covering the body), made at that frame after the frame's solids; point and normal may be JAX values
            to differentiate (the gradient with respect to a normal is tangent to the unit sphere).
        plan: None (the cuts are made for this call), or the ``CutPlan`` of this model, schedule, steps and plane
            cuts (``plan_cuts``; ValueError naming ``plan`` for another, or, with plane cuts, for concrete planes
            where its pieces do not hold).
        newton_iterations: as ``backward_euler_step`` (by default every step converges;
            ``newton_iterations=1, tolerance=None`` is the paper's single iteration, approximate for gradients).
        tolerance: see ``newton_iterations``.
        line_search: see ``newton_iterations``.
        forces: None (each segment's system force, e.g. gravity on its pieces), or a function ``(k, system)`` of a
            segment's index and ``FEMSystem`` returning its forces, (n_k, 3) or (frames_k, n_k, 3) per frame, as
            ``rollout`` takes them; it may close over traced parameters.
        state: the ``State`` at frame 0 on the DOFs before the schedule's cuts; None: the model's state then (the
            plan's ``start``).
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
    planes = _check_planes(list(plane_cuts), steps, _UNDER_JIT if plan is None else None)
    if plan is None:
        plan = _plan(model, schedule, steps, [(f, *c) for f, _, _, c in planes])
    else:
        plan = _check_plan(plan, model, schedule, steps, planes)
    points = jnp.stack([jnp.asarray(p) for _, p, _, _ in planes]) if planes else jnp.zeros((0, 3))
    normals = jnp.stack([jnp.asarray(n) for _, _, n, _ in planes]) if planes else jnp.zeros((0, 3))
    traced = any(c[0] is None for *_, c in planes)
    if planes and not traced and plan.cuts is not None:  # a plan given: its pieces must hold at these planes
        o = _time_order(plan.frames)
        found = [np.stack([c[j] for *_, c in planes])[o] for j in (0, 1)]
        with jax.ensure_compile_time_eval():  # a host check, also under eager jax.grad
            if not bool(plan.cuts.holds(*found)):
                raise ValueError(_MOVED)
    options = dict(
        newton_iterations=newton_iterations, tolerance=tolerance, line_search=line_search, forces=forces, state=state
    )
    return _run_plan(plan, points, normals, traced, material, h, options)


def _run_plan(plan: CutPlan, points, normals, traced: bool, material: Material, h, options: dict) -> list[State]:
    """The JAX phase on a checked plan: the segments' systems at the planes (given order; ``traced``: checked to
    hold at run time, else the caller checked them), each segment rolled out."""
    systems = None
    if plan.cuts is not None:
        o = jnp.asarray(_time_order(plan.frames))
        points, normals = jnp.asarray(points)[o], jnp.asarray(normals)[o]
        if traced:
            points = require(points, (~plan.cuts.holds(points, normals), _CHANGED))
        systems = plan.cuts.systems(points, normals)
    segments = []
    for s in plan.segments:  # None: the system before the cuts; an int: a plane cut's (_plane_segments)
        system = plan.initial if s.system is None else s.system
        if isinstance(system, int):
            assert systems is not None
            system = systems[system]
        segments.append(s._replace(system=system))
    state = options.pop("state")
    if state is None:
        state = plan.start
    elif not isinstance(state, State):
        raise ValueError(f"state: expected None or a State, got {type(state).__name__}")
    return _run(segments, state, material, h, plan.steps, **options)


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
