"""Sparse linear solves from JAX, one implementation for every package (DESIGN.md, "Sparse linear algebra").
Private to the distribution.

A system is a CSR pattern (``CSRPattern``: row pointers, column indices, and what a solve needs of them, analysed
once on the host by ``csr_pattern``) and its values (``data``, which may change from call to call: the FEM Newton
matrix is reassembled every iteration). Two paths, chosen when the computation is lowered
(``jax.lax.platform_dependent``, as ``_jaxcga_shared.platform``):

* CPU: on the host, behind ``host_call``. Direct solves by CHOLMOD's sparse Cholesky (``sksparse_minimal``) for
  symmetric positive definite matrices and SuperLU (scipy) otherwise (``factorize``, ``host_direct``); the
  Jacobi-preconditioned CG compiled by numba without the GIL (``host_pcg``, ``_jaxcga_shared.pcg``) for the
  large FEM Newton systems.
* GPU (and every platform other than the CPU): a preconditioned conjugate gradient in JAX, no copy to the host
  (small traced systems, up to ``spd_solve``'s ``dense_up_to`` unknowns, by a dense Cholesky factorization).
  Traced values (``device_pcg``): the matrix-vector product is one ``jax.ops.segment_sum`` over the CSR entries,
  or, for a matrix of full 3 x 3 node blocks (the FEM systems), over its blocks: a ninth of the indices and a
  third of the scatter's adds; the preconditioner the inverse of the diagonal, or of the diagonal 3 x 3 blocks
  for the FEM systems (one block per node). A fixed matrix (``SparseSolver``): a multigrid V-cycle, built once
  (``_jaxcga_shared.multigrid``).
  Not cuDSS's sparse Cholesky: its library (167 MB) cannot travel to the GPU machines this project is tested on,
  so it could not be measured (benchmarks/README.md, "Solves on a GPU").

``SparseSolver`` is a fixed matrix factored once (the harmonic fields, ARAP's global step, the cage's Dirichlet
problem), solved for many right-hand sides, with its adjoint through ``jax.custom_vjp``; ``spd_solve`` solves a
symmetric positive definite system whose values are traced (XFEM's Newton direction and implicit gradient).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jaxtyping import Array, Float, Int
from sksparse_minimal import SparseCholesky

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import require
from _jaxcga_shared.ell import ell_matrix, ell_matvec
from _jaxcga_shared.host import host_call, to_devices
from _jaxcga_shared.platform import PerPlatform

# relative residual of a prefactored system's device solve (the host's is a direct solve): 1e-10 left ARAP 8e-9 of
# its size from libigl's direct iteration on an H100, over the tests' 1e-10
DEVICE_RTOL = 1e-12
DEVICE_MAX_ITERATIONS = 1000  # the multigrid CG took 30 to 70 to 1e-12 on the meshes of the tests and benchmarks
# CG iterations between two convergence checks (``preconditioned_cg``): the FEM Newton solves run ~150 cheap ones
CG_CHECK_EVERY = 4
MULTIGRID_CG_CHECK_EVERY = 2  # the fixed systems' multigrid CG: ~30 dearer iterations (``SparseSolver.device_solve``)


class BlockLayout(eqx.Module):
    """The stored blocks of a matrix of full ``block`` x ``block`` blocks (``CSRPattern.full_blocks``), one entry
    each, the padding's too (the CSR data's length over ``block^2``), found once by ``csr_pattern``.

    Attributes:
        rows: (count,) each block's block row; the number of block rows for the padding's (dropped).
        columns: (count,) each block's block column.
        starts: (count,) the CSR index of each block's first entry.
        strides: (count,) the distance in the CSR data between the entries of a block's consecutive rows.
    """

    rows: Int[Array, " count"]
    columns: Int[Array, " count"]
    starts: Int[Array, " count"]
    strides: Int[Array, " count"]


class CSRPattern(eqx.Module):
    """The structure of an (n, n) CSR matrix, analysed once (``csr_pattern``); its data is passed with each solve.

    Attributes:
        indptr: (n + 1,) row pointers; entries past ``indptr[-1]`` are padding (a fixed capacity), ignored.
        indices: (nnz,) column indices.
        rows: (nnz,) the row of each entry, n for padding (dropped by the matrix-vector product's segment sum).
        block_slots: (nnz,) where each entry goes in the (n / block, block, block) diagonal blocks (flattened),
            ``n * block`` (dropped) for the entries off them and the padding.
        n: the number of rows.
        block: the preconditioner's block size (1: Jacobi; 3: one block per node of a 3-D FEM system).
        full_blocks: whether the matrix is made of full ``block`` x ``block`` blocks (``_full_blocks``), so that
            the matrix-vector product runs over blocks (``_block_matvec``).
        blocks: where those blocks are (``BlockLayout``); None unless made of full blocks.
    """

    indptr: Int[Array, " n_plus_one"]
    indices: Int[Array, " nnz"]
    rows: Int[Array, " nnz"]
    block_slots: Int[Array, " nnz"]
    n: int = eqx.field(static=True)
    block: int = eqx.field(static=True)
    full_blocks: bool = eqx.field(static=True, default=False)
    blocks: BlockLayout | None = None


def csr_pattern(
    indptr, indices, *, block: int = 1, full_blocks: bool | None = None, on_host: bool = False
) -> CSRPattern:
    """Analyse a CSR structure (host, numpy): each entry's row and its slot in the diagonal blocks.

    Args:
        indptr: (n + 1,) int row pointers.
        indices: (nnz,) int column indices, nnz >= ``indptr[-1]`` (the rest is padding).
        block: the preconditioner's block size, dividing n.
        full_blocks: whether the structure is made of full ``block`` x ``block`` blocks (``_full_blocks``); None
            checks it (20 ms a million entries), True is the caller's construction's guarantee (an XFEM
            system's pattern, built after every cut).
        on_host: numpy arrays instead of device arrays (``to_devices``).
    Returns:
        The ``CSRPattern``.
    """
    indptr, indices = np.asarray(indptr), np.asarray(indices)
    n = len(indptr) - 1
    if indptr.ndim != 1 or n < 0 or indptr[0] != 0 or np.any(np.diff(indptr) < 0) or indptr[-1] > len(indices):
        raise ValueError(f"indptr: expected non-decreasing row pointers from 0 to at most {len(indices)}")
    if block < 1 or n % block:
        raise ValueError(f"block: expected a positive divisor of the {n} rows, got {block}")
    used = int(indptr[-1])
    if used and (indices[:used].min() < 0 or indices[:used].max() >= n):
        raise ValueError(f"indices: column indices must lie in [0, {n})")
    index = indices.dtype if np.issubdtype(indices.dtype, np.integer) else np.int64
    if n * block >= np.iinfo(index).max:
        index = np.int64
    # in the index type from the start: an XFEM system's pattern has millions of entries
    rows = np.full(len(indices), n, index)
    rows[:used] = np.repeat(np.arange(n, dtype=index), np.diff(indptr))
    columns = indices[:used].astype(index, copy=False)
    row_block, column_block = rows[:used] // block, columns // block
    in_block = rows[:used] * block + (columns - column_block * block)
    slots = np.full(len(indices), n * block, index)
    slots[:used] = np.where(row_block == column_block, in_block, n * block)
    if full_blocks is None:
        full_blocks = block > 1 and _full_blocks(indptr, indices[:used], block)
    full = bool(full_blocks) and block > 1
    indptr, indices = (a.astype(index, copy=False) for a in (indptr, indices))
    blocks = BlockLayout(*to_devices(*_block_layout(indptr, indices, block), on_host=on_host)) if full else None
    indptr, indices, rows, slots = to_devices(indptr, indices, rows, slots, on_host=on_host)
    return CSRPattern(
        indptr=indptr, indices=indices, rows=rows, block_slots=slots, n=n, block=block, full_blocks=full, blocks=blocks
    )


def _block_layout(indptr: np.ndarray, indices: np.ndarray, size: int) -> tuple[np.ndarray, ...]:
    """``BlockLayout``'s arrays for a structure of full ``size`` x ``size`` blocks (host: a search per block that a
    GPU would run as a loop of launches in every solve)."""
    index = indptr.dtype
    nodes = (len(indptr) - 1) // size
    count = len(indices) // size**2  # every stored block, the padding's too
    node_indptr = indptr[::size] // size**2  # a block row's blocks: size^2 entries each
    degree = np.diff(node_indptr)
    used = int(node_indptr[-1])
    rows = np.full(count, nodes, index)  # nodes for the padding: dropped
    rows[:used] = np.repeat(np.arange(nodes, dtype=index), degree)
    first = node_indptr[rows[:used]]
    starts, strides = np.zeros(count, index), np.zeros(count, index)
    starts[:used] = size**2 * first + size * (np.arange(used, dtype=index) - first)
    # entry (a, b) of a block: a block row's rows are ``size * degree`` entries apart
    strides[:used] = size * degree[rows[:used]]
    return rows, indices[starts] // size, starts, strides


def _full_blocks(indptr: np.ndarray, indices: np.ndarray, block: int) -> bool:
    """Whether a CSR structure is made of full ``block`` x ``block`` blocks stored block row by block row: the
    ``block`` rows of each block row hold the same columns, in groups of ``block`` consecutive columns from a
    multiple of ``block`` (a DOF-level matrix expanded from a node-level one, as ``xfem.assembly_pattern``'s)."""
    lengths = np.diff(indptr)
    if np.any(lengths % block) or np.any(lengths.reshape(-1, block) != lengths[::block, None]):
        return False
    position = np.arange(len(indices)) - np.repeat(indptr[:-1], lengths)  # within its row
    within = position % block
    if np.any(indices % block != within):
        return False
    # each group's columns follow its first one, and each row of a block row repeats the block row's first
    if np.any(indices - indices[np.arange(len(indices)) - within] != within):
        return False
    row_in_block = np.repeat(np.arange(len(lengths)) % block, lengths)
    return bool(np.all(indices == indices[np.arange(len(indices)) - row_in_block * np.repeat(lengths, lengths)]))


# ---------------------------------------------------------------------------------------------------------
# the host path (numpy, float64)


def host_csr(data, indptr, indices) -> sp.csr_matrix:
    n, used = len(indptr) - 1, int(indptr[-1])  # entries past indptr[-1] are padding
    return sp.csr_matrix(
        (np.asarray(data, np.float64)[:used], np.asarray(indices)[:used], np.asarray(indptr)), shape=(n, n)
    )


def factorize(A, symmetric: bool) -> Callable:
    """The factored ``A`` (host): CHOLMOD for a symmetric positive definite A, SuperLU otherwise. Returns
    ``solve(b, transpose=False)``. ValueError naming A if it is singular (or not positive definite)."""
    A = sp.csc_matrix(A, dtype=np.float64)
    if symmetric:
        try:
            factor = SparseCholesky(A)
        except ValueError as error:  # CHOLMOD: a zero or negative pivot
            raise ValueError(f"A: the matrix is singular or not positive definite ({error})") from None
        return lambda b, transpose=False: factor.solve_A(b)
    try:
        lu = spla.splu(A)
    except RuntimeError as error:  # SuperLU reports an exactly singular matrix this way
        raise ValueError(f"A: the matrix is singular ({error})") from None
    return lambda b, transpose=False: lu.solve(b, trans="T" if transpose else "N")


def host_direct(data, b, indptr, indices) -> np.ndarray:
    """The exact solve of a symmetric CSR system (host): CHOLMOD, SuperLU for an indefinite matrix, NaN for a
    singular one (checked by the caller inside jit)."""
    A = host_csr(data, indptr, indices)
    rhs = np.asarray(b, np.float64)
    for symmetric in (True, False):
        try:
            return factorize(A, symmetric)(rhs).astype(b.dtype)
        except ValueError:  # not positive definite (CHOLMOD), then singular (SuperLU)
            pass
    return np.full_like(b, np.nan)


def host_pcg(data, b, rtol, indptr, indices) -> np.ndarray:
    """Jacobi-preconditioned CG on the host to the relative residual ``rtol``, from 0, at most n iterations
    (``_jaxcga_shared.pcg``: compiled, without the GIL).

    Not scipy's ``cg``: its vector dot products go to numpy's multithreaded BLAS, whose threads stall on a loaded
    2-core machine (benchmarks/README.md, "FEM linear solver"). Not a numpy loop either: its ~14 array operations
    per iteration each hand the GIL over, and wait for a background thread (a cut's manifold3d or libigl call) to
    give it back."""
    from _jaxcga_shared.pcg import jacobi_pcg  # numba is imported on first use, not with every package

    A = host_csr(data, indptr, indices)
    return jacobi_pcg(A.data, A.indptr, A.indices, 1 / A.diagonal(), np.asarray(b, np.float64), float(rtol)).astype(
        b.dtype
    )


# ---------------------------------------------------------------------------------------------------------
# the device path (JAX)


def csr_matvec(pattern: CSRPattern, data, x):
    """``A x`` for the CSR matrix (pattern, data) and x of shape (n,) or (n, k): one segment sum."""
    products = (data if x.ndim == 1 else data[:, None]) * x[pattern.indices]
    return jax.ops.segment_sum(products, pattern.rows, num_segments=pattern.n, indices_are_sorted=True)


def _block_matvec(pattern: CSRPattern, data):
    """``x -> A x`` for a matrix of full blocks (``pattern.full_blocks``), x of shape (n,) or (n, k): the blocks
    are gathered from the CSR data once, then each product is a block gather of x and one segment sum over the
    blocks, whose sorted adds a GPU's scatter makes one per block row and component instead of one per entry."""
    size = pattern.block
    nodes = pattern.n // size
    layout = pattern.blocks
    if layout is None:
        raise ValueError("pattern: a pattern of full blocks from csr_pattern (its BlockLayout)")
    count, row, columns = layout.rows.shape[0], layout.rows, layout.columns
    offsets = jnp.arange(size, dtype=layout.starts.dtype)
    slots = layout.starts[:, None, None] + layout.strides[:, None, None] * offsets[None, :, None] + offsets[None, None]
    blocks = jnp.where((row < nodes)[:, None, None], data[slots], 0)

    def matvec(x):
        gathered = x.reshape(nodes, size, *x.shape[1:])[columns]  # (count, size[, k])
        trailing = (1,) * (x.ndim - 1)
        # a product and a sum, not a dot: XLA turns batches of tiny dots into matrix-unit calls
        products = jnp.sum(blocks.reshape(count, size, size, *trailing) * gathered[:, None], axis=2)
        return jax.ops.segment_sum(products, row, num_segments=nodes, indices_are_sorted=True).reshape(x.shape)

    return matvec


def matvec(pattern: CSRPattern, data):
    """``x -> A x`` for the matrix (pattern, data): over its blocks where it is made of full blocks, over its
    entries otherwise."""
    if pattern.full_blocks:
        return _block_matvec(pattern, data)
    return functools.partial(csr_matvec, pattern, data)


def _preconditioner(pattern: CSRPattern, data):
    """The inverse diagonal blocks of A as a function ``r -> P r``, and whether they are all positive definite
    (a necessary condition for A; a zero or negative diagonal entry is the common failure)."""
    size = pattern.block
    count = pattern.n // size
    blocks = jax.ops.segment_sum(data, pattern.block_slots, num_segments=pattern.n * size)
    blocks = blocks.reshape(count, size, size)
    if size == 1:
        diagonal = blocks[:, 0, 0]
        positive = jnp.all(diagonal > 0)
        inverse = 1 / jnp.where(diagonal > 0, diagonal, 1)
        return (lambda r: inverse.reshape((-1,) + (1,) * (r.ndim - 1)) * r), positive
    # Cholesky of every block: NaN where one is not positive definite
    factor = jnp.linalg.cholesky(blocks)
    positive = jnp.all(jnp.isfinite(factor))
    identity = jnp.broadcast_to(jnp.eye(size, dtype=data.dtype), blocks.shape)
    inverse = jnp.where(
        jnp.isfinite(factor).all((1, 2))[:, None, None], jax.scipy.linalg.cho_solve((factor, True), identity), identity
    )

    def apply(r):
        columns = r.reshape(count, 1, size, -1)
        # a product and a sum, not a dot: it runs in every CG iteration, and XLA turns batches of tiny dots into
        # matrix-unit calls
        return jnp.sum(inverse[..., None] * columns, axis=2).reshape(r.shape)

    return apply, positive


class PCGInfo(eqx.Module):
    """How a ``device_pcg`` ended.

    Attributes:
        iterations: the iterations run.
        relative_residual: (k,) or () ``|r| / |b|`` of the iterate (the recurrence's residual, as the host CG).
        converged: () whether every column reached the tolerance.
        breakdown: () whether A showed it is not positive definite (a non-positive ``p.Ap`` or diagonal block).
    """

    iterations: Int[Array, ""]
    relative_residual: Float[Array, "*k"]
    converged: Array
    breakdown: Array


def device_pcg(pattern: CSRPattern, data, b, rtol, max_iterations: int | None = None):
    """Block-Jacobi preconditioned CG in JAX for a symmetric positive definite A: x with
    ``|A x - b| <= rtol |b|`` (each column of a (n, k) b), from 0, at most ``max_iterations`` iterations (default
    n). Runs anywhere (jit, vmap); differentiate the solve with an implicit rule, not through the loop.

    Returns:
        x of b's shape and a ``PCGInfo``. On a breakdown the loop stops with the iterate so far."""
    precondition, positive = _preconditioner(pattern, data)
    limit = pattern.n if max_iterations is None else int(max_iterations)
    return preconditioned_cg(matvec(pattern, data), precondition, b, rtol, limit, x0=None, positive=positive)


def preconditioned_cg(
    matvec,
    precondition,
    b,
    rtol,
    max_iterations: int,
    *,
    x0=None,
    positive: Array | bool = True,
    check_every: int = CG_CHECK_EVERY,
):
    """CG for a symmetric positive definite ``matvec`` with the SPD preconditioner ``precondition`` (functions of
    (n,) or (n, k) arrays): x with ``|A x - b| <= rtol |b|`` per column, from ``x0`` (default 0), at most
    ``max_iterations`` iterations; ``positive`` False marks A as not positive definite before the first
    iteration. Returns x and a ``PCGInfo``; on a breakdown the loop stops with the iterate so far.

    Each loop step runs ``check_every`` iterations, those after the loop's end (convergence, breakdown, the limit)
    masked to no-ops: a GPU copies a while loop's condition to the host and waits for it at every step, and the
    iterates are the same whatever ``check_every``."""
    if int(check_every) != check_every or check_every < 1:
        raise ValueError(f"check_every: expected an int >= 1, got {check_every!r}")

    def dot(u, v):
        return jnp.sum(u * v, axis=0)

    bb = dot(b, b)
    stop = jnp.asarray(rtol, b.dtype) ** 2 * bb
    x = jnp.zeros_like(b) if x0 is None else x0.astype(b.dtype)
    r = b if x0 is None else b - matvec(x)
    z = precondition(r)
    start = (jnp.zeros((), jnp.int32), x, r, z, dot(r, z), dot(r, r), ~jnp.asarray(positive))

    def running(k, rr, broken):
        return (k < max_iterations) & jnp.any(rr > stop) & ~broken

    def iteration(carry):
        k, x, r, p, rz, rr, broken = carry
        live = running(k, rr, broken)
        Ap = matvec(p)
        pAp = dot(p, Ap)
        active = (rr > stop) & live
        broken = broken | jnp.any(active & ~(pAp > 0))
        alpha = jnp.where(active & (pAp > 0), rz / jnp.where(pAp > 0, pAp, 1), 0)
        alpha = lift_rank(alpha, p.ndim)  # one step per column of (n, k) right-hand sides
        x = x + alpha * p
        r = r - alpha * Ap
        z = precondition(r)
        rz_new = dot(r, z)
        beta = jnp.where(active & (rz != 0), rz_new / jnp.where(rz != 0, rz, 1), 0)
        return k + live.astype(jnp.int32), x, r, z + lift_rank(beta, p.ndim) * p, rz_new, dot(r, r), broken

    def body(carry):
        for _ in range(int(check_every)):
            carry = iteration(carry)
        return carry

    k, x, _, _, _, rr, broken = jax.lax.while_loop(lambda c: running(c[0], c[5], c[6]), body, start)
    relative = jnp.sqrt(rr / jnp.where(bb > 0, bb, 1))
    return x, PCGInfo(
        iterations=jnp.asarray(k), relative_residual=relative, converged=jnp.all(rr <= stop) & ~broken, breakdown=broken
    )


def _not_converged(what: str, limit: str) -> str:
    return (
        f"{what}: the conjugate gradient did not reach its tolerance in {limit} iterations (the matrix is "
        "singular, not positive definite, or too ill-conditioned)"
    )


def checked_device_pcg(pattern: CSRPattern, data, b, rtol, max_iterations: int | None = None, *, what: str = "A"):
    """``device_pcg``'s x, with a runtime check (``checks.require``) naming ``what`` when it broke down or did not
    converge."""
    x, info = device_pcg(pattern, data, b, rtol, max_iterations)
    limit = str(pattern.n if max_iterations is None else max_iterations)
    return require(x, (~info.converged, _not_converged(what, limit)))


# ---------------------------------------------------------------------------------------------------------
# traced values: XFEM's Newton direction and implicit gradient


def _direct(data, b, rtol, indptr, indices):
    return host_direct(data, b, indptr, indices)


def _on_host(host, pattern, data, b, rtol):
    return host_call(host, jax.ShapeDtypeStruct(b.shape, b.dtype), data, b, rtol, pattern.indptr, pattern.indices)


def dense_cholesky_solve(pattern: CSRPattern, data, b):
    """``A^-1 b`` by a dense Cholesky factorization of the CSR system (pattern, data), for systems small enough
    that one factorization costs less than CG's iterations, and whether A is positive definite (its factor is
    finite; where it is not, x is NaN)."""
    # padding entries sit in row n, dropped with it
    A = jnp.zeros((pattern.n + 1, pattern.n), data.dtype).at[pattern.rows, pattern.indices].add(data)[:-1]
    L = jnp.linalg.cholesky(A, symmetrize_input=False)
    return jax.scipy.linalg.cho_solve((L, True), b), jnp.all(jnp.isfinite(L))


def _on_device(host, max_iterations, on_failure, what, dense_up_to, pattern, data, b, rtol):
    def iterative():
        if on_failure == "error":
            return checked_device_pcg(pattern, data, b, rtol, max_iterations, what=what)
        x, info = device_pcg(pattern, data, b, rtol, max_iterations)
        if on_failure == "accept":
            return jnp.where(info.breakdown & (info.iterations == 0), jnp.nan, x)  # not positive definite at all
        return jax.lax.cond(info.converged, lambda: x, lambda: _on_host(host, pattern, data, b, rtol))

    if pattern.n > dense_up_to:
        return iterative()
    x, positive = dense_cholesky_solve(pattern, data, b)
    return jax.lax.cond(positive, lambda: x, iterative)  # not positive definite: CG, as the CPU after CHOLMOD


def spd_solve(
    pattern: CSRPattern,
    data,
    b,
    rtol,
    *,
    host: Callable = _direct,
    max_iterations=None,
    on_failure: str = "error",
    what: str = "A",
    dense_up_to: int = 0,
):
    """Solve the symmetric positive definite CSR system (pattern, data) for b (n,) from traced code.

    CPU: ``host(data, b, rtol, indptr, indices)`` through ``host_call`` (numpy arrays; by default
    ``host_direct``, which has no use for rtol). Elsewhere: a system of at most ``dense_up_to`` unknowns by
    ``dense_cholesky_solve`` (exact, as a host that factorizes systems that small), a larger one, or one that is not
    positive definite, by ``device_pcg`` to ``rtol``; when CG falls short, ``on_failure`` decides: ``"error"`` (a
    runtime check naming ``what``), ``"host"`` (``host`` on the host, as the CPU does) or ``"accept"`` (the
    iterate: an inexact Newton direction, as the host CG's after its n iterations). Not differentiable (the
    callers differentiate implicitly)."""
    if on_failure not in ("error", "host", "accept"):
        raise ValueError(f"on_failure: expected 'error', 'host' or 'accept', got {on_failure!r}")
    if int(dense_up_to) != dense_up_to or dense_up_to < 0:
        raise ValueError(f"dense_up_to: expected an int >= 0, got {dense_up_to!r}")
    return jax.lax.platform_dependent(
        pattern,
        data,
        b,
        jnp.asarray(rtol, b.dtype),
        cpu=functools.partial(_on_host, host),
        default=functools.partial(_on_device, host, max_iterations, on_failure, what, int(dense_up_to)),
    )


# ``spd_solve``'s default configuration, registered for the CPU test of its two variants' agreement
SPD_SOLVE = PerPlatform(
    "sparse_spd_solve",
    cpu=functools.partial(_on_host, _direct),
    gpu=functools.partial(_on_device, _direct, None, "error", "A", 0),
    differentiated=False,
    float32=False,
)  # CHOLMOD is float64; gradients: tests/shared_layer/test_sparse.py

# and with its small systems factorized densely off the CPU (``dense_up_to``, the FEM Newton systems')
SPD_SOLVE_DENSE = PerPlatform(
    "sparse_spd_solve_dense",
    cpu=functools.partial(_on_host, _direct),
    gpu=functools.partial(_on_device, _direct, None, "error", "A", 1 << 30),
    differentiated=False,
    float32=False,
)


# ---------------------------------------------------------------------------------------------------------
# a fixed matrix, factored once


class SparseSolver:
    """``A x = b`` for a fixed square sparse A (float64), prepared once: factored on the host (CHOLMOD for
    ``symmetric=True``, a promise that A is symmetric positive definite; SuperLU otherwise) and, when symmetric,
    on first use off the CPU, its multigrid hierarchy built for the device CG (``device_rtol``, checked: an
    unconverged solve is an error).

    Call it on b of shape (n,) or (n, k) inside or outside jit: on the CPU the factor solves it on the host; on
    other platforms a symmetric system is solved on the device by ``device_solve`` (an unsymmetric one on the
    host).
    Differentiable in reverse mode with respect to b (the adjoint is the solve with A^T: the same solve for a
    symmetric A); works under vmap. Hashable by identity (a static argument, or closed over).

    Raises:
        ValueError: A is not square, empty, not symmetric when promised, or singular (not positive definite)."""

    def __init__(self, A, symmetric: bool = False, device_rtol: float = DEVICE_RTOL):
        A = sp.csr_matrix(A, dtype=np.float64)
        # scipy is not annotated: pyright infers from its code that a matrix's shape may be None
        shape: tuple[int, ...] = A.shape  # pyright: ignore[reportAssignmentType]
        if A.ndim != 2 or shape[0] != shape[1]:
            raise ValueError(f"A: expected a square sparse matrix, got shape {shape}")
        if shape[0] == 0:
            raise ValueError("A: the system is empty")
        self.n = shape[0]
        self.symmetric = symmetric
        if symmetric and abs(A - A.T).max() > 1e-12 * abs(A).max():
            raise ValueError("A: symmetric=True but the matrix is not symmetric")
        self._factor = factorize(A, symmetric)
        self._A = A
        self.device_rtol = device_rtol
        self._solve = _prefactored(self)

    def host_solve(self, b, transpose: bool = False) -> np.ndarray:
        """The solve in numpy (float64), for host code."""
        return self._factor(np.asarray(b, np.float64), transpose)

    @functools.cached_property
    def _device_system(self):
        """A in ELL form and its multigrid hierarchy for the device CG (built on first use: host-only users skip
        it)."""
        from _jaxcga_shared.multigrid import multigrid_precompute

        with jax.ensure_compile_time_eval():  # first used while tracing: device arrays, not the trace's values
            return ell_matrix(self._A), multigrid_precompute(self._A)

    def device_solve(self, b, x0=None):
        """The device path, on any platform (what a GPU runs): CG preconditioned by a multigrid V-cycle
        (``_jaxcga_shared.multigrid``) to ``device_rtol``, from ``x0`` (default 0), checked."""
        from _jaxcga_shared.multigrid import v_cycle

        if not self.symmetric:
            raise ValueError("symmetric: the device solve needs a symmetric positive definite system (symmetric=True)")
        A, hierarchy = self._device_system
        x, info = preconditioned_cg(
            lambda x: ell_matvec(A, x),
            lambda r: v_cycle(hierarchy, r),
            b,
            self.device_rtol,
            DEVICE_MAX_ITERATIONS,
            x0=x0,
            # ~30 iterations of ~150 us: checking every 2 saves ~15 round trips (10-30 us each) for half an iteration
            # of masked work on average; every 4 pays only if a round trip costs over ~20 us
            check_every=MULTIGRID_CG_CHECK_EVERY,
        )
        return require(x, (~info.converged, _not_converged("A", str(DEVICE_MAX_ITERATIONS))))

    def __call__(self, b, x0=None):
        """``A^-1 b``; ``x0`` (b's shape) is a first guess for the device's iterative solve (the host's direct
        solve has no use for it); the result does not depend on it, and no gradient flows to it."""
        b = jnp.asarray(b)
        if b.ndim not in (1, 2) or b.shape[0] != self.n:
            raise ValueError(f"b: expected shape ({self.n},) or ({self.n}, k), got {b.shape}")
        if x0 is not None:
            x0 = jax.lax.stop_gradient(jnp.asarray(x0, b.dtype))
            if x0.shape != b.shape:
                raise ValueError(f"x0: expected b's shape {b.shape}, got {x0.shape}")
        return self._solve(b, x0)


def _prefactored(solver: SparseSolver):
    def host(b, transpose):
        return solver.host_solve(b, transpose).astype(b.dtype)

    def call(b, x0, transpose):
        def on_host(b, x0):
            return host_call(functools.partial(host, transpose=transpose), jax.ShapeDtypeStruct(b.shape, b.dtype), b)

        if not solver.symmetric:
            return on_host(b, x0)
        return jax.lax.platform_dependent(b, x0, cpu=on_host, default=solver.device_solve)

    @jax.custom_vjp
    def solve(b, x0):
        return call(b, x0, False)

    def forward(b, x0):
        return call(b, x0, False), None

    def backward(_, g):
        return call(g, None, True), None  # (A^-1)^T g; the guess x0 does not change the solution

    solve.defvjp(forward, backward)
    return solve
