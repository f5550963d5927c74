"""Linear tetrahedral elements: the shape functions of eq. 5 with ``P(X) = [1 X Y Z]`` (sec. 3.2 of the XFEM
paper), and the exact mass matrix (eq. 7) and body force (eq. 8) of sec. 3.3 for them.

Shape functions. Solving eq. 5, ``P(X_i)^T a_j = delta_ij`` over the four nodes of a tet, gives its
barycentric coordinates: with ``D = [X1 - X0, X2 - X0, X3 - X0]`` (columns), ``(N1, N2, N3) = D^-1 (X - X0)``
and ``N0 = 1 - N1 - N2 - N3``. The rows of ``D^-1`` are ``(b x c, c x a, a x b) / det D`` for the columns
a, b, c (no general inverse, so gradients in X stay cheap and exact), and ``grad N0 = -(sum of the others)``.
The deformation gradient of deformed positions x is ``F_e = sum_a x_{T[e, a]} grads[e, a]^T``.

Mass and force. For linear shape functions the integrals are closed forms (``int_e l1^i l2^j l3^k l4^l =
6 V_e i! j! k! l! / (i + j + k + l + 3)!`` for barycentric coordinates l): ``int_e N_a N_b = V_e (1 + delta_ab)
/ 20`` and ``int_e N_a = V_e / 4``. Eq. 7's
block ``M_ij = (...) (x) I_3`` is returned as its scalar factor: one (n, n) matrix used for each of the
three components.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_points, check_positive, require
from _jaxcga_shared.platform import EXACT
from xfem._tetmesh import (
    _bad_index,
    _host_tets,
    _host_volumes,
    _index_message,
    _jax_mesh_arrays,
)


def _gradients(x):
    """Shape-function gradients (..., 4, 3) and 6 x signed volume (...,) of tets with corners x (..., 4, 3)."""
    a, b, c = x[..., 1, :] - x[..., 0, :], x[..., 2, :] - x[..., 0, :], x[..., 3, :] - x[..., 0, :]
    bc, ca, ab = jnp.cross(b, c), jnp.cross(c, a), jnp.cross(a, b)
    det = jnp.sum(a * bc, axis=-1)
    rows = jnp.stack([bc, ca, ab], axis=-2) / det[..., None, None]
    return jnp.concatenate([-jnp.sum(rows, axis=-2, keepdims=True), rows], axis=-2), det


def _bad_volume(det):
    return jnp.any(~(det > 0))  # NaN counts as bad


_VOLUME_MESSAGE = "X: every tetrahedron needs a positive volume (T positively oriented, see tet_mesh)"


def shape_gradients(
    X: Float[ArrayLike, "n 3"], T: Int[ArrayLike, "m 4"]
) -> tuple[Float[Array, "m 4 3"], Float[Array, " m"]]:
    """The constant gradients of the four linear shape functions of each tet (JAX, differentiable in X).

    Args:
        X: (n, 3) float rest positions.
        T: (m, 4) int tets, positively oriented.
    Returns:
        grads (m, 4, 3): ``grads[e, a] = grad N_a`` on tet e; volumes (m,) the tets' volumes.
    Raises:
        ValueError (inside jit a runtime error with the message): bad shapes, indices out of range, a tet of
        non-positive volume.

    Examples:
        >>> import xfem
        >>> tet = xfem.one_tet()
        >>> gradients, volumes = xfem.shape_gradients(tet.X, tet.T)
        >>> (gradients[0].round(6) + 0.0).tolist(), [round(v, 6) for v in volumes.tolist()]
        ([[-1.0, -1.0, -1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], [0.166667])
    """
    X, T = _jax_mesh_arrays(X, T)
    grads, volumes, bad_index, bad_volume = _shape_gradients(X, T)
    grads = require(grads, (bad_index, _index_message(X.shape[0])), (bad_volume, _VOLUME_MESSAGE))
    return grads, volumes


@jax.jit
def _shape_gradients(X, T):
    grads, det = _gradients(X[T])
    return grads, det / 6, _bad_index(T, X.shape[0]), _bad_volume(det)


def shape_functions(
    X: Float[ArrayLike, "n 3"],
    T: Int[ArrayLike, "m 4"],
    points: Float[ArrayLike, "k 3"],
    elements: Int[ArrayLike, " k"],
) -> Float[Array, "k 4"]:
    """The four shape functions ``N_a`` of tet ``elements[i]`` at ``points[i]`` (its barycentric coordinates).

    A point outside its tet gets the affine extension (some ``N_a < 0``); nothing checks containment.

    Args:
        X: (n, 3) float rest positions.
        T: (m, 4) int tets, positively oriented.
        points: (k, 3) float positions.
        elements: (k,) int, the tet of each point.
    Returns:
        (k, 4) shape-function values, ``N[i, a]`` for node ``T[elements[i], a]``.
    """
    X, T = _jax_mesh_arrays(X, T)
    points, elements = jnp.asarray(points), jnp.asarray(elements)
    if points.ndim != 2 or points.shape[1] != 3 or not jnp.issubdtype(points.dtype, jnp.floating):
        raise ValueError(f"points: expected float positions of shape (k, 3), got {points.dtype} {points.shape}")
    if elements.shape != points.shape[:1] or not jnp.issubdtype(elements.dtype, jnp.integer):
        raise ValueError(
            f"elements: expected integer tet indices of shape ({points.shape[0]},), "
            f"got {elements.dtype} {elements.shape}"
        )
    N, bad_elements, bad_index, bad_volume = _shape_functions(X, T, jnp.asarray(points, X.dtype), elements)
    return require(
        N,
        (bad_elements, f"elements: tet indices must lie in [0, {T.shape[0]})"),
        (bad_index, _index_message(X.shape[0])),
        (bad_volume, _VOLUME_MESSAGE),
    )


@jax.jit
def _shape_functions(X, T, points, elements):
    tets = T[elements]
    x = X[tets]
    grads, det = _gradients(x)
    barycentric = jnp.einsum("kaj,kj->ka", grads[:, 1:], points - x[:, 0], precision=EXACT)
    N = jnp.concatenate([1 - jnp.sum(barycentric, axis=1, keepdims=True), barycentric], axis=1)
    return N, jnp.any((elements < 0) | (elements >= T.shape[0])), _bad_index(tets, X.shape[0]), _bad_volume(det)


def consistent_mass(
    X: Float[npt.ArrayLike, "n 3"], T: Int[npt.ArrayLike, "m 4"], density: float | Float[npt.ArrayLike, " m"]
) -> sp.csr_matrix:
    """The consistent mass matrix of eq. 7, scalar factor: ``M_ij = int rho phi_i phi_j`` (host, scipy).

    Per tet ``M_e[a, b] = rho_e V_e (1 + delta_ab) / 20`` (exact). The full eq. 7 matrix is
    ``kron(M, I_3)`` for interleaved (x, y, z) coefficients.

    Args:
        X: (n, 3) rest positions.
        T: (m, 4) int tets, positively oriented.
        density: scalar or (m,) positive mass density per tet.
    Returns:
        (n, n) float64 ``scipy.sparse.csr_matrix``, exactly symmetric, positive definite when every node
        is in a tet (as in a ``TetMesh``).
    """
    X = check_points("X", X)
    T = _host_tets(T, len(X))
    volume = _host_volumes(X, T)
    if np.any(volume <= 0):
        e = int(np.argmax(volume <= 0))
        raise ValueError(
            f"T: tet {e} = {T[e].tolist()} has non-positive volume {volume[e]:.3g}; orient the tets with tet_mesh"
        )
    weight = check_positive("density", density, ((), (len(T),))) * volume / 20
    values = weight[:, None, None] * (1 + np.eye(4))
    rows = np.broadcast_to(T[:, :, None], values.shape)
    cols = np.broadcast_to(T[:, None, :], values.shape)
    M = sp.csr_matrix((values.ravel(), (rows.ravel(), cols.ravel())), shape=(len(X), len(X)))
    return (M + M.T) * 0.5  # summing duplicates in another order leaves M_ij != M_ji in the last bit


def _jax_density(density, m: int, dtype):
    rho = jnp.asarray(density)
    if rho.shape not in ((), (m,)):
        raise ValueError(f"density: expected finite positive values of shape () or ({m},), got {rho.shape}")
    return jnp.asarray(rho, dtype)


def lumped_mass(
    X: Float[ArrayLike, "n 3"], T: Int[ArrayLike, "m 4"], density: float | Float[ArrayLike, " m"]
) -> Float[Array, " n"]:
    """The row-sum lumped mass: each tet gives ``rho_e V_e / 4`` to each of its nodes (JAX, differentiable).

    Args:
        X: (n, 3) float rest positions.
        T: (m, 4) int tets, positively oriented.
        density: scalar or (m,) positive mass density per tet.
    Returns:
        (n,) nodal masses, the row sums of ``consistent_mass``.

    Examples:
        >>> import xfem
        >>> tet = xfem.one_tet()
        >>> [round(m, 6) for m in xfem.lumped_mass(tet.X, tet.T, 6.0).tolist()]  # mass 1, a quarter per node
        [0.25, 0.25, 0.25, 0.25]
    """
    X, T = _jax_mesh_arrays(X, T)
    masses, bad_density, bad_index, bad_volume = _lumped_mass(X, T, _jax_density(density, T.shape[0], X.dtype))
    return require(
        masses,
        (bad_density, "density: expected finite positive values"),
        (bad_index, _index_message(X.shape[0])),
        (bad_volume, _VOLUME_MESSAGE),
    )


@jax.jit
def _lumped_mass(X, T, rho):
    _, det = _gradients(X[T])
    share = rho * det / 24
    masses = jnp.zeros(X.shape[0], X.dtype).at[T].add(jnp.broadcast_to(share[:, None], T.shape))
    return masses, jnp.any(~(rho > 0) | ~jnp.isfinite(rho)), _bad_index(T, X.shape[0]), _bad_volume(det)


def body_force(
    X: Float[ArrayLike, "n 3"], T: Int[ArrayLike, "m 4"], b: Float[ArrayLike, " 3"] | Float[ArrayLike, "m 3"]
) -> Float[Array, "n 3"]:
    """Nodal body forces of eq. 8, ``f_i = int b phi_i``, exact for a force density constant per tet:
    each tet gives ``b_e V_e / 4`` to each of its nodes (JAX, differentiable in X and b).

    Args:
        X: (n, 3) float rest positions.
        T: (m, 4) int tets, positively oriented.
        b: (3,) or (m, 3) force per unit volume (e.g. ``rho * g``).
    Returns:
        (n, 3) nodal forces.
    """
    X, T = _jax_mesh_arrays(X, T)
    b = jnp.asarray(b)
    if b.shape not in ((3,), (T.shape[0], 3)):
        raise ValueError(f"b: expected a force density of shape (3,) or ({T.shape[0]}, 3), got {b.shape}")
    f, bad_b, bad_index, bad_volume = _body_force(X, T, jnp.asarray(b, X.dtype))
    return require(
        f,
        (bad_b, "b: non-finite values (NaN or inf)"),
        (bad_index, _index_message(X.shape[0])),
        (bad_volume, _VOLUME_MESSAGE),
    )


@jax.jit
def _body_force(X, T, b):
    _, det = _gradients(X[T])
    share = jnp.broadcast_to(b, (T.shape[0], 3)) * (det / 24)[:, None]
    f = jnp.zeros(X.shape, X.dtype).at[T].add(jnp.broadcast_to(share[:, None, :], (*T.shape, 3)))
    return f, ~jnp.all(jnp.isfinite(b)), _bad_index(T, X.shape[0]), _bad_volume(det)
