"""Sparse assembly of the backward Euler system of the XFEM paper, sec. 3.3: the 3n x 3n matrix
``M (x) I3 + h^2 d^2U/dx^2`` (eq. 7, 9, 10) and the 3n vectors of eq. 6 and 8, summed from per-element
12-vectors and 12 x 12 blocks.

The sparsity is fixed by the element list (and, for XFEM's custom mass entries, by extra node couplings),
so ``assembly_pattern`` computes it once on the host in vectorized numpy: the CSR structure of the matrix and,
for each of the ``144 m`` element Hessian entries, the CSR data slot it adds into. Assembly in JAX is then a
single scatter-add (``assemble_matrix``), jit- and grad-able. Dirichlet conditions are applied by
substitution: the pattern of the free nodes only (the fixed nodes' rows and columns removed) is built
directly, and entries touching a fixed node go to a discarded slot.

Node ordering: DOF ``3 i + k`` is coordinate k of node i, the element 12-ordering is node-major (entry
``3 a + k`` is coordinate k of the element's local node a). The CSR of node pairs is expanded to 3 x 3
blocks, so row ``3 a + k`` of the reduced matrix holds the columns ``3 b + c`` of the free nodes b coupled
with free node a, b ascending, c = 0, 1, 2.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Array, Float, Int

from _jaxcga_shared.checks import check_index_range
from _jaxcga_shared.host import to_devices
from _jaxcga_shared.sparse import CSRPattern, csr_matvec, csr_pattern


class CapacityError(ValueError):
    """A padded system's capacity (``nnz_capacity``, ``SystemCapacity``) is smaller than the system."""


class AssemblyPattern(eqx.Module):
    """The CSR structure of the reduced (free-DOF) 3n x 3n matrix and the scatter maps into it; build it with
    ``assembly_pattern``.

    Attributes:
        n: the number of DOF nodes.
        n_free: the number of free (not fixed) nodes; the matrix is 3 n_free x 3 n_free.
        nnz: the number of stored entries.
        m: the number of elements the pattern was built for.
        free: (n_free,) the free nodes, ascending: reduced node r is node ``free[r]``.
        free_index: (n,) the reduced index of each node, -1 for a fixed node.
        csr: the ``_jaxcga_shared.sparse.CSRPattern`` of the matrix (3 x 3 node blocks), which the solves take;
            its ``indptr`` (3 n_free + 1,) CSR row pointers, ``indptr[-1]`` <= nnz (the rest is padding),
            ``indices`` (nnz,) column indices, ascending within a row, and ``rows`` (nnz,) the row of each entry
            (3 n_free for padding) are also the pattern's.
        hessian_slots: (144 m,) the data slot of each element Hessian entry ``H[e, r, c]`` (flattened in C
            order); ``nnz`` or more (out of bounds) for entries on a fixed node's row or column, which are
            discarded.
    """

    n: int = eqx.field(static=True)
    n_free: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    free: Int[Array, " n_free"]
    free_index: Int[Array, " n"]
    csr: CSRPattern
    hessian_slots: Int[Array, " entries"]

    @property
    def indptr(self) -> Int[Array, " rows_plus_one"]:
        return self.csr.indptr

    @property
    def indices(self) -> Int[Array, " nnz"]:
        return self.csr.indices

    @property
    def rows(self) -> Int[Array, " nnz"]:
        return self.csr.rows


def _host_fixed(fixed, n: int) -> np.ndarray:
    fixed = np.asarray(fixed)
    if fixed.size == 0:
        return np.zeros(0, np.int64)
    if fixed.ndim != 1 or not np.issubdtype(fixed.dtype, np.integer):
        raise ValueError(f"fixed: expected a 1-D integer array of node indices, got {fixed.dtype} {fixed.shape}")
    check_index_range("fixed", fixed, n, "node")
    if len(np.unique(fixed)) != len(fixed):
        raise ValueError("fixed: repeated node indices")
    return fixed.astype(np.int64)


def _host_elements(T, n: int) -> np.ndarray:
    T = np.asarray(T)
    if T.ndim != 2 or T.shape[1] != 4 or not np.issubdtype(T.dtype, np.integer):
        raise ValueError(f"T: expected integer elements of shape (m, 4), got {T.dtype} {T.shape}")
    check_index_range("T", T, n, "node")
    return T.astype(np.int64)


