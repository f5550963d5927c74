"""glTF 2.0 / FBX / COLLADA reading and writing (deform._gltf), checked against trimesh, pygltflib and
hand-built files."""

import base64
import json
import shutil
import struct
import subprocess
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pygltflib
import pytest
import trimesh

from deform import SkinnedMesh, load_model, rest_pose, save_model, skin_model, weld
from tests.deform._gltf_reference import Reference
from tests.shared import given, load_character, read_gltf

DATA = Path(__file__).resolve().parents[1] / "data"
MODELS = ["Arm5", "3Cylinder4bones", "PlaneWith3Bones", "RiggedSimple", "CesiumMan"]
# (vertices, faces, joints, bones = joints + non-joint ancestors, clips)
COUNTS = {
    "Arm5": (2935, 5037, 23, 25, 0),
    "3Cylinder4bones": (509, 758, 4, 12, 0),
    "PlaneWith3Bones": (25, 32, 3, 10, 0),
    "RiggedSimple": (160, 188, 2, 4, 1),
    "CesiumMan": (3273, 4672, 19, 20, 1),
}
needs_assimp = pytest.mark.skipif(
    shutil.which("assimp") is None, reason="the assimp CLI is not installed (Debian package assimp-utils)"
)


def _quat_matrix(q):
    """Rotation matrix of a unit quaternion (x, y, z, w), written out (independent of scipy)."""
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _trs_matrix(t, q, s):
    m = np.eye(4)
    m[:3, :3] = _quat_matrix(q) * np.asarray(s)
    m[:3, 3] = t
    return m


def _assert_same(a, b):
    """Exactly equal pytrees: static fields (names, parents, joints, sizes, interpolations) and arrays."""
    leaves_a, tree_a = jax.tree_util.tree_flatten(a)
    leaves_b, tree_b = jax.tree_util.tree_flatten(b)
    assert tree_a == tree_b
    for x, y in zip(leaves_a, leaves_b):
        assert x.dtype == y.dtype and x.shape == y.shape
        np.testing.assert_array_equal(x, y)


def _trimesh_counts(path):
    scene = trimesh.load(path, process=False)
    assert isinstance(scene, trimesh.Scene)
    return sum(len(g.vertices) for g in scene.geometry.values()), sum(len(g.faces) for g in scene.geometry.values())


# ------------------------------------------------------------------------------------------ real files


@pytest.mark.parametrize("name", MODELS)
def test_counts_against_trimesh_and_pygltflib(name):
    path = DATA / f"{name}.glb"
    model = load_model(path)
    mesh, skeleton = model.mesh, model.skeleton
    n, m, j, _, _ = COUNTS[name]
    assert (mesh.num_vertices, mesh.F.shape[0], mesh.num_joints, skeleton.num_bones, len(model.clips)) == COUNTS[name]
    assert _trimesh_counts(path) == (n, m)
    assert mesh.primitive_sizes == ((n, m),)
    assert mesh.V.dtype == jnp.float64 and mesh.W.dtype == jnp.float64 and mesh.inverse_bind.dtype == jnp.float64
    assert mesh.F.dtype == jnp.int32 and mesh.J.dtype == jnp.int32
    assert model.name == name

    reference = Reference(path)
    gltf = reference.gltf
    (skin,) = gltf.skins
    assert [skeleton.names[i] for i in mesh.joints] == [gltf.nodes[i].name for i in given(skin.joints)]
    ibm = reference.accessor(skin.inverseBindMatrices)
    np.testing.assert_array_equal(mesh.inverse_bind, ibm.reshape(j, 4, 4).transpose(0, 2, 1))
    np.testing.assert_allclose(np.asarray(mesh.W).sum(axis=1), 1.0, atol=1e-2)
    for clip, anim in zip(model.clips, gltf.animations):
        assert len(clip.channels) == len(anim.channels)  # every channel of these files animates a bone
        for channel, raw in zip(clip.channels, anim.channels):
            assert skeleton.names[channel.bone] == gltf.nodes[given(raw.target.node)].name
            assert channel.path == raw.target.path
            times = gltf.accessors[anim.samplers[raw.sampler].input]
            assert channel.times.shape == (times.count,)
            assert float(channel.times[0]) == given(times.min)[0] and float(channel.times[-1]) == given(times.max)[0]


def test_skeleton_order_and_non_joint_ancestors():
    # RiggedSimple: joints Bone, Bone.001 under two non-joint ancestors carrying matrices (Z_UP, Armature).
    model = load_model(DATA / "RiggedSimple.glb")
    assert model.skeleton.names == ("Z_UP", "Armature", "Bone", "Bone.001")
    assert model.skeleton.parents == (-1, 0, 1, 2)
    assert model.clips[0].name == "clip0"  # unnamed in the file
    assert {c.path for c in model.clips[0].channels} == {"translation", "rotation", "scale"}
    # Arm5: the mesh's pivot nodes are not ancestors of a joint, so they are not bones.
    arm = load_model(DATA / "Arm5.glb")
    assert arm.skeleton.names[:2] == ("RootNode", "Character1_RightShoulder")
    assert not any("Pivot" in name for name in arm.skeleton.names)


