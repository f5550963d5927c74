"""Spline-aligned deformation (deformation paper eq. 1-2, sec. III-A/B) and the B-spline fit of key
motors (eq. 3-5, sec. III-C): the bases against scipy and their closed forms, the harmonic parameter
against its closed form on a tube, binding, rigid handles, a linear bend against Rodrigues' rotation,
batches, gradients by finite differences; the fit against numpy's least squares on both solver paths."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.interpolate import BSpline
from scipy.spatial.transform import Rotation

import jaxcga as cga
from deform import (
    blend_motors,
    clamped_knots,
    identity_motors,
    motor_about,
    motor_field_solve,
    motor_logs,
    spline_fit_precompute,
    spline_fit_solve,
    spline_parameter,
    spline_precompute,
    spline_weights,
)
from jaxcga import KINDS, MOTOR_GENERATOR, Multivector
from tests.shared import check_gradient, tube

V, F, START, END = tube()


@jax.jit
def _motors(axes, angles, shifts):
    return cga.motor(cga.rotor(axes, angles), shifts)


def random_motors(rng, k, angle=1.0, shift=1.0):
    """k <= 16 random motors, rotation angles below ``angle`` (so log(exp(x)) = x); drawn 16 at a time
    so that every k shares one compiled function."""
    pool = _motors(rng.normal(size=(16, 3)), rng.uniform(0.1, angle, 16), rng.normal(scale=shift, size=(16, 3)))
    return Multivector(pool.values[:k], pool.blades)


@jax.jit
def motors_from_logs(x):
    return cga.exp_motor(Multivector(x.reshape(-1, 6), MOTOR_GENERATOR)).embed(KINDS["motor"])


# jitted once per shape: eager multivector code compiles every primitive separately, which is slower
deformed = jax.jit(motor_field_solve)
moved = jax.jit(lambda motor, x: cga.apply_to_points(motor, x))
fitted_logs = jax.jit(lambda fit, Q: motor_logs(spline_fit_solve(fit, Q)))
logs_of = jax.jit(motor_logs)


def take(motors, i):
    return Multivector(motors.values[i], motors.blades)


# ---------------------------------------------------------------- bases
@pytest.mark.parametrize("num_keys, degree", [(4, 3), (7, 3), (5, 2), (3, 1), (9, 4)])
def test_bspline_weights_equal_scipy(num_keys, degree):
    lam = np.concatenate([np.linspace(0.0, 1.0, 201), np.random.default_rng(0).uniform(size=50)])
    W = np.asarray(spline_weights(lam, "bspline", num_keys, degree))
    reference = BSpline.design_matrix(lam, clamped_knots(num_keys, degree), degree).toarray()
    np.testing.assert_allclose(W, reference, atol=1e-14)


def test_closed_form_bases():
    lam = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(spline_weights(lam, "linear"), np.stack([1 - lam, lam], 1), atol=1e-15)
    lagrange = np.stack([2 * lam**2 - 3 * lam + 1, -4 * lam**2 + 4 * lam, 2 * lam**2 - lam], 1)
    np.testing.assert_allclose(spline_weights(lam, "lagrange"), lagrange, atol=1e-14)
    bezier = np.stack([(1 - lam) ** 3, 3 * lam * (1 - lam) ** 2, 3 * lam**2 * (1 - lam), lam**3], 1)
    np.testing.assert_allclose(spline_weights(lam, "bezier"), bezier, atol=1e-15)
    # the cubic Bezier basis is the 4-key cubic B-spline on a clamped knot vector
    np.testing.assert_allclose(spline_weights(lam, "bspline", 4), bezier, atol=1e-15)


@pytest.mark.parametrize("basis, num_keys", [("linear", None), ("lagrange", None), ("bezier", 6), ("bspline", 8)])
def test_bases_are_a_partition_of_unity_and_interpolate_the_end_keys(basis, num_keys):
    lam = np.linspace(0.0, 1.0, 333)
    W = np.asarray(spline_weights(lam, basis, num_keys))
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-14)
    k = W.shape[1]
    np.testing.assert_array_equal(W[0], np.eye(k)[0])
    np.testing.assert_array_equal(W[-1], np.eye(k)[-1])


def test_weights_bad_input():
    lam = np.linspace(0, 1, 5)
    with pytest.raises(ValueError, match="basis"):
        spline_weights(lam, "hermite")
    with pytest.raises(ValueError, match="num_keys"):
        spline_weights(lam, "lagrange", num_keys=4)
    with pytest.raises(ValueError, match="num_keys"):
        spline_weights(lam, "bspline", num_keys=3, degree=3)
    with pytest.raises(ValueError, match="degree"):
        spline_weights(lam, "bspline", num_keys=3, degree=0)
    with pytest.raises(ValueError, match="lam"):
        spline_weights(np.array([0.0, 1.1]), "linear")
    with pytest.raises(ValueError, match="lam"):
        spline_weights(np.array([0.0, np.nan]), "linear")
    with pytest.raises(ValueError, match=r"lam.*\(n,\)"):
        spline_weights(lam[None], "linear")
    with pytest.raises(Exception, match="lam"):  # inside jit: eqx.error_if
        jax.jit(lambda x: spline_weights(x, "linear"))(jnp.array([-0.5, 0.5])).block_until_ready()
    # rounding just outside [0, 1] is clipped
    W = np.asarray(spline_weights(np.array([-1e-12, 1 + 1e-12]), "linear"))
    np.testing.assert_array_equal(W, np.eye(2))


# ---------------------------------------------------------------- the harmonic parameter and binding
def test_parameter_is_linear_along_the_tube():
    # z is harmonic on the (intrinsically flat) tube, and the cotangent Laplacian reproduces it
    lam = np.asarray(spline_parameter(V, F, START, END))
    np.testing.assert_allclose(lam, (V[:, 2] + 1) / 2, atol=1e-11)
    assert np.all(lam[START] == 0.0) and np.all(lam[END] == 1.0)
    lam_mv = np.asarray(spline_parameter(V, F, START, END, laplacian="mean_value"))
    assert lam_mv.min() >= 0 and lam_mv.max() <= 1 and np.all(lam_mv[END] == 1.0)
    with pytest.raises(ValueError, match="disjoint"):
        spline_parameter(V, F, START, START[:3])
    with pytest.raises(ValueError, match="start, end"):
        spline_parameter(V, F, [], END)  # pyright: ignore[reportArgumentType]


@pytest.mark.parametrize(
    "basis, num_keys",
    [("linear", None), ("lagrange", None), pytest.param("bspline", 6, marks=pytest.mark.slow)],
)
def test_rest_motors_give_the_rest_mesh_and_handles_move_rigidly(basis, num_keys):
    rng = np.random.default_rng(1)
    k = spline_weights(np.zeros(1), basis, num_keys).shape[1]
    rest = random_motors(rng, k)
    field = spline_precompute(V, F, START, END, rest_motors=rest, basis=basis, num_keys=num_keys)
    assert field.num_keys == k
    np.testing.assert_allclose(deformed(field, rest), V, atol=1e-12)
    np.testing.assert_allclose(
        deformed(spline_precompute(V, F, START, END, basis=basis, num_keys=num_keys), identity_motors(k)), V, atol=1e-15
    )
    keys = random_motors(rng, k)
    X = np.asarray(deformed(field, keys))
    # lambda = 0 on H_1, 1 on H_n: those vertices move by R_1 ~R^0_1 and R_n ~R^0_n
    first = take(keys, 0) * cga.reverse(take(rest, 0))
    last = take(keys, k - 1) * cga.reverse(take(rest, k - 1))
    np.testing.assert_allclose(X[START], moved(first, V[START]), atol=1e-12)
    np.testing.assert_allclose(X[END], moved(last, V[END]), atol=1e-12)


def test_one_motor_on_every_key_moves_the_mesh_rigidly():
    G = random_motors(np.random.default_rng(2), 1)
    field = spline_precompute(V, F, START, END, basis="bspline", num_keys=7)
    keys = Multivector(jnp.repeat(G.values, 7, axis=0), G.blades)
    np.testing.assert_allclose(deformed(field, keys), moved(G, V), atol=1e-12)


def test_linear_bend_turns_each_section_by_its_share_of_the_angle():
    # R_1 = identity, R_2 = a quarter turn about the x axis through (0, 0.5, -1): with linear weights
    # M_i = exp(lambda_i log R_2) is the turn by lambda_i * 90 degrees about the same axis (Fig. 2)
    center, angle = np.array([0.0, 0.5, -1.0]), np.pi / 2
    bend = motor_about(jnp.asarray(center), cga.rotor(jnp.array([1.0, 0.0, 0.0]), jnp.asarray(angle)))
    keys = Multivector(jnp.concatenate([identity_motors(1).values, bend.values[None]]), KINDS["motor"])
    X = np.asarray(deformed(spline_precompute(V, F, START, END, basis="linear"), keys))
    lam = (V[:, 2] + 1) / 2
    expected = Rotation.from_rotvec(np.outer(lam * angle, [1.0, 0.0, 0.0])).apply(V - center) + center
    np.testing.assert_allclose(X, expected, atol=1e-10)
    np.testing.assert_allclose(X[START], V[START], atol=1e-15)
    np.testing.assert_allclose(X[END], moved(bend, V[END]), atol=1e-12)


@pytest.mark.slow
def test_jit_and_vmap_over_batches_of_key_motors():
    rng = np.random.default_rng(3)
    field = spline_precompute(V, F, START, END, basis="bspline", num_keys=5)
    batch = Multivector(jnp.stack([random_motors(rng, 5).values for _ in range(3)]), KINDS["motor"])
    one_by_one = np.stack([deformed(field, Multivector(batch.values[b], batch.blades)) for b in range(3)])
    np.testing.assert_allclose(deformed(field, batch), one_by_one, atol=1e-13)  # leading batch axes
    np.testing.assert_allclose(
        jax.jit(jax.vmap(lambda keys: motor_field_solve(field, keys)))(batch), one_by_one, atol=1e-13
    )


@pytest.mark.slow
def test_gradient_with_respect_to_key_motor_logs():
    rng = np.random.default_rng(4)
    small = tube(max_edge=0.4)
    field = spline_precompute(small[0], small[1], small[2], small[3], basis="lagrange")
    weights = jnp.asarray(rng.normal(size=(len(small[0]), 3)))

    def loss(x):
        return jnp.sum(weights * motor_field_solve(field, motors_from_logs(x)) ** 2)

    check_gradient(jax.jit(loss), jnp.asarray(rng.normal(scale=0.5, size=18)))


# ---------------------------------------------------------------- B-spline fit (eq. 3-5)
@pytest.mark.slow
def test_fit_recovers_the_key_motors_that_generated_the_data():
    rng = np.random.default_rng(5)
    lam = np.linspace(0.0, 1.0, 12)
    R_logs = rng.normal(scale=0.4, size=(5, 6))
    A = np.asarray(spline_weights(lam, "bspline", 5))
    Q = blend_motors(A, motors_from_logs(jnp.asarray(R_logs)))  # eq. (3)
    fit = spline_fit_precompute(lam, 5)
    assert fit.method == "cholesky" and 1 <= fit.condition < 1e3
    np.testing.assert_allclose(fitted_logs(fit, Q), R_logs, atol=1e-10)
    # the fit of data off the spline is numpy's least-squares solution
    noisy = random_motors(rng, 12, angle=2.0)
    q = np.asarray(logs_of(noisy))
    np.testing.assert_allclose(fitted_logs(fit, noisy), np.linalg.lstsq(A, q, rcond=None)[0], atol=1e-12)


@pytest.mark.slow
def test_ill_conditioned_fit_takes_the_svd_path_and_gives_the_minimum_norm_solution():
    rng = np.random.default_rng(6)
    lam = np.linspace(0.0, 0.3, 9)  # keys 5 and 6 of 7 have no parameter in their support
    fit = spline_fit_precompute(lam, 7)
    assert fit.method == "svd" and fit.condition == np.inf
    Q = random_motors(rng, 9)
    A = np.asarray(spline_weights(lam, "bspline", 7))
    reference = np.linalg.lstsq(A, np.asarray(logs_of(Q)), rcond=None)[0]
    # compared as motors: the minimum-norm logs may leave the principal branch of the logarithm
    motors = np.asarray(jax.jit(spline_fit_solve)(fit, Q).values)
    np.testing.assert_allclose(motors, motors_from_logs(jnp.asarray(reference)).values, atol=1e-10)
    np.testing.assert_array_equal(motors[5:], identity_motors(2).values)  # minimum norm: keys without data stay
    # the identity
    # a well-conditioned problem forced onto the SVD path gives the Cholesky answer
    lam = np.linspace(0.0, 1.0, 10)
    forced, normal = spline_fit_precompute(lam, 4, max_condition=1.0), spline_fit_precompute(lam, 4)
    assert (forced.method, normal.method) == ("svd", "cholesky")
    Q = random_motors(rng, 10)
    np.testing.assert_allclose(fitted_logs(forced, Q), fitted_logs(normal, Q), atol=1e-12)


@pytest.mark.slow
def test_fit_is_a_jax_function_of_the_motors():
    rng = np.random.default_rng(7)
    fit = spline_fit_precompute(np.linspace(0.0, 1.0, 8), 4)
    batch = Multivector(jnp.stack([random_motors(rng, 8).values for _ in range(3)]), KINDS["motor"])
    one_by_one = np.stack([fitted_logs(fit, Multivector(batch.values[b], batch.blades)) for b in range(3)])
    np.testing.assert_allclose(fitted_logs(fit, batch), one_by_one, atol=1e-13)  # leading batch axes
    np.testing.assert_allclose(jax.jit(jax.vmap(lambda Q: fitted_logs(fit, Q)))(batch), one_by_one, atol=1e-13)
    target = jnp.asarray(rng.normal(size=(4, 8)))

    def loss(x):
        return jnp.sum(target * spline_fit_solve(fit, motors_from_logs(x)).values)

    check_gradient(jax.jit(loss), jnp.asarray(rng.normal(scale=0.4, size=48)))


def test_fit_bad_input():
    lam = np.linspace(0.0, 1.0, 8)
    with pytest.raises(ValueError, match="lam"):
        spline_fit_precompute(lam[None], 4)
    with pytest.raises(ValueError, match="lam"):
        spline_fit_precompute(lam + 0.5, 4)
    with pytest.raises(ValueError, match="num_keys"):
        spline_fit_precompute(lam, 3)
    with pytest.raises(ValueError, match="max_condition"):
        spline_fit_precompute(lam, 4, max_condition=0.5)
    with pytest.raises(ValueError, match="rcond"):
        spline_fit_precompute(lam, 4, rcond=2.0)
    with pytest.raises(ValueError, match="lam"):
        jax.jit(lambda x: spline_fit_precompute(x, 4).A)(jnp.asarray(lam))
    fit = spline_fit_precompute(lam, 4)
    with pytest.raises(ValueError, match=r"Q.*\(\.\.\., 8\)"):
        spline_fit_solve(fit, identity_motors(7))
    with pytest.raises(ValueError, match="Q"):
        spline_fit_solve(fit, Multivector(jnp.zeros((8, 5)), KINDS["vector"]))
    with pytest.raises(ValueError, match="data"):
        spline_fit_solve(fit.A, identity_motors(8))  # pyright: ignore[reportArgumentType]
