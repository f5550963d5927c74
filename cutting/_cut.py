"""Planar cut of a (skinned) triangle mesh: Algorithm 1 of the cut/tear/drill paper (sec. 4.2.1),
with the weights of new vertices of sec. 4.3 and, beyond the paper, optional capping.

Steps, vectorized over faces (host numpy; the predicates may run on the jaxcga kernel):

1. signed distances of the vertices (``predicates="euclidean"`` or ``"ga"``, Table 1); a vertex within
   ``tolerance`` (relative to the bounding-box diagonal) of the plane is snapped *onto* it (its
   position is kept, only its side changes);
2. one new vertex per edge whose endpoints lie strictly on opposite sides, at ``t = s_i / (s_i - s_j)``
   along the edge, weights blended from the edge's endpoints (sec. 4.3);
3. every face re-triangulated by a table over its 27 sign patterns (a lone vertex gives 1 + 2
   triangles, the quadrilateral split by whichever diagonal leaves no sliver; a vertex on the plane
   1 + 1); where a piece would still be a sliver (``_geometry.sliver_mask``), the vertex next to the
   face's new point nearest an end of its edge is snapped onto the plane too, and steps 2-3 repeat;
4. faces sorted into the positive side (``n . x > d``) and the negative side;
5. each side compacted into its own mesh; with ``cap=True`` and a closed input, the cut loops are
   triangulated (manifold3d) and close both halves.

These are the four sub-routines of the paper's Table 1, one function each, which ``cut_topology`` and ``cut``
call in turn: (1) the vertices' sides, step 1 (``vertex_sides``); (2) the intersection points and the split
faces' pieces, steps 2-3 (``intersections``); (3) the new vertices' weights (``new_vertex_data``); (4) the split
into two meshes, steps 4-5 (``separate``, ``split_mesh``). Only (1) and (2) use the predicates.

Vertices on the plane and new vertices belong to both halves (each half has its own copy). The
original vertices keep their rest positions, joints and weights, so skinning a half at any pose gives,
at every original vertex, exactly what skinning the input gives.

For a fixed topology (``CutTopology``) the positions of new vertices are a JAX function of the vertices
and the ``Plane`` (``cut_positions``), so they can be differentiated with respect to the tool.
"""

from __future__ import annotations

import itertools
from typing import Literal, NamedTuple, overload

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_choice, check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from cutting._geometry import (
    MeshEdges,
    SmallestFace,
    mesh_edges,
    posed_vertices,
    rest_positions,
    skinned_mesh_like,
    sliver_mask,
)
from cutting._predicates import PREDICATES, edge_points, signed_distances
from cutting._tools import Plane, check_plane
from cutting._weights import blend_weights
from deform._model import SkinnedMesh


def _split_tables(diagonal: int):
    """For each sign pattern (s0, s1, s2) in {-1, 0, 1}^3 (code = 9 (s0+1) + 3 (s1+1) + (s2+1)):
    the positive and negative triangles as slots (0-2: the face's corners, 3-5: the new vertex on
    local edge (k, k+1)); -1 pads. All-zero (a face in the plane) is handled by the caller.
    ``diagonal``: which diagonal splits the quadrilateral that a lone corner leaves on the other side
    (0: from the new point next to the lone corner's successor to the far corner, 1: the other one)."""
    positive = -np.ones((27, 2, 3), np.int64)
    negative = -np.ones((27, 2, 3), np.int64)
    for signs in itertools.product((-1, 0, 1), repeat=3):
        code = 9 * (signs[0] + 1) + 3 * (signs[1] + 1) + (signs[2] + 1)
        if all(s >= 0 for s in signs) or all(s <= 0 for s in signs):
            side = positive if any(s > 0 for s in signs) else negative
            side[code, 0] = (0, 1, 2)
            continue
        tris = {1: [], -1: []}
        if 0 in signs:  # one corner on the plane, the others on opposite sides
            z = signs.index(0)
            a, b = (z + 1) % 3, (z + 2) % 3
            x = 3 + a  # new vertex on edge (a, b)
            tris[signs[a]].append((z, a, x))
            tris[signs[b]].append((z, x, b))
        else:  # a lone corner a on one side, b and c on the other
            a = next(k for k in range(3) if signs.count(signs[k]) == 1)
            b, c = (a + 1) % 3, (a + 2) % 3
            x, y = 3 + a, 3 + c  # new vertices on edges (a, b) and (c, a)
            tris[signs[a]].append((a, x, y))
            tris[signs[b]] += [(x, b, c), (x, c, y)] if diagonal == 0 else [(x, b, y), (y, b, c)]
        for side, sign in ((positive, 1), (negative, -1)):
            for k, tri in enumerate(tris[sign]):
                side[code, k] = tri
    return positive, negative


