"""libigl's spokes ARAP iteration written out in numpy / scipy, with libigl's own rotation fit in single
or double precision: the independent reference of tests/deform/test_arap.py and benchmarks/bench_arap.py."""

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as splinalg


def libigl_arap_in_numpy(V, F, b, bc, U0, iterations, single_precision):
    """libigl's spokes ARAP iteration written out with scipy, its rotations from libigl's own
    ``fit_rotations`` in single (what ``igl.arap_solve`` uses) or double precision: place the handles,
    fit every cell's rotation, solve ``-L_ff x_f = rhs_f + L_fb bc``."""
    n = len(V)
    L = sp.csr_matrix(igl.cotmatrix(V, F))
    W = (L - sp.diags(L.diagonal())).tocoo()
    i, j, w = W.row, W.col, W.data
    free = np.setdiff1d(np.arange(n), b)
    solve = splinalg.factorized(sp.csc_matrix(-L[free][:, free]))
    boundary = L[free][:, b] @ bc
    v = V[i] - V[j]
    x = U0.copy()
    for _ in range(iterations):
        x[b] = bc
        S = np.zeros((n, 3, 3))
        np.add.at(S, i, w[:, None, None] * v[:, :, None] * (x[i] - x[j])[:, None, :])
        # arap_solve scales S into [-1, 1] first, for its single-precision SVD
        S /= np.abs(S).max()
        R = igl.fit_rotations(S.transpose(1, 0, 2).reshape(3 * n, 3), single_precision)
        R = R.reshape(3, n, 3).transpose(1, 0, 2)
        rhs = np.zeros((n, 3))
        np.add.at(rhs, i, 0.5 * w[:, None] * np.einsum("nkl,nl->nk", R[i] + R[j], v))
        x[free] = np.stack([solve(rhs[free, k] + boundary[:, k]) for k in range(3)], 1)
    return x
