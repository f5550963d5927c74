"""Physics on rigged characters: a clip played on a ``CharacterBody`` (``xfem._character_body``) with secondary
dynamics, cut mid-animation by XFEM, differentiable end to end (``simulate_character``).

Formulation (moving targets with a rest shape that follows the rig). Frames k = 0..N at the clip times
``t_k = start + k h``; ``S_k`` are the tet nodes skinned at t_k (``body.node_model``, any method of
``deform.METHODS``). The step to frame k is the backward Euler step of eq. 10 (``xfem._backward_euler``):

* the driven nodes are Dirichlet nodes placed at ``S_k``: they follow the rig exactly;
* each element's stable neo-Hookean energy is taken relative to its skinned shape: with ``F_rig`` the rig's
  deformation gradient of the element (``F_rig = sum_a S_k[a] grad N_a^T`` over its rest shape functions), the
  element's shape gradients become ``grad N_a^T F_rig^-1`` and its weight ``|p| det F_rig``. The elastic energy is
  zero at the skinned pose, so with every node driven, or in the limit of a stiff material and a slow clip, the
  body is the skinned body; otherwise the free nodes (the flesh) lag behind the rig, overshoot and settle;
* inertia (the consistent mass of the rest configuration), gravity (``body.gravity``) and Rayleigh damping
  (``Material.damping``) act in world space.

This is the moving-target option of the issue, not Complementary Dynamics (Zhang et al. 2020): CD keeps the rig's
displacement and solves for a complementary one orthogonal to it, with the elastic energy of the whole displacement
from the rest shape; here the rig defines the rest shape itself, as rig-space and "rest-shape-follows-rig" secondary
motion does, so that the stiff limit is the rig exactly.

Cuts (Algorithm 1 of the XFEM paper with the cuts given in advance, ``xfem._simulate``): ``plane_cuts`` (slabs,
differentiable in their planes) and ``cuts`` (solids) at given frames, all in the rest configuration. A cut is made
at the state of frame f - 1, before the step to frame f. A piece of the body that no longer holds an anchor
(``body.anchors``, the driven nodes nearest the skeleton's root; ``XFEMModel.anchors``) is released: its driven
nodes are free from then on and its rest shape stays the skinned shape of frame f - 1, so it falls (with no contact,
its centroid accelerates at exactly g: the elastic and damping forces sum to zero). The pieces that keep an anchor
follow the clip. The surface is carried with its pieces (``xfem.surface_map``).

Newton. Each step minimizes by ``_newton``'s factored mode (``xfem._backward_euler``): the direction is CG on the
true Hessian preconditioned by the CHOLMOD factor of the projected one. Skinning leaves elements far from their
rig shapes near the joints (flattened, stretched), where the projection of the element Hessians stays active at the
minimizer, and projected Newton converges linearly there (tens of iterations); the true Hessian is positive definite
near the minimizer, and the factored direction converges quadratically. A character's body is made of limbs, so its
factor stays sparse. The XFEM paper's single iteration (``newton_iterations=1, tolerance=None``) takes the projected
direction by the same factor. Newton starts from the best of the previous positions, the inertial guess, and the
inertial guess plus the rig's acceleration (the flesh carried along by the rig).

Gradients. Every step is differentiable through its implicit gradient (exact for converged steps, the default; the
adjoint solve by CHOLMOD) in
the material (Young's modulus, Poisson's ratio, damping) and in the planes of plane cuts (``xfem.plane_cuts``: exact
for the pieces found at the planes).
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Callable, Sequence
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

import deform
from _jaxcga_shared.checks import check_choice
from _jaxcga_shared.platform import EXACT
from xfem._backward_euler import (
    _NEWTON_RESULT,
    FEMSystem,
    SolveStats,
    State,
    _advance,
    _checked_material,
    _step_arguments,
)
from xfem._character_body import CharacterBody
from xfem._character_reduced import CharacterSubspace, play_reduced
from xfem._cut_system import PlaneCuts, _plane_cuts
from xfem._material import Material
from xfem._neohookean import _cofactor
from xfem._simulate import _check_planes, _check_steps
from xfem._surface_tets import surface_map
from xfem._xfem import XFEMModel, _dof_components, xfem_model

_FLATTEST = 0.2  # below this thickness of its rig deformation (_rig_rest_system), an element's weight is lowered
# Newton iterations per step at most: a cap far above what the factored steps take (module docstring, Newton), so
# that a hard frame still converges
_CHARACTER_NEWTON_ITERATIONS = 100
_TINY = 1e-9  # determinants and cofactor norms are kept off zero by this much before they divide

_PLANES_UNDER_JIT = (
    "simulate_character finds the pieces of plane cuts on the host at concrete planes: call it outside jax.jit and "
    "jax.vmap (eager jax.grad is fine)"
)


class CharacterSegment(NamedTuple):
    """The frames between two cut frames of a ``CharacterMotion`` (the first segment starts at frame 0).

    Attributes:
        first: the segment's first frame.
        surface: (frames_k, s_k, 3) the surface's vertices at each of its frames (JAX, differentiable).
        faces: (f, 3) int64 triangles into them (the model's, in order).
        piece: (f,) int64 the connected piece of the body of each triangle.
        vertex: (s_k,) int64 the vertex of the model's surface each row copies (a vertex is copied where a
            triangle on the other side of a cut uses it).
        states: the ``State`` of the body's DOFs at each frame (x, v of shape (frames_k, n_k, 3)) and each step's
            ``SolveStats`` (the first segment's frame 0 is the start, with no step: converged, 0 iterations).
        driven: (n_k,) bool the DOFs placed on the rig in this segment.
        dof_node: (n_k,) int64 the tet node of each DOF.
        dof_piece: (n_k,) int64 the connected piece of each DOF (``XFEMModel.components``).
        pieces: the number of connected pieces of the body.
        system: the segment's ``FEMSystem`` in the rest configuration (its mass and gravity loads; the steps move
            its elements' rest shapes to the rig's), None where every DOF is driven.
    """

    first: int
    surface: Float[Array, "frames s 3"]
    faces: Int[np.ndarray, "f 3"]
    piece: Int[np.ndarray, " f"]
    vertex: Int[np.ndarray, " s"]
    states: State
    driven: np.ndarray
    dof_node: Int[np.ndarray, " n"]
    dof_piece: Int[np.ndarray, " n"]
    pieces: int
    system: FEMSystem | None


class CharacterMotion(NamedTuple):
    """A clip played on a ``CharacterBody`` (``simulate_character``).

    Attributes:
        body: the ``CharacterBody``.
        times: (N + 1,) float64 the clip time of each frame.
        h: the time step.
        segments: the ``CharacterSegment``s, in frame order; their frames concatenated are 0..N.
    """

    body: CharacterBody
    times: Float[np.ndarray, " frames"]
    h: float
    segments: list[CharacterSegment]

    @property
    def frames(self) -> int:
        """N + 1, the frames including frame 0."""
        return len(self.times)

    def _at(self, frame: int) -> tuple[CharacterSegment, int]:
        if int(frame) != frame or not -self.frames <= frame < self.frames:
            raise ValueError(f"frame: expected an int in [0, {self.frames}), got {frame!r}")
        frame = int(frame) % self.frames
        for segment in reversed(self.segments):
            if segment.first <= frame:
                return segment, frame - segment.first
        raise AssertionError("the segments cover every frame")

    def surface(self, frame: int) -> tuple[Float[np.ndarray, "s 3"], Int[np.ndarray, "f 3"], Int[np.ndarray, " f"]]:
        """The surface at a frame: vertices (s_k, 3), triangles (f, 3) and each triangle's piece (f,), numpy.

        Args:
            frame: in [0, frames) (negative counts from the end).
        """
        segment, k = self._at(frame)
        return np.asarray(segment.surface[k]), segment.faces, segment.piece

    @property
    def pieces_per_frame(self) -> Int[np.ndarray, " frames"]:
        """(N + 1,) int64 the connected pieces of the body at each frame."""
        counts = np.zeros(self.frames, np.int64)
        for segment in self.segments:
            counts[segment.first :] = segment.pieces
        return counts


class _Stage(NamedTuple):
    """A segment's host data: its first frame, the system (or its index among the plane cuts' systems), the DOF
    copy map from the previous segment, each DOF's node, the DOFs whose rest shape follows the rig, the surface map
    and the piece count."""

    first: int
    system: FEMSystem | int | None
    source: np.ndarray | None
    dof_node: np.ndarray
    follows: np.ndarray
    surface: tuple
    dof_piece: np.ndarray
    pieces: int


def _stage(model: XFEMModel, body: CharacterBody, first: int, system, source) -> _Stage:
    """The host data of the model's current pieces."""
    count, label = model.components()
    arrays = model._system_arrays()
    fixed = arrays[-1]
    if model.anchors is None:
        follows = np.ones(len(model.dof_node), bool)
    else:  # a piece follows the rig while it holds an anchor (XFEMModel.anchors)
        anchored = np.zeros(count, bool)
        anchored[label[np.isin(model.dof_node, model.anchors)]] = True
        follows = anchored[label]
    driven = np.zeros(len(model.dof_node), bool)
    driven[fixed] = True
    mapping = surface_map(model, body.embedding, body.surface, body.faces)
    return _Stage(first, system, source, model.dof_node.copy(), follows, (*mapping, driven), label, int(count))