@pytest.mark.parametrize("name", ["Arm5", "3Cylinder4bones", "PlaneWith3Bones", "RiggedSimple"])
def test_matrix_nodes_decompose_into_trs(name):
    model = load_model(DATA / f"{name}.glb")
    gltf = read_gltf(DATA / f"{name}.glb")
    by_name = {node.name: node for node in gltf.nodes}
    skeleton, checked = model.skeleton, 0
    for b, bone in enumerate(skeleton.names):
        node = by_name[bone]
        if node.matrix is None:
            continue
        q = np.asarray(skeleton.rotation[b])
        assert abs(np.linalg.norm(q) - 1.0) < 1e-12
        recomposed = _trs_matrix(skeleton.translation[b], q, skeleton.scale[b])
        np.testing.assert_allclose(recomposed, np.asarray(node.matrix).reshape(4, 4).T, atol=1e-6)
        checked += 1
    assert checked > 0


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("suffix", [".glb", ".gltf"])
def test_round_trip_is_exact(tmp_path, name, suffix):
    first = load_model(DATA / f"{name}.glb")
    out = tmp_path / f"{name}{suffix}"
    save_model(first, out)
    if suffix == ".gltf":
        assert (tmp_path / f"{name}.bin").is_file()
    _assert_same(load_model(out), first)
    assert _trimesh_counts(out) == COUNTS[name][:2]
    gltf = read_gltf(out)
    assert gltf.asset.version == "2.0" and gltf.asset.generator == "jaxcga"
    assert all((view.byteOffset or 0) % 4 == 0 for view in gltf.bufferViews)
    assert sum(view.byteLength for view in gltf.bufferViews) <= gltf.buffers[0].byteLength
    primitive = gltf.meshes[0].primitives[0]
    position = gltf.accessors[given(primitive.attributes.POSITION)]
    np.testing.assert_array_equal(position.min, np.asarray(first.mesh.V).min(axis=0))
    assert gltf.bufferViews[given(position.bufferView)].target == pygltflib.ARRAY_BUFFER
    indices = gltf.accessors[given(primitive.indices)]
    assert gltf.bufferViews[given(indices.bufferView)].target == pygltflib.ELEMENT_ARRAY_BUFFER


# ------------------------------------------------------------------------------------------ FBX via assimp


@needs_assimp
def test_fbx_matches_glb():
    fbx, glb = load_model(DATA / "Arm5.fbx"), load_model(DATA / "Arm5.glb")
    assert fbx.skeleton.names == glb.skeleton.names and fbx.skeleton.parents == glb.skeleton.parents
    assert fbx.mesh.num_vertices == glb.mesh.num_vertices == 2935
    np.testing.assert_array_equal(fbx.mesh.V, glb.mesh.V)
    assert (
        load_model(DATA / "3Cylinder4bones.fbx").skeleton.names
        == load_model(DATA / "3Cylinder4bones.glb").skeleton.names
    )


def _quaternion_sign(a, b):
    """``a`` with each row's sign flipped where b's row is nearer -a (q and -q are one rotation); rows of 4
    are quaternions, other widths are returned as they are."""
    a, b = np.asarray(a), np.asarray(b)
    return a * np.where(np.sum(a * b, axis=-1, keepdims=True) < 0, -1.0, 1.0) if a.shape[-1] == 4 else a


@needs_assimp
def test_collada_matches_the_gltf_it_was_made_from(tmp_path):
    # RiggedSimple: an animated two-joint rig (assimp 5.2 cannot write CesiumMan's or Arm5's embedded textures)
    dae = tmp_path / "RiggedSimple.dae"
    done = subprocess.run(
        ["assimp", "export", str(DATA / "RiggedSimple.glb"), str(dae), "-f", "collada"],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0 and dae.is_file(), done.stdout + done.stderr
    collada, glb = load_model(dae), load_model(DATA / "RiggedSimple.glb")
    assert collada.skeleton.names == glb.skeleton.names and collada.skeleton.parents == glb.skeleton.parents
    np.testing.assert_array_equal(collada.mesh.V, glb.mesh.V)
    np.testing.assert_array_equal(collada.mesh.F, glb.mesh.F)
    np.testing.assert_allclose(collada.mesh.inverse_bind, glb.mesh.inverse_bind, atol=1e-6)
    for name in ("translation", "rotation", "scale"):
        np.testing.assert_allclose(
            _quaternion_sign(getattr(collada.skeleton, name), getattr(glb.skeleton, name)),
            getattr(glb.skeleton, name),
            atol=1e-6,
        )
    # assimp reads glTF key times as milliseconds (1000 ticks per second) and its COLLADA exporter writes the
    # ticks as seconds: the .dae's clip runs 1000 times slower, keys and values otherwise the same
    (a,), (b,) = collada.clips, glb.clips
    ratio = a.end / b.end
    assert ratio == pytest.approx(1000.0, rel=1e-6)
    assert len(a.channels) == len(b.channels)
    for ca, cb in zip(a.channels, b.channels):
        assert (ca.bone, ca.path, ca.interpolation) == (cb.bone, cb.path, cb.interpolation)
        np.testing.assert_allclose(ca.times, ratio * np.asarray(cb.times), rtol=1e-6)
        np.testing.assert_allclose(_quaternion_sign(ca.values, cb.values), cb.values, atol=1e-6)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(rest_pose(glb, "lbs")), axis=0)))
    for t in (0.0, 0.7, 1.3, 2.05):  # rest, between keys, and near the clip's end
        np.testing.assert_allclose(
            skin_model(collada, jnp.asarray(ratio * t), "lbs"),
            skin_model(glb, jnp.asarray(t), "lbs"),
            atol=1e-6 * diagonal,
        )


