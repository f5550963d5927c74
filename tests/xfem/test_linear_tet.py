"""Linear tetrahedra (XFEM paper eq. 5, 7, 8): shape functions and gradients against a direct solve of eq. 5
with numpy, partition of unity, the Kronecker delta, linear precision and exact gradients of linear fields;
the consistent mass against a degree-2-exact quadrature (4-point rule) and closed-form moments of the
unit tet; lumped mass and body forces against total mass, total force and first moments; gradients by
finite differences; float32; bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.shared import check_gradient
from xfem import body_force, box_tets, consistent_mass, lumped_mass, one_tet, shape_functions, shape_gradients, tet_mesh

RNG = np.random.default_rng(7)
# 40 independent random tets (reoriented by tet_mesh) and a small box mesh with jittered nodes
RANDOM = tet_mesh(RNG.normal(size=(160, 3)), np.arange(160).reshape(40, 4))
_BOX = box_tets((2, 1, 2), size=(1.0, 2.0, 0.5), origin=(0.2, -0.3, 1.0))
BOX = tet_mesh(_BOX.X + 0.01 * RNG.normal(size=_BOX.X.shape), _BOX.T)
MESHES = {"random": RANDOM, "box": BOX}

# the 4-point rule exact for polynomials of degree 2 on a tet: barycentric permutations of (a, b, b, b)
_A, _B = (5 + 3 * np.sqrt(5)) / 20, (5 - np.sqrt(5)) / 20
QUADRATURE = np.full((4, 4), _B) + (_A - _B) * np.eye(4)  # (points, barycentric), weights V / 4 each


def _eq5_coefficients(mesh):
    """inv([1 X Y Z]) per tet: column j holds the coefficients a_j of N_j (eq. 5), by numpy's solver."""
    x = np.asarray(mesh.X)[np.asarray(mesh.T)]
    P = np.concatenate([np.ones((len(x), 4, 1)), x], axis=2)
    return np.linalg.inv(P)


def _volumes(mesh):
    x = np.asarray(mesh.X)[np.asarray(mesh.T)]
    return np.linalg.det(x[:, 1:] - x[:, :1]) / 6