def _clip_times(body: CharacterBody, clip, seconds, fps, start) -> tuple[np.ndarray, int | str | None]:
    """The frames' clip times (and the clip, None for a model without clips)."""
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (math.isfinite(fps) and 0 < fps <= 10000):
        raise ValueError(f"fps: expected frames per second in (0, 10000], got {fps!r}")
    model = body.model
    if model.clips:
        animation = model.clip(clip)  # a ValueError naming the clip
        first, end = animation.start, animation.end
    elif clip not in (0, None):
        raise ValueError(f"clip: the model has no clips, got {clip!r}")
    else:
        first = end = 0.0
    if start is None:
        start = first
    if seconds is None:
        if end <= start:
            raise ValueError("seconds: the model has no clip to take the length from; give the seconds to simulate")
        seconds = end - start
    if (
        isinstance(seconds, bool)
        or not isinstance(seconds, (int, float))
        or not (math.isfinite(seconds) and seconds > 0)
    ):
        raise ValueError(f"seconds: expected a positive duration, got {seconds!r}")
    if isinstance(start, bool) or not isinstance(start, (int, float)) or not math.isfinite(start):
        raise ValueError(f"start: expected a finite clip time, got {start!r}")
    steps = max(1, round(seconds * fps))
    times = start + np.arange(steps + 1) / fps
    if model.clips and (times[0] < first - 1e-9 or times[-1] > end + 1e-9):
        warnings.warn(
            f"seconds: the frames run from {times[0]:.4g} s to {times[-1]:.4g} s, outside the clip "
            f"({first:.4g} to {end:.4g} s); the rig holds the clip's end poses there (glTF clamps)",
            stacklevel=3,
        )
    return times, (clip if model.clips else None)


