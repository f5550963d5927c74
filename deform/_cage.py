"""Harmonic-coordinate cages: sec. VI of the CGA mesh-deformation paper (Joshi et al. 2007,
"Harmonic coordinates for character articulation").

A closed cage (c vertices ``P_j``) encloses the mesh. Harmonic coordinate ``lambda_j`` is the solution of
Laplace's equation inside the cage whose boundary values are cage vertex j's hat function (1 at ``P_j``,
0 at the other cage vertices, linear on every cage face). They form a partition of unity, reproduce
linear functions (``sum_j lambda_j P_j = p``) and interpolate at the cage vertices, so

* the positional cage moves vertex i to ``p_i = sum_j lambda^i_j P_j`` (the classic HC deformation);
* the motor cage replaces every cage vertex by a motor ``R_j`` and moves vertex i by
  ``M_i = exp(sum_j lambda^i_j log R_j)`` (sec. VI), through ``deform._motor_field``.

Relation to the paper's ``p_i = M_i o ~M_i``: there the motors carry the point at the origin o to the
vertex, i.e. the rest motors are the translators ``T_{P_j}`` (then ``exp(sum_j lambda_j log T_{P_j}) =
T_{p_i}`` by linear precision). That is the binding of sec. III-A with rest motors ``T_{P_j}``
(``motor_field_precompute(V, coords, rest_motors=translator(P))`` gives back the paper's formula). Here the
rest motors are the identity, so the key motors are motions of space, ``p'_i = M_i p_i ~M_i``: identity
motors leave the mesh at rest, the same rigid motor G on every cage vertex moves the mesh rigidly by G, and
translators ``T_{d_j}`` give the positional cage ``p_i + sum_j lambda_j d_j`` (the two bindings agree there).

Discretization: the cage surface is first midpoint-subdivided (its new vertices carry the hat functions'
exact values, averages of their parents'), then the interior is tetrahedralized with TetGen (switches
``pq1.414Y`` and a maximum tet volume relative to the cage's volume). ``Y`` keeps that surface (TetGen
may still split a few of its triangles: checked that every boundary facet stays inside one cage face,
where the hat functions are linear), so the Dirichlet values are the hat functions exactly. The
subdivision is what lets TetGen refine the interior at all: under ``Y`` it rejects every interior point
that encroaches on a large cage face (a cube cage otherwise gets one interior node whatever the volume
bound). The coordinates
solve the tetrahedral cotangent Laplace equation (``igl.cotmatrix`` on the tets) with those Dirichlet
values (``_jaxcga_shared.sparse.SparseSolver``, factored and solved on the host as in ``deform._harmonic``),
and every mesh vertex gets the coordinates of the tet that contains it (``igl.in_element`` on an AABB
tree), interpolated linearly; vertices on the cage up to round-off take the hat functions of its face.

TetGen is AGPL-3.0 (its Python wrapper ``tetgen`` is MIT): an optional extra (``pip install jaxcga[tetgen]``).
Without it the interior is meshed by fTetWild (MPL-2.0), which keeps the surface only within a narrow envelope:
every boundary node moves to its closest point of the cage, so the Dirichlet values are again the hat functions
exactly and linear precision holds on the tets (their boundary is then a polyhedron inscribed in the cage, which
may cut its sharp corners); a mesh vertex left between that polyhedron and the cage takes the hat functions of
the cage face it lies on, or, off the cage, the nearest tet's coordinates extrapolated. The cage vertices are
then nodes of no tet, kept first with the identity as coordinates.
"""

from __future__ import annotations

import igl
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import trimesh
from jaxtyping import ArrayLike, Float, Int

from _jaxcga_shared.checks import check_faces, check_points
from _jaxcga_shared.host import quiet_stdout
from _jaxcga_shared.mesh import bounding_diagonal
from _jaxcga_shared.sparse import SparseSolver
from _jaxcga_shared.tetmeshing import embed, ftetwild, optional_tetgen
from deform._motor_field import MotorField, motor_field_precompute

# points off the cage by less than this fraction of its bounding diagonal count as on it
_SURFACE_TOLERANCE = 1e-9


