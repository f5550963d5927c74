"""The placement of planar and slab cuts as a parameter (issue 31): the piece integrals that enter the system
(volumes, masses ``rho int_p phi_a phi_b``, loads ``int_p phi_a`` and the body forces they give) as JAX
functions of the planes, for the combinatorics found at the given planes, in the manner of
``cutting.cut_positions``.

A slab cut (``plane_cut_solid`` with an extent covering the body) removes the slab ``|n . (X - p)| < eps / 2``.
Each piece of an element it meets is a part of a previous piece on one side of the slab: the previous piece
clipped by the half-space ``side n . (X - p) >= eps / 2`` (side = -1 below, +1 above). On the host, a copy of the
model is cut by manifold3d's Booleans as usual (the DOF numbering, the enrichment of eq. 16, which pieces exist),
and each new piece is clipped again by its half-space, recording a replay: every vertex of the clipped polyhedron
is a constant (a tet corner, a vertex of a piece made by an earlier non-planar cut) or the point where the
segment between two earlier vertices crosses a plane, ``A + sigma_A / (sigma_A - sigma_B) (B - A)``; faces are
vertex cycles, the cap a fan of the crossing points, all fixed by the sign pattern. In JAX the vertices follow
from the planes, and the exact moments (eq. 21, ``triangle_moment_terms``) give the integrals (eq. 13, 14,
``shape_function_integrals``). Clipping convex pieces gives one polyhedron per piece and side, so a replayed
piece is matched to the model's by its side and its volume (to ``_MATCH`` of its tet's volume); where a cut splits
a non-convex piece (made by an earlier non-planar cut) into several on one side, the match fails with a
ValueError. Pieces of elements the planes do not meet keep their values (constants), and so do the pieces of
elements that a solid cut between the planes meets (``plane_cuts``: from that cut on, their geometry is the
Booleans', and their gradient with respect to earlier planes is dropped).

The system is then assembled in JAX from the piece integrals exactly as ``XFEMModel.system`` assembles it on the
host (the mass entries symmetrized, ``M (x) I3`` scattered into the free-DOF pattern, gravity loads), so it equals
the Boolean path to rounding. The gradient is exact for the topology found: only where a plane crosses a
vertex, edge or face of a piece (the combinatorics change) is the function not differentiable, and beyond such a
crossing the replay no longer equals the Booleans (``PlaneCuts.holds`` tells; ``cut_system`` finds the pieces
anew at every call).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
import numpy.typing as npt
from jax.extend.core import concrete_or_error
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import check_finite, check_vectors, require
from _jaxcga_shared.host import to_devices
from _jaxcga_shared.mesh import TET_FACES
from xfem._assembly import scalar_slots
from xfem._backward_euler import FEMSystem, State
from xfem._cuts import _positive, plane_cut_solid
from xfem._integration import (
    linear_shape_coefficients,
    shape_function_integrals,
    triangle_moment_terms,
)
from xfem._subdomains import CutReport, check_cut, solid_mesh
from xfem._tetmesh import tet_volumes
from xfem._xfem import XFEMModel, xfem_model

# a replayed piece's volume must equal the Boolean piece's to this fraction of its tet's volume
_MATCH = 1e-9
# a normal is unit when its length is within this of 1
_UNIT = 1e-9
# the slab's square extends this many times the largest distance of a node from the point (it covers the body)
_COVER = 2.5


class _Replay(eqx.Module):
    """One system's replay (``PlaneCuts``): the JAX arrays that turn planes into the system's differentiable
    fields. The vertex table is evaluated block by block: stage k's constants, then its crossing points on
    plane k (``lerp_*``: the two earlier vertices and the side)."""

    consts: tuple[Float[Array, "c 3"], ...]
    lerp_a: tuple[Int[Array, " l"], ...]
    lerp_b: tuple[Int[Array, " l"], ...]
    lerp_side: tuple[Float[Array, " l"], ...]
    # per stage: the clipped pieces' vertices, their side and whether they were kept; every node's place (-1 below
    # the slab, 0 in it, 1 above): the combinatorics that the replay holds for (``PlaneCuts.holds``)
    check_ids: tuple[Int[Array, " v"], ...]
    check_side: tuple[Float[Array, " v"], ...]
    check_kept: tuple[Array, ...]
    node_place: tuple[Int[Array, " n"], ...]
    epsilon: Float[Array, " k"]
    triangles: Int[Array, "t 3"]  # fans of the replayed pieces' faces, into the vertex table
    triangle_row: Int[Array, " t"]  # the replayed piece of each triangle
    origin: Float[Array, "r 3"]  # the replayed pieces' tets' centroids (the moments' origin)
    c: Float[Array, "r 4"]
    g: Float[Array, "r 4 3"]
    rho: Float[Array, " r"]
    rows: Int[Array, " r"]  # their rows in the system's element list
    volume: Float[Array, " p"]  # every piece's values at the planes found (the constants)
    mass: Float[Array, "p 4 4"]
    load: Float[Array, "p 4"]
    dofs: Int[Array, "p 4"]
    weight: Float[Array, " p"]  # the density of each piece's element (its load times gravity is the force)
    gravity: Float[Array, "3"]
    entry: Int[Array, " e"]  # for each piece mass entry (p, a, b), its mass entry (r, c) (k where dropped)
    transposed: Int[Array, " e"]  # and its entry (c, r)
    slots: Int[Array, "k 3"]  # ``scalar_slots`` of the mass entries
    entries: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)
    n: int = eqx.field(static=True)


def _positions(replay: _Replay, points, normals):
    """The vertex table at the planes, the unit normals and the planes' offsets ``n . p``."""
    normals = normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    offsets = jnp.sum(normals * points, axis=-1)
    positions = jnp.zeros((0, 3), points.dtype)
    for k, const in enumerate(replay.consts):
        positions = jnp.concatenate([positions, const])
        A, B = positions[replay.lerp_a[k]], positions[replay.lerp_b[k]]
        side, half = replay.lerp_side[k], replay.epsilon[k] / 2
        sA = side * (A @ normals[k] - offsets[k]) - half
        sB = side * (B @ normals[k] - offsets[k]) - half
        positions = jnp.concatenate([positions, A + (sA / (sA - sB))[:, None] * (B - A)])
    return positions, normals, offsets


