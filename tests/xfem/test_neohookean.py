"""Stable neo-Hookean (xfem/_neohookean.py): rest state, stress and stiffness against autodiff and finite
differences, the projection against a numpy eigendecomposition, linear elasticity at small strain (Lamé
mapping, Young's modulus and Poisson's ratio under uniaxial stress), isotropy, inverted and degenerate
elements, float32, per-element parameters, bad input.

Batches have fixed sizes (16 deformation gradients, M = 8 tets) so that each function compiles once."""

import functools
from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from xfem import (
    element_energy,
    element_gradient_hessian,
    lame,
    stable_neohookean_energy,
    stable_neohookean_pk1,
)

E, NU = 1e6, 0.4  # the XFEM paper's material (sec. 5)
MU, LAM = lame(E, NU)
M = 8

# degenerate and inverted deformation gradients: repeated singular values, reflections, rank deficient, zero
SPECIAL = np.array(
    [
        np.eye(3),
        np.diag([1.0, 1.0, -1.0]),
        -np.eye(3),
        np.zeros((3, 3)),
        np.diag([2.0, 2.0, 0.5]),
        np.diag([1.0, 0.0, 0.0]),
        np.diag([0.3, 0.3, -0.3]),
        Rotation.from_rotvec([0.3, -1.0, 2.0]).as_matrix() * 1.5,
    ]
)


def _random_F(rng, m, spread=0.6):
    F = np.eye(3) + spread * rng.standard_normal((m, 3, 3))
    F[: m // 2] *= -np.sign(np.linalg.det(F[: m // 2]))[:, None, None]  # the first half inverted
    return F


def _tets(rng, m=M):
    """Well-shaped random rest tets: shape-function gradients (m, 4, 3), volumes (m,), rest positions (m, 4, 3)."""
    regular = np.array([[1.0, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1]]) / np.sqrt(8)
    R = Rotation.random(m, rng=rng).as_matrix()
    X = np.einsum("mij,maj->mai", R, regular + 0.15 * rng.standard_normal((m, 4, 3))) * rng.uniform(0.5, 2, (m, 1, 1))
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=-1)
    Dinv = np.linalg.inv(Dm)  # F = Ds Dm^-1: node a > 0 has gradient row a - 1 of Dm^-1
    grads = np.concatenate([-Dinv.sum(1, keepdims=True), Dinv], axis=1)
    return grads, np.abs(np.linalg.det(Dm)) / 6, X


def _deformed(F, X):
    """Node positions with deformation gradient F (m, 3, 3) from rest positions X (m, 4, 3)."""
    return np.einsum("mij,maj->mai", F, X)


def _sandwich_np(grads, A, volumes):
    """vol B^T A B with B = dvec(F)/dx (9 x 12) built explicitly."""
    B = np.einsum("kl,maj->mkjal", np.eye(3), grads).reshape(-1, 9, 12)
    return volumes[:, None, None] * np.swapaxes(B, 1, 2) @ A @ B


def _density(f):
    return stable_neohookean_energy(f, MU, LAM)


_pk1_auto = jax.jit(jax.vmap(jax.grad(_density)))
# dP/dF by autodiff of the energy, independent of the closed form and of its eigensystem
_stiffness_auto = jax.jit(lambda F: jax.vmap(jax.hessian(_density))(F).reshape(-1, 9, 9))


@functools.partial(jax.jit, static_argnames="project")
def _hessian_jvp(x, grads, vol, young, dx, dyoung, project):
    def hessian(x, young):
        return element_gradient_hessian(x, grads, vol, *lame(young, NU), project=project)[1]

    return jax.jvp(hessian, (x, young), (dx, dyoung))


@pytest.fixture(scope="module")
def tets():
    return _tets(np.random.default_rng(0))


