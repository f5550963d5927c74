"""The built-in default arm: a clean closed mesh, sound weights, a rig that reproduces the bind pose.

The rig is checked against plain numpy (own quaternion->matrix, parents chained, linear-blend skinning as in
the glTF specification), not against the library's skinning.
"""

import igl
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

from deform import default_arm


@pytest.fixture(scope="module")
def arm():
    return default_arm()


def _np(x):
    return np.asarray(x, dtype=np.float64)


def _quat_matrix(q):
    """(..., 3, 3) rotation matrices of (x, y, z, w) unit quaternions."""
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def _globals(translation, rotation, scale, parents):
    local = np.tile(np.eye(4), (len(parents), 1, 1))
    local[:, :3, :3] = _quat_matrix(rotation) * scale[:, None, :]
    local[:, :3, 3] = translation
    G = []
    for i, p in enumerate(parents):
        G.append(local[i] if p < 0 else G[p] @ local[i])
    return np.stack(G)


def _pose(model, t):
    """Local TRS of every bone at time t: rest values overridden by the LINEAR channels (nlerp for rotations)."""
    sk = model.skeleton
    trs = {"translation": _np(sk.translation).copy(), "rotation": _np(sk.rotation).copy(), "scale": _np(sk.scale)}
    for c in model.clip("wave").channels:
        times, values = _np(c.times), _np(c.values)
        value = np.array([np.interp(t, times, v) for v in values.T])
        if c.path == "rotation":
            value /= np.linalg.norm(value)
        trs[c.path][c.bone] = value
    return trs["translation"], trs["rotation"], trs["scale"]


def _skin(model, translation, rotation, scale):
    """Linear-blend skinning of the mesh, glTF specification: sum_k W_k * G[joint] @ inverse_bind @ [V, 1]."""
    mesh = model.mesh
    G = _globals(translation, rotation, scale, model.skeleton.parents)
    joint = G[list(mesh.joints)] @ _np(mesh.inverse_bind)
    M = np.einsum("nk,nkij->nij", _np(mesh.W), joint[np.asarray(mesh.J)])
    return np.einsum("nij,nj->ni", M[:, :3, :3], _np(mesh.V)) + M[:, :3, 3]


def _dense_weights(model):
    """(n, bones) weight of every bone on every vertex."""
    W, J = _np(model.mesh.W), np.asarray(model.mesh.J)
    dense = np.zeros((len(W), model.skeleton.num_bones))
    np.add.at(dense, (np.arange(len(W))[:, None], np.asarray(model.mesh.joints)[J]), W)
    return dense


def _heads(model):
    sk = model.skeleton
    return _globals(_np(sk.translation), _np(sk.rotation), _np(sk.scale), sk.parents)[:, :3, 3]


@pytest.mark.parametrize("kwargs", [{}, {"ring_vertices": 7, "rings_per_unit": 30.0}])
def test_mesh_is_closed_oriented_manifold(kwargs):
    mesh = default_arm(**kwargs).mesh
    V, F = _np(mesh.V), np.asarray(mesh.F)
    tm = trimesh.Trimesh(V, F, process=False)
    assert tm.is_watertight
    assert tm.is_winding_consistent
    assert tm.euler_number == 2
    assert tm.volume > 0  # outward normals
    assert tm.area_faces.min() > 1e-7
    assert len(np.unique(V, axis=0)) == len(V)  # no duplicate vertices hiding a seam
    # no self-intersection: just inside every face the winding number is 1, just outside 0
    centres, normals = tm.triangles_center, tm.face_normals
    for side, expected in ((-1e-4, 1.0), (1e-4, 0.0)):
        w = np.asarray(igl.winding_number(V, F.astype(np.int64), centres + side * normals))
        np.testing.assert_allclose(w, expected, atol=0.02)
    assert mesh.primitive_sizes == ((len(V), len(F)),)


def test_default_sizes_and_shape(arm):
    mesh, sk = arm.mesh, arm.skeleton
    assert 2000 <= mesh.num_vertices <= 5000
    assert mesh.F.dtype == jnp.int32 and mesh.J.dtype == jnp.int32
    assert mesh.V.dtype == jnp.float64 and mesh.W.dtype == jnp.float64
    assert sk.names[:4] == ("shoulder", "upper_arm", "forearm", "hand")
    assert sk.parents[0] == -1
    V = _np(mesh.V)
    # an arm along +x: about 0.85 m long, at most 0.1 m across, the shoulder joint inside the mesh
    extent = V.max(0) - V.min(0)
    assert 0.75 < extent[0] < 0.95 and extent[1] < 0.11
    tm = trimesh.Trimesh(V, np.asarray(mesh.F), process=False)
    inside = np.asarray(igl.winding_number(V, np.asarray(mesh.F, np.int64), _heads(arm)))
    np.testing.assert_allclose(inside, 1.0, atol=1e-6)  # every joint lies inside the skin
    assert 0.002 < tm.volume < 0.006  # litres of a human arm