@pytest.mark.parametrize("name", MESHES)
def test_shape_gradients_and_functions_solve_eq5(name):
    mesh = MESHES[name]
    C = _eq5_coefficients(mesh)
    grads, volumes = shape_gradients(mesh.X, mesh.T)
    np.testing.assert_allclose(grads, C[:, 1:, :].transpose(0, 2, 1), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(volumes, _volumes(mesh), rtol=1e-12)
    elements = RNG.integers(0, mesh.n_elements, 300)
    bary = RNG.dirichlet(np.ones(4), 300)
    points = np.einsum("ka,kaj->kj", bary, np.asarray(mesh.X)[np.asarray(mesh.T)[elements]])
    N = shape_functions(mesh.X, mesh.T, points, elements)
    reference = np.einsum("kj,kja->ka", np.concatenate([np.ones((300, 1)), points], axis=1), C[elements])
    np.testing.assert_allclose(N, reference, atol=1e-12)
    np.testing.assert_allclose(N, bary, atol=1e-12)  # barycentric coordinates


@pytest.mark.parametrize("name", MESHES)
def test_partition_of_unity_kronecker_delta_linear_precision(name):
    mesh = MESHES[name]
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    m = mesh.n_elements
    # Kronecker delta: N_a at node b of the same tet
    N = shape_functions(X, T, X[T].reshape(-1, 3), np.repeat(np.arange(m), 4))
    np.testing.assert_allclose(N.reshape(m, 4, 4), np.broadcast_to(np.eye(4), (m, 4, 4)), atol=1e-12)
    # partition of unity and linear precision also outside the tet (the affine extension)
    points = RNG.normal(size=(200, 3))
    elements = RNG.integers(0, m, 200)
    N = shape_functions(X, T, points, elements)
    np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(jnp.einsum("ka,kaj->kj", N, X[T[elements]]), points, atol=1e-11)


@pytest.mark.parametrize("name", MESHES)
def test_gradients_reproduce_linear_fields(name):
    mesh = MESHES[name]
    grads, _ = shape_gradients(mesh.X, mesh.T)
    np.testing.assert_allclose(grads.sum(axis=1), 0.0, atol=1e-12)
    A, c = RNG.normal(size=(3, 3)), RNG.normal(size=3)
    x = np.asarray(mesh.X) @ A.T + c
    F = jnp.einsum("eai,eaj->eij", x[np.asarray(mesh.T)], grads)  # F_e = sum_a x_a grad N_a^T
    np.testing.assert_allclose(F, np.broadcast_to(A, F.shape), atol=1e-11)
    np.testing.assert_allclose(
        jnp.einsum("eai,eaj->eij", mesh.X[mesh.T], grads), np.broadcast_to(np.eye(3), F.shape), atol=1e-12
    )


@pytest.mark.slow
def test_gradients_by_finite_differences():
    mesh = box_tets((1, 1, 1))
    T = mesh.T
    W = jnp.asarray(RNG.normal(size=(6, 4, 3)))
    w = jnp.asarray(RNG.normal(size=(8,)))
    forces = jnp.asarray(RNG.normal(size=(8, 3)))

    @jax.jit
    def loss(flat):
        X = flat.reshape(-1, 3)
        grads, volumes = shape_gradients(X, T)
        return (
            jnp.sum(jnp.tanh(grads) * W)
            + jnp.sum(volumes**2)
            + jnp.sum(lumped_mass(X, T, 2.0) * w)
            + jnp.sum(body_force(X, T, jnp.array([0.3, -1.0, 0.5])) * forces)
        )

    check_gradient(loss, mesh.X.ravel() + 0.02 * jnp.asarray(RNG.normal(size=24)))


def _quadrature_product(mesh, x, y, density):
    """int rho u v over the mesh for the piecewise linear fields with nodal values x, y (4-point rule)."""
    T = np.asarray(mesh.T)
    u, v = QUADRATURE @ x[T].T, QUADRATURE @ y[T].T  # (points, m): u at each quadrature point of each tet
    return np.sum(density * _volumes(mesh) / 4 * (u * v).sum(axis=0))


@pytest.mark.parametrize("name", MESHES)
def test_consistent_mass_against_quadrature(name):
    mesh = MESHES[name]
    density = RNG.uniform(0.5, 3.0, mesh.n_elements)
    M = consistent_mass(mesh.X, mesh.T, density)
    assert M.shape == (mesh.n_nodes, mesh.n_nodes) and M.format == "csr"
    assert abs(M - M.T).max() == 0
    np.testing.assert_allclose(M.sum(), np.sum(density * _volumes(mesh)), rtol=1e-13)  # integral of rho * 1 * 1
    x, y = RNG.normal(size=mesh.n_nodes), RNG.normal(size=mesh.n_nodes)
    np.testing.assert_allclose(x @ M @ y, _quadrature_product(mesh, x, y, density), rtol=1e-12)
    np.testing.assert_allclose(lumped_mass(mesh.X, mesh.T, density), np.asarray(M.sum(axis=1)).ravel(), rtol=1e-13)
    scalar = consistent_mass(mesh.X, mesh.T, 2.5)
    np.testing.assert_allclose(x @ scalar @ y, _quadrature_product(mesh, x, y, 2.5), rtol=1e-12)


def test_consistent_mass_closed_forms_on_unit_tet_and_positive_definite():
    mesh = one_tet()
    X = np.asarray(mesh.X)
    M = consistent_mass(mesh.X, mesh.T, 1.0)
    # int x^2 = 2! 3! / 5! ... = 1/60 and int x y = 1/120 over the unit corner tet
    np.testing.assert_allclose(X[:, 0] @ M @ X[:, 0], 1 / 60, rtol=1e-14)
    np.testing.assert_allclose(X[:, 0] @ M @ X[:, 1], 1 / 120, rtol=1e-14)
    np.testing.assert_allclose(M.sum(), 1 / 6, rtol=1e-14)
    # the quadrature rule used above reproduces those closed forms too
    np.testing.assert_allclose(_quadrature_product(mesh, X[:, 0], X[:, 0], 1.0), 1 / 60, rtol=1e-14)
    box = consistent_mass(BOX.X, BOX.T, 1.0).toarray()
    assert np.linalg.eigvalsh(box).min() > 0


def test_lumped_mass_and_body_force_totals_and_moments():
    mesh = box_tets((2, 2, 1), size=(2.0, 1.0, 3.0), origin=(1.0, 0.0, -1.0))
    volume, centroid = 6.0, np.array([2.0, 0.5, 0.5])
    masses = lumped_mass(mesh.X, mesh.T, 1.5)
    np.testing.assert_allclose(masses.sum(), 1.5 * volume, rtol=1e-14)
    assert masses.min() > 0
    b = np.array([0.0, -9.81, 2.0])
    f = body_force(mesh.X, mesh.T, b)
    np.testing.assert_allclose(f.sum(axis=0), b * volume, rtol=1e-14)
    # sum_a X_a f_a = int X b^T = (first moment) b^T = volume * centroid b^T, since sum_a X_a N_a = X
    np.testing.assert_allclose(mesh.X.T @ f, volume * np.outer(centroid, b), rtol=1e-13, atol=1e-13)
    # per-tet force densities against the quadrature of int b_e N_a (degree 1)
    be = RNG.normal(size=(mesh.n_elements, 3))
    reference = np.zeros((mesh.n_nodes, 3))
    weights = _volumes(mesh)[:, None, None] / 4 * QUADRATURE.sum(axis=0)[None, :, None]  # (m, 4, 1)
    np.add.at(reference, np.asarray(mesh.T), weights * be[:, None, :])
    np.testing.assert_allclose(body_force(mesh.X, mesh.T, be), reference, rtol=1e-13)
    np.testing.assert_allclose(jax.jit(body_force)(mesh.X, mesh.T, be), reference, rtol=1e-13)


def test_float32():
    X32 = BOX.X.astype(jnp.float32)
    grads, volumes = shape_gradients(X32, BOX.T)
    assert grads.dtype == volumes.dtype == jnp.float32
    np.testing.assert_allclose(grads, shape_gradients(BOX.X, BOX.T)[0], rtol=1e-4, atol=1e-4)
    assert lumped_mass(X32, BOX.T, 1.0).dtype == body_force(X32, BOX.T, np.ones(3)).dtype == jnp.float32


def test_bad_input():
    X, T = BOX.X, BOX.T
    inverted = jnp.asarray(T).at[0].set(T[0, jnp.array([1, 0, 2, 3])])
    with pytest.raises(ValueError, match=r"X: expected float positions of shape \(n, 3\)"):
        shape_gradients(X[:, :2], T)
    with pytest.raises(ValueError, match="T: expected integer tets"):
        shape_gradients(X, T.astype(float))
    with pytest.raises(ValueError, match="X: every tetrahedron needs a positive volume"):
        shape_gradients(X, inverted)
    # a check under jit: JAX raises a RuntimeError, or a ValueError when the executable was cached (on a GPU when
    # the result is ready)
    with pytest.raises((RuntimeError, ValueError), match="X: every tetrahedron needs a positive volume"):
        jax.block_until_ready(jax.jit(shape_gradients)(X, inverted))
    with pytest.raises(ValueError, match=r"points: expected float positions of shape \(k, 3\)"):
        shape_functions(X, T, np.zeros((2, 2)), np.zeros(2, int))
    with pytest.raises(ValueError, match=r"elements: expected integer tet indices of shape \(2,\)"):
        shape_functions(X, T, np.zeros((2, 3)), np.zeros(3, int))
    with pytest.raises(ValueError, match=r"elements: tet indices must lie in \[0, 24\)"):
        shape_functions(X, T, np.zeros((2, 3)), np.array([0, 24]))
    with pytest.raises(ValueError, match="density: expected finite positive values"):
        consistent_mass(X, T, -1.0)
    with pytest.raises(ValueError, match=r"density: expected finite positive values of shape \(\) or \(24,\)"):
        consistent_mass(X, T, np.ones(3))
    with pytest.raises(ValueError, match="T: tet 0 .* has non-positive volume"):
        consistent_mass(X, inverted, 1.0)
    with pytest.raises(ValueError, match=r"density: expected finite positive values of shape \(\) or \(24,\)"):
        lumped_mass(X, T, np.ones(3))
    with pytest.raises(ValueError, match="density: expected finite positive values"):
        lumped_mass(X, T, np.zeros(24))
    with pytest.raises(ValueError, match="X: every tetrahedron needs a positive volume"):
        lumped_mass(X, inverted, 1.0)
    with pytest.raises(ValueError, match=r"b: expected a force density of shape \(3,\) or \(24, 3\)"):
        body_force(X, T, np.ones(2))
    with pytest.raises(ValueError, match="b: non-finite values"):
        body_force(X, T, np.array([0.0, np.nan, 0.0]))
