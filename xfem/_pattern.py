"""The node-pair sparsity of an element list and the CSR slot of every element Hessian entry, compiled by numba
(``assembly_pattern``'s host work; module docstring of ``xfem._assembly`` for the layout).

Vectorized numpy needs a global sort of the 16 m node-pair keys, a binary search of each, and a 144 m broadcast;
a cut XFEM system repeats that after every cut. Here it is one pass over the node rows: a row's columns come from
the elements at its node (a marker array drops the repeats), are sorted in place (a few dozen), and the element
entries of the row are written with their rank. ``nogil``: the build runs beside a step in a compiling thread.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def _by_row(rows, n_rows):  # pragma: no cover (compiled)
    """Counting sort: row pointers (n_rows + 1,) and the positions of ``rows`` grouped by row, in input order;
    negative rows are left out."""
    pointers = np.zeros(n_rows + 1, np.int64)
    for r in rows:
        if r >= 0:
            pointers[r + 1] += 1
    for r in range(n_rows):
        pointers[r + 1] += pointers[r]
    fill = pointers[:-1].copy()
    order = np.empty(pointers[-1], np.int64)
    for q in range(rows.shape[0]):
        r = rows[q]
        if r >= 0:
            order[fill[r]] = q
            fill[r] += 1
    return pointers, order


@numba.njit(nogil=True, cache=True)
def node_pairs(free_nodes, n_free, extra_rows, extra_cols):  # pragma: no cover (compiled)
    """The node pairs of the reduced system.

    Args:
        free_nodes: (m, 4) int64 reduced node of each element corner, -1 for a fixed node.
        n_free: the number of free nodes.
        extra_rows: (k,) int64 further coupled pairs of free nodes (repeats allowed).
        extra_cols: see ``extra_rows``.
    Returns:
        node_indptr (n_free + 1,) and node_cols (pairs,): the CSR of the node pairs, columns ascending within a
        row; pair (m, 4, 4): the index in node_cols of the pair (corner a, corner b) of each element, -1 where
        either node is fixed. All int64.
    """
    m = free_nodes.shape[0]
    corners, corner_order = _by_row(free_nodes.ravel(), n_free)
    extras, extra_order = _by_row(extra_rows, n_free)
    node_indptr = np.zeros(n_free + 1, np.int64)
    node_cols = np.empty(4 * corners[-1] + extras[-1], np.int64)
    pair = np.full((m, 4, 4), -1, np.int64)
    seen_in = np.full(n_free, -1, np.int64)  # the row that last met each column: repeats are dropped
    rank = np.empty(n_free, np.int64)
    start = 0
    for row in range(n_free):
        count = 0
        for q in range(corners[row], corners[row + 1]):
            e = corner_order[q] // 4
            for b in range(4):
                col = free_nodes[e, b]
                if col >= 0 and seen_in[col] != row:
                    seen_in[col] = row
                    node_cols[start + count] = col
                    count += 1
        for q in range(extras[row], extras[row + 1]):
            col = extra_cols[extra_order[q]]
            if seen_in[col] != row:
                seen_in[col] = row
                node_cols[start + count] = col
                count += 1
        columns = node_cols[start : start + count]
        columns.sort()
        for p in range(count):
            rank[columns[p]] = start + p
        for q in range(corners[row], corners[row + 1]):
            e, a = corner_order[q] // 4, corner_order[q] % 4
            for b in range(4):
                if free_nodes[e, b] >= 0:
                    pair[e, a, b] = rank[free_nodes[e, b]]
        start += count
        node_indptr[row + 1] = start
    return node_indptr, node_cols[:start], pair


@numba.njit(nogil=True, cache=True)
def hessian_maps(free_nodes, node_indptr, pair, discarded, base, stride):  # pragma: no cover (compiled)
    """The scatter map of the element Hessians in its compact form, written into ``base`` and ``stride`` (m, 4, 4):
    entry (e, a, k, b, c), ``H[e, 3 a + k, 3 b + c]``, goes to slot ``base[e, a, b] + k stride[e, a, b] + c``. In
    row 3 r + k (r the free node of corner a) lies the k-th copy of row r's pairs, 3 entries a pair; ``discarded
    + c`` where either node is fixed."""
    for e in range(pair.shape[0]):
        for a in range(4):
            row = free_nodes[e, a]
            start = node_indptr[row] if row >= 0 else 0
            row_stride = 3 * (node_indptr[row + 1] - start) if row >= 0 else 0
            for b in range(4):
                p = pair[e, a, b]
                base[e, a, b] = 9 * start + 3 * (p - start) if p >= 0 else discarded
                stride[e, a, b] = row_stride if p >= 0 else 0


@numba.njit(nogil=True, cache=True)
def block_csr(node_indptr, node_cols, indptr, indices):  # pragma: no cover (compiled)
    """The 3 x 3 block expansion of the node-pair CSR: row 3 a + k holds the columns 3 b + c of row a's nodes b in
    order, c = 0, 1, 2. ``indptr`` (3 n_free + 1,) and ``indices`` (at least 9 pairs) are written in place."""
    n_free = node_indptr.shape[0] - 1
    at = 0
    for row in range(n_free):
        for k in range(3):
            indptr[3 * row + k] = at
            for p in range(node_indptr[row], node_indptr[row + 1]):
                for c in range(3):
                    indices[at] = 3 * node_cols[p] + c
                    at += 1
    indptr[3 * n_free] = at