_TABLES = (_split_tables(0), _split_tables(1))


class CutTopology(NamedTuple):
    """The topology of a planar cut (``cut_topology``), in an extended vertex numbering: the n input
    vertices, then one new vertex per crossing edge.

    Attributes:
        crossing: (p, 2) int the edges (i, j) that carry the new vertices n .. n + p - 1.
        t: (p,) parameter of each new vertex along its edge, ``x = (1 - t) V_i + t V_j``.
        points: (p, 3) positions of the new vertices (by the selected predicates).
        positive: (a,) extended indices of the positive half's vertices (its vertex order).
        positive_faces: (fa, 3) the positive half's faces in its own numbering (caps included).
        negative, negative_faces: the same for the negative half.
        distances: (n,) signed distances of the input vertices after snapping (0: on the plane).
    """

    crossing: Int[np.ndarray, "p 2"]
    t: Float[np.ndarray, " p"]
    points: Float[np.ndarray, "p 3"]
    positive: Int[np.ndarray, " a"]
    positive_faces: Int[np.ndarray, "fa 3"]
    negative: Int[np.ndarray, " b"]
    negative_faces: Int[np.ndarray, "fb 3"]
    distances: Float[np.ndarray, " n"]


def _is_closed(edges: MeshEdges) -> bool:
    return bool(np.all(edges.edge_counts == 2))


def _row_range(rows):
    """(smallest, largest) of each row of an (m, 3) array, column by column (numpy's axis-1
    reductions of narrow rows are several times slower)."""
    a, b, c = rows[:, 0], rows[:, 1], rows[:, 2]
    return np.minimum(np.minimum(a, b), c), np.maximum(np.maximum(a, b), c)


