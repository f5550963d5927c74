"""Tearing a (skinned) triangle mesh with a scalpel: Algorithm 2 of the cut/tear/drill paper
(sec. 4.2.2), with the weights of new vertices of sec. 4.3.

The scalpel is a segment known at time steps t_0 .. t_k (``Scalpel(handle, tip)``: at t_i it runs
from ``handle[i]`` to ``tip[i]``; where it crosses the surface more than once, the crossing nearest the
handle counts), given by its endpoints or as a blade moved by motors (``scalpel_path``).

1. S_i, the crossing of the scalpel with the surface at t_i (the tear points);
2. for each step i, the plane Pi_i through S_i and the scalpel's endpoints at t_{i+1};
3. from S_i's face, the intersection of Pi_i with the surface is followed face by face (across
   shared edges, towards S_{i+1}) until S_{i+1}'s face: the edge points Q_j, in order on the skin;
4. weights of S_0, S_k (barycentric in their faces) and of every Q_j (on its edge), sec. 4.3;
5. the faces on the path are re-triangulated: the tips S_0 and S_k become vertices inside their
   faces, every Q_j is duplicated, one copy for each side of the tear;
6. the two copies of every Q_j are pushed apart along Pi's normal, ``opening / 2`` each.

Successive samples make one tear along the whole path (the paper's successive tears): in the face
of an intermediate sample S_i the path goes straight from the point where it enters the face to
the point where it leaves it (the paper's assumption that the tear curve is smooth between close
samples). A plane that passes within ``tolerance`` of a vertex of the path, that would put a tear
point within 2% of an edge's length from its end, or that would leave a piece of a face smaller or
thinner than the sliver rule of ``_geometry.sliver_mask`` allows, is moved along its normal in steps of
5% of an edge (a gentle perturbation, as the XFEM paper's sec. 6.1 does for cuts through vertices), so
that no sliver triangle is created; ``TearTopology.shift`` records the move.

For a fixed topology (``TearTopology``), the positions of the new vertices are a JAX function of the
vertices, the ``Scalpel`` and the opening (``tear_positions``), so they can be differentiated.
"""

from __future__ import annotations

from typing import Literal, NamedTuple, NoReturn, overload

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_choice, check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from _jaxcga_shared.platform import EXACT
from cutting._geometry import (
    MeshEdges,
    SmallestFace,
    cross3,
    cross_rows,
    fan_triangles,
    mesh_edges,
    posed_vertices,
    rest_positions,
    segment_hits,
    skinned_mesh_like,
    sliver_mask,
)
from cutting._predicates import PREDICATES, edge_points, signed_distances
from cutting._tools import Scalpel, check_scalpel
from cutting._weights import blend_weights
from deform._model import SkinnedMesh

# A tear point keeps at least this fraction of its edge from both ends; the plane is moved (in steps
# of _SHIFT_STEP mean edge lengths of the starting face) until every point does: no sliver triangles.
_EDGE_MARGIN = 0.02
_SHIFT_STEP = 0.05
# Tip points keep at least this barycentric coordinate in their face (no sliver fan triangle when
# the scalpel meets the surface on or near an edge).
_TIP_MARGIN = 0.02
# The edge margins alone allow a corner piece of 0.02 x 0.02 of its face; each face's pieces are
# checked against the rule of ``sliver_mask`` with this headroom (the final points come from the
# predicates, which may round differently), and the plane moves on where one is a sliver.
_PIECE_HEADROOM = 1.1