def _check_cage(cage_V, cage_F):
    cage_V = check_points("cage_V", cage_V, min_count=4, rows="c")
    cage_F = check_faces("cage_F", cage_F, len(cage_V), min_count=4)
    unused = np.setdiff1d(np.arange(len(cage_V)), cage_F)
    if len(unused):
        raise ValueError(f"cage_V: vertex {int(unused[0])} is on no face of cage_F; every cage vertex must be")
    mesh = trimesh.Trimesh(cage_V, cage_F, process=False)
    if not mesh.is_watertight or not mesh.is_winding_consistent:
        raise ValueError(
            "cage_F: the cage must be a closed, consistently oriented 2-manifold "
            f"(watertight: {mesh.is_watertight}, winding consistent: {mesh.is_winding_consistent})"
        )
    if abs(mesh.volume) <= 1e-12 * mesh.scale**3:
        raise ValueError("cage_V: the cage encloses no volume")
    if mesh.volume < 0:  # inward normals: flip, so that inside means winding number +1
        cage_F = cage_F[:, ::-1].copy()
    return cage_V, cage_F, abs(mesh.volume)


def _subdivide(cage_V, cage_F, levels: int):
    """Midpoint subdivision (each triangle into 4, ``levels`` times): the surface vertices sV, faces sF,
    and S (len(sV), c) sparse, row i the cage hat functions at surface vertex i (sV = S cage_V)."""
    S = sp.identity(len(cage_V), format="csr").tocsr()  # tocsr: scipy's stubs type identity as dia
    F = cage_F
    for _ in range(levels):
        edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
        unique, index = np.unique(edges, axis=0, return_inverse=True)
        # midpoint of edge 01, 12, 20 of each face (scipy's stubs allow a shape of None)
        mid = S.shape[0] + index.reshape(3, -1)  # pyright: ignore[reportOptionalSubscript]
        S = sp.vstack([S, (S[unique[:, 0]] + S[unique[:, 1]]) * 0.5]).tocsr()
        a, b, c = F.T
        F = np.concatenate(
            [
                np.stack(rows, 1)
                for rows in ([a, mid[0], mid[2]], [mid[0], b, mid[1]], [mid[2], mid[1], c], [mid[0], mid[1], mid[2]])
            ]
        )
    return S @ cage_V, F, S


def _hat_values(cage_V, cage_F, X):
    """The cage's hat functions (len(X), c) at the points of the cage closest to X, and their distances."""
    distance2, face, closest = igl.point_mesh_squared_distance(X, cage_V, cage_F)
    corners = cage_F[face]
    values = np.zeros((len(X), len(cage_V)))
    np.put_along_axis(
        values, corners, igl.barycentric_coordinates(closest, *cage_V[corners].transpose(1, 0, 2)), axis=1
    )
    return values, np.sqrt(distance2)


class _TetGenFailure(ValueError):
    """TetGen's own error (e.g. "Internal TetGen error within `recoversubfaces`")."""


def _tetrahedralize(tetgen, cage_V, cage_F, sV, sF, max_tet_volume):
    """TetGen on the subdivided surface; checks that the tets' boundary lies on the cage, face by face.
    Returns the nodes, the tets and the boundary nodes."""
    try:
        with quiet_stdout():  # the wrapper prints "parsing switches / success" from C even with Q
            TV, TT = tetgen.TetGen(sV, sF).tetrahedralize(switches=f"pq1.414YQa{max_tet_volume:.17g}")[:2]
    except RuntimeError as error:
        raise _TetGenFailure(f"cage_F: TetGen failed to tetrahedralize the cage ({error})") from None
    TV, TT = np.asarray(TV, np.float64), np.asarray(TT, np.int64)
    facets = np.asarray(igl.boundary_facets(TT)[0])
    # Y keeps the surface, but TetGen may still split a few surface triangles: harmless as long as every
    # boundary facet lies in one cage face, where the hat functions are linear
    tolerance = _SURFACE_TOLERANCE * bounding_diagonal(cage_V)
    _, face, _ = igl.point_mesh_squared_distance(TV[facets].mean(axis=1), cage_V, cage_F)
    corners = cage_V[cage_F[face]].transpose(1, 0, 2)
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    bary = np.stack([igl.barycentric_coordinates(TV[facets[:, k]], *corners) for k in range(3)])
    off_plane = np.abs(np.einsum("kij,ij->ki", TV[facets.T] - corners[0], normal))
    if len(TV) < len(sV) or not np.array_equal(TV[: len(sV)], sV) or bary.min() < -1e-9 or off_plane.max() > tolerance:
        raise ValueError(
            "cage_F: TetGen changed the cage surface (a boundary facet leaves its cage face); "
            "remove self-intersections or near-degenerate faces from the cage"
        )
    return TV, TT, np.unique(facets)


