"""Linear elasticity on linear tetrahedra, written out in numpy: the independent reference for the FEM
core's validation (a small-load static solution must match it). Textbook P1 stiffness: per tet the
6 x 12 strain-displacement matrix B from the barycentric gradients, the isotropic 6 x 6 material matrix
D (Voigt, engineering shear strains), K_e = V_e B^T D B."""

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as splinalg


def barycentric_gradients(X, T):
    """(m, 4, 3) gradients of the four barycentric coordinates and (m,) volumes, by inverting
    [[1, X_a]] per tet (independent of xfem's shape functions)."""
    A = np.concatenate([np.ones((len(T), 4, 1)), X[T]], axis=2)  # rows [1, x, y, z] per vertex
    coefficients = np.linalg.inv(A)  # column a holds N_a's coefficients [c0, cx, cy, cz]
    return np.transpose(coefficients[:, 1:, :], (0, 2, 1)), np.abs(np.linalg.det(A)) / 6.0


def stiffness(X, T, young: float, poisson: float):
    """The (3n, 3n) linear-elastic stiffness matrix, node-major DOFs [x0, y0, z0, x1, ...]."""
    grads, volumes = barycentric_gradients(X, T)
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    mu = young / (2 * (1 + poisson))
    D = np.zeros((6, 6))
    D[:3, :3] = lam
    D[np.arange(3), np.arange(3)] += 2 * mu
    D[np.arange(3, 6), np.arange(3, 6)] = mu
    m = len(T)
    B = np.zeros((m, 6, 12))
    for a in range(4):
        gx, gy, gz = grads[:, a, 0], grads[:, a, 1], grads[:, a, 2]
        c = 3 * a
        B[:, 0, c], B[:, 1, c + 1], B[:, 2, c + 2] = gx, gy, gz
        B[:, 3, c], B[:, 3, c + 1] = gy, gx  # gamma_xy
        B[:, 4, c + 1], B[:, 4, c + 2] = gz, gy  # gamma_yz
        B[:, 5, c], B[:, 5, c + 2] = gz, gx  # gamma_xz
    Ke = volumes[:, None, None] * np.einsum("mki,kl,mlj->mij", B, D, B)
    dofs = (3 * T[:, :, None] + np.arange(3)).reshape(m, 12)
    rows = np.repeat(dofs, 12, axis=1).ravel()
    cols = np.tile(dofs, (1, 12)).ravel()
    n = 3 * len(X)
    return sp.csr_matrix((Ke.ravel(), (rows, cols)), shape=(n, n))


def static_displacement(X, T, young: float, poisson: float, force, fixed):
    """Solve K u = f with the nodes ``fixed`` clamped (u = 0): (n, 3) displacements."""
    K = stiffness(X, T, young, poisson)
    n = len(X)
    clamped = np.zeros(3 * n, bool)
    clamped[(3 * np.asarray(fixed)[:, None] + np.arange(3)).ravel()] = True
    free = np.flatnonzero(~clamped)
    u = np.zeros(3 * n)
    u[free] = np.asarray(splinalg.spsolve(sp.csc_matrix(K[free][:, free]), np.asarray(force, np.float64).ravel()[free]))
    return u.reshape(n, 3)
