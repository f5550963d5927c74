"""Harmonic motor handles (deformation paper sec. IV) and fitting key motors to targets: the rest mesh
from identity motors, rigid handles, the same motor everywhere is that rigid map, batches, gradients by
finite differences, recovery of known key motors by optimistix for the spline, the handles and the FFD,
bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga as cga
from deform import (
    bounding_lattice,
    default_arm,
    ffd_precompute,
    fit_key_motors,
    generators_to_motors,
    handles_precompute,
    harmonic_fields,
    identity_motors,
    motor_about,
    motor_field_precompute,
    motor_field_solve,
    spline_precompute,
)
from tests.shared import assert_checks_placed_per_platform, check_gradient

ARM = default_arm().mesh
V, F = np.asarray(ARM.V, np.float64), np.asarray(ARM.F)
X = V[:, 0]
HANDLES = [np.flatnonzero(X < 0.0), np.flatnonzero(X > 0.75), np.flatnonzero(np.abs(X - 0.4) < 0.01)]
FIELD = handles_precompute(V, F, HANDLES)


def _motors(rng, k, rotation=0.5, translation=0.1):
    generators = np.concatenate(
        [rng.uniform(-rotation, rotation, (k, 3)), rng.uniform(-translation, translation, (k, 3))], axis=1
    )
    return generators_to_motors(jnp.asarray(generators))


@pytest.mark.slow
def test_weights_are_the_harmonic_fields_and_identity_motors_give_the_rest_mesh():
    np.testing.assert_array_equal(FIELD.weights, harmonic_fields(V, F, HANDLES))
    np.testing.assert_allclose(FIELD.weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(motor_field_solve(FIELD, identity_motors(3)), V, atol=1e-14)


@pytest.mark.slow
@pytest.mark.parametrize("laplacian", ["cotangent", "mean_value"])
def test_handle_vertices_move_rigidly_by_their_motor(laplacian):
    field = handles_precompute(V, F, HANDLES, laplacian=laplacian)
    motors = _motors(np.random.default_rng(1), 3)
    moved = np.asarray(motor_field_solve(field, motors))
    for j, part in enumerate(HANDLES):
        one = cga.Multivector(motors.values[j], motors.blades)
        np.testing.assert_allclose(moved[part], cga.apply_to_points(one, V[part]), atol=1e-12)
    # between the handles the motion blends: nowhere equal to a handle's rigid map
    free = np.setdiff1d(np.arange(len(V)), np.concatenate(HANDLES))
    rigid = [
        np.asarray(cga.apply_to_points(cga.Multivector(motors.values[j], motors.blades), V[free])) for j in range(3)
    ]
    assert all(np.abs(moved[free] - r).max() > 1e-3 for r in rigid)


@pytest.mark.slow
def test_the_same_motor_on_every_handle_is_that_rigid_map():
    G = motor_about(jnp.array([0.3, 0.1, -0.2]), cga.rotor(jnp.array([1.0, 2.0, 0.5]), 2.5), jnp.array([0.4, 0, 1]))
    motors = cga.Multivector(jnp.broadcast_to(G.values, (3, 8)), G.blades)
    np.testing.assert_allclose(motor_field_solve(FIELD, motors), cga.apply_to_points(G, V), atol=1e-12)


def test_binding_to_rest_motors_gives_back_the_rest_mesh():
    rest = _motors(np.random.default_rng(2), 3)
    bound = motor_field_precompute(V, FIELD.weights, rest_motors=rest)
    np.testing.assert_allclose(motor_field_solve(bound, rest), V, atol=1e-12)
    with pytest.raises(ValueError, match="rest_motors"):
        motor_field_precompute(V, FIELD.weights, rest_motors=identity_motors(2))


@pytest.mark.slow
def test_batches_of_handle_motors_under_jit_and_vmap():
    rng = np.random.default_rng(3)
    batch = cga.Multivector(jnp.stack([_motors(rng, 3).values for _ in range(4)]), cga.KINDS["motor"])
    one_by_one = np.stack([motor_field_solve(FIELD, cga.Multivector(batch.values[i], batch.blades)) for i in range(4)])
    np.testing.assert_allclose(jax.jit(motor_field_solve)(FIELD, batch), one_by_one, atol=1e-12)  # leading batch axes
    mapped = jax.vmap(lambda values: motor_field_solve(FIELD, cga.Multivector(values, batch.blades)))(batch.values)
    np.testing.assert_allclose(mapped, one_by_one, atol=1e-12)


@pytest.mark.slow
def test_gradient_with_respect_to_handle_generators_matches_finite_differences():
    rng = np.random.default_rng(4)
    target = V + 0.05 * rng.normal(size=V.shape)
    params0 = jnp.asarray(rng.uniform(-0.3, 0.3, 18))

    def loss(params):
        return jnp.sum((motor_field_solve(FIELD, generators_to_motors(params.reshape(3, 6))) - target) ** 2)

    check_gradient(jax.jit(loss), params0)


@pytest.mark.parametrize(
    "method, solver", [("spline", "gauss_newton"), ("handles", "levenberg_marquardt"), ("ffd", "levenberg_marquardt")]
)
@pytest.mark.slow
def test_fit_recovers_known_key_motors(method, solver):
    """Targets from known key motors of the spline (eq. 1-2), the harmonic handles (sec. IV) and the motor
    FFD (eq. 7-8) are fitted back (Gauss-Newton compiles in half the time of Levenberg-Marquardt, which
    is the default). Handles: the fixed region (key 0) is not fitted."""
    rng = np.random.default_rng(5)
    if method == "spline":
        field, free = spline_precompute(V, F, HANDLES[0], HANDLES[1], num_keys=4), None
    elif method == "handles":
        field, free = FIELD, [1, 2]
    else:
        field, free = ffd_precompute(V, bounding_lattice(V, (2, 2, 2), padding=0.05)), None
    keys = np.arange(field.num_keys) if free is None else np.asarray(free)
    truth = np.zeros((field.num_keys, 6))
    truth[keys] = np.concatenate([rng.uniform(-0.4, 0.4, (len(keys), 3)), rng.uniform(-0.1, 0.1, (len(keys), 3))], 1)
    targets = jax.jit(motor_field_solve)(field, generators_to_motors(jnp.asarray(truth)))
    fit = fit_key_motors(field, targets, free=free, solver=solver)
    diagonal = np.linalg.norm(V.max(axis=0) - V.min(axis=0))
    assert bool(fit.converged) and float(fit.max_error) < 1e-6 * diagonal
    np.testing.assert_allclose(fit.generators, truth, atol=1e-6)
    if free is not None:
        np.testing.assert_allclose(fit.motors.values[0], identity_motors(1).values[0])  # the fixed region


@pytest.mark.slow
def test_fit_by_gradient_based_minimisation():
    """BFGS on the squared residual (optimistix.minimise) reaches the same handle motors."""
    rng = np.random.default_rng(7)
    truth = np.zeros((3, 6))
    truth[1:] = np.concatenate([rng.uniform(-0.3, 0.3, (2, 3)), rng.uniform(-0.05, 0.05, (2, 3))], axis=1)
    targets = motor_field_solve(FIELD, generators_to_motors(jnp.asarray(truth)))
    fit = fit_key_motors(FIELD, targets, free=[1, 2], solver="bfgs", max_steps=400)
    diagonal = np.linalg.norm(V.max(axis=0) - V.min(axis=0))
    assert float(fit.max_error) < 1e-6 * diagonal
    np.testing.assert_allclose(fit.generators, truth, atol=1e-5)


@pytest.mark.slow
def test_fit_to_a_handful_of_vertices_with_a_regularizer():
    tip = HANDLES[1][:3]
    targets = V[tip] + np.array([0.0, 0.15, 0.05])
    fit = fit_key_motors(FIELD, targets, tip, free=[1, 2], regularization=1e-6)
    assert float(fit.max_error) < 1e-3
    # the fixed handle stays where it is, the rest of the mesh moves smoothly
    np.testing.assert_allclose(fit.positions[HANDLES[0]], V[HANDLES[0]], atol=1e-12)
    assert np.all(np.isfinite(fit.positions))


def test_bad_input():
    with pytest.raises(ValueError, match="handles"):
        handles_precompute(V, F, [HANDLES[0], HANDLES[0]])
    with pytest.raises(ValueError, match="key_motors"):
        motor_field_solve(FIELD, identity_motors(2))
    with pytest.raises(ValueError, match="targets"):
        fit_key_motors(FIELD, V[:3], [0, 1])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="free"):
        fit_key_motors(FIELD, V, free=[3])
    with pytest.raises(ValueError, match="field"):
        fit_key_motors("field", V)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="weights"):
        motor_field_precompute(V, np.ones((len(V) - 1, 3)))
    with pytest.raises(ValueError, match="field"):
        motor_field_solve(FIELD.weights, identity_motors(3))  # pyright: ignore[reportArgumentType]


def test_a_key_motor_without_a_norm_raises_eagerly_and_under_jit():
    zero_key = cga.Multivector(identity_motors(3).values.at[1].set(0.0), "motor")
    with pytest.raises(ValueError, match="key_motors: a key motor has non-positive norm"):
        motor_field_solve(FIELD, zero_key)
    # a failed callback: a JaxRuntimeError, or a ValueError from an executable compiled by an earlier test
    with pytest.raises((RuntimeError, ValueError), match="key_motors: a key motor has non-positive norm"):
        jax.block_until_ready(jax.jit(motor_field_solve)(FIELD, zero_key))  # on a GPU: when the result is ready


def test_the_key_motors_are_checked_on_the_positions():
    assert_checks_placed_per_platform(motor_field_solve, FIELD, identity_motors(3))