class TearTopology(NamedTuple):
    """The topology of a tear (``tear_topology``), and the geometry it was computed from.

    Attributes:
        sample_faces: (k+1,) int the face crossed by the scalpel at each sample t_i.
        sample_corners: (k+1, 3) int that face's vertices (``F[sample_faces]``).
        sample_points: (k+1, 3) the crossings S_i.
        sample_barycentric: (k+1, 3) barycentric coordinates of S_i in its face.
        faces: (p,) int the faces on the tear path, in order from S_0's face to S_k's face.
        edge_ids: (p-1,) int the edge (``MeshEdges`` id) between path faces j and j+1 that carries Q_j.
        crossing: (p-1, 2) int its vertices (i, j).
        t: (p-1,) parameter of Q_j along its edge, ``Q = (1 - t) V_i + t V_j``.
        points: (p-1, 3) the Q_j before the opening.
        step: (p-1,) int the scalpel step i (plane Pi_i) that gave Q_j.
        planes: (k, 4) the planes Pi_i as (unit normal, d): the normal points to the tear's left
            (face normal x path direction), d includes the perturbation.
        orientation: (k,) +1 or -1: Pi_i's normal is ``orientation * (A - S_i) x (B - S_i)``
            normalized, with A, B the scalpel's endpoints at t_{i+1}.
        shift: (k,) how far each plane was moved along its oriented normal (the perturbation; mostly 0):
            ``planes[i, 3] = planes[i, :3] . S_i + shift[i]``.
    """

    sample_faces: Int[np.ndarray, " s"]
    sample_corners: Int[np.ndarray, "s 3"]
    sample_points: Float[np.ndarray, "s 3"]
    sample_barycentric: Float[np.ndarray, "s 3"]
    faces: Int[np.ndarray, " f"]
    edge_ids: Int[np.ndarray, " q"]
    crossing: Int[np.ndarray, "q 2"]
    t: Float[np.ndarray, " q"]
    points: Float[np.ndarray, "q 3"]
    step: Int[np.ndarray, " q"]
    planes: Float[np.ndarray, "k 4"]
    orientation: Float[np.ndarray, " k"]
    shift: Float[np.ndarray, " k"]


def scalpel_path(blade: Float[ArrayLike, "2 3"], motors: cga.Multivector) -> Scalpel:
    """A scalpel from a blade moved by motors: the segment ``blade`` (2, 3) (handle end first)
    carried by each of the k+1 versors ``motors`` (a jaxcga Multivector of motors or similitudes with
    batch shape (k+1,), e.g. two motors for the paper's two time steps, or a motor spline sampled at
    t_0 .. t_k).

    Args:
        blade: (2, 3) the segment's handle end and tip at rest.
        motors: versors with batch shape (k+1,).
    Returns:
        The ``Scalpel`` (float64 numpy ends (k+1, 3)) that ``tear`` takes."""
    blade = np.asarray(blade, np.float64)
    if blade.shape != (2, 3) or not np.all(np.isfinite(blade)):
        raise ValueError(f"blade: expected 2 finite endpoints of shape (2, 3), got {blade.shape}")
    if not isinstance(motors, cga.Multivector) or len(motors.batch_shape) != 1 or motors.batch_shape[0] < 2:
        raise ValueError("motors: expected a jaxcga versor Multivector with batch shape (k+1,), k+1 >= 2")
    per_sample = cga.Multivector(motors.values[:, None, :], motors.blades)  # (k+1, 1) against (2,) points
    samples = np.asarray(cga.apply_to_points(per_sample, jnp.asarray(blade)), np.float64)
    return Scalpel(samples[:, 0], samples[:, 1])


def _tip(V, F, segment, index):
    faces, barycentric, _ = segment_hits(V, F, segment[0], segment[1])
    if len(faces) == 0:
        raise ValueError(
            f"scalpel (sample {index}): the scalpel does not cross the surface (no face between "
            f"{segment[0].tolist()} and {segment[1].tolist()})"
        )
    b = np.maximum(barycentric[0], _TIP_MARGIN)
    b /= b.sum()
    return int(faces[0]), b, b @ V[F[faces[0]]]


def _face_normal(V, corners):
    return cross_rows(V[corners[1]] - V[corners[0]], V[corners[2]] - V[corners[0]])


class _NearVertex(Exception):
    """The plane passes within the tolerance of a vertex of the path, or leaves a sliver piece: move it
    and walk again."""


class _Lost(Exception):
    """The plane's curve leaves the faces being followed (after a move, it may miss the first face)."""