def _split(V, F, edges: MeshEdges, s, sign, n, d, predicates, smallest):
    """The new points of the current signs and the pieces of the split faces, and the vertices to snap
    onto the plane: for each face whose pieces are slivers with either diagonal (``sliver_mask``), the
    endpoint nearest to the face's new point that lies closest (along its edge) to an end.

    Returns (crossing (p, 2), t (p,), points (p, 3), pieces: for each diagonal the (positive, negative)
    pieces of the split faces (split, 2, 3) as extended vertex ids (-1 pads), diagonal (split,) the one
    chosen, snap (k,) vertex ids)."""
    e = edges.edges
    crossing_mask = sign[e[:, 0]] * sign[e[:, 1]] < 0
    # np.compress and np.take select rows several times faster than a mask or an index array
    crossing = np.compress(crossing_mask, e, axis=0)
    points, t = edge_points(
        V[crossing[:, 0]], V[crossing[:, 1]], s[crossing[:, 0]], s[crossing[:, 1]], n, d, predicates
    )
    new_index = np.full(len(e), -1, np.int64)
    new_index[crossing_mask] = len(V) + np.arange(len(crossing))
    face_signs = sign[F]
    lowest, highest = _row_range(face_signs)
    split = (lowest < 0) & (highest > 0)
    # Only the split faces go through the tables. Slots: the corners, then the new vertex (or -1)
    # on each local edge.
    split_edges = np.compress(split, edges.face_edges, axis=0)
    slots = np.concatenate([np.compress(split, F, axis=0), new_index[split_edges]], axis=1)
    code = np.compress(split, face_signs, axis=0) @ np.array([9, 3, 1]) + 13
    extended = np.concatenate([V, points])
    corners = np.take(V, slots[:, :3], axis=0)  # (split, 3, 3)
    smallest.near(corners)
    pieces, poor = [], []
    for positive, negative in _TABLES:
        templates = np.concatenate([positive[code], negative[code]], axis=1)  # (split, 4, 3)
        ids = np.take_along_axis(slots[:, None, :], np.where(templates < 0, 0, templates), axis=2)
        ids = np.where(templates < 0, -1, ids)
        valid = ids[:, :, 0] >= 0
        bad = np.zeros(valid.shape, bool)
        parent = np.nonzero(valid)[0]
        bad[valid] = sliver_mask(np.take(extended, ids[valid], axis=0), corners[parent], smallest)
        pieces.append((ids[:, :2], ids[:, 2:]))
        poor.append(bad.any(axis=1))
    diagonal = (poor[0] & ~poor[1]).astype(np.int64)
    stuck = np.flatnonzero(poor[0] & poor[1])
    if not len(stuck):
        return crossing, t, points, pieces, diagonal, np.zeros(0, np.int64)
    # the face's new point nearest an end of its edge, and that end
    local = new_index[split_edges[stuck]] - len(V)  # (k, 3), negative: no point
    along = t[np.maximum(local, 0)]
    margin = np.where(local >= 0, np.minimum(along, 1.0 - along), np.inf)
    nearest = local[np.arange(len(stuck)), np.argmin(margin, axis=1)]
    snap = np.where(t[nearest] < 0.5, crossing[nearest, 0], crossing[nearest, 1])
    return crossing, t, points, pieces, diagonal, np.unique(snap)


def cut_topology(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    plane: Plane,
    *,
    predicates: str = "ga",
    tolerance: float = 1e-6,
    cap: bool = False,
    edges: MeshEdges | None = None,
) -> CutTopology:
    """Topology and new vertices of cutting the triangle mesh (V, F) by a plane (Algorithm 1).

    Args:
        V: (n, 3) vertex positions (the mesh as it is cut: rest pose or posed).
        F: (m, 3) int faces.
        plane: the ``Plane`` (``Plane(normal, distance)``, ``Plane.through(point, normal)`` or
            ``Plane.from_multivector`` of a jaxcga plane vector, eq. 5).
        predicates: ``"ga"`` (the conformal point's inner product with the plane vector, the meet of an edge's
            line with the plane) or ``"euclidean"`` (``n . x - d``, ``a + t (b - a)``): Table 1; the same cut.
        tolerance: vertices closer to the plane than ``tolerance`` times the bounding-box diagonal
            count as on it; so does a vertex next to which a crossing would leave a sliver piece.
        cap: close both halves with the triangulated cut loops (the input must be closed).
        edges: ``mesh_edges(F)``, precomputed once per topology.
    Returns:
        The ``CutTopology`` (its attributes say what it holds), which ``cut`` applies to a ``SkinnedMesh`` and
        ``cut_positions`` to the vertices.
    Raises:
        ValueError: bad shapes, non-finite input, or a plane that misses the mesh (all vertices on one
            side: there is nothing to cut) or only grazes it (all on one side once snapped).

    Examples:
        >>> import numpy as np
        >>> import cutting
        >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])  # a unit square in two triangles
        >>> F = np.array([[0, 1, 2], [0, 2, 3]])
        >>> topology = cutting.cut_topology(V, F, cutting.Plane([1.0, 0.0, 0.0], 0.5))
        >>> topology.crossing.tolist()  # the edges that carry the new vertices
        [[0, 1], [0, 2], [2, 3]]
    """
    check_choice("predicates", predicates, PREDICATES)
    V, F = check_triangle_mesh(V, F, min_faces=0)
    if not tolerance >= 0:
        raise ValueError(f"tolerance: expected a non-negative number, got {tolerance}")
    edges = mesh_edges(F) if edges is None else edges
    if edges.face_edges.shape != F.shape:
        raise ValueError(f"edges: computed for another mesh (face_edges {edges.face_edges.shape}, F {F.shape})")
    n, d = check_plane(plane)
    s = vertex_sides(V, F, n, d, predicates, tolerance)
    crossings = intersections(V, F, edges, s, n, d, predicates)
    return separate(V, F, edges, n, crossings, cap)