@needs_assimp
def test_assimp_failure_reports_its_output(tmp_path):
    bad = tmp_path / "bad.fbx"
    bad.write_text("not an fbx file")
    with pytest.raises(ValueError, match="assimp could not convert(.|\n)*Failed to load"):
        load_model(bad)


def test_missing_assimp_names_the_package(tmp_path, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path))
    with pytest.raises(RuntimeError, match="assimp-utils"):
        load_model(DATA / "Arm5.fbx")


# ------------------------------------------------------------------------------------------ synthetic file

_DTYPE = {5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
ROOT_T, ROOT_Q, ROOT_S = (1.0, 2.0, 3.0), (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5)), (1.0, 2.0, 3.0)
IBM0 = [np.eye(4), np.eye(4)]  # translations, so that neither is the identity
IBM0[0][:3, 3] = (0.5, -1.0, 2.0)
IBM0[1][:3, 3] = (0.0, 0.0, -4.0)
W8 = np.array([51, 0, 0, 0, 204, 0, 0, 0])  # normalized UNSIGNED_BYTE, 8 influences
CUBIC = np.array([[0, 0, 0, 32767], [0, 0, 16384, 28378], [0, 0, -32767, 0]] * 2)  # normalized SHORT


class _Builder:
    """A glTF written by hand: buffer 0 is an external .bin, buffer 1 a base64 data: URI."""

    def __init__(self):
        self.bins = [bytearray(), bytearray()]
        self.doc = {"asset": {"version": "2.0"}, "bufferViews": [], "accessors": []}

    def view(self, raw: bytes, buffer=0, stride=None):
        data = self.bins[buffer]
        data.extend(b"\0" * (-len(data) % 4))
        self.doc["bufferViews"].append({"buffer": buffer, "byteOffset": len(data), "byteLength": len(raw)})
        if stride:
            self.doc["bufferViews"][-1]["byteStride"] = stride
        data.extend(raw)
        return len(self.doc["bufferViews"]) - 1

    def accessor(self, values, ctype, kind, buffer=0, **extra):
        values = np.asarray(values, _DTYPE[ctype])
        acc = {
            "bufferView": self.view(values.tobytes(), buffer),
            "componentType": ctype,
            "count": len(values),
            "type": kind,
        }
        self.doc["accessors"].append({**acc, **extra})
        return len(self.doc["accessors"]) - 1

    def write(self, path):
        self.doc["buffers"] = [
            {"uri": "syn data.bin", "byteLength": len(self.bins[0])},
            {
                "uri": "data:application/octet-stream;base64," + base64.b64encode(self.bins[1]).decode(),
                "byteLength": len(self.bins[1]),
            },
        ]
        (path.parent / "syn data.bin").write_bytes(bytes(self.bins[0]))
        path.write_text(json.dumps(self.doc))
        return path


