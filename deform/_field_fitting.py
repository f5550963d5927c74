"""Fitting the key motors of a motor field to target vertex positions (issue: "recover handle motors
from target vertex positions by gradient descent"), for every deformation built on ``MotorField``:
spline-aligned deformation (eq. 1-2), harmonic motor handles (sec. IV), motor FFD (eq. 7-8) and motor
cages (sec. VI).

Each fitted key motor is ``R_j = exp(B_j)`` with B_j a motor generator (six bivector components e12,
e13, e23, e1inf, e2inf, e3inf); B = 0 is the identity, i.e. the bound rest mesh, so the regularizer
``lambda |B|^2`` pulls toward it. The residual ``(field(exp(B))[vertices] - targets) / diagonal`` is
minimized by optimistix (the solvers of ``deform.fit_pose``: Levenberg-Marquardt by default,
Gauss-Newton, BFGS, gradient descent); keys not in ``free`` keep the motors given in ``fixed_motors``
(the identity by default: a fixed region).
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_choice
from _jaxcga_shared.mesh import bounding_diagonal
from deform._fitting import SOLVERS, check_targets, run_solver
from deform._motor_field import MotorField, identity_motors, motor_field_solve
from jaxcga import KINDS, Multivector


class MotorFit(eqx.Module):
    """Result of ``fit_key_motors``.

    Attributes:
        generators: (k, 6) motor generators B_j of every key (zeros for keys not fitted).
        motors: the key motors, batch shape (k,).
        positions: (n, 3) deformed positions of the fit.
        max_error, rms_error: largest and root-mean-square distance to the targets.
        steps: solver steps taken. converged: whether the solver met its tolerance.
    """

    generators: Float[Array, "k 6"]
    motors: Multivector
    positions: Float[Array, "n 3"]
    max_error: Float[Array, ""]
    rms_error: Float[Array, ""]
    steps: Int[Array, ""]
    converged: Array


def generators_to_motors(generators: Float[Array, "... k 6"]) -> Multivector:
    """Key motors ``exp(B_j)``, batch shape (..., k), from motor generators.

    Args:
        generators: (..., k, 6) motor generators (e12, e13, e23, e1inf, e2inf, e3inf).

    Returns:
        The motors, batch shape (..., k).

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> import deform
        >>> M = deform.generators_to_motors(jnp.array([[0.0, 0, 0, -1.0, 0, 0]]))  # exp(-t einf / 2), t = (2, 0, 0)
        >>> cga.apply_to_points(M, jnp.zeros(3)).round(6).tolist()
        [[2.0, 0.0, 0.0]]
    """
    generators = jnp.asarray(generators)
    if generators.ndim < 1 or generators.shape[-1] != 6:
        raise ValueError(f"generators: expected shape (..., k, 6), got {generators.shape}")
    return cga.exp_motor(Multivector(generators, cga.MOTOR_GENERATOR))


class _FitData(eqx.Module):
    field: MotorField  # restricted to the targeted vertices
    targets: Float[Array, "t 3"]
    fixed_values: Float[Array, "k 8"]
    free: Int[Array, " f"]
    scale: Float[Array, ""]
    root_regularization: Float[Array, ""]


def _motors_of(y, data: _FitData) -> Multivector:
    return Multivector(data.fixed_values.at[data.free].set(generators_to_motors(y).values), KINDS["motor"])


def _residuals(y, data: _FitData):
    r = ((motor_field_solve(data.field, _motors_of(y, data)) - data.targets) / data.scale).ravel()
    return jnp.concatenate([r, data.root_regularization * y.ravel()])


def fit_key_motors(
    field: MotorField,
    targets: Float[ArrayLike, "t 3"],
    vertices: Int[ArrayLike, " t"] | None = None,
    *,
    free: Int[npt.ArrayLike, " f"] | None = None,
    fixed_motors: Multivector | None = None,
    regularization: float = 0.0,
    solver: str = "levenberg_marquardt",
    max_steps: int = 200,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    init: Float[Array, "k 6"] | None = None,
) -> MotorFit:
    """Fit the key motors of ``field`` so that its vertices ``vertices`` reach ``targets``.

    Args:
        field: a ``MotorField`` (from ``spline_precompute``, ``handles_precompute``, ``ffd_precompute``,
            ``cage_precompute`` or ``motor_field_precompute``).
        targets: (t, 3) target positions (t = n when ``vertices`` is None).
        vertices: (t,) int vertex indices, or None for all.
        free: (f,) int indices of the keys to fit (default all); the others keep ``fixed_motors``.
        fixed_motors: motors (batch shape (k,)) for the keys not fitted; default identities.
        regularization: weight of ``lambda |B|^2`` toward the rest (use it with few targets).
        solver: one of ``deform.SOLVERS``.
        max_steps: solver limits and tolerances.
        rtol: see ``max_steps``.
        atol: see ``max_steps``.
        init: (k, 6) starting generators (zeros: the rest).
    Returns:
        a ``MotorFit``."""
    if not isinstance(field, MotorField):
        raise ValueError(f"field: expected a deform.MotorField, got {type(field).__name__}")
    n, k = field.bound.shape[0], field.num_keys
    dtype = field.weights.dtype
    targets, index = check_targets(targets, vertices, n, dtype)
    free = np.arange(k) if free is None else np.asarray(free).reshape(-1)
    if (
        not np.issubdtype(free.dtype, np.integer)
        or len(free) == 0
        or free.min() < 0
        or free.max() >= k
        or len(np.unique(free)) != len(free)
    ):
        raise ValueError(f"free: expected distinct key indices in [0, {k}), got {free}")
    if regularization < 0:
        raise ValueError(f"regularization: expected >= 0, got {regularization}")
    check_choice("solver", solver, SOLVERS)
    fixed = identity_motors(k, dtype) if fixed_motors is None else fixed_motors
    if not isinstance(fixed, Multivector) or fixed.batch_shape != (k,) or not set(fixed.blades) <= set(KINDS["motor"]):
        raise ValueError(f"fixed_motors: expected motors with batch shape ({k},)")
    fixed_values = fixed.embed(KINDS["motor"]).values.astype(dtype)
    y0 = jnp.zeros((len(free), 6), dtype) if init is None else jnp.asarray(init, dtype)[free]
    if init is not None and jnp.shape(init) != (k, 6):
        raise ValueError(f"init: expected shape ({k}, 6), got {jnp.shape(init)}")

    # Only the targeted vertices are deformed inside the solver. Everything travels as the solver's
    # args and the residual is a module-level function, so a second fit of the same sizes reuses the
    # compiled solver (closed-over arrays would also be folded into the code as constants).
    data = _FitData(
        MotorField(field.weights[index], field.bound[index]),
        targets,
        fixed_values,
        jnp.asarray(free),
        jnp.asarray(bounding_diagonal(field.bound), dtype),
        jnp.sqrt(jnp.asarray(regularization, dtype)),
    )
    sol = run_solver(_residuals, solver, y0, data, max_steps, rtol, atol)
    motors = _motors_of(sol.value, data)
    positions = motor_field_solve(field, motors)
    dist = jnp.linalg.norm(positions[index] - targets, axis=-1)
    return MotorFit(
        generators=jnp.zeros((k, 6), dtype).at[free].set(sol.value),
        motors=motors,
        positions=positions,
        max_error=jnp.max(dist),
        rms_error=jnp.sqrt(jnp.mean(dist**2)),
        steps=sol.stats["num_steps"],
        converged=sol.result == optx.RESULTS.successful,
    )