# Table 1's sub-routines (module docstring), timed one by one by bench_cutting.


def vertex_sides(V, F, n, d, predicates: str, tolerance: float) -> Float[np.ndarray, " n"]:
    """Sub-routine 1: the vertices' signed distances from the plane, those within ``tolerance`` x the bounding-box
    diagonal snapped to 0.

    Args:
        V: (n, 3) vertex positions; F: (m, 3) int faces.
        n: (3,) the plane's unit normal (``check_plane``).
        d: the plane's offset (``check_plane``).
        predicates: as in ``cut_topology``.
        tolerance: see ``predicates``.
    Returns:
        (n,) the signed distances. Raises a ValueError where the plane misses the mesh."""
    s = signed_distances(V, n, d, predicates)
    s = np.where(np.abs(s) <= tolerance * bounding_diagonal(V), 0.0, s)
    if not (np.any(s[F] > 0) and np.any(s[F] < 0)):
        raise ValueError("plane: misses the mesh (every vertex lies on one side of it); nothing to cut")
    return s


class _Crossings(NamedTuple):
    """What sub-routine 2 leaves: the new points and the pieces of the split faces (``_split``), the vertices'
    signs (0: on the plane, snapped included) and their signed distances with the snapped ones set to 0."""

    crossing: Int[np.ndarray, "p 2"]
    t: Float[np.ndarray, " p"]
    points: Float[np.ndarray, "p 3"]
    pieces: list
    diagonal: Int[np.ndarray, " split"]
    sign: Int[np.ndarray, " n"]
    distances: Float[np.ndarray, " n"]


def intersections(V, F, edges: MeshEdges, s, n, d, predicates: str) -> _Crossings:
    """Sub-routine 2: the faces that the plane splits, their intersection points and their pieces, vertices
    snapped onto the plane where a piece would be a sliver.

    Args:
        V: (n, 3) vertex positions; F: (m, 3) int faces; edges: ``mesh_edges(F)``.
        s: (n,) ``vertex_sides``' signed distances.
        n: as in ``vertex_sides``.
        d: see ``n``.
        predicates: see ``n``.
    Returns:
        The ``_Crossings``. Raises a ValueError where the plane only grazes the mesh."""
    sign = np.sign(s).astype(np.int64)
    smallest = SmallestFace(V, F)
    # Each pass snaps at least one more vertex onto the plane, so this ends (at worst with no split face).
    for _ in range(len(V) + 1):
        crossing, t, points, pieces, diagonal, snap = _split(V, F, edges, s, sign, n, d, predicates, smallest)
        if not len(snap):
            break
        sign[snap] = 0
    if not (np.any(sign[F] > 0) and np.any(sign[F] < 0)):
        raise ValueError(
            "plane: only grazes the mesh (every vertex on one side of it lies so close to it that "
            "cutting there would leave sliver faces); nothing to cut"
        )
    return _Crossings(crossing, t, points, pieces, diagonal, sign, np.where(sign == 0, 0.0, s))


