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

from collections.abc import Callable

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
from deform._model import RiggedModel
from jaxcga._multivector import KINDS, Multivector

SOLVERS = ("levenberg_marquardt", "gauss_newton", "bfgs", "gradient_descent")
PARAMETERS_PER_BONE = 7  # six motor-generator components and one log-scale


def pose_from_parameters(model: RiggedModel, params: Float[ArrayLike, "... b 7"]) -> Multivector:
    """Local similitudes ``L_rest exp(B) D(exp(sigma))`` of every bone, batch shape (..., b).

    Args:
        model: the RiggedModel (its skeleton's rest pose is the reference).
        params: (..., b, 7): motor-generator components (e12, e13, e23, e1inf, e2inf, e3inf) and the
            log-scale of each bone.

    Returns:
        The local similitudes, batch shape (..., b).
    """
    params = jnp.asarray(params)
    b = model.skeleton.num_bones
    if params.ndim < 2 or params.shape[-2:] != (b, PARAMETERS_PER_BONE):
        raise ValueError(f"params: expected shape (..., {b}, {PARAMETERS_PER_BONE}), got {params.shape}")
    skeleton = model.skeleton
    return similitudes_from_parameters((skeleton.translation, skeleton.rotation, skeleton.scale), params)


def similitudes_from_parameters(rest, params) -> Multivector:
    """``pose_from_parameters`` from the rest TRS as arrays ``(translation, rotation, scale)``, each (..., b, 3 | 4
    | 3), and parameters (..., b, 7), unchecked (the packed fits share it)."""
    motion = cga.exp_motor(Multivector(params[..., :6], cga.MOTOR_GENERATOR))
    dilation = cga.dilator(jnp.exp(params[..., 6]))
    return (_rig.trs_to_versor(*rest) * motion * dilation).embed(KINDS["similitude"])


def skin_parameters(
    model: RiggedModel, params: Float[ArrayLike, "... b 7"], method: str = "cga"
) -> Float[Array, "... n 3"]:
    """Skinned positions (..., n, 3) for parameters (..., b, 7) (see ``pose_from_parameters``).

    Args:
        model: the RiggedModel.
        params: (..., b, 7) parameters, see ``pose_from_parameters``.
        method: skinning method (``deform.METHODS``).

    Returns:
        (..., n, 3) the skinned positions.
    """
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


def _solver(name: str, rtol: float, atol: float, parameters: int, progress=None):
    verbose = False if progress is None else _reporter(progress, 2.0 if name in _LEAST_SQUARES else 1.0)
    if name == "levenberg_marquardt":
        return optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)
    if name == "gauss_newton":
        return optx.GaussNewton(rtol=rtol, atol=atol, verbose=verbose)
    if name == "bfgs":
        return optx.BFGS(rtol=rtol, atol=atol, verbose=verbose)
    if name == "gradient_descent":
        # gradients only, L-BFGS's directions with a line search, a curvature pair per parameter (the problem is badly
        # conditioned: a shoulder's rotation moves the whole arm, a hand's scale only the hand, so a short curvature
        # history or a fixed step size cannot resolve both scales)
        return optx.OptaxMinimiser(optax.lbfgs(memory_size=parameters), rtol=rtol, atol=atol, verbose=verbose)
    raise ValueError(f"solver: expected one of {SOLVERS}, got {name!r}")


_LEAST_SQUARES = ("levenberg_marquardt", "gauss_newton")  # their loss is half the sum of squared residuals


def _reporter(progress, scale: float):
    """An optimistix ``verbose`` function that calls ``progress(loss)`` on the host after each solver step, with
    the sum of squared residuals at the point the step evaluated (``scale`` times the solver's own loss; the
    "last accepted" loss is a placeholder 0 at the first step)."""

    def verbose(**values):
        jax.debug.callback(progress, scale * values["loss_this_step"][1], ordered=True)

    return verbose


def check_targets(targets, vertices, n: int, dtype, item: str = ""):
    """Targets (t, 3) and the vertex indices (t,) they belong to (all n vertices when None), checked; ``item``
    follows the arguments' names in the messages (``"[2]"``: one model's of a list)."""
    targets = jnp.asarray(targets, dtype)
    index = np.arange(n) if vertices is None else np.asarray(vertices)
    if index.ndim != 1 or not np.issubdtype(index.dtype, np.integer):
        raise ValueError(f"vertices{item}: expected a (t,) integer array, got {index.dtype} {index.shape}")
    check_index_range(f"vertices{item}", index, n)
    if targets.shape != (len(index), 3):
        raise ValueError(f"targets{item}: expected shape ({len(index)}, 3), got {targets.shape}")
    if not bool(jnp.all(jnp.isfinite(targets))):
        raise ValueError(f"targets{item}: contains NaN or infinity")
    return targets, index


