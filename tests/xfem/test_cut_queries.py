"""The compiled geometric queries of the cuts: eq. 16's inside test and nearest subdomain (the batched winding
numbers of ``xfem._winding`` against libigl's ``winding_number`` on closed meshes of several sizes; the
nearest-solid rule of ``_nearest_subdomains``, the first solid that holds a point, else the nearest boundary by
libigl's distance, on solids in two groups) and the culling's separating axis test of tets against triangles
(``xfem._overlap``) against a linear program: a common point as convex combinations of both."""

import igl
import manifold3d
import numpy as np
from scipy.optimize import linprog

from xfem._overlap import tet_triangle_overlap
from xfem._subdomains import solid_mesh
from xfem._winding import winding_numbers
from xfem._xfem import _nearest_subdomains

RNG = np.random.default_rng(3)


def _mesh(solid):
    V, F, _ = solid_mesh(solid)
    return V, F


SOLIDS = [
    manifold3d.Manifold.cube((1.0, 1.0, 1.0)),
    manifold3d.Manifold.sphere(0.6, 24).translate((2.0, 0.0, 0.0)),
    manifold3d.Manifold.cube((1.0, 1.0, 1.0)) - manifold3d.Manifold.sphere(0.6, 16),  # a cube with a corner bitten off
]


def test_winding_numbers_are_libigls():
    meshes = [_mesh(solid) for solid in SOLIDS]
    points = RNG.uniform(-0.7, 2.7, size=(600, 3))
    mesh = RNG.integers(0, len(meshes), len(points))
    sizes = np.array([(len(V), len(F)) for V, F in meshes])
    vertex_start, face_start = (np.concatenate([[0], np.cumsum(sizes[:, k])]) for k in (0, 1))
    V = np.concatenate([m[0] for m in meshes])
    F = np.concatenate([m[1] for m in meshes])
    winding = winding_numbers(V, F, vertex_start, face_start, mesh, points)
    expected = np.empty(len(points))
    for s, (Vs, Fs) in enumerate(meshes):
        expected[mesh == s] = igl.winding_number(Vs, Fs, points[mesh == s])
    np.testing.assert_allclose(winding, expected, atol=1e-12)
    assert 0 < np.count_nonzero(winding > 0.5) < len(points)  # points inside and outside


def test_nearest_subdomain_is_the_first_holding_else_the_nearest():
    # group 0: two overlapping boxes; group 1: one box and a sphere far from it
    unit = manifold3d.Manifold.cube((1.0, 1.0, 1.0))
    group0 = [unit, unit.translate((0.5, 0.0, 0.0))]
    group1 = [unit, manifold3d.Manifold.sphere(0.5, 24).translate((3.0, 0.5, 0.5))]
    meshes = [_mesh(solid) for solid in group0 + group1]
    first = np.array([0, 2, 4])
    points = np.array(
        [
            [0.25, 0.5, 0.5],  # group 0: in the first box only
            [1.25, 0.5, 0.5],  # in the second only
            [0.75, 0.5, 0.5],  # in both: the first
            [-0.3, 0.5, 0.5],  # in neither, nearer the first
            [1.8, 0.5, 0.5],  # in neither, nearer the second
            [0.5, 0.5, 0.5],  # group 1: in the box
            [3.0, 0.5, 0.5],  # in the sphere
            [2.2, 0.5, 0.5],  # in neither, nearer the sphere (0.3 from it, 1.2 from the box)
        ]
    )
    group = np.array([0, 0, 0, 0, 0, 1, 1, 1])
    np.testing.assert_array_equal(_nearest_subdomains(meshes, first, group, points), [0, 1, 0, 0, 1, 0, 1, 1])


def _common_point(P, Q) -> bool:
    """Whether tet P and triangle Q share a point: weights l (4) and m (3), >= 0, each summing to 1, with
    l P = m Q (a feasibility linear program)."""
    equalities = np.zeros((5, 7))
    equalities[:3, :4], equalities[:3, 4:] = P.T, -Q.T
    equalities[3, :4] = equalities[4, 4:] = 1.0
    result = linprog(np.zeros(7), A_eq=equalities, b_eq=[0, 0, 0, 1, 1], bounds=(0, None), method="highs")
    return result.status == 0


def test_tet_triangle_overlap_is_a_common_point():
    P = RNG.normal(size=(400, 4, 3))
    P[:, [1, 2]] = P[:, [2, 1]]  # either orientation
    Q = RNG.normal(size=(400, 3, 3)) * 0.6 + RNG.normal(size=(400, 1, 3)) * 0.7
    overlap = tet_triangle_overlap(P, Q, 0.0)
    expected = np.array([_common_point(p, q) for p, q in zip(P, Q)])
    np.testing.assert_array_equal(overlap, expected)
    assert 50 < np.count_nonzero(expected) < 350  # both outcomes, many times
    # a gap below slack times an axis's length counts as contact: a triangle just above a tet's top corner
    tet = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    above = np.array([[-1.0, -1, 1 + 1e-9], [2, -1, 1 + 1e-9], [-1, 2, 1 + 1e-9]])
    assert not tet_triangle_overlap(tet[None], above[None], 0.0)[0]
    assert tet_triangle_overlap(tet[None], above[None], 1e-8)[0]