def sorted_unique(values: np.ndarray) -> np.ndarray:
    """``np.unique`` of an integer array (flattened), by a sort: numpy 2.3 and later take a hash table for plain
    ``np.unique``, 2-10x slower than sorting on the hundreds of thousands of node pairs a cut system has."""
    ordered = np.sort(values, axis=None)
    return ordered[np.concatenate([[True], ordered[1:] != ordered[:-1]])] if len(ordered) else ordered


def _block_slots(node_indptr, degree, a, p, k, c):
    """CSR slot of entry (3 a + k, 3 b + c), b being the column node of the p-th stored node pair, which lies in
    node row a (see the module docstring). Row a = n_free (a fixed node's entry, discarded) gives a dummy."""
    degree = np.append(degree, 0)
    return 9 * node_indptr[a] + 3 * k * degree[a] + 3 * (p - node_indptr[a]) + c


def assembly_pattern(
    T: Int[npt.ArrayLike, "m 4"],
    n: int,
    fixed: Int[npt.ArrayLike, " k"] = (),
    coupling: sp.spmatrix | sp.sparray | Float[npt.ArrayLike, "n n"] | None = None,
    nnz_capacity: int | None = None,
) -> AssemblyPattern:
    """Precompute the sparsity of the free-DOF system and the scatter map of the element Hessians (host).

    Args:
        T: (m, 4) int elements, indices into the n DOF nodes (nodes may repeat across elements in any way;
            in XFEM they are enriched copies, not mesh vertices).
        n: the number of DOF nodes.
        fixed: (k,) distinct int nodes removed from the system (Dirichlet by substitution); () for none.
        coupling: None, or an (n, n) scipy sparse (or dense) matrix whose nonzero pattern is added to the
            node couplings of T, e.g. a mass matrix with entries between nodes that share no element.
    Returns:
        The ``AssemblyPattern``.
    """
    n = int(n)
    if n < 1:
        raise ValueError(f"n: expected a positive number of nodes, got {n}")
    T = _host_elements(T, n)
    fixed = _host_fixed(fixed, n)
    # node-pair keys a * n_free + b in 32 bits where they fit: their sort is the pattern's largest cost
    free_index = np.full(n, -1, np.int32 if n * n < 2**31 else np.int64)
    free = np.setdiff1d(np.arange(n), fixed)
    free_index[free] = np.arange(len(free))
    nf = len(free)

    F = free_index[T]  # (m, 4) reduced nodes, -1 where fixed
    ra = np.broadcast_to(F[:, :, None], (len(T), 4, 4))
    cb = np.broadcast_to(F[:, None, :], (len(T), 4, 4))
    valid = (ra >= 0) & (cb >= 0)
    keys = sorted_unique((ra * nf + cb)[valid])
    if coupling is not None:
        C = sp.coo_matrix(coupling)
        if C.shape != (n, n):
            raise ValueError(f"coupling: expected shape ({n}, {n}), got {C.shape}")
        a, b = free_index[C.row[C.data != 0]], free_index[C.col[C.data != 0]]
        extra = (a * nf + b)[(a >= 0) & (b >= 0)]
        # most couplings (a mass matrix's) are element pairs already: only the others join the sort
        at = np.minimum(np.searchsorted(keys, extra), max(len(keys) - 1, 0))
        extra = extra[keys[at] != extra] if len(keys) else extra
        if len(extra):
            keys = sorted_unique(np.concatenate([keys, extra]))
    node_rows, node_cols = keys // max(nf, 1), keys % max(nf, 1)
    degree = np.bincount(node_rows, minlength=nf)
    node_indptr = np.concatenate([[0], np.cumsum(degree)])
    nnz = 9 * len(keys)

    # the DOF-level CSR: row 3 a + k holds the blocks (b, c) of node row a in order
    k3 = np.arange(3)
    indptr = np.concatenate([(9 * node_indptr[:-1, None] + 3 * k3 * degree[:, None]).ravel(), [nnz]])
    # node row a stores its pairs once per coordinate k: entry t in [0, 3 degree) of the row uses pair t % degree
    t = np.arange(3 * len(keys)) - np.repeat(3 * node_indptr[:-1], 3 * degree)
    pair_of_entry = np.repeat(node_indptr[:-1], 3 * degree) + t % np.repeat(np.maximum(degree, 1), 3 * degree)
    indices = (3 * node_cols[pair_of_entry][:, None] + k3).ravel()

    if nnz_capacity is not None and (int(nnz_capacity) != nnz_capacity or nnz_capacity < nnz or nf < 1):
        raise CapacityError(
            f"nnz_capacity: expected an int >= the pattern's {nnz} entries (and a free node), got {nnz_capacity!r}"
        )
    stored = nnz if nnz_capacity is None else int(nnz_capacity)
    index = np.int32 if stored + 3 < 2**31 - 1 else np.int64

    # the slot of every element Hessian entry (e, a, k, b, l): _block_slots split into its node-pair part
    # (m, 4, 4) and the coordinate offsets, broadcast once (in 32 bits: 144 m entries)
    kept = (ra >= 0) & (cb >= 0)
    pair = np.searchsorted(keys, np.where(kept, ra * nf + cb, 0))
    start, row_degree = node_indptr[np.where(kept, ra, 0)], degree[np.where(kept, ra, 0)] if nf else 0
    base = np.where(kept, 9 * start + 3 * (pair - start), stored).astype(index)  # stored + c: past the end
    stride = np.where(kept, 3 * row_degree, 0).astype(index)
    slots = (
        base[:, :, None, :, None] + stride[:, :, None, :, None] * k3.astype(index)[:, None, None] + k3.astype(index)
    ).reshape(-1)

    if nnz_capacity is not None:
        pad = stored - nnz
        # padded entries lie past indptr[-1]: the solves and matvec ignore them
        indices = np.concatenate([indices, np.full(pad, 3 * nf - 1, indices.dtype)])
        nnz = stored

    csr = csr_pattern(np.asarray(indptr, index), np.asarray(indices, index), block=3)
    free, free_index, slots = to_devices(*(np.asarray(a, index) for a in (free, free_index, slots)))
    return AssemblyPattern(
        n=n, n_free=nf, nnz=nnz, m=len(T), free=free, free_index=free_index, csr=csr, hessian_slots=slots
    )