def run_solver(residuals, name: str, y0, args, max_steps: int, rtol: float, atol: float, progress=None):
    """optimistix on ``residuals(y, args)``: least squares for Levenberg-Marquardt / Gauss-Newton, else
    minimisation of the squared residual (BFGS, gradient descent). Returns the solution object. ``progress``:
    None, or called after each step with the sum of squared residuals (``fit_pose``)."""
    opt = _solver(name, rtol, atol, y0.size, progress)
    if not isinstance(opt, optx.AbstractMinimiser):  # Levenberg-Marquardt, Gauss-Newton
        return optx.least_squares(residuals, opt, y0, args=args, max_steps=max_steps, throw=False)
    if name == "gradient_descent":
        return _stationary_descent(residuals, opt, y0, args, max_steps, rtol, atol)
    return optx.minimise(_squared, opt, y0, args=(residuals, args), max_steps=max_steps, throw=False)


def _stationary_descent(residuals, opt, y0, args, max_steps: int, rtol: float, atol: float):
    """optax's L-BFGS through optimistix, its ``converged`` (result successful) also requiring the gradient to be
    at the step tolerance: a stalled line search (a zero step) meets the step test, but never passes for
    convergence."""
    # optax mixes its int32 step count with floats: standard promotion for this call only, so a caller's strict
    # promotion (the tests') still holds everywhere else
    with jax.numpy_dtype_promotion("standard"):
        sol = optx.minimise(_squared, opt, y0, args=(residuals, args), max_steps=max_steps, throw=False)
    y = jax.lax.stop_gradient(sol.value)
    # at a converged point Newton's step H^-1 g is within the step tolerance, so |g| is within it times the
    # largest curvature, at most the Gauss-Newton matrix's largest diagonal entry (2 |dr/dy_k|^2) over the
    # problems here (a necessary test: it never fails a converged fit, and fails a stall far from the minimum)
    gradient = jax.grad(_squared)(y, (residuals, args))
    curvature = 2.0 * jnp.max(jnp.sum(jax.jacfwd(residuals)(y, args).reshape(-1, y.size) ** 2, axis=0))
    stationary = jnp.max(jnp.abs(gradient)) <= curvature * (atol + rtol * jnp.max(jnp.abs(y)))
    result = optx.RESULTS.where(
        (sol.result == optx.RESULTS.successful) & ~stationary, optx.RESULTS.nonlinear_divergence, sol.result
    )
    return eqx.tree_at(lambda s: s.result, sol, result)


def _squared(y, residuals_and_args):
    residuals, args = residuals_and_args
    r = residuals(y, args)
    return jnp.sum(r * r)


def full_parameters(y, fit_scale: bool):
    """(..., b, 7) parameters from the fitted ones: a zero log-scale column when the dilations are not fitted."""
    return y if fit_scale else jnp.concatenate([y, jnp.zeros(y.shape[:-1] + (1,), y.dtype)], axis=-1)


class FitData(eqx.Module):
    """What ``fit_pose``'s residual needs, as arrays: one model's rig, the targeted vertices' bind data and the
    targets. The packed fits (``deform.fit_packed``) stack one per model, padded, with masks.

    Attributes:
        rest: the rest TRS ``(translation (b, 3), rotation (b, 4), scale (b, 3))``.
        parents: (b,) parent of each bone, -1 for a root.
        joint_bones: (j,) bone of each joint.
        inverse_bind: (j, 4, 4) inverse bind matrices.
        V, J, W: (t, 3), (t, k), (t, k): bind positions, joint indices and weights of the targeted vertices.
        targets: (t, 3) their targets.
        target_mask: (t,) 1 for a target, 0 for padding (its residual is zero).
        bone_mask: (b,) 1 for a bone, 0 for padding (not regularized: its parameters stay zero).
        diagonal: () the rest pose's bounding diagonal, the unit of the residual.
        root_regularization: () ``sqrt(lambda)``.
        fit_scale: static, whether the log-scales are fitted (else the parameters are (b, 6)).
        method: static, the skinning method.
    """

    rest: tuple[Array, Array, Array]
    parents: Int[Array, " b"]
    joint_bones: Int[Array, " j"]
    inverse_bind: Float[Array, "j 4 4"]
    V: Float[Array, "t 3"]
    J: Int[Array, "t k"]
    W: Float[Array, "t k"]
    targets: Float[Array, "t 3"]
    target_mask: Float[Array, " t"]
    bone_mask: Float[Array, " b"]
    diagonal: Float[Array, ""]
    root_regularization: Float[Array, ""]
    fit_scale: bool = eqx.field(static=True)
    method: str = eqx.field(static=True)


def pose_residuals(y, data: FitData):
    """``fit_pose``'s residuals: the targeted vertices' offsets over the bounding diagonal, then
    ``sqrt(lambda) y`` (zeros without regularization, so both share a compiled solver); padded targets and bones
    (masks 0) contribute zeros."""
    local = similitudes_from_parameters(data.rest, full_parameters(y, data.fit_scale))
    moved = _pose.skin_local(
        data.parents, data.joint_bones, data.inverse_bind, data.V, data.J, data.W, local, data.method
    )
    offsets = (moved - data.targets) / data.diagonal * data.target_mask[:, None]
    return jnp.concatenate([offsets.ravel(), (data.root_regularization * data.bone_mask[:, None] * y).ravel()])