def _rig(body: CharacterBody, times: np.ndarray, method: str, clip, interpolation: str) -> np.ndarray:
    """(N + 1, n, 3) float64 the tet nodes skinned at each time."""
    model = body.node_model
    if clip is None:
        rest = np.asarray(deform.rest_pose(model, method), np.float64)
        return np.broadcast_to(rest, (len(times), *rest.shape)).copy()

    def skin(t):
        return deform.skin_model(model, t, method, clip, interpolation)

    return np.asarray(jax.vmap(skin)(jnp.asarray(times, jnp.float64)), np.float64)


def _rig_rest_system(system: FEMSystem, rest: Float[Array, "n 3"]) -> FEMSystem:
    """The system with each element's rest shape moved to ``rest`` (module docstring): shape gradients
    ``grads F_rig^-1`` and weights ``volumes |det F_rig|``, the weight of a flattened element lowered (below)."""
    F_rig = jnp.einsum("mai,maj->mij", rest[system.T], system.grads, precision=EXACT)
    cof, det = _cofactor(F_rig)  # F^-1 = cof^T / det: the thickness below needs no SVD either
    # skinning flattens or inverts an element where weights change fast across it (near joints). Its rest shape
    # stays the rig's (the energy is zero at the rig's shape, so the stiff limit is the rig), but its stiffness
    # across the flat direction grows as 1 / thickness, with thickness = |det F| / |cof F|_F (singular values
    # s0 >= s1 >= s2: s0 s1 s2 / |(s0 s1, s0 s2, s1 s2)|, which is s2 to first order in s2 / s1 and lies in
    # [s2 / sqrt 3, s2]): the weight is multiplied by (thickness / _FLATTEST)^4 below _FLATTEST, which takes it to
    # zero (Newton's matrix stays well conditioned, and such an element, far from its own shape after a small move
    # across, stops slowing Newton down); an inverted element (det < 0) is a mirror image, weighted by its volume's
    # magnitude
    thickness = jnp.abs(det) / jnp.maximum(jnp.sqrt(jnp.sum(cof * cof, axis=(1, 2))), _TINY)
    safe = jnp.where(det < 0, -1.0, 1.0) * jnp.maximum(jnp.abs(det), _TINY)
    inverse = cof.swapaxes(-1, -2) / safe[:, None, None]
    grads = jnp.einsum("maj,mjk->mak", system.grads, inverse, precision=EXACT)
    weight = jnp.abs(det) * jnp.minimum(1.0, (thickness / _FLATTEST) ** 4)
    return eqx.tree_at(lambda s: (s.grads, s.volumes), system, (grads, system.volumes * weight))