def _tetrahedralize_ftetwild(cage_V, cage_F, max_tet_volume):
    """fTetWild's tets of the cage with their boundary nodes moved onto it (module docstring): the nodes, the
    first c being cage_V in no tet, the tets and the boundary nodes."""
    diagonal = bounding_diagonal(cage_V)
    edge = (6 * np.sqrt(2) * max_tet_volume) ** (1 / 3) / diagonal  # a regular tet of the largest volume
    # the envelope narrower than the tets: the boundary nodes move by at most its width onto the cage
    TV, TT = ftetwild(cage_V, cage_F, min(edge, 1.0), min(1e-3, edge / 20))
    used, TT = np.unique(TT, return_inverse=True)
    TV, TT = TV[used], TT.reshape(-1, 4) + len(cage_V)
    TV = np.concatenate([cage_V, TV])
    boundary = np.unique(np.asarray(igl.boundary_facets(TT)[0]))
    TV[boundary] = igl.point_mesh_squared_distance(TV[boundary], cage_V, cage_F)[2]
    x = TV[TT]
    if np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])).min() <= 0:
        raise ValueError("cage_F: moving fTetWild's boundary nodes onto the cage inverted a tet; lower max_tet_volume")
    return TV, TT, np.union1d(np.arange(len(cage_V)), boundary)  # the cage vertices' values are given too


def harmonic_coordinates(
    cage_V: Float[ArrayLike, "c 3"],
    cage_F: Int[ArrayLike, "m 3"],
    *,
    max_tet_volume: float = 1e-4,
    subdivisions: int | None = None,
) -> tuple[Float[np.ndarray, "N 3"], Int[np.ndarray, "t 4"], Float[np.ndarray, "N c"]]:
    """Harmonic coordinates of a closed cage on a tetrahedralization of its interior.

    Args:
        cage_V: (c, 3) cage vertex positions.
        cage_F: (m, 3) int faces of a closed, consistently oriented 2-manifold (either orientation).
        max_tet_volume: the largest tet volume as a fraction of the cage's volume (the resolution).
        subdivisions: midpoint subdivisions of the cage surface before meshing (TetGen keeps the surface,
            so large cage faces would leave the interior coarse; fTetWild, without TetGen, needs none and
            ignores it); None: enough to bring the median cage
            edge down to the edge of a regular tet of the largest volume.
    Returns:
        TV (N, 3) tet nodes, the first c being cage_V (nodes of no tet without TetGen); TT (t, 4) int tets;
        H (N, c) the coordinates at the nodes (numpy, float64), the identity on the first c rows.
    Raises:
        ValueError: bad shapes, an open, non-manifold or inconsistently oriented cage, no volume, a
            cage TetGen cannot mesh without changing its surface."""
    cage_V, cage_F, volume = _check_cage(cage_V, cage_F)
    return _harmonic_coordinates(cage_V, cage_F, volume, max_tet_volume, subdivisions)


def _harmonic_coordinates(cage_V, cage_F, volume, max_tet_volume, subdivisions):
    if not 0 < max_tet_volume <= 1:
        raise ValueError(f"max_tet_volume: expected a fraction of the cage's volume in (0, 1], got {max_tet_volume}")
    if subdivisions is None:
        edge = np.median(np.linalg.norm(cage_V[cage_F] - cage_V[np.roll(cage_F, 1, axis=1)], axis=2))
        tet_edge = (6 * np.sqrt(2) * max_tet_volume * volume) ** (1 / 3)
        subdivisions = max(0, int(np.ceil(np.log2(edge / tet_edge))))
    elif not isinstance(subdivisions, int) or subdivisions < 0:
        raise ValueError(f"subdivisions: expected None or an int >= 0, got {subdivisions!r}")
    tetgen = optional_tetgen()
    if tetgen is None:  # fTetWild needs no subdivision: it places its own boundary nodes
        TV, TT, boundary = _tetrahedralize_ftetwild(cage_V, cage_F, max_tet_volume * volume)
        H = np.empty((len(TV), len(cage_V)))
        H[boundary] = _hat_values(cage_V, cage_F, TV[boundary])[0]
        H[: len(cage_V)] = np.eye(len(cage_V))
    else:
        # TetGen's boundary recovery sometimes fails on the many coplanar points of a subdivided face:
        # retry with fewer subdivisions.
        for level in range(subdivisions, -1, -1):
            sV, sF, S = _subdivide(cage_V, cage_F, level)
            try:
                TV, TT, boundary = _tetrahedralize(tetgen, cage_V, cage_F, sV, sF, max_tet_volume * volume)
                break
            except _TetGenFailure:
                if level == 0:
                    raise
        H = np.empty((len(TV), len(cage_V)))
        H[boundary] = _hat_values(cage_V, cage_F, TV[boundary])[0]
        H[: len(sV)] = S.toarray()  # exact: the subdivision's averages, not a closest-point projection
    free = np.setdiff1d(np.arange(len(TV)), boundary)
    if len(free):
        # host-side Dirichlet solve -L_ff H_f = L_fb H_b (the precompute needs no JAX trace)
        L = sp.csr_matrix(igl.cotmatrix(TV, TT))
        H[free] = SparseSolver(-L[free][:, free], symmetric=True).host_solve(L[free][:, boundary] @ H[boundary])
    return TV, TT, H


