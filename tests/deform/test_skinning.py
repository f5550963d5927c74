"""Skinning equations (16), (17) in both variants, and DQS, on hand-made rigs.

Independent checks: eq. (17) evaluated literally with the kernel's generic sandwich on conformal
points (sum of conformal points, then down-projection), matrix LBS from numpy, a rigid motion on
every bone, DQS from the kernel's motor -> dual quaternion conversion, finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
import jaxcga as cga
from tests.deform._rigs import random_model, random_pose
from tests.shared import assert_checks_placed_per_platform

MODEL = random_model(0, rest_scale=(0.5, 2.0))
B = MODEL.skeleton.num_bones
MESH = MODEL.mesh


def _numpy_lbs(model, local_matrices):
    parents = model.skeleton.parents
    g = []
    for i, p in enumerate(parents):
        g.append(np.asarray(local_matrices[i]) if p < 0 else g[p] @ np.asarray(local_matrices[i]))
    joint = np.stack([g[b] for b in model.mesh.joints]) @ np.asarray(model.mesh.inverse_bind)
    V, J, W = (np.asarray(x) for x in (model.mesh.V, model.mesh.J, model.mesh.W))
    blended = np.einsum("nk,nkij->nij", W, joint[J])
    return np.einsum("nij,nj->ni", blended[:, :3, :3], V) + blended[:, :3, 3]


def test_joint_versors_take_precomputed_inverse_bind_versors():
    local = random_pose(2, B, scale_range=(0.5, 2.0))
    global_versors = deform.forward_kinematics(MODEL.skeleton.parents, local)
    inverse_bind = deform.inverse_bind_versors(MESH)
    given = deform.joint_versors(MESH, global_versors, inverse_bind)
    np.testing.assert_allclose(given.values, deform.joint_versors(MESH, global_versors).values, atol=1e-13)
    # against the matrices: joint matrix = global bone matrix @ inverse bind matrix
    expected = deform.joint_matrices(MESH, cga.versor_to_matrix(global_versors))
    np.testing.assert_allclose(cga.versor_to_matrix(given), expected, atol=1e-12)
    with pytest.raises(ValueError, match="inverse_bind: expected versors with batch shape"):
        deform.joint_versors(MESH, global_versors, inverse_bind[:-1])
    with pytest.raises(ValueError, match="inverse_bind: expected versors"):
        deform.joint_versors(MESH, global_versors, MESH.inverse_bind)  # pyright: ignore[reportArgumentType]


@pytest.mark.parametrize("method", deform.METHODS)
def test_rest_pose_reproduces_bind_positions(method):
    np.testing.assert_allclose(deform.rest_pose(MODEL, method), MESH.V, atol=1e-12)


@pytest.mark.slow
def test_cga_with_dilations_against_numpy_lbs():
    local = random_pose(1, B, scale_range=(0.5, 2.0))
    expected = _numpy_lbs(MODEL, cga.versor_to_matrix(local))
    np.testing.assert_allclose(deform.skin_pose(MODEL, local, "lbs"), expected, atol=1e-12)
    # the paper's evaluation (sec. 4.3, the default): each sandwiched point down-projected, then blended
    np.testing.assert_allclose(deform.skin_pose(MODEL, local, "cga"), expected, atol=1e-12)
    joints = deform.joint_versors(MESH, deform.forward_kinematics(MODEL.skeleton.parents, local))
    normalized = deform.skin_cga(MESH.V, MESH.J, MESH.W, joints, normalize_points=True)
    np.testing.assert_allclose(normalized, expected, atol=1e-12)
    # Eq. (17) down-projected after the sum: each influence weighted by lambda = 1 / (its joint's scale).
    matrices = np.asarray(cga.versor_to_matrix(joints))
    scale = np.cbrt(np.linalg.det(matrices[:, :3, :3]))
    moved = np.einsum("nkij,nj->nki", matrices[np.asarray(MESH.J), :3, :3], np.asarray(MESH.V))
    moved = moved + matrices[np.asarray(MESH.J), :3, 3]
    weight = np.asarray(MESH.W) / scale[np.asarray(MESH.J)]
    literal = np.einsum("nk,nki->ni", weight, moved) / weight.sum(axis=1, keepdims=True)
    np.testing.assert_allclose(
        deform.skin_cga(MESH.V, MESH.J, MESH.W, joints, normalize_points=False), literal, atol=1e-12
    )
    assert np.max(np.abs(literal - expected)) > 1e-2  # dilations make the two evaluations differ


def test_cga_equals_lbs_for_rigid_joints():
    model = random_model(11)
    local = random_pose(11, B)
    np.testing.assert_allclose(deform.skin_pose(model, local, "cga"), deform.skin_pose(model, local, "lbs"), atol=1e-12)


def test_cga_equals_literal_equation_17():
    """sum_n w_mn (M_n B_n) c[m] (M_n B_n)^-1 with the kernel's generic sandwich, down-projected term by
    term (sec. 4.3, the default) or as a sum."""
    local = random_pose(2, B, scale_range=(0.5, 2.0))
    joints = deform.joint_versors(MESH, deform.forward_kinematics(MODEL.skeleton.parents, local))
    moved = cga.sandwich(joints[MESH.J], cga.up(MESH.V)[:, None])  # (n, k) conformal points
    terms = jnp.einsum("nk,nkc->nc", MESH.W, cga.down(moved))
    np.testing.assert_allclose(deform.skin_pose(MODEL, local, "cga"), terms, atol=1e-11)
    summed = cga.Multivector(jnp.einsum("nk,nkc->nc", MESH.W, moved.values), moved.blades)
    np.testing.assert_allclose(
        deform.skin_cga(MESH.V, MESH.J, MESH.W, joints, normalize_points=False), cga.down(summed), atol=1e-11
    )


@pytest.mark.slow
def test_motor_blend_equals_dqs_for_rigid_poses():
    local = random_pose(3, B)
    model = random_model(3)  # rigid rest pose too
    dqs = deform.skin_pose(model, local, "dqs")
    np.testing.assert_allclose(deform.skin_pose(model, local, "cga_motor_blend"), dqs, atol=1e-12)
    # DQS from the kernel's own motor -> dual quaternion conversion agrees with the matrix route.
    joints = deform.joint_versors(model.mesh, deform.forward_kinematics(model.skeleton.parents, local))
    dq = cga.motor_to_dual_quaternion(cga.matrix_to_motor(cga.versor_to_matrix(joints)))
    np.testing.assert_allclose(deform.skin_dqs(model.mesh.V, model.mesh.J, model.mesh.W, dq), dqs, atol=1e-12)
    # and it differs from LBS: the methods are not all the same code path
    assert np.max(np.abs(np.asarray(dqs) - np.asarray(deform.skin_pose(model, local, "lbs")))) > 1e-3


def _numpy_dqs(V, J, W, dq):
    """Kavan et al.'s DQS per vertex, in numpy: align each influence's sign with the first's, blend,
    normalize by the real part's norm, rotate and translate."""

    def qmul(a, b):
        w1, v1, w2, v2 = a[0], a[1:], b[0], b[1:]
        return np.concatenate([[w1 * w2 - v1 @ v2], w1 * v2 + w2 * v1 + np.cross(v1, v2)])

    out = np.empty_like(V)
    for m in range(len(V)):
        q = dq[J[m]]
        signs = np.where(q[:, :4] @ q[0, :4] < 0, -1.0, 1.0)
        b = np.einsum("k,k,kc->c", W[m], signs, q)
        real, dual = b[:4] / np.linalg.norm(b[:4]), b[4:] / np.linalg.norm(b[:4])
        conj = real * np.array([1, -1, -1, -1])
        rotated = qmul(qmul(real, np.concatenate([[0.0], V[m]])), conj)[1:]
        out[m] = rotated + 2 * qmul(dual, conj)[1:]
    return out