def test_rig_is_not_identity(arm):
    sk = arm.skeleton
    rotation = _np(sk.rotation)
    assert np.abs(np.abs(rotation[:, 3]) - 1).max() > 1e-3
    assert np.abs(_np(sk.translation)).max() > 0.1
    heads = _heads(arm)
    # the elbow is bent: shoulder joint, elbow and wrist are not collinear
    e, w = heads[sk.index("forearm")], heads[sk.index("hand")]
    u = heads[sk.index("upper_arm")]
    cos = np.dot(e - u, w - e) / np.linalg.norm(e - u) / np.linalg.norm(w - e)
    assert cos < np.cos(np.radians(5))
    lengths = np.linalg.norm(np.diff(heads[1:], axis=0), axis=1)
    np.testing.assert_allclose(lengths, [0.30, 0.27], atol=0.01)


def test_weights(arm):
    mesh = arm.mesh
    W, J = _np(mesh.W), np.asarray(mesh.J)
    assert W.shape == J.shape and W.shape[1] == 4
    np.testing.assert_allclose(W.sum(1), 1.0, rtol=0, atol=1e-12)
    assert (W >= 0).all()
    assert ((W > 0).sum(1) <= 4).all()
    assert (J[W == 0] == 0).all()
    assert J.min() >= 0 and J.max() < mesh.num_joints
    assert sorted(mesh.joints) == list(mesh.joints) and len(set(mesh.joints)) == mesh.num_joints
    # every joint carries weight
    dense = _dense_weights(arm)
    assert (dense[:, list(mesh.joints)].max(0) > 0.99).all()
    # smooth: adjacent vertices have close weights
    edges = trimesh.Trimesh(_np(mesh.V), np.asarray(mesh.F), process=False).edges_unique
    assert np.abs(dense[edges[:, 0]] - dense[edges[:, 1]]).max() < 0.25


