"""Drilling a (skinned) triangle mesh with a cylindrical drill: Algorithm 3 of the cut/tear/drill
paper (sec. 4.2.3), with the weights of new vertices of sec. 4.3.

The drill (``Drill(tip, base, radius)``) is given by its tip A, its base B and its radius r; Pi is the
plane through B perpendicular to the axis, P the projection onto it.

1. a vertex is inside the drill when |P(v) - B| < r (on it within ``tolerance``); as in the paper,
   the cylinder is unbounded along its axis (the tip only picks the sheets drilled, step 2), so a
   drill held along the surface cuts a groove as long as the surface stays inside it;
2. the faces pierced by the axis segment B -> A are the seeds; the affected faces are the faces
   with a vertex inside the drill, or an edge that passes through it, connected to a seed (the
   paper's breadth-first search, here connected components of that face graph), so the drill only
   goes through the sheets of the surface that its axis reaches;
3. every edge (v_i, v_j) of an affected face meets the cylinder where alpha is a root in [0, 1] of
   K alpha^2 + L alpha + N = 0 (eq. 18-20, mu = P(v_i), nu = P(v_j)); the point alpha v_i + (1 - alpha)
   v_j lies exactly on the cylinder (the projection is affine). An edge with both ends outside can
   cross it twice;
4. weights of the new points from their edges (sec. 4.3);
5. each affected face is replaced by the convex pieces of it that lie outside the drill (the runs of
   its boundary outside the cylinder, each closed by a straight chord), vertices inside are removed;
   a new point that would leave a sliver piece (``_geometry.sliver_mask``) is dropped, the hole's
   boundary then passes through its neighbour on the face's boundary, and step 5 repeats.

When a hole has fewer than ``min_points`` boundary points (a drill thin against the faces), the
affected faces are split (midpoints of their edges; neighbours get conforming 2- or 3-way splits)
and the mesh is drilled again, at most ``max_refinements`` times (the paper's "split and drill
again").

For a fixed topology (``DrillTopology``) the new points are a JAX function of the vertices and the
``Drill`` (``drill_positions``), so they can be differentiated with respect to the tool.
"""

from __future__ import annotations

import math
from typing import Literal, NamedTuple, overload

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from cutting._geometry import (
    MeshEdges,
    SmallestFace,
    fan_triangles,
    mesh_edges,
    posed_vertices,
    rest_positions,
    segment_hits,
    skinned_mesh_like,
    sliver_mask,
)
from cutting._tools import Drill, check_drill
from cutting._weights import blend_weights
from deform._model import SkinnedMesh


class DrillTopology(NamedTuple):
    """The topology of a drilled hole (``drill_topology``), in an extended vertex numbering: the vertices
    of the mesh as drilled (the input's, then ``parents``' midpoints from refinement), then the new points.

    Attributes:
        parents: (r, 2) int refinement: vertex n + k is the midpoint of vertices ``parents[k]``.
        refinements: how many times the affected faces were split.
        vertices: (n + r, 3) the vertex positions that were drilled (the input's, then midpoints).
        crossing: (p, 2) int the edge (i, j) of each new point.
        alpha: (p,) its root of eq. (18-20): the point is ``alpha V_i + (1 - alpha) V_j``.
        root: (p,) +1 or -1: the sign of the square root that gives alpha.
        points: (p, 3) the new points, on the cylinder.
        faces: (f, 3) the drilled mesh's faces in the extended numbering.
        kept: (k,) the extended indices of the drilled mesh's vertices, in its vertex order
            (vertices inside the hole are gone).
        holes: number of holes (connected drilled regions).
    """

    parents: Int[np.ndarray, "r 2"]
    refinements: int
    vertices: Float[np.ndarray, "nr 3"]
    crossing: Int[np.ndarray, "p 2"]
    alpha: Float[np.ndarray, " p"]
    root: Float[np.ndarray, " p"]
    points: Float[np.ndarray, "p 3"]
    faces: Int[np.ndarray, "f 3"]
    kept: Int[np.ndarray, " k"]
    holes: int


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


