"""align_points (Horn's quaternion method) against known rigid motions from scipy, batched, weighted,
differentiated (against central finite differences) and rejecting bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import jaxcga as cga

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
seeds = st.integers(0, 2**32 - 1)
N = 10

_align_jit = jax.jit(cga.align_points)
_apply_jit = jax.jit(cga.apply_to_points)


def _a(x):
    return np.asarray(x, dtype=np.float64)


def _problem(rng, n=N, batch=()):
    src = rng.normal(size=batch + (n, 3)) * 2
    rots = Rotation.random(int(np.prod(batch)) if batch else None, rng=rng)
    t = rng.normal(size=batch + (3,)) * 3
    mats = rots.as_matrix().reshape(batch + (3, 3))
    tgt = np.einsum("...ij,...nj->...ni", mats, src) + t[..., None, :]
    return src, tgt, rots, t


@SETTINGS
@given(seeds)
def test_align_points_recovers_rigid_motion(seed):
    rng = np.random.default_rng(seed)
    src, tgt, rot, t = _problem(rng)
    M = _align_jit(src, tgt)
    assert M.blades == cga.KINDS["motor"]
    np.testing.assert_allclose(_a(_apply_jit(M, src)), tgt, atol=1e-12)
    H = _a(cga.versor_to_matrix(M))
    np.testing.assert_allclose(H[:3, :3], rot.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(H[:3, 3], t, atol=1e-12)
    # The rotor is unit and has a non-negative scalar part.
    r, _ = cga.motor_rotor_translation(M)
    np.testing.assert_allclose(np.linalg.norm(_a(r.values)), 1.0, rtol=1e-13)
    assert float(r["1"]) >= 0


@pytest.mark.parametrize("axis", [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [1.0, 1.0, 1.0]])
def test_align_points_half_turns(axis):
    rng = np.random.default_rng(1)
    src = rng.normal(size=(N, 3))
    rot = Rotation.from_rotvec(np.pi * np.asarray(axis) / np.linalg.norm(axis))
    tgt = rot.apply(src) + np.array([1.0, -2.0, 0.5])
    M = _align_jit(src, tgt)
    np.testing.assert_allclose(_a(_apply_jit(M, src)), tgt, atol=1e-12)


def test_align_points_minimal_three_points_and_identity():
    rng = np.random.default_rng(2)
    src = rng.normal(size=(3, 3))
    rot = Rotation.from_rotvec([0.3, -1.0, 2.0])
    tgt = rot.apply(src) + np.array([0.0, 1.0, 2.0])
    np.testing.assert_allclose(_a(_apply_jit(_align_jit(src, tgt), src)), tgt, atol=1e-12)
    M = _align_jit(src, src)
    np.testing.assert_allclose(_a(M.values), np.r_[1.0, np.zeros(7)], atol=1e-14)


def test_align_points_batched():
    rng = np.random.default_rng(3)
    src, tgt, rots, t = _problem(rng, batch=(5,))
    M = _align_jit(src, tgt)
    assert M.batch_shape == (5,)
    np.testing.assert_allclose(_a(_apply_jit(_expand(M), src)), tgt, atol=1e-12)
    H = _a(cga.versor_to_matrix(M))
    np.testing.assert_allclose(H[:, :3, :3], rots.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(H[:, :3, 3], t, atol=1e-12)
    # Each problem solved alone gives the same motor.
    for k in range(5):
        np.testing.assert_allclose(_a(_align_jit(src[k], tgt[k]).values), _a(M.values)[k], atol=1e-12)


def _expand(M):
    """Batch (5,) motors to (5, 1) so that they broadcast against (5, n) points."""
    return cga.Multivector(_a(M.values)[:, None, :], M.blades)


@jax.jit
def _weighted_residual(src, tgt, w, perturbations):
    """sum_i w_i |M(src_i) - tgt_i|^2 for the weighted fit M and for M exp(b) with each b given."""
    M = cga.align_points(src, tgt, w)
    perturbed = M * cga.exp(cga.Multivector(perturbations, cga.MOTOR_GENERATOR))  # batch
    moved = cga.apply_to_points(cga.Multivector(perturbed.values[:, None, :], perturbed.blades), src)
    return (
        jnp.sum(w * jnp.sum((cga.apply_to_points(M, src) - tgt) ** 2, axis=-1)),
        jnp.sum(w[None] * jnp.sum((moved - tgt[None]) ** 2, axis=-1), axis=-1),
    )


def test_align_points_weights():
    rng = np.random.default_rng(4)
    src, tgt, rot, t = _problem(rng)
    # Outliers with zero weight do not matter.
    tgt_bad = tgt.copy()
    tgt_bad[:3] += rng.normal(size=(3, 3)) * 5
    w = np.r_[np.zeros(3), np.ones(N - 3)]
    M = _align_jit(src, tgt_bad, w)
    np.testing.assert_allclose(_a(_apply_jit(M, src[3:])), tgt[3:], atol=1e-12)
    # Without the weights they do.
    M_unweighted = _align_jit(src, tgt_bad)
    assert np.abs(_a(_apply_jit(M_unweighted, src[3:])) - tgt[3:]).max() > 1e-3
    # Weights are relative: scaling them changes nothing.
    np.testing.assert_allclose(_a(_align_jit(src, tgt_bad, 7.0 * w).values), _a(M.values), atol=1e-13)
    # The weighted fit minimizes the weighted residual: small perturbations M exp(b) of it are worse.
    w2 = rng.uniform(0.1, 2.0, size=N)
    base, perturbed = _weighted_residual(src, tgt_bad, w2, rng.normal(size=(6, 6)) * 1e-3)
    assert np.all(_a(perturbed) > float(base))


def test_align_points_rejects_bad_input():
    src = np.zeros((N, 3))
    with pytest.raises(ValueError):
        cga.align_points(src, np.zeros((N + 1, 3)))  # different n
    with pytest.raises(ValueError):
        cga.align_points(src, np.zeros((N, 2)))
    with pytest.raises(ValueError):
        cga.align_points(np.zeros(3), np.zeros(3))  # no point axis
    with pytest.raises(ValueError):
        cga.align_points(src, src, np.ones(N - 1))  # weights of the wrong length


@pytest.mark.slow
def test_align_points_is_differentiable():
    rng = np.random.default_rng(5)
    src, clean, _, _ = _problem(rng)
    tgt = clean + rng.normal(size=clean.shape) * 0.1  # noisy: a non-trivial fit
    probe = rng.normal(size=(4, 3))

    def loss(target):
        M = cga.align_points(jnp.asarray(src), target)
        return jnp.sum(cga.apply_to_points(M, jnp.asarray(probe)) ** 2)

    value_and_grad = jax.jit(jax.value_and_grad(loss))
    val, g = value_and_grad(jnp.asarray(tgt))
    g = _a(g)
    assert np.isfinite(float(val)) and np.all(np.isfinite(g))
    h = 1e-6
    for _ in range(3):
        d = rng.normal(size=tgt.shape)
        fd = (
            float(value_and_grad(jnp.asarray(tgt + h * d))[0]) - float(value_and_grad(jnp.asarray(tgt - h * d))[0])
        ) / (2 * h)
        np.testing.assert_allclose(np.sum(g * d), fd, rtol=1e-6, atol=1e-6 * max(1.0, abs(fd)))
    # At noise-free data (an exact fit) the gradient is finite too.
    _, g0 = value_and_grad(jnp.asarray(clean))
    assert np.all(np.isfinite(_a(g0)))