def _host_pairs(pattern: AssemblyPattern):
    """The stored node pairs as sorted keys ``a * n_free + b`` (host), with the node-level row pointers."""
    indptr, indices, rows = (np.asarray(a, np.int64) for a in (pattern.indptr, pattern.indices, pattern.rows))
    first = (rows % 3 == 0) & (indices % 3 == 0)  # entry (3 a, 3 b): one per node pair, in CSR order
    keys = rows[first] // 3 * pattern.n_free + indices[first] // 3
    node_indptr = indptr[::3] // 9
    return keys, node_indptr, np.diff(node_indptr)


def scalar_slots(
    pattern: AssemblyPattern, rows: Int[npt.ArrayLike, " k"], cols: Int[npt.ArrayLike, " k"]
) -> Int[np.ndarray, "k 3"]:
    """The data slots of the entries ``(3 r + k, 3 c + k)``, k = 0, 1, 2, of a scalar (n, n) matrix expanded by
    ``(x) I3`` (the mass matrix of eq. 7); host, numpy.

    Args:
        pattern: the ``AssemblyPattern``; every pair (r, c) of free nodes must be stored in it (build it with
            the scalar matrix as ``coupling``).
        rows: (k,) int node rows in [0, n).
        cols: (k,) int node columns in [0, n).
    Returns:
        (k, 3) int slots for ``assemble_scalar``; ``nnz`` (discarded) where r or c is fixed.
    """
    rows, cols = np.asarray(rows), np.asarray(cols)
    if (
        rows.ndim != 1
        or rows.shape != cols.shape
        or not (np.issubdtype(rows.dtype, np.integer) and np.issubdtype(cols.dtype, np.integer))
    ):
        raise ValueError(f"rows, cols: expected two 1-D integer arrays of one length, got {rows.shape}, {cols.shape}")
    if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= pattern.n):
        raise ValueError(f"rows, cols: node indices must lie in [0, {pattern.n})")
    free_index = np.asarray(pattern.free_index, np.int64)
    ra, cb = free_index[rows], free_index[cols]
    valid = (ra >= 0) & (cb >= 0)
    keys, node_indptr, degree = _host_pairs(pattern)
    wanted = np.where(valid, ra * pattern.n_free + cb, 0)
    p = np.minimum(np.searchsorted(keys, wanted), max(len(keys) - 1, 0))
    missing = valid & (keys[p] != wanted) if len(keys) else valid
    if np.any(missing):
        e = int(np.argmax(missing))
        raise ValueError(
            f"rows, cols: the node pair ({rows[e]}, {cols[e]}) is not in the pattern; pass the matrix "
            "as coupling to assembly_pattern"
        )
    k3 = np.arange(3)
    slots = _block_slots(node_indptr, degree, np.where(valid, ra, pattern.n_free)[:, None], p[:, None], k3, k3)
    return np.where(valid[:, None], slots, pattern.nnz)


