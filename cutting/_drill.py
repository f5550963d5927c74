"""Drilling a (skinned) triangle mesh with a cylindrical drill: Algorithm 3 of the cut/tear/drill
paper (sec. 4.2.3), with the weights of new vertices of sec. 4.3.

The drill (``Drill(tip, base, radius)``) is given by its tip A, its base B and its radius r; Pi is the
plane through B perpendicular to the axis, P the projection onto it, h(x) = (x - B) . (A - B) / |A - B|
a point's height along the axis. The drilled volume is the finite cylinder |P(x) - B| < r, 0 <= h(x) <=
|A - B|.

1. a vertex is inside the drill when |P(v) - B| < r (on it within ``tolerance``);
2. the seeds are the faces that meet the drilled volume: an edge that comes inside it (a corner inside
   it included), or a face that the axis segment B -> A pierces (a drill inside one large face). Every
   sheet in the drill's way gets its own hole: inner meshes, clothing layers, both sides of a limb,
   separate parts, open surfaces. The affected faces are the faces with a vertex inside the (unbounded)
   cylinder, or an edge that passes through it, connected to a seed (the paper's breadth-first search,
   here connected components of that face graph): a drill held along a surface cuts a groove as long as
   the surface stays inside the cylinder. A connected drilled region is a hole; one that lies wholly
   inside the cylinder (a small part, no rim) is removed whole;
3. every edge (v_i, v_j) of an affected face meets the cylinder where alpha is a root in [0, 1] of
   K alpha^2 + L alpha + N = 0 (eq. 18-20, mu = P(v_i), nu = P(v_j)); the point alpha v_i + (1 - alpha)
   v_j lies exactly on the cylinder (the projection is affine). An edge with both ends outside can
   cross it twice;
4. weights of the new points from their edges (sec. 4.3);
5. each affected face is replaced by the convex pieces of it that lie outside the drill (the runs of
   its boundary outside the cylinder, each closed by a straight chord: the rim), vertices inside are
   removed; a new point that would leave a sliver piece (``_geometry.sliver_mask``) is dropped, the
   hole's boundary then passes through its neighbour on the face's boundary, and step 5 repeats.

The paper's "split and drill again": the faces of a hole with fewer than ``min_points`` boundary points
(a drill thin against the faces), and the faces whose rim chord or rim vertex lies farther than
``rim_tolerance`` from the cylinder (a chord of the circle seen under the angle phi from the axis
strays r (1 - cos(phi / 2)) inside it; a dropped point's neighbour lies off it), are split (their edges
at the midpoints, or a little aside where a midpoint would lie next to the cylinder and snap the rim to
it; neighbours get conforming 2- or 3-way splits) and the mesh is drilled again. Each split halves the
edges the rim crosses, so the rim converges onto the cylinder at any mesh resolution, down to the scale
of the sliver rule: no split makes a face that the rule would call too small, so on a mesh whose smallest
face is large against the drill (an octahedron) the rim comes within about sqrt(1e-3 x that face's
doubled area) of the cylinder (``DrillTopology.rim_distance``).

The drill works on the faces that may meet its cylinder and the faces that share an edge with them (the
only ones a split reaches): its cost is that of the hole, not of the mesh, beyond a few passes over the
vertices.

For a fixed topology (``DrillTopology``) the new points are a JAX function of the vertices and the
``Drill`` (``drill_positions``), so they can be differentiated with respect to the tool.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, overload

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int
from scipy.sparse.csgraph import connected_components

from _jaxcga_shared.checks import check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from cutting._geometry import (
    PIECE_AREA,
    MeshEdges,
    SmallestFace,
    cross_rows,
    fan_triangles,
    mesh_edges,
    posed_vertices,
    rest_positions,
    skinned_mesh_like,
    sliver_mask,
)
from cutting._tools import Drill, check_drill
from cutting._weights import blend_weights
from deform._model import SkinnedMesh


class DrillTopology(NamedTuple):
    """The topology of a drilled hole (``drill_topology``), in an extended vertex numbering: the vertices
    of the mesh as drilled (the input's, then the split points of refinement), then the new points.

    Attributes:
        parents: (r, 2) int refinement: vertex n + k splits the edge ``parents[k]`` = (i, j) at
            ``split[k] V_i + (1 - split[k]) V_j``.
        split: (r,) where: 1/2 (the midpoint), or 3/8 or 5/8 where the midpoint would lie next to the
            cylinder.
        refinements: how many times the affected faces were split.
        vertices: (n + r, 3) the vertex positions that were drilled (the input's, then split points).
        crossing: (p, 2) int the edge (i, j) of each new point.
        alpha: (p,) its root of eq. (18-20): the point is ``alpha V_i + (1 - alpha) V_j``.
        root: (p,) +1 or -1: the sign of the square root that gives alpha.
        points: (p, 3) the new points, on the cylinder.
        faces: (f, 3) the drilled mesh's faces in the extended numbering.
        kept: (k,) the extended indices of the drilled mesh's vertices, in its vertex order
            (vertices inside the hole are gone).
        holes: number of holes (connected drilled regions with a rim; a limb drilled through has two
            in its skin, and one more in every layer or part inside it that the drill crosses).
        removed: number of connected regions removed whole (they lay inside the drill: a small part).
        rim_distance: the largest distance from the cylinder of a rim vertex or of the midpoint of a rim
            edge. Within ``rim_tolerance`` x the diagonal unless the sliver rule stopped the splits (a
            mesh whose smallest face is large against the drill, such as an octahedron: the rim then
            passes through vertices within about sqrt(1e-3 x the smallest face's doubled area) of it).
    """

    parents: Int[np.ndarray, "r 2"]
    split: Float[np.ndarray, " r"]
    refinements: int
    vertices: Float[np.ndarray, "nr 3"]
    crossing: Int[np.ndarray, "p 2"]
    alpha: Float[np.ndarray, " p"]
    root: Float[np.ndarray, " p"]
    points: Float[np.ndarray, "p 3"]
    faces: Int[np.ndarray, "f 3"]
    kept: Int[np.ndarray, " k"]
    holes: int
    removed: int
    rim_distance: float


def _refine_tables():
    """Triangles of a face whose local edges with bit k set are split at their midpoints (slot 3 + k);
    slots 0-2 are the corners. -1 pads."""
    table = -np.ones((8, 4, 3), np.int64)
    for code in range(8):
        split = [k for k in range(3) if code >> k & 1]
        if len(split) == 0:
            tris = [(0, 1, 2)]
        elif len(split) == 1:
            k = split[0]
            tris = [(k, 3 + k, (k + 2) % 3), (3 + k, (k + 1) % 3, (k + 2) % 3)]
        elif len(split) == 2:
            k = next(k for k in range(3) if k in split and (k + 1) % 3 in split)
            k1 = (k + 1) % 3
            tris = [(3 + k, k1, 3 + k1), (k, 3 + k, 3 + k1), (k, 3 + k1, (k + 2) % 3)]
        else:
            tris = [(0, 3, 5), (3, 1, 4), (5, 4, 2), (3, 4, 5)]
        table[code, : len(tris)] = tris
    return table


_REFINE = _refine_tables()


def _refine(V, F, edges: MeshEdges, face_mask, at=None):
    """Split every edge of the masked faces; every face on a split edge is re-triangulated conformingly.
    ``at``: a function of the split edges (s, 2) giving the parameter t of each split point
    ``t V_i + (1 - t) V_j`` (None: midpoints). Returns (V, F, parents, t)."""
    split = np.zeros(len(edges.edges), bool)
    split[edges.face_edges[face_mask].ravel()] = True
    parents = edges.edges[split]
    midpoint = np.full(len(edges.edges), -1, np.int64)
    midpoint[split] = len(V) + np.arange(len(parents))
    code = split[edges.face_edges] @ np.array([1, 2, 4])
    slots = np.concatenate([F, midpoint[edges.face_edges]], axis=1)
    templates = _REFINE[code]
    valid = templates[:, :, 0] >= 0
    faces = np.take_along_axis(slots[:, None, :], np.where(templates < 0, 0, templates), axis=2)[valid]
    t = np.full(len(parents), 0.5) if at is None else at(parents)
    points = t[:, None] * V[parents[:, 0]] + (1.0 - t[:, None]) * V[parents[:, 1]]
    return np.concatenate([V, points]), faces, parents, t


def refine(
    mesh: SkinnedMesh,
    faces: Int[ArrayLike, " f"] | None = None,
    *,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = None,
) -> SkinnedMesh:
    """The paper's "split" of sec. 4.2.3 on a skinned mesh: every edge of the given faces is split at
    its midpoint, faces on split edges are re-triangulated conformingly (4, 3 or 2 triangles); a
    midpoint gets its edge's blended weights (sec. 4.3).

    Args:
        mesh: the SkinnedMesh (``deform``).
        faces: (f,) int the faces to split (all faces when None).
        joint_matrices: (j, 4, 4) joint matrices of a pose: split in that pose (midpoints of the posed
            edges, rest positions by inverse LBS).
    Returns:
        The refined SkinnedMesh (the input's vertices first, in order, then the midpoints).

    Examples:
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> finer = cutting.refine(mesh, [0, 1])  # split two faces (and the neighbours that keep it conforming)
        >>> finer.F.shape[0] > mesh.F.shape[0]
        True
    """
    F = np.asarray(mesh.F)
    mask = np.ones(len(F), bool)
    if faces is not None:
        mask = np.zeros(len(F), bool)
        mask[np.asarray(faces)] = True
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    refined, F_new, parents, _ = _refine(space, F, mesh_edges(F), mask)
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    J_mid, W_mid = blend_weights(J, W, parents, np.full(parents.shape, 0.5))
    rest = rest_positions(J_mid, W_mid, refined[len(space) :], joint_matrices)
    return skinned_mesh_like(
        mesh,
        np.concatenate([np.asarray(mesh.V, np.float64), rest]),
        F_new,
        np.concatenate([J, J_mid]),
        np.concatenate([W, W_mid]),
    )


def _cylinder_roots(mu, nu, radius, lengths, margin):
    """Roots alpha of eq. (18-20) for edges with mu = P(v_i) - B, nu = P(v_j) - B (p, 2) in the plane
    Pi, kept strictly inside the edge (farther than ``margin`` from both ends).
    Returns (edge index, alpha, root sign) of every crossing."""
    diff = mu - nu
    K = np.einsum("ij,ij->i", diff, diff)  # eq. (18)
    L = 2.0 * np.einsum("ij,ij->i", diff, nu)  # eq. (19)
    N = np.einsum("ij,ij->i", nu, nu) - radius**2  # eq. (20)
    disc = L * L - 4.0 * K * N
    ok = (K > 0) & (disc > 0)
    root = np.sqrt(np.where(ok, disc, 0.0))
    safe_K = np.where(ok, K, 1.0)
    found = []
    for sign in (1.0, -1.0):
        alpha = (-L + sign * root) / (2.0 * safe_K)
        inner = ok & (alpha * lengths > margin) & ((1.0 - alpha) * lengths > margin)
        index = np.flatnonzero(inner)
        found.append((index, alpha[index], np.full(len(index), sign)))
    return tuple(np.concatenate(parts) for parts in zip(*found))


class _Frame(NamedTuple):
    """The drill in its own frame: the base B, the rows (u, w, d) of a rotation (d along the axis from B to
    the tip A), the drilled length |A - B| and the radius. A point's coordinates (u, w, h) in it are its
    radial vector P(x) - B in Pi (u, w) and its height h along the axis (0 at B, ``length`` at A)."""

    base: np.ndarray
    basis: np.ndarray
    length: float
    radius: float

    def coordinates(self, X):
        return (X - self.base) @ self.basis.T


def _frame(tip, base, radius) -> _Frame:
    d = tip - base
    length = float(np.linalg.norm(d))
    d = d / length
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    return _Frame(base, np.stack([u, np.cross(d, u), d]), length, radius)


def _side_codes(C, reach):
    """One byte per point (coordinates C (n, 3) in the drill's frame): the half-spaces u > reach,
    u < -reach, w > reach, w < -reach that it lies in (bits 0-3). A face whose corners share a bit lies
    outside the cylinder of radius ``reach``."""
    u, w = C[:, 0], C[:, 1]
    return ((u > reach) | (u < -reach) << 1 | (w > reach) << 2 | (w < -reach) << 3).astype(np.uint8)


def _edges_meeting(C, pairs, radius, length, margin):
    """Which edges ``pairs`` (e, 2) come strictly inside the drilled part of the cylinder: the smallest
    distance to the axis over the part of the edge with 0 <= h <= length is below radius - margin."""
    a, b = C[pairs[:, 0]], C[pairs[:, 1]]
    step = b - a
    # the parameters t in [0, 1] of the edge's points between the two ends of the drill
    rise = step[:, 2]
    flat = rise == 0
    safe = np.where(flat, 1.0, rise)
    t0, t1 = -a[:, 2] / safe, (length - a[:, 2]) / safe
    low = np.where(flat, np.where((a[:, 2] >= 0) & (a[:, 2] <= length), 0.0, 1.0), np.minimum(t0, t1))
    high = np.where(flat, np.where((a[:, 2] >= 0) & (a[:, 2] <= length), 1.0, 0.0), np.maximum(t0, t1))
    low, high = np.maximum(low, 0.0), np.minimum(high, 1.0)
    # the squared distance to the axis is a convex quadratic in t: its minimum over [low, high]
    span = step[:, 0] ** 2 + step[:, 1] ** 2
    t = -(a[:, 0] * step[:, 0] + a[:, 1] * step[:, 1]) / np.where(span > 0, span, 1.0)
    t = np.clip(t, low, high)
    u, w = a[:, 0] + t * step[:, 0], a[:, 1] + t * step[:, 1]
    return (low <= high) & (u * u + w * w < (radius - margin) ** 2)


def _pierced(C, F, length):
    """Which faces F the axis segment from the base (h = 0) to the tip (h = length) crosses: the axis, the origin
    of the drill frame's (u, w) plane, lies in the face projected onto it (barycentric coordinates, boundary
    included), at a height between 0 and length."""
    a, b, c = (C[F[:, k]] for k in range(3))
    ab, ac = b - a, c - a
    det = ab[:, 0] * ac[:, 1] - ab[:, 1] * ac[:, 0]
    ok = det != 0
    safe = np.where(ok, det, 1.0)
    beta = (-a[:, 0] * ac[:, 1] + a[:, 1] * ac[:, 0]) / safe
    gamma = (-ab[:, 0] * a[:, 1] + ab[:, 1] * a[:, 0]) / safe
    alpha = 1.0 - beta - gamma
    height = alpha * a[:, 2] + beta * b[:, 2] + gamma * c[:, 2]
    return ok & (alpha >= 0) & (beta >= 0) & (gamma >= 0) & (height >= 0) & (height <= length)


class _Pass(NamedTuple):
    """One drilling pass over the faces near the drill: their adjacency, the affected faces (bool), the
    hole (connected drilled region) of each affected face (0 elsewhere), the crossings on the affected
    faces' edges (local edge ids, alpha, root sign), and per hole: whether a corner lies outside the drill,
    whether it is removed whole (no corner outside, no crossing, no corner on the cylinder) and its number
    of boundary points (crossings and corners on the cylinder)."""

    edges: MeshEdges
    affected: np.ndarray
    hole: np.ndarray
    index: np.ndarray
    alpha: np.ndarray
    sign: np.ndarray
    outside: np.ndarray
    whole: np.ndarray
    count: np.ndarray


def _drill_once(V, C, F, frame: _Frame, margin) -> _Pass:
    """One drilling pass (Algorithm 3, steps 1-3) over the faces F near the drill (global vertex ids into V
    and their drill-frame coordinates C): the seeds (faces that meet the drilled part of the cylinder), the
    search over the faces that meet the cylinder around them, and the crossings on the affected edges."""
    radius, length = frame.radius, frame.length
    edges = mesh_edges(F)
    pairs = edges.edges
    rho2 = C[:, 0] ** 2 + C[:, 1] ** 2
    inside = rho2 < (radius - margin) ** 2
    spans = V[pairs[:, 1]] - V[pairs[:, 0]]
    crossing_edge, alpha, sign = _cylinder_roots(
        C[pairs[:, 0], :2], C[pairs[:, 1], :2], radius, np.sqrt(np.einsum("ij,ij->i", spans, spans)), margin
    )
    crossed = np.zeros(len(pairs), bool)
    crossed[crossing_edge] = True
    # a face meets the cylinder when a corner lies inside it or an edge passes through it
    hit = inside[F].any(axis=1) | crossed[edges.face_edges].any(axis=1)
    # seeds: faces that meet the cylinder between base and tip (an edge inside it there, which includes a
    # corner inside it), or that its axis pierces (the drill inside a face larger than it)
    seed = _edges_meeting(C, pairs, radius, length, margin)[edges.face_edges].any(axis=1)
    seed |= _pierced(C, F, length)
    if not seed.any():
        raise ValueError("drill: misses the mesh (no face meets the cylinder between its base and tip)")
    # the affected faces: connected components of the faces that meet the cylinder (or are seeds) that
    # hold a seed (the paper's breadth-first search from the seeds)
    region = hit | seed
    members = np.flatnonzero(region)
    number = np.full(len(F), -1, np.int64)
    number[members] = np.arange(len(members))
    a, b = edges.edge_faces[:, 0], edges.edge_faces[:, 1]
    link = (b >= 0) & region[a] & region[np.maximum(b, 0)]
    a, b = number[a[link]], number[b[link]]
    graph = sp.coo_matrix((np.ones(len(a)), (a, b)), shape=(len(members), len(members)))
    _, components = connected_components(graph, directed=False)
    labels = np.full(len(F), -1, np.int64)
    labels[members] = components
    holes_of = np.unique(labels[seed])
    affected = region & np.isin(labels, holes_of)
    on_affected = np.unique(edges.face_edges[affected])
    if len(on_affected) and edges.edge_counts[on_affected].max() > 2:
        bad = pairs[on_affected[np.argmax(edges.edge_counts[on_affected])]]
        raise ValueError(
            f"mesh: the drill meets a non-manifold edge {bad.tolist()} (more than two faces on it); "
            "the hole around it is not defined"
        )
    hole = np.where(affected, np.searchsorted(holes_of, labels), 0)
    keep = np.isin(crossing_edge, on_affected)
    index, alpha, sign = crossing_edge[keep], alpha[keep], sign[keep]
    # per hole: its boundary points (crossings, corners on the cylinder) and whether a corner lies outside
    count = len(holes_of)
    first = edges.edge_faces[index, 0]
    owner = np.where(affected[first], first, edges.edge_faces[index, 1])
    points = np.bincount(hole[owner], minlength=count)
    corners, corner_hole = F[affected].ravel(), np.repeat(hole[affected], 3)
    on = np.abs(np.sqrt(rho2[corners]) - radius) <= margin
    unique_on = np.unique(np.stack([corner_hole[on], corners[on]]), axis=1)
    points += np.bincount(unique_on[0], minlength=count)
    outside = np.bincount(corner_hole, weights=rho2[corners] > (radius + margin) ** 2, minlength=count) > 0
    return _Pass(edges, affected, hole, index, alpha, sign, outside, ~outside & (points == 0), points)


def drill_topology(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    drill: Drill,
    *,
    min_points: int = 6,
    max_refinements: int | None = None,
    rim_tolerance: float = 5e-4,
    tolerance: float = 1e-6,
    edges: MeshEdges | None = None,
) -> DrillTopology:
    """The topology of drilling the triangle mesh (V, F) (Algorithm 3).

    Args:
        V: (n, 3) vertex positions (rest pose or posed).
        F: (m, 3) int faces.
        drill: the ``Drill``: tip A and base B (3,) and radius r > 0; it drills every sheet of the
            surface that meets the cylinder between B and A.
        min_points: fewest boundary points per hole before its faces are split and drilled again (the
            paper suggests 6).
        max_refinements: how many times at most (None: as many as the largest face the drill meets
            needs to come down to the scale of the drill and of ``rim_tolerance``, plus 3).
        rim_tolerance: the largest distance of the hole's rim (its vertices and the midpoints of its
            edges) from the cylinder, times the bounding-box diagonal; faces whose rim is farther are
            split and drilled again (``inf``: no limit), as far as the sliver rule lets them (see
            ``DrillTopology.rim_distance``, the distance reached).
        tolerance: vertices within ``tolerance`` times the bounding-box diagonal of the cylinder count
            as on it (no sliver triangles).
        edges: ``mesh_edges(F)``: accepted for the signature that cut, tear and drill share and checked
            against F; the drill builds the adjacency of the few faces near it itself.
    Returns:
        The ``DrillTopology`` (its attributes say what it holds), which ``drill`` applies to a ``SkinnedMesh`` and
        ``drill_positions`` to the vertices.
    Raises:
        ValueError: bad input, a drill that misses the mesh, a drill wider than the part of the mesh it
            meets, a hole that stays below three boundary points, or a rim that stays farther than
            ``rim_tolerance`` from the cylinder, after ``max_refinements`` splits.

    Examples:
        >>> import numpy as np
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> drill = cutting.Drill([0.2, 0.0, -0.2], [0.2, 0.0, 0.2], 0.01)  # through the upper arm, front to back
        >>> cutting.drill_topology(np.asarray(mesh.V), np.asarray(mesh.F), drill).holes
        2
    """
    V, F = check_triangle_mesh(V, F, min_faces=0)
    tip, base, radius = check_drill(drill)
    if min_points < 3 or (max_refinements is not None and max_refinements < 0):
        raise ValueError(f"min_points, max_refinements: expected >= 3 and >= 0, got {min_points}, {max_refinements}")
    if not tolerance >= 0:
        raise ValueError(f"tolerance: expected a non-negative number, got {tolerance}")
    if not rim_tolerance > 0:
        raise ValueError(f"rim_tolerance: expected a positive number (inf for no limit), got {rim_tolerance}")
    if edges is not None and edges.face_edges.shape != F.shape:
        raise ValueError(f"edges: computed for another mesh (face_edges {edges.face_edges.shape}, F {F.shape})")
    frame = _frame(tip, base, radius)
    C = frame.coordinates(V)
    reach = float(np.sqrt((C[:, 0] ** 2 + C[:, 1] ** 2).max(initial=0.0)))
    if reach <= radius:
        raise ValueError(
            f"drill.radius: {radius:.4g} exceeds the model's size: every vertex lies within "
            f"{reach:.4g} of the drill's axis; give a smaller radius"
        )
    diagonal = bounding_diagonal(V)
    margin, rim_limit = tolerance * diagonal, rim_tolerance * diagonal
    # The drill only changes faces that may meet its (unbounded) cylinder, and splits only their edges: it
    # works on them and the faces that share an edge with them (two corners among theirs).
    code = _side_codes(C, radius + margin)
    near = (code[F[:, 0]] & code[F[:, 1]] & code[F[:, 2]]) == 0
    touched = np.zeros(len(V), bool)
    touched[F[near]] = True
    corner = touched[F]
    near_local = (corner[:, 0] & (corner[:, 1] | corner[:, 2])) | (corner[:, 1] & corner[:, 2])
    local = np.flatnonzero(near_local)
    F_local = F[local]
    smallest = SmallestFace(V, F)  # the input's: refinement only adds smaller faces
    all_parents, all_split, refinements, budget = [], [], 0, max_refinements
    while True:
        state = _drill_once(V, C, F_local, frame, margin)
        if not refinements:  # faces of the input near the drill
            smallest.near(np.take(V, F_local[state.affected], axis=0))
        if budget is None:
            budget = _budget(V, F_local[state.affected], radius, rim_limit)
        pairs = state.edges.edges[state.index]
        alpha = state.alpha[:, None]
        points = alpha * V[pairs[:, 0]] + (1.0 - alpha) * V[pairs[:, 1]]
        point_C = alpha * C[pairs[:, 0]] + (1.0 - alpha) * C[pairs[:, 1]]
        # faces with every corner inside the drill are removed whole (the drill is convex); the others
        # are cut along the rim
        interior = (C[F_local, 0] ** 2 + C[F_local, 1] ** 2 < (radius - margin) ** 2).all(axis=1)
        rim_faces = np.flatnonzero(state.affected & ~interior)
        alive = np.ones(len(pairs), bool)
        pieces, todo = {}, rim_faces
        # Each pass drops at least one new point (it snaps to the vertex or point next to it), so this ends;
        # a pass redoes the faces on the edges of the points dropped.
        while True:
            done, drop = _retriangulate(
                V,
                C,
                F_local,
                state.edges,
                state.index,
                state.alpha,
                alive,
                points,
                point_C,
                todo,
                radius,
                margin,
                smallest,
            )
            pieces.update(done)
            if not len(drop):
                break
            alive[drop] = False
            todo = np.intersect1d(state.edges.edge_faces[state.index[drop]].ravel(), rim_faces)
        # the new points left, numbered n, n + 1, ... in the order of the crossings
        renumber = np.concatenate([np.arange(len(V)), len(V) + np.cumsum(alive) - 1])
        triangles = [t for f in rim_faces.tolist() for t in pieces[f][0]]
        chords = [(a, b, f) for f in rim_faces.tolist() for a, b in pieces[f][1]]
        faces = np.concatenate(
            [np.compress(~state.affected, F_local, axis=0), renumber[np.asarray(triangles, np.int64).reshape(-1, 3)]]
        )
        chords = np.asarray(chords, np.int64).reshape(-1, 3)
        chords[:, :2] = renumber[chords[:, :2]]
        alpha, sign = state.alpha[alive], state.sign[alive]
        pairs, points, point_C = pairs[alive], points[alive], point_C[alive]
        # faces to split: those of a hole with too few points, those whose rim strays from the cylinder
        few = state.outside & (state.count < min_points)
        split = state.affected & few[state.hole]
        off = _rim_distance(np.concatenate([C, point_C]), chords, radius)
        split[chords[off > rim_limit, 2]] = True
        split &= _splittable(V, F_local, state.edges, smallest)
        if not split.any() or refinements == budget:
            break
        away = 2.0 * math.sqrt(PIECE_AREA * smallest.bound)
        V, F_local, parents, t = _refine(
            V, F_local, state.edges, split, lambda pairs: _split_parameters(C, pairs, radius, away)
        )
        C = np.concatenate([C, t[:, None] * C[parents[:, 0]] + (1.0 - t[:, None]) * C[parents[:, 1]]])
        all_parents.append(parents)
        all_split.append(t)
        refinements += 1
    if state.whole.all():
        # every face the drill meets lies inside it: no rim anywhere
        raise ValueError(
            f"drill.radius: {radius:.4g} is wider than the part of the model the drill meets (its faces "
            "all lie inside the drill); give a smaller radius"
        )
    fewest = int(state.count[state.outside].min(initial=min_points))
    if fewest < 3:
        raise ValueError(
            f"drill.radius: a hole has {fewest} boundary points after {refinements} refinements "
            "(the drill is too thin for the faces it meets; raise max_refinements or the radius)"
        )
    if split.any() and off.max(initial=0.0) > rim_limit:
        raise ValueError(
            f"drill: the hole's rim lies {off.max() / diagonal:.3g} x the bounding-box diagonal off the "
            f"cylinder after {refinements} refinements (rim_tolerance {rim_tolerance:.3g}); raise "
            "max_refinements or rim_tolerance"
        )
    faces = np.concatenate([np.compress(~near_local, F, axis=0), faces])
    used = np.zeros(len(V) + len(points), bool)
    used[faces] = True
    kept = np.flatnonzero(used)
    renumber = np.cumsum(used) - 1
    parents = np.concatenate(all_parents) if all_parents else np.zeros((0, 2), np.int64)
    return DrillTopology(
        parents,
        np.concatenate(all_split) if all_split else np.zeros(0),
        refinements,
        V,
        pairs,
        alpha,
        sign,
        points,
        renumber[faces],
        kept,
        int((~state.whole).sum()),
        int(state.whole.sum()),
        float(off.max(initial=0.0)),
    )


def _budget(V, corners, radius, rim_limit) -> int:
    """Refinements that bring the longest edge among the faces ``corners`` (f, 3) down to the length at
    which a hole has its points and its rim's chords keep within ``rim_limit`` of the cylinder, plus 3.
    A chord of the circle r seen under angle phi strays r (1 - cos(phi / 2)) from it; edges of at most
    2 sqrt(2 r rim_limit) keep it within rim_limit, edges of r give a hole about 6 points."""
    if not len(corners):
        return 3
    X = V[corners]
    longest = float(
        np.sqrt(
            max(np.einsum("ij,ij->i", d, d).max() for d in (X[:, 1] - X[:, 0], X[:, 2] - X[:, 1], X[:, 0] - X[:, 2]))
        )
    )
    target = min(radius, 2.0 * math.sqrt(2.0 * radius * rim_limit)) if math.isfinite(rim_limit) else radius
    return max(0, math.ceil(math.log2(max(longest / target, 1.0)))) + 3


def _split_parameters(C, pairs, radius, away):
    """Where to split the edges ``pairs`` (s, 2): at the midpoint, unless it lies within ``away`` of the
    cylinder (a vertex there would become a sliver's corner, and the rim would snap to it), then at 3/8
    or 5/8 of the edge, the first as far, or the farthest."""
    candidates = np.array([0.5, 0.375, 0.625])
    a, b = C[pairs[:, 0], None, :2], C[pairs[:, 1], None, :2]
    X = candidates[None, :, None] * a + (1.0 - candidates[None, :, None]) * b
    gap = np.abs(np.sqrt(np.einsum("sck,sck->sc", X, X)) - radius)
    far = gap >= away
    choice = np.where(far.any(axis=1), np.argmax(far, axis=1), np.argmax(gap, axis=1))
    return candidates[choice]


def _splittable(V, F, edges: MeshEdges, smallest: SmallestFace):
    """Which faces may be split: neither they nor a face sharing an edge with them (split to conform) would
    leave an eighth of their area under the sliver rule's smallest piece (``sliver_mask``): with split
    points at 3/8 to 5/8 of the edges, no child keeps less than (3/8)^2 of its face."""
    X = V[F]
    normal = cross_rows(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0])
    doubled = np.sqrt(np.einsum("ij,ij->i", normal, normal))
    small = doubled < 8.0 * PIECE_AREA * smallest.bound
    if small.any():
        small = doubled < 8.0 * PIECE_AREA * smallest.value()
    near_small = np.zeros(len(edges.edges), bool)
    near_small[edges.face_edges[small].ravel()] = True
    return ~small & ~near_small[edges.face_edges].any(axis=1)


def _rim_distance(C, chords, radius):
    """Distance from the cylinder of each rim chord (c, 3: its two ends, ids into the drill-frame
    coordinates C, and its face): the largest of its ends' and its midpoint's (a chord of the circle
    strays farthest from it there)."""
    if not len(chords):
        return np.zeros(0)
    a, b = C[chords[:, 0], :2], C[chords[:, 1], :2]
    m = 0.5 * (a + b)
    return np.max([np.abs(np.sqrt(np.einsum("ij,ij->i", x, x)) - radius) for x in (a, b, m)], axis=0)


def _retriangulate(V, C, F, edges: MeshEdges, index, alpha, alive, points, point_C, faces, radius, margin, smallest):
    """Step 5 of Algorithm 3 on the local faces ``faces`` along the rim: for each, its pieces outside the
    drill and its rim chords, in the extended numbering (the new points of the crossings ``index``, alpha,
    where ``alive``, are vertices n + p). Returns ({face: (triangles, chords)}, the crossings to drop). A
    new point is dropped in each face whose pieces are slivers (``sliver_mask``): the one (or the two on
    one edge) closest to its neighbour on the face's boundary, relative to that edge's length; without it
    the hole's boundary passes through the neighbour. Per face in plain Python: the faces along a rim are
    few, and small arrays cost more than they save."""
    n = len(V)
    results, faces = _simple_pieces(V, C, F, edges, index, alive, points, faces, radius, margin, smallest)
    corners = F[faces]
    flat = corners.ravel()
    live = np.flatnonzero(alive)
    # radial vectors P(x) - B of the corners and the new points (the projection is affine)
    radial = dict(zip(flat.tolist(), C[flat, :2].tolist()))
    radial.update(zip((n + live).tolist(), point_C[live, :2].tolist()))
    position = dict(zip(flat.tolist(), V[flat].tolist()))
    position.update(zip((n + live).tolist(), points[live].tolist()))
    # the new points of each edge, ordered from its first vertex (edges.edges[e, 0]) to its second
    on_edge: dict[int, list[tuple[float, int]]] = {}
    for p, e, a in zip(live.tolist(), index[live].tolist(), alpha[live].tolist()):
        on_edge.setdefault(e, []).append((1.0 - a, n + p))
    for entries in on_edge.values():
        entries.sort()
    limit = radius * radius
    # corners strictly inside the drill: a boundary step from one is never outside, and the hole's
    # boundary never passes through one (no vertex stays inside the drill)
    squared = C[flat, 0] ** 2 + C[flat, 1] ** 2
    inside = set(flat[squared < (radius - margin) ** 2].tolist())
    triangles, parents, cycles = [], [], []
    for f, face, local_edges in zip(faces.tolist(), corners.tolist(), edges.face_edges[faces].tolist()):
        cycle, counts = [], []  # the boundary, and how many steps of it lie on each of the face's edges
        for k in range(3):
            a, b = face[k], face[(k + 1) % 3]
            cycle.append(a)
            ordered = [vid for _, vid in on_edge.get(local_edges[k], ())]
            cycle += ordered if a < b else ordered[::-1]
            counts.append(len(ordered) + 1)
        cycles.append((face, cycle, counts))
        m = len(cycle)
        pieces, chords = [], []
        # a boundary piece is outside the drill when its midpoint is (the drill is convex)
        outside = []
        for i in range(m):
            a, b = cycle[i], cycle[(i + 1) % m]
            x, y = radial[a], radial[b]
            mx, my = x[0] + y[0], x[1] + y[1]
            outside.append(0.25 * (mx * mx + my * my) > limit and a not in inside and b not in inside)
        if all(outside):
            pieces.append(tuple(face))
        elif any(outside):
            # each run of the boundary outside the drill, closed by a chord (the rim), is a convex piece
            start = next(i for i in range(m) if outside[i] and not outside[i - 1])
            run = [cycle[start]]
            for step in range(m):
                i = (start + step) % m
                if outside[i]:
                    run.append(cycle[(i + 1) % m])
                    continue
                if len(run) >= 3:
                    pieces += fan_triangles(run, [position[v] for v in run])
                if len(run) >= 2:  # a run of one step leaves no piece, but the step joins the rim
                    chords.append((run[-1], run[0]))
                run = [cycle[(i + 1) % m]]
        results[f] = (pieces, chords)
        triangles += pieces
        parents += [len(cycles) - 1] * len(pieces)
    if not triangles:
        return results, np.zeros(0, np.int64)
    piece_corners = np.asarray([[position[v] for v in t] for t in triangles])
    parents = np.asarray(parents, np.int64)
    poor = sliver_mask(piece_corners, np.take(V, corners[parents], axis=0), smallest)
    drop = []
    for f in np.unique(parents[poor]).tolist():
        face, cycle, counts = cycles[f]
        spans = []  # the length of the face's edge under each step of the boundary
        for k in range(3):
            pa, pb = position[face[k]], position[face[(k + 1) % 3]]
            spans += [((pa[0] - pb[0]) ** 2 + (pa[1] - pb[1]) ** 2 + (pa[2] - pb[2]) ** 2) ** 0.5] * counts[k]
        m = len(cycle)
        steps = [
            (math.dist(position[a], position[b]) / spans[i], i)
            for i, (a, b) in enumerate(zip(cycle, cycle[1:] + cycle[:1]))
            if max(a, b) >= n and a not in inside and b not in inside
        ]
        if steps:
            _, i = min(steps)
            drop += [v - n for v in (cycle[i], cycle[(i + 1) % m]) if v >= n]
    return results, np.unique(np.asarray(drop, np.int64))


def _simple_pieces(V, C, F, edges: MeshEdges, index, alive, points, faces, radius, margin, smallest):
    """Step 5 in arrays for the commonest faces along a rim: one crossing on each of two edges, none on the third
    (dropped ones included), every corner clearly inside or outside the drill, and no sliver among the pieces.
    The lone corner between the crossed edges keeps a triangle (it is outside) or leaves a quadrilateral (it is
    inside), split as ``fan_triangles`` would; the chord joins the two points. The same pieces, chords and ids as
    the per-face loop of ``_retriangulate``. Returns ({face: (triangles, chords)}, the other faces)."""
    n = len(V)
    all_count = np.bincount(index, minlength=len(edges.edges))
    alive_count = np.bincount(index[alive], minlength=len(edges.edges))
    point_of = np.full(len(edges.edges), -1, np.int64)
    point_of[index[alive]] = n + np.flatnonzero(alive)
    local = edges.face_edges[faces]
    counts = alive_count[local]
    corners = F[faces]
    squared = C[corners, 0] ** 2 + C[corners, 1] ** 2
    inside = squared < (radius - margin) ** 2
    clear = inside | (squared > (radius + margin) ** 2)
    simple = (
        (np.sort(counts, axis=1) == [0, 1, 1]).all(axis=1)
        & (all_count[local] == counts).all(axis=1)
        & clear.all(axis=1)
    )
    if not simple.any():
        return {}, faces
    rows = np.flatnonzero(simple)
    # the lone corner l: opposite the uncrossed edge k0 (edges run corner k -> corner k + 1)
    lone = (np.argmin(counts[rows], axis=1) + 2) % 3
    r = np.arange(len(rows))
    face = corners[rows]
    L, A, B = face[r, lone], face[r, (lone + 1) % 3], face[r, (lone + 2) % 3]
    after, before = point_of[local[rows, lone]], point_of[local[rows, (lone + 2) % 3]]
    out = ~inside[rows, lone]
    X = np.concatenate([V, points])
    # quadrilaterals (after, A, B, before): the diagonal whose smaller triangle is larger (fan_triangles' rule)
    quad = np.stack([after, A, B, before], axis=1)[~out]
    P = X[quad]

    def squared_cross(a, b, c):
        normal = cross_rows(P[:, b] - P[:, a], P[:, c] - P[:, a])
        return normal[:, 0] * normal[:, 0] + normal[:, 1] * normal[:, 1] + normal[:, 2] * normal[:, 2]

    even = np.minimum(squared_cross(0, 1, 2), squared_cross(0, 2, 3))
    odd = np.minimum(squared_cross(1, 2, 3), squared_cross(1, 3, 0))
    shift = np.where(odd > even, 1, 0)
    ring = np.take_along_axis(quad, (shift[:, None] + np.arange(4)) % 4, axis=1)
    quads = np.stack([ring[:, [0, 1, 2]], ring[:, [0, 2, 3]]], axis=1)
    pieces = [np.stack([before, L, after], axis=1)[out], quads[:, 0], quads[:, 1]]
    owner = [np.flatnonzero(out), np.flatnonzero(~out), np.flatnonzero(~out)]
    piece_faces = np.concatenate(pieces)
    owner = np.concatenate(owner)
    poor = sliver_mask(np.take(X, piece_faces, axis=0), np.take(V, face[owner], axis=0), smallest)
    keep = np.ones(len(rows), bool)
    keep[owner[poor]] = False
    chords = np.where(out[:, None], np.stack([after, before], axis=1), np.stack([before, after], axis=1))
    results: dict[int, tuple[list, list]] = {}
    face_ids = faces[rows].tolist()
    for f, tri, chord, ok in zip(face_ids, np.stack([before, L, after], axis=1).tolist(), chords.tolist(), keep & out):
        if ok:
            results[f] = ([tuple(tri)], [tuple(chord)])
    for f, (first, second), chord, ok in zip(
        np.asarray(face_ids)[~out].tolist(), quads.tolist(), chords[~out].tolist(), keep[~out]
    ):
        if ok:
            results[f] = ([tuple(first), tuple(second)], [tuple(chord)])
    simple[rows[~keep]] = False
    return results, faces[~simple]


def _split_levels(parents: Int[np.ndarray, "r 2"], n: int) -> list[slice]:
    """The refinement's split points (vertex n + k splits the edge ``parents[k]``) in levels (slices of
    ``parents``) whose parents all precede the level (they may be split points of an earlier one): each
    level is one vectorized step."""
    levels, done = [], 0
    while done < len(parents):
        later = np.flatnonzero(parents[done:].max(axis=1) >= n + done)
        stop = done + (later[0] if len(later) else len(parents) - done)
        levels.append(slice(done, stop))
        done = stop
    return levels


@overload
def drill(
    mesh: SkinnedMesh,
    drill: Drill,
    *,
    min_points: int = ...,
    max_refinements: int | None = ...,
    rim_tolerance: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[False] = ...,
) -> SkinnedMesh: ...


@overload
def drill(
    mesh: SkinnedMesh,
    drill: Drill,
    *,
    min_points: int = ...,
    max_refinements: int | None = ...,
    rim_tolerance: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[True],
) -> tuple[SkinnedMesh, DrillTopology]: ...


def drill(
    mesh: SkinnedMesh,
    drill: Drill,
    *,
    min_points: int = 6,
    max_refinements: int | None = None,
    rim_tolerance: float = 5e-4,
    tolerance: float = 1e-6,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = None,
    edges: MeshEdges | None = None,
    return_topology: bool = False,
) -> SkinnedMesh | tuple[SkinnedMesh, DrillTopology]:
    """Drill a hole into a skinned mesh with a cylinder from the drill's base to its tip (Algorithm 3).

    Args:
        mesh: the SkinnedMesh (``deform``).
        drill: the ``Drill`` (see ``drill_topology``), in the space of the mesh as drilled: the bind
            pose, or the pose of ``joint_matrices``.
        min_points: see ``drill_topology``.
        max_refinements: see ``min_points``.
        rim_tolerance: see ``min_points``.
        tolerance: see ``min_points``.
        joint_matrices: (j, 4, 4) joint matrices of a pose (``deform.joint_matrices``): drill the mesh
            *in that pose*, the drill in world space. New vertices get the rest positions whose LBS
            image in that pose is their drilled position (exact for LBS).
        edges: ``mesh_edges(mesh.F)``, precomputed.
        return_topology: also return the ``DrillTopology`` (for ``drill_positions``).
    Returns:
        The drilled SkinnedMesh (its vertices: the input's outside the hole, in order, then refinement
        split points and new points), and the DrillTopology when ``return_topology``.

    Examples:
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh  # along +x, about 0.09 thick
        >>> drilled = cutting.drill(mesh, cutting.Drill([0.2, 0.0, -0.2], [0.2, 0.0, 0.2], 0.01))  # tip, base, radius
        >>> drilled.V.shape[0] > mesh.V.shape[0]  # the holes' rims
        True
    """
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    topology = drill_topology(
        space,
        mesh.F,
        drill,
        min_points=min_points,
        max_refinements=max_refinements,
        rim_tolerance=rim_tolerance,
        tolerance=tolerance,
        edges=edges,
    )
    rest = np.asarray(mesh.V, np.float64)
    for level in _split_levels(topology.parents, len(rest)):
        pairs, t = topology.parents[level], topology.split[level, None]
        J_mid, W_mid = blend_weights(J, W, pairs, np.concatenate([t, 1.0 - t], axis=1))
        target = t * topology.vertices[pairs[:, 0]] + (1.0 - t) * topology.vertices[pairs[:, 1]]
        rest = np.concatenate([rest, rest_positions(J_mid, W_mid, target, joint_matrices)])
        J, W = np.concatenate([J, J_mid]), np.concatenate([W, W_mid])
    J_new, W_new = blend_weights(J, W, topology.crossing, np.stack([topology.alpha, 1.0 - topology.alpha], axis=1))
    rest = np.concatenate([rest, rest_positions(J_new, W_new, topology.points, joint_matrices)])
    J, W = np.concatenate([J, J_new]), np.concatenate([W, W_new])
    kept = topology.kept
    # np.take selects rows several times faster than an index array
    V_kept, J_kept, W_kept = (np.take(x, kept, axis=0) for x in (rest, J, W))
    drilled = skinned_mesh_like(mesh, V_kept, topology.faces, J_kept, W_kept)
    return (drilled, topology) if return_topology else drilled


def drill_positions(V: Float[ArrayLike, "n 3"], topology: DrillTopology, drill: Drill) -> Float[Array, "p 3"]:
    """Positions of a drill's new points as a JAX function of the vertices and the drill, for a fixed
    topology: differentiable with respect to both (``jax.grad`` over a ``Drill`` gives a ``Drill``). The
    refinement's split points are formed from V (``topology.parents``, ``topology.split``), then eq. (18-20)
    is solved for each point's alpha (the root of ``topology.root``): the point ``alpha V_i + (1 - alpha) V_j``.

    Args:
        V: (n, 3) the input's vertex positions, as drilled (posed, when drilled with ``joint_matrices``).
        topology: the hole's ``DrillTopology``.
        drill: the ``Drill``.
    Returns:
        (p, 3) the new points, in the order of ``topology.crossing``.

    Examples:
        >>> import numpy as np
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> V, F = np.asarray(mesh.V), np.asarray(mesh.F)
        >>> drill = cutting.Drill([0.2, 0.0, -0.2], [0.2, 0.0, 0.2], 0.01)
        >>> topology = cutting.drill_topology(V, F, drill)
        >>> cutting.drill_positions(V, topology, drill).shape == topology.points.shape  # a JAX function of V and drill
        True
    """
    V = jnp.asarray(V)
    n = len(topology.vertices) - len(topology.parents)
    if V.shape != (n, 3):
        raise ValueError(f"V: expected the {n} vertices that were drilled, shape ({n}, 3), got {V.shape}")
    for level in _split_levels(topology.parents, n):
        pairs, t = topology.parents[level], topology.split[level, None]
        V = jnp.concatenate([V, t * V[pairs[:, 0]] + (1.0 - t) * V[pairs[:, 1]]])
    tip, base, radius = jnp.asarray(drill.tip), jnp.asarray(drill.base), jnp.asarray(drill.radius)
    crossing = topology.crossing
    axis = (tip - base) / jnp.linalg.norm(tip - base)
    relative = V - base[None]
    radial = relative - (relative @ axis)[:, None] * axis[None]
    mu, nu = radial[crossing[:, 0]], radial[crossing[:, 1]]
    K = jnp.sum((mu - nu) ** 2, -1)
    L = 2.0 * jnp.sum((mu - nu) * nu, -1)
    N = jnp.sum(nu * nu, -1) - radius**2
    alpha = (-L + jnp.asarray(topology.root) * jnp.sqrt(L * L - 4.0 * K * N)) / (2.0 * K)
    return alpha[:, None] * V[crossing[:, 0]] + (1.0 - alpha[:, None]) * V[crossing[:, 1]]