def test_lame_closed_form_and_errors():
    mu, lam = lame(2.6, 0.3)
    assert mu == pytest.approx(1.0) and lam == pytest.approx(2.6 * 0.3 / (1.3 * 0.4))
    mu, lam = lame(np.array([1.0, 2.0]), 0.25)
    np.testing.assert_allclose(mu, [0.4, 0.8])
    np.testing.assert_allclose(lam, [0.4, 0.8])
    assert jax.grad(lambda e: lame(e, 0.3)[0])(2.0) == pytest.approx(1 / 2.6)
    bad = [
        (0.0, 0.3, "young"),
        (-1.0, 0.3, "young"),
        (np.array([1.0, -2.0]), 0.3, "young"),
        (1.0, 0.5, "poisson"),
        (1.0, -1.0, "poisson"),
        (1.0, np.nan, "poisson"),
    ]
    for young, poisson, name in bad:
        with pytest.raises(ValueError, match=name):
            lame(young, poisson)
    with pytest.raises(RuntimeError, match="poisson"):
        jax.block_until_ready(jax.jit(lame)(1.0, 0.7))


def test_rest_state_and_rigid_motions_are_zero_energy_and_stress_free():
    # the legacy keyword keeps the seeded stream (scipy's signature names only rng)
    F = jnp.asarray(np.concatenate([np.eye(3)[None], Rotation.random(15, random_state=1).as_matrix()]))  # pyright: ignore[reportCallIssue]
    psi, P = stable_neohookean_energy(F, MU, LAM), stable_neohookean_pk1(F, MU, LAM)
    assert float(psi[0]) == 0.0 and float(jnp.abs(P[0]).max()) == 0.0  # exactly, at F = I
    assert float(jnp.abs(psi).max()) < 1e-9 * E and float(jnp.abs(P).max()) < 1e-9 * E


def test_pk1_is_the_gradient_of_the_energy():
    F = jnp.asarray(np.concatenate([_random_F(np.random.default_rng(2), 8), SPECIAL]))
    assert int(jnp.sum(jnp.linalg.det(F) < 0)) >= 8
    np.testing.assert_allclose(stable_neohookean_pk1(F, MU, LAM), _pk1_auto(F), rtol=1e-12, atol=1e-12 * E)


def test_uniaxial_strain_closed_form():
    # F = diag(s, 1, 1) in the paper's eq. 14, by hand, with its alpha and the rest constant Psi_0 written out:
    # I_C = s^2 + 2, J = s, Psi = mu'/2 (s^2 - 1) + lam'/2 (s - alpha)^2 - mu'/2 log(s^2 + 3) - Psi_0
    mu_s, lam_s = 4 / 3 * MU, LAM + 5 / 6 * MU
    alpha = 1 + mu_s / lam_s - mu_s / (4 * lam_s)
    psi0 = lam_s / 2 * (1 - alpha) ** 2 - mu_s / 2 * np.log(4)
    s = np.linspace(-1, 3, 16)  # inverted, collapsed (s = 0 is not in it, s = 1/15 is close), stretched
    psi = mu_s / 2 * (s**2 - 1) + lam_s / 2 * (s - alpha) ** 2 - mu_s / 2 * np.log(s**2 + 3) - psi0
    p11 = mu_s * s + lam_s * (s - alpha) - mu_s * s / (s**2 + 3)  # d psi / ds
    p22 = mu_s - mu_s / (s**2 + 3) + lam_s * (s - alpha) * s  # (cof F)_22 = s
    F = jnp.asarray(np.einsum("m,ij->mij", s, np.diag([1.0, 0, 0])) + np.diag([0, 1.0, 1.0]))
    P = np.asarray(stable_neohookean_pk1(F, MU, LAM))
    np.testing.assert_allclose(stable_neohookean_energy(F, MU, LAM), psi, rtol=1e-10, atol=1e-9 * E)
    np.testing.assert_allclose(P[:, 0, 0], p11, rtol=1e-12, atol=1e-9 * E)
    np.testing.assert_allclose(P[:, 1, 1], p22, rtol=1e-12, atol=1e-9 * E)
    np.testing.assert_allclose(P[:, 2, 2], p22, rtol=1e-12, atol=1e-9 * E)
    assert np.abs(P - P * np.eye(3)).max() == 0.0