# The pieces that a chord leaves of a face, in ``_retriangulate``'s order: a triangle and a quadrilateral, as
# slots of [corners 0-2, the points on local edges 0-2], for the chord's local edges (0, 1), (0, 2) and (1, 2).
_CHORD_TRIANGLES = np.array([[3, 1, 4], [5, 0, 3], [4, 2, 5]])
_CHORD_QUADS = np.array([[4, 2, 0, 3], [3, 1, 2, 5], [5, 0, 1, 4]])
# The boundary of a tip face with its one point (slot 3) on local edge k, fanned from the tip (slot 4).
_TIP_CYCLES = np.array([[0, 3, 1, 2], [0, 1, 3, 2], [0, 1, 2, 3]])
_TIP_FANS = np.stack([_TIP_CYCLES, np.roll(_TIP_CYCLES, -1, axis=1), np.full((3, 4), 4)], axis=2)  # (3, 4, 3)
# ``fan_triangles`` of a quadrilateral: from each apex a, the triangles (a, a+i, a+i+1), i = 1, 2 (mod 4)
_APEX = np.repeat(np.arange(4), 2)
_FAN_B = (_APEX + np.tile([1, 2], 4)) % 4
_FAN_C = (_FAN_B + 1) % 4


def _local_edges(edges: MeshEdges, faces, edge_ids):
    """The local index (0-2) of each edge in its face."""
    return np.argmax(edges.face_edges[faces] == np.asarray(edge_ids)[:, None], axis=1)


def _quad_fans(quads):
    """``fan_triangles`` of quadrilaterals (c, 4, 3), in its arithmetic: the two triangles (c, 2, 3, 3) from
    the first apex whose smaller triangle is largest."""
    apex = quads[:, _APEX]
    n = cross_rows(quads[:, _FAN_B] - apex, quads[:, _FAN_C] - apex)
    sizes = n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1] + n[..., 2] * n[..., 2]
    best = np.argmax(sizes.reshape(-1, 4, 2).min(axis=2), axis=1)
    ring = np.take_along_axis(quads, ((best[:, None] + np.arange(4)) % 4)[:, :, None], axis=1)
    return np.stack([ring[:, [0, 1, 2]], ring[:, [0, 2, 3]]], axis=1)


def _slivers(V, F, edges: MeshEdges, chords, tips, smallest: SmallestFace) -> bool:
    """Whether the tear leaves a sliver piece (``sliver_mask`` with _PIECE_HEADROOM) of a face it crosses:
    the same split as ``_retriangulate``, all faces at once. ``chords``: (face, entry edge, entry point,
    exit edge, exit point) of the faces it goes through; ``tips``: (face, edge, point, tip) of the faces it
    starts or ends in, fanned from the tip."""
    pieces, parents = [], []
    if chords:
        faces, entry, entry_point, exit_, exit_point = (np.asarray(x) for x in zip(*chords))
        corners = np.take(V, F[faces], axis=0)
        smallest.near(corners)
        slots = np.concatenate([corners, np.zeros_like(corners)], axis=1)
        rows = np.arange(len(faces))
        k_in, k_out = _local_edges(edges, faces, entry), _local_edges(edges, faces, exit_)
        slots[rows, 3 + k_in] = entry_point
        slots[rows, 3 + k_out] = exit_point
        case = k_in + k_out - 1  # (0, 1) -> 0, (0, 2) -> 1, (1, 2) -> 2
        pieces += [slots[rows[:, None], _CHORD_TRIANGLES[case]], _quad_fans(slots[rows[:, None], _CHORD_QUADS[case]])]
        parents += [corners, np.repeat(corners, 2, axis=0)]
    if tips:
        faces, edge, point, tip = (np.asarray(x) for x in zip(*tips))
        corners = np.take(V, F[faces], axis=0)
        smallest.near(corners)
        slots = np.concatenate([corners, point[:, None], tip[:, None]], axis=1)
        fans = _TIP_FANS[_local_edges(edges, faces, edge)]  # (c, 4, 3)
        pieces.append(slots[np.arange(len(faces))[:, None, None], fans])
        parents.append(np.repeat(corners, 4, axis=0))
    if not pieces:
        return False
    pieces = np.concatenate([p.reshape(-1, 3, 3) for p in pieces])
    return bool(sliver_mask(pieces, np.concatenate(parents), smallest, _PIECE_HEADROOM).any())