@eqx.filter_jit
def _holds(replay: _Replay, points, normals):
    """Whether every clipped vertex and every node is on the side of each plane it was on when the pieces were
    found."""
    positions, normals, offsets = _positions(replay, points, normals)
    holds = jnp.asarray(True)
    n = replay.node_place[0].shape[0]
    for k in range(len(replay.consts)):
        half = replay.epsilon[k] / 2
        s = positions @ normals[k] - offsets[k]
        sigma = replay.check_side[k] * s[replay.check_ids[k]] - half
        place = jnp.where(s[:n] > half, 1, jnp.where(s[:n] < -half, -1, 0))
        holds &= jnp.all((sigma >= 0) == replay.check_kept[k]) & jnp.all(place == replay.node_place[k])
    return holds


@eqx.filter_jit
def _fields(replay: _Replay, points, normals):
    """The system's volumes, mass values, mass data and forces at the planes (points, normals)."""
    positions, _, _ = _positions(replay, points, normals)
    r = replay.rows.shape[0]
    values, _ = triangle_moment_terms(jnp, positions[replay.triangles] - replay.origin[replay.triangle_row][:, None])
    sums = jax.ops.segment_sum(values, replay.triangle_row, r)
    second = sums[:, 4:].reshape(r, 3, 3)
    mass, load = shape_function_integrals(
        jnp, replay.c, replay.g, sums[:, 0], sums[:, 1:4], (second + jnp.swapaxes(second, 1, 2)) / 2
    )
    volume = replay.volume.at[replay.rows].set(sums[:, 0])
    mass = replay.mass.at[replay.rows].set(replay.rho[:, None, None] * mass)
    load = replay.load.at[replay.rows].set(load)
    # M = (M + M^T) / 2 of the summed piece blocks, as XFEMModel._system_arrays
    flat = mass.reshape(-1)
    values = (
        0.5
        * (
            jax.ops.segment_sum(flat, replay.entry, replay.entries + 1)
            + jax.ops.segment_sum(flat, replay.transposed, replay.entries + 1)
        )[:-1]
    )
    mass_data = (
        jnp.zeros(replay.nnz, values.dtype)
        .at[replay.slots]
        .add(jnp.broadcast_to(values[:, None], replay.slots.shape), mode="drop")
    )
    weights = load * replay.weight[:, None]
    gravity = lift_rank(replay.gravity, 3)
    force = jnp.zeros((replay.n, 3), values.dtype).at[replay.dofs].add(weights[:, :, None] * gravity)
    return volume, values, mass_data, force


