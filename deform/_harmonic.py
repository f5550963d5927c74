"""Harmonic fields on a triangle mesh: sec. VIII of the CGA mesh-deformation paper.

A field ``l`` solves Laplace's equation ``L l = 0`` on the free vertices with Dirichlet values on
constrained vertex sets (handles, fixed regions). With the rows of the constrained vertices removed,
the free values solve ``L_ff l_f = -L_fc l_c``; ``L_ff`` is factored once (``harmonic_precompute``) and
every set of boundary values is one back-substitution (``harmonic_solve``), a JAX function of those
values (differentiable, jit- and vmap-able).

Weights of ``L``:

* ``"cotangent"``: ``igl.cotmatrix`` (symmetric, ``L_ij = (cot a_ij + cot b_ij) / 2``); the fields are
  then exactly those of ``igl.harmonic(V, F, b, bc, 1)``.
* ``"mean_value"``: Floater's mean-value weights ``w_ij = (tan(g_ij / 2) + tan(d_ij / 2)) / |v_j - v_i|``
  with g, d the angles at v_i of the two triangles on edge ij (libigl's Python bindings have no
  mean-value Laplacian, so it is assembled here, vectorized). The weights are positive, so the fields
  obey the maximum principle even on obtuse meshes; the matrix is not symmetric.

``harmonic_fields(V, F, handles)`` gives one field per handle, 1 on its own vertices and 0 on the other
handles' (the fixed region is a handle whose motion is the identity), so the fields sum to one.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import igl
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_choice, check_index_range, check_triangle_mesh
from _jaxcga_shared.sparse import SparseSolver
from deform._parts import UNHANDLED, mesh_parts

LAPLACIANS = ("cotangent", "mean_value")


def mean_value_laplacian(V: Float[ArrayLike, "n 3"], F: Int[ArrayLike, "m 3"]) -> sp.csr_matrix:
    """Floater's mean-value Laplacian (n, n): ``L_ij = w_ij``, ``L_ii = -sum_j w_ij`` (rows sum to 0).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int faces.

    Returns:
        (n, n) the scipy CSR matrix.
    """
    V, F = check_triangle_mesh(V, F)
    rows, cols, values = [], [], []
    for k in range(3):
        a, b, c = F[:, k], F[:, (k + 1) % 3], F[:, (k + 2) % 3]
        u, w = V[b] - V[a], V[c] - V[a]
        lu, lw = np.linalg.norm(u, axis=1), np.linalg.norm(w, axis=1)
        # tan(theta / 2) = (|u||w| - u.w) / |u x w| for the corner angle theta at a
        half = (lu * lw - np.einsum("ij,ij->i", u, w)) / np.linalg.norm(np.cross(u, w), axis=1)
        rows += [a, a]
        cols += [b, c]
        values += [half / lu, half / lw]
    rows, cols, values = np.concatenate(rows), np.concatenate(cols), np.concatenate(values)
    if not np.all(np.isfinite(values)):
        raise ValueError("F: a degenerate face (zero area or a repeated vertex) has no mean-value weights")
    n = len(V)
    W = sp.csr_matrix((values, (rows, cols)), shape=(n, n))
    return (W - sp.diags(np.asarray(W.sum(axis=1)).ravel())).tocsr()


def laplacian(
    V: Float[ArrayLike, "n 3"], F: Int[ArrayLike, "m 3"], kind: str = "cotangent"
) -> sp.csc_matrix | sp.csr_matrix:
    """The mesh Laplacian (n, n) with the weights ``kind`` in ``LAPLACIANS``; rows sum to zero (a scipy sparse
    matrix: CSC for cotangent weights, as libigl returns it; CSR for mean-value weights).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int faces.
        kind: ``"cotangent"`` or ``"mean_value"``.

    Returns:
        (n, n) the scipy sparse Laplacian.

    Examples:
        >>> import numpy as np
        >>> import deform
        >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> L = deform.laplacian(V, np.array([[0, 1, 2], [0, 2, 3]]))
        >>> L.shape, bool(np.allclose(L.sum(axis=1), 0.0))
        ((4, 4), True)
    """
    return _laplacian(V, F, kind)


def _laplacian(V, F, kind: str) -> sp.csc_matrix | sp.csr_matrix:
    # ``laplacian``'s body, also reached from ``harmonic_precompute``, whose keyword ``laplacian`` shadows it
    check_choice("kind", kind, LAPLACIANS)
    if kind == "mean_value":
        return mean_value_laplacian(V, F)
    V, F = check_triangle_mesh(V, F)
    return sp.csc_matrix(igl.cotmatrix(V, F))


class HarmonicData(eqx.Module):
    """The factored Dirichlet problem (``harmonic_precompute``), the argument of ``harmonic_solve``.

    Attributes:
        constrained: (c,) the vertices with prescribed values. free: (f,) the other vertices, in order.
        coupling_rows, coupling_columns, coupling_values: ``L_fc`` (f, c) in coordinate form.
        solver: ``-L_ff``, factored. n: the number of vertices.
    """

    # numpy, float64: the host solve keeps full precision, the JAX solve casts to the values' dtype
    constrained: Int[np.ndarray, " c"]
    free: Int[np.ndarray, " f"]
    coupling_rows: Int[np.ndarray, " e"]
    coupling_columns: Int[np.ndarray, " e"]
    coupling_values: Float[np.ndarray, " e"]
    solver: SparseSolver = eqx.field(static=True)
    n: int = eqx.field(static=True)


def _check_bc(data: HarmonicData, bc):
    c = len(data.constrained)
    if bc.ndim not in (1, 2) or bc.shape[0] != c:
        raise ValueError(f"bc: expected shape ({c},) or ({c}, h), got {bc.shape}")


def _host_solve(data: HarmonicData, bc) -> np.ndarray:
    """``harmonic_solve`` for boundary values known on the host, in numpy (float64): the same values, without
    JAX's per-operation dispatch."""
    bc = np.asarray(bc, np.float64)
    _check_bc(data, bc)
    coupling = sp.csr_matrix(
        (data.coupling_values, (data.coupling_rows, data.coupling_columns)),
        shape=(len(data.free), len(data.constrained)),
    )
    out = np.empty((data.n,) + bc.shape[1:])
    out[data.constrained] = bc
    out[data.free] = data.solver.host_solve(coupling @ bc)
    return out


