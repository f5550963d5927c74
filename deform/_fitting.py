"""Fitting bone motors and dilations to target vertex positions (the design card's "fit motor
handles to target poses by gradient descent", on the rigged deformation of eq. 17).

Each bone's local versor is its rest versor times a change in its own frame,
``L_i = L_i^rest exp(B_i) D(exp(sigma_i))``, with B_i a motor generator (6 bivector components:
e12, e13, e23 rotation, e1inf, e2inf, e3inf translation) and sigma_i a log-scale. Parameters are zero
at the rest pose, so the regularizer ``lambda |params|^2`` pulls toward it. The residual
``(skin(params)[vertices] - targets) / diagonal`` is minimized by optimistix (Levenberg-Marquardt by
default, Gauss-Newton, or BFGS / gradient descent on the squared residual; gradient descent is optax's Adam
through ``optimistix.OptaxMinimiser``, a first-order method that needs thousands of steps where
Levenberg-Marquardt needs tens).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

import jaxcga as cga
from _jaxcga_shared.checks import check_choice, check_index_range
from _jaxcga_shared.mesh import bounding_diagonal
from deform import _pose, _rig
from deform._model import RiggedModel, SkinnedMesh
from jaxcga._multivector import KINDS, Multivector

SOLVERS = ("levenberg_marquardt", "gauss_newton", "bfgs", "gradient_descent")
PARAMETERS_PER_BONE = 7  # six motor-generator components and one log-scale
_ADAM_RATE = 1e-2  # gradient_descent's initial step per parameter (radians, log-scale, model units)


def pose_from_parameters(model: RiggedModel, params: Float[ArrayLike, "... b 7"]) -> Multivector:
    """Local similitudes ``L_rest exp(B) D(exp(sigma))`` of every bone, batch shape (..., b).

    Args:
        model: the RiggedModel (its skeleton's rest pose is the reference).
        params: (..., b, 7): motor-generator components (e12, e13, e23, e1inf, e2inf, e3inf) and the
            log-scale of each bone."""
    params = jnp.asarray(params)
    b = model.skeleton.num_bones
    if params.ndim < 2 or params.shape[-2:] != (b, PARAMETERS_PER_BONE):
        raise ValueError(f"params: expected shape (..., {b}, {PARAMETERS_PER_BONE}), got {params.shape}")
    motion = cga.exp_motor(Multivector(params[..., :6], cga.MOTOR_GENERATOR))
    dilation = cga.dilator(jnp.exp(params[..., 6]))
    rest = _rig.local_versors(model.skeleton)
    return (rest * motion * dilation).embed(KINDS["similitude"])


def skin_parameters(
    model: RiggedModel, params: Float[ArrayLike, "... b 7"], method: str = "cga"
) -> Float[Array, "... n 3"]:
    """Skinned positions (..., n, 3) for parameters (..., b, 7) (see ``pose_from_parameters``).

    Args:
        model: the RiggedModel.
        params: (..., b, 7) parameters, see ``pose_from_parameters``.
        method: skinning method (``deform.METHODS``)."""
    return _pose.skin_pose(model, pose_from_parameters(model, params), method)


def _rest_diagonal(model: RiggedModel) -> float:
    """Bounding-box diagonal of the skinned rest pose (world space), the unit of fitting errors."""
    return bounding_diagonal(_pose.rest_pose(model, "lbs"))


class PoseFit(eqx.Module):
    """Result of ``fit_pose``.

    Attributes:
        params: (b, 7) fitted parameters (see ``pose_from_parameters``).
        local: fitted local similitudes, batch shape (b,).
        positions: (n, 3) skinned positions of the fit.
        max_error: largest distance between fitted and target vertices.
        rms_error: root-mean-square distance.
        steps: solver steps taken.
        converged: whether the solver met its tolerance within max_steps.
    """

    params: Float[Array, "b 7"]
    local: Multivector
    positions: Float[Array, "n 3"]
    max_error: Float[Array, ""]
    rms_error: Float[Array, ""]
    steps: Int[Array, ""]
    converged: Array


def _solver(name: str, rtol: float, atol: float, max_steps: int):
    if name == "levenberg_marquardt":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol)
    if name == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol)
    if name == "bfgs":
        return optx.BFGS(rtol=rtol, atol=atol)
    if name == "gradient_descent":
        # Adam (first order, per-parameter step sizes) with a learning rate decaying to zero over max_steps:
        # a fixed rate keeps oscillating at its own size near the minimum and never meets the tolerances
        adam = optax.adam(optax.cosine_decay_schedule(_ADAM_RATE, max_steps))
        return optx.OptaxMinimiser(adam, rtol=rtol, atol=atol)
    raise ValueError(f"solver: expected one of {SOLVERS}, got {name!r}")


def check_targets(targets, vertices, n: int, dtype):
    """Targets (t, 3) and the vertex indices (t,) they belong to (all n vertices when None), checked."""
    targets = jnp.asarray(targets, dtype)
    index = np.arange(n) if vertices is None else np.asarray(vertices)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        raise ValueError(f"vertices: expected a (t,) integer array, got {index.dtype} {index.shape}")
    check_index_range("vertices", index, n)
    if targets.shape != (len(index), 3):
        raise ValueError(f"targets: expected shape ({len(index)}, 3), got {targets.shape}")
    if not bool(jnp.all(jnp.isfinite(targets))):
        raise ValueError("targets: contains NaN or infinity")
    return targets, index


def run_solver(residuals, name: str, y0, args, max_steps: int, rtol: float, atol: float):
    """optimistix on ``residuals(y, args)``: least squares for Levenberg-Marquardt / Gauss-Newton, else
    minimisation of the squared residual (BFGS, gradient descent). Returns the solution object."""
    opt = _solver(name, rtol, atol, max_steps)
    if not isinstance(opt, optx.AbstractMinimiser):  # Levenberg-Marquardt, Gauss-Newton
        return optx.least_squares(residuals, opt, y0, args=args, max_steps=max_steps, throw=False)
    if name == "gradient_descent":
        # optax mixes its int32 step count with floats (schedule, bias correction): standard promotion for this
        # call only, so a caller's strict promotion (the tests') still holds everywhere else
        with jax.numpy_dtype_promotion("standard"):
            return optx.minimise(_squared, opt, y0, args=(residuals, args), max_steps=max_steps, throw=False)
    return optx.minimise(_squared, opt, y0, args=(residuals, args), max_steps=max_steps, throw=False)


def _squared(y, residuals_and_args):
    residuals, args = residuals_and_args
    r = residuals(y, args)
    return jnp.sum(r * r)


def _full_parameters(y, fit_scale: bool):
    """(b, 7) parameters from the fitted ones: a zero log-scale column when the dilations are not fitted."""
    return y if fit_scale else jnp.concatenate([y, jnp.zeros((y.shape[0], 1), y.dtype)], axis=-1)


def _pose_residuals(y, args):
    """``fit_pose``'s residuals: the targeted vertices' offsets over the bounding diagonal, then
    ``sqrt(lambda) y`` (zeros without regularization, so both share a compiled solver)."""
    reduced, targets, diagonal, root_regularization, fit_scale, method = args
    moved = skin_parameters(reduced, _full_parameters(y, fit_scale), method)
    return jnp.concatenate([((moved - targets) / diagonal).ravel(), root_regularization * y.ravel()])


def fit_pose(
    model: RiggedModel,
    targets: Float[Array, "t 3"],
    vertices: Int[Array, " t"] | None = None,
    *,
    method: str = "cga",
    regularization: float = 0.0,
    fit_scale: bool = True,
    solver: str = "levenberg_marquardt",
    max_steps: int = 200,
    rtol: float = 1e-10,
    atol: float = 1e-12,
    init: Float[Array, "b 7"] | None = None,
) -> PoseFit:
    """Fit every bone's motor (and dilation) so that the skinned vertices reach ``targets``.

    Args:
        model: the RiggedModel.
        targets: (t, 3) target positions of the vertices ``vertices`` (all vertices when None: t = n).
        vertices: (t,) int vertex indices, or None.
        method: skinning method (``deform.METHODS``; "dqs" cannot fit dilations).
        regularization: weight lambda of ``lambda |params|^2`` toward the rest pose (use it when only a
            handful of vertices are targeted).
        fit_scale: also fit each bone's dilation (log-scale); otherwise motors only.
        solver: one of ``SOLVERS``. "gradient_descent" (Adam, its learning rate decaying to zero over
            ``max_steps``) is first order: give it thousands of steps (e.g. ``max_steps=10_000``).
        max_steps, rtol, atol: solver limits and tolerances.
        init: (b, 7) starting parameters (zeros: the rest pose).
    Returns:
        a PoseFit."""
    n = model.mesh.num_vertices
    b = model.skeleton.num_bones
    targets, index = check_targets(targets, vertices, n, model.mesh.V.dtype)
    if regularization < 0:
        raise ValueError(f"regularization: expected >= 0, got {regularization}")
    if not isinstance(max_steps, int) or max_steps < 1:
        raise ValueError(f"max_steps: expected an int >= 1, got {max_steps!r}")
    check_choice("method", method, _pose.METHODS)
    if method == "dqs" and fit_scale:
        raise ValueError("method: dual-quaternion skinning cannot represent dilations; use fit_scale=False")
    dtype = model.mesh.V.dtype
    diagonal = jnp.asarray(_rest_diagonal(model), dtype)
    width = PARAMETERS_PER_BONE if fit_scale else 6
    y0 = jnp.zeros((b, width), dtype) if init is None else jnp.asarray(init, dtype)[:, :width]
    if init is not None and y0.shape != (b, width):
        raise ValueError(f"init: expected shape ({b}, {PARAMETERS_PER_BONE}), got {jnp.shape(init)}")

    # Only the targeted vertices are skinned inside the solver.
    mesh = model.mesh
    subset = SkinnedMesh(
        mesh.V[index], jnp.zeros((0, 3), jnp.int32), mesh.J[index], mesh.W[index], mesh.inverse_bind, mesh.joints
    )
    reduced = RiggedModel(subset, model.skeleton, (), model.name)
    # the data travel as solver arguments, the residual is one module-level function: fits of one size and
    # kind share optimistix's compiled solver (a closure per call compiled it anew, ~10 s each)
    args = (reduced, targets, diagonal, jnp.sqrt(jnp.asarray(regularization, dtype)), fit_scale, method)
    sol = run_solver(_pose_residuals, solver, y0, args, max_steps, rtol, atol)
    params = _full_parameters(sol.value, fit_scale)
    local = pose_from_parameters(model, params)
    positions = _pose.skin_pose(model, local, method)
    dist = jnp.linalg.norm(positions[index] - targets, axis=-1)
    return PoseFit(
        params=params,
        local=local,
        positions=positions,
        max_error=jnp.max(dist),
        rms_error=jnp.sqrt(jnp.mean(dist**2)),
        steps=sol.stats["num_steps"],
        converged=sol.result == optx.RESULTS.successful,
    )


def random_parameters(
    key: PRNGKeyArray,
    model: RiggedModel,
    rotation: float = 0.4,
    translation: float = 0.0,
    log_scale: float = 0.0,
    dtype: DTypeLike | None = None,
) -> Float[Array, "b 7"]:
    """Random pose parameters (b, 7): uniform in [-rotation, rotation] for the rotation bivector,
    translation in units of the mesh's bounding-box diagonal, and log-scale, for tests and examples.

    Args:
        key: a JAX random key.
        model: the RiggedModel (its bone count b and rest diagonal).
        rotation, translation, log_scale: the half-widths of the uniform ranges.
        dtype: the parameters' dtype; None: the mesh's."""
    b = model.skeleton.num_bones
    dtype = dtype or model.mesh.V.dtype
    k1, k2, k3 = jax.random.split(key, 3)
    diagonal = _rest_diagonal(model)
    rot = jax.random.uniform(k1, (b, 3), dtype, -rotation, rotation)
    trans = jax.random.uniform(k2, (b, 3), dtype, -translation, translation) * diagonal
    scale = jax.random.uniform(k3, (b, 1), dtype, -log_scale, log_scale)
    return jnp.concatenate([rot, trans, scale], axis=-1)
