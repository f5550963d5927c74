"""The glTF 2.0 writer: a model's files (``.glb``, or ``.gltf`` with its ``.bin``), laid out as the specification's
sections "Binary Data Storage", "Skins", "Animations" and "GLB File Format Specification" say; ``deform.save_model``
(in ``deform._gltf``, with the reader) writes them. It needs the model's bundles only for their types, so that
``RiggedModel.to_glb`` can call it without an import cycle. Everything here runs on the host with numpy.
"""

from __future__ import annotations

import json
import os
import urllib.parse
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from _jaxcga_shared.gltf import ARRAY_BUFFER, ELEMENT_ARRAY_BUFFER, BufferWriter, glb_bytes

if TYPE_CHECKING:
    from deform._model import AnimationClip, RiggedModel, SkinnedMesh

GLTF_OUTPUTS = (".glb", ".gltf")  # what save_model writes


def _finite(name: str, x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: contains non-finite values; cannot write glTF")
    return x


def _mesh_json(mesh: SkinnedMesh, writer: BufferWriter) -> list[dict]:
    V = _finite("model.mesh.V", mesh.V).astype("<f4")
    W = _finite("model.mesh.W", mesh.W).astype("<f4")
    F, J = np.asarray(mesh.F, dtype=np.int64), np.asarray(mesh.J, dtype=np.int64)
    n, k = len(V), J.shape[1]
    if k == 0:
        raise ValueError("model.mesh.J: expected at least one influence per vertex, got shape (n, 0)")
    if F.size and (F.min() < 0 or F.max() >= n):
        raise ValueError(f"model.mesh.F: indices must be in [0, {n})")
    if J.size and (J.min() < 0 or J.max() >= mesh.num_joints):
        raise ValueError(f"model.mesh.J: joint indices must be in [0, {mesh.num_joints})")
    pad = -k % 4  # glTF stores influences in sets of 4
    J = np.pad(J, ((0, 0), (0, pad))).astype("<u2")
    W = np.pad(W, ((0, 0), (0, pad)))
    primitives, v0, f0 = [], 0, 0
    for p, (nv, nf) in enumerate(mesh.primitive_sizes or ((n, len(F)),)):
        faces = F[f0 : f0 + nf] - v0
        if nv == 0 or nf == 0:
            raise ValueError(f"model.mesh.primitive_sizes: primitive {p} is empty {(nv, nf)}; glTF cannot store it")
        if faces.min() < 0 or faces.max() >= nv:
            raise ValueError(
                f"model.mesh.F: faces of primitive {p} use vertices of another primitive; set primitive_sizes=()"
            )
        attributes = {"POSITION": writer.accessor(V[v0 : v0 + nv], "VEC3", ARRAY_BUFFER, bounds=True)}
        for s in range(J.shape[1] // 4):
            attributes[f"JOINTS_{s}"] = writer.accessor(J[v0 : v0 + nv, 4 * s : 4 * s + 4], "VEC4", ARRAY_BUFFER)
            attributes[f"WEIGHTS_{s}"] = writer.accessor(W[v0 : v0 + nv, 4 * s : 4 * s + 4], "VEC4", ARRAY_BUFFER)
        indices = writer.accessor(faces.reshape(-1).astype("<u4"), "SCALAR", ELEMENT_ARRAY_BUFFER)
        primitives.append({"attributes": attributes, "indices": indices, "mode": 4})
        v0, f0 = v0 + nv, f0 + nf
    return primitives


def _animation_json(clip: AnimationClip, writer: BufferWriter) -> dict:
    samplers, channels, inputs = [], [], {}
    for c, channel in enumerate(clip.channels):
        times = _finite(f"clip {clip.name!r} channel {c} times", channel.times).astype("<f4")
        if np.any(np.diff(times) <= 0):
            raise ValueError(f"clip {clip.name!r} channel {c}: times must be strictly increasing (in float32)")
        values = _finite(f"clip {clip.name!r} channel {c} values", channel.values).astype("<f4")
        d = values.shape[-1]
        if times.tobytes() not in inputs:
            inputs[times.tobytes()] = writer.accessor(times, "SCALAR", bounds=True)  # min/max required for inputs
        output = writer.accessor(values.reshape(-1, d), f"VEC{d}")
        samplers.append({"input": inputs[times.tobytes()], "output": output, "interpolation": channel.interpolation})
        channels.append({"sampler": c, "target": {"node": channel.bone, "path": channel.path}})
    return {"name": clip.name, "samplers": samplers, "channels": channels}


def buffer_file(path: str | Path, what: str = "path") -> Path | None:
    """The buffer file ``save_model`` writes beside ``path``: ``<stem>.bin`` for a .gltf, None for a .glb.

    Args:
        path: str or Path of the .gltf or .glb to write.
        what: the argument named in the error.
    Returns:
        The ``<stem>.bin`` path for a .gltf, None for a .glb.
    Raises:
        ValueError: that file exists and is not a buffer of the .gltf at ``path`` (none there, or one that
            does not refer to it): writing would destroy an unrelated file.
    """
    path = Path(path)
    if path.suffix.lower() != ".gltf":
        return None
    bin_path = path.with_suffix(".bin")
    if not bin_path.exists():
        return bin_path
    try:
        buffers = json.loads(path.read_bytes()).get("buffers", [])
        uris = [urllib.parse.unquote(b["uri"]) for b in buffers if isinstance(b, dict) and "uri" in b]
    except (OSError, ValueError, AttributeError, TypeError):  # no .gltf there, or not a glTF document
        uris = []
    if not any(os.path.realpath(path.parent / uri) == os.path.realpath(bin_path) for uri in uris):
        raise ValueError(
            f"{what}: {bin_path} exists and is not the buffer of {path}; writing {path.name} would replace it "
            "(move it away or choose another name)"
        )
    return bin_path


def model_files(model: RiggedModel, path: str | Path) -> dict[Path, bytes | str]:
    """The files ``save_model(model, path)`` writes, ``{path: content}``: the .glb, or the .gltf and its buffer
    (``save_models`` writes several models as one unit). Arguments and errors as
    ``save_model``'s, except that nothing is written."""
    path = Path(path)
    if path.suffix.lower() not in GLTF_OUTPUTS:
        raise ValueError(f"path: expected a .glb or .gltf file name, got {path.name!r}")
    bin_path = buffer_file(path)
    mesh, skeleton = model.mesh, model.skeleton
    repeated = sorted({skeleton.names[j] for j in mesh.joints if mesh.joints.count(j) > 1})
    if repeated:
        raise ValueError(
            f"model.mesh.joints: bones {repeated} appear as several joints (different inverse bind matrices); "
            "one glTF skin lists each node once"
        )
    writer = BufferWriter()
    primitives = _mesh_json(mesh, writer)
    ibm = _finite("model.mesh.inverse_bind", mesh.inverse_bind).astype("<f4").transpose(0, 2, 1).reshape(-1, 16)
    skin = {"joints": list(mesh.joints), "inverseBindMatrices": writer.accessor(ibm, "MAT4")}
    t, r, s = (_finite(f"model.skeleton.{a}", getattr(skeleton, a)) for a in ("translation", "rotation", "scale"))
    b = skeleton.num_bones
    nodes = [
        {"name": skeleton.names[i], "translation": t[i].tolist(), "rotation": r[i].tolist(), "scale": s[i].tolist()}
        for i in range(b)
    ]
    for i, p in enumerate(skeleton.parents):
        if p != -1:
            nodes[p].setdefault("children", []).append(i)
    nodes.append({"name": model.name, "mesh": 0, "skin": 0})
    roots = [i for i, p in enumerate(skeleton.parents) if p == -1] + [b]
    animations = [_animation_json(clip, writer) for clip in model.clips if clip.channels]
    blob = writer.blob()
    buffer: dict[str, int | str] = {"byteLength": len(blob)}
    if bin_path is not None:
        buffer["uri"] = urllib.parse.quote(bin_path.name)
    doc = {
        "asset": {"version": "2.0", "generator": "jaxcga"},
        "scene": 0,
        "scenes": [{"name": model.name, "nodes": roots}],
        "nodes": nodes,
        "meshes": [{"name": model.name, "primitives": primitives}],
        "skins": [skin],
        "accessors": writer.accessors,
        "bufferViews": writer.views,
        "buffers": [buffer],
    }
    if animations:
        doc["animations"] = animations
    if bin_path is not None:
        return {path: json.dumps(doc, indent=1), bin_path: blob}
    return {path: glb_bytes(doc, blob)}