def harmonic_solve(data: HarmonicData, bc: Float[ArrayLike, "c ..."]) -> Float[Array, "n ..."]:
    """The harmonic fields for boundary values ``bc``: a JAX function of ``bc`` (differentiable, jit- and
    vmap-able).

    Args:
        data: ``harmonic_precompute``'s output.
        bc: (c,) or (c, h) boundary values, one column per field, rows in the order of ``constrained``.
    Returns:
        (n,) or (n, h) the fields at every vertex."""
    if not isinstance(data, HarmonicData):
        raise ValueError("data: expected the HarmonicData returned by harmonic_precompute")
    bc = jnp.asarray(bc)
    _check_bc(data, bc)
    if not jnp.issubdtype(bc.dtype, jnp.floating):
        bc = bc.astype(jnp.float64)
    # L_fc l_c, rows gathered and summed
    values = jnp.asarray(data.coupling_values, bc.dtype).reshape((-1,) + (1,) * (bc.ndim - 1))
    coupling = (
        jnp.zeros((len(data.free),) + bc.shape[1:], bc.dtype)
        .at[data.coupling_rows]
        .add(values * bc[data.coupling_columns])
    )
    free_values = data.solver(coupling)  # -L_ff l_f = L_fc l_c
    out = jnp.zeros((data.n,) + bc.shape[1:], bc.dtype)
    return out.at[data.constrained].set(bc).at[data.free].set(free_values)


