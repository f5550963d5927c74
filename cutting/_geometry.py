"""Geometry shared by cut, tear and drill: the reusable adjacency (``mesh_edges``), input checks, the
mesh in a pose and back to rest (before / after animation), segment-surface hits, the
triangulation of the convex pieces that a tool leaves of a face, and the sliver rule they keep (``sliver_mask``)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from jaxtyping import ArrayLike, Int

from deform._model import SkinnedMesh


class MeshEdges(NamedTuple):
    """Reusable adjacency of a triangle mesh (the preprocessing of a cut, tear or drill).

    Attributes:
        edges: (e, 2) int unique undirected edges, smaller index first.
        face_edges: (m, 3) int edge id of each face's local edge (k, k+1 mod 3).
        edge_faces: (e, 2) int the first and the last face on each edge (-1 for the second of a
            boundary edge); tear and drill walk across faces with it.
        edge_counts: (e,) int faces on each edge (2 inside a manifold, 1 on its boundary).
    """

    edges: Int[np.ndarray, "e 2"]
    face_edges: Int[np.ndarray, "m 3"]
    edge_faces: Int[np.ndarray, "e 2"]
    edge_counts: Int[np.ndarray, " e"]


def mesh_edges(F: Int[ArrayLike, "m 3"]) -> MeshEdges:
    """The reusable adjacency of a triangle mesh: its unique edges and each face's edge ids.

    Args:
        F: (m, 3) int faces.
    Returns:
        The ``MeshEdges`` (pass it as ``edges=`` to the cut, tear and drill of meshes with these faces).

    Examples:
        >>> import numpy as np
        >>> import cutting
        >>> cutting.mesh_edges(np.array([[0, 1, 2], [0, 2, 3]])).edges.tolist()
        [[0, 1], [0, 2], [0, 3], [1, 2], [2, 3]]
    """
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3:
        raise ValueError(f"F: expected shape (m, 3), got {F.shape}")
    a, b = F.astype(np.int64), np.roll(F, -1, axis=1).astype(np.int64)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    # one integer key per undirected edge: a 1-D unique is several times faster than unique(axis=0)
    n = int(F.max(initial=0)) + 1
    keys, inverse = np.unique((lo * n + hi).ravel(), return_inverse=True)
    inverse = inverse.reshape(-1)
    face_of = np.repeat(np.arange(len(F)), 3)
    # Last writer wins in a fancy assignment: forwards gives each edge's last face, backwards its first.
    first = np.empty(len(keys), np.int64)
    first[inverse[::-1]] = face_of[::-1]
    last = np.empty(len(keys), np.int64)
    last[inverse] = face_of
    counts = np.bincount(inverse, minlength=len(keys))
    edge_faces = np.stack([first, np.where(counts >= 2, last, -1)], axis=1)
    return MeshEdges(np.stack([keys // n, keys % n], axis=1), inverse.reshape(-1, 3), edge_faces, counts)


def posed_vertices(mesh: SkinnedMesh, joint_matrices) -> tuple[np.ndarray, np.ndarray | None]:
    """The mesh's vertices in the space it is operated in: the bind pose when ``joint_matrices`` is
    None, else their LBS image (eq. 16) under the (j, 4, 4) joint matrices of a pose."""
    V = np.asarray(mesh.V, np.float64)
    if joint_matrices is None:
        return V, None
    joint_matrices = np.asarray(joint_matrices, np.float64)
    if joint_matrices.shape != (mesh.num_joints, 4, 4):
        raise ValueError(f"joint_matrices: expected shape ({mesh.num_joints}, 4, 4), got {joint_matrices.shape}")
    M = joint_matrices[:, :3, :]
    homogeneous = np.concatenate([V, np.ones((len(V), 1))], axis=1)
    return np.einsum(
        "nk,nkij,nj->ni", np.asarray(mesh.W, np.float64), M[np.asarray(mesh.J)], homogeneous
    ), joint_matrices


def rest_positions(J_new, W_new, targets, joint_matrices):
    """Rest positions of new vertices: bind-pose positions when ``joint_matrices`` is None, else the
    rest positions whose LBS image (eq. 16) under ``joint_matrices`` is ``targets`` (the inverse of
    each new vertex's blended affine map), so that re-posing reproduces the tool's surface."""
    targets = np.asarray(targets, np.float64)
    if joint_matrices is None:
        return targets
    M = np.asarray(joint_matrices, np.float64)[:, :3, :]
    blended = np.einsum("pk,pkij->pij", W_new, M[J_new])
    return np.linalg.solve(blended[:, :, :3], (targets - blended[:, :, 3])[:, :, None])[:, :, 0]


def skinned_mesh_like(mesh: SkinnedMesh, V, F, J, W) -> SkinnedMesh:
    """A SkinnedMesh with ``mesh``'s joints, inverse binds and dtypes. Numpy arrays (host data,
    traced like JAX arrays by jit): no per-array device transfer on the interactive path."""
    V, F, J, W = (np.asarray(x).astype(like.dtype) for x, like in ((V, mesh.V), (F, mesh.F), (J, mesh.J), (W, mesh.W)))
    # numpy on purpose (see above), where SkinnedMesh's fields are annotated as JAX arrays
    return SkinnedMesh(V, F, J, W, mesh.inverse_bind, mesh.joints)  # pyright: ignore[reportArgumentType]


def cross_rows(a, b):
    """Row-wise cross product of (..., 3) arrays (np.cross spends most of its time on axis handling
    for the small and medium arrays of the interactive path)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def cross3(a, b):
    """Cross product of two 3-vectors as Python floats (for per-face work on a tool's path)."""
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def _straddling_faces(V, F, start, end):
    """Faces that the segment start -> end may cross: their corners lie on both sides (or on) of two
    planes through the segment's line and within its extent along it. One byte per vertex, OR-ed
    over each face's corners: a cheap necessary condition that leaves a handful of faces."""
    direction = end - start
    length = float(np.linalg.norm(direction))
    d = direction / length
    u = np.cross(d, [1.0, 0.0, 0.0] if abs(d[0]) < 0.9 else [0.0, 1.0, 0.0])
    u /= np.linalg.norm(u)
    w = np.cross(d, u)
    a, b, s = ((V - start) @ np.stack([u, w, d], axis=1)).T
    code = (a <= 0) | (a >= 0) << 1 | (b <= 0) << 2 | (b >= 0) << 3 | (s <= length) << 4 | (s >= 0) << 5
    code = code.astype(np.uint8)[F]
    return np.flatnonzero((code[:, 0] | code[:, 1] | code[:, 2]) == 63)


