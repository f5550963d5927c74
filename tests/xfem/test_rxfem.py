"""The RXFEM baseline (Koschier et al. 2017, ``xfem._rxfem``): Keast's 24-point rule against the closed-form
monomial integrals of the unit tetrahedron; an uncut body steps exactly as plain FEM (``fem_from_mesh``); a full
planar cut separates a bar into two pieces whose masses and volumes are the analytic split; the cut-off piece of a
hanging bar falls with g; on a through-cut both methods make the same DOFs, the same mass (the moment-fitted rules
against the exact divergence-theorem integrals) and the same steps; intersecting cuts are refused."""

from math import factorial

import jax.numpy as jnp
import numpy as np
import pytest

from tests.xfem._models import EPS, MATERIAL, RHO, G, H, deformed_state, plane, tall_box
from xfem import (
    KEAST24,
    KEAST24_WEIGHTS,
    State,
    backward_euler_step,
    box_tets,
    fem_from_mesh,
    moment_fitted_weights,
    rxfem_model,
    rxfem_schedule,
    scene,
    tet_mesh,
    xfem_model,
)

Z_CUT = 0.61  # a horizontal cut of the tall box between its node layers (z = 0, 0.5, 1, 1.5)


def _row_mass(system) -> np.ndarray:
    """(n,) the row sums of the scalar mass matrix: each DOF's share of the mass."""
    return np.bincount(np.asarray(system.mass_rows), np.asarray(system.mass_values), minlength=system.n)


def test_keast_rule_is_exact_to_degree_6():
    # int over the unit tet of x^a y^b z^c = a! b! c! / (a + b + c + 3)!
    X = KEAST24[:, 1:]  # barycentric (l0, l1, l2, l3) -> the unit tet's point (l1, l2, l3)
    assert KEAST24.shape == (24, 4) and np.allclose(KEAST24.sum(axis=1), 1) and np.all(KEAST24 > 0)
    for a in range(7):
        for b in range(7 - a):
            for c in range(7 - a - b):
                exact = factorial(a) * factorial(b) * factorial(c) / factorial(a + b + c + 3)
                rule = KEAST24_WEIGHTS @ (X[:, 0] ** a * X[:, 1] ** b * X[:, 2] ** c) / 6
                assert abs(rule - exact) < 1e-14, (a, b, c)


def test_moment_fitting_integrates_a_corner_piece():
    # the corner {x + y + z < s} of the unit tet: the unit tet scaled by s, moments in closed form
    s = 0.3
    Xe = np.array([[[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]]], np.float64)
    origin = np.zeros((1, 3))
    volume = np.array([s**3 / 6])
    first = np.full((1, 3), s**4 / 24)
    second = np.full((1, 3, 3), s**5 / 120) + np.eye(3) * s**5 / 120  # x^2: 2 s^5 / 120, xy: s^5 / 120
    w = moment_fitted_weights(Xe, origin, volume, first, second)
    X = KEAST24[:, 1:]
    assert abs(w.sum() - volume[0]) < 1e-15
    np.testing.assert_allclose(w[0] @ X, first[0], rtol=1e-12)
    np.testing.assert_allclose(np.einsum("q,qi,qj->ij", w[0], X, X), second[0], rtol=1e-12)
    with pytest.raises(ValueError, match="origin"):
        moment_fitted_weights(Xe, np.zeros((2, 3)), volume, first, second)
    with pytest.raises(ValueError, match="second"):
        moment_fitted_weights(Xe, origin, volume, first, np.full((1, 3, 3), np.nan))
    with pytest.raises(ValueError, match="degenerate"):
        moment_fitted_weights(np.zeros((1, 4, 3)), origin, volume, first, second)


