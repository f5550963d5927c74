"""FABRIK (Aristidou & Lasenby 2011) and the joint motors of the deformation paper's sec. III-C / Fig. 5:
reached targets, bone lengths, fixed root, the straight chain for far targets, the law of cosines for
two bones, jit / vmap / gradients, motors that map rest joints onto posed joints, minimal rotations, and
the whole path: FABRIK -> motors -> B-spline fit -> spline deformation of a tube."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga as cga
from deform import (
    chain_motors,
    fabrik,
    motor_field_solve,
    rotor_between,
    spline_fit_precompute,
    spline_fit_solve,
    spline_precompute,
)
from jaxcga import Multivector
from tests.shared import check_gradient, tube

solve = jax.jit(fabrik, static_argnames="max_iterations")
moved = jax.jit(lambda motor, x: cga.apply_to_points(motor, x))


def random_chain(rng, bones=5):
    directions = rng.normal(size=(bones, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    lengths = rng.uniform(0.5, 1.5, bones)
    root = rng.normal(size=3)
    return np.concatenate([root[None], root + np.cumsum(lengths[:, None] * directions, axis=0)]), lengths


def reachable_target(rng, P, lengths, fraction):
    direction = rng.normal(size=3)
    return P[0] + fraction * lengths.sum() * direction / np.linalg.norm(direction)


def test_reachable_targets_are_reached_with_bone_lengths_kept_and_the_root_fixed():
    rng = np.random.default_rng(0)
    for _ in range(5):
        P, lengths = random_chain(rng)
        target = reachable_target(rng, P, lengths, rng.uniform(0.3, 0.9))
        S = np.asarray(solve(P, target, max_iterations=500, tolerance=1e-11))
        assert np.linalg.norm(S[-1] - target) <= 1e-11
        np.testing.assert_allclose(np.linalg.norm(np.diff(S, axis=0), axis=1), lengths, rtol=1e-12)
        np.testing.assert_array_equal(S[0], P[0])


def test_unreachable_target_stretches_the_chain_straight_toward_it():
    rng = np.random.default_rng(1)
    P, lengths = random_chain(rng)
    target = reachable_target(rng, P, lengths, 1.5)
    S = np.asarray(solve(P, target))
    direction = (target - P[0]) / np.linalg.norm(target - P[0])
    offsets = np.concatenate([[0.0], np.cumsum(lengths)])
    np.testing.assert_allclose(S, P[0] + offsets[:, None] * direction, atol=1e-12)


def test_two_bones_bend_by_the_law_of_cosines():
    a, b = 1.0, 0.7
    P = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, a], [0.0, 0.0, a + b]])
    for c in (0.5, 1.0, 1.5):
        target = c * np.array([0.6, 0.0, 0.8])
        S = np.asarray(solve(P, target, max_iterations=1000, tolerance=1e-12))
        upper, lower = S[1] - S[0], S[2] - S[1]
        elbow = np.arccos(np.dot(-upper, lower) / (a * b))  # the angle inside the triangle at the elbow
        np.testing.assert_allclose(elbow, np.arccos((a**2 + b**2 - c**2) / (2 * a * b)), atol=1e-9)
        np.testing.assert_allclose(S[2], target, atol=1e-12)


def test_vmap_over_targets_and_gradients():
    rng = np.random.default_rng(2)
    P, lengths = random_chain(rng, bones=3)
    targets = np.stack([reachable_target(rng, P, lengths, f) for f in (0.4, 0.7, 1.2)])
    batched = jax.jit(jax.vmap(lambda t: fabrik(P, t, max_iterations=100)))(targets)
    for t, S in zip(targets, np.asarray(batched)):
        np.testing.assert_allclose(S, solve(P, t, max_iterations=100), atol=1e-14)
    # a fixed number of passes (tolerance 0) is a smooth function of the target
    weights = jnp.asarray(rng.normal(size=(4, 3)))
    loss = jax.jit(lambda t: jnp.sum(weights * fabrik(P, t, max_iterations=20, tolerance=0.0)))
    check_gradient(loss, jnp.asarray(targets[0]))


def test_bad_input():
    P = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match=r"P.*\(m \+ 1, 3\)"):
        fabrik(P[:1], np.zeros(3))
    with pytest.raises(ValueError, match=r"target.*\(3,\)"):
        fabrik(P, np.zeros(2))
    with pytest.raises(ValueError, match="max_iterations"):
        fabrik(P, np.zeros(3), max_iterations=0)
    with pytest.raises(Exception, match="positive length"):
        solve(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), np.ones(3)).block_until_ready()
    with pytest.raises(Exception, match="target"):
        solve(P, np.array([np.nan, 0.0, 0.0])).block_until_ready()
    with pytest.raises(ValueError, match="posed"):
        chain_motors(P, np.zeros((3, 3)))


# ---------------------------------------------------------------- joint motors
def test_rotor_between_is_the_minimal_rotation():
    rng = np.random.default_rng(3)
    u, v = rng.normal(size=(50, 3)), rng.normal(size=(50, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    v[0], v[1], v[2] = u[0], -u[1], -u[2] + np.array([1e-13, 0.0, 0.0])  # parallel, opposite, near opposite
    v[2] /= np.linalg.norm(v[2])
    R = rotor_between(u, v)
    np.testing.assert_allclose(moved(R, u), v, atol=1e-12)
    # minimal: the rotation angle is the angle between u and v (the rotor's scalar part is cos(angle / 2))
    angle = 2 * np.arccos(np.clip(np.abs(np.asarray(R.values[:, 0])), 0, 1))
    np.testing.assert_allclose(angle, np.arccos(np.clip(np.sum(u * v, axis=1), -1, 1)), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(R.values), axis=1), 1.0, atol=1e-14)


def test_motors_map_rest_joints_onto_posed_joints():
    rng = np.random.default_rng(4)
    P, lengths = random_chain(rng)
    S = solve(P, reachable_target(rng, P, lengths, 0.6))
    Q = chain_motors(P, S)
    assert Q.batch_shape == (len(P),)
    np.testing.assert_allclose(moved(Q, P), S, atol=1e-12)
    # Q_{i+1} is bone i's rigid motion: it carries rest joint i onto posed joint i too
    bones = Multivector(Q.values[1:], Q.blades)
    np.testing.assert_allclose(moved(bones, P[:-1]), S[:-1], atol=1e-12)
    np.testing.assert_allclose(Q.values[0], np.eye(8)[0], atol=1e-15)  # fixed root: identity


@pytest.mark.slow
def test_fabrik_drives_a_spline_path_deformation_of_a_tube():
    # Fig. 5: a chain along the tube's axis, solved for a target; its joint motors Q_i at lambda_i = i / m
    # are fitted by k < m + 1 B-spline key motors that deform the tube
    V, F, start, end = tube()
    m, k = 8, 5
    P = np.stack([np.zeros(m + 1), np.zeros(m + 1), np.linspace(-1.0, 1.0, m + 1)], axis=1)
    target = np.array([0.9, 0.3, 0.6])
    S = solve(P, target, max_iterations=200)
    np.testing.assert_allclose(S[-1], target, atol=1e-9)
    fit = spline_fit_precompute(np.arange(m + 1) / m, k)
    assert fit.method == "cholesky"
    keys = spline_fit_solve(fit, chain_motors(P, S))
    X = np.asarray(jax.jit(motor_field_solve)(spline_precompute(V, F, start, end, num_keys=k), keys))
    np.testing.assert_allclose(X[start], V[start], atol=0.01)  # the root handle stays (up to the fit)
    assert np.linalg.norm(X[end].mean(axis=0) - target) < 0.02  # the tip cap's centre is near the target
    # the tube follows the chain: the centre of the ring at each rest joint lands near the posed joint
    for i in range(m + 1):
        ring = np.abs(V[:, 2] - P[i, 2]) < 1e-9
        assert np.linalg.norm(X[ring].mean(axis=0) - S[i]) < 0.03