@pytest.mark.slow
def test_dqs_and_motor_blend_against_numpy_dqs_with_flipped_signs():
    """Negating a joint's dual quaternion (or motor) is the same transformation: the blends align
    signs per vertex, so flipping any subset of joints changes nothing."""
    model = random_model(7)
    local = random_pose(7, model.skeleton.num_bones)
    joints = deform.joint_versors(model.mesh, deform.forward_kinematics(model.skeleton.parents, local))
    dq = np.asarray(cga.motor_to_dual_quaternion(cga.matrix_to_motor(cga.versor_to_matrix(joints))))
    flips = np.where(np.arange(len(dq)) % 2 == 1, -1.0, 1.0)[:, None]
    V, J, W = (np.asarray(x) for x in (model.mesh.V, model.mesh.J, model.mesh.W))
    expected = _numpy_dqs(V, J, W, dq)
    for sign in (np.ones_like(flips), flips, -flips):
        np.testing.assert_allclose(deform.skin_dqs(V, J, W, dq * sign), expected, atol=1e-12)
        flipped = cga.Multivector(joints.values * sign, joints.blades)
        np.testing.assert_allclose(deform.skin_cga_motor_blend(V, J, W, flipped), expected, atol=1e-12)
    # and under vmap over poses (the weights are computed for the whole batch in one pass)
    batch = jnp.stack([dq, dq * flips])
    np.testing.assert_allclose(
        jax.vmap(lambda d: deform.skin_dqs(V, J, W, d))(batch), np.stack([expected] * 2), atol=1e-12
    )


