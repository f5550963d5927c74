"""Batched 3 x 3 Jacobi SVD and symmetric eigendecomposition (xfem/_jacobi3.py) against numpy's LAPACK: the
factorizations rebuild their matrices, the factors are rotations, the singular values and eigenvalues match,
in float64 and float32. The matrices come in jit-compiled batches (XLA's vectorized code, where a decision
computed twice with different rounding would break a factorization; orthogonal F, whose column norms are all
equal, is the case that caught a separate sort), with repeated, zero, tiny and clustered singular values."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

# the batched 3 x 3 eigensolver and SVD behind the neo-Hookean Hessians have no public API
from xfem._jacobi3 import eigh3, svd3

# float32: XLA:GPU's division, square root and hypot are approximate (a few ulp), the CPU's correctly rounded
F32_TOL = 2e-6 if jax.default_backend() == "cpu" else 1e-5
N = 4000  # matrices per family: every family in one batch, compiled once per dtype
SINGULAR_VALUES = (
    [1, 1, 1],
    [2, 1, 1],
    [1, 1, 0],
    [1, 0, 0],
    [0, 0, 0],
    [1, 1 + 1e-8, 1e-8],
    [1, 1e-9, 1e-9],
    [1e-12, 1, 1 + 1e-14],
    [3, 1e-300, 2],
    [1e5, 1, 1e-5],
)


def _matrices(rng, n=N):
    families = [
        rng.standard_normal((n, 3, 3)),
        np.eye(3) + 1e-9 * rng.standard_normal((n, 3, 3)),
        np.where(rng.random((n, 3, 3)) < 0.6, 0.0, np.round(rng.standard_normal((n, 3, 3)))),
    ]
    U, V = (Rotation.random(n, rng=rng).as_matrix() for _ in range(2))
    for s in SINGULAR_VALUES:  # random rotations and signs around prescribed singular values
        signed = np.array(s) * np.where(rng.random((n, 3)) < 0.5, 1.0, -1.0)
        families.append(np.einsum("mij,mj,mkj->mik", U, signed, V))
    return np.concatenate(families)


def _rotation_error(R):
    return np.maximum(np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max((-2, -1)), np.abs(np.linalg.det(R) - 1))


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-14), (np.float32, F32_TOL)])
def test_svd3_is_a_rotation_variant_svd(dtype, tol):
    F = _matrices(np.random.default_rng(0)).astype(dtype)
    U, s, Vt = (np.asarray(a, np.float64) for a in jax.jit(svd3)(jnp.asarray(F)))
    assert U.dtype == s.dtype == Vt.dtype
    F = F.astype(np.float64)
    scale = np.abs(F).max((1, 2))
    assert np.all(np.abs(np.einsum("mij,mj,mjk->mik", U, s, Vt) - F).max((1, 2)) <= tol * scale)
    assert np.all(_rotation_error(U) <= tol) and np.all(_rotation_error(Vt) <= tol)
    reference = np.linalg.svd(F, compute_uv=False)  # decreasing, non-negative
    assert np.all(np.abs(np.abs(s) - reference).max(1) <= 4 * tol * scale)
    assert np.all(s[:, :2] >= 0)
    assert np.all(s[:, 0] >= s[:, 1] - tol * scale) and np.all(s[:, 1] >= np.abs(s[:, 2]) - tol * scale)
    # s_2 carries det F's sign wherever det F is clearly away from zero
    det = np.linalg.det(F)
    clear = np.abs(det) > 1e3 * tol * scale**3
    assert np.all(np.sign(s[clear, 2]) == np.sign(det[clear]))


@pytest.mark.parametrize("dtype, tol", [(np.float64, 1e-14), (np.float32, F32_TOL)])
def test_eigh3_is_an_eigendecomposition(dtype, tol):
    rng = np.random.default_rng(1)
    A = _matrices(rng)
    A = (A + np.swapaxes(A, 1, 2)).astype(dtype)
    w, Q = (np.asarray(a, np.float64) for a in jax.jit(eigh3)(jnp.asarray(A)))
    A = A.astype(np.float64)
    scale = np.abs(A).max((1, 2))
    assert np.all(np.abs(np.einsum("mij,mj,mkj->mik", Q, w, Q) - A).max((1, 2)) <= tol * scale)
    assert np.all(_rotation_error(Q) <= tol)
    assert np.all(np.abs(np.sort(w, 1) - np.linalg.eigvalsh(A)).max(1) <= 4 * tol * scale)