def check_options(method: str, regularization: float, fit_scale: bool, solver: str, max_steps: int):
    """The fitting options shared by ``fit_pose`` and ``deform.fit_packed``, checked."""
    if not regularization >= 0:
        raise ValueError(f"regularization: expected >= 0, got {regularization}")
    if not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise ValueError(f"max_steps: expected an int >= 1, got {max_steps!r}")
    check_choice("method", method, _pose.METHODS)
    check_choice("solver", solver, SOLVERS)
    if method == "dqs" and fit_scale:
        raise ValueError("method: dual-quaternion skinning cannot represent dilations; use fit_scale=False")


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
    progress: Callable[[Array], object] | None = None,
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
        max_steps: solver limits and tolerances.
        rtol: see ``max_steps``.
        atol: see ``max_steps``.
        init: (b, 7) starting parameters (zeros: the rest pose).
        progress: None, or a function called on the host after each solver step with a () array: the sum of
            the squared residuals (distances over the rest diagonal, and the regularization's) at the point the
            step evaluated (the rest pose first; a trial point the solver then rejects counts too), in order, also
            under ``jit`` (``jax.debug.callback``); for a progress bar.
    Returns:
        a PoseFit."""
    n = model.mesh.num_vertices
    b = model.skeleton.num_bones
    targets, index = check_targets(targets, vertices, n, model.mesh.V.dtype)
    check_options(method, regularization, fit_scale, solver, max_steps)
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected None or a function, got {type(progress).__name__}")
    dtype = model.mesh.V.dtype
    diagonal = jnp.asarray(_rest_diagonal(model), dtype)
    width = PARAMETERS_PER_BONE if fit_scale else 6
    y0 = jnp.zeros((b, width), dtype) if init is None else jnp.asarray(init, dtype)[:, :width]
    if init is not None and y0.shape != (b, width):
        raise ValueError(f"init: expected shape ({b}, {PARAMETERS_PER_BONE}), got {jnp.shape(init)}")

    # Only the targeted vertices are skinned inside the solver. The data travel as solver arguments, the
    # residual is one module-level function: fits of one size and kind share optimistix's compiled solver (a
    # closure per call compiled it anew, ~10 s each)
    mesh, skeleton = model.mesh, model.skeleton
    data = FitData(
        rest=(skeleton.translation, skeleton.rotation, skeleton.scale),
        parents=jnp.asarray(skeleton.parents, jnp.int32),
        joint_bones=jnp.asarray(mesh.joints, jnp.int32),
        inverse_bind=mesh.inverse_bind,
        V=mesh.V[index],
        J=mesh.J[index],
        W=mesh.W[index],
        targets=targets,
        target_mask=jnp.ones(len(index), dtype),
        bone_mask=jnp.ones(b, dtype),
        diagonal=diagonal,
        root_regularization=jnp.sqrt(jnp.asarray(regularization, dtype)),
        fit_scale=fit_scale,
        method=method,
    )
    sol = run_solver(pose_residuals, solver, y0, data, max_steps, rtol, atol, progress)
    params = full_parameters(sol.value, fit_scale)
    local = pose_from_parameters(model, params)
    positions = _pose.skin_pose(model, local, method)
    return pose_fit(
        params, local, positions, targets, index, sol.stats["num_steps"], sol.result == optx.RESULTS.successful
    )


def pose_fit(params, local, positions, targets, index, steps, converged) -> PoseFit:
    """The PoseFit of fitted parameters, their local similitudes and skinned positions, with the errors at the
    targeted vertices ``index``."""
    dist = jnp.linalg.norm(positions[index] - targets, axis=-1)
    return PoseFit(
        params=params,
        local=local,
        positions=positions,
        max_error=jnp.max(dist),
        rms_error=jnp.sqrt(jnp.mean(dist**2)),
        steps=steps,
        converged=converged,
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
        rotation: the half-widths of the uniform ranges.
        translation: see ``rotation``.
        log_scale: see ``rotation``.
        dtype: the parameters' dtype; None: the mesh's.

    Returns:
        (b, 7) the parameters (``pose_from_parameters``).
    """
    b = model.skeleton.num_bones
    dtype = dtype or model.mesh.V.dtype
    k1, k2, k3 = jax.random.split(key, 3)
    diagonal = _rest_diagonal(model)
    rot = jax.random.uniform(k1, (b, 3), dtype, -rotation, rotation)
    trans = jax.random.uniform(k2, (b, 3), dtype, -translation, translation) * diagonal
    scale = jax.random.uniform(k3, (b, 1), dtype, -log_scale, log_scale)
    return jnp.concatenate([rot, trans, scale], axis=-1)