@pytest.mark.parametrize("method", deform.METHODS)
def test_same_rigid_motion_on_every_bone_gives_that_map(method):
    model = random_model(4)
    rigid = cga.motor(cga.rotor(jnp.array([0.3, -1.0, 0.5]), 2.1), jnp.array([0.4, -2.0, 1.5]))
    local = deform.local_versors(model.skeleton)
    roots = jnp.asarray([p < 0 for p in model.skeleton.parents])[:, None]
    moved = (rigid * local).embed(cga.KINDS["similitude"])
    local = cga.Multivector(jnp.where(roots, moved.values, local.values), local.blades)
    expected = cga.apply_to_points(rigid, model.mesh.V)
    np.testing.assert_allclose(deform.skin_pose(model, local, method), expected, atol=1e-12)


@pytest.mark.parametrize("method", ["cga", "cga_motor_blend"])
def test_same_similitude_on_every_bone_gives_that_map(method):
    model = random_model(5, rest_scale=(0.7, 1.4))
    sim = cga.similitude(cga.rotor(jnp.array([1.0, 0.2, 0.0]), 0.7), jnp.array([1.0, 2.0, -0.5]), 1.7)
    local = deform.local_versors(model.skeleton)
    roots = jnp.asarray([p < 0 for p in model.skeleton.parents])[:, None]
    moved = (sim * local).embed(cga.KINDS["similitude"])
    local = cga.Multivector(jnp.where(roots, moved.values, local.values), local.blades)
    np.testing.assert_allclose(
        deform.skin_pose(model, local, method), cga.apply_to_points(sim, model.mesh.V), atol=1e-12
    )


def test_dqs_rejects_scaled_joints():
    local = random_pose(6, B, scale_range=(1.5, 2.0))
    with pytest.raises(Exception, match="rigid"):
        jax.block_until_ready(deform.skin_pose(MODEL, local, "dqs"))


@pytest.mark.slow
def test_motor_blend_dilation_is_blended_in_log_space():
    """One vertex, two joints with pure dilations s1, s2 and weights w: scale s1^w1 s2^w2."""
    V = jnp.array([[1.0, 2.0, 3.0]])
    J = jnp.array([[0, 1]], jnp.int32)
    W = jnp.array([[0.25, 0.75]])
    joints = cga.dilator(jnp.array([2.0, 0.5])).embed(cga.KINDS["similitude"])
    out = deform.skin_cga_motor_blend(V, J, W, joints)
    np.testing.assert_allclose(out, V * 2.0**0.25 * 0.5**0.75, atol=1e-14)
    # eq. (17) down-projected after the sum blends the scales harmonically (each point weighted by 1 / scale)
    np.testing.assert_allclose(
        deform.skin_cga(V, J, W, joints, normalize_points=False), V / (0.25 / 2.0 + 0.75 / 0.5), atol=1e-14
    )
    # down-projected term by term (the default), linearly
    np.testing.assert_allclose(deform.skin_cga(V, J, W, joints), V * (0.25 * 2.0 + 0.75 * 0.5), atol=1e-14)