class _Table:
    """The host vertex table of a replay: per stage (plane) its constants, then its crossing points."""

    def __init__(self):
        self.positions = np.zeros((0, 3))
        self.consts: list[np.ndarray] = []
        self.lerps: list[list[tuple[int, int, float]]] = []
        self.checks: list[list[tuple[np.ndarray, float, np.ndarray]]] = []  # per stage: (ids, side, kept)
        self.places: list[np.ndarray] = []
        self._new: list[np.ndarray] = []
        self._crossings: dict[tuple, int] = {}
        self.corners: np.ndarray | None = None  # the ids of the mesh nodes (the first stage's constants)

    def stage(self, consts: list[np.ndarray], place: np.ndarray) -> list[np.ndarray]:
        """Start the next plane's stage with its constant vertices and the nodes' places; returns their ids."""
        self._close()
        self.checks.append([])
        self.places.append(place)
        offset = len(self.positions)
        block = np.concatenate(consts) if consts else np.zeros((0, 3))
        self.consts.append(block)
        self.lerps.append([])
        self._crossings = {}
        self.positions = np.concatenate([self.positions, block])
        ids, start = [], offset
        for V in consts:
            ids.append(np.arange(start, start + len(V)))
            start += len(V)
        return ids

    def crossing(self, a: int, b: int, side: float, s: np.ndarray, half: float) -> int:
        """The id of the point where segment (a, b) of earlier vertices crosses the current plane's face on
        ``side`` (s: the earlier vertices' signed distances to the plane)."""
        a, b = min(a, b), max(a, b)
        key = (a, b, side)
        if key not in self._crossings:
            A, B = self.positions[a], self.positions[b]
            sA, sB = side * s[a] - half, side * s[b] - half
            self.lerps[-1].append(key)
            self._new.append(A + sA / (sA - sB) * (B - A))
            self._crossings[key] = len(self.positions) + len(self._new) - 1
        return self._crossings[key]

    def _close(self) -> None:
        if self._new:
            self.positions = np.concatenate([self.positions, np.stack(self._new)])
            self._new = []

    def arrays(self) -> dict:
        """The stages' constants, crossings (a, b, side) and checks as arrays (``_Replay``'s fields)."""
        self._close()
        lerps = [np.asarray(k, np.float64).reshape(-1, 3) for k in self.lerps]

        def checks(stage):
            if not stage:
                return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, bool)
            ids, sides, kept = zip(*stage)
            return (
                np.concatenate(ids),
                np.repeat(sides, [len(i) for i in ids]).astype(np.float64),
                np.concatenate(kept),
            )

        # no stage: solids before the first plane (their systems are constants)
        ids, sides, kept = zip(*(checks(stage) for stage in self.checks)) if self.checks else ((), (), ())
        return dict(
            consts=tuple(self.consts),
            lerp_a=tuple(k[:, 0].astype(np.int64) for k in lerps),
            lerp_b=tuple(k[:, 1].astype(np.int64) for k in lerps),
            lerp_side=tuple(k[:, 2] for k in lerps),
            check_ids=ids,
            check_side=sides,
            check_kept=kept,
            node_place=tuple(self.places),
        )