def _interpolate(cage_V, cage_F, TV, TT, H, V):
    """Coordinates of the points V: on the cage (up to round-off), the hat functions of the face they lie on;
    elsewhere linear in their tet, or, inside the cage but in no tet (fTetWild's boundary inscribed in the
    cage), in the nearest tet, extrapolated."""
    values, distance = _hat_values(cage_V, cage_F, V)
    # in_element has no tolerance, and without TetGen a tet may reach past a concave cage vertex: points on the
    # cage take its hat functions first
    coords = values
    off = np.flatnonzero(distance > _SURFACE_TOLERANCE * bounding_diagonal(cage_V))
    if len(off):
        tree = igl.AABB()
        tree.init(TV, TT)
        tet = np.asarray(igl.in_element(TV, TT, V[off], tree))
        inside = tet >= 0
        corners = TT[tet[inside]]
        bary = np.asarray(igl.barycentric_coordinates(V[off[inside]], *(TV[corners[:, k]] for k in range(4))))
        coords[off[inside]] = np.einsum("nk,nkc->nc", bary, H[corners])
        far = off[~inside]
        if len(far):
            winding = np.asarray(igl.winding_number(cage_V, cage_F, V[far])).reshape(-1)
            if np.any(winding <= 0.5):
                i = int(far[np.argmax(winding <= 0.5)])
                raise ValueError(
                    f"V: {int((winding <= 0.5).sum())} vertices lie outside the cage, the first is vertex {i} at "
                    f"{V[i].tolist()} (winding number {float(winding[np.argmax(winding <= 0.5)]):.3g}, expected 1)"
                )
            element, weights, _ = embed(TV, TT, V[far])
            coords[far] = np.einsum("nk,nkc->nc", weights, H[TT[element]])
    return coords


def cage_precompute(
    V: Float[ArrayLike, "n 3"],
    cage_V: Float[ArrayLike, "c 3"],
    cage_F: Int[ArrayLike, "m 3"],
    *,
    max_tet_volume: float = 1e-4,
    subdivisions: int | None = None,
) -> MotorField:
    """Bind the mesh vertices V to a cage by harmonic coordinates (sec. VI).

    Args:
        V: (n, 3) mesh vertices, all inside the cage (or on it).
        cage_V: (c, 3) cage vertices.
        cage_F: (m, 3) int faces of a closed, consistently oriented 2-manifold (inward orientation is flipped).
        max_tet_volume: the resolution, see ``harmonic_coordinates``.
        subdivisions: see ``max_tet_volume``.
    Returns:
        a ``MotorField`` whose weights are the harmonic coordinates ``lambda^i_j`` (n, c) and whose bound
        positions are V (identity rest motors): ``motor_field_solve`` on it and cage motors (batch shape
        (..., c)) is the motor cage, ``blend_positions(field.weights, P)`` on moved cage vertices P the
        positional cage. Its arrays have the default JAX float dtype (``jax.tree.map(lambda a:
        a.astype(jnp.float32), field)`` makes a float32 one).
    Raises:
        ValueError: see ``harmonic_coordinates``; V of the wrong shape or not finite; a vertex of V
            outside the cage (the message names it and its winding number)."""
    V = check_points("V", V, min_count=1)
    cage_V, cage_F, volume = _check_cage(cage_V, cage_F)
    TV, TT, H = _harmonic_coordinates(cage_V, cage_F, volume, max_tet_volume, subdivisions)
    coords = _interpolate(cage_V, cage_F, TV, TT, H, V)
    dtype = jnp.result_type(float)
    return motor_field_precompute(jnp.asarray(V, dtype), jnp.asarray(coords, dtype))