def segment_hits(V, F, start, end, faces=None):
    """Crossings of the segment start -> end with the triangles F (Moller-Trumbore, vectorized).

    Returns (faces (h,), barycentric (h, 3), s (h,)): the faces crossed, the crossing's barycentric
    coordinates in each face and its parameter along the segment, sorted by s (from ``start``).
    ``faces``: the faces to test (default: those that ``_straddling_faces`` leaves)."""
    faces = _straddling_faces(V, F, start, end) if faces is None else np.asarray(faces)
    corners = F[faces]
    A, B, C = (V[corners[:, k]] for k in range(3))
    direction = end - start
    e1, e2 = B - A, C - A
    p = cross_rows(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-300
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    offset = start - A
    u = np.einsum("ij,ij->i", offset, p) * inv
    q = cross_rows(offset, e1)
    v = (q @ direction) * inv
    s = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (s >= 0) & (s <= 1)
    order = np.argsort(s[hit], kind="stable")
    u, v, s = u[hit][order], v[hit][order], s[hit][order]
    return faces[hit][order], np.stack([1.0 - u - v, u, v], axis=1), s


def fan_triangles(polygon, coordinates):
    """Triangles of a convex polygon (vertex ids in the face's winding order) whose boundary may hold
    collinear points (new points on an edge): the fan from the apex whose smallest triangle is
    largest, so that no triangle is degenerate. ``coordinates``: the polygon's k points (sequences of
    3 floats; Python lists are fastest for these few points)."""
    k = len(polygon)
    if k == 3:
        return [tuple(polygon)]
    P = coordinates
    best, best_area = 0, -1.0
    for apex in range(k):
        a = P[apex]
        smallest = float("inf")
        for i in range(1, k - 1):
            b, c = P[(apex + i) % k], P[(apex + i + 1) % k]
            n = cross3((b[0] - a[0], b[1] - a[1], b[2] - a[2]), (c[0] - a[0], c[1] - a[1], c[2] - a[2]))
            smallest = min(smallest, n[0] * n[0] + n[1] * n[1] + n[2] * n[2])
        if smallest > best_area:
            best, best_area = apex, smallest
    ring = [polygon[(best + i) % k] for i in range(k)]
    return [(ring[0], ring[i], ring[i + 1]) for i in range(1, k - 1)]


# A piece that a tool leaves of a face keeps at least PIECE_AREA of the mesh's smallest face area, and
# no angle under PIECE_ANGLE radians unless the face has a smaller one: a new point that would make a
# smaller piece snaps to the vertex it lies next to (the mesh's own scale, so vertices move no more
# than these slivers need).
PIECE_AREA = 1e-3
PIECE_ANGLE = 1e-3


def triangle_quality(A, B, C):
    """(twice the area (t,), smallest angle (t,)) of the triangles with corners A, B, C (t, 3)."""
    doubled, dots = _area_and_dots(A, B, C)
    # the angle at a corner from its two edges: atan2(|cross|, dot), |cross| = twice the area
    return doubled, np.min([np.arctan2(doubled, dot) for dot in dots], axis=0)


def _area_and_dots(A, B, C):
    """Twice the areas (t,) of the triangles A, B, C (t, 3) and the dot products of the two edges at each corner."""
    ab, bc, ca = B - A, C - B, A - C
    normal = cross_rows(ab, -ca)
    doubled = np.sqrt(np.einsum("ij,ij->i", normal, normal))
    return doubled, [-np.einsum("ij,ij->i", ca, ab), -np.einsum("ij,ij->i", ab, bc), -np.einsum("ij,ij->i", bc, ca)]


class SmallestFace:
    """Twice the area of the input's smallest face, the reference of ``sliver_mask``. The faces near the tool
    (``near``) bound it from above; the whole mesh is scanned only for a piece small against them (on a large
    mesh the scan cost more than the tool's own work)."""

    def __init__(self, V, F):
        self._V, self._F = V, F
        self._value: float | None = None
        self.bound = np.inf

    def near(self, corners):
        """Lower the bound with faces of the input given by their corners (f, 3, 3)."""
        if len(corners):
            # the arithmetic of the scan in value(), so that the bound is never below the value
            normal = cross_rows(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            squared = normal[:, 0] * normal[:, 0] + normal[:, 1] * normal[:, 1] + normal[:, 2] * normal[:, 2]
            self.bound = min(self.bound, float(np.sqrt(squared.min())))

    def value(self) -> float:
        if self._value is None:
            # imported on first use: most tools never need the scan, and importing numba is slow
            from cutting._smallest_face import smallest_squared_doubled_area

            V, F = np.ascontiguousarray(self._V, np.float64), np.ascontiguousarray(self._F)
            self._value = float(np.sqrt(smallest_squared_doubled_area(V, F))) if len(F) else 0.0
        return self._value


def sliver_mask(pieces, faces, smallest: SmallestFace, headroom: float = 1.0):
    """Which pieces (t, 3, 3) (corner positions) of faces (t, 3, 3) are slivers: under ``headroom``
    x PIECE_AREA of the input's smallest face, or with an angle under ``headroom`` x PIECE_ANGLE and
    the face's own smallest angle. Exact angles and the input's smallest face only where a cheap
    bound leaves the answer open (few pieces are near either limit)."""
    area, dots = _area_and_dots(pieces[:, 0], pieces[:, 1], pieces[:, 2])
    limit = headroom * PIECE_AREA
    small = area < limit * smallest.bound
    if small.any():
        small = area < limit * smallest.value()
    angle_limit = headroom * PIECE_ANGLE
    # An angle under angle_limit (small) has a positive dot and |cross| / dot under its tangent, below
    # 2 angle_limit; the others cannot be thin.
    open_ = np.flatnonzero(np.any([area <= 2.0 * angle_limit * dot for dot in dots], axis=0))
    if len(open_):
        angle = np.min([np.arctan2(area[open_], dot[open_]) for dot in dots], axis=0)
        _, face_angle = triangle_quality(faces[open_, 0], faces[open_, 1], faces[open_, 2])
        small[open_[angle < np.minimum(angle_limit, face_angle)]] = True
    return small
