"""Smoothed-aggregation algebraic multigrid: the preconditioner of a fixed symmetric positive definite system's
conjugate gradient on a GPU (``sparse.SparseSolver``). Private to the distribution.

The hierarchy (aggregates, smoothed prolongators P, Galerkin coarse operators P^T A P) is built once on the host
by pyamg; the V-cycle runs in JAX. Every level is smoothed by the same Chebyshev polynomial in ``diag(A)^-1 A`` (or
damped Jacobi sweeps) before and after its coarse correction, with R = P^T, so the V-cycle is a symmetric positive
definite operator, as CG needs; the coarsest level is solved exactly by its dense inverse. Matrices are stored
row-padded (``_jaxcga_shared.ell``). On ARAP's 60k-unknown system the CG takes 32 iterations to 1e-12
where Jacobi CG takes 1,100 to 1e-10.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, Float

from _jaxcga_shared.ell import ELLMatrix, ell_matrix, ell_matvec
from _jaxcga_shared.host import to_devices


class Level(eqx.Module):
    """One level above the coarsest: its operator, the prolongation from the next coarser level and its
    transpose, ``1 / diag(A)`` and the largest eigenvalue of ``diag(A)^-1 A`` (estimated)."""

    A: ELLMatrix
    P: ELLMatrix
    R: ELLMatrix
    inverse_diagonal: Float[Array, " n"]
    rho: float = eqx.field(static=True)


SMOOTHERS = ("chebyshev", "jacobi")


class Multigrid(eqx.Module):
    """A smoothed-aggregation hierarchy (``multigrid_precompute``), applied by ``v_cycle``."""

    levels: tuple[Level, ...]
    coarse_inverse: Float[Array, "nc nc"]
    smoother: str = eqx.field(static=True)
    degree: int = eqx.field(static=True)


def multigrid_precompute(
    A, *, max_coarse: int = 1000, smoother: str = "chebyshev", degree: int = 3, strength: str = "evolution"
) -> Multigrid:
    """Build the hierarchy of a symmetric positive definite scipy sparse ``A`` (host, float64): pyamg's smoothed
    aggregation (its ``strength`` of connection measure) down to at most ``max_coarse`` unknowns (none for a
    smaller A: the V-cycle is then the exact inverse). Each level is smoothed before and after its coarse
    correction by a Chebyshev polynomial of ``degree`` in ``diag(A)^-1 A`` (``degree`` matrix-vector products)
    or by ``degree`` damped Jacobi sweeps.

    The defaults took the fewest CG iterations per matrix-vector product on ARAP's 60k system (27 for 1e-12
    against 72 for pyamg's defaults with two Jacobi sweeps; benchmarks/README.md, "Solves on a GPU").

    Raises:
        ValueError: A's diagonal is not positive (A is not positive definite), or a bad option."""
    import pyamg  # imported on first use: only a device solve needs it

    if smoother not in SMOOTHERS:
        raise ValueError(f"smoother: expected one of {SMOOTHERS}, got {smoother!r}")
    if not isinstance(degree, int) or degree < 1:
        raise ValueError(f"degree: expected an int >= 1, got {degree!r}")
    A = sp.csr_matrix(A, dtype=np.float64)
    if np.any(A.diagonal() <= 0):
        raise ValueError("A: a diagonal entry is not positive (the matrix is not positive definite)")
    if A.shape[0] <= max_coarse:  # pyright: ignore[reportOptionalSubscript]  (scipy: see ell_matrix)
        operators, prolongations = [A], []
    else:
        hierarchy = pyamg.smoothed_aggregation_solver(A, symmetry="symmetric", strength=strength, max_coarse=max_coarse)
        operators = [sp.csr_matrix(level.A) for level in hierarchy.levels]
        prolongations = [sp.csr_matrix(level.P) for level in hierarchy.levels[:-1]]
    levels = []
    for M, P in zip(operators[:-1], prolongations):
        inverse_diagonal = 1 / M.diagonal()
        estimate = pyamg.util.linalg.approximate_spectral_radius(sp.diags(inverse_diagonal) @ M)
        rho = float(estimate)  # pyright: ignore[reportArgumentType]  (pyamg's annotation includes its eigenvectors)
        (inverse_diagonal,) = to_devices(inverse_diagonal)
        levels.append(Level(ell_matrix(M), ell_matrix(P), ell_matrix(P.T), inverse_diagonal, rho))
    (coarse_inverse,) = to_devices(np.linalg.inv(operators[-1].toarray()))
    return Multigrid(levels=tuple(levels), coarse_inverse=coarse_inverse, smoother=smoother, degree=degree)


def _smooth(mg: Multigrid, level: Level, r, x):
    """x plus the smoother applied to the residual ``r - A x`` (x None: 0). The same symmetric operator before
    and after the coarse correction, so the V-cycle is symmetric; each keeps ``|I - S A|`` below 1 on A's
    spectrum (the estimate of rho enlarged by 10%), so the V-cycle is positive definite."""
    inverse_diagonal = level.inverse_diagonal.astype(r.dtype)
    inverse_diagonal = inverse_diagonal if r.ndim == 1 else inverse_diagonal[:, None]

    def preconditioned_residual(x):
        return inverse_diagonal * (r if x is None else r - ell_matvec(level.A, x))

    if mg.smoother == "jacobi":
        omega = 4 / (3 * level.rho)  # pyamg's damping
        for _ in range(mg.degree):
            step = omega * preconditioned_residual(x)
            x = step if x is None else x + step
        return x
    # Chebyshev over [rho / 30, 1.1 rho] (Saad, "Iterative Methods for Sparse Linear Systems", Algorithm 12.1)
    low, high = level.rho / 30, 1.1 * level.rho
    theta, delta = (high + low) / 2, (high - low) / 2
    sigma = theta / delta
    ratio = 1 / sigma
    direction = preconditioned_residual(x) / theta
    for _ in range(mg.degree - 1):
        x = direction if x is None else x + direction
        next_ratio = 1 / (2 * sigma - ratio)
        direction = next_ratio * ratio * direction + 2 * next_ratio / delta * preconditioned_residual(x)
        ratio = next_ratio
    return direction if x is None else x + direction


def v_cycle(mg: Multigrid, r):
    """One V-cycle from 0 for the residual r, (n,) or (n, k): an approximation of ``A^-1 r``."""

    def cycle(depth: int, r):
        if depth == len(mg.levels):
            return jnp.matmul(mg.coarse_inverse.astype(r.dtype), r, precision=jax.lax.Precision.HIGHEST)
        level = mg.levels[depth]
        x = _smooth(mg, level, r, None)
        assert x is not None  # the smoother from 0 returns its first iterate
        x = x + ell_matvec(level.P, cycle(depth + 1, ell_matvec(level.R, r - ell_matvec(level.A, x))))
        return _smooth(mg, level, r, x)

    return cycle(0, r)