def separate(V, F, edges: MeshEdges, n, crossings: _Crossings, cap: bool) -> CutTopology:
    """Sub-routine 4, faces: every face (or piece) to the side it lies on, the halves' vertices and faces in
    their own numbering, the cut loops capped with ``cap``.

    Args:
        V: (n, 3) vertex positions; F: (m, 3) int faces; edges: ``mesh_edges(F)``.
        n: (3,) the plane's unit normal.
        crossings: ``intersections``' result.
        cap: as in ``cut_topology``.
    Returns:
        The ``CutTopology``."""
    crossing, t, points, pieces, diagonal, sign, s = crossings
    face_signs = sign[F]
    lowest, highest = _row_range(face_signs)
    in_plane = (lowest == 0) & (highest == 0)
    flat = F[in_plane]
    normal = np.cross(V[flat[:, 1]] - V[flat[:, 0]], V[flat[:, 2]] - V[flat[:, 0]])
    sides = []
    for k, (sign_of_side, whole) in enumerate(
        ((1, (lowest >= 0) & (highest > 0)), (-1, (highest <= 0) & (lowest < 0)))
    ):
        chosen = np.where(diagonal[:, None, None] == 0, pieces[0][k], pieces[1][k])
        valid = chosen[:, :, 0] >= 0
        # A face lying in the plane closes the half that its normal points away from.
        sides.append(
            np.concatenate([np.compress(whole, F, axis=0), chosen[valid], flat[sign_of_side * (normal @ n) < 0]])
        )

    if cap:
        if not _is_closed(edges):
            raise ValueError("cap: the input mesh is not closed (an edge is not shared by exactly two faces)")
        extended = np.concatenate([V, points])
        cap_faces = _cap(extended, sides[0], n)
        sides = [np.concatenate([sides[0], cap_faces]), np.concatenate([sides[1], cap_faces[:, ::-1]])]

    halves = []
    for faces in sides:
        used = np.zeros(len(V) + len(points), bool)
        used[faces] = True
        local = np.cumsum(used) - 1
        halves += [np.flatnonzero(used), local[faces]]
    return CutTopology(crossing, t, points, halves[0], halves[1], halves[2], halves[3], s)