def _walk(
    V, F, edges: MeshEdges, s, margin, start, entry_edge, entry_point, origin, goal, target, visited, smallest, final
):
    """Follow the zero set of the signed distances s from face ``start`` (entered over
    ``entry_edge`` at ``entry_point``, or from the tip ``origin`` inside it) to face ``target`` (the
    last sample's face, holding the tip ``goal``, when ``final``).
    Returns the crossed edge ids and the faces entered (target last)."""
    crossed, entered = [], []
    # The faces' pieces are checked together when the walk ends or fails: a sliver in any face it went
    # through moves the plane, as a check face by face would have.
    chords, tips = [], []

    def stop(error: Exception) -> NoReturn:
        if _slivers(V, F, edges, chords, tips, smallest):
            raise _NearVertex
        raise error

    f, e_from, point_in = start, entry_edge, entry_point
    for _ in range(len(F) + 1):
        if np.abs(s[F[f]]).min() <= margin:
            raise _NearVertex
        candidates = [
            int(e) for e in edges.face_edges[f] if e != e_from and s[edges.edges[e, 0]] * s[edges.edges[e, 1]] < 0
        ]
        if not candidates:
            stop(_Lost())
        if len(candidates) > 1:
            # only in the first face: leave it towards the next sample
            def progress(e):
                i, j = edges.edges[e]
                x = V[i] + s[i] / (s[i] - s[j]) * (V[j] - V[i])
                return float((x - origin) @ (goal - origin))

            candidates.sort(key=progress, reverse=True)
        e = candidates[0]
        i, j = edges.edges[e]
        t = s[i] / (s[i] - s[j])
        if min(t, 1.0 - t) < _EDGE_MARGIN:
            raise _NearVertex
        point_out = V[i] + t * (V[j] - V[i])
        if e_from is None:
            tips.append((f, e, point_out, origin))
        else:
            chords.append((f, e_from, point_in, e, point_out))
        if edges.edge_counts[e] != 2:
            stop(
                ValueError(
                    "mesh: the tear reaches the boundary of the surface or a non-manifold edge "
                    f"(edge {edges.edges[e].tolist()}; if the mesh has seams of split vertices, weld "
                    "it first: deform.weld or load_model(..., weld=True))"
                )
            )
        g = int(edges.edge_faces[e, 0] if edges.edge_faces[e, 0] != f else edges.edge_faces[e, 1])
        crossed.append(e)
        entered.append(g)
        if g == target and g in visited:
            # an earlier step went through the next sample's face: cut twice, it would lose or double area
            stop(ValueError("scalpel: the tear path crosses itself (it passed through the next sample's face)"))
        if g == target:
            if final:
                tips.append((g, e, point_out, goal))
            if _slivers(V, F, edges, chords, tips, smallest):
                raise _NearVertex
            return crossed, entered
        if g == start:
            stop(
                ValueError(
                    "scalpel: the tear plane's curve on the surface does not reach the next sample "
                    "(it closes on itself; the samples are too far apart)"
                )
            )
        if g in visited:
            stop(ValueError("scalpel: the tear path crosses itself"))
        visited.add(g)
        f, e_from, point_in = g, e, point_out
    stop(ValueError("scalpel: the tear path does not reach the next sample"))