def test_uncut_model_is_plain_fem():
    mesh = box_tets((2, 2, 2))
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] < 1e-9)
    model = rxfem_model(mesh, RHO, fixed=fixed, state=deformed_state(mesh))
    reference = fem_from_mesh(mesh, RHO, fixed=fixed)
    state = deformed_state(mesh)
    for _ in range(3):
        model.step(H, MATERIAL, newton_iterations=1)
        state = backward_euler_step(reference, state, H, MATERIAL, newton_iterations=1)
    np.testing.assert_allclose(np.asarray(model.state.x), np.asarray(state.x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(model.state.v), np.asarray(state.v), rtol=0, atol=1e-12)
    assert model.pieces() == 1 and len(model.system().T) == mesh.T.shape[0]


def test_planar_cut_splits_mass_and_volume_analytically():
    mesh = tall_box()
    model = rxfem_model(mesh, RHO)
    model.cut(plane((0.5, 0.5, Z_CUT), (0.0, 0.0, 1.0)))
    count, label = model.components()
    assert count == 2 == model.pieces()
    mass = _row_mass(model.system())
    lower = label == label[np.argmin(model.X[model.dof_node, 2])]
    # 1 x 1 cross-section: the slab of thickness EPS leaves Z_CUT - EPS/2 below and 1.5 - Z_CUT - EPS/2 above
    expected = RHO * np.array([Z_CUT - EPS / 2, 1.5 - Z_CUT - EPS / 2])
    np.testing.assert_allclose([mass[lower].sum(), mass[~lower].sum()], expected, rtol=1e-12)
    element, _, volume, _, _ = model.piece_arrays()
    assert abs(volume.sum() - expected.sum() / RHO) < 1e-12
    # each piece of a cut element enters the step as 24 element rows carrying its volume
    rows = model.quadrature_rows()
    assert set(np.unique(rows).tolist()) == {1, 24}
    system = model.system()
    assert len(system.T) == rows.sum()
    assert abs(float(jnp.sum(system.volumes[: rows.sum()])) - volume.sum()) < 1e-12


def test_cut_off_piece_of_hanging_bar_falls_with_g():
    mesh = tall_box()
    top = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    model = rxfem_model(mesh, RHO, fixed=top)
    model.cut(plane())
    _, label = model.components()
    lower = label != label[np.isin(model.dof_node, top)][0]
    mass = _row_mass(model.system())[lower]  # the piece's centre of mass weights
    velocities = []
    for _ in range(4):
        model.step(H, MATERIAL, newton_iterations=1)
        velocities.append(mass @ np.asarray(model.state.v)[lower] / mass.sum())
    # the free piece's centre of mass accelerates with g (up to the single inexact Newton iteration per step)
    acceleration = np.diff(velocities, axis=0) / H
    np.testing.assert_allclose(acceleration, np.broadcast_to(G, acceleration.shape), rtol=0, atol=1e-2)
    assert np.all(np.isin(model.dof_node[lower], top, invert=True))


def test_through_cut_agrees_with_ours():
    mesh = tall_box()
    top = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    ours = xfem_model(mesh, RHO, fixed=top, state=deformed_state(mesh))
    rxfem = rxfem_model(mesh, RHO, fixed=top, state=deformed_state(mesh))
    ours.cut(plane())
    rxfem.cut(plane())
    np.testing.assert_array_equal(ours.dof_sid, rxfem.dof_sid)
    a, b = ours.piece_arrays(), rxfem.piece_arrays()
    np.testing.assert_array_equal(a[1], b[1])  # the same DOFs per piece
    for exact, fitted in zip(a[2:], b[2:]):  # volume, mass, load: the rules against the exact integrals
        np.testing.assert_allclose(fitted, exact, rtol=0, atol=1e-13 * np.abs(exact).max())
    for _ in range(2):
        ours.step(H, MATERIAL, newton_iterations=1)
        rxfem.step(H, MATERIAL, newton_iterations=1)
    np.testing.assert_allclose(np.asarray(rxfem.state.x), np.asarray(ours.state.x), rtol=0, atol=1e-10)
    np.testing.assert_allclose(np.asarray(rxfem.state.v), np.asarray(ours.state.v), rtol=0, atol=1e-8)


def test_intersecting_cut_is_refused_and_surfaces_are_thickened():
    mesh = tall_box()
    model = rxfem_model(mesh, RHO)
    model.cut(plane())
    dofs = model.dof_sid.copy()
    with pytest.raises(ValueError, match="intersect"):
        model.cut(plane((0.43, 0.5, 0.75), (1.0, 0.06, -0.03)))
    np.testing.assert_array_equal(model.dof_sid, dofs)  # left unchanged
    # a parallel cut that meets no earlier one is made; given as an open surface (V, F) thickened by EPS
    V = np.array([[-1.0, -1.0, 1.2], [2.0, -1.0, 1.2], [2.0, 2.0, 1.23], [-1.0, 2.0, 1.23]])
    F = np.array([[0, 1, 2], [0, 2, 3]])
    model.cut((V, F), epsilon=EPS)
    assert model.pieces() == 3
    with pytest.raises(ValueError, match="epsilon"):
        model.cut((V, F))
    with pytest.raises(ValueError, match="epsilon"):
        model.cut(plane((0.5, 0.5, 0.3), (0.0, 0.0, 1.0)), epsilon=EPS)
    with pytest.raises(ValueError, match="mesh"):
        rxfem_model("not a mesh", RHO)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="state"):
        rxfem_model(mesh, RHO, state=State(jnp.zeros((3, 3)), jnp.zeros((3, 3))))


@pytest.mark.parametrize(("name", "kept", "left"), [("sticks", 5, 5), ("thin", 4, 1)])
def test_schedule_leaves_out_the_intersecting_cuts(name, kept, left):
    sc = scene(name, "small")
    ours, rx, rest = rxfem_schedule(sc)
    assert (len(ours.cuts), len(rest)) == (kept, left) == (len(rx.cuts), left)
    assert isinstance(rx.model(), type(rxfem_model(sc.mesh, sc.density)))


def test_crossings_count_inside_the_body_only():
    # two tets sharing one vertex (manifold3d keeps the pinched boundary a solid): two cuts that cross in the empty
    # corner between them, outside the body, do not intersect for RXFEM; crossing inside a tet they do
    X = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]], np.float64)
    mesh = tet_mesh(X, np.array([[0, 1, 2, 3], [0, 4, 6, 5]]))
    model = rxfem_model(mesh, RHO)
    assert model.body().volume() == pytest.approx(1 / 3)
    model.cut(plane((0.0, 0.0, 0.3), (0.02, 0.01, 1.0)))
    assert model.intersecting(plane((-0.3, 0.0, 0.0), (1.0, 0.01, 0.03), extent=0.5).translate((0, 0.0, 0.3))) is None
    with pytest.raises(ValueError, match="intersect"):
        model.cut(plane((0.2, 0.2, 0.2), (1.0, 0.01, 0.03)))