def _synthetic(tmp_path, *, shared=False, mode=None, weight=204, root_matrix=None, skins=True):
    """Three bones (matrix root, 'a', 'a'), two skinned meshes / three mesh nodes, two clips."""
    g = _Builder()
    root = _trs_matrix(ROOT_T, ROOT_Q, ROOT_S) if root_matrix is None else root_matrix
    g.doc["nodes"] = [
        {"matrix": root.T.reshape(-1).tolist(), "children": [1, 3]},
        {"name": "a", "translation": [0.0, 1.0, 0.0], "children": [2]},
        {"name": "a", "rotation": [0.0, 0.0, 0.0, 1.0]},
        {"name": "meshA", "mesh": 0, "skin": 0, "translation": [9.0, 9.0, 9.0]},
        {"name": "meshB", "mesh": 1, "skin": 0 if shared else 1},
        {"name": "meshC", "mesh": 1, "skin": 0},
        {"name": "other"},
    ]
    g.doc["scene"], g.doc["scenes"] = 0, [{"nodes": [0, 4, 5, 6]}]
    ibm = g.accessor(np.stack(IBM0).transpose(0, 2, 1).reshape(2, 16), 5126, "MAT4")
    g.doc["skins"] = [{"joints": [1, 2], "inverseBindMatrices": ibm}, {"joints": [2, 0]}]
    # mesh 0, primitive 0: no indices, 8 influences as normalized UNSIGNED_BYTE
    p0 = {
        "POSITION": g.accessor([[0, 0, 0], [1, 0, 0], [0, 1, 0]], 5126, "VEC3", min=[0, 0, 0], max=[1, 1, 0]),
        "JOINTS_0": g.accessor([[0, 0, 0, 0]] * 3, 5121, "VEC4"),
        "WEIGHTS_0": g.accessor([W8[:4]] * 3, 5121, "VEC4", normalized=True),
        "JOINTS_1": g.accessor([[1, 0, 0, 0]] * 3, 5121, "VEC4", buffer=1),
        "WEIGHTS_1": g.accessor([[weight, 0, 0, 0]] * 3, 5121, "VEC4", buffer=1, normalized=True),
    }
    # mesh 0, primitive 1: POSITION interleaved with NORMAL (byteStride 24), UNSIGNED_SHORT indices, float weights
    quad = np.array([[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], "<f4")
    view = g.view(np.hstack([quad, np.zeros_like(quad)]).tobytes(), stride=24)
    g.doc["accessors"].append(
        {"bufferView": view, "componentType": 5126, "count": 4, "type": "VEC3", "min": [0, 0, 1], "max": [1, 1, 1]}
    )
    g.doc["accessors"].append({"bufferView": view, "byteOffset": 12, "componentType": 5126, "count": 4, "type": "VEC3"})
    p1 = {
        "POSITION": len(g.doc["accessors"]) - 2,
        "NORMAL": len(g.doc["accessors"]) - 1,
        "JOINTS_0": g.accessor([[1, 0, 0, 0]] * 4, 5123, "VEC4"),
        "WEIGHTS_0": g.accessor([[0.25, 0.75, 0, 0]] * 4, 5126, "VEC4"),
    }
    # mesh 1: sparse POSITION (zeros + two replaced vertices), UNSIGNED_INT indices, UNSIGNED_SHORT weights
    sparse = {
        "count": 2,
        "indices": {"bufferView": g.view(np.array([1, 2], "<u2").tobytes()), "componentType": 5123},
        "values": {"bufferView": g.view(np.array([[2, 0, 0], [0, 2, 0]], "<f4").tobytes())},
    }
    g.doc["accessors"].append(
        {"componentType": 5126, "count": 3, "type": "VEC3", "min": [0, 0, 0], "max": [2, 2, 0], "sparse": sparse}
    )
    p2 = {
        "POSITION": len(g.doc["accessors"]) - 1,
        "JOINTS_0": g.accessor([[0, 1, 0, 0]] * 3, 5123, "VEC4"),
        "WEIGHTS_0": g.accessor(
            [[65535, 0, 0, 0], [32768, 32767, 0, 0], [0, 65535, 0, 0]], 5123, "VEC4", normalized=True
        ),
    }
    prim2 = {"attributes": p2, "indices": g.accessor([2, 1, 0], 5125, "SCALAR")}
    if mode is not None:
        prim2["mode"] = mode
    g.doc["meshes"] = [
        {
            "name": "m0",
            "primitives": [
                {"attributes": p0},
                {"attributes": p1, "indices": g.accessor([0, 1, 2, 0, 2, 3], 5123, "SCALAR")},
            ],
        },
        {"name": "m1", "primitives": [prim2]},
    ]
    if not skins:
        for node in g.doc["nodes"]:
            node.pop("skin", None)
    times = g.accessor([0.0, 1.0, 2.0], 5126, "SCALAR", min=[0.0], max=[2.0])
    cubic_times = g.accessor([0.0, 1.5], 5126, "SCALAR", min=[0.0], max=[1.5])
    g.doc["animations"] = [
        {
            "name": "walk",
            "samplers": [
                {
                    "input": times,
                    "output": g.accessor([[0, 0, 0], [0, 1, 0], [0, 2, 0]], 5126, "VEC3"),
                    "interpolation": "STEP",
                },
                {
                    "input": cubic_times,
                    "output": g.accessor(CUBIC, 5122, "VEC4", normalized=True),
                    "interpolation": "CUBICSPLINE",
                },
                {"input": times, "output": g.accessor([0.0, 1.0, 0.5], 5126, "SCALAR")},
            ],
            "channels": [
                {"sampler": 0, "target": {"node": 1, "path": "translation"}},
                {"sampler": 1, "target": {"node": 2, "path": "rotation"}},
                {"sampler": 0, "target": {"node": 6, "path": "translation"}},  # not a bone: dropped
                {"sampler": 0, "target": {"node": 3, "path": "translation"}},  # the mesh node: dropped
                {"sampler": 2, "target": {"node": 2, "path": "weights"}},  # morph weights: dropped
            ],
        },
        {
            "samplers": [{"input": times, "output": g.accessor([[1, 1, 1], [2, 2, 2], [1, 1, 1]], 5126, "VEC3")}],
            "channels": [{"sampler": 0, "target": {"node": 1, "path": "scale"}}],
        },
    ]
    return g.write(tmp_path / "syn.gltf")


def test_synthetic_file(tmp_path):
    model = load_model(_synthetic(tmp_path))
    skeleton, mesh = model.skeleton, model.mesh
    assert skeleton.names == ("node0", "a", "a.001") and skeleton.parents == (-1, 0, 1)
    assert np.allclose(skeleton.translation[0], ROOT_T, atol=1e-12) and np.allclose(
        skeleton.scale[0], ROOT_S, atol=1e-12
    )
    assert abs(abs(np.dot(np.asarray(skeleton.rotation[0]), ROOT_Q)) - 1) < 1e-12
    np.testing.assert_array_equal(skeleton.translation[1], [0, 1, 0])

    # skins 0 and 1 both hold node 2, with different inverse binds: two joints for bone 2
    assert mesh.joints == (1, 2, 2, 0)
    np.testing.assert_array_equal(mesh.inverse_bind, np.stack([IBM0[0], IBM0[1], np.eye(4), np.eye(4)]))
    assert mesh.primitive_sizes == ((3, 1), (4, 2), (3, 1), (3, 1))
    np.testing.assert_array_equal(mesh.F, [[0, 1, 2], [3, 4, 5], [3, 5, 6], [9, 8, 7], [12, 11, 10]])
    np.testing.assert_array_equal(mesh.V[3:7], [[0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]])
    np.testing.assert_array_equal(mesh.V[7:10], [[0, 0, 0], [2, 0, 0], [0, 2, 0]])
    assert mesh.J.shape == (13, 8)
    np.testing.assert_array_equal(mesh.W[0], W8 / 255.0)
    np.testing.assert_array_equal(mesh.W[3], [0.25, 0.75, 0, 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(mesh.W[8, :2], [32768 / 65535, 32767 / 65535])
    np.testing.assert_array_equal(mesh.J[0], [0, 0, 0, 0, 1, 0, 0, 0])
    np.testing.assert_array_equal(mesh.J[7, :2], [2, 3])  # meshB, skin 1: nodes 2, 0 -> joints 2, 3
    np.testing.assert_array_equal(mesh.J[10, :2], [0, 1])  # meshC, skin 0

    walk, other = model.clips
    assert (walk.name, other.name) == ("walk", "clip1")
    step, cubic = walk.channels
    assert (step.bone, step.path, step.interpolation) == (1, "translation", "STEP")
    np.testing.assert_array_equal(step.values, [[0, 0, 0], [0, 1, 0], [0, 2, 0]])
    assert (cubic.bone, cubic.path, cubic.interpolation) == (2, "rotation", "CUBICSPLINE")
    assert cubic.values.shape == (2, 3, 4)
    np.testing.assert_array_equal(cubic.values, np.maximum(CUBIC / 32767.0, -1.0).reshape(2, 3, 4))
    np.testing.assert_array_equal(cubic.times, [0.0, 1.5])
    assert (other.channels[0].bone, other.channels[0].interpolation) == (1, "LINEAR")

    with pytest.raises(ValueError, match="appear as several joints"):
        save_model(model, tmp_path / "out.glb")


def test_synthetic_round_trip(tmp_path):
    first = load_model(_synthetic(tmp_path, shared=True))
    assert first.mesh.joints == (1, 2)
    save_model(first, tmp_path / "a.glb")
    second = load_model(tmp_path / "a.glb")
    # normalized integers were dequantized to float64 and written as float32: rounded once ...
    for x, y in zip(jax.tree_util.tree_leaves(first), jax.tree_util.tree_leaves(second)):
        np.testing.assert_allclose(x, y, rtol=1e-7, atol=1e-7)
    assert second.mesh.primitive_sizes == first.mesh.primitive_sizes and second.mesh.J.shape == (13, 8)
    assert [c.interpolation for c in second.clips[0].channels] == ["STEP", "CUBICSPLINE"]
    # ... and then exact
    save_model(second, tmp_path / "a.gltf")  # same stem, same model name
    _assert_same(load_model(tmp_path / "a.gltf"), second)


def _rigid_scene(tmp_path):
    """A skin of two joints (hips, arm; no inverse bind matrices: the bind pose is not the rest pose), a prop mesh
    without a skin under an animated node ('holder') under the arm, with a non-uniform scale of its own, and a static
    mesh outside the skeleton; written as a GLB so that the reference reads it too."""
    g = _Builder()
    half = (0.0, 0.0, np.sqrt(0.5), np.sqrt(0.5))  # 90 degrees about z
    g.doc["scene"], g.doc["scenes"] = 0, [{"nodes": [0, 5]}]
    g.doc["nodes"] = [
        {"name": "hips", "translation": [0.0, 1.0, 0.0], "children": [1, 4]},
        {"name": "arm", "translation": [1.0, 0.0, 0.0], "rotation": list(half), "scale": [2, 2, 2], "children": [2]},
        {"name": "holder", "translation": [0.0, 0.5, 0.0], "scale": [0.5, 0.5, 0.5], "children": [3]},
        {"name": "prop", "mesh": 1, "translation": [0.25, 0.0, 0.0], "scale": [1.0, 2.0, 3.0]},
        {"name": "body", "mesh": 0, "skin": 0},
        {"name": "scenery", "mesh": 1, "translation": [5.0, 0.0, 0.0]},
    ]
    g.doc["skins"] = [{"joints": [0, 1]}]
    triangle = [[0, 0, 0], [1, 0, 0], [0, 1, 0]]
    skinned = {
        "POSITION": g.accessor(triangle, 5126, "VEC3", min=[0, 0, 0], max=[1, 1, 0]),
        "JOINTS_0": g.accessor([[0, 1, 0, 0]] * 3, 5121, "VEC4"),
        "WEIGHTS_0": g.accessor([[1, 0, 0, 0], [0.5, 0.5, 0, 0], [0, 1, 0, 0]], 5126, "VEC4"),
    }
    prop = {
        "POSITION": g.accessor([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], 5126, "VEC3", min=[0] * 3, max=[1] * 3)
    }
    g.doc["meshes"] = [
        {"primitives": [{"attributes": skinned}]},
        {"primitives": [{"attributes": prop, "indices": g.accessor([0, 1, 2, 0, 2, 3], 5123, "SCALAR")}]},
    ]
    times = g.accessor([0.0, 1.0], 5126, "SCALAR", min=[0.0], max=[1.0])
    g.doc["animations"] = [
        {
            "samplers": [
                {"input": times, "output": g.accessor([half, [0.0, 0.0, 0.0, 1.0]], 5126, "VEC4")},
                {"input": times, "output": g.accessor([[0.0, 0.5, 0.0], [0.0, 1.5, 0.25]], 5126, "VEC3")},
            ],
            "channels": [
                {"sampler": 0, "target": {"node": 1, "path": "rotation"}},
                {"sampler": 1, "target": {"node": 2, "path": "translation"}},
            ],
        }
    ]
    blob = bytes(g.bins[0]) + b"\0" * (-len(g.bins[0]) % 4)
    g.doc["buffers"] = [{"byteLength": len(blob)}]
    chunk = json.dumps(g.doc).encode()
    chunk += b" " * (-len(chunk) % 4)
    body = struct.pack("<I4s", len(chunk), b"JSON") + chunk + struct.pack("<I4s", len(blob), b"BIN\0") + blob
    path = tmp_path / "rigid.glb"
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    return path


def test_rigid_attachments_follow_their_node(tmp_path):
    """The prop (a mesh node without a skin, below a joint) is a part with weight 1 on the nearest bone, its
    animated parent 'holder'; the scenery outside the skeleton is left out. At rest and under the clip, LBS and
    eq. (17) put the prop where the specification's world transform does (the independent reference: global(node)
    @ p) and the skinned triangle where LBS does; a save -> load round trip keeps all of it."""
    path = _rigid_scene(tmp_path)
    model = load_model(path)
    mesh, skeleton = model.mesh, model.skeleton
    assert skeleton.names == ("hips", "arm", "holder")  # the prop's own node is baked, not a bone
    assert mesh.primitive_sizes == ((4, 2), (3, 1))  # node order: the prop, then the body; no scenery
    np.testing.assert_array_equal(mesh.J[:4, 0], [mesh.J[0, 0]] * 4)
    assert mesh.joints[int(mesh.J[0, 0])] == 2
    np.testing.assert_array_equal(mesh.W[:4], [[1, 0, 0, 0]] * 4)
    reference = Reference(path)
    # the bind pose is the identity (no inverse bind matrices), so V is the prop's place relative to its bone
    np.testing.assert_allclose(rest_pose(model, "lbs"), reference.skin(), atol=1e-12)
    np.testing.assert_allclose(rest_pose(model, "cga"), reference.skin(), atol=1e-12)
    for t in (0.0, 0.3, 1.0):
        expected = reference.skin(0, t)
        assert t == 0 or np.abs(expected[:4] - reference.skin()[:4]).max() > 0.1  # the prop does move
        np.testing.assert_allclose(skin_model(model, t, "lbs"), expected, atol=1e-12)
        np.testing.assert_allclose(skin_model(model, t, "cga"), expected, atol=1e-12)
    save_model(model, tmp_path / "again.glb")
    again = load_model(tmp_path / "again.glb")
    assert again.mesh.primitive_sizes == mesh.primitive_sizes
    for t in (0.0, 0.3, 1.0):
        np.testing.assert_allclose(skin_model(again, t, "lbs"), reference.skin(0, t), atol=1e-6)


def test_rigid_attachments_survive_a_round_trip_on_the_robot(tmp_path):
    """RobotExpressive (15 rigid meshes, skinned hands) -> save -> load: the same primitives, joints and bones, the
    positions rounded once to float32 (they were placed in float64), skinning unchanged, and exact from then on."""
    first = load_character("RobotExpressive", weld=False)
    save_model(first, tmp_path / "robot.glb")
    second = load_model(tmp_path / "robot.glb")
    assert second.mesh.primitive_sizes == first.mesh.primitive_sizes and len(first.mesh.primitive_sizes) == 19
    assert second.mesh.joints == first.mesh.joints and second.skeleton.names == first.skeleton.names
    np.testing.assert_array_equal(second.mesh.F, first.mesh.F)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(first.mesh.V), axis=0)))
    np.testing.assert_allclose(second.mesh.V, first.mesh.V, rtol=0, atol=1e-7 * diagonal)
    for t in (0.0, 1.2):
        np.testing.assert_allclose(skin_model(second, t, "lbs"), skin_model(first, t, "lbs"), atol=1e-6 * diagonal)
    (tmp_path / "again").mkdir()
    save_model(second, tmp_path / "again" / "robot.gltf")  # same stem, same model name
    _assert_same(load_model(tmp_path / "again" / "robot.gltf"), second)