@pytest.mark.slow
@pytest.mark.parametrize("method", deform.METHODS)
def test_batched_poses_under_vmap_equal_one_by_one(method):
    params = jnp.stack([deform.random_parameters(jax.random.PRNGKey(k), MODEL, 0.5, 0.1, 0.0) for k in range(3)])
    local = deform.pose_from_parameters(MODEL, params)
    if method == "dqs":
        local = deform.pose_from_parameters(random_model(0), params)
    model = random_model(0) if method == "dqs" else MODEL
    # vmap, and leading batch axes without vmap, in one compiled call
    batched, broadcast = jax.jit(
        lambda L: (jax.vmap(lambda p: deform.skin_pose(model, p, method))(L), deform.skin_pose(model, L, method))
    )(local)
    for k in range(3):
        np.testing.assert_allclose(batched[k], deform.skin_pose(model, local[k], method), atol=1e-12)
    np.testing.assert_allclose(broadcast, batched, atol=1e-12)


@pytest.mark.parametrize("dense", [True, False])
def test_dilation_blend_paths_agree_under_vmap_and_grad(dense, monkeypatch):
    """Eq. (17)'s lambda row goes through a dense weight matrix for small skeletons and through the
    per-influence gather for large ones: both equal the literal weighted sum, batched and
    differentiated (weights included)."""
    from deform import _skinning  # the two internal blend paths and their switch have no public API

    if not dense:
        monkeypatch.setattr(_skinning, "DENSE_DILATION_BLEND_MAX_JOINTS", 0)
    rng = np.random.default_rng(4)
    J, W = np.asarray(MESH.J), np.asarray(MESH.W)
    dilations = jnp.asarray(rng.uniform(0.5, 2.0, size=(3, int(J.max()) + 1)))
    expected = np.einsum("nk,pnk->pn", W, np.asarray(dilations)[:, J])
    np.testing.assert_allclose(
        jax.vmap(lambda d: _skinning._blend_dilations(MESH.J, MESH.W, d))(dilations), expected, atol=1e-14
    )
    np.testing.assert_allclose(_skinning._blend_dilations(MESH.J, MESH.W, dilations), expected, atol=1e-14)
    weights = jnp.stack([MESH.W, MESH.W[:, ::-1]])  # a batch of meshes (weights) under vmap
    np.testing.assert_allclose(
        jax.vmap(lambda w: _skinning._blend_dilations(MESH.J, w, dilations[0]))(weights),
        np.einsum("bnk,nk->bn", np.asarray(weights), np.asarray(dilations)[0, J]),
        atol=1e-14,
    )
    grad_w = jax.grad(lambda w: jnp.sum(_skinning._blend_dilations(MESH.J, w, dilations) ** 2))(MESH.W)
    np.testing.assert_allclose(grad_w, np.einsum("pn,pnk->nk", 2 * expected, np.asarray(dilations)[:, J]), atol=1e-12)


@pytest.mark.slow
@pytest.mark.parametrize("method", deform.METHODS)
def test_gradients_match_finite_differences(method):
    model = random_model(7)
    p0 = deform.random_parameters(jax.random.PRNGKey(7), model, 0.5, 0.1, 0.0 if method == "dqs" else 0.1)
    target = jnp.asarray(np.random.default_rng(7).normal(size=(model.mesh.num_vertices, 3)))

    def loss(p):
        return jnp.sum((deform.skin_parameters(model, p, method) - target) ** 2)

    grad = jax.grad(loss)(p0)
    rng = np.random.default_rng(8)
    for _ in range(3):
        d = jnp.asarray(rng.normal(size=p0.shape))
        if method == "dqs":
            d = d.at[:, 6].set(0.0)
        h = 1e-6
        fd = (loss(p0 + h * d) - loss(p0 - h * d)) / (2 * h)
        np.testing.assert_allclose(jnp.sum(grad * d), fd, rtol=1e-6, atol=1e-7)


@pytest.mark.slow
def test_float32_skinning():
    model = jax.tree_util.tree_map(
        lambda x: x.astype(jnp.float32) if jnp.issubdtype(x.dtype, jnp.floating) else x, random_model(9)
    )
    local = deform.local_versors(model.skeleton)
    for method in deform.METHODS:
        out = deform.skin_pose(model, local, method)
        assert out.dtype == jnp.float32
        np.testing.assert_allclose(out, model.mesh.V, atol=1e-4)