@eqx.filter_jit
def _play(system, state, h, material, rest_start, rests, targets, iterations, tolerance, line_search):
    """The frames of a segment: a ``lax.scan`` of steps, each with its rig rest shape and driven targets."""
    mu, lam = material.lame()

    # only the Newton result is kept for the reverse pass (as ``xfem.rollout``)
    @functools.partial(
        jax.checkpoint, prevent_cse=False, policy=jax.checkpoint_policies.save_only_these_names(_NEWTON_RESULT)
    )
    def body(carry, frame):
        s, before, previous = carry  # the rig rest shapes of the two frames before
        rest, target = frame
        moved = _rig_rest_system(system, rest)
        # Newton's third start: the inertial one plus the rig's acceleration (the flesh keeps its motion relative to
        # the rig), nearer the minimizer than the inertial start when the rig turns a limb
        guess = s.x + h * s.v + (rest - 2 * previous + before)
        s = _advance(
            moved,
            s,
            h,
            mu,
            lam,
            target,
            system.force,
            iterations,
            tolerance,
            line_search,
            material.damping,
            guess,
            factored=True,
        )
        return (s, previous, rest), s

    # before frame 1 the rig moves at its first velocity (no acceleration)
    first = rests[0] if rests.shape[0] else rest_start  # a segment of no frames (a cut at frame 1)
    start = (state, 2 * rest_start - first, rest_start)
    return jax.lax.scan(body, start, (rests, targets))[1]


def _check_cuts(cuts, steps: int) -> list[tuple[int, manifold3d.Manifold]]:
    checked = []
    for k, entry in enumerate(cuts):
        if (
            not isinstance(entry, tuple)
            or len(entry) != 2
            or isinstance(entry[0], bool)
            or not isinstance(entry[0], int)
            or not 1 <= entry[0] <= steps
            or not isinstance(entry[1], manifold3d.Manifold)
        ):
            raise ValueError(
                f"cuts[{k}]: expected (frame, manifold3d.Manifold) with an int frame in [1, {steps}], got {entry!r}"
            )
        checked.append(entry)
    return checked