def harmonic_precompute(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    constrained: Int[ArrayLike, " c"],
    *,
    laplacian: str = "cotangent",
    unhandled: str = "follow",
) -> HarmonicData:
    """Factor the Dirichlet problem of the Laplacian ``laplacian`` with the vertices ``constrained`` fixed.

    A connected part of the mesh with no constrained vertex follows the part it is attached or nearest to
    (``deform.mesh_parts``): bridges, extra edges of the Laplacian from its vertices facing that part to their
    nearest vertices there, carry the field over, so that the system is never singular and the fields stay a
    partition of unity.

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int faces.
        constrained: (c,) int distinct vertex indices with prescribed values.
        laplacian: ``"cotangent"`` or ``"mean_value"`` (``LAPLACIANS``).
        unhandled: ``"follow"`` (default: parts without a constrained vertex follow, as above) or ``"error"``
            (a ValueError naming those parts).
    Returns:
        ``HarmonicData``, the argument of ``harmonic_solve``.
    Raises:
        ValueError: bad mesh, indices out of range or repeated, no constrained or no free vertex, or (with
            ``unhandled="error"``) a part with no constrained vertex."""
    check_choice("laplacian", laplacian, LAPLACIANS)
    check_choice("unhandled", unhandled, UNHANDLED)
    V, F = check_triangle_mesh(V, F)
    constrained = np.asarray(constrained)
    if constrained.ndim != 1 or not np.issubdtype(constrained.dtype, np.integer) or len(constrained) == 0:
        raise ValueError(f"constrained: expected a non-empty 1-D array of vertex indices, got {constrained!r}")
    check_index_range("constrained", constrained, len(V))
    if len(np.unique(constrained)) != len(constrained):
        raise ValueError("constrained: a vertex is listed twice")
    if len(constrained) == len(V):
        raise ValueError("constrained: every vertex is constrained; nothing to solve")
    parts = mesh_parts(V, F, constrained, unhandled=unhandled)
    L = _laplacian(V, F, laplacian)
    if len(parts.bridges):
        L = L + parts.laplacian()
    n = len(V)
    is_free = np.ones(n, bool)
    is_free[constrained] = False
    free = np.flatnonzero(is_free)  # a mask, not setdiff1d: that sorts (0.1 s at 160k)
    L = sp.csc_matrix(L)  # columns, then rows: 7 ms at 130k vertices, against 50 ms for rows first on CSR
    coupling = L[:, constrained][free].tocoo()  # L_fc
    solver = SparseSolver(-L[:, free][free], symmetric=laplacian == "cotangent")
    return HarmonicData(
        constrained.astype(np.int64),
        free,
        coupling.row.astype(np.int64),
        coupling.col.astype(np.int64),
        coupling.data,
        solver,
        n,
    )


def harmonic_fields(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    handles: Sequence[Int[ArrayLike, "*k"]],
    *,
    laplacian: str = "cotangent",
    unhandled: str = "follow",
) -> Float[Array, "n h"]:
    """One harmonic field per handle (sec. VIII): 1 on the handle's vertices, 0 on the other handles',
    harmonic elsewhere; the fields sum to one at every vertex.

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int faces.
        handles: h >= 1 disjoint, non-empty index arrays (the fixed region counts as a handle).
        laplacian: ``"cotangent"`` or ``"mean_value"``.
        unhandled: ``"follow"`` (default: a connected part without a handle takes the fields of the part it is
            attached or nearest to, ``harmonic_precompute``) or ``"error"``.
    Returns:
        (n, h) fields, a JAX array."""
    if isinstance(handles, np.ndarray) or len(handles) == 0:
        raise ValueError("handles: expected a sequence of index arrays, one per handle")
    parts = [np.asarray(h).reshape(-1) for h in handles]
    if any(len(p) == 0 for p in parts):
        raise ValueError("handles: every handle needs at least one vertex")
    constrained = np.concatenate(parts)
    if len(np.unique(constrained)) != len(constrained):
        raise ValueError("handles: the handles must be disjoint (a vertex is in two handles or twice in one)")
    bc = np.zeros((len(constrained), len(parts)))
    bc[np.arange(len(constrained)), np.repeat(np.arange(len(parts)), [len(p) for p in parts])] = 1.0
    data = harmonic_precompute(V, F, constrained, laplacian=laplacian, unhandled=unhandled)
    return jnp.asarray(_host_solve(data, bc))  # constant bc: no autodiff needed