def tear_topology(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    scalpel: Scalpel,
    *,
    predicates: str = "euclidean",
    tolerance: float = 1e-6,
    edges: MeshEdges | None = None,
) -> TearTopology:
    """The tear path of a scalpel moving over the mesh (V, F) (Algorithm 2, steps 1-3).

    Args:
        V: (n, 3) vertex positions (rest pose or posed).
        F: (m, 3) int faces.
        scalpel: the ``Scalpel``: handle and tip ends (k+1, 3) at k+1 >= 2 time steps.
        predicates: ``"euclidean"`` or ``"ga"`` (Table 1) for the side of a vertex and the edge points.
        tolerance: planes passing closer than ``tolerance`` times the bounding-box diagonal to a path
            vertex are moved away from it (see the module docstring).
        edges: ``mesh_edges(F)``, precomputed once per topology.
    Raises:
        ValueError: a scalpel sample that does not cross the surface, a tear that crosses no edge
            (it stays inside one face), reaches the boundary, crosses itself or cannot be followed."""
    check_choice("predicates", predicates, PREDICATES)
    V, F = check_triangle_mesh(V, F, min_faces=0)
    segments = check_scalpel(scalpel)
    if not tolerance >= 0:
        raise ValueError(f"tolerance: expected a non-negative number, got {tolerance}")
    edges = mesh_edges(F) if edges is None else edges
    if edges.face_edges.shape != F.shape:
        raise ValueError(f"edges: computed for another mesh (face_edges {edges.face_edges.shape}, F {F.shape})")
    diagonal = bounding_diagonal(V)
    margin = tolerance * diagonal
    smallest = SmallestFace(V, F)
    samples = [_tip(V, F, segment, i) for i, segment in enumerate(segments)]
    sample_faces = np.array([f for f, _, _ in samples])
    sample_points = np.array([p for _, _, p in samples])
    sample_barycentric = np.array([b for _, b, _ in samples])

    faces, crossed, steps = [int(sample_faces[0])], [], []
    planes, orientation, shifts, point_chunks, t_chunks = [], [], [], [], []
    visited = {faces[0]}
    entry_edge, entry_point = None, sample_points[0]
    for i in range(len(segments) - 1):
        origin, goal = sample_points[i], sample_points[i + 1]
        A, B = segments[i + 1]
        normal = cross_rows(A - origin, B - origin)
        length = np.linalg.norm(normal)
        if length <= 1e-12 * diagonal**2:
            raise ValueError(
                f"scalpel (sample {i + 1}): the scalpel passes through the previous tear point, so the "
                "tear plane is not defined (move the scalpel between samples)"
            )
        n = normal / length
        d = float(n @ origin)
        target = int(sample_faces[i + 1])
        sign, shift = 1.0, 0.0
        step_edges, step_faces = [], []
        if target != faces[-1]:
            # the plane as given, then moved along its normal both ways (gentle perturbation)
            corners = V[F[faces[-1]]]
            unit = _SHIFT_STEP * np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).mean()
            for shift in unit * np.array([0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]):
                s = signed_distances(V, n, d + shift, predicates)
                try:
                    step_edges, step_faces = _walk(
                        V,
                        F,
                        edges,
                        s,
                        margin,
                        faces[-1],
                        entry_edge,
                        entry_point,
                        origin,
                        goal,
                        target,
                        set(visited),
                        smallest,
                        final=i == len(segments) - 2,
                    )
                    break
                except _NearVertex:
                    failure = (
                        f"scalpel (sample {i + 1}): the tear plane keeps passing through or next to "
                        "vertices of the mesh (within the tolerance, or leaving sliver triangles); move "
                        "the scalpel slightly"
                    )
                except _Lost:
                    failure = (
                        "scalpel: the tear plane leaves the surface's path between two samples (the "
                        "samples are too far apart or the tear turns back)"
                    )
            else:
                raise ValueError(failure)
            # Orient the normal to the left of the path: face normal x direction of travel.
            i0, j0 = edges.edges[step_edges[0]]
            first_point = V[i0] + s[i0] / (s[i0] - s[j0]) * (V[j0] - V[i0])
            left = cross_rows(_face_normal(V, F[faces[-1]]), first_point - entry_point)
            sign = 1.0 if n @ left >= 0 else -1.0
            visited.update(step_faces)
            pairs = edges.edges[step_edges]
            points, t = edge_points(
                V[pairs[:, 0]], V[pairs[:, 1]], s[pairs[:, 0]], s[pairs[:, 1]], n, d + shift, predicates
            )
        else:
            points, t = np.zeros((0, 3)), np.zeros(0)
        planes.append(np.append(sign * n, sign * (d + shift)))
        orientation.append(sign)
        shifts.append(sign * shift)  # along the oriented normal
        point_chunks.append(points)
        t_chunks.append(t)
        crossed += step_edges
        steps += [i] * len(step_edges)
        faces += step_faces
        if step_edges:
            entry_edge, entry_point = step_edges[-1], points[-1]
    if not crossed:
        raise ValueError(
            "scalpel: the tear crosses no edge of the mesh (it stays inside one face); move the "
            "scalpel farther between samples"
        )
    crossed = np.asarray(crossed)
    return TearTopology(
        sample_faces,
        F[sample_faces],
        sample_points,
        sample_barycentric,
        np.asarray(faces),
        crossed,
        edges.edges[crossed],
        np.concatenate(t_chunks),
        np.concatenate(point_chunks),
        np.asarray(steps),
        np.asarray(planes),
        np.asarray(orientation),
        np.asarray(shifts),
    )