def _system(model: XFEMModel) -> FEMSystem | None:
    """The model's system; None where every DOF is driven (the rig alone moves the body)."""
    return None if len(model._system_arrays()[-1]) == len(model.dof_node) else model.system()


def _stages(model: XFEMModel, body: CharacterBody, solids: list, planes: list) -> tuple[list[_Stage], PlaneCuts | None]:
    """The segments' host data (cutting the model for solids alone; a copy for plane cuts, ``xfem.plane_cuts``)."""
    frames = sorted({f for f, _ in solids} | {f for f, *_ in planes})
    stages = [_stage(model, body, 0, _system(model), None)]
    if not planes:
        for frame in frames:
            source = np.arange(len(model.dof_sid))
            for f, solid in solids:
                if f == frame:
                    report = model.cut(solid)
                    if report.dof_source is not None:
                        source = source[report.dof_source]
            stages.append(_stage(model, body, frame, _system(model), source))
        return stages, None
    entries, ends = [], {}
    for frame in frames:  # a frame's solids, then its planes (as xfem.simulate)
        entries += [solid for f, solid in solids if f == frame]
        entries += [(point, normal, epsilon) for f, point, normal, epsilon in planes if f == frame]
        ends[len(entries) - 1] = frame

    def after_cut(k: int, copy: XFEMModel) -> None:  # each frame's pieces, once its last cut is made
        if k in ends:
            stages.append(_stage(copy, body, ends[k], k, None))

    cuts = _plane_cuts(model, entries, after_cut)
    first = 0
    for index, end in enumerate(sorted(ends)):  # the DOF copy maps of each frame's cuts, composed
        source = None
        for report in cuts.reports[first : end + 1]:
            if report.dof_source is not None:
                source = report.dof_source if source is None else source[report.dof_source]
        stages[index + 1] = stages[index + 1]._replace(source=source)
        first = end + 1
    return stages, cuts


