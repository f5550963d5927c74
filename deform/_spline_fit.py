"""Path deformation through B-spline fitting: eq. (3)-(5), sec. III-C of the CGA mesh-deformation paper.

Given m motors Q_i at parameters lambda_i, find k key motors R_j with
``Q_i ~ exp(sum_j N_j(lambda_i) log R_j)`` (eq. 3). In the six bivector components of the logarithms
this is the linear system ``Q = A R`` (eq. 4), ``A_ij = N_j(lambda_i)`` (m, k), solved in the least-squares
sense through the normal equations ``A^T A R = A^T Q`` (eq. 5), one right-hand side per component.

The parameters are fixed, so ``A`` is factored once on the host (``spline_fit_precompute``): by Cholesky
when ``cond(A^T A)`` is at most ``max_condition``, else (the knot vector leaves a key without data, or too
few parameters) by SVD, whose pseudo-inverse gives the minimum-norm least-squares solution. Each fit is
then a JAX function of the Q_i (``spline_fit_solve``: jit, vmap, grad). The fitted key motors drive ``deform._spline``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import jax.scipy.linalg as jsl
import numpy as np
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga
from _jaxcga_shared.platform import EXACT
from deform._motor_field import _check_key_motors, motor_logs
from deform._spline import check_parameter, spline_weights
from jaxcga import KINDS, MOTOR_GENERATOR, Multivector

METHODS = ("cholesky", "svd")


class SplineFitData(eqx.Module):
    """The factored least-squares problem of eq. (5) for fixed parameters (``spline_fit_precompute``), the
    argument of ``spline_fit_solve``.

    Attributes:
        A: (m, k) basis matrix ``N_j(lambda_i)``.
        factor: (k, k) lower Cholesky factor of ``A^T A`` (method "cholesky"), or (k, m) the
            pseudo-inverse of A (method "svd").
        method: "cholesky" or "svd", the solver that was used.
        condition: ``cond(A^T A)`` (inf when singular).
    """

    A: Float[Array, "m k"]
    factor: Float[Array, "k _"]
    method: str = eqx.field(static=True)
    condition: float = eqx.field(static=True)


def spline_fit_solve(data: SplineFitData, Q: Multivector) -> Multivector:
    """The fitted key motors ``R_j = exp(log R_j)`` (batch shape (..., k)) for motors Q with batch shape
    (..., m) at the parameters of ``data``: the least-squares fit of eq. (5) in the logarithms.

    Args:
        data: ``spline_fit_precompute``'s output.
        Q: motors at the parameters, batch shape (..., m).

    Returns:
        The key motors, batch shape (..., k).
    """
    if not isinstance(data, SplineFitData):
        raise ValueError("data: expected the SplineFitData returned by spline_fit_precompute")
    m, k = data.A.shape
    Q = _check_key_motors("Q", Q, m)
    q = motor_logs(Q)
    if data.method == "svd":
        logs = jnp.einsum("km,...mc->...kc", data.factor.astype(q.dtype), q, precision=EXACT)
    else:
        rhs = jnp.einsum("mk,...mc->...kc", data.A.astype(q.dtype), q, precision=EXACT)  # A^T Q
        columns = jnp.moveaxis(rhs, -2, 0).reshape(k, -1)
        solved = jsl.cho_solve((data.factor.astype(q.dtype), True), columns)
        logs = jnp.moveaxis(solved.reshape((k,) + rhs.shape[:-2] + (6,)), 0, -2)
    return cga.exp_motor(Multivector(logs, MOTOR_GENERATOR)).embed(KINDS["motor"])


def spline_fit_precompute(
    lam: Float[ArrayLike, " m"],
    num_keys: int,
    *,
    degree: int = 3,
    max_condition: float = 1e8,
    rcond: float | None = None,
) -> SplineFitData:
    """Factor the least-squares fit of k key motors to motors given at parameters ``lam`` (eq. 3-5).

    Args:
        lam: (m,) concrete parameters in [0, 1] (e.g. joint index / number of bones).
        num_keys: k >= degree + 1 key motors, a clamped uniform B-spline (see ``deform._spline``).
        degree: the B-spline degree (3: the paper's cubic).
        max_condition: the largest ``cond(A^T A)`` solved by Cholesky on the normal equations; the normal
            equations square A's condition number, so beyond ~1e8 they lose over half the float64 digits.
        rcond: singular values below ``rcond * s_max`` count as zero on the SVD path (default: numpy's
            ``lstsq`` cut-off, machine epsilon times max(m, k)).

    Returns:
        The ``SplineFitData`` (the factored system), for ``spline_fit_solve``.
    """
    if not isinstance(max_condition, (int, float)) or not max_condition >= 1:
        raise ValueError(f"max_condition: expected a number >= 1, got {max_condition!r}")
    if rcond is not None and not 0 <= rcond < 1:
        raise ValueError(f"rcond: expected a number in [0, 1), got {rcond!r}")
    if isinstance(lam, jax.core.Tracer):
        raise ValueError("lam: expected concrete parameters (the fit is factored on the host), got a tracer")
    A = np.asarray(
        spline_weights(check_parameter(np.asarray(lam, np.float64)), "bspline", num_keys, degree), np.float64
    )
    m, k = A.shape
    U, s, Vt = np.linalg.svd(A, full_matrices=False)
    condition = float((s[0] / s[-1]) ** 2) if m >= k and s[-1] > 0 else float("inf")
    if condition <= max_condition:
        factor = np.linalg.cholesky(A.T @ A)
        method = "cholesky"
    else:
        cutoff = (np.finfo(np.float64).eps * max(m, k) if rcond is None else rcond) * s[0]
        inverse = np.divide(1.0, s, out=np.zeros_like(s), where=s > cutoff)
        factor = (Vt.T * inverse) @ U.T
        method = "svd"
    return SplineFitData(jnp.asarray(A), jnp.asarray(factor), method, condition)