def _retriangulate(V, F, edges: MeshEdges, topology: TearTopology, n_vertices: int):
    """Triangles replacing the path faces (Algorithm 2, step 5). Vertex ids: the input's, then S_0
    (n), S_k (n+1), the left copies of Q_j (n+2+j), the right copies (n+2+q+j). Per path face in
    plain Python: a path crosses few faces, and small arrays cost more than they save."""
    q = len(topology.t)
    tips = (n_vertices, n_vertices + 1)
    point_of_edge = {e: j for j, e in enumerate(topology.edge_ids.tolist())}
    corners_of = F[topology.faces].tolist()
    position = dict(zip(np.ravel(corners_of).tolist(), V[np.ravel(corners_of)].tolist()))
    points = topology.points.tolist()
    sample_points = topology.sample_points[[0, -1]].tolist()

    def sub(a, b):
        return (a[0] - b[0], a[1] - b[1], a[2] - b[2])

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    def is_left(normal, origin, direction, corner):
        # the corner lies left of the directed path (face normal x direction)
        return dot(cross3(normal, direction), sub(position[corner], origin)) > 0

    triangles = []
    last = len(topology.faces) - 1
    for at, (corners, local) in enumerate(zip(corners_of, edges.face_edges[topology.faces].tolist())):
        a, b, c = (position[v] for v in corners)
        normal = cross3(sub(b, a), sub(c, a))
        entry = at - 1 if at > 0 else None
        exit_ = at if at < last else None
        # the face's boundary in winding order, with its path points on their edges
        cycle = []
        for k in range(3):
            cycle.append(("corner", corners[k]))
            j = point_of_edge.get(local[k])
            if j is not None and j in (entry, exit_):
                cycle.append(("point", j))
        if entry is None or exit_ is None:  # a tip face: fan from the tip S inside it
            tip = tips[0] if entry is None else tips[1]
            j = exit_ if entry is None else entry
            tip_point = sample_points[0] if entry is None else sample_points[1]
            direction = sub(points[j], tip_point) if entry is None else sub(tip_point, points[j])
            for m in range(len(cycle)):
                x, y = cycle[m], cycle[(m + 1) % len(cycle)]
                if "point" in (x[0], y[0]):
                    corner = y[1] if x[0] == "point" else x[1]
                    copy = _copy(j, q, n_vertices, is_left(normal, points[j], direction, corner))
                    ids = [copy if z[0] == "point" else z[1] for z in (x, y)]
                else:
                    ids = [x[1], y[1]]
                triangles.append((ids[0], ids[1], tip))
            continue
        # a chord face: the segment entry -> exit splits it into two convex pieces
        start = cycle.index(("point", entry))
        cycle = cycle[start:] + cycle[:start]
        stop = cycle.index(("point", exit_))
        direction = sub(points[exit_], points[entry])
        for piece in (cycle[: stop + 1], cycle[stop:] + cycle[:1]):
            corner = next(z[1] for z in piece if z[0] == "corner")
            left = is_left(normal, points[entry], direction, corner)
            ids = [_copy(z[1], q, n_vertices, left) if z[0] == "point" else z[1] for z in piece]
            coordinates = [points[z[1]] if z[0] == "point" else position[z[1]] for z in piece]
            triangles += fan_triangles(ids, coordinates)
    return np.asarray(triangles, np.int64).reshape(-1, 3)