def simulate_character(
    body: CharacterBody,
    clip: int | str = 0,
    seconds: float | None = None,
    fps: float = 30.0,
    *,
    material: Material,
    method: str = "cga",
    interpolation: str = "gltf",
    start: float | None = None,
    plane_cuts: Sequence[tuple[int, Float[ArrayLike, " 3"], Float[ArrayLike, " 3"], float]] = (),
    cuts: Sequence[tuple[int, manifold3d.Manifold]] = (),
    newton_iterations: int = _CHARACTER_NEWTON_ITERATIONS,
    tolerance: float | Literal["auto"] | None = "auto",
    line_search: bool = True,
    progress: Callable[[str, int, int], None] | None = None,
    subspace: CharacterSubspace | None = None,
) -> CharacterMotion:
    """Play a clip on a character's body with secondary dynamics and cuts (module docstring: the formulation);
    differentiable (reverse mode, eager) in ``material`` and the points and normals of ``plane_cuts``.

    Args:
        body: the ``CharacterBody`` (``character_body``).
        clip: the clip's name or index (a model without clips stands in its rest pose).
        seconds: the duration to simulate; None: the clip's length (from ``start``).
        fps: frames per second; the time step is 1 / fps.
        material: the ``Material``: Young's modulus (Pa for a model in metres), Poisson's ratio and the Rayleigh
            ``damping`` (seconds; None: undamped).
        method: the skinning method of the rig (``deform.METHODS``).
        interpolation: the clip's key interpolation (``deform.INTERPOLATIONS``).
        start: the clip time of frame 0; None: the clip's start.
        plane_cuts: ``(frame, point, normal, epsilon)``: a slab of thickness epsilon about the plane through point
            with the unit normal, across the whole body in the rest configuration, made before the step to that
            frame (1 <= frame <= N); point and normal may be JAX values to differentiate.
        cuts: ``(frame, solid)``: closed ``manifold3d.Manifold`` cut solids in the rest configuration
            (``xfem.cut_solid``, ``xfem.plane_cut_solid``, ``xfem.blade_solid``), made before the frame's planes.
        newton_iterations: as ``backward_euler_step`` (by default every step converges,
            within 100 iterations: a moving rig's steps can take more than the 50 of ``backward_euler_step``, and
            ``states.stats`` says where one did not; ``newton_iterations=1, tolerance=None`` is the XFEM paper's
            single iteration, approximate for gradients).
        tolerance: see ``newton_iterations``.
        line_search: see ``newton_iterations``.
        progress: None, or ``progress(stage, done, total)`` called on the host as the work advances: stage
            ``"rig"`` (the rig skinned), ``"cuts"`` (the cut frames' pieces found), ``"frames"`` (after each
            segment's frames).
        subspace: None (the full space), or a ``CharacterSubspace`` of the body (``xfem.character_subspace``): the
            real-time reduced mode (``xfem._character_reduced``: skinning eigenmodes carried by the rig, one k x k
            solve per frame, no Newton iterations, so ``newton_iterations``, ``tolerance`` and ``line_search`` do not
            apply); no cuts; its one segment has no ``system``.
    Returns:
        The ``CharacterMotion``: the surface of every frame in segments between cut frames.
    """
    if not isinstance(body, CharacterBody):
        raise ValueError(f"body: expected a CharacterBody (xfem.character_body), got {type(body).__name__}")
    if not isinstance(material, Material):
        raise ValueError(f"material: expected an xfem.Material(young, poisson, damping), got {type(material).__name__}")
    check_choice("method", method, deform.METHODS)
    check_choice("interpolation", interpolation, deform.INTERPOLATIONS)
    if progress is not None and not callable(progress):
        raise ValueError("progress: expected None or a function (stage, done, total)")
    times, clip_key = _clip_times(body, clip, seconds, fps, start)
    steps, h = len(times) - 1, 1.0 / fps
    _check_steps(steps)
    planes = _check_planes(list(plane_cuts), steps, _PLANES_UNDER_JIT)
    solids = _check_cuts(list(cuts), steps)
    report = progress or (lambda stage, done, total: None)
    if subspace is not None:
        if planes or solids:
            raise ValueError("subspace: the reduced mode does not cut; pass no plane_cuts and no cuts with a subspace")
        return _reduced_motion(body, subspace, times, clip_key, h, material, method, interpolation, report)
    rig = _rig(body, times, method, clip_key, interpolation)
    report("rig", 1, 1)
    start_state = State(rig[0], (rig[1] - rig[0]) / h)
    model = xfem_model(
        body.tets, body.density, body.gravity, fixed=body.driven, state=start_state, anchors=body.anchors
    )
    with model, jax.ensure_compile_time_eval():  # host work, also under eager jax.grad; the model's threads end
        stages, replay = _stages(model, body, solids, [(f, *c) for f, _, _, c in planes])
    report("cuts", len(stages) - 1, len(stages) - 1)
    systems = None
    if replay is not None:
        points = jnp.stack([jnp.asarray(p, jnp.float64) for _, p, _, _ in planes])
        normals = jnp.stack([jnp.asarray(n, jnp.float64) for _, _, n, _ in planes])
        order = np.argsort([f for f, *_ in planes], kind="stable")  # the planes in the cuts' time order
        systems = replay.systems(points[order], normals[order])
    segments = []
    state = State(jnp.asarray(rig[0]), jnp.asarray(start_state.v))
    followed = np.ones(len(stages[0].dof_node), bool)  # the DOFs whose rest shape followed the rig so far
    frozen = rig[0][stages[0].dof_node]  # the rest positions of the others
    for index, stage in enumerate(stages):
        system = stage.system
        if isinstance(system, int):
            assert systems is not None
            system = systems[system]
        end = stages[index + 1].first if index + 1 < len(stages) else steps + 1
        if stage.source is not None:  # Algorithm 1 line 7: the new DOFs copy their source's x and v
            source = jnp.asarray(stage.source)
            state = State(state.x[source], state.v[source])
            followed, frozen = followed[stage.source], frozen[stage.source]
        # a piece released by this frame's cuts keeps the rig's shape at the cut (frame first - 1) as its rest shape
        frozen = np.where(followed[:, None], rig[max(stage.first - 1, 0)][stage.dof_node], frozen)
        followed = stage.follows
        frames = np.arange(max(stage.first, 1), end)
        rest_start = np.where(followed[:, None], rig[frames[0] - 1][stage.dof_node], frozen) if len(frames) else frozen
        rests = np.where(stage.follows[None, :, None], rig[frames][:, stage.dof_node], frozen[None])
        if system is None:  # every DOF on the rig
            played = _on_rig(state, jnp.asarray(rig[frames][:, stage.dof_node]), h)
        else:
            assert isinstance(system, FEMSystem)
            targets = rig[frames][:, stage.dof_node[np.asarray(system.fixed)]]
            _, _, h_checked, _, _, iterations, tol, search = _step_arguments(
                system, state, h, material, None, newton_iterations, tolerance, line_search
            )
            played = _play(
                system,
                state,
                h_checked,
                _checked_material(material, system, system.grads.dtype),
                jnp.asarray(rest_start),
                jnp.asarray(rests),
                jnp.asarray(targets),
                iterations,
                tol,
                search,
            )
        if stage.first == 0:  # frame 0, the start, before the steps
            played = _prepend(state, played)
        if len(frames):
            state = State(played.x[-1], played.v[-1])
        weights, dofs, faces, piece, vertex, driven = stage.surface
        surface = jnp.einsum("ka,fkad->fkd", jnp.asarray(weights), played.x[:, jnp.asarray(dofs)], precision=EXACT)
        segments.append(
            CharacterSegment(
                stage.first,
                surface,
                faces,
                piece,
                vertex,
                played,
                driven,
                stage.dof_node,
                stage.dof_piece,
                stage.pieces,
                system,
            )
        )
        report("frames", int(end - 1), steps)
    return CharacterMotion(body, times, h, segments)


