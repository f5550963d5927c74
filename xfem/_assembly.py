"""Sparse assembly of the backward Euler system of the XFEM paper, sec. 3.3: the 3n x 3n matrix
``M (x) I3 + h^2 d^2U/dx^2`` (eq. 7, 9, 10) and the 3n vectors of eq. 6 and 8, summed from per-element
12-vectors and 12 x 12 blocks.

The sparsity is fixed by the element list (and, for XFEM's custom mass entries, by extra node couplings),
so ``assembly_pattern`` computes it once on the host (loops compiled by numba, ``xfem._pattern``): the CSR
structure of the matrix and, for the ``144 m`` element Hessian entries, the CSR data slots they add into
(kept as a base and a stride per element node pair, ``element_slots``). Assembly in JAX is then a single
scatter-add (``assemble_matrix``, ``add_element_hessians``), jit- and grad-able: each row of a 3 x 3 block is 3
consecutive slots, so it adds rows of 3 (a window scatter of 48 starts an element, which XLA's CPU scatter runs
several times faster than 144 single entries). Dirichlet conditions are applied by substitution: the
pattern of the free nodes only (the fixed nodes' rows and columns removed) is built directly, and entries
touching a fixed node go to a discarded slot.

Node ordering: DOF ``3 i + k`` is coordinate k of node i, the element 12-ordering is node-major (entry
``3 a + k`` is coordinate k of the element's local node a). The CSR of node pairs is expanded to 3 x 3
blocks, so row ``3 a + k`` of the reduced matrix holds the columns ``3 b + c`` of the free nodes b coupled
with free node a, b ascending, c = 0, 1, 2.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Array, Float, Int

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import check_index_range
from _jaxcga_shared.host import to_devices
from _jaxcga_shared.sparse import CSRPattern, csr_pattern
from _jaxcga_shared.sparse import matvec as sparse_matvec


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
        hessian_base, hessian_stride: (m, 4, 4) the scatter map of the element Hessians, compact: entry
            ``H[e, 3 a + k, 3 b + c]`` adds into slot ``base[e, a, b] + k stride[e, a, b] + c``
            (``hessian_slots``; 32 integers an element where the slots are 144, expanded on the device).
    """

    n: int = eqx.field(static=True)
    n_free: int = eqx.field(static=True)
    nnz: int = eqx.field(static=True)
    m: int = eqx.field(static=True)
    free: Int[Array, " n_free"]
    free_index: Int[Array, " n"]
    csr: CSRPattern
    hessian_base: Int[Array, "m 4 4"]
    hessian_stride: Int[Array, "m 4 4"]

    @property
    def hessian_slots(self) -> Int[Array, " entries"]:
        """(144 m,) the data slot of each element Hessian entry ``H[e, r, c]`` (flattened in C order); ``nnz`` or
        more (out of bounds) for entries on a fixed node's row or column, which are discarded."""
        return element_slots(self.hessian_base, self.hessian_stride).reshape(-1)

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
    if len(sorted_unique(fixed)) != len(fixed):
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
    ``np.unique`` of integers, 2-10x slower than a sort on 10^5 to 10^6 of them."""
    ordered = np.sort(values, axis=None)
    return ordered[np.concatenate([[True], ordered[1:] != ordered[:-1]])] if len(ordered) else ordered


def element_slots(base: Int[Array, "*m 4 4"], stride: Int[Array, "*m 4 4"]) -> Int[Array, "*m 144"]:
    """The data slots of whole element Hessians, (..., 144) in ``H[e].ravel()`` order, from the compact map
    (``AssemblyPattern.hessian_base``, ``hessian_stride``); jit-able: the step expands them chunk by chunk."""
    k = jnp.arange(3, dtype=base.dtype)
    rows = stride[..., :, None, :, None] * lift_rank(k[:, None, None], stride.ndim + 2)
    slots = base[..., :, None, :, None] + rows + lift_rank(k, stride.ndim + 2)
    return slots.reshape(*base.shape[:-2], 144)


_ROWS_OF_THREE = jax.lax.ScatterDimensionNumbers(
    update_window_dims=(1,), inserted_window_dims=(), scatter_dims_to_operand_dims=(0,)
)


def add_element_hessians(
    data: Float[Array, " c"], base: Int[Array, "m 4 4"], stride: Int[Array, "m 4 4"], H: Float[Array, "m 12 12"]
) -> Float[Array, " c"]:
    """``data`` plus the element Hessians ``H`` at their slots (``element_slots(base, stride)``), a row of 3 of a
    3 x 3 block at a time (module docstring). Rows whose slots are out of bounds (a fixed node's) are dropped."""
    k = jnp.arange(3, dtype=base.dtype)
    starts = base[:, :, None, :] + k[None, None, :, None] * stride[:, :, None, :]  # (m, a, k, b)
    rows = H.reshape(-1, 4, 3, 4, 3)  # (m, a, k, b, l): the row (a, k) of block (a, b) is l = 0, 1, 2
    return jax.lax.scatter_add(
        data, starts.reshape(-1, 1), rows.reshape(-1, 3), _ROWS_OF_THREE, mode=jax.lax.GatherScatterMode.FILL_OR_DROP
    )


class _HostPattern(NamedTuple):
    """What ``scalar_slots`` reads of a pattern, on the host (int64): the stored node pairs as sorted keys
    ``a * n_free + b``, the node-level row pointers and row lengths, and the free index of each node."""

    keys: np.ndarray
    node_indptr: np.ndarray
    degree: np.ndarray
    free_index: np.ndarray


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
        nnz_capacity: None, or the entries to store, at least the pattern's (``CapacityError`` otherwise): the
            rest is padding, so that systems of one capacity share their shapes.
    Returns:
        The ``AssemblyPattern``.
    """
    return _assembly_pattern(T, n, fixed, coupling, nnz_capacity)[0]


def _assembly_pattern(
    T, n, fixed, coupling, nnz_capacity, on_host: bool = False
) -> tuple[AssemblyPattern, _HostPattern]:
    """``assembly_pattern`` and its ``_HostPattern`` (for ``_scalar_slots``); ``on_host``: numpy arrays instead of
    device arrays (``to_devices``)."""
    from xfem._pattern import block_csr, hessian_maps, node_pairs  # numba: imported on first use

    n = int(n)
    if n < 1:
        raise ValueError(f"n: expected a positive number of nodes, got {n}")
    T = _host_elements(T, n)
    fixed = _host_fixed(fixed, n)
    is_free = np.ones(n, bool)
    is_free[fixed] = False
    free = np.flatnonzero(is_free)
    free_index = np.full(n, -1, np.int64)
    free_index[free] = np.arange(len(free))
    nf = len(free)
    extra_rows = extra_cols = np.zeros(0, np.int64)
    if coupling is not None:
        C = sp.coo_matrix(coupling)
        if C.shape != (n, n):
            raise ValueError(f"coupling: expected shape ({n}, {n}), got {C.shape}")
        a, b = free_index[C.row[C.data != 0]], free_index[C.col[C.data != 0]]
        extra_rows, extra_cols = a[(a >= 0) & (b >= 0)], b[(a >= 0) & (b >= 0)]
    F = free_index[T]  # (m, 4) reduced nodes, -1 where fixed
    node_indptr, node_cols, pair = node_pairs(F, nf, extra_rows, extra_cols)
    nnz = 9 * len(node_cols)
    if nnz_capacity is not None and (int(nnz_capacity) != nnz_capacity or nnz_capacity < nnz or nf < 1):
        raise CapacityError(
            f"nnz_capacity: expected an int >= the pattern's {nnz} entries (and a free node), got {nnz_capacity!r}"
        )
    stored = nnz if nnz_capacity is None else int(nnz_capacity)
    index = np.int32 if stored + 3 < 2**31 - 1 else np.int64
    # the DOF-level CSR (module docstring); padded entries lie past indptr[-1]: the solves and matvec ignore them
    indptr = np.empty(3 * nf + 1, index)
    indices = np.full(stored, 3 * nf - 1, index)
    block_csr(node_indptr, node_cols, indptr, indices)
    base, stride = np.empty((len(T), 4, 4), index), np.empty((len(T), 4, 4), index)
    hessian_maps(F, node_indptr, pair, stored, base, stride)

    on_device = to_devices(*(np.asarray(a, index) for a in (free, free_index, base, stride)), on_host=on_host)
    pattern = AssemblyPattern(
        n=n,
        n_free=nf,
        nnz=stored,
        m=len(T),
        free=on_device[0],
        free_index=on_device[1],
        csr=csr_pattern(indptr, indices, block=3, full_blocks=True, on_host=on_host),  # block_csr: full blocks
        hessian_base=on_device[2],
        hessian_stride=on_device[3],
    )
    degree = np.diff(node_indptr)
    keys = np.repeat(np.arange(nf, dtype=np.int64), degree) * nf + node_cols
    return pattern, _HostPattern(keys, node_indptr, degree, free_index)


def _host_pattern(pattern: AssemblyPattern) -> _HostPattern:
    """The ``_HostPattern`` of a pattern, read back from its arrays."""
    indptr, indices, rows = (np.asarray(a, np.int64) for a in (pattern.indptr, pattern.indices, pattern.rows))
    first = (rows % 3 == 0) & (indices % 3 == 0)  # entry (3 a, 3 b): one per node pair, in CSR order
    keys = rows[first] // 3 * pattern.n_free + indices[first] // 3
    node_indptr = indptr[::3] // 9
    return _HostPattern(keys, node_indptr, np.diff(node_indptr), np.asarray(pattern.free_index, np.int64))


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
    return _scalar_slots(pattern, _host_pattern(pattern), rows, cols)


def _scalar_slots(pattern: AssemblyPattern, host: _HostPattern, rows, cols) -> np.ndarray:
    """``scalar_slots`` from the pattern's ``_HostPattern``."""
    rows, cols = np.asarray(rows), np.asarray(cols)
    if (
        rows.ndim != 1
        or rows.shape != cols.shape
        or not (np.issubdtype(rows.dtype, np.integer) and np.issubdtype(cols.dtype, np.integer))
    ):
        raise ValueError(f"rows, cols: expected two 1-D integer arrays of one length, got {rows.shape}, {cols.shape}")
    if rows.size and (min(rows.min(), cols.min()) < 0 or max(rows.max(), cols.max()) >= pattern.n):
        raise ValueError(f"rows, cols: node indices must lie in [0, {pattern.n})")
    keys, node_indptr, degree, free_index = host
    ra, cb = free_index[rows], free_index[cols]
    valid = (ra >= 0) & (cb >= 0)
    wanted = np.where(valid, ra * pattern.n_free + cb, 0)
    p = np.minimum(np.searchsorted(keys, wanted), max(len(keys) - 1, 0))
    missing = valid & (keys[p] != wanted) if len(keys) else valid
    if np.any(missing):
        e = int(np.argmax(missing))
        raise ValueError(
            f"rows, cols: the node pair ({rows[e]}, {cols[e]}) is not in the pattern; pass the matrix "
            "as coupling to assembly_pattern"
        )
    # row 3 a + k of node row a holds its pairs' 3-entry blocks once per k: slot of (3 a + k, 3 b + k)
    a = np.where(valid, ra, 0)[:, None]
    k3 = np.arange(3)
    slots = 9 * node_indptr[a] + 3 * k3 * degree[a] + 3 * (p[:, None] - node_indptr[a]) + k3
    return np.where(valid[:, None], slots, pattern.nnz)


def assemble_matrix(pattern: AssemblyPattern, H: Float[Array, "m 12 12"]) -> Float[Array, " nnz"]:
    """Sum element 12 x 12 blocks into the reduced CSR matrix (one scatter-add, ``add_element_hessians``;
    jit/grad-able).

    Args:
        pattern: the ``AssemblyPattern`` of the elements.
        H: (m, 12, 12) float element matrices in the node-major 12-ordering.
    Returns:
        (nnz,) the CSR data, in the order of ``pattern.indices``.
    """
    H = jnp.asarray(H)
    if H.shape != (pattern.m, 12, 12):
        raise ValueError(f"H: expected shape ({pattern.m}, 12, 12), got {H.shape}")
    return add_element_hessians(jnp.zeros(pattern.nnz, H.dtype), pattern.hessian_base, pattern.hessian_stride, H)


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
    return sparse_matvec(pattern.csr, data)(x)


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