def _copy(j, q, n_vertices, is_left):
    return n_vertices + 2 + j if is_left else n_vertices + 2 + q + j


@overload
def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel,
    *,
    opening: float = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[False] = ...,
) -> SkinnedMesh: ...


@overload
def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel,
    *,
    opening: float = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[True],
) -> tuple[SkinnedMesh, TearTopology]: ...


def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel,
    *,
    opening: float = 0.0,
    predicates: str = "euclidean",
    side_weight: float = 0.0,
    tolerance: float = 1e-6,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = None,
    edges: MeshEdges | None = None,
    return_topology: bool = False,
) -> SkinnedMesh | tuple[SkinnedMesh, TearTopology]:
    """Tear a skinned mesh with a scalpel moving through its samples (Algorithm 2).

    Args:
        mesh: the SkinnedMesh (``deform``).
        scalpel: the ``Scalpel``: its handle and tip ends (k+1, 3) at time steps t_0 .. t_k, in the
            space of the mesh as torn: the bind pose, or the pose of ``joint_matrices``. Two samples
            are the paper's ``scalpel_0, scalpel_1``; more make one tear along the whole path.
        opening: the distance between the two copies of every interior tear point (each is pushed
            ``opening / 2`` along the tear plane's normal, away from it); 0 leaves a closed slit.
        predicates: ``"euclidean"`` or ``"ga"`` (Table 1).
        side_weight: in [0, 1]; 0 gives both copies of a tear point the barycentric weights of its
            edge (sec. 4.3); towards 1 each copy leans to the weights of its own side's endpoint.
        tolerance: see ``tear_topology``.
        joint_matrices: (j, 4, 4) joint matrices of a pose (``deform.joint_matrices``): tear the mesh
            *in that pose*, the scalpel in world space. New vertices get the rest positions whose LBS
            image in that pose is their torn position (exact for LBS).
        edges: ``mesh_edges(mesh.F)``, precomputed.
        return_topology: also return the ``TearTopology`` (for ``tear_positions``).
    Returns:
        The torn SkinnedMesh (the input's vertices first, in order; then S_0, S_k, the left copies of
        the Q_j, the right copies), and the TearTopology when ``return_topology``."""
    if not 0.0 <= side_weight <= 1.0:
        raise ValueError(f"side_weight: expected a number in [0, 1], got {side_weight}")
    if not (np.isfinite(opening) and opening >= 0):
        raise ValueError(f"opening: expected a finite non-negative distance, got {opening}")
    F = np.asarray(mesh.F)
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    edges = mesh_edges(F) if edges is None else edges
    topology = tear_topology(space, F, scalpel, predicates=predicates, tolerance=tolerance, edges=edges)
    n_vertices, q = len(space), len(topology.t)

    tip_faces = topology.sample_faces[[0, -1]]
    J_tips, W_tips = blend_weights(J, W, F[tip_faces], topology.sample_barycentric[[0, -1]])
    J_q, W_q = blend_weights(J, W, topology.crossing, np.stack([1.0 - topology.t, topology.t], axis=1))
    normals = topology.planes[topology.step, :3]
    copies_J, copies_W = [], []
    for side in (1.0, -1.0):
        if side_weight > 0 and q:
            own = np.where(
                side * np.einsum("ij,ij->i", space[topology.crossing[:, 0]] - topology.points, normals) > 0,
                topology.crossing[:, 0],
                topology.crossing[:, 1],
            )
            Jc, Wc = blend_weights(
                np.concatenate([J, J_q]),
                np.concatenate([W, W_q]),
                np.stack([n_vertices + np.arange(q), own], axis=1),
                np.broadcast_to([1.0 - side_weight, side_weight], (q, 2)),
            )
        else:
            Jc, Wc = J_q, W_q
        copies_J.append(Jc)
        copies_W.append(Wc)
    J_new = np.concatenate([J_tips] + copies_J)
    W_new = np.concatenate([W_tips] + copies_W)
    world = np.concatenate(
        [
            topology.sample_points[[0, -1]],
            topology.points + 0.5 * opening * normals,
            topology.points - 0.5 * opening * normals,
        ]
    )
    rest = rest_positions(J_new, W_new, world, joint_matrices)

    keep = np.ones(len(F), bool)
    keep[topology.faces] = False
    triangles = _retriangulate(space, F, edges, topology, n_vertices)
    torn = skinned_mesh_like(
        mesh,
        np.concatenate([np.asarray(mesh.V, np.float64), rest]),
        np.concatenate([np.compress(keep, F, axis=0), triangles]),
        np.concatenate([J, J_new]),
        np.concatenate([W, W_new]),
    )
    return (torn, topology) if return_topology else torn