def test_rigid_meshes_without_a_skin_are_not_a_rigged_model(tmp_path):
    """Meshes under a node hierarchy with no skin anywhere are static scenery: still "no skinned mesh"."""
    path = _rigid_scene(tmp_path)
    gltf = read_gltf(path)
    gltf.nodes[4].skin = None
    gltf.skins = []
    gltf.save_binary(str(tmp_path / "noskin.glb"))
    with pytest.raises(ValueError, match="no skinned mesh"):
        load_model(tmp_path / "noskin.glb")


def test_weld_keyword_matches_weld(tmp_path):
    _assert_same(load_model(DATA / "Arm5.glb", weld=True).mesh, weld(load_model(DATA / "Arm5.glb").mesh))


# ------------------------------------------------------------------------------------------ bad input


def test_bad_input(tmp_path):
    with pytest.raises(FileNotFoundError, match="no such file"):
        load_model(tmp_path / "missing.glb")
    (tmp_path / "junk.glb").write_bytes(b"hello, not a model")
    with pytest.raises(ValueError, match="not a glTF"):
        load_model(tmp_path / "junk.glb")
    (tmp_path / "v1.gltf").write_text(json.dumps({"asset": {"version": "1.0"}}))
    with pytest.raises(ValueError, match="not a glTF 2.0"):
        load_model(tmp_path / "v1.gltf")
    (tmp_path / "trunc.glb").write_bytes((DATA / "RiggedSimple.glb").read_bytes()[:1000])
    with pytest.raises(ValueError, match="truncated"):
        load_model(tmp_path / "trunc.glb")
    with pytest.raises(ValueError, match="no skinned mesh"):
        load_model(_synthetic(tmp_path, skins=False))
    with pytest.raises(ValueError, match=r"primitive 0: WEIGHTS of vertex 0 sum to 1.2"):
        load_model(_synthetic(tmp_path, weight=255))
    with pytest.raises(ValueError, match=r"mode 1 \(LINES\)"):
        load_model(_synthetic(tmp_path, mode=1))
    shear = np.eye(4)
    shear[0, 1] = 0.1
    with pytest.raises(ValueError, match="node 0.*shear"):
        load_model(_synthetic(tmp_path, root_matrix=shear))
    path = _synthetic(tmp_path)
    (tmp_path / "syn data.bin").unlink()
    with pytest.raises(FileNotFoundError, match="syn data.bin"):
        load_model(path)
    with pytest.raises(ValueError, match=r"\.glb or \.gltf"):
        save_model(load_model(DATA / "RiggedSimple.glb"), tmp_path / "out.obj")