def assemble_matrix(pattern: AssemblyPattern, H: Float[Array, "m 12 12"]) -> Float[Array, " nnz"]:
    """Sum element 12 x 12 blocks into the reduced CSR matrix (one scatter-add; jit/grad-able).

    Args:
        pattern: the ``AssemblyPattern`` of the elements.
        H: (m, 12, 12) float element matrices in the node-major 12-ordering.
    Returns:
        (nnz,) the CSR data, in the order of ``pattern.indices``.
    """
    H = jnp.asarray(H)
    if H.shape != (pattern.m, 12, 12):
        raise ValueError(f"H: expected shape ({pattern.m}, 12, 12), got {H.shape}")
    return jnp.zeros(pattern.nnz, H.dtype).at[pattern.hessian_slots].add(H.reshape(-1), mode="drop")


def assemble_scalar(
    pattern: AssemblyPattern, slots: Int[Array, "k 3"], values: Float[Array, " k"]
) -> Float[Array, " nnz"]:
    """The CSR data of a scalar (n, n) matrix expanded by ``(x) I3`` and reduced to the free nodes.

    Args:
        pattern: the ``AssemblyPattern``.
        slots: (k, 3) int slots from ``scalar_slots``.
        values: (k,) float entries of the scalar matrix at those (row, col) pairs.
    Returns:
        (nnz,) the CSR data.
    """
    values = jnp.asarray(values)
    if slots.ndim != 2 or slots.shape[1] != 3 or values.shape != slots.shape[:1]:
        raise ValueError(f"slots, values: expected shapes (k, 3) and (k,), got {slots.shape}, {values.shape}")
    return (
        jnp.zeros(pattern.nnz, values.dtype).at[slots].add(jnp.broadcast_to(values[:, None], slots.shape), mode="drop")
    )


def assemble_vector(T: Int[Array, "m 4"], g: Float[Array, "m 12"], n: int) -> Float[Array, "n 3"]:
    """Sum element 12-vectors (node-major) into an (n, 3) nodal array (jit/grad-able).

    Args:
        T: (m, 4) int elements.
        g: (m, 12) float element vectors.
        n: the number of DOF nodes.
    Returns:
        (n, 3) nodal sums.
    """
    T, g = jnp.asarray(T), jnp.asarray(g)
    if T.ndim != 2 or T.shape[1] != 4 or g.shape != (T.shape[0], 12):
        raise ValueError(f"T, g: expected shapes (m, 4) and (m, 12), got {T.shape}, {g.shape}")
    return jax.ops.segment_sum(g.reshape(-1, 3), T.reshape(-1), num_segments=n)


def restrict(pattern: AssemblyPattern, v: Float[Array, "n 3"]) -> Float[Array, " dofs"]:
    """The free rows of a nodal array as a vector in the pattern's DOF order.

    Args:
        pattern: the ``AssemblyPattern``.
        v: (n, 3) nodal values.
    Returns:
        (3 n_free,) ``v[pattern.free].ravel()``.
    """
    if v.shape != (pattern.n, 3):
        raise ValueError(f"v: expected shape ({pattern.n}, 3), got {v.shape}")
    return v[pattern.free].reshape(-1)


def matvec(pattern: AssemblyPattern, data: Float[Array, " nnz"], x: Float[Array, " dofs"]) -> Float[Array, " dofs"]:
    """The product of the reduced CSR matrix with a vector (jit/grad-able).

    Args:
        pattern: the ``AssemblyPattern``.
        data: (nnz,) the matrix's CSR data.
        x: (3 n_free,) the vector.
    Returns:
        (3 n_free,) the product.
    """
    return csr_matvec(pattern.csr, data, x)


def to_scipy(pattern: AssemblyPattern, data: Float[npt.ArrayLike, " nnz"]) -> sp.csr_matrix:
    """The reduced matrix as a scipy CSR matrix (host).

    Args:
        pattern: the ``AssemblyPattern``.
        data: (nnz,) the matrix's CSR data.
    Returns:
        (3 n_free, 3 n_free) ``scipy.sparse.csr_matrix``.
    """
    indptr = np.asarray(pattern.indptr)
    used = int(indptr[-1])  # the rest is padding (``nnz_capacity``)
    return sp.csr_matrix(
        (np.asarray(data)[:used], np.asarray(pattern.indices)[:used], indptr),
        shape=(3 * pattern.n_free, 3 * pattern.n_free),
    )