def tear_positions(
    V: Float[ArrayLike, "n 3"], topology: TearTopology, scalpel: Scalpel, *, opening: Float[ArrayLike, ""] = 0.0
) -> tuple[Float[Array, "2 3"], Float[Array, "q 3"], Float[Array, "q 3"]]:
    """Positions of a tear's new vertices as a JAX function of the vertices, the scalpel and the
    opening, for a fixed topology: differentiable with respect to all three (``jax.grad`` over a
    ``Scalpel`` gives a ``Scalpel``). Each S_i is the scalpel's crossing with its face's plane, kept the
    same 2% (barycentric) off the face's edges as in ``tear_topology``.

    Args:
        V: (n, 3) vertex positions, as torn (posed, when torn with ``joint_matrices``).
        topology: the tear's ``TearTopology``.
        scalpel: the ``Scalpel``, with as many samples (k+1) as the topology was computed from.
        opening: () the distance between the two copies of every Q_j (see ``tear``).
    Returns:
        (tips (2, 3): S_0 and S_k, left (q, 3), right (q, 3): the two copies of every Q_j)."""
    V = jnp.asarray(V)
    X0, X1 = jnp.asarray(scalpel.handle), jnp.asarray(scalpel.tip)
    if X0.shape != (len(topology.sample_faces), 3) or X1.shape != X0.shape:
        raise ValueError(
            f"scalpel: expected handle and tip ends of shape ({len(topology.sample_faces)}, 3) (the "
            f"topology's samples), got {X0.shape}, {X1.shape}"
        )
    corners = V[jnp.asarray(topology.sample_corners)]  # (k+1, 3, 3)
    face_normals = jnp.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    s = jnp.sum(face_normals * (corners[:, 0] - X0), -1) / jnp.sum(face_normals * (X1 - X0), -1)
    crossings = X0 + s[:, None] * (X1 - X0)
    # barycentric coordinates in the face, with tear_topology's margin (piecewise smooth in the tool)
    squared = jnp.sum(face_normals * face_normals, -1)
    barycentric = (
        jnp.stack(
            [
                jnp.sum(
                    face_normals * jnp.cross(corners[:, (k + 1) % 3] - crossings, corners[:, (k + 2) % 3] - crossings),
                    -1,
                )
                for k in range(3)
            ],
            axis=-1,
        )
        / squared[:, None]
    )
    barycentric = jnp.maximum(barycentric, _TIP_MARGIN)
    barycentric = barycentric / jnp.sum(barycentric, -1, keepdims=True)
    samples = jnp.einsum("sk,skc->sc", barycentric, corners, precision=EXACT)
    normals = jnp.cross(X0[1:] - samples[:-1], X1[1:] - samples[:-1])
    normals = jnp.asarray(topology.orientation)[:, None] * normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    offsets = jnp.sum(normals * samples[:-1], -1) + jnp.asarray(topology.shift)
    step = jnp.asarray(topology.step)
    n, d = normals[step], offsets[step]
    A, B = V[topology.crossing[:, 0]], V[topology.crossing[:, 1]]
    sA, sB = jnp.sum(A * n, -1) - d, jnp.sum(B * n, -1) - d
    Q = A + (sA / (sA - sB))[:, None] * (B - A)
    half = 0.5 * opening * n
    return samples[jnp.array([0, -1])], Q + half, Q - half