def test_each_bone_drives_the_vertices_near_it(arm):
    dense = _dense_weights(arm)
    sk, V = arm.skeleton, _np(arm.mesh.V)
    heads = _heads(arm)
    tip = V[np.argmax(np.linalg.norm(V, axis=1))]
    ends = np.concatenate([heads[1:], tip[None]])

    def distance(p, a, b):
        t = np.clip(((p - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
        return np.linalg.norm(p - a - t[:, None] * (b - a), axis=1)

    d = np.stack([distance(V, heads[i], ends[i]) for i in range(sk.num_bones)], 1)
    dominant = dense.argmax(1)
    assert (d[np.arange(len(V)), dominant] <= d.min(1) + 0.06).all()
    # beyond the wrist (by more than the blend window) the hand alone moves the skin
    wrist = heads[sk.index("hand")]
    axis = (tip - wrist) / np.linalg.norm(tip - wrist)
    beyond = (V - wrist) @ axis > 0.06
    assert beyond.sum() > 100
    np.testing.assert_allclose(dense[beyond, sk.index("hand")], 1.0, atol=1e-12)
    # so does the upper arm around its middle
    mid = np.abs((V - heads[1]) @ (heads[2] - heads[1]) / np.linalg.norm(heads[2] - heads[1]) - 0.15) < 0.05
    np.testing.assert_allclose(dense[mid, sk.index("upper_arm")], 1.0, atol=1e-12)


def test_inverse_bind_is_inverse_of_rest_globals(arm):
    sk = arm.skeleton
    G = _globals(_np(sk.translation), _np(sk.rotation), _np(sk.scale), sk.parents)
    eye = G[list(arm.mesh.joints)] @ _np(arm.mesh.inverse_bind)
    np.testing.assert_allclose(eye, np.broadcast_to(np.eye(4), eye.shape), atol=1e-12)


def test_rest_pose_reproduces_bind_positions(arm):
    sk = arm.skeleton
    V = _skin(arm, _np(sk.translation), _np(sk.rotation), _np(sk.scale))
    np.testing.assert_allclose(V, _np(arm.mesh.V), rtol=0, atol=1e-12)


def test_clip_bends_the_elbow_and_keeps_rigid_parts_rigid(arm):
    clip = arm.clip("wave")
    times = np.unique(np.concatenate([_np(c.times) for c in clip.channels]))
    assert 1.5 <= clip.end - clip.start <= 3.0
    rest = _skin(arm, *_pose(arm, times[0]))
    np.testing.assert_allclose(rest, _np(arm.mesh.V), atol=1e-12)  # the clip starts at rest
    V0 = _np(arm.mesh.V)
    tip = np.argmax(np.linalg.norm(V0, axis=1))
    hand = _dense_weights(arm)[:, arm.skeleton.index("hand")] == 1.0
    reach = []
    for t in times:
        V = _skin(arm, *_pose(arm, t))
        assert np.isfinite(V).all()
        reach.append(np.linalg.norm(V[tip]))
        # the hand, moved by one bone only, moves rigidly: its edge lengths to a few of its vertices keep
        idx = np.flatnonzero(hand)[:: max(1, hand.sum() // 50)]
        d0 = np.linalg.norm(V0[idx, None] - V0[None, idx], axis=-1)
        np.testing.assert_allclose(np.linalg.norm(V[idx, None] - V[None, idx], axis=-1), d0, atol=1e-12)
    reach = np.array(reach)
    assert reach[0] > 0.7
    assert reach[0] - reach.min() > 0.2  # the elbow flexes: the fingertip comes much closer to the shoulder
    np.testing.assert_allclose(reach[-1], reach[0], atol=1e-9)  # and the clip ends where it started


def test_channels(arm):
    sk = arm.skeleton
    clip = arm.clip("wave")
    assert clip.name == "wave" and len(clip.channels) >= 3
    paths = {sk.names[c.bone]: set() for c in clip.channels}
    for c in clip.channels:
        assert 0 <= c.bone < sk.num_bones
        assert c.interpolation == "LINEAR"
        assert c.path in ("translation", "rotation")  # rigid only: dual-quaternion skinning has no scale
        paths[sk.names[c.bone]].add(c.path)
        times, values = _np(c.times), _np(c.values)
        assert len(times) >= 5 and (np.diff(times) > 0).all()
        assert np.isfinite(values).all()
        if c.path == "rotation":
            np.testing.assert_allclose(np.linalg.norm(values, axis=1), 1.0, atol=1e-12)
            assert (np.sum(values[1:] * values[:-1], axis=1) > 0).all()
    assert "rotation" in paths["forearm"]


def test_deterministic(arm):
    again = default_arm()
    for a, b in zip(
        [arm.mesh.V, arm.mesh.F, arm.mesh.J, arm.mesh.W, arm.mesh.inverse_bind, arm.skeleton.rotation],
        [again.mesh.V, again.mesh.F, again.mesh.J, again.mesh.W, again.mesh.inverse_bind, again.skeleton.rotation],
    ):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for c, d in zip(arm.clips[0].channels, again.clips[0].channels):
        np.testing.assert_array_equal(np.asarray(c.values), np.asarray(d.values))


def test_float32(arm):
    arm32 = default_arm(dtype=jnp.float32)
    for x in (
        arm32.mesh.V,
        arm32.mesh.W,
        arm32.mesh.inverse_bind,
        arm32.skeleton.translation,
        arm32.skeleton.rotation,
        arm32.skeleton.scale,
        *(c.values for c in arm32.clips[0].channels),
        *(c.times for c in arm32.clips[0].channels),
    ):
        assert x.dtype == jnp.float32
    assert arm32.mesh.F.dtype == jnp.int32 and arm32.mesh.J.dtype == jnp.int32
    np.testing.assert_allclose(_np(arm32.mesh.V), _np(arm.mesh.V), atol=1e-6)
    sk = arm32.skeleton
    V = _skin(arm32, _np(sk.translation), _np(sk.rotation), _np(sk.scale))
    np.testing.assert_allclose(V, _np(arm.mesh.V), atol=1e-5)


@pytest.mark.parametrize(
    "kwargs",
    [
        {"ring_vertices": 2},
        {"ring_vertices": 3.5},
        {"rings_per_unit": 0.0},
        {"rings_per_unit": np.nan},
        {"dtype": jnp.int32},
    ],
)
def test_bad_arguments(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        default_arm(**kwargs)