def tube_cage(
    V: Float[ArrayLike, "n 3"], axis: int | None = None, segments: int = 6, sides: int = 8, margin: float = 1.05
) -> tuple[Float[np.ndarray, "c 3"], Int[np.ndarray, "m 3"]]:
    """A coarse closed cage around a mesh elongated along ``axis`` (default: its longest extent): rings
    of regular polygons (``segments + 1`` of them, ``sides`` vertices each) whose radii cover the
    vertices of the slabs they bound, times ``margin``, capped by a fan at each end.

    Args:
        V: (n, 3) mesh vertices, n >= 2.
        axis: the tube's axis, 0, 1 or 2; None: the mesh's longest extent.
        segments: rings along the axis, minus one (>= 1).
        sides: vertices per ring (>= 3).
        margin: the rings' radii over the slabs' largest vertex radius (>= 1).
    Returns:
        (cage_V (c, 3), cage_F (m, 3)), outward oriented; c = (segments + 1) sides + 2."""
    V = check_points("V", V, min_count=2)
    if segments < 1 or sides < 3 or margin < 1.0:
        raise ValueError(f"segments, sides, margin: expected >= 1, >= 3, >= 1, got {segments}, {sides}, {margin}")
    axis = int(np.argmax(np.ptp(V, axis=0))) if axis is None else axis
    if axis not in (0, 1, 2):
        raise ValueError(f"axis: expected 0, 1, 2 or None, got {axis}")
    order = [axis] + [i for i in range(3) if i != axis]  # work with the tube's axis first
    X = V[:, order]
    pad = 0.05 * np.ptp(X[:, 0])
    if pad == 0:
        raise ValueError("V: the mesh has no extent along the axis")
    xs = np.linspace(X[:, 0].min() - pad, X[:, 0].max() + pad, segments + 1)
    centre = (X[:, 1:].min(0) + X[:, 1:].max(0)) / 2
    radius = np.linalg.norm(X[:, 1:] - centre, axis=1)
    slab = np.clip(np.searchsorted(xs, X[:, 0]) - 1, 0, segments - 1)
    slab_radius = np.array([radius[slab == s].max(initial=0.0) for s in range(segments)])
    slab_radius = np.maximum(slab_radius, 1e-3 * np.ptp(X[:, 0]))  # an empty slab still gets a ring
    ring_radius = np.maximum(np.r_[slab_radius[0], slab_radius], np.r_[slab_radius, slab_radius[-1]])
    ring_radius *= margin / np.cos(np.pi / sides)  # the polygon's sides, not only its corners, cover the radius
    angle = 2 * np.pi * np.arange(sides) / sides
    rings = [
        np.column_stack([np.full(sides, x), centre[0] + r * np.cos(angle), centre[1] + r * np.sin(angle)])
        for x, r in zip(xs, ring_radius)
    ]
    cage_V = np.concatenate(rings + [[[xs[0], *centre]], [[xs[-1], *centre]]])
    k, j = np.meshgrid(np.arange(segments), np.arange(sides), indexing="ij")
    a, b = k * sides + j, k * sides + (j + 1) % sides
    quads = np.concatenate(
        [np.stack([a, b, b + sides], -1).reshape(-1, 3), np.stack([a, b + sides, a + sides], -1).reshape(-1, 3)]
    )
    first, last = len(cage_V) - 2, len(cage_V) - 1
    caps = np.concatenate(
        [
            np.column_stack([np.full(sides, first), (np.arange(sides) + 1) % sides, np.arange(sides)]),
            np.column_stack(
                [
                    np.full(sides, last),
                    segments * sides + np.arange(sides),
                    segments * sides + (np.arange(sides) + 1) % sides,
                ]
            ),
        ]
    )
    cage_F = np.concatenate([quads, caps])
    cage_V = cage_V[:, np.argsort(order)]
    if trimesh.Trimesh(cage_V, cage_F, process=False).volume < 0:
        cage_F = cage_F[:, ::-1]
    return cage_V, cage_F
