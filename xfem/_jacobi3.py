"""Batched 3 x 3 rotation-variant SVD and symmetric eigendecomposition by Jacobi rotations, written in jnp for
the closed-form eigensystem of the stable neo-Hookean stiffness (``xfem._neohookean``, [SGK18] sec. 4).

Why not ``jnp.linalg.svd`` / ``eigh``: on CPU they call LAPACK once per 3 x 3 matrix, a few us each, most of
the time of the projected Hessians. Here every step is elementwise over the batch, and XLA fuses it into a few
vector loops (benchmarks/README.md, "Element Hessians").

SVD, ``F = U diag(s) V^T`` with U and V rotations (det +1), ``|s_0| >= |s_1| >= |s_2|``, s_0, s_1 >= 0 and s_2
carrying the sign of det F ([SGK18]'s rotation-variant SVD):

1. one-sided (Hestenes) Jacobi: plane rotations V of the columns of B = F V until they are orthogonal. Each
   rotation is computed from the current columns (``|b_i|^2, |b_j|^2, b_i . b_j``), not from F^T F, so small
   singular values keep their relative accuracy. Of the two rotations that orthogonalize a pair (90 degrees
   apart), the one that leaves the longer column first (``_sorting_rotation``): the sweep's pair order (0, 1),
   (0, 2), (1, 2) is a sorting network, so B's columns end sorted by decreasing norm and a zero column can only
   come last;
2. QR of B by Givens rotations, B = U R: U is a rotation, R is diagonal up to rounding (B's columns are
   orthogonal), R_00, R_11 >= 0; s = diag(R).

Symmetric eigendecomposition, ``A = Q diag(w) Q^T`` with Q a rotation (eigenvalues unsorted): cyclic two-sided
Jacobi with the smaller rotation angle (Rutishauser's formulas).

Every decision (the sign of a rotation angle, a swap, a zero pivot) is taken inside the computation of a
rotation's (c, s), which has square roots and divisions: XLA's fusion does not copy such expensive values into
the several kernels that use them, so every kernel applies the same rotation. Cheap values it may recompute in
each consumer kernel instead, with rounding that can differ between kernels; a first version sorted the columns
by a separate norm comparison, which XLA duplicated, and at equal norms (orthogonal F) the comparison came out
differently for B and V in 5% of the cases. For the same reason the sweeps run in a ``fori_loop``, whose carry
is materialized each sweep: fully unrolled, XLA recomputed the chains of cheap rotation products in many
kernels, and the projected Hessians took over 20x as long. ``tests/xfem/test_jacobi3.py``
checks the factorizations on such matrices in compiled batches.

Sweeps: a fixed count, cyclic Jacobi converges quadratically. Measured in float64 on 3 x 10^6 random,
orthogonal, rank-deficient, clustered and sparse matrices: with 5 SVD sweeps (4 are not enough, residual
5e-11) the residual ``|F - U diag(s) V^T| / max|F|`` stays below 3e-15, and with 4 eigh sweeps
``|A - Q diag(w) Q^T| / max|A|`` below 2.2e-15.

No derivative rules: ``_neohookean`` differentiates its projection by the Daleckii-Krein formula, which uses
the eigensystem's values, not their derivatives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

_SVD_SWEEPS = 5
_EIGH_SWEEPS = 4
_PAIRS = ((0, 1), (0, 2), (1, 2))


def _symmetric_rotation(alpha, beta, gamma):
    """(c, s, t) of the Jacobi rotation that zeroes the off-diagonal entry ``gamma`` of the symmetric 2 x 2
    block ``[[alpha, gamma], [gamma, beta]]`` (Rutishauser): ``t = s / c``, the tangent of the smaller angle."""
    nonzero = gamma != 0
    zeta = (beta - alpha) / (2 * jnp.where(nonzero, gamma, 1))
    t = jnp.where(zeta >= 0, 1, -1) / (jnp.abs(zeta) + jnp.hypot(1, zeta))
    t = jnp.where(nonzero, t, 0)
    c = 1 / jnp.sqrt(1 + t * t)
    return c, c * t, t


def _sorting_rotation(alpha, beta, gamma):
    """(c, s) of the plane rotation of columns (b_i, b_j) -> (c b_i - s b_j, s b_i + c b_j) that makes them
    orthogonal with ``|b_i'| >= |b_j'|``, from ``alpha = |b_i|^2``, ``beta = |b_j|^2``, ``gamma = b_i . b_j``.

    Of the two rotations that zero gamma (90 degrees apart, tan t with ``t^2 + 2 zeta t - 1 = 0``,
    ``zeta = (beta - alpha) / (2 gamma)``), the one with ``t gamma <= (alpha - beta) / 2``, since
    ``|b_i'|^2 - |b_j'|^2 = alpha - beta - 2 t gamma``: ``t = -sign(gamma) m``, ``m = w + sqrt(1 + w^2)``,
    ``w = (beta - alpha) / (2 |gamma|)``. gamma = 0 gives w = +-inf: no rotation, or a swap (c = 0) when
    beta > alpha."""
    d = beta - alpha
    magnitude = 2 * jnp.abs(gamma)
    w = jnp.where(magnitude > 0, d / jnp.where(magnitude > 0, magnitude, 1), jnp.where(d > 0, jnp.inf, -jnp.inf))
    root = jnp.hypot(1, w)
    m = jnp.where(w >= 0, w + root, 1 / (root - w))  # no cancellation for w < 0
    r = jnp.where(m <= 1, m, 1 / m)  # min(m, 1/m), in [0, 1]
    q = 1 / jnp.sqrt(1 + r * r)
    c, s = jnp.where(m <= 1, q, r * q), jnp.where(m <= 1, r * q, q)
    return c, jnp.where(gamma >= 0, -s, s)


def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _rotate(cols, i, j, c, s):
    """Columns i, j of a matrix given as a list of columns, rotated: ``(c b_i - s b_j, s b_i + c b_j)``."""
    bi, bj = cols[i], cols[j]
    cols[i] = [c * x - s * y for x, y in zip(bi, bj)]
    cols[j] = [s * x + c * y for x, y in zip(bi, bj)]


def svd3(F):
    """Rotation-variant SVD of a batch of 3 x 3 matrices (module docstring).

    Args:
        F: (..., 3, 3) floating matrices.
    Returns:
        U (..., 3, 3), s (..., 3), Vt (..., 3, 3) with ``F = U diag(s) Vt``, U and Vt rotations,
        ``s_0 >= s_1 >= |s_2|`` and ``s_0 s_1 s_2 = det F``.
    """
    one, zero = jnp.ones(F.shape[:-2], F.dtype), jnp.zeros(F.shape[:-2], F.dtype)
    B = [[F[..., r, k] for r in range(3)] for k in range(3)]  # columns of F
    V = [[one if r == k else zero for r in range(3)] for k in range(3)]

    def sweep(_, carry):
        B, V = [list(col) for col in carry[0]], [list(col) for col in carry[1]]
        for i, j in _PAIRS:
            c, s = _sorting_rotation(_dot(B[i], B[i]), _dot(B[j], B[j]), _dot(B[i], B[j]))
            _rotate(B, i, j, c, s)
            _rotate(V, i, j, c, s)
        return B, V

    B, V = jax.lax.fori_loop(0, _SVD_SWEEPS, sweep, (B, V))
    # QR by Givens on rows: R = G B, U = G^T; rows (p, k) rotated to zero R[k, col]
    R = [[B[k][r] for k in range(3)] for r in range(3)]  # rows
    U = [[one if r == k else zero for r in range(3)] for k in range(3)]  # columns
    for p, k, col in ((0, 1, 0), (0, 2, 0), (1, 2, 1)):
        a, b = R[p][col], R[k][col]
        r = jnp.hypot(a, b)
        nonzero = r != 0
        c = jnp.where(nonzero, a / jnp.where(nonzero, r, 1), 1)
        s = jnp.where(nonzero, b / jnp.where(nonzero, r, 1), 0)
        rp, rk = R[p], R[k]
        R[p] = [c * x + s * y for x, y in zip(rp, rk)]
        R[k] = [-s * x + c * y for x, y in zip(rp, rk)]
        _rotate(U, p, k, c, -s)
    s = jnp.stack([R[0][0], R[1][1], R[2][2]], axis=-1)
    U = jnp.stack([jnp.stack(col, axis=-1) for col in U], axis=-1)
    Vt = jnp.stack([jnp.stack(col, axis=-1) for col in V], axis=-2)
    return U, s, Vt


def eigh3(A):
    """Eigendecomposition of a batch of symmetric 3 x 3 matrices by cyclic Jacobi (module docstring).

    Args:
        A: (..., 3, 3) symmetric floating matrices (the upper triangle is read).
    Returns:
        w (..., 3) eigenvalues (unsorted) and Q (..., 3, 3), a rotation whose columns are the eigenvectors:
        ``A = Q diag(w) Q^T``.
    """
    one, zero = jnp.ones(A.shape[:-2], A.dtype), jnp.zeros(A.shape[:-2], A.dtype)
    a = {(r, k): A[..., r, k] for r in range(3) for k in range(r, 3)}
    Q = [[one if r == k else zero for r in range(3)] for k in range(3)]  # columns

    def sweep(_, carry):
        a, Q = dict(carry[0]), [list(col) for col in carry[1]]
        for p, q in _PAIRS:
            r = 3 - p - q
            c, s, t = _symmetric_rotation(a[p, p], a[q, q], a[p, q])
            apq = a[p, q]
            a[p, p], a[q, q], a[p, q] = a[p, p] - t * apq, a[q, q] + t * apq, jnp.zeros_like(apq)
            arp, arq = a[min(r, p), max(r, p)], a[min(r, q), max(r, q)]
            a[min(r, p), max(r, p)], a[min(r, q), max(r, q)] = c * arp - s * arq, s * arp + c * arq
            _rotate(Q, p, q, c, s)
        return a, Q

    a, Q = jax.lax.fori_loop(0, _EIGH_SWEEPS, sweep, (a, Q))
    w = jnp.stack([a[0, 0], a[1, 1], a[2, 2]], axis=-1)
    return w, jnp.stack([jnp.stack(col, axis=-1) for col in Q], axis=-1)
