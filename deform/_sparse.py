"""A sparse linear system factored once on the host and solved from JAX (DESIGN.md, "Sparse linear
algebra"): ``jax.pure_callback`` runs the factor's solve, ``jax.custom_vjp`` gives its adjoint (the
solve with the transposed factor; the same solve for a symmetric system). The harmonic fields use it;
so will ARAP's global step.

The factorization is scipy's sparse LU (SuperLU): the one sparse direct solver that ships with the
project's dependencies, and it handles the unsymmetric mean-value Laplacian as well as the symmetric
cotangent one.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla


class SparseSolver:
    """``A x = b`` for a fixed square sparse ``A``, factored once (host, float64).

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
        try:
            self._lu = spla.splu(A)
        except RuntimeError as error:  # SuperLU reports an exactly singular matrix this way
            raise ValueError(f"A: the matrix is singular ({error})") from None
        self._solve = _make_solve(self)

    def host_solve(self, b, transpose: bool = False) -> np.ndarray:
        """The solve in numpy (float64), for host code."""
        b = np.asarray(b, np.float64)
        return self._lu.solve(b, trans="T" if transpose and not self.symmetric else "N")

    def __call__(self, b):
        b = jnp.asarray(b)
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise ValueError(f"b: expected shape ({self.n},) or ({self.n}, k), got {b.shape}")
        return self._solve(b)


def _make_solve(solver: SparseSolver):
    def host(b, transpose):
        return solver.host_solve(b, transpose).astype(b.dtype)

    def call(b, transpose):
        return jax.pure_callback(lambda x: host(np.asarray(x), transpose), jax.ShapeDtypeStruct(b.shape, b.dtype), b,
                                 vmap_method="sequential")

    @jax.custom_vjp
    def solve(b):
        return call(b, False)

    def forward(b):
        return call(b, False), None

    def backward(_, g):
        return (call(g, True),)  # (A^-1)^T g

    solve.defvjp(forward, backward)
    return solve
