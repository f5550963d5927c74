"""The rig: TRS -> matrices / versors, forward kinematics, clip sampling (glTF specification and the
multivector path), user keyframes, clips made from poses.

Independent references: scipy's Slerp and Rotation, closed-form polynomials and interpolants."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation, Slerp

import deform
import jaxcga as cga
from tests.deform._rigs import random_model, random_pose, unit_quaternions


def _channel(path, times, values, interpolation="LINEAR", bone=0):
    return deform.Channel(jnp.asarray(times, float), jnp.asarray(values, float), bone, path, interpolation)


def test_trs_matrix_and_versor_agree():
    rng = np.random.default_rng(0)
    q = unit_quaternions(rng, 6)
    t = rng.normal(size=(6, 3))
    s = np.repeat(rng.uniform(0.3, 3.0, (6, 1)), 3, axis=1)
    m = deform.trs_to_matrix(jnp.asarray(t), jnp.asarray(q), jnp.asarray(s))
    expected = np.zeros((6, 4, 4))
    expected[:, :3, :3] = Rotation.from_quat(q).as_matrix() * s[:, None, :]
    expected[:, :3, 3] = t
    expected[:, 3, 3] = 1
    np.testing.assert_allclose(m, expected, atol=1e-13)
    v = deform.trs_to_versor(jnp.asarray(t), jnp.asarray(q), jnp.asarray(s))
    np.testing.assert_allclose(cga.versor_to_matrix(v), expected, atol=1e-12)
    back_t, back_q, back_s = deform.versor_to_trs(v)
    np.testing.assert_allclose(back_t, t, atol=1e-12)
    np.testing.assert_allclose(np.abs(np.sum(np.asarray(back_q) * q, axis=1)), 1.0, atol=1e-12)
    np.testing.assert_allclose(back_s, s, atol=1e-12)


def test_non_uniform_scale_has_no_versor():
    with pytest.raises(Exception, match="non-uniform"):
        jax.block_until_ready(deform.trs_to_versor(jnp.zeros(3), jnp.array([0.0, 0, 0, 1]), jnp.array([1.0, 2.0, 1.0])))
    # the matrix path takes it
    m = deform.trs_to_matrix(jnp.zeros(3), jnp.array([0.0, 0, 0, 1]), jnp.array([1.0, 2.0, 1.0]))
    np.testing.assert_allclose(np.diag(m), [1, 2, 1, 1])


@pytest.mark.slow
def test_forward_kinematics_versors_equal_matrices():
    model = random_model(1, parents=(-1, 0, 0, 1, 3, 3, -1, 6), rest_scale=(0.5, 2.0))
    local = random_pose(2, 8, scale_range=(0.5, 1.5))
    g_v = deform.forward_kinematics(model.skeleton.parents, local)
    g_m = deform.forward_kinematics_matrices(model.skeleton.parents, cga.versor_to_matrix(local))
    np.testing.assert_allclose(cga.versor_to_matrix(g_v), g_m, atol=1e-11)
    # chained products by hand for one leaf: bone 5 <- 3 <- 1 <- 0
    chain = local[0] * local[1] * local[3] * local[5]
    np.testing.assert_allclose(g_v[5].values, chain.values, atol=1e-12)
    # jit and a batch of poses
    batched = cga.Multivector(jnp.stack([local.values, local.values]), local.blades)
    out = jax.jit(lambda l: deform.forward_kinematics(model.skeleton.parents, l))(batched)
    np.testing.assert_allclose(out.values[1], g_v.values, atol=1e-12)


def test_forward_kinematics_matrices_equal_the_product_down_each_chain():
    # a chain of depth 11 (rounds of doubling on a GPU: 4), a branch and a second root, against numpy's products
    parents = (-1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 3, 12, -1, 14)
    local = cga.versor_to_matrix(random_pose(3, len(parents), scale_range=(0.8, 1.25)))
    expected = []
    for i, p in enumerate(parents):
        expected.append(np.asarray(local[i]) if p < 0 else expected[p] @ np.asarray(local[i]))
    np.testing.assert_allclose(deform.forward_kinematics_matrices(parents, local), np.stack(expected), atol=1e-12)
    # parents as a traced array (packed rigs) give the same globals
    traced = jax.jit(deform.forward_kinematics_matrices)(jnp.asarray(parents), local)
    np.testing.assert_allclose(traced, np.stack(expected), atol=1e-12)
    with pytest.raises(ValueError, match=r"parents: bone 1 has parent 2"):
        deform.forward_kinematics_matrices((-1, 2, 0), local[:3])


def test_linear_translation_and_clamping():
    c = _channel("translation", [0.0, 1.0, 3.0], [[0, 0, 0], [1, 2, 3], [3, 2, 1]])
    np.testing.assert_allclose(deform.sample_channel(c, 0.5), [0.5, 1.0, 1.5])
    np.testing.assert_allclose(deform.sample_channel(c, 2.0), [2.0, 2.0, 2.0])
    np.testing.assert_allclose(deform.sample_channel(c, -1.0), [0, 0, 0])
    np.testing.assert_allclose(deform.sample_channel(c, 9.0), [3, 2, 1])
    np.testing.assert_allclose(deform.sample_channel(c, 1.0), [1, 2, 3])


def test_linear_rotation_is_shortest_arc_slerp():
    rng = np.random.default_rng(3)
    q = unit_quaternions(rng, 4)
    q[2] = -q[2]  # a sign flip between keys must not change the path
    times = np.array([0.0, 0.7, 1.5, 2.0])
    c = _channel("rotation", times, q)
    ref = Slerp(times, Rotation.from_quat(q))
    for t in [0.1, 0.69, 1.0, 1.8]:
        out = np.asarray(deform.sample_channel(c, t))
        np.testing.assert_allclose(Rotation.from_quat(out).as_matrix(), ref([t]).as_matrix()[0], atol=1e-10)


def test_step_holds_each_key():
    c = _channel("scale", [0.0, 1.0, 2.0], [[1, 1, 1], [2, 2, 2], [3, 3, 3]], "STEP")
    for t, v in [(0.0, 1), (0.99, 1), (1.0, 2), (1.5, 2), (2.0, 3), (5.0, 3)]:
        np.testing.assert_allclose(deform.sample_channel(c, t), [v, v, v])


def test_cubic_spline_reproduces_a_cubic():
    """Hermite keys with the exact derivatives of a cubic reproduce it between keys."""
    times = np.array([0.0, 0.5, 1.7, 2.0])

    def p(t):
        return np.stack([t**3 - 2 * t, 0.5 * t**2 + 1, -(t**3) + t], axis=-1)

    def dp(t):
        return np.stack([3 * t**2 - 2, t, -3 * t**2 + 1], axis=-1)

    values = np.stack([dp(times), p(times), dp(times)], axis=1)  # in-tangent, value, out-tangent
    c = _channel("translation", times, values, "CUBICSPLINE")
    for t in [0.2, 0.5, 1.1, 1.95]:
        np.testing.assert_allclose(deform.sample_channel(c, t), p(np.array(t)), atol=1e-12)


@pytest.mark.slow
def test_versor_sampling_equals_specification_for_translation_and_rotation():
    model = random_model(4)
    rng = np.random.default_rng(4)
    times = np.array([0.0, 0.4, 1.0, 1.6])
    channels = (
        _channel("rotation", times, unit_quaternions(rng, 4), bone=1),
        _channel("translation", times, rng.normal(size=(4, 3)), bone=2),
        _channel("rotation", times[:2], unit_quaternions(rng, 2), "STEP", bone=3),
    )
    clip = deform.AnimationClip(channels, "test")
    for t in [0.0, 0.2, 0.55, 1.3, 2.0]:
        spec = deform.sample_matrices(model.skeleton, clip, t)
        ours = cga.versor_to_matrix(deform.sample_versors(model.skeleton, clip, t))
        np.testing.assert_allclose(ours, spec, atol=1e-11)


@pytest.mark.slow
def test_versor_sampling_blends_dilations_geometrically():
    model = random_model(5)
    clip = deform.AnimationClip((_channel("scale", [0.0, 1.0], [[1.0] * 3, [4.0] * 3], bone=1),))
    spec = deform.sample_trs(model.skeleton, clip, 0.5)[2][1]
    np.testing.assert_allclose(spec, [2.5] * 3)  # the specification lerps
    m = cga.versor_to_matrix(deform.sample_versors(model.skeleton, clip, 0.5)[1])
    np.testing.assert_allclose(np.cbrt(np.linalg.det(m[:3, :3])), 2.0, atol=1e-12)  # log blending: sqrt(1 * 4)


def test_sampling_vmaps_over_times():
    model = random_model(6)
    rng = np.random.default_rng(6)
    clip = deform.AnimationClip((_channel("rotation", [0.0, 1.0, 2.0], unit_quaternions(rng, 3), bone=1),))
    times = jnp.linspace(-0.5, 2.5, 7)
    batched = jax.jit(jax.vmap(lambda t: deform.sample_versors(model.skeleton, clip, t).values))(times)
    for k, t in enumerate(times):
        np.testing.assert_allclose(batched[k], deform.sample_versors(model.skeleton, clip, t).values, atol=1e-12)


@pytest.mark.slow
def test_keyframes_blend_linearly_and_align_signs():
    a, b = random_pose(7, 3), random_pose(8, 3)
    keys = deform.Keyframes(jnp.array([0.0, 2.0]), cga.Multivector(jnp.stack([a.values, -b.values]), a.blades))
    np.testing.assert_allclose(deform.sample_keyframes(keys, 0.0).values, a.values, atol=1e-12)
    at_end = deform.sample_keyframes(keys, 2.0)
    np.testing.assert_allclose(cga.versor_to_matrix(at_end), cga.versor_to_matrix(b), atol=1e-12)
    # halfway: (a + b) / 2 renormalized, b's sign flipped to a's hemisphere first
    mid = deform.sample_keyframes(keys, 1.0)
    aligned = jnp.where(jnp.sum(a.values * b.values, axis=-1, keepdims=True) < 0, -b.values, b.values)
    expected = cga.blend_linear(a, cga.Multivector(aligned, b.blades), 0.5)
    np.testing.assert_allclose(mid.values, expected.values, atol=1e-12)
    with pytest.raises(ValueError, match="poses"):
        deform.Keyframes(jnp.array([0.0]), a)


@pytest.mark.slow
def test_clip_from_poses_round_trip():
    model = random_model(9)
    poses = cga.Multivector(jnp.stack([random_pose(k, 5).values for k in range(4)]), random_pose(0, 5).blades)
    times = jnp.array([0.0, 0.5, 1.0, 2.0])
    clip = deform.clip_from_poses(times, poses, "made")
    assert len(clip.channels) == 10  # translation + rotation per bone, no scale channel
    for k, t in enumerate(times):
        np.testing.assert_allclose(
            deform.sample_matrices(model.skeleton, clip, t), cga.versor_to_matrix(poses[k]), atol=1e-12
        )
    rotation = [c for c in clip.channels if c.path == "rotation"][0].values
    assert np.all(np.sum(np.asarray(rotation[1:] * rotation[:-1]), axis=-1) >= 0)


def test_model_validation_errors():
    with pytest.raises(ValueError, match="parents"):
        deform.Skeleton(jnp.zeros((2, 3)), jnp.zeros((2, 4)), jnp.ones((2, 3)), (1, -1), ("a", "b"))
    with pytest.raises(ValueError, match="names"):
        deform.Skeleton(jnp.zeros((2, 3)), jnp.zeros((2, 4)), jnp.ones((2, 3)), (-1, 0), ("a", "a"))
    with pytest.raises(ValueError, match="rotation"):
        deform.Skeleton(jnp.zeros((2, 3)), jnp.zeros((2, 3)), jnp.ones((2, 3)), (-1, 0), ("a", "b"))
    with pytest.raises(ValueError, match="values"):
        _channel("rotation", [0.0, 1.0], [[0, 0, 0], [0, 0, 0]])
    with pytest.raises(ValueError, match="interpolation"):
        _channel("translation", [0.0], [[0, 0, 0]], "SMOOTH")
    model = random_model(10)
    with pytest.raises(ValueError, match="no clip"):
        model.clip("walk")
    with pytest.raises(ValueError, match="local"):
        deform.forward_kinematics(model.skeleton.parents, random_pose(0, 3))
