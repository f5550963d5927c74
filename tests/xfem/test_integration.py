"""Exact subdomain integration (XFEM paper eq. 13, 14, 19-21): moments of boxes and of affine images of the
unit simplex against closed forms; an icosphere and a cylinder against trimesh's mass properties; whole
tets against the FEM consistent mass and body force; tets split by planes (manifold3d ``trim_by_plane``) and
cut by a thin slab: pieces add up to the tet, a corner piece against a degree-2 quadrature rule; Boolean
pieces (a cube with a square hole, a cube minus a polyhedral sphere) against analytic values; the batched
call against one call per piece; origin shifts far from the world origin; bad input."""

from __future__ import annotations

import manifold3d as m3
import numpy as np
import pytest
import trimesh

from xfem import Moments, body_force, consistent_mass, element_piece_integrals, moments_of_pieces, polyhedron_moments

# the per-piece linear shape coefficients are internal to XFEM's integration (no public API)
from xfem._integration import linear_shape_coefficients

RNG = np.random.default_rng(11)
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])  # outward for a positively oriented tet
# the 4-point rule exact for polynomials of degree 2 on a tet: barycentric permutations of (a, b, b, b)
_A, _B = (5 + 3 * np.sqrt(5)) / 20, (5 - np.sqrt(5)) / 20
QUADRATURE = np.full((4, 4), _B) + (_A - _B) * np.eye(4)


def _random_tets(k):
    x = RNG.normal(size=(k, 4, 3))
    flip = np.linalg.det(x[:, 1:] - x[:, :1]) < 0
    x[flip, 1:3] = x[flip, 2:0:-1]  # swap two corners: positive orientation
    return x