def _refine(V, F, edges: MeshEdges, face_mask):
    """Split every edge of the masked faces at its midpoint; every face on a split edge is
    re-triangulated conformingly. Returns (V, F, parents)."""
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
    return np.concatenate([V, 0.5 * (V[parents[:, 0]] + V[parents[:, 1]])]), faces, parents


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
        The refined SkinnedMesh (the input's vertices first, in order, then the midpoints)."""
    F = np.asarray(mesh.F)
    mask = np.ones(len(F), bool)
    if faces is not None:
        mask = np.zeros(len(F), bool)
        mask[np.asarray(faces)] = True
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    refined, F_new, parents = _refine(space, F, mesh_edges(F), mask)
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
    """Roots alpha of eq. (18-20) for edges with mu = P(v_i) - B, nu = P(v_j) - B (p, 3), kept
    strictly inside the edge (farther than ``margin`` from both ends).
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


class _Axis(NamedTuple):
    """The drill's axis: base B, unit direction, and the heights (v - B) . axis of all vertices."""

    base: np.ndarray
    direction: np.ndarray
    heights: np.ndarray

    def radial(self, V, index):
        """P(v) - B for the vertices ``index`` (computed where needed: few vertices are near a hole)."""
        return V[index] - self.base - self.heights[index, None] * self.direction


def _crossed(axis: _Axis, V, pairs, radius, margin):
    """Roots of eq. (18-20) on the edges ``pairs`` (see ``_cylinder_roots``)."""
    spans = V[pairs[:, 1]] - V[pairs[:, 0]]
    ends = axis.radial(V, pairs.ravel()).reshape(-1, 2, 3)
    return _cylinder_roots(ends[:, 0], ends[:, 1], radius, np.sqrt(np.einsum("ij,ij->i", spans, spans)), margin)


class _Pass(NamedTuple):
    """One drilling pass: the affected faces (m,) bool, the crossings (edge ids, alpha, root sign), the
    drill's axis, the number of holes and the fewest boundary points of a hole."""

    affected: np.ndarray
    index: np.ndarray
    alpha: np.ndarray
    sign: np.ndarray
    axis: _Axis
    holes: int
    fewest: int


def _drill_once(V, F, edges: MeshEdges, tip, base, radius, margin) -> _Pass:
    """One drilling pass (Algorithm 3, steps 1-3): the seeds pierced by the axis, the breadth-first
    search over the faces around them, and the crossings on the edges of the affected faces."""
    direction = (tip - base) / np.linalg.norm(tip - base)
    heights = V @ direction - base @ direction
    axis = _Axis(base, direction, heights)
    # |P(v) - B|^2 = |v - B|^2 - h^2, without forming P(v) for every vertex
    squared = np.einsum("ij,ij->i", V, V) - 2.0 * (V @ base) + base @ base - heights * heights
    inside = squared < (radius - margin) ** 2
    seeds, _, _ = segment_hits(V, F, base, tip)
    if len(seeds) == 0:
        raise ValueError("drill: misses the mesh (its axis from base to tip crosses no face)")
    # BFS: a neighbour is affected when a corner lies inside the drill or an edge passes through it
    visited = np.zeros(len(F), bool)
    visited[seeds] = True
    layers, frontier = [seeds], seeds
    while len(frontier):
        neighbours = edges.edge_faces[edges.face_edges[frontier].ravel()].ravel()
        neighbours = np.unique(neighbours[neighbours >= 0])
        neighbours = neighbours[~visited[neighbours]]
        visited[neighbours] = True
        hit = inside[F[neighbours]].any(axis=1)
        rest = np.flatnonzero(~hit)
        if len(rest):
            local_edges = edges.face_edges[neighbours[rest]]
            index, _, _ = _crossed(axis, V, edges.edges[local_edges.ravel()], radius, margin)
            hit[rest[np.unique(index // 3)]] = True
        frontier = neighbours[hit]
        layers.append(frontier)
    affected_faces = np.concatenate(layers)
    affected = np.zeros(len(F), bool)
    affected[affected_faces] = True
    # crossings on the edges of the affected faces
    on_affected = np.unique(edges.face_edges[affected_faces])
    if edges.edge_counts[on_affected].max() > 2:
        bad = edges.edges[on_affected[np.argmax(edges.edge_counts[on_affected])]]
        raise ValueError(
            f"mesh: the drill meets a non-manifold edge {bad.tolist()} (more than two faces on it); "
            "the hole around it is not defined"
        )
    index, alpha, sign = _crossed(axis, V, edges.edges[on_affected], radius, margin)
    index = on_affected[index]
    # holes: connected components of the affected faces (union-find over their shared edges: a few
    # dozen faces, cheaper in Python than a sparse graph); each hole needs enough boundary points
    local = np.full(len(F), -1, np.int64)
    local[affected_faces] = np.arange(len(affected_faces))
    a, b = edges.edge_faces[on_affected, 0], edges.edge_faces[on_affected, 1]
    a, b = local[a], np.where(b >= 0, local[np.maximum(b, 0)], -1)
    link = (a >= 0) & (b >= 0)
    parent = list(range(len(affected_faces)))

    def root(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    for x, y in zip(a[link].tolist(), b[link].tolist()):
        parent[root(x)] = root(y)
    _, labels = np.unique([root(x) for x in range(len(affected_faces))], return_inverse=True)
    holes = int(labels.max()) + 1
    first = edges.edge_faces[index, 0]
    face_of_edge = np.where(affected[first], first, edges.edge_faces[index, 1])
    counts = np.bincount(labels[local[face_of_edge]], minlength=holes)
    return _Pass(affected, index, alpha, sign, axis, holes, int(counts.min()))


def drill_topology(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    drill: Drill,
    *,
    min_points: int = 6,
    max_refinements: int = 4,
    tolerance: float = 1e-6,
    edges: MeshEdges | None = None,
) -> DrillTopology:
    """The topology of drilling the triangle mesh (V, F) (Algorithm 3).

    Args:
        V: (n, 3) vertex positions (rest pose or posed).
        F: (m, 3) int faces.
        drill: the ``Drill``: tip A and base B (3,) and radius r > 0; it drills the sheets of the
            surface that the segment B -> A pierces.
        min_points: fewest boundary points per hole before the affected faces are split and drilled
            again (the paper suggests 6).
        max_refinements: how many times at most.
        tolerance: vertices within ``tolerance`` times the bounding-box diagonal of the cylinder count
            as on it (no sliver triangles).
        edges: ``mesh_edges(F)``, precomputed once per topology.
    Raises:
        ValueError: bad input, a drill that misses the mesh, a drill wider than the part of the mesh it
            meets, or a hole that stays below three boundary points after ``max_refinements`` splits."""
    V, F = check_triangle_mesh(V, F, min_faces=0)
    tip, base, radius = check_drill(drill)
    if min_points < 3 or max_refinements < 0:
        raise ValueError(f"min_points, max_refinements: expected >= 3 and >= 0, got {min_points}, {max_refinements}")
    if not tolerance >= 0:
        raise ValueError(f"tolerance: expected a non-negative number, got {tolerance}")
    edges = mesh_edges(F) if edges is None else edges
    if edges.face_edges.shape != F.shape:
        raise ValueError(f"edges: computed for another mesh (face_edges {edges.face_edges.shape}, F {F.shape})")
    reach = float(_axis_distance(V, tip, base).max())
    if reach <= radius:
        raise ValueError(
            f"drill.radius: {radius:.4g} exceeds the model's size: every vertex lies within "
            f"{reach:.4g} of the drill's axis; give a smaller radius"
        )
    margin = tolerance * bounding_diagonal(V)
    smallest = SmallestFace(V, F)  # the input's: refinement only adds smaller faces
    all_parents, refinements = [], 0
    while True:
        state = _drill_once(V, F, edges, tip, base, radius, margin)
        if not refinements:  # faces of the input near the drill
            smallest.near(np.take(V, F[state.affected], axis=0))
        if state.fewest >= min_points or refinements == max_refinements:
            break
        V, F, parents = _refine(V, F, edges, state.affected)
        all_parents.append(parents)
        edges = mesh_edges(F)
        refinements += 1
    if state.fewest == 0 and _axis_distance(V[F[state.affected]], tip, base).max() <= radius:
        # every face around a hole lies inside the drill: no edge crosses its surface
        raise ValueError(
            f"drill.radius: {radius:.4g} is wider than the part of the model the drill meets (its faces "
            "all lie inside the drill); give a smaller radius"
        )
    if state.fewest < 3:
        raise ValueError(
            f"drill.radius: a hole has {state.fewest} boundary points after {refinements} refinements "
            "(the drill is too thin for the faces it meets; raise max_refinements or the radius)"
        )
    index, alpha, sign = state.index, state.alpha, state.sign
    # Each pass drops at least one new point (it snaps to the vertex or point next to it), so this ends.
    for _ in range(len(index) + 1):
        crossing = edges.edges[index]
        points = alpha[:, None] * V[crossing[:, 0]] + (1.0 - alpha[:, None]) * V[crossing[:, 1]]
        faces, drop = _retriangulate(V, F, edges, state, index, alpha, points, crossing, radius, smallest)
        if not len(drop):
            break
        keep = np.ones(len(index), bool)
        keep[drop] = False
        index, alpha, sign = index[keep], alpha[keep], sign[keep]
    used = np.zeros(len(V) + len(points), bool)
    used[faces] = True
    kept = np.flatnonzero(used)
    local = np.cumsum(used) - 1
    parents = np.concatenate(all_parents) if all_parents else np.zeros((0, 2), np.int64)
    return DrillTopology(parents, refinements, V, crossing, alpha, sign, points, local[faces], kept, state.holes)


def _axis_distance(X, tip, base) -> np.ndarray:
    direction = (tip - base) / np.linalg.norm(tip - base)
    offsets = X - base
    radial = offsets - (offsets @ direction)[..., None] * direction
    return np.sqrt(np.einsum("...j,...j->...", radial, radial))  # np.linalg.norm takes half as long again


def _retriangulate(V, F, edges: MeshEdges, state: _Pass, index, alpha, points, crossing, radius, smallest):
    """Faces of the drilled mesh (Algorithm 3, step 5) in the extended numbering, and the new points
    to drop: in each face whose pieces are slivers (``sliver_mask``), the new point (or the two on one
    edge) closest to its neighbour on the face's boundary, relative to that edge's length; without it
    the hole's boundary passes through the neighbour. Per affected face in plain Python: the faces
    near a hole are few, and small arrays cost more than they save."""
    affected = np.flatnonzero(state.affected)
    n = len(V)
    corners = F[affected]
    # radial vectors P(x) - B of the corners and the new points (the projection is affine)
    axis = state.axis
    radial = dict(zip(corners.ravel().tolist(), axis.radial(V, corners.ravel()).tolist()))
    point_radial = alpha[:, None] * axis.radial(V, crossing[:, 0]) + (1.0 - alpha[:, None]) * axis.radial(
        V, crossing[:, 1]
    )
    radial.update(zip(range(n, n + len(points)), point_radial.tolist()))
    position = dict(zip(corners.ravel().tolist(), V[corners.ravel()].tolist()))
    position.update(zip(range(n, n + len(points)), points.tolist()))
    # the new points of each edge, ordered from its first vertex (edges.edges[e, 0]) to its second
    on_edge: dict[int, list[tuple[float, int]]] = {}
    for p, (e, a) in enumerate(zip(index.tolist(), alpha.tolist())):
        on_edge.setdefault(e, []).append((1.0 - a, n + p))
    for entries in on_edge.values():
        entries.sort()
    limit = radius * radius
    triangles, parents, cycles = [], [], []
    for face, local_edges in zip(corners.tolist(), edges.face_edges[affected].tolist()):
        cycle, counts = [], []  # the boundary, and how many steps of it lie on each of the face's edges
        for k in range(3):
            a, b = face[k], face[(k + 1) % 3]
            cycle.append(a)
            ordered = [vid for _, vid in on_edge.get(local_edges[k], ())]
            cycle += ordered if a < b else ordered[::-1]
            counts.append(len(ordered) + 1)
        cycles.append((face, cycle, counts))
        m = len(cycle)
        before = len(triangles)
        # a boundary piece is outside the drill when its midpoint is (the drill is convex)
        outside = []
        for i in range(m):
            x, y = radial[cycle[i]], radial[cycle[(i + 1) % m]]
            mx, my, mz = x[0] + y[0], x[1] + y[1], x[2] + y[2]
            outside.append(0.25 * (mx * mx + my * my + mz * mz) > limit)
        if all(outside):
            triangles.append(tuple(face))
        elif any(outside):
            # each run of the boundary outside the drill, closed by a chord, is a convex piece
            start = next(i for i in range(m) if outside[i] and not outside[i - 1])
            run = [cycle[start]]
            for step in range(m):
                i = (start + step) % m
                if outside[i]:
                    run.append(cycle[(i + 1) % m])
                    continue
                if len(run) >= 3:
                    triangles += fan_triangles(run, [position[v] for v in run])
                run = [cycle[(i + 1) % m]]
        parents += [len(cycles) - 1] * (len(triangles) - before)
    pieces = np.asarray(triangles, np.int64).reshape(-1, 3)
    parents = np.asarray(parents, np.int64)
    piece_corners = np.take(np.concatenate([V, points]), pieces, axis=0)
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
            (math.dist(position[cycle[i]], position[cycle[(i + 1) % m]]) / spans[i], i)
            for i in range(m)
            if max(cycle[i], cycle[(i + 1) % m]) >= n
        ]
        if steps:
            _, i = min(steps)
            drop += [v - n for v in (cycle[i], cycle[(i + 1) % m]) if v >= n]
    return np.concatenate([np.compress(~state.affected, F, axis=0), pieces]), np.unique(np.asarray(drop, np.int64))


def _midpoint_levels(parents: Int[np.ndarray, "r 2"], n: int) -> list[Int[np.ndarray, "l 2"]]:
    """The refinement midpoints (vertex n + k is the midpoint of ``parents[k]``) in levels whose parents
    all precede the level (they may be midpoints of an earlier one): each level is one vectorized step."""
    levels, done = [], 0
    while done < len(parents):
        pending = parents[done:]
        later = np.flatnonzero(pending.max(axis=1) >= n + done)
        levels.append(pending[: later[0] if len(later) else len(pending)])
        done += len(levels[-1])
    return levels


@overload
def drill(
    mesh: SkinnedMesh,
    drill: Drill,
    *,
    min_points: int = ...,
    max_refinements: int = ...,
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
    max_refinements: int = ...,
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
    max_refinements: int = 4,
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
        min_points, max_refinements, tolerance: see ``drill_topology``.
        joint_matrices: (j, 4, 4) joint matrices of a pose (``deform.joint_matrices``): drill the mesh
            *in that pose*, the drill in world space. New vertices get the rest positions whose LBS
            image in that pose is their drilled position (exact for LBS).
        edges: ``mesh_edges(mesh.F)``, precomputed.
        return_topology: also return the ``DrillTopology`` (for ``drill_positions``).
    Returns:
        The drilled SkinnedMesh (its vertices: the input's outside the hole, in order, then refinement
        midpoints and new points), and the DrillTopology when ``return_topology``."""
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    topology = drill_topology(
        space, mesh.F, drill, min_points=min_points, max_refinements=max_refinements, tolerance=tolerance, edges=edges
    )
    rest = np.asarray(mesh.V, np.float64)
    for level in _midpoint_levels(topology.parents, len(rest)):
        J_mid, W_mid = blend_weights(J, W, level, np.full(level.shape, 0.5))
        target = 0.5 * (topology.vertices[level[:, 0]] + topology.vertices[level[:, 1]])
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
    refinement midpoints are formed from V (``topology.parents``), then eq. (18-20) is solved for
    each point's alpha (the root of ``topology.root``): the point ``alpha V_i + (1 - alpha) V_j``.

    Args:
        V: (n, 3) the input's vertex positions, as drilled (posed, when drilled with ``joint_matrices``).
        topology: the hole's ``DrillTopology``.
        drill: the ``Drill``.
    Returns:
        (p, 3) the new points, in the order of ``topology.crossing``."""
    V = jnp.asarray(V)
    n = len(topology.vertices) - len(topology.parents)
    if V.shape != (n, 3):
        raise ValueError(f"V: expected the {n} vertices that were drilled, shape ({n}, 3), got {V.shape}")
    for level in _midpoint_levels(topology.parents, n):
        V = jnp.concatenate([V, 0.5 * (V[level[:, 0]] + V[level[:, 1]])])
    tip, base, radius = jnp.asarray(drill.tip), jnp.asarray(drill.base), jnp.asarray(drill.radius)
    crossing = topology.crossing
    axis = (tip - base) / jnp.linalg.norm(tip - base)
    relative = V - base
    radial = relative - (relative @ axis)[:, None] * axis
    mu, nu = radial[crossing[:, 0]], radial[crossing[:, 1]]
    K = jnp.sum((mu - nu) ** 2, -1)
    L = 2.0 * jnp.sum((mu - nu) * nu, -1)
    N = jnp.sum(nu * nu, -1) - radius**2
    alpha = (-L + jnp.asarray(topology.root) * jnp.sqrt(L * L - 4.0 * K * N)) / (2.0 * K)
    return alpha[:, None] * V[crossing[:, 0]] + (1.0 - alpha[:, None]) * V[crossing[:, 1]]
