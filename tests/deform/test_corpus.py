"""The corpus of public rigged characters (tests/data/characters, ``CHARACTERS`` in tests/shared.py): together the
models cover what real characters bring (many joints, several skins, morph targets, a part inside another, clothing
over the body, a coarse mesh, a large mesh), fit in 5 MB, and every one loads and skins as the glTF specification
says (the independent reference of tests/deform/_gltf_reference.py), for LBS and eq. (17)."""

from __future__ import annotations

import json
import struct

import igl
import numpy as np
import pytest

import deform
from tests.deform._gltf_reference import Reference
from tests.shared import (
    CHARACTERS,
    DATA,
    character_params,
    connected_parts,
    gltf_json,
    load_character,
    moving_mesh_nodes,
)

MAX_BYTES = 5_000_000  # the new files under tests/data/characters (CesiumMan was there before)
LARGE = 25_000  # welded vertices of the largest model (the benchmarks' real_* figures run on it)
COARSE = 1_000  # faces of the coarse model
MANY_JOINTS = 50
LAYER_GAP = 0.01  # a part lies over another when its vertices are this fraction of the diagonal from it


def _diagonal(V) -> float:
    V = np.asarray(V)
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def _inner_parts(V, parts) -> list[tuple[int, int]]:
    """(inner, outer) part indices where the inner part's bounding box lies strictly inside the outer's."""
    boxes = np.array([(V[p].min(axis=0), V[p].max(axis=0)) for p in parts])
    inside = np.all(boxes[:, None, 0] > boxes[None, :, 0], axis=2) & np.all(
        boxes[:, None, 1] < boxes[None, :, 1], axis=2
    )
    return [tuple(pair) for pair in np.argwhere(inside)]


