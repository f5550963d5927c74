"""Jacobi-preconditioned conjugate gradients on a CSR matrix, compiled by numba, without the GIL.

The Newton solve of a large FEM step (``xfem._backward_euler._host_newton_direction``, through
``_jaxcga_shared.sparse.host_pcg``) runs on the host on a CPU. As a numpy
loop each CG iteration is ~14 array operations, and each releases the GIL and takes it back: thousands of
hand-overs per step, each a chance to wait for another thread (the background cuts' thread, the next capacity
level's compilation, the application's own threads). Here the iteration
is three fused loops (the CSR product with p.Ap, the updates with r.z and r.r, the new direction) in one call
with ``nogil=True``: other threads run beside it, and the CG never waits for them.

Same algorithm and stopping rule as the numpy loop it replaces: x_0 = 0, stop when ||r||^2 <= rtol^2 ||b||^2 or
after n iterations; only the order of the sums' additions differs (``fastmath`` reassociation, for vectorized
sums; NaN and infinity keep their IEEE meaning). It is faster than the numpy loop too (benchmarks/README.md,
"FEM linear solver").
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True, fastmath={"reassoc", "contract"})
def _pcg(data, indptr, indices, inverse_diagonal, b, rtol):  # pragma: no cover (compiled)
    n = b.shape[0]
    x = np.zeros(n)
    r = b.copy()
    z = inverse_diagonal * r
    p = z.copy()
    Ap = np.empty(n)
    rz = 0.0
    rr = 0.0
    for i in range(n):
        rz += r[i] * z[i]
        rr += r[i] * r[i]
    stop = rtol * rtol * rr
    for _ in range(max(n, 1)):
        if rr <= stop:
            break
        pAp = 0.0
        for i in range(n):
            s = 0.0
            for k in range(indptr[i], indptr[i + 1]):
                s += data[k] * p[indices[k]]
            Ap[i] = s
            pAp += p[i] * s
        alpha = rz / pAp
        rz_new = 0.0
        rr = 0.0
        for i in range(n):
            x[i] += alpha * p[i]
            r[i] -= alpha * Ap[i]
            z[i] = inverse_diagonal[i] * r[i]
            rz_new += r[i] * z[i]
            rr += r[i] * r[i]
        beta = rz_new / rz
        rz = rz_new
        for i in range(n):
            p[i] = z[i] + beta * p[i]
    return x


def jacobi_pcg(
    data: np.ndarray, indptr: np.ndarray, indices: np.ndarray, inverse_diagonal: np.ndarray, b: np.ndarray, rtol: float
) -> np.ndarray:
    """x with ||A x - b|| <= rtol ||b|| (or the iterate after n iterations), A the CSR matrix (data, indptr,
    indices) of n rows, preconditioned by ``inverse_diagonal`` = 1 / diag(A). float64, x_0 = 0; runs without the
    GIL. An unconverged iterate still decreases the quadratic model, so it is still a descent direction."""
    # unsigned indices: numba then skips the wrap-around of negative ones (the CSR product took 2x scipy's time
    # with int32 or int64, the same time with uint32), and 32 bits read half the bytes of 64
    index = np.uint32 if max(len(data), len(b)) < np.iinfo(np.uint32).max else np.uint64
    return _pcg(
        np.ascontiguousarray(data, np.float64),
        np.ascontiguousarray(indptr, index),
        np.ascontiguousarray(indices, index),
        np.ascontiguousarray(inverse_diagonal, np.float64),
        np.ascontiguousarray(b, np.float64),
        float(rtol),
    )
