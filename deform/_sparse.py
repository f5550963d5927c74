"""A sparse linear system factored once on the host and solved from JAX (DESIGN.md, "Sparse linear
algebra"): ``host_call`` (a ``jax.pure_callback`` without its device copy) runs the factor's solve,
``jax.custom_vjp`` gives its adjoint (the solve with the transposed factor; the same solve for a symmetric
system). The harmonic fields use it; so will ARAP's global step.

Two factorizations, picked by the system:

* symmetric positive definite (cotangent Laplacians, ARAP's global step): CHOLMOD's sparse Cholesky
  (LDL^T with a fill-reducing ordering) through ``sksparse_minimal``: the fastest factorization of a large
  Laplacian (benchmarks/README.md, "Kernel and deformers").
* unsymmetric (the mean-value Laplacian): scipy's sparse LU (SuperLU).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from sksparse_minimal import SparseCholesky

from _jaxcga_shared.host import host_call


class SparseSolver:
    """``A x = b`` for a fixed square sparse ``A``, factored once (host, float64); ``symmetric=True``
    promises a symmetric positive definite A (Cholesky), otherwise LU.

    Call it on ``b`` of shape (n,) or (n, k) inside or outside jit; it is differentiable (reverse mode)
    with respect to ``b`` and works under vmap (one host solve per batch element). Hashable by
    identity, so it can be closed over or passed as a static argument."""

    def __init__(self, A, symmetric: bool = False):
        A = sp.csc_matrix(A, dtype=np.float64)
        if A.ndim != 2 or A.shape[0] != A.shape[1]:
            raise ValueError(f"A: expected a square sparse matrix, got shape {A.shape}")
        if A.shape[0] == 0:
            raise ValueError("A: the system is empty")
        self.n = A.shape[0]
        self.symmetric = symmetric
        if symmetric:
            if abs(A - A.T).max() > 1e-12 * abs(A).max():
                raise ValueError("A: symmetric=True but the matrix is not symmetric")
            try:
                self._cholesky = SparseCholesky(A)
            except ValueError as error:  # CHOLMOD: a zero or negative pivot
                raise ValueError(f"A: the matrix is singular or not positive definite ({error})") from None
        else:
            try:
                self._lu = spla.splu(A)
            except RuntimeError as error:  # SuperLU reports an exactly singular matrix this way
                raise ValueError(f"A: the matrix is singular ({error})") from None
        self._solve = _make_solve(self)

    def host_solve(self, b, transpose: bool = False) -> np.ndarray:
        """The solve in numpy (float64), for host code."""
        b = np.asarray(b, np.float64)
        if self.symmetric:
            return self._cholesky.solve_A(b)
        return self._lu.solve(b, trans="T" if transpose else "N")

    def __call__(self, b):
        b = jnp.asarray(b)
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise ValueError(f"b: expected shape ({self.n},) or ({self.n}, k), got {b.shape}")
        return self._solve(b)


def _make_solve(solver: SparseSolver):
    def host(b, transpose):
        return solver.host_solve(b, transpose).astype(b.dtype)

    def call(b, transpose):
        # host_call, not jax.pure_callback: its device copy of b could hang a one-core machine (_jaxcga_shared.host)
        return host_call(functools.partial(host, transpose=transpose), jax.ShapeDtypeStruct(b.shape, b.dtype), b)

    @jax.custom_vjp
    def solve(b):
        return call(b, False)

    def forward(b):
        return call(b, False), None

    def backward(_, g):
        return (call(g, True),)  # (A^-1)^T g

    solve.defvjp(forward, backward)
    return solve
