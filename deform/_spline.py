"""Spline-aligned (spline path) deformation: eq. (1)-(2), sec. III-A/B of the CGA mesh-deformation paper.

A harmonic field ``lambda`` (0 on the start handle H_1, 1 on the end handle H_n, sec. VIII) places every
vertex on a spline path; the vertex's deforming motor is ``M_i = S(lambda_i) = exp(sum_j W_j(lambda_i)
log R_j)`` (eq. 1) and the vertex moves to ``M_i p'_i ~M_i`` (eq. 2), with ``p'_i`` bound once by the
rest key motors (sec. III-A). The bases W (Fig. 2-4) form a partition of unity on [0, 1]:

* ``"linear"``: ``1 - l, l`` (k = 2, Fig. 2);
* ``"lagrange"``: the quadratic Lagrange polynomials ``2l^2 - 3l + 1, -4l^2 + 4l, 2l^2 - l`` (k = 3, Fig. 3);
* ``"bezier"``: the Bernstein polynomials of degree k - 1 (k = 4 by default: cubic Bezier);
* ``"bspline"``: clamped uniform B-splines of degree d with k >= d + 1 keys (Fig. 4; d = 3: cubic).

Every basis is 1 on its first key at ``l = 0`` and on its last key at ``l = 1``, so the handles H_1 and
H_n move rigidly by R_1 and R_n. The per-vertex work is ``deform._motor_field``'s.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_choice, require
from _jaxcga_shared.platform import EXACT
from deform._ffd import MAX_DEGREE, _bernstein
from deform._harmonic import harmonic_precompute, harmonic_solve
from deform._motor_field import MotorField, motor_field_precompute
from jaxcga import Multivector

BASES = ("linear", "lagrange", "bezier", "bspline")
_FIXED_KEYS = {"linear": 2, "lagrange": 3}
_ROUNDING = 1e-9  # how far outside [0, 1] a parameter may stray by rounding; it is clipped back


def check_parameter(lam) -> Float[Array, " n"]:
    """``lam`` as a float vector (n,) in [0, 1]: ValueError for a bad shape or (when concrete) values
    outside [0, 1] beyond rounding, a runtime error with the message inside jit; rounding is clipped away."""
    lam = jnp.asarray(lam)
    if lam.ndim != 1:
        raise ValueError(f"lam: expected a parameter vector of shape (n,), got shape {lam.shape}")
    if not jnp.issubdtype(lam.dtype, jnp.floating):
        lam = lam.astype(jnp.result_type(float))
    outside = ~jnp.all((lam >= -_ROUNDING) & (lam <= 1 + _ROUNDING))  # NaN counts as outside
    lam = require(lam, (outside, "lam: spline parameters must lie in [0, 1] (and be finite)"))
    return jnp.clip(lam, 0.0, 1.0)


def _powers(lam, degree: int):
    """(n, degree + 1) columns 1, l, ..., l^degree (products, so derivatives are finite at l = 0)."""
    columns = [jnp.ones_like(lam)]
    for _ in range(degree):
        columns.append(columns[-1] * lam)
    return jnp.stack(columns, axis=-1)


def clamped_knots(num_keys: int, degree: int) -> np.ndarray:
    """The clamped uniform knot vector (num_keys + degree + 1,): degree + 1 zeros, uniform interior
    knots, degree + 1 ones.

    Args:
        num_keys: k >= degree + 1 control points.
        degree: the B-spline degree.

    Returns:
        (num_keys + degree + 1,) the knots.

    Examples:
        >>> import deform
        >>> deform.clamped_knots(5, 3).tolist()
        [0.0, 0.0, 0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 1.0]
    """
    interior = np.linspace(0.0, 1.0, num_keys - degree + 1)
    return np.concatenate([np.zeros(degree), interior, np.ones(degree)])


def _bspline(lam, num_keys: int, degree: int):
    """Cox-de Boor recursion on every basis function at once; the knot vector is static, so the
    0/0 terms of repeated knots are dropped at trace time instead of guarded at run time."""
    t = clamped_knots(num_keys, degree)
    spans = num_keys - degree
    # span s with t[s] <= l < t[s + 1]; l = 1 belongs to the last non-empty span
    span = jnp.clip(jnp.floor(lam * spans).astype(jnp.int32), 0, spans - 1) + degree
    N = jax.nn.one_hot(span, len(t) - 1, dtype=lam.dtype)
    for p in range(1, degree + 1):
        count = len(t) - p - 1
        i = np.arange(count)
        left, right = t[i + p] - t[i], t[i + p + 1] - t[i + 1]
        inv_left = np.divide(1.0, left, out=np.zeros(count), where=left > 0)
        inv_right = np.divide(1.0, right, out=np.zeros(count), where=right > 0)
        # per-knot rows (1, count) against the parameters' column (n, 1)
        lo, hi, inv_left, inv_right = (
            jnp.asarray(a, lam.dtype)[None] for a in (t[i], t[i + p + 1], inv_left, inv_right)
        )
        x = lam[:, None]
        N = ((x - lo) * inv_left) * N[:, :-1] + ((hi - x) * inv_right) * N[:, 1:]
    return N


def spline_weights(
    lam: Float[ArrayLike, " n"], basis: str = "bspline", num_keys: int | None = None, degree: int = 3
) -> Float[Array, "n k"]:
    """The weights ``W_j(lambda_i)`` of eq. (1): an (n, k) partition of unity.

    Args:
        lam: (n,) parameters in [0, 1] (rounding up to 1e-9 outside is clipped).
        basis: one of ``BASES``.
        num_keys: k; ``None`` for the basis' default (linear 2, lagrange 3, bezier 4, bspline degree + 1).
            ``"linear"`` and ``"lagrange"`` accept only their own k.
        degree: the B-spline degree d >= 1 (``"bspline"`` only; k >= d + 1).

    Returns:
        (n, k) the weights, rows summing to one.

    Examples:
        >>> import jax.numpy as jnp
        >>> import deform
        >>> deform.spline_weights(jnp.array([0.0, 0.5, 1.0]), "linear").tolist()
        [[1.0, 0.0], [0.5, 0.5], [0.0, 1.0]]
    """
    check_choice("basis", basis, BASES)
    lam = check_parameter(lam)
    if basis in _FIXED_KEYS:
        k = _FIXED_KEYS[basis]
        if num_keys not in (None, k):
            raise ValueError(f"num_keys: the {basis} basis has exactly {k} keys, got {num_keys}")
    elif basis == "bezier":
        k = 4 if num_keys is None else num_keys
        if not isinstance(k, int) or not 2 <= k <= MAX_DEGREE + 1:
            raise ValueError(f"num_keys: the Bezier basis needs an integer k in [2, {MAX_DEGREE + 1}], got {num_keys}")
    else:
        if not isinstance(degree, int) or degree < 1:
            raise ValueError(f"degree: expected an integer B-spline degree >= 1, got {degree}")
        k = degree + 1 if num_keys is None else num_keys
        if not isinstance(k, int) or k < degree + 1:
            raise ValueError(f"num_keys: a degree-{degree} B-spline needs an integer k >= {degree + 1}, got {num_keys}")
    if basis == "linear":
        return jnp.stack([1 - lam, lam], axis=-1)
    if basis == "lagrange":
        return jnp.matmul(
            _powers(lam, 2),
            jnp.asarray([[1.0, 0.0, 0.0], [-3.0, 4.0, -1.0], [2.0, -4.0, 2.0]], lam.dtype),
            precision=EXACT,
        )
    if basis == "bezier":
        return _bernstein(k - 1, lam)
    return _bspline(lam, k, degree)


def spline_parameter(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    start: Int[ArrayLike, " s"],
    end: Int[ArrayLike, " e"],
    *,
    laplacian: str = "cotangent",
    unhandled: str = "follow",
) -> Float[Array, " n"]:
    """The harmonic field ``lambda`` (sec. III-A, VIII): 0 on the ``start`` vertices (H_1), 1 on the
    ``end`` vertices (H_n), harmonic elsewhere, clipped to [0, 1] (the cotangent Laplacian has no
    maximum principle on obtuse meshes, and the bases are defined on [0, 1] only).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int faces.
        start: (s,) int vertex indices of the first handle (lambda = 0).
        end: (e,) int vertex indices of the second handle (lambda = 1), disjoint from ``start``, both non-empty.
        laplacian: ``"cotangent"`` or ``"mean_value"``.
        unhandled: ``"follow"`` (default: a connected part of the mesh with neither handle takes the parameter
            of the part it is attached or nearest to, ``deform.mesh_parts``) or ``"error"``.

    Returns:
        (n,) the parameter lambda of each vertex, in [0, 1].
    """
    start, end = np.asarray(start).reshape(-1), np.asarray(end).reshape(-1)
    if len(start) == 0 or len(end) == 0:
        raise ValueError("start, end: both handles need at least one vertex")
    if np.intersect1d(start, end).size:
        raise ValueError("start, end: the handles must be disjoint")
    data = harmonic_precompute(V, F, np.concatenate([start, end]), laplacian=laplacian, unhandled=unhandled)
    bc = np.concatenate([np.zeros(len(start)), np.ones(len(end))])
    return jnp.clip(harmonic_solve(data, jnp.asarray(bc)), 0.0, 1.0)


def spline_precompute(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    start: Int[ArrayLike, " s"],
    end: Int[ArrayLike, " e"],
    *,
    rest_motors: Multivector | None = None,
    basis: str = "bspline",
    num_keys: int | None = None,
    degree: int = 3,
    laplacian: str = "cotangent",
    unhandled: str = "follow",
) -> MotorField:
    """Bind a mesh to k key motors along a spline path (eq. 1-2, sec. III-A).

    Args:
        V: (n, 3) rest positions.
        F: (m, 3) int faces.
        start: (s,) int vertex indices of the handle H_1 (lambda = 0).
        end: (e,) int vertex indices of the handle H_n (lambda = 1).
        rest_motors: None (identity rest motors: key motors are motions of space) or motors with batch
            shape (k,) that give back the rest mesh.
        basis: the spline basis, see ``spline_weights``.
        num_keys: see ``basis``.
        degree: see ``basis``.
        laplacian: ``"cotangent"`` or ``"mean_value"`` for the harmonic field.
        unhandled: ``"follow"`` (default) or ``"error"``, see ``spline_parameter``.
    Returns:
        A ``MotorField``: ``motor_field_solve`` on it and key motors with batch shape (..., k) gives the
        deformed positions (..., n, 3).
    """
    lam = spline_parameter(V, F, start, end, laplacian=laplacian, unhandled=unhandled)
    return motor_field_precompute(V, spline_weights(lam, basis, num_keys, degree), rest_motors=rest_motors)
