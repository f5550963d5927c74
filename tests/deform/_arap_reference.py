"""libigl's ARAP iteration written out in numpy / scipy for its spokes and spokes-and-rims energies, with
libigl's own rotation fit in single or double precision: the independent reference of
tests/deform/test_arap.py and benchmarks/bench_arap.py."""

import igl
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as splinalg

EDGES = ((1, 2), (2, 0), (0, 1))  # libigl's edge e of a triangle, opposite corner e


def libigl_rotation_blocks(V, F, energy):
    """libigl's ``arap_linear_block`` as triplets (row, rotation, vector): the global step's right-hand side
    is ``rhs[row] += R[rotation] @ vector`` and the covariance ``S[rotation] += vector x[row]^T``. Transcribed
    from libigl's arap_linear_block_spokes / _spokes_and_rims loops, vectorized over faces."""
    C = np.asarray(igl.cotmatrix_entries(V, F))
    rows, rotations, vectors = [], [], []

    def add(row, rotation, vector):
        rows.append(row)
        rotations.append(rotation)
        vectors.append(vector)

    for e, (s, d) in enumerate(EDGES):
        source, dest = F[:, s], F[:, d]
        if energy == "spokes":
            v = 0.5 * C[:, e, None] * (V[source] - V[dest])
            add(source, dest, v)
            add(dest, source, -v)
        else:
            v = C[:, e, None] * (V[source] - V[dest]) / 3.0
            for f, (rs, rd) in enumerate(EDGES):
                if f == e:
                    add(F[:, rs], F[:, rd], v)
                    add(F[:, rd], F[:, rs], -v)
                elif rd == s:
                    add(F[:, rd], F[:, rs], v)
                elif rs == d:
                    add(F[:, rs], F[:, rd], -v)
        add(source, source, v)
        add(dest, dest, -v)
    return np.concatenate(rows), np.concatenate(rotations), np.concatenate(vectors)


def libigl_arap_in_numpy(V, F, b, bc, U0, iterations, single_precision, energy="spokes"):
    """libigl's ARAP iteration (``energy`` "spokes" or "spokes_and_rims") written out with scipy, its
    rotations from libigl's own ``fit_rotations`` in single (what ``igl.arap_solve`` uses) or double
    precision: place the handles, fit every cell's rotation, solve ``-L_ff x_f = rhs_f + L_fb bc``."""
    n = len(V)
    L = sp.csr_matrix(igl.cotmatrix(V, F))
    row, rotation, vector = libigl_rotation_blocks(V, F, energy)
    free = np.setdiff1d(np.arange(n), b)
    solve = splinalg.factorized(sp.csc_matrix(-L[free][:, free]))
    boundary = L[free][:, b] @ bc
    x = U0.copy()
    for _ in range(iterations):
        x[b] = bc
        S = np.zeros((n, 3, 3))
        np.add.at(S, rotation, vector[:, :, None] * x[row][:, None, :])
        # arap_solve scales S into [-1, 1] first, for its single-precision SVD
        S /= np.abs(S).max()
        R = np.asarray(igl.fit_rotations(S.transpose(1, 0, 2).reshape(3 * n, 3), single_precision))
        R = R.reshape(3, n, 3).transpose(1, 0, 2)
        rhs = np.zeros((n, 3))
        np.add.at(rhs, row, np.einsum("nkl,nl->nk", R[rotation], vector))
        x[free] = np.stack([solve(rhs[free, k] + boundary[:, k]) for k in range(3)], 1)
    return x