def _layers(V, F, parts) -> list[tuple[int, float]]:
    """(part, fraction) for each part of 20 vertices or more: the fraction of its vertices within LAYER_GAP x the
    diagonal of the surface of the other parts (1: it lies over them, as clothing over a body)."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    label = np.full(len(V), -1)
    for i, part in enumerate(parts):
        label[part] = i
    face_part = label[F[:, 0]]
    gap = LAYER_GAP * _diagonal(V)
    result = []
    for i, part in enumerate(parts):
        others = F[face_part != i]
        if len(part) < 20 or not len(others):
            continue
        squared, _, _ = igl.point_mesh_squared_distance(V[part], V, others)
        result.append((i, float(np.mean(np.sqrt(squared) < gap))))
    return result


def test_the_corpus_is_listed_and_small():
    files = sorted((DATA / "characters").glob("*"))
    assert {p.name for p in files} == {p.name for p in CHARACTERS.values() if p.parent.name == "characters"}
    assert len(CHARACTERS) >= 6
    readme = (DATA / "README.md").read_text()
    for path in CHARACTERS.values():
        assert path.name in readme, f"{path.name} has no licence line in tests/data/README.md"
    assert sum(p.stat().st_size for p in files) <= MAX_BYTES


def test_the_corpus_covers_real_characters():
    """Each property holds on at least one model, counted independently of the loader where the file says it (skins,
    morph targets) and on the welded mesh otherwise."""
    documents = {name: gltf_json(path) for name, path in CHARACTERS.items()}
    skins = {name: len(doc.get("skins", [])) for name, doc in documents.items()}
    morphs = {
        name: sum(len(p.get("targets", [])) for m in doc.get("meshes", []) for p in m["primitives"])
        for name, doc in documents.items()
    }
    assert max(skins.values()) >= 2, skins
    assert max(morphs.values()) >= 1, morphs
    models = {name: load_character(name) for name in CHARACTERS}
    joints = {name: model.mesh.num_joints for name, model in models.items()}
    sizes = {name: (len(model.mesh.V), len(model.mesh.F)) for name, model in models.items()}
    assert max(joints.values()) >= MANY_JOINTS, joints
    assert min(f for _, f in sizes.values()) <= COARSE, sizes
    assert max(v for v, _ in sizes.values()) >= LARGE, sizes
    inner, layered = {}, {}
    for name, model in models.items():
        V, F = np.asarray(model.mesh.V, np.float64), np.asarray(model.mesh.F)
        parts = connected_parts(F, len(V))
        inner[name] = len(_inner_parts(V, parts))
        layered[name] = max((fraction for _, fraction in _layers(V, F, parts)), default=0.0)
    assert max(inner.values()) >= 1, inner
    assert max(layered.values()) >= 0.9, layered


def test_the_part_measures_on_a_synthetic_scene():
    """A small box inside a big one is an inner part and no layer; a sheet 0.5% of the diagonal over the big box's
    top is a layer; a box far away is neither."""
    import trimesh

    big = trimesh.creation.box(extents=(2, 2, 2))
    small = trimesh.creation.box(extents=(0.5, 0.5, 0.5))
    far = trimesh.creation.box(extents=(0.5, 0.5, 0.5)).apply_translation((6, 0, 0))
    diagonal = np.linalg.norm([6.25 + 1, 2, 2])  # the scene's box: x in [-1, 6.25], y and z in [-1, 1]
    sheet = trimesh.creation.box(extents=(1.5, 1.5, 1e-3)).apply_translation((0, 0, float(1 + 0.005 * diagonal)))
    subdivided = trimesh.remesh.subdivide_to_size(sheet.vertices, sheet.faces, max_edge=0.3)
    sheet = trimesh.Trimesh(subdivided[0], subdivided[1])
    scene = trimesh.util.concatenate([big, small, far, sheet])
    assert isinstance(scene, trimesh.Trimesh)
    V, F = np.asarray(scene.vertices), np.asarray(scene.faces)
    parts = connected_parts(F, len(V))
    assert sorted(map(len, parts)) == [8, 8, 8, len(sheet.vertices)]
    which = {}
    for i, part in enumerate(parts):
        lo, hi = V[part].min(axis=0), V[part].max(axis=0)
        which["sheet" if len(part) > 8 else "far" if lo[0] > 5 else "big" if hi[0] > 0.9 else "small"] = i
    assert _inner_parts(V, parts) == [(which["small"], which["big"])]
    fractions = dict(_layers(V, F, parts))
    assert fractions == {which["sheet"]: 1.0}  # the boxes have 8 vertices: too few to count


def _clip_time(model) -> float | None:
    """40% into the first clip, None without one."""
    if not model.clips:
        return None
    times = np.concatenate([np.asarray(c.times) for c in model.clips[0].channels])
    return float(times.min() + 0.4 * (times.max() - times.min()))


@pytest.mark.parametrize("name", character_params())
def test_every_character_skins_as_the_specification(name):
    """LBS and eq. (17) of the unwelded model equal the independent reference's skinning (the specification's
    sampling, kinematics and blend) at a time inside the first clip, or in the rest pose without one; the welded
    model skins to finite positions, each one of the unwelded positions."""
    from scipy.spatial import KDTree

    model = load_character(name, weld=False)
    reference = Reference(CHARACTERS[name])
    t = _clip_time(model)
    expected = reference.skin(0, t) if t is not None else reference.skin()
    scale = _diagonal(expected)

    def skin(model, method):
        return np.asarray(deform.skin_model(model, t, method) if t is not None else deform.rest_pose(model, method))

    # float32 data, summed in another order by another formula: 1.5e-7 of the diagonal at most on the corpus
    np.testing.assert_allclose(skin(model, "lbs"), expected, atol=3e-7 * scale)
    # the files' float32 inverse bind matrices are similitudes to ~1e-7 only, and eq. (17) takes their nearest
    # similitudes: 1.8e-6 of the diagonal on MaleBaseMesh
    np.testing.assert_allclose(skin(model, "cga"), expected, atol=5e-6 * scale)
    welded = skin(load_character(name), "cga")
    assert np.isfinite(welded).all()
    distance, _ = KDTree(skin(model, "cga")).query(welded)
    assert distance.max() <= 1e-9 * scale


@pytest.mark.slow
def test_the_robot_s_rigid_parts_follow_their_bones():
    """RobotExpressive skins only its hands; its torso, head, arms, legs and feet are meshes without a skin under its
    joints (rigid attachments). All of them are read, counted from the file (every primitive of a mesh node at or
    below a used skin's joint), and every clip of a few, at two times, skins as the reference draws them (the
    rigid parts with their node's world transform), for LBS and eq. (17)."""
    import jax

    path = CHARACTERS["RobotExpressive"]
    document = gltf_json(path)
    rigid = [i for i in moving_mesh_nodes(document) if "skin" not in document["nodes"][i]]
    assert rigid == [0, 3, 4, 6, 7, 8, 13, 14, 33, 34, 56, 57, 61, 62, 69]
    nodes = document["nodes"]
    read = [i for i, n in enumerate(nodes) if "mesh" in n and ("skin" in n or i in rigid)]
    counts = [
        document["accessors"][prim["attributes"]["POSITION"]]["count"]
        for i in read
        for prim in document["meshes"][nodes[i]["mesh"]]["primitives"]
    ]
    model = load_character("RobotExpressive", weld=False)
    assert [v for v, _ in model.mesh.primitive_sizes] == counts
    reference = Reference(path)
    for clip in ("Dance", "Jump", "Punch", "WalkJump"):
        a = [c.name for c in model.clips].index(clip)
        end = float(model.clip(a).end)
        for method in ("lbs", "cga"):
            skin = jax.jit(lambda t, a=a, method=method: deform.skin_model(model, t, method, clip=a))
            for t in (0.3 * end, 0.7 * end):
                expected = reference.skin(a, t)
                # as in test_every_character_skins_as_the_specification: 2.1e-7 (lbs), 2.5e-6 (cga) on all 14 clips
                atol = (3e-7 if method == "lbs" else 5e-6) * _diagonal(expected)
                np.testing.assert_allclose(skin(t), expected, atol=atol, err_msg=f"{clip} at {t:.3g} s, {method}")


@pytest.mark.parametrize("extension", ["KHR_draco_mesh_compression", "EXT_meshopt_compression"])
def test_a_compressed_character_is_refused_by_name(tmp_path, extension):
    """Real characters often come Draco- or meshopt-compressed (the Khronos samples' copies on GitHub are): the loader
    names the extension instead of reading garbage. The file: Fox.glb with the extension required."""
    data = CHARACTERS["Fox"].read_bytes()
    (length,) = struct.unpack("<I", data[12:16])
    document = json.loads(data[20 : 20 + length])
    document["extensionsRequired"] = [extension]
    document["extensionsUsed"] = [extension]
    chunk = json.dumps(document).encode()
    chunk += b" " * (-len(chunk) % 4)
    rest = data[20 + length :]  # the BIN chunk, as it was
    body = struct.pack("<I4s", len(chunk), b"JSON") + chunk + rest
    path = tmp_path / "compressed.glb"
    path.write_bytes(struct.pack("<4sII", b"glTF", 2, 12 + len(body)) + body)
    with pytest.raises(ValueError, match=rf"required extensions \['{extension}'\] are not supported"):
        deform.load_model(path)