# ------------------------------------------------------------------------------------------ weld


def test_weld_triangle_soup_restores_shared_vertices():
    mesh = load_model(DATA / "PlaneWith3Bones.glb").mesh
    V, F, J, W = (np.asarray(a) for a in (mesh.V, mesh.F, mesh.J, mesh.W))
    soup = SkinnedMesh(
        V=jnp.asarray(V[F].reshape(-1, 3)),
        F=jnp.arange(F.size, dtype=jnp.int32).reshape(-1, 3),
        J=jnp.asarray(J[F].reshape(F.size, -1)),
        W=jnp.asarray(W[F].reshape(F.size, -1)),
        inverse_bind=mesh.inverse_bind,
        joints=mesh.joints,
    )
    welded = weld(soup)
    assert welded.num_vertices == len(np.unique(F)) == 25
    assert welded.primitive_sizes == ((25, 32),)
    np.testing.assert_array_equal(np.asarray(welded.V)[np.asarray(welded.F)], V[F])
    np.testing.assert_array_equal(np.asarray(welded.W)[np.asarray(welded.F)], W[F])
    assert welded.F.dtype == jnp.int32


def test_weld_real_model_and_degenerate_faces():
    mesh = load_model(DATA / "Arm5.glb").mesh
    welded = weld(mesh)
    rows = np.hstack([np.asarray(mesh.V), np.asarray(mesh.J), np.asarray(mesh.W)])
    assert welded.num_vertices == len(np.unique(rows, axis=0)) == 2535
    assert welded.F.shape == mesh.F.shape  # seams only: no face collapses
    np.testing.assert_array_equal(np.asarray(welded.V)[np.asarray(welded.F)], np.asarray(mesh.V)[np.asarray(mesh.F)])
    _assert_same(weld(welded), welded)

    # vertices 1 and 2 coincide (face 0 collapses); vertex 3 has the same position but other weights
    V = jnp.asarray([[0.0, 0, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0], [0, 1, 0]])
    J = jnp.zeros((5, 4), jnp.int32).at[:, 1].set(1)
    W = jnp.asarray([[1.0, 0, 0, 0]] * 3 + [[0.5, 0.5, 0, 0], [1.0, 0, 0, 0]])
    F = jnp.asarray([[0, 1, 2], [0, 2, 4], [0, 3, 4], [0, 1, 1]], jnp.int32)
    tiny = SkinnedMesh(V=V, F=F, J=J, W=W, inverse_bind=jnp.eye(4)[None].repeat(2, 0), joints=(0, 1))
    welded = weld(tiny)
    assert welded.num_vertices == 4
    np.testing.assert_array_equal(welded.F, [[0, 1, 3], [0, 2, 3]])


