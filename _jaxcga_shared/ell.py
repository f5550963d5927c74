"""Sparse matrices with their rows padded to one width (ELL): a GPU sums a padded row in one gather-and-reduce,
where a CSR segment sum needs atomic adds (benchmarks/README.md, "Solves on a GPU"). Private to the
distribution."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, Float, Int

from _jaxcga_shared.host import to_devices


def padded_rows(rows, columns, values, n: int, fill: int | None = None):
    """Entries sorted by row then column (host, numpy) as padded (n, k) tables, k the longest row (at least 1):
    the columns padded with ``fill`` (None: the row's own index), each array of ``values`` (per entry, any
    trailing shape) with zeros. Returns the column table and the list of value tables."""
    counts = np.bincount(rows, minlength=n)
    slot = np.arange(len(rows)) - np.repeat(np.cumsum(counts) - counts, counts)
    k = max(int(counts.max(initial=0)), 1)
    table = np.repeat(np.arange(n)[:, None], k, axis=1) if fill is None else np.full((n, k), fill)
    table[rows, slot] = columns
    padded = []
    for v in values:
        out = np.zeros((n, k) + v.shape[1:])
        out[rows, slot] = v
        padded.append(out)
    return table, padded


class ELLMatrix(eqx.Module):
    """A sparse matrix with its rows padded to one width: row i is ``sum_k values[i, k] x[columns[i, k]]``
    (padding: value 0)."""

    columns: Int[Array, "n width"]
    values: Float[Array, "n width"]


def ell_matrix(M) -> ELLMatrix:
    """The ELL form of a scipy sparse matrix (host; device arrays)."""
    M = sp.csr_matrix(M)
    M.sort_indices()
    # scipy is not annotated: pyright infers from its code that a matrix's shape may be None
    n_rows, n_columns = M.shape  # pyright: ignore[reportOptionalIterable, reportGeneralTypeIssues]
    rows = np.repeat(np.arange(n_rows), np.diff(M.indptr))
    columns, (values,) = padded_rows(rows, M.indices, [M.data], n_rows, fill=0)
    columns, values = to_devices(columns.astype(np.int32 if n_columns < 2**31 else np.int64), values)
    return ELLMatrix(columns, values)


def ell_matvec(M: ELLMatrix, x):
    """``M x`` for x of shape (columns,) or (columns, k), in x's dtype (a product and a sum, not a dot: no
    reduced-precision matrix unit)."""
    values = M.values.astype(x.dtype)
    return jnp.sum((values if x.ndim == 1 else values[..., None]) * x[M.columns], axis=1)