def _box_moments(lo, hi):
    """Closed-form integrals of 1, X_i, X_i X_j over the box [lo, hi] (products of 1D integrals)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    i0, i1, i2 = hi - lo, (hi**2 - lo**2) / 2, (hi**3 - lo**3) / 3
    volume = np.asarray(np.prod(i0))
    first = volume / i0 * i1
    second = np.outer(first, first) / volume
    np.fill_diagonal(second, volume / i0 * i2)
    return Moments(volume, first, second)


def _box_mesh(lo, hi):
    box = trimesh.creation.box(bounds=np.array([lo, hi], float))
    return np.asarray(box.vertices), np.asarray(box.faces)


def _to_manifold(V, F):
    return m3.Manifold(
        m3.Mesh64(vert_properties=np.ascontiguousarray(V, np.float64), tri_verts=np.ascontiguousarray(F, np.uint64))
    )


def _mesh64(manifold):
    mesh = manifold.to_mesh64()
    assert mesh.vert_properties.dtype == np.float64  # to_mesh would round positions to float32
    return mesh.vert_properties[:, :3], mesh.tri_verts.astype(np.int64)


def _assert_moments(got, want, rtol):
    scale = abs(float(want.volume)) + np.abs(want.first).max() + np.abs(want.second).max()
    for g, w in zip(got, want):
        np.testing.assert_allclose(g, w, rtol=0, atol=rtol * scale)


@pytest.mark.parametrize("lo, hi", [((0, 0, 0), (1, 1, 1)), ((0.5, -2.0, 3.0), (1.7, -1.5, 3.25))])
def test_box_moments(lo, hi):
    _assert_moments(polyhedron_moments(*_box_mesh(lo, hi)), _box_moments(lo, hi), 1e-14)


def test_tet_moments_against_affine_images_of_the_unit_simplex():
    # unit simplex: int 1 = 1/6, int x = 1/24, int x^2 = 2!/5! = 1/60, int x y = 1/5! = 1/120
    unit = Moments(np.asarray(1 / 6), np.full(3, 1 / 24), np.full((3, 3), 1 / 120) + np.eye(3) / 120)
    for x in _random_tets(5):
        A, t = (x[1:] - x[0]).T, x[0]  # X = A Y + t maps the unit simplex onto the tet
        J = np.linalg.det(A)
        Af = A @ unit.first
        want = Moments(
            J * unit.volume,
            J * (Af + t * unit.volume),
            J * (A @ unit.second @ A.T + np.outer(Af, t) + np.outer(t, Af) + np.outer(t, t) * unit.volume),
        )
        _assert_moments(polyhedron_moments(x, TET_FACES), want, 1e-14)


@pytest.mark.parametrize(
    "mesh",
    [
        trimesh.creation.icosphere(subdivisions=2, radius=0.7),
        trimesh.creation.cylinder(radius=0.4, height=1.3, sections=24),
    ],
    ids=["icosphere", "cylinder"],
)
def test_against_trimesh_mass_properties(mesh):
    mesh = mesh.copy()
    mesh.apply_translation([0.3, -1.2, 2.0])
    got = polyhedron_moments(mesh.vertices, mesh.faces, origin=mesh.vertices[0])
    np.testing.assert_allclose(got.volume, mesh.volume, rtol=1e-13)
    center = got.first / got.volume + mesh.vertices[0]
    np.testing.assert_allclose(center, mesh.center_mass, rtol=0, atol=1e-13)
    C = got.second - np.outer(got.first, got.first) / got.volume  # covariance about the center of mass
    inertia = np.trace(C) * np.eye(3) - C  # trimesh's moment_inertia is about the center of mass, density 1
    np.testing.assert_allclose(inertia, mesh.moment_inertia, rtol=0, atol=1e-13 * np.abs(inertia).max())


def test_whole_tets_give_the_fem_consistent_mass_and_body_force():
    x = _random_tets(6)
    V = x.reshape(-1, 3)
    F = (TET_FACES[None] + 4 * np.arange(6)[:, None, None]).reshape(-1, 3)
    piece = np.repeat(np.arange(6), 4)
    density = RNG.uniform(0.5, 2.0, size=6)
    c, g = linear_shape_coefficients(x, origin=x.mean(axis=1))
    moments = moments_of_pieces(V, F, piece, 6, origin=x.mean(axis=1))
    mass, load, volume = element_piece_integrals(c, g, moments, density)
    T = np.arange(24).reshape(6, 4)
    M = consistent_mass(V, T, density).toarray()
    f = np.asarray(body_force(V, T, np.array([1.0, 0.0, 0.0])))[:, 0]
    for e in range(6):
        block = M[4 * e : 4 * e + 4, 4 * e : 4 * e + 4]
        np.testing.assert_allclose(mass[e], block, rtol=0, atol=1e-13 * np.abs(block).max())
        np.testing.assert_allclose(load[e], f[4 * e : 4 * e + 4], rtol=0, atol=1e-13 * volume[e])
    np.testing.assert_allclose(volume, np.linalg.det(x[:, 1:] - x[:, :1]) / 6, rtol=1e-13)


def test_far_from_the_world_origin_the_local_origin_keeps_precision():
    x = _random_tets(1)[0]
    far = x + np.array([1e4, -2e4, 5e3])
    c, g = linear_shape_coefficients(far, origin=far[0])
    mass = element_piece_integrals(c, g, polyhedron_moments(far, TET_FACES, origin=far[0]))[0]
    # far - far[0] is exact (Sterbenz), and the mass is translation invariant
    want = consistent_mass(far - far[0], np.arange(4)[None], 1.0).toarray()
    np.testing.assert_allclose(mass, want, rtol=0, atol=1e-13 * np.abs(want).max())


def test_plane_splits_add_up_to_the_tet():
    x = _random_tets(3)
    for Xe in x:
        tet = _to_manifold(Xe, TET_FACES)
        c, g = linear_shape_coefficients(Xe, origin=Xe.mean(axis=0))
        whole = element_piece_integrals(c, g, polyhedron_moments(Xe, TET_FACES, origin=Xe.mean(axis=0)))
        normal = RNG.normal(size=3)
        offset = normal @ Xe.mean(axis=0) / np.linalg.norm(normal)  # through the centroid: both sides non-empty
        sides = [_mesh64(tet.trim_by_plane(s * normal, s * offset)) for s in (1, -1)]
        V = np.concatenate([sides[0][0], sides[1][0]])
        F = np.concatenate([sides[0][1], sides[1][1] + len(sides[0][0])])
        piece = np.repeat([0, 1], [len(sides[0][1]), len(sides[1][1])])
        mass, load, volume = element_piece_integrals(c, g, moments_of_pieces(V, F, piece, 2, origin=Xe.mean(axis=0)))
        assert np.all(volume > 0.01 * whole[2])
        np.testing.assert_allclose(mass.sum(axis=0), whole[0], rtol=0, atol=1e-12 * np.abs(whole[0]).max())
        np.testing.assert_allclose(load.sum(axis=0), whole[1], rtol=0, atol=1e-12 * float(whole[2]))
        np.testing.assert_allclose(volume.sum(), whole[2], rtol=1e-12)


def test_corner_piece_against_quadrature():
    """The piece N_0 > t of a tet is the tet scaled by 1 - t about node 0: integrate over it by a degree-2 rule."""
    Xe = _random_tets(1)[0]
    t = 0.37
    c, g = linear_shape_coefficients(Xe)
    unit = np.linalg.norm(g[0])
    corner = _mesh64(_to_manifold(Xe, TET_FACES).trim_by_plane(g[0], (t - c[0]) / unit))
    mass, load, volume = element_piece_integrals(c, g, polyhedron_moments(*corner))
    small = Xe[0] + (1 - t) * (Xe - Xe[0])
    points = QUADRATURE @ small
    N = c + points @ g.T  # (4 points, 4 shape functions)
    weight = np.linalg.det(small[1:] - small[0]) / 6 / 4
    np.testing.assert_allclose(volume, 4 * weight, rtol=1e-12)
    np.testing.assert_allclose(mass, weight * N.T @ N, rtol=0, atol=1e-12 * np.abs(mass).max())
    np.testing.assert_allclose(load, weight * N.sum(axis=0), rtol=0, atol=1e-12 * float(volume))


def test_thin_slab_cut_pieces_plus_the_slab_part_give_the_tet():
    Xe = np.array([[0.1, 0.2, 0.0], [1.3, 0.1, 0.2], [0.2, 1.1, 0.1], [0.3, 0.2, 0.9]])
    tet = _to_manifold(Xe, TET_FACES)
    slab = m3.Manifold.cube([4.0, 4.0, 0.01], center=True).rotate([10.0, -20.0, 0.0]).translate([0.4, 0.4, 0.3])
    solids = (tet - slab).decompose() + [tet ^ slab]
    pieces = [_mesh64(p) for p in solids]
    assert len(pieces) == 3  # two pieces of material and the part of the slab inside the tet
    V = np.concatenate([p[0] for p in pieces])
    starts = np.cumsum([0] + [len(p[0]) for p in pieces])
    F = np.concatenate([p[1] + s for p, s in zip(pieces, starts)])
    piece = np.repeat(np.arange(3), [len(p[1]) for p in pieces])
    c, g = linear_shape_coefficients(Xe, origin=Xe.mean(axis=0))
    moments = moments_of_pieces(V, F, piece, 3, origin=Xe.mean(axis=0))
    mass, load, volume = element_piece_integrals(c, g, moments)
    M = consistent_mass(Xe, np.arange(4)[None], 1.0).toarray()
    np.testing.assert_allclose(volume, [p.volume() for p in solids], rtol=1e-12)  # manifold3d's own volumes
    assert 0 < volume[2] < 0.05 * volume.sum()
    np.testing.assert_allclose(volume.sum(), np.linalg.det(Xe[1:] - Xe[0]) / 6, rtol=1e-12)
    np.testing.assert_allclose(mass.sum(axis=0), M, rtol=0, atol=1e-12 * np.abs(M).max())
    # with rho = 1 the row sums of the consistent mass are int N_a = V / 4
    np.testing.assert_allclose(load.sum(axis=0), M.sum(axis=0), rtol=0, atol=1e-12 * volume.sum())


def test_cube_with_a_square_hole():
    cube = _to_manifold(*_box_mesh((0, 0, 0), (2, 2, 2)))
    drill = _to_manifold(*_box_mesh((0.5, 0.25, -1), (1.5, 1.25, 3)))
    got = polyhedron_moments(*_mesh64(cube - drill))
    full, hole = _box_moments((0, 0, 0), (2, 2, 2)), _box_moments((0.5, 0.25, 0), (1.5, 1.25, 2))
    _assert_moments(got, Moments(*(a - b for a, b in zip(full, hole))), 1e-14)


def test_cube_minus_a_polyhedral_sphere():
    sphere = trimesh.creation.icosphere(subdivisions=2, radius=0.6)
    sphere.apply_translation([1.0, 0.9, 1.1])
    cube = _to_manifold(*_box_mesh((0, 0, 0), (2, 2, 2)))
    got = polyhedron_moments(*_mesh64(cube - _to_manifold(sphere.vertices, sphere.faces)))
    ball = polyhedron_moments(sphere.vertices, sphere.faces)
    np.testing.assert_allclose(ball.volume, 4 / 3 * np.pi * 0.6**3, rtol=0.05)  # the polyhedron, not the ball
    _assert_moments(got, Moments(*(a - b for a, b in zip(_box_moments((0, 0, 0), (2, 2, 2)), ball))), 1e-14)


def test_batched_pieces_equal_one_call_per_piece():
    meshes = [
        _box_mesh((0, 0, 0), (1, 2, 3)),
        (_random_tets(1)[0], TET_FACES),
        (trimesh.creation.icosphere(1).vertices, trimesh.creation.icosphere(1).faces),
    ]
    origins = RNG.normal(size=(4, 3))
    starts = np.cumsum([0] + [len(V) for V, _ in meshes])
    V = np.concatenate([V for V, _ in meshes])
    F = np.concatenate([F + s for (_, F), s in zip(meshes, starts)])
    piece = np.repeat([0, 1, 3], [len(F) for _, F in meshes])  # piece 2 is empty
    order = RNG.permutation(len(F))
    got = moments_of_pieces(V, F[order], piece[order], 4, origin=origins)
    for k, (Vk, Fk) in zip([0, 1, 3], meshes):
        _assert_moments(Moments(*(m[k] for m in got)), polyhedron_moments(Vk, Fk, origin=origins[k]), 1e-14)
    assert got.volume[2] == 0 and not np.any(got.first[2]) and not np.any(got.second[2])


def test_bad_input():
    V, F = _random_tets(1)[0], TET_FACES
    with pytest.raises(ValueError, match="closed"):
        polyhedron_moments(V, F[:3])
    with pytest.raises(ValueError, match="inward"):
        polyhedron_moments(V, F[:, ::-1])
    with pytest.raises(ValueError, match="piece"):
        moments_of_pieces(V, F, np.array([0, 0, 0, 2]), 2)
    with pytest.raises(ValueError, match="F"):
        polyhedron_moments(V, F + 1)
    with pytest.raises(ValueError, match="V"):
        polyhedron_moments(V[:, :2], F)
    with pytest.raises(ValueError, match="V"):
        polyhedron_moments(np.where(V == V[0, 0], np.nan, V), F)
    with pytest.raises(ValueError, match="origin"):
        moments_of_pieces(V, F, np.zeros(4, int), 1, origin=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="Xe"):
        linear_shape_coefficients(np.zeros((4, 3)))
    c, g = linear_shape_coefficients(V)
    moments = polyhedron_moments(V, F)
    with pytest.raises(ValueError, match="g"):
        element_piece_integrals(c, g[:, :2], moments)
    with pytest.raises(ValueError, match="broadcast"):
        element_piece_integrals(np.stack([c, c]), g, Moments(np.ones(3), np.zeros((3, 3)), np.zeros((3, 3, 3))))
    with pytest.raises(ValueError, match="second"):
        element_piece_integrals(c, g, Moments(moments.volume, moments.first, moments.second[:2]))
    with pytest.raises(ValueError, match="density"):
        element_piece_integrals(c, g, moments, density=-1.0)