# ------------------------------------------------------------------------------------------ corrupt buffers


def _corrupt_glb(tmp_path, pick, name=None):
    """RiggedSimple.glb with element 1 of the accessor that ``pick(json)`` names overwritten by NaN (the bytes
    of a corrupt buffer), and that accessor named ``name``: (path, accessor index)."""
    raw = bytearray((DATA / "RiggedSimple.glb").read_bytes())
    length = struct.unpack_from("<I", raw, 12)[0]
    doc = json.loads(raw[20 : 20 + length])
    index = pick(doc)
    accessor = doc["accessors"][index]
    view = doc["bufferViews"][accessor["bufferView"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4, "MAT4": 16}[accessor["type"]]
    stride = view.get("byteStride", 4 * width)
    offset = 20 + length + 8 + view.get("byteOffset", 0) + accessor.get("byteOffset", 0) + stride
    struct.pack_into("<f", raw, offset, float("nan"))
    if name is not None:  # a longer JSON chunk: rebuild the container
        accessor["name"] = name
        text = json.dumps(doc).encode()
        text += b" " * (-len(text) % 4)
        binary = raw[20 + length :]
        raw = bytearray(struct.pack("<III", 0x46546C67, 2, 12 + 8 + len(text) + len(binary)))
        raw += struct.pack("<II", len(text), 0x4E4F534A) + text + binary
    path = tmp_path / "corrupt.glb"
    path.write_bytes(bytes(raw))
    return path, index


def test_a_non_finite_accessor_is_named(tmp_path):
    """A NaN in a float buffer is caught where it is read, naming the accessor and what reads it (before:
    positions loaded as NaN and a later step failed with an unrelated message)."""
    path, index = _corrupt_glb(tmp_path, lambda d: d["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
    with pytest.raises(
        ValueError,
        match=rf"POSITION \(accessor {index}\) holds 1 non-finite elements .* the "
        r"first at element 1",
    ):
        load_model(path)
    path, index = _corrupt_glb(tmp_path, lambda d: d["animations"][0]["samplers"][0]["output"], name="keys")
    with pytest.raises(ValueError, match=rf"animation 0 .* output \(accessor {index} 'keys'\) holds 1 non-finite"):
        load_model(path)
    path, index = _corrupt_glb(tmp_path, lambda d: d["skins"][0]["inverseBindMatrices"])
    with pytest.raises(ValueError, match=rf"corrupt.glb: skin 0 inverseBindMatrices \(accessor {index}\)"):
        load_model(path)


def test_a_non_finite_node_transform_is_named(tmp_path):
    doc = json.loads(_synthetic(tmp_path).read_text())
    doc["nodes"][1]["translation"] = [float("nan"), 1.0, 0.0]  # Python's json writes and reads NaN
    doc["nodes"][0]["matrix"][12] = float("inf")
    path = tmp_path / "nan.gltf"  # beside the synthetic file's buffer
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"node 0 \(node0\): matrix must be finite"):
        load_model(path)
    doc["nodes"][0]["matrix"][12] = 0.0
    path.write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"node 1 \(a\): translation, rotation, scale must be finite, got \[nan, 1.0"):
        load_model(path)


def test_to_glb_is_the_glb_save_model_writes(tmp_path):
    model = load_model(DATA / "RiggedSimple.glb")
    save_model(model, tmp_path / "model.glb")
    assert model.to_glb() == (tmp_path / "model.glb").read_bytes()