def _cap(extended, positive_faces, n):
    """Triangles closing the positive half (normal -n, out of it) over its boundary loops on the plane.
    The negative half is closed by the same triangles reversed."""
    import manifold3d

    directed = np.stack([positive_faces, np.roll(positive_faces, -1, axis=1)], axis=-1).reshape(-1, 2)
    key = np.sort(directed, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = directed[counts[inverse.ravel()] == 1]
    if len(boundary) == 0:
        return np.zeros((0, 3), np.int64)
    # The cap runs along each boundary edge in the opposite direction: follow v -> u.
    following = dict(zip(boundary[:, 1].tolist(), boundary[:, 0].tolist()))
    if len(following) != len(boundary):
        raise ValueError("cap: the cut loops are not simple (the input is not manifold along the cut)")
    loops, seen = [], set()
    for start in following:
        if start in seen:
            continue
        loop, v = [], start
        while v not in seen:
            seen.add(v)
            loop.append(v)
            v = following.get(v)
            if v is None:
                raise ValueError("cap: a cut loop is open (the input is not closed along the cut)")
        loops.append(np.asarray(loop))
    # A frame (u, w) of the plane in which the cap, seen from the negative side (-n), is counter-clockwise.
    u = np.cross(n, [1.0, 0.0, 0.0] if abs(n[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(-n, u)
    polygons = [np.stack([extended[loop] @ u, extended[loop] @ w], axis=1) for loop in loops]
    triangles = np.asarray(manifold3d.triangulate(polygons), np.int64).reshape(-1, 3)
    vertex_of = np.concatenate(loops)
    faces = vertex_of[triangles]
    normal = np.cross(extended[faces[:, 1]] - extended[faces[:, 0]], extended[faces[:, 2]] - extended[faces[:, 0]])
    flip = normal @ n > 0
    faces[flip] = faces[flip][:, ::-1]
    return faces


def cut_positions(V: Float[ArrayLike, "n 3"], topology: CutTopology, plane: Plane) -> Float[Array, "p 3"]:
    """Positions of the new vertices of a cut as a JAX function of the vertices and the plane, for a
    fixed topology: differentiable with respect to both (``jax.grad`` over a ``Plane`` gives a ``Plane``).

    Args:
        V: (n, 3) vertex positions, as cut (posed, when cut with ``joint_matrices``).
        topology: the cut's ``CutTopology`` (its ``crossing`` edges are used).
        plane: the ``Plane``; its normal need not be unit length (the intersection does not depend on it).
    Returns:
        (p, 3) the new vertices, in the order of ``topology.crossing``.

    Examples:
        >>> import numpy as np
        >>> import cutting
        >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> F = np.array([[0, 1, 2], [0, 2, 3]])
        >>> plane = cutting.Plane([1.0, 0.0, 0.0], 0.5)
        >>> (cutting.cut_positions(V, cutting.cut_topology(V, F, plane), plane) + 0.0).tolist()
        [[0.5, 0.0, 0.0], [0.5, 0.5, 0.0], [0.5, 1.0, 0.0]]
    """
    V = jnp.asarray(V)
    if V.shape != (len(topology.distances), 3):
        raise ValueError(
            f"V: expected the {len(topology.distances)} vertices that were cut, shape "
            f"({len(topology.distances)}, 3), got {V.shape}"
        )
    crossing = topology.crossing
    normal, distance = jnp.asarray(plane.normal), jnp.asarray(plane.distance)
    A, B = V[crossing[:, 0]], V[crossing[:, 1]]
    sA, sB = A @ normal - distance, B @ normal - distance
    t = sA / (sA - sB)
    return A + t[:, None] * (B - A)


@overload
def cut(
    mesh: SkinnedMesh,
    plane: Plane,
    *,
    cap: bool = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[False] = ...,
) -> tuple[SkinnedMesh, SkinnedMesh]: ...


@overload
def cut(
    mesh: SkinnedMesh,
    plane: Plane,
    *,
    cap: bool = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[True],
) -> tuple[tuple[SkinnedMesh, SkinnedMesh], CutTopology]: ...


def cut(
    mesh: SkinnedMesh,
    plane: Plane,
    *,
    cap: bool = False,
    predicates: str = "ga",
    side_weight: float = 0.0,
    tolerance: float = 1e-6,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = None,
    edges: MeshEdges | None = None,
    return_topology: bool = False,
) -> tuple[SkinnedMesh, SkinnedMesh] | tuple[tuple[SkinnedMesh, SkinnedMesh], CutTopology]:
    """Cut a skinned mesh by a plane (Algorithm 1): the positive side (``n . x > d``), then the negative.

    Both halves are SkinnedMeshes with the input's joints and inverse bind matrices; they animate with
    every skinning method.

    Args:
        mesh: the SkinnedMesh (``deform``).
        plane: the ``Plane``, in the space of the mesh as cut: the bind pose, or the pose given by
            ``joint_matrices``.
        cap: close both halves (the input must be closed).
        predicates: ``"ga"`` (the conformal point's inner product with the plane vector, the meet of an edge's
            line with the plane) or ``"euclidean"`` (``n . x - d``, ``a + t (b - a)``): Table 1; the same cut.
        side_weight: in [0, 1]; 0 gives every new vertex the barycentric weights of its edge
            (sec. 4.3, the same in both halves); towards 1 each half's copy leans to the weights of its
            own side's endpoint (the variant that favours one side), 1 uses that endpoint's alone.
        tolerance: snapping distance relative to the bounding-box diagonal (see ``cut_topology``).
        joint_matrices: (j, 4, 4) joint matrices of a pose (``deform.joint_matrices``): cut the mesh
            *in that pose* (after animation), the plane in world space. New vertices get the rest
            positions whose LBS image in that pose is their position on the cut (exact for LBS, and
            for eq. (17) with rigid joints; other methods within their difference from LBS).
        edges: ``mesh_edges(mesh.F)``, precomputed.
        return_topology: also return the ``CutTopology`` (for ``cut_positions``).
    Returns:
        (positive, negative) SkinnedMeshes, and ``((positive, negative), topology)`` when
        ``return_topology``.

    Examples:
        >>> import deform, cutting
        >>> arm = deform.default_arm()
        >>> upper, lower = cutting.cut(arm.mesh, cutting.Plane([1.0, 0.0, 0.0], 0.3))  # across the upper arm
        >>> upper.V.shape[0] + lower.V.shape[0] > arm.mesh.V.shape[0]  # the new vertices are in both halves
        True
    """
    if not 0.0 <= side_weight <= 1.0:
        raise ValueError(f"side_weight: expected a number in [0, 1], got {side_weight}")
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    cut_space, joint_matrices = posed_vertices(mesh, joint_matrices)
    topology = cut_topology(cut_space, F, plane, predicates=predicates, tolerance=tolerance, cap=cap, edges=edges)
    rest, weights = new_vertex_data(V, J, W, topology, side_weight, joint_matrices)
    halves = split_mesh(mesh, V, J, W, topology, rest, weights)
    if return_topology:
        return (halves[0], halves[1]), topology
    return halves[0], halves[1]


def new_vertex_data(V, J, W, topology: CutTopology, side_weight: float, joint_matrices):
    """Sub-routine 3: the new vertices' skinning data (sec. 4.3).

    Args:
        V: (n, 3) the input's rest positions; J: (n, k) int its joints; W: (n, k) its weights.
        topology: the cut's ``CutTopology``.
        side_weight: as in ``cut`` (None or the (j, 4, 4) pose the mesh was cut in).
        joint_matrices: see ``side_weight``.
    Returns:
        (rest positions (p, 3) of the new vertices, [(J_new (p, k) int, W_new (p, k)) for the positive half, then
        for the negative]: the same in both halves when ``side_weight`` is 0)."""
    crossing, t = topology.crossing, topology.t
    coefficients = np.stack([1.0 - t, t], axis=1)
    J_bary, W_bary = blend_weights(J, W, crossing, coefficients)
    # cut in the bind pose: the new vertices are the intersection points (of the predicates chosen)
    rest = topology.points
    if joint_matrices is not None:
        rest = rest_positions(J_bary, W_bary, topology.points, joint_matrices)
    weights = []
    for sign in (1, -1):
        J_new, W_new = J_bary, W_bary
        if side_weight > 0:
            # the endpoint on this half's side of each crossing edge
            own = np.where(sign * topology.distances[crossing[:, 0]] > 0, crossing[:, 0], crossing[:, 1])
            J_new, W_new = blend_weights(
                np.concatenate([J, J_bary]),
                np.concatenate([W, W_bary]),
                np.stack([len(V) + np.arange(len(t)), own], axis=1),
                np.broadcast_to([1.0 - side_weight, side_weight], (len(t), 2)),
            )
        weights.append((J_new, W_new))
    return rest, weights


def split_mesh(mesh: SkinnedMesh, V, J, W, topology: CutTopology, rest, weights) -> list[SkinnedMesh]:
    """Sub-routine 4, meshes: the positive and the negative half as SkinnedMeshes.

    Args:
        mesh: the input SkinnedMesh (its joints, inverse binds and dtypes).
        V: (n, 3) its rest positions; J: (n, k) int its joints; W: (n, k) its weights.
        topology: the cut's ``CutTopology``.
        rest: ``new_vertex_data``'s results.
        weights: see ``rest``.
    Returns:
        [positive, negative] SkinnedMeshes."""
    halves = []
    for keep, faces, (J_new, W_new) in zip(
        (topology.positive, topology.negative), (topology.positive_faces, topology.negative_faces), weights
    ):
        ext_V = np.concatenate([V, rest])
        ext_J = np.concatenate([J, J_new])
        ext_W = np.concatenate([W, W_new])
        V_half, J_half, W_half = (np.take(x, keep, axis=0) for x in (ext_V, ext_J, ext_W))
        halves.append(skinned_mesh_like(mesh, V_half, faces, J_half, W_half))
    return halves