def test_bad_input_is_named():
    V, J, W = MESH.V, MESH.J, MESH.W
    m = jnp.zeros((MESH.num_joints, 4, 4))
    with pytest.raises(ValueError, match="V: expected shape"):
        deform.skin_lbs(V[:, :2], J, W, m)
    with pytest.raises(ValueError, match="J: expected integer"):
        deform.skin_lbs(V, J.astype(float), W, m)
    with pytest.raises(ValueError, match="W: expected shape"):
        deform.skin_lbs(V, J, W[:, :2], m)
    with pytest.raises(ValueError, match="joint_matrices"):
        deform.skin_lbs(V, J, W, jnp.zeros((3, 3)))
    with pytest.raises(ValueError, match="joint_versors"):
        deform.skin_cga(V, J, W, jnp.zeros((3, 16)))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="joint_dual_quaternions"):
        deform.skin_dqs(V, J, W, jnp.zeros((3, 7)))
    with pytest.raises(ValueError, match="method"):
        deform.skin_pose(MODEL, deform.local_versors(MODEL.skeleton), "nope")


def test_a_joint_versor_that_is_no_similitude_raises_eagerly_and_under_jit():
    local = random_pose(3, B, scale_range=(0.5, 2.0))
    joints = deform.joint_versors(MESH, deform.forward_kinematics(MODEL.skeleton.parents, local))
    # its dilated rotor part (the eo^einf blades) outweighs its rotor part: no similitude R D has that
    eoinf = joints.blades.index(cga.KINDS["similitude"][10])
    bad = cga.Multivector(joints.values.at[1].set(0.0).at[1, eoinf].set(1.0), joints.blades)
    V, J, W = MESH.V, MESH.J, MESH.W
    with pytest.raises(ValueError, match="joint_versors: not similitude versors"):
        deform.skin_cga_motor_blend(V, J, W, bad)
    # a failed callback: a JaxRuntimeError, or a ValueError from an executable compiled by an earlier test
    with pytest.raises((RuntimeError, ValueError), match="joint_versors: not similitude versors"):
        jax.block_until_ready(jax.jit(deform.skin_cga_motor_blend)(V, J, W, bad))  # on a GPU: when it is ready
    assert_checks_placed_per_platform(deform.skin_cga_motor_blend, V, J, W, joints)


_RIGID_MODEL = random_model(12)
_SKIN = {
    method: jax.jit(lambda local, m=method: deform.skin_pose(_RIGID_MODEL, local, m))
    for method in ("lbs", "cga", "cga_motor_blend")
}


@pytest.mark.parametrize("d", [1e-4, *(pytest.param(d, marks=pytest.mark.slow) for d in (1e-2, 1.0, 1e2)), 1e4])
def test_skinning_with_large_and_small_dilations_stays_exact(d):
    """A root bone dilated by d scales every joint: eq. (17) equals LBS with the same matrices, and the
    motor blend equals DQS of the joints' rigid parts applied to d x (the dilation about the origin it
    factors out), to the precision the versors' components carry (~max(d, 1/d) ulps)."""
    model = _RIGID_MODEL
    b = model.skeleton.num_bones
    scales = jnp.where(jnp.arange(b) == 0, d, 1.0)
    rng = np.random.default_rng(12)
    q = rng.normal(size=(b, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    t = jnp.asarray(rng.normal(size=(b, 3)))
    local = cga.similitude(cga.quaternion_to_rotor(jnp.asarray(q)), t, scales)
    matrices = deform.trs_to_matrix(t, jnp.asarray(q[:, [1, 2, 3, 0]]), jnp.repeat(scales[:, None], 3, axis=1))
    lbs = np.asarray(_SKIN["lbs"](matrices))
    size = np.abs(lbs).max()
    tol = max(1e-13, 16 * np.finfo(np.float64).eps * max(d, 1 / d)) * size
    np.testing.assert_allclose(_SKIN["cga"](local), lbs, rtol=0, atol=tol)
    mesh = model.mesh
    joints = deform.joint_matrices(mesh, deform.forward_kinematics_matrices(model.skeleton.parents, matrices))
    rigid = joints.at[..., :3, :3].divide(d)
    dqs = deform.skin_dqs(mesh.V * d, mesh.J, mesh.W, deform.matrices_to_dual_quaternions(rigid))
    np.testing.assert_allclose(_SKIN["cga_motor_blend"](local), dqs, rtol=0, atol=tol)