def _clip(table: _Table, faces: list[tuple[int, ...]], side: float, s: np.ndarray, half: float):
    """The part of a polyhedron (outward faces as vertex cycles, convex polygons) where ``side s >= half``: its
    faces clipped (Sutherland-Hodgman) and the cap fanned from its first crossing point; None if empty."""
    ids = np.fromiter({v for face in faces for v in face}, np.int64)
    flags = side * s[ids] - half >= 0
    table.checks[-1].append((ids, side, flags))
    kept = dict(zip(ids.tolist(), flags.tolist()))
    if not any(kept.values()):
        return None
    if all(kept.values()):
        return faces
    clipped, segments = [], []
    for face in faces:
        out, exits, entries = [], [], []
        for i, a in enumerate(face):
            b = face[(i + 1) % len(face)]
            if kept[a]:
                out.append(a)
            if kept[a] != kept[b]:
                x = table.crossing(a, b, side, s, half)
                out.append(x)
                (exits if kept[a] else entries).append(x)
        if len(out) >= 3:
            clipped.append(tuple(out))
        # a convex face leaves by one crossing and comes back by the next: the cap's edge runs the other way
        segments += list(zip(entries, exits))
    if segments:
        centre = segments[0][0]
        clipped += [(centre, a, b) for a, b in segments if centre not in (a, b)]
    return clipped