def test_small_strain_is_linear_elasticity():
    rng = np.random.default_rng(3)
    eps = rng.standard_normal((4, 3, 3))
    eps = (eps + np.swapaxes(eps, 1, 2)) / 2
    sizes = np.array([1e-2, 1e-3, 1e-4, 1e-5])
    strain = (sizes[:, None, None, None] * eps).reshape(16, 3, 3)
    P = np.asarray(stable_neohookean_pk1(jnp.asarray(np.eye(3) + strain), MU, LAM))
    linear = 2 * MU * strain + LAM * np.trace(strain, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    errors = np.abs(P - linear).max(axis=(1, 2)).reshape(4, 4)
    ratios = errors[:-1] / errors[1:]  # error O(|eps|^2): 10x smaller strain, 100x smaller error
    assert np.all((ratios > 90) & (ratios < 110)), ratios
    assert np.all(errors < 30 * E * sizes[:, None] ** 2)


def test_uniaxial_stress_recovers_young_and_poisson():
    # pull along x, lateral faces free: P_22(diag(1 + e, 1 + d, 1 + d)) = 0 fixes d; then P_11 / e -> E, -d / e -> nu
    def stress(e, d):
        return np.asarray(stable_neohookean_pk1(jnp.diag(jnp.asarray([1 + e, 1 + d, 1 + d])), MU, LAM))

    for e in (1e-4, 1e-5):
        # scipy is unannotated: pyright takes rtol's type from its default and sees full_output's tuple
        d = cast(float, brentq(lambda d: stress(e, d)[1, 1], -e, e, xtol=1e-16, rtol=1e-15))  # pyright: ignore[reportArgumentType]
        assert stress(e, d)[0, 0] / e == pytest.approx(E, rel=10 * e)
        assert -d / e == pytest.approx(NU, rel=10 * e)


def test_isotropy_and_frame_indifference():
    F = jnp.asarray(_random_F(np.random.default_rng(4), 16))
    # the legacy keyword keeps the seeded stream (scipy's signature names only rng)
    R = jnp.asarray(Rotation.random(16, random_state=5).as_matrix())  # pyright: ignore[reportCallIssue]
    psi, P = stable_neohookean_energy(F, MU, LAM), stable_neohookean_pk1(F, MU, LAM)
    scale = float(jnp.abs(P).max())
    np.testing.assert_allclose(stable_neohookean_energy(R @ F, MU, LAM), psi, rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(stable_neohookean_pk1(R @ F, MU, LAM), R @ P, atol=1e-12 * scale)
    np.testing.assert_allclose(stable_neohookean_energy(F @ R, MU, LAM), psi, rtol=1e-10, atol=1e-12 * scale)
    np.testing.assert_allclose(stable_neohookean_pk1(F @ R, MU, LAM), P @ R, atol=1e-12 * scale)


def test_element_gradient_and_hessian_match_autodiff(tets):
    grads, vol, X = tets
    rng = np.random.default_rng(6)
    x = jnp.asarray(_deformed(_random_F(rng, M), X) + rng.normal(0, 0.05, (M, 4, 3)))

    @jax.jit
    def autodiff(x):
        def energy(xe, ge, ve):
            return element_energy(xe[None], ge[None], ve[None], MU, LAM)[0]

        return jax.vmap(jax.grad(energy))(x, grads, vol), jax.vmap(jax.hessian(energy))(x, grads, vol)

    g, H = element_gradient_hessian(x, grads, vol, MU, LAM, project=False)
    g_auto, H_auto = autodiff(x)
    gs, Hs = np.abs(g).max(1, keepdims=True), np.abs(H).max((1, 2), keepdims=True)
    assert np.all(np.abs(g - g_auto.reshape(M, 12)) <= 1e-11 * gs)
    assert np.all(np.abs(H - H_auto.reshape(M, 12, 12)) <= 1e-11 * Hs)
    np.testing.assert_allclose(H, np.swapaxes(H, 1, 2), atol=1e-13 * Hs.max())


@pytest.mark.slow
def test_element_gradient_and_hessian_finite_differences(tets):
    # one inverted tet, repeated M times (the batch size the element functions are compiled for)
    grads, vol, X = (np.repeat(a[:1], M, 0) for a in tets)
    x0 = _deformed(_random_F(np.random.default_rng(7), 2), X[:2])[0]
    assert np.linalg.det(np.einsum("ai,aj->ij", x0, grads[0])) < 0
    g, H = element_gradient_hessian(jnp.asarray(np.repeat(x0[None], M, 0)), grads, vol, MU, LAM, project=False)
    h = 1e-6
    plus = np.repeat(x0[None], 12, 0) + h * np.eye(12).reshape(12, 4, 3)
    minus = plus - 2 * h * np.eye(12).reshape(12, 4, 3)

    rows = [*range(8), *range(12, 16)]  # x (12, 4, 3) is evaluated as x[0:8] and x[4:12]

    def energy(x):
        return np.concatenate([element_energy(x[k : k + M], grads, vol, MU, LAM) for k in (0, 4)])[rows]

    def gradient(x):
        return np.concatenate([element_gradient_hessian(x[k : k + M], grads, vol, MU, LAM)[0] for k in (0, 4)])[rows]

    fd_g = (energy(plus) - energy(minus)) / (2 * h)
    fd_H = (gradient(plus) - gradient(minus)) / (2 * h)
    np.testing.assert_allclose(g[0], fd_g, rtol=1e-6, atol=1e-7 * np.abs(fd_g).max())
    np.testing.assert_allclose(H[0], fd_H, rtol=1e-6, atol=1e-7 * np.abs(fd_H).max())


def test_projected_hessian_is_the_psd_part(tets):
    grads, vol, X = tets
    rng = np.random.default_rng(8)
    Fs = [_random_F(rng, M, 1.0), SPECIAL, np.eye(3) + 0.02 * rng.standard_normal((M, 3, 3))]
    A = np.asarray(_stiffness_auto(jnp.asarray(np.concatenate(Fs))))
    w, Q = np.linalg.eigh(A)
    scale = np.abs(A).max((1, 2)) + E
    assert np.all(np.abs(A - np.swapaxes(A, 1, 2)).max((1, 2)) < 1e-12 * scale)
    assert np.sum(w.min(1) < -1e-6 * scale) >= 8  # the projection has work to do
    A_plus = np.einsum("mik,mk,mjk->mij", Q, np.maximum(w, 0), Q)
    for k, F in enumerate(Fs):
        H = np.asarray(element_gradient_hessian(jnp.asarray(_deformed(F, X)), grads, vol, MU, LAM)[1])
        H_ref = _sandwich_np(np.asarray(grads), A_plus[k * M : (k + 1) * M], np.asarray(vol))
        Hs = np.abs(H_ref).max((1, 2)) + 1e-12 * E
        assert np.all(np.abs(H - H_ref).max((1, 2)) <= 1e-10 * Hs)
        assert np.all(np.linalg.eigvalsh(H).min(1) >= -1e-9 * Hs)
        # where dP/dF is already PSD (some near rest), the projection changes nothing
        psd = w[k * M : (k + 1) * M].min(1) >= 0
        H_unprojected = np.asarray(
            element_gradient_hessian(jnp.asarray(_deformed(F, X)), grads, vol, MU, LAM, project=False)[1]
        )
        assert np.all(np.abs(H - H_unprojected)[psd].max((1, 2)) <= 1e-10 * Hs[psd])
    assert np.sum(w[2 * M :].min(1) >= 0) >= 2


@pytest.mark.slow
def test_degenerate_and_inverted_elements_stay_finite(tets):
    grads, vol, X = tets
    x = jnp.asarray(_deformed(SPECIAL, X))
    dx = jnp.asarray(np.random.default_rng(9).standard_normal((M, 4, 3)))
    assert np.isfinite(element_energy(x, grads, vol, MU, LAM)).all()
    assert np.isfinite(_pk1_auto(jnp.asarray(np.concatenate([SPECIAL, SPECIAL])))).all()
    for project in (True, False):
        g, H = element_gradient_hessian(x, grads, vol, MU, LAM, project=project)
        assert np.isfinite(g).all() and np.isfinite(H).all()
    # derivatives of the projected Hessian along x and Young's modulus (third derivatives; material fitting),
    # forward and reverse through the projection's custom JVP (the unprojected one is plain autodiff of
    # polynomials and 1 / (I_C + 1))
    assert np.isfinite(_hessian_jvp(x, grads, vol, E, dx, 1e5, True)[1]).all()
    total = jax.jit(jax.grad(lambda x, e: element_gradient_hessian(x, grads, vol, *lame(e, NU))[1].sum(), (0, 1)))
    d_x, d_young = total(x, E)
    assert np.isfinite(d_x).all() and np.isfinite(d_young)


@pytest.mark.slow
def test_projected_hessian_derivative(tets):
    # the custom JVP (Daleckii-Krein) against central differences at generic states, inverted ones included
    grads, vol, X = tets
    rng = np.random.default_rng(10)
    x = jnp.asarray(_deformed(_random_F(rng, M), X))
    dx = jnp.asarray(rng.standard_normal((M, 4, 3)))
    tangent = _hessian_jvp(x, grads, vol, E, dx, 1e5, True)[1]
    h = 1e-6
    fd = (
        element_gradient_hessian(x + h * dx, grads, vol, *lame(E + h * 1e5, NU))[1]
        - element_gradient_hessian(x - h * dx, grads, vol, *lame(E - h * 1e5, NU))[1]
    ) / (2 * h)
    assert np.all(np.abs(tangent - fd) <= 1e-6 * np.abs(fd).max((1, 2), keepdims=True))


@pytest.mark.slow
def test_per_element_parameters_and_float32(tets):
    grads, vol, X = tets
    rng = np.random.default_rng(11)
    x = jnp.asarray(_deformed(_random_F(rng, M), X))
    young = rng.uniform(1e5, 1e7, M)
    mu, lam = (np.asarray(p) for p in lame(young, NU))
    g, H = element_gradient_hessian(x, grads, vol, mu, lam)
    for e in (0, 5):
        ge, He = element_gradient_hessian(x, grads, vol, float(mu[e]), float(lam[e]))
        np.testing.assert_allclose(g[e], ge[e], rtol=1e-12, atol=1e-12 * np.abs(ge[e]).max())
        np.testing.assert_allclose(H[e], He[e], rtol=1e-12, atol=1e-12 * np.abs(He[e]).max())
    # at fixed nu the energy is linear in E: d(total energy)/d(young_e) = energy_e / young_e
    energy = element_energy(x, grads, vol, mu, lam)
    d_young = jax.jit(jax.grad(lambda y: element_energy(x, grads, vol, *lame(y, NU)).sum()))(jnp.asarray(young))
    np.testing.assert_allclose(d_young, energy / young, rtol=1e-12)

    x32, grads32, vol32 = (jnp.asarray(a, jnp.float32) for a in (x, grads, vol))
    g32, H32 = element_gradient_hessian(x32, grads32, vol32, mu, lam)
    assert g32.dtype == H32.dtype == jnp.float32
    assert element_energy(x32, grads32, vol32, mu, lam).dtype == jnp.float32
    np.testing.assert_allclose(g32, g, rtol=1e-3, atol=1e-4 * np.abs(g).max())
    Hs = np.abs(H).max((1, 2))
    assert np.all(np.abs(np.asarray(H32, np.float64) - H).max((1, 2)) <= 1e-4 * Hs)
    assert np.all(np.linalg.eigvalsh(np.asarray(H32, np.float64)).min(1) >= -1e-5 * Hs)


def test_bad_input(tets):
    grads, vol, X = (jnp.asarray(a) for a in tets)
    with pytest.raises(ValueError, match="F:"):
        stable_neohookean_energy(jnp.eye(2), MU, LAM)
    with pytest.raises(ValueError, match="F:"):
        stable_neohookean_pk1(jnp.eye(3, dtype=jnp.int32), MU, LAM)
    with pytest.raises(ValueError, match="mu:"):
        stable_neohookean_energy(jnp.zeros((4, 3, 3)), jnp.ones(3), LAM)
    with pytest.raises(ValueError, match="mu:"):
        stable_neohookean_energy(jnp.eye(3), -1.0, LAM)
    with pytest.raises(ValueError, match="lam:"):
        stable_neohookean_pk1(jnp.eye(3), 1.0, -1.0)
    with pytest.raises(ValueError, match="x:"):
        element_energy(X[:, :3], grads, vol, MU, LAM)
    with pytest.raises(ValueError, match="grads:"):
        element_gradient_hessian(X, grads[:-1], vol, MU, LAM)
    with pytest.raises(ValueError, match="volumes:"):
        element_gradient_hessian(X, grads, vol.astype(jnp.float32), MU, LAM)
    with pytest.raises(ValueError, match="lam:"):
        element_gradient_hessian(X, grads, vol, MU, jnp.ones(M - 1))
    with pytest.raises(RuntimeError, match="mu:"):
        jax.block_until_ready(jax.jit(lambda mu: element_energy(X, grads, vol, mu, LAM))(-1.0))