def _reduced_motion(body, subspace, times, clip, h, material, method, interpolation, report) -> CharacterMotion:
    """``simulate_character`` in a subspace: one segment of every frame (``xfem._character_reduced``)."""
    played = play_reduced(body, subspace, times, clip, material, method, interpolation)
    report("rig", 1, 1)
    frames, n = played.x.shape[:2]
    stats = SolveStats(jnp.ones(frames, bool), jnp.zeros(frames, jnp.int32), jnp.zeros(frames, played.x.dtype))
    count, label = _dof_components(np.asarray(body.tets.T), n)
    driven = np.zeros(n, bool)
    driven[body.driven] = True
    segment = CharacterSegment(
        0,
        played.surface,
        body.faces,
        label[body.embedding.nodes[body.faces[:, 0], 0]],
        np.arange(len(body.surface)),
        State(played.x, played.v, stats),
        driven,
        np.arange(n),
        label,
        int(count),
        None,
    )
    report("frames", frames - 1, frames - 1)
    return CharacterMotion(body, times, h, [segment])


def _on_rig(state: State, positions: Float[Array, "frames n 3"], h) -> State:
    """Frames placed on the rig (velocities by backward differences), each a converged step of 0 iterations."""
    previous = jnp.concatenate([state.x[None], positions[:-1]])
    frames = positions.shape[0]
    dtype = positions.dtype
    stats = SolveStats(jnp.ones(frames, bool), jnp.zeros(frames, jnp.int32), jnp.zeros(frames, dtype))
    return State(positions, (positions - previous) / h, stats)


def _prepend(start: State, frames: State) -> State:
    """The start state followed by a segment's frames (its stats: no step, converged)."""
    first = State(start.x, start.v)
    return jax.tree.map(lambda a, b: jnp.concatenate([jnp.asarray(a)[None], b]), first, frames)