class PlaneCuts:
    """Slab cuts by planes, replayed (module docstring): ``plane_cuts`` builds it.

    Attributes:
        model: the copy of the model cut by every cut (the input model is left uncut), for later cuts and
            queries.
        reports: the ``CutReport`` of each cut of the copy, in order (``dof_source``: the DOF copy map of the
            cut, Algorithm 1 line 7).
        points: (k, 3) the k planes' points found; normals: (k, 3) their unit normals; epsilons: (k,) the slab
            thicknesses.
    """

    def __init__(
        self,
        model: XFEMModel,
        reports: list[CutReport],
        points: Float[np.ndarray, "k 3"],
        normals: Float[np.ndarray, "k 3"],
        epsilons: Float[np.ndarray, " k"],
        replays: list[_Replay],
        systems: list[FEMSystem],
    ):
        self.model, self.reports = model, reports
        self.points, self.normals, self.epsilons = points, normals, epsilons
        self._replays, self._systems = replays, systems

    def systems(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> list[FEMSystem]:
        """The system after each cut, a JAX function of the planes (differentiable, jit-able).

        Args:
            points: (k, 3) the planes' points.
            normals: (k, 3) their normals (normalized here: the gradient is tangent to the unit sphere).
        Returns:
            An ``FEMSystem`` per cut: the system after cut j (of the copy cut by cuts 0..j) depends on the planes
            among those cuts; its volumes, mass values, mass data and forces carry the gradient.
        """
        points, normals = self._planes(points, normals)
        result = []
        for replay, system in zip(self._replays, self._systems):
            planes = len(replay.consts)  # the planes among the cuts so far
            fields = _fields(replay, points[:planes], normals[:planes])
            result.append(eqx.tree_at(lambda t: (t.volumes, t.mass_values, t.mass_data, t.force), system, fields))
        return result

    def _planes(self, points, normals):
        k = len(self.points)
        points, normals = jnp.asarray(points), jnp.asarray(normals)
        if points.shape != (k, 3) or normals.shape != (k, 3):
            raise ValueError(f"points, normals: expected shape ({k}, 3), got {points.shape} and {normals.shape}")
        dtype = self._systems[0].grads.dtype
        points, normals = points.astype(dtype), normals.astype(dtype)
        length = jnp.linalg.norm(normals, axis=-1)
        points = require(points, (~jnp.all(jnp.isfinite(points)), "points: non-finite values (NaN or inf)"))
        normals = require(
            normals, (~jnp.all(jnp.isfinite(length) & (length > 0)), "normals: expected finite nonzero normals")
        )
        return points, normals

    def system(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> FEMSystem:
        """The system after the last cut (``systems``).

        Args:
            points: (k, 3) the planes' points.
            normals: (k, 3) their normals.
        """
        return self.systems(points, normals)[-1]

    def holds(self, points: Float[ArrayLike, "k 3"], normals: Float[ArrayLike, "k 3"]) -> Bool[Array, ""]:
        """Whether ``systems`` is exact at these planes: every node and every vertex of the replayed pieces lies on
        the side of each slab it lay on at the planes found (a JAX bool; jit-able). Where it is False, the
        pieces' combinatorics may differ: cut anew (``plane_cuts``) at these planes. Not checked: the vertices of
        earlier non-planar cuts' pieces that the slabs did not meet.

        Args:
            points: (k, 3) the planes' points.
            normals: (k, 3) their normals.
        """
        points, normals = self._planes(points, normals)
        return _holds(self._replays[-1], points, normals)


def _plane(point, normal, epsilon, index: str = ""):
    """The checked plane: host float64 point, unit normal, epsilon (ValueError naming the argument)."""
    point = np.asarray(check_finite("point" + index, check_vectors("point" + index, point)), np.float64)
    normal = np.asarray(check_finite("normal" + index, check_vectors("normal" + index, normal)), np.float64)
    if point.shape != (3,) or normal.shape != (3,):
        raise ValueError(f"point{index}, normal{index}: expected shape (3,), got {point.shape} and {normal.shape}")
    if abs(np.linalg.norm(normal) - 1) > _UNIT:
        raise ValueError(f"normal{index}: expected a unit normal, got length {np.linalg.norm(normal)!r}")
    return point, normal, _positive("epsilon" + index, epsilon, "slab thickness")


def _copy(model: XFEMModel) -> XFEMModel:
    """A model built from the same mesh, density, gravity and fixed nodes, cut by the model's cuts again
    (``XFEMModel.replay``), in the model's state."""
    copy = xfem_model(model.mesh, model.rho, model.gravity, model.fixed_nodes, anchors=model.anchors)
    copy.replay(model.cuts)
    copy.state = State(np.asarray(model.state.x), np.asarray(model.state.v))
    return copy


def _entry(entry, index: str):
    """A checked entry of ``plane_cuts``: (point, normal, epsilon) or (None, solid, perturb)."""
    if isinstance(entry, manifold3d.Manifold):
        entry = (entry, 0.0)
    if isinstance(entry, (tuple, list)) and len(entry) == 2 and isinstance(entry[0], manifold3d.Manifold):
        check_cut(*entry)  # pyright: ignore[reportArgumentType]  # check_cut validates the user's solid, perturb
        return None, entry[0], float(entry[1])
    if isinstance(entry, (tuple, list)) and len(entry) == 3:
        return _plane(*entry, index=index)
    raise ValueError(
        f"cuts{index}: expected (point, normal, epsilon) or a cut solid (a manifold3d.Manifold, or (solid, perturb))"
    )


def plane_cuts(
    model: XFEMModel,
    cuts: Sequence[
        tuple[Float[npt.ArrayLike, " 3"], Float[npt.ArrayLike, " 3"], float]
        | manifold3d.Manifold
        | tuple[manifold3d.Manifold, float]
    ],
) -> PlaneCuts:
    """Cut a copy of the model by slabs (``plane_cut_solid`` covering the body), in order, and replay the pieces
    they make as JAX functions of the planes (module docstring).

    Args:
        model: the ``XFEMModel``; left uncut. Its earlier cuts (any solids) are constants of the replay.
        cuts: a sequence of planes (point (3,), normal (3,) unit, epsilon > 0), concrete values, and possibly cut
            solids between them (a ``manifold3d.Manifold``, or (solid, perturb)): cut as ``XFEMModel.cut`` does,
            the pieces of the elements a solid meets are constants from then on.
    Returns:
        The ``PlaneCuts``: the cut copy, the cuts' reports and ``systems(points, normals)`` (one system per cut,
        points and normals one per plane).
    Raises:
        ValueError: a bad plane (naming ``point``, ``normal``, ``epsilon`` and its index), a bad solid, a plane
        that misses the body, or pieces the replay cannot follow (``model``: a non-convex piece split into
        several).
    """
    return _plane_cuts(model, cuts)


def _plane_cuts(model: XFEMModel, cuts, after_cut: Callable[[int, XFEMModel], None] | None = None) -> PlaneCuts:
    """``plane_cuts``, calling ``after_cut(k, copy)`` once cut k is made (host queries of each stage's pieces)."""
    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel, got {type(model).__name__}")
    cuts = list(cuts)
    if not cuts:
        raise ValueError("cuts: expected at least one (point, normal, epsilon)")
    checked = [_entry(entry, f"[{k}]" if len(cuts) > 1 else "") for k, entry in enumerate(cuts)]
    if all(entry[0] is None for entry in checked):
        raise ValueError("cuts: expected at least one (point, normal, epsilon)")
    with _copy(model) as copy:  # its Boolean threads end with the cuts; the pieces stay for host queries
        return _cut_copy(copy, cuts, checked, after_cut)


def _cut_copy(copy: XFEMModel, cuts: list, checked: list, after_cut) -> PlaneCuts:
    """``_plane_cuts`` on the model's copy."""
    tet_volume = np.asarray(tet_volumes(copy.X, copy.T))
    table = _Table()
    programs: dict[int, list[tuple[int, ...]]] = {}  # replayed piece sid -> faces
    planes, reports, replays, systems = [], [], [], []
    for k, entry in enumerate(checked):
        name = f"point[{k}], normal[{k}]" if len(cuts) > 1 else "point, normal"
        if entry[0] is None:
            report = copy.cut(entry[1], entry[2])
            for e in report.elements_touched.tolist():  # its pieces' geometry is the Booleans' from now on
                for sid in copy.sub.element_subdomains(e):
                    programs.pop(sid, None)
            for sid in report.element_children:
                programs.pop(sid, None)
        else:
            point, normal, epsilon = entry
            report = _cut_by_plane(copy, table, programs, point, normal, epsilon, name)
            planes.append(entry)
        reports.append(report)
        replay, system, elements = _stage_replay(copy, table, programs, [c[2] for c in planes])
        if planes:  # the replay at the planes found must give the Booleans' pieces
            volume = _fields(
                replay, jnp.asarray(np.stack([c[0] for c in planes])), jnp.asarray(np.stack([c[1] for c in planes]))
            )[0]
            rows = np.asarray(replay.rows)
            bad = (
                np.abs(np.asarray(volume)[rows] - np.asarray(system.volumes)[rows])
                > _MATCH * tet_volume[elements[rows]]
            )
            if np.any(bad):
                e = int(elements[rows][np.argmax(bad)])
                raise ValueError(
                    f"model: the pieces of element {e} after cut {k} are not the slabs' half-spaces of "
                    "its earlier pieces (a non-convex piece split into several?)"
                )
        replays.append(replay)
        systems.append(system)
        if after_cut is not None:
            after_cut(k, copy)
    return PlaneCuts(
        copy,
        reports,
        np.stack([c[0] for c in planes]),
        np.stack([c[1] for c in planes]),
        np.array([c[2] for c in planes]),
        replays,
        systems,
    )


def _cut_by_plane(copy: XFEMModel, table: _Table, programs: dict, point, normal, epsilon, name: str) -> CutReport:
    """Cut the copy by the slab and replay the pieces of the elements it meets (``programs``, new stage of the
    table)."""
    X, T = copy.X, copy.T
    half = epsilon / 2
    s_nodes = (X - point) @ normal
    near = np.flatnonzero(
        (s_nodes[T].min(axis=1) <= half * (1 + 1e-9)) & (s_nodes[T].max(axis=1) >= -half * (1 + 1e-9))
    )
    exact = copy._exact
    prior = {e: list(copy.sub.element_subdomains(e)) for e in near.tolist()}
    solids = {
        sid: copy.sub.element_solid(sid) for e in near.tolist() if e in exact for sid in prior[e] if sid not in programs
    }
    extent = _COVER * 2 * float(np.max(np.linalg.norm(X - point, axis=1)))
    report = copy.cut(plane_cut_solid(point, normal, extent, epsilon))
    touched = report.elements_touched
    if len(touched) == 0:
        raise ValueError(f"{name}: the slab misses the body (no element meets it)")
    if not set(touched.tolist()) <= set(prior):
        raise ValueError(f"{name}: the cut met elements away from its plane")
    used = [sid for e in touched.tolist() for sid in prior[e] if sid in solids]
    meshes = [solid_mesh(solids[sid]) for sid in used]
    place = np.where(s_nodes > half, 1, np.where(s_nodes < -half, -1, 0))
    first = table.corners is None
    ids = table.stage(([X] if first else []) + [m.V for m in meshes], place)
    if first:
        table.corners = ids.pop(0)
    start = {sid: (m, i) for sid, m, i in zip(used, meshes, ids)}
    s_table = (table.positions - point) @ normal
    made = {}
    for e in touched.tolist():
        for sid in copy.sub.element_subdomains(e):
            origin = sid if sid in prior[e] else copy.sub.element_parent(sid)
            if origin not in prior[e]:
                raise ValueError(f"model: piece {sid} of element {e} has no piece before the cut")
            side = 1.0 if (copy._integrals[sid][3] - point) @ normal > 0 else -1.0
            if origin in programs:
                faces = programs[origin]
            elif origin in start:
                mesh, at = start[origin]
                faces = [tuple(f) for f in at[mesh.F].tolist()]
            else:  # the whole tet (a TetMesh's tets are positively oriented: TET_FACES are outward)
                corners = table.corners  # set by the first stage
                faces = [tuple(f) for f in corners[T[e]][TET_FACES].tolist()]  # pyright: ignore[reportOptionalSubscript]
            clipped = _clip(table, faces, side, s_table, half)
            if clipped is None:
                raise ValueError(f"model: piece {sid} of element {e} is not on the side of the slab its point is")
            made[sid] = clipped
    for sid in report.element_children:
        programs.pop(sid, None)
    programs.update(made)
    return report


def _stage_replay(copy: XFEMModel, table: _Table, programs: dict, epsilons: list):
    """The ``_Replay`` of the copy's current system, that system (host) and the pieces' elements."""
    element, dofs, volume, mass, load = copy.piece_arrays()
    system = copy.system()
    sids = copy.piece_ids()
    rows = np.flatnonzero(np.isin(sids, list(programs)))
    by_length: dict[int, tuple[list, list]] = {}  # the faces by their vertex count, fanned together
    for r, row in enumerate(rows.tolist()):
        for face in programs[int(sids[row])]:
            faces, owners = by_length.setdefault(len(face), ([], []))
            faces.append(face)
            owners.append(r)
    triangles, triangle_row = [np.zeros((0, 3), np.int64)], [np.zeros(0, np.int64)]
    for length, (faces, owners) in by_length.items():
        faces, i = np.asarray(faces, np.int64), np.arange(1, length - 1)
        triangles.append(
            np.stack([np.repeat(faces[:, :1], length - 2, axis=1), faces[:, i], faces[:, i + 1]], axis=-1).reshape(
                -1, 3
            )
        )
        triangle_row.append(np.repeat(np.asarray(owners, np.int64), length - 2))
    Xe = copy.X[copy.T[element[rows]]]
    origin = Xe.mean(axis=1)
    c, g = linear_shape_coefficients(Xe, origin)
    n = system.n
    mass_rows, mass_cols = np.asarray(system.mass_rows, np.int64), np.asarray(system.mass_cols, np.int64)
    keys = mass_rows * n + mass_cols
    r_ = np.broadcast_to(dofs[:, :, None], mass.shape).ravel()
    c_ = np.broadcast_to(dofs[:, None, :], mass.shape).ravel()

    def entry(key):
        at = np.minimum(np.searchsorted(keys, key), len(keys) - 1)
        return np.where(keys[at] == key, at, len(keys))  # an entry fem_system dropped (an exact zero)

    rho = copy.rho[element]
    host = dict(  # the array fields, put on the device in one batch
        **table.arrays(),
        epsilon=np.asarray(epsilons, np.float64),
        triangles=np.concatenate(triangles),
        triangle_row=np.concatenate(triangle_row),
        origin=origin,
        c=c,
        g=g,
        rho=rho[rows],
        rows=rows,
        volume=volume,
        mass=mass,
        load=load,
        dofs=dofs,
        weight=rho,
        gravity=np.asarray(copy.gravity, np.float64),
        entry=entry(r_ * n + c_),
        transposed=entry(c_ * n + r_),
        slots=scalar_slots(system.pattern, mass_rows, mass_cols),
    )
    leaves, tree = jax.tree.flatten(host)
    replay = _Replay(
        **jax.tree.unflatten(tree, to_devices(*leaves)), entries=len(keys), nnz=int(system.pattern.nnz), n=n
    )
    return replay, system, element


_UNDER_JIT = (
    "cut_system finds the pieces on the host and needs a concrete plane (under jit, call plane_cuts "
    "outside and its system(points, normals) inside)"
)


def _concrete(name: str, x, advice: str = _UNDER_JIT) -> np.ndarray:
    """The concrete value of x (also of a tracer of eager ``jax.grad``), or ValueError naming it and giving the
    advice (under jit)."""
    try:
        return np.asarray(concrete_or_error(None, x, name))
    except jax.errors.ConcretizationTypeError:
        raise ValueError(f"{name}: {advice}") from None


def cut_system(
    model: XFEMModel, point: Float[ArrayLike, " 3"], normal: Float[ArrayLike, " 3"], epsilon: float
) -> FEMSystem:
    """The system of the model as if cut by the slab of thickness epsilon across the plane (point, normal)
    (``plane_cut_solid`` with an extent covering the body, ``XFEMModel.cut``), the model left uncut: its DOF
    numbering is the cut model's, and its volumes, mass values, mass data and forces are JAX functions of point and
    normal (module docstring), differentiable by ``jax.grad`` (eagerly: the pieces are found at the concrete plane;
    under jit use ``plane_cuts(...).system``). Each call cuts a copy of the model on the host (its earlier cuts made
    again, then the slab's Booleans): for many planes near one another, ``plane_cuts`` once and its ``system``.

    Args:
        model: the ``XFEMModel`` (earlier cuts of any solids are constants).
        point: (3,) a point of the mid-plane.
        normal: (3,) its unit normal (the gradient with respect to it is tangent to the unit sphere).
        epsilon: the slab's thickness > 0.
    Returns:
        The ``FEMSystem`` (``XFEMModel.system`` of the cut model, to rounding).
    """
    cuts = plane_cuts(model, [(_concrete("point", point), _concrete("normal", normal), epsilon)])
    return cuts.system(jnp.asarray(point)[None], jnp.asarray(normal)[None])
