"""Harmonic fields on a triangle mesh: sec. VIII of the CGA mesh-deformation paper.

A field ``l`` solves Laplace's equation ``L l = 0`` on the free vertices with Dirichlet values on
constrained vertex sets (handles, fixed regions). With the rows of the constrained vertices removed,
the free values solve ``L_ff l_f = -L_fc l_c``; ``L_ff`` is factored once (``harmonic_precompute``) and
every set of boundary values is one back-substitution (``HarmonicSolver``), a JAX function of those
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

from typing import Sequence

import igl
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from _jaxcga_shared.sparse import SparseSolver

LAPLACIANS = ("cotangent", "mean_value")


def _check_mesh(V, F):
    V = np.asarray(V, np.float64)
    F = np.asarray(F)
    if V.ndim != 2 or V.shape[1] != 3 or not np.all(np.isfinite(V)):
        raise ValueError(f"V: expected finite positions of shape (n, 3), got {V.shape}")
    if F.ndim != 2 or F.shape[1] != 3 or not np.issubdtype(F.dtype, np.integer) or len(F) == 0:
        raise ValueError(f"F: expected integer faces of shape (m, 3), m > 0, got {F.dtype} {F.shape}")
    if F.min() < 0 or F.max() >= len(V):
        raise ValueError(f"F: vertex indices must lie in [0, {len(V)})")
    return V, F.astype(np.int64)


def mean_value_laplacian(V, F) -> sp.csr_matrix:
    """Floater's mean-value Laplacian (n, n): ``L_ij = w_ij``, ``L_ii = -sum_j w_ij`` (rows sum to 0)."""
    V, F = _check_mesh(V, F)
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


def laplacian(V, F, weights: str = "cotangent") -> sp.sparray:
    """The mesh Laplacian (n, n) with ``weights`` in ``LAPLACIANS``; rows sum to zero (a scipy sparse
    matrix: CSC for cotangent weights, as libigl returns it; CSR for mean-value weights)."""
    if weights not in LAPLACIANS:
        raise ValueError(f"weights: expected one of {LAPLACIANS}, got {weights!r}")
    if weights == "mean_value":
        return mean_value_laplacian(V, F)
    V, F = _check_mesh(V, F)
    return sp.csc_matrix(igl.cotmatrix(V, F))


class HarmonicSolver:
    """Precomputed Dirichlet problem (``harmonic_precompute``). Call it on boundary values
    ``bc (c,)`` or ``(c, h)`` (one column per field, rows in the order of ``constrained``) to get the
    fields ``(n,)`` or ``(n, h)`` at every vertex: a JAX function of ``bc``."""

    def __init__(self, L, constrained, n: int, symmetric: bool):
        self.n = n
        self.constrained = constrained
        is_free = np.ones(n, bool)
        is_free[constrained] = False
        self.free = np.flatnonzero(is_free)  # a mask, not setdiff1d: that sorts (0.1 s at 160k)
        L = sp.csc_matrix(L)  # columns, then rows: 7 ms at 130k vertices, against 50 ms for rows first on CSR
        self._coupling = L[:, constrained][self.free].tocsr()  # L_fc
        self._solve = SparseSolver(-L[:, self.free][self.free], symmetric=symmetric)

    def _check_bc(self, bc):
        if bc.ndim not in (1, 2) or bc.shape[0] != len(self.constrained):
            raise ValueError(f"bc: expected shape ({len(self.constrained)},) or ({len(self.constrained)}, h), "
                             f"got {bc.shape}")

    def host(self, bc) -> np.ndarray:
        """The fields for boundary values known on the host, in numpy (float64): the same values as a
        call, without JAX's per-operation dispatch (85 ms at 130k vertices)."""
        bc = np.asarray(bc, np.float64)
        self._check_bc(bc)
        out = np.empty((self.n,) + bc.shape[1:])
        out[self.constrained] = bc
        out[self.free] = self._solve.host_solve(self._coupling @ bc)
        return out

    def __call__(self, bc):
        bc = jnp.asarray(bc)
        self._check_bc(bc)
        if not jnp.issubdtype(bc.dtype, jnp.floating):
            bc = bc.astype(jnp.float64)
        coupling = _sparse_matmul(self._coupling, bc)
        free_values = self._solve(coupling)  # -L_ff l_f = L_fc l_c
        out = jnp.zeros((self.n,) + bc.shape[1:], bc.dtype)
        return out.at[self.constrained].set(bc).at[self.free].set(free_values)


def _sparse_matmul(A: sp.csr_matrix, x):
    """``A @ x`` for a constant scipy CSR matrix and a JAX array (rows gathered and summed)."""
    A = A.tocoo()
    rows, cols = np.asarray(A.row), np.asarray(A.col)
    values = jnp.asarray(A.data, x.dtype)
    contributions = values.reshape((-1,) + (1,) * (x.ndim - 1)) * x[cols]
    return jnp.zeros((A.shape[0],) + x.shape[1:], x.dtype).at[rows].add(contributions)


def harmonic_precompute(V, F, constrained, weights: str = "cotangent") -> HarmonicSolver:
    """Factor the Dirichlet problem of ``weights``' Laplacian with the vertices ``constrained`` fixed.

    Args:
        V: (n, 3) vertex positions. F: (m, 3) int faces.
        constrained: (c,) int distinct vertex indices with prescribed values.
        weights: ``"cotangent"`` or ``"mean_value"``.
    Raises:
        ValueError: bad mesh, indices out of range or repeated, no constrained or no free vertex, or
            a free part with no path to a constrained vertex (the system is singular)."""
    V, F = _check_mesh(V, F)
    constrained = np.asarray(constrained)
    if constrained.ndim != 1 or not np.issubdtype(constrained.dtype, np.integer) or len(constrained) == 0:
        raise ValueError(f"constrained: expected a non-empty 1-D array of vertex indices, got {constrained!r}")
    if constrained.min() < 0 or constrained.max() >= len(V):
        raise ValueError(f"constrained: vertex indices must lie in [0, {len(V)})")
    if len(np.unique(constrained)) != len(constrained):
        raise ValueError("constrained: a vertex is listed twice")
    if len(constrained) == len(V):
        raise ValueError("constrained: every vertex is constrained; nothing to solve")
    L = laplacian(V, F, weights)
    # every connected part of the mesh needs a constrained vertex, or L_ff is singular there
    parts, labels = connected_components(L, directed=False)
    reached = np.zeros(parts, bool)
    reached[labels[constrained]] = True
    unreached = np.flatnonzero(~reached)
    if len(unreached):
        raise ValueError(f"constrained: {len(unreached)} connected part(s) of the mesh hold no constrained vertex "
                         f"(e.g. vertex {int(np.flatnonzero(labels == unreached[0])[0])}); their fields are undefined")
    return HarmonicSolver(L, constrained, len(V), symmetric=weights == "cotangent")


def harmonic_fields(V, F, handles: Sequence, weights: str = "cotangent"):
    """One harmonic field per handle (sec. VIII): 1 on the handle's vertices, 0 on the other handles',
    harmonic elsewhere; the fields sum to one at every vertex.

    Args:
        V: (n, 3) vertex positions. F: (m, 3) int faces.
        handles: h >= 1 disjoint, non-empty index arrays (the fixed region counts as a handle).
        weights: ``"cotangent"`` or ``"mean_value"``.
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
    return jnp.asarray(harmonic_precompute(V, F, constrained, weights).host(bc))  # constant bc: no autodiff needed
