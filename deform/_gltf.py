"""Rigged-model I/O: glTF 2.0 reading and saving (the file writer itself is ``deform._gltf_write``), FBX / COLLADA
through assimp, vertex welding.

Semantics are those of the glTF 2.0 specification (sections "Concepts", "Binary Data Storage",
"Skins", "Animations", "GLB File Format Specification"):

* accessors are read with numpy over their buffer views (``byteOffset``, ``byteStride``,
  ``componentType``, ``type``, ``count``); ``normalized`` integers are dequantized as the spec says
  (``max(c / 127, -1)`` for BYTE, ``c / 255`` for UNSIGNED_BYTE, ``max(c / 32767, -1)`` for SHORT,
  ``c / 65535`` for UNSIGNED_SHORT); sparse accessors are applied on top of their base data; a NaN or
  infinity in any float accessor is an error naming the accessor and what reads it;
* matrices are column-major in the file and row-major (``M @ [x, 1]``) in memory; a node's local
  transform is ``T * R * S`` or its ``matrix``, which is decomposed into T, R, S (a shear is an error);
* the skeleton is every joint of every skin that a skinned mesh node uses, every animated node between a rigid
  attachment (below) and them, plus all their ancestors,
  in depth-first order from the scene roots (children in the order the file lists them);
* a skinned vertex is ``sum_k W[:, k] * global(bone) @ inverse_bind @ [V, 1]``: the transform of the
  node that holds the mesh is ignored, so meshes are read in their own space;
* a mesh node without a skin that is a joint of a used skin or lies below one (a rigid attachment: a robot's
  torso, a prop in a hand) is drawn by the spec at ``global(node) @ p``; it is read as a part with weight 1 on its
  nearest bone b (the node itself or an ancestor; animated nodes between become bones), with b's inverse bind
  matrix (b's inverse global rest transform when no used skin has one) and V placed so that this is exact under
  any pose; mesh nodes outside the skeleton (static scenery) are not read;
* animation channels on nodes outside the skeleton and morph-target ``weights`` channels are dropped.

Images, materials, normals, texture coordinates, morph targets (the base positions are read, the weights
ignored) and cameras are not read. FBX,
COLLADA and every other format assimp imports are converted to GLB by the ``assimp`` command-line
tool (Debian package ``assimp-utils``) first. Everything here runs on the host with numpy.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import struct
import subprocess
import tempfile
import urllib.parse
from collections.abc import Mapping
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from _jaxcga_shared.gltf import CHUNK_BIN, CHUNK_JSON, FLOAT, GLB_MAGIC, UINT, USHORT
from _jaxcga_shared.output import write_files
from deform._gltf_write import model_files
from deform._model import INTERPOLATIONS, PATHS, AnimationClip, Channel, RiggedModel, Skeleton, SkinnedMesh
from deform._rig import quaternion_xyzw_to_matrix

_COMPONENT = {5120: "<i1", 5121: "<u1", 5122: "<i2", 5123: "<u2", 5125: "<u4", 5126: "<f4"}
_NORMALIZER = {5120: 127.0, 5121: 255.0, 5122: 32767.0, 5123: 65535.0}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_MODES = {
    0: "POINTS",
    1: "LINES",
    2: "LINE_LOOP",
    3: "LINE_STRIP",
    4: "TRIANGLES",
    5: "TRIANGLE_STRIP",
    6: "TRIANGLE_FAN",
}
# Extensions whose geometry lives outside plain accessors.
_UNSUPPORTED_EXTENSIONS = {"KHR_draco_mesh_compression", "EXT_meshopt_compression"}
# Float32 data: columns of a rotation-times-scale matrix are orthogonal to about 1e-7; a shear is far larger.
_SHEAR_TOLERANCE = 1e-5
_WEIGHT_TOLERANCE = 1e-2


def _float_array(x) -> jnp.ndarray:
    # converted by numpy and copied by device_put: a conversion on the device, or jnp.asarray's staging, is a
    # compiled program per shape
    return jax.device_put(np.asarray(x, dtype=jnp.result_type(float)))


def _int_array(x) -> jnp.ndarray:
    return jax.device_put(np.asarray(x, dtype=np.int32))


# ----------------------------------------------------------------------------------------------- reading


class _Document:
    """A parsed glTF: its JSON, its buffers (loaded lazily) and the file name used in error messages."""

    def __init__(self, path: Path, source: str):
        self.source = source
        self.base = path.parent
        self.glb_bin = None
        raw = path.read_bytes()
        if raw[:4] == GLB_MAGIC:
            self.json = self._parse_glb(raw)
        else:
            try:
                self.json = json.loads(raw.decode("utf-8"))
            except (UnicodeDecodeError, json.JSONDecodeError) as e:
                raise ValueError(f"{source}: not a glTF 2.0 file (neither GLB nor glTF JSON): {e}") from None
        if not isinstance(self.json, dict) or not str(self.json.get("asset", {}).get("version", "")).startswith("2."):
            raise ValueError(f"{source}: not a glTF 2.0 file (asset.version must be '2.x')")
        unsupported = _UNSUPPORTED_EXTENSIONS & set(self.json.get("extensionsRequired", ()))
        if unsupported:
            raise ValueError(
                f"{source}: required extensions {sorted(unsupported)} are not supported (compressed geometry)"
            )
        self._buffers = {}

    def _parse_glb(self, raw: bytes) -> dict:
        if len(raw) < 20:
            raise ValueError(f"{self.source}: truncated GLB file ({len(raw)} bytes)")
        _, version, length = struct.unpack_from("<4sII", raw, 0)
        if version != 2:
            raise ValueError(f"{self.source}: GLB container version {version}, expected 2")
        if length > len(raw):
            raise ValueError(f"{self.source}: truncated GLB file (header says {length} bytes, file has {len(raw)})")
        doc, offset = None, 12
        while offset + 8 <= length:
            size, kind = struct.unpack_from("<II", raw, offset)
            chunk = raw[offset + 8 : offset + 8 + size]
            if len(chunk) != size:
                raise ValueError(f"{self.source}: truncated GLB chunk at byte {offset}")
            if doc is None:
                if kind != CHUNK_JSON:
                    raise ValueError(f"{self.source}: the first GLB chunk must be JSON")
                try:
                    doc = json.loads(chunk.decode("utf-8"))
                except (UnicodeDecodeError, json.JSONDecodeError) as e:
                    raise ValueError(f"{self.source}: malformed GLB JSON chunk: {e}") from None
            elif kind == CHUNK_BIN and self.glb_bin is None:
                self.glb_bin = chunk
            offset += 8 + size
        if doc is None:
            raise ValueError(f"{self.source}: GLB file without a JSON chunk")
        return doc

    def item(self, kind: str, index, what: str) -> dict:
        items = self.json.get(kind, [])
        if not isinstance(index, int) or not 0 <= index < len(items):
            raise ValueError(f"{self._at(what)} refers to {kind}[{index}], the file has {len(items)} {kind}")
        return items[index]

    def buffer(self, index: int | None) -> bytes:  # None: a view without "buffer", refused by item()
        if index not in self._buffers:
            spec = self.item("buffers", index, "a buffer view")
            uri = spec.get("uri")
            if uri is None:
                if index != 0 or self.glb_bin is None:
                    raise ValueError(f"{self.source}: buffer {index} has no uri and there is no GLB binary chunk")
                data = self.glb_bin
            elif uri.startswith("data:"):
                header, _, payload = uri.partition(",")
                data = (
                    base64.b64decode(payload) if header.endswith(";base64") else urllib.parse.unquote_to_bytes(payload)
                )
            else:
                file = self.base / urllib.parse.unquote(uri)
                if not file.is_file():
                    raise FileNotFoundError(f"{self.source}: buffer {index} refers to {uri!r}, no such file {file}")
                data = file.read_bytes()
            if len(data) < spec.get("byteLength", 0):
                raise ValueError(
                    f"{self.source}: buffer {index} holds {len(data)} bytes, byteLength says {spec['byteLength']}"
                )
            self._buffers[index] = data
        return self._buffers[index]

    def _at(self, what: str) -> str:
        """``what`` prefixed by the file, once (a primitive's or channel's ``what`` already starts with it)."""
        return what if what.startswith(self.source) else f"{self.source}: {what}"

    def _view(self, view_index, offset: int, count: int, width: int, dtype: np.dtype, what: str) -> np.ndarray:
        view = self.item("bufferViews", view_index, what)
        data = self.buffer(view.get("buffer"))
        start, length = view.get("byteOffset", 0), view["byteLength"]
        element = dtype.itemsize * width
        stride = view.get("byteStride") or element
        if start + length > len(data):
            raise ValueError(
                f"{self.source}: buffer view {view_index} ends past its buffer ({start + length} > {len(data)})"
            )
        if count and offset + stride * (count - 1) + element > length:
            raise ValueError(f"{self._at(what)} reads past the end of buffer view {view_index}")
        strided = np.ndarray(
            (count, width), dtype, buffer=data, offset=start + offset, strides=(stride, dtype.itemsize)
        )
        return strided.copy()

    def accessor(self, index, what: str, types: tuple[str, ...], components: tuple[int, ...]) -> np.ndarray:
        """Accessor ``index`` as a (count, width) array: float64 when ``FLOAT`` is allowed, else int64."""
        acc = self.item("accessors", index, what)
        ctype, kind = acc.get("componentType"), acc.get("type")
        if kind not in types or ctype not in components:
            raise ValueError(
                f"{self._at(what)} (accessor {index}) must have type {' or '.join(types)} and componentType in "
                f"{list(components)}, got {kind} / {ctype}"
            )
        count, width, dtype = acc["count"], _WIDTH[kind], np.dtype(_COMPONENT[ctype])
        if "bufferView" in acc:
            out = self._view(acc["bufferView"], acc.get("byteOffset", 0), count, width, dtype, what)
        else:
            out = np.zeros((count, width), dtype)
        sparse = acc.get("sparse")
        if sparse:
            n, ind, val = sparse["count"], sparse["indices"], sparse["values"]
            if ind.get("componentType") not in (5121, 5123, 5125):
                raise ValueError(f"{self._at(what)} (accessor {index}) has sparse indices of an invalid componentType")
            idx = self._view(
                ind["bufferView"], ind.get("byteOffset", 0), n, 1, np.dtype(_COMPONENT[ind["componentType"]]), what
            )
            values = self._view(val["bufferView"], val.get("byteOffset", 0), n, width, dtype, what)
            if n and idx.max() >= count:
                raise ValueError(f"{self._at(what)} (accessor {index}) has a sparse index past its count {count}")
            out[idx[:, 0]] = values
        if FLOAT not in components:
            return out.astype(np.int64)
        if acc.get("normalized", False) and ctype in _NORMALIZER:
            return np.maximum(out / _NORMALIZER[ctype], -1.0)
        bad = ~np.isfinite(out).all(axis=1)
        if bad.any():  # a corrupt buffer: blame it here rather than on whatever it would break later
            named = f" {acc['name']!r}" if "name" in acc else ""
            raise ValueError(
                f"{self._at(what)} (accessor {index}{named}) holds {int(bad.sum())} non-finite "
                f"elements (NaN or infinity) of {count}, the first at element {int(np.argmax(bad))}"
            )
        return out.astype(np.float64)


_FLOATS = (FLOAT, 5120, 5121, 5122, 5123)  # float, or quantized integers (KHR_mesh_quantization)


def _decompose(matrix: np.ndarray, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Translation, unit quaternion (x, y, z, w) and scale of an affine 4x4 matrix ``T * R * S``."""
    if np.abs(matrix[3] - (0.0, 0.0, 0.0, 1.0)).max() > 1e-6:
        raise ValueError(f"{where}: matrix is not affine (last row {matrix[3].tolist()}, expected [0, 0, 0, 1])")
    linear = matrix[:3, :3]
    scale = np.linalg.norm(linear, axis=0)
    if scale.min() <= 1e-12 * max(1.0, scale.max()):
        raise ValueError(f"{where}: matrix has a zero scale and cannot be decomposed into T * R * S")
    if np.linalg.det(linear) < 0:
        scale[0] = -scale[0]  # a reflection becomes a negative x scale, as in three.js
    rotation = linear / scale
    error = np.abs(rotation.T @ rotation - np.eye(3)).max()
    if error > _SHEAR_TOLERANCE:
        raise ValueError(f"{where}: matrix has a shear (columns {error:.2g} from orthogonal) and is not T * R * S")
    from scipy.spatial.transform import Rotation  # here: nodes given by matrices are rare, the import is slow

    return matrix[:3, 3].copy(), Rotation.from_matrix(rotation).as_quat(), scale


def _node_trs(node: dict, where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    has_trs = any(k in node for k in ("translation", "rotation", "scale"))
    if "matrix" in node:
        matrix = np.asarray(node["matrix"], dtype=np.float64)
        if matrix.shape != (16,):
            raise ValueError(f"{where}: matrix must have 16 numbers, got {matrix.shape}")
        if not np.isfinite(matrix).all():
            raise ValueError(f"{where}: matrix must be finite, got a NaN or infinity")
        matrix = matrix.reshape(4, 4).T  # column-major in the file
        if not has_trs:
            return _decompose(matrix, where)
        if not np.array_equal(matrix, np.eye(4)):
            raise ValueError(f"{where}: node has both a matrix and translation/rotation/scale")
    t = np.asarray(node.get("translation", (0.0, 0.0, 0.0)), dtype=np.float64)
    r = np.asarray(node.get("rotation", (0.0, 0.0, 0.0, 1.0)), dtype=np.float64)
    s = np.asarray(node.get("scale", (1.0, 1.0, 1.0)), dtype=np.float64)
    if t.shape != (3,) or r.shape != (4,) or s.shape != (3,):
        raise ValueError(f"{where}: translation, rotation, scale must have 3, 4, 3 numbers")
    if not (np.isfinite(t).all() and np.isfinite(r).all() and np.isfinite(s).all()):
        raise ValueError(
            f"{where}: translation, rotation, scale must be finite, got {t.tolist()}, {r.tolist()}, {s.tolist()}"
        )
    if not np.linalg.norm(r) > 0:
        raise ValueError(f"{where}: rotation must be a unit quaternion (x, y, z, w), got {r.tolist()}")
    return t, r, s


def _unique_names(names: list[str]) -> list[str]:
    used, out = set(), []
    for base in names:
        name, k = base, 0
        while name in used:
            k += 1
            name = f"{base}.{k:03d}"
        used.add(name)
        out.append(name)
    return out


def _parents(doc: _Document) -> list[int]:
    """Each node's parent (-1 for a root); a node listed as the child of two nodes, or of itself, is an error."""
    nodes = doc.json.get("nodes", [])
    parent = [-1] * len(nodes)
    for i, node in enumerate(nodes):
        for c in node.get("children", []):
            if not isinstance(c, int) or not 0 <= c < len(nodes) or c == i or parent[c] != -1:
                raise ValueError(
                    f"{doc.source}: node {i} lists child {c}, which is not a valid node with a single parent"
                )
            parent[c] = i
    return parent


def _rigid_nodes(doc: _Document, skinned: list[int], parent: list[int]) -> list[int]:
    """The nodes with a mesh and no skin that move with the skeleton: a joint of a used skin or a descendant of one."""
    nodes = doc.json.get("nodes", [])
    joints = set()
    for i in skinned:
        skin = doc.item("skins", nodes[i]["skin"], f"node {i}")
        joints.update(j for j in skin.get("joints", []) if isinstance(j, int))
    rigid = []
    for i, node in enumerate(nodes):
        if "mesh" not in node or "skin" in node:
            continue
        j, steps = i, 0
        while j != -1 and j not in joints and steps <= len(nodes):  # steps: a cycle is reported by _skeleton
            j, steps = parent[j], steps + 1
        if j in joints:
            rigid.append(i)
    return rigid


def _skeleton(
    doc: _Document, skinned: list[int], rigid: list[int], parent: list[int]
) -> tuple[Skeleton, dict[int, int]]:
    """The skeleton of the used skins and of the rigid mesh nodes, and the map node index -> bone index."""
    src, nodes = doc.source, doc.json.get("nodes", [])
    needed = set()

    def add(j):
        while j != -1 and j not in needed:
            needed.add(j)
            j = parent[j]

    for i in skinned:
        skin = doc.item("skins", nodes[i]["skin"], f"node {i}")
        if not skin.get("joints"):
            raise ValueError(f"{src}: skin {nodes[i]['skin']} has no joints")
        for j in skin["joints"]:
            doc.item("nodes", j, f"skin {nodes[i]['skin']}")
            add(j)
    # a rigid mesh's node, and every node between it and the skeleton, that an animation moves becomes a bone (with
    # its ancestors), so that the mesh moves exactly as its node does under any pose; nodes no channel moves are
    # baked into the mesh instead (a bone there would only add the files' float noise in scale to the skeleton)
    animated = {
        c.get("target", {}).get("node")
        for a in doc.json.get("animations", [])
        for c in a.get("channels", [])
        if c.get("target", {}).get("path") in PATHS
    }
    for i in rigid:
        j = i
        while j != -1 and j not in needed:
            if j in animated:
                add(j)
                break
            j = parent[j]
    scenes = doc.json.get("scenes", [])
    scene_roots = scenes[doc.json.get("scene", 0)].get("nodes", []) if scenes else []
    roots = [r for r in dict.fromkeys([*scene_roots, *range(len(nodes))]) if parent[r] == -1]
    order, bone_of, stack = [], {}, [r for r in reversed(roots) if r in needed]
    while stack:
        i = stack.pop()
        bone_of[i] = len(order)
        order.append(i)
        stack.extend(c for c in reversed(nodes[i].get("children", [])) if c in needed)
    if len(order) != len(needed):
        raise ValueError(f"{src}: joint nodes {sorted(needed - set(order))} are not reachable from a root (cycle)")
    names = _unique_names([nodes[i].get("name") or f"node{i}" for i in order])
    trs = [_node_trs(nodes[i], f"{src}: node {i} ({names[b]})") for b, i in enumerate(order)]
    skeleton = Skeleton(
        translation=_float_array(np.array([t for t, _, _ in trs]).reshape(-1, 3)),
        rotation=_float_array(np.array([r for _, r, _ in trs]).reshape(-1, 4)),
        scale=_float_array(np.array([s for _, _, s in trs]).reshape(-1, 3)),
        parents=tuple(bone_of[parent[i]] if parent[i] != -1 else -1 for i in order),
        names=tuple(names),
    )
    return skeleton, bone_of


def _joint_table(doc: _Document, skins: list[int], bone_of: dict[int, int]):
    """Joints (bone, inverse bind) as the union over ``skins``, and per skin its joint -> global index map."""
    bones, matrices, index, maps = [], [], {}, {}
    for s in skins:
        skin = doc.json["skins"][s]
        n = len(skin["joints"])
        if "inverseBindMatrices" in skin:
            ibm = doc.accessor(skin["inverseBindMatrices"], f"skin {s} inverseBindMatrices", ("MAT4",), (FLOAT,))
            if len(ibm) != n:
                raise ValueError(f"{doc.source}: skin {s} has {n} joints but {len(ibm)} inverse bind matrices")
            ibm = ibm.reshape(n, 4, 4).transpose(0, 2, 1)  # column-major in the file
        else:
            ibm = np.broadcast_to(np.eye(4), (n, 4, 4))
        local = []
        for node, matrix in zip(skin["joints"], ibm):
            key = (bone_of[node], matrix.tobytes())
            if key not in index:
                index[key] = len(bones)
                bones.append(bone_of[node])
                matrices.append(matrix)
            local.append(index[key])
        maps[s] = np.asarray(local, dtype=np.int64)
    return tuple(bones), np.asarray(matrices, dtype=np.float64).reshape(-1, 4, 4), maps


def _primitive(doc: _Document, prim: dict, skin_joints: int | None, where: str):
    """V (n, 3), F (m, 3), J (n, 4s) local joint indices, W (n, 4s) of one skinned primitive; for a rigid one
    (``skin_joints`` None) J and W are None."""
    mode = prim.get("mode", 4)
    if mode != 4:
        raise ValueError(
            f"{where}: primitive mode {mode} ({_MODES.get(mode, 'unknown')}); only TRIANGLES (4) is supported"
        )
    attrs = prim.get("attributes", {})
    if "POSITION" not in attrs:
        raise ValueError(f"{where}: primitive has no POSITION attribute")
    V = doc.accessor(attrs["POSITION"], f"{where} POSITION", ("VEC3",), _FLOATS)
    n = len(V)
    if "indices" in prim:
        F = doc.accessor(prim["indices"], f"{where} indices", ("SCALAR",), (5121, USHORT, UINT))[:, 0]
    else:
        F = np.arange(n)
    if len(F) % 3 or (len(F) and F.max() >= n):
        raise ValueError(f"{where}: indices must be a multiple of 3 and below the vertex count {n}")
    if skin_joints is None:
        return V, F.reshape(-1, 3), None, None
    sets = 0
    while f"JOINTS_{sets}" in attrs:
        sets += 1
    if sets == 0 or any(f"WEIGHTS_{s}" not in attrs for s in range(sets)) or f"WEIGHTS_{sets}" in attrs:
        raise ValueError(f"{where}: a skinned primitive needs matching JOINTS_0/WEIGHTS_0 (and _1, ...) attributes")
    J = np.hstack(
        [doc.accessor(attrs[f"JOINTS_{s}"], f"{where} JOINTS_{s}", ("VEC4",), (5121, USHORT)) for s in range(sets)]
    )
    W = np.hstack(
        [
            doc.accessor(attrs[f"WEIGHTS_{s}"], f"{where} WEIGHTS_{s}", ("VEC4",), (FLOAT, 5121, USHORT))
            for s in range(sets)
        ]
    )
    if len(J) != n or len(W) != n:
        raise ValueError(f"{where}: JOINTS/WEIGHTS have {len(J)}/{len(W)} entries, POSITION has {n}")
    if J.size and J.max() >= skin_joints:
        raise ValueError(f"{where}: JOINTS index {J.max()} is past the skin's {skin_joints} joints")
    off = np.abs(W.sum(axis=1) - 1.0)
    if off.size and off.max() > _WEIGHT_TOLERANCE:
        v = int(off.argmax())
        raise ValueError(
            f"{where}: WEIGHTS of vertex {v} sum to {W[v].sum():.6g}; weights must sum to 1 (+-{_WEIGHT_TOLERANCE})"
        )
    return V, F.reshape(-1, 3), J, W


def _global_rest(doc: _Document, i: int, parent: list[int]) -> np.ndarray:
    """The node's global rest transform (4, 4): the product of its ancestors' local T * R * S, float64."""
    out = np.eye(4)
    while i != -1:
        t, r, s = _node_trs(doc.json["nodes"][i], f"{doc.source}: node {i}")
        local = np.eye(4)
        local[:3, :3] = quaternion_xyzw_to_matrix(r / np.linalg.norm(r)) * s  # normalized, as glTF readers do
        local[:3, 3] = t
        out = local @ out
        i = parent[i]
    return out


def _mesh(doc: _Document, skinned: list[int], rigid: list[int], bone_of: dict[int, int], parent: list[int]):
    nodes = doc.json["nodes"]
    skins = list(dict.fromkeys(nodes[i]["skin"] for i in skinned))
    joints, inverse_bind, maps = _joint_table(doc, skins, bone_of)
    joints, inverse_bind = list(joints), list(inverse_bind)
    first_joint = {}  # bone -> its first joint
    for k, bone in enumerate(joints):
        first_joint.setdefault(bone, k)
    parts = []
    for i in sorted([*skinned, *rigid]):
        node = nodes[i]
        mesh = doc.item("meshes", node["mesh"], f"node {i}")
        if "skin" in node:
            n_joints = len(doc.json["skins"][node["skin"]]["joints"])
        else:
            # rigid: weight 1 on the nearest bone b at or above the node, with b's bind matrix when a used skin has
            # one (V then lies in the bind pose, as the skinned meshes' V does), else b's rest pose; V = bind(b) @
            # inv(global(b, rest)) @ global(node, rest) @ p, so that joint @ V = global(node, pose) @ p exactly, the
            # nodes between b and the node being unanimated
            b = i
            while b not in bone_of:
                b = parent[b]
            n_joints, rest_b = None, _global_rest(doc, b, parent)
            if bone_of[b] in first_joint:
                joint = first_joint[bone_of[b]]
            else:
                joint = first_joint[bone_of[b]] = len(joints)
                joints.append(bone_of[b])
                inverse_bind.append(np.linalg.inv(rest_b))
            place = np.linalg.inv(inverse_bind[joint]) @ np.linalg.inv(rest_b) @ _global_rest(doc, i, parent)
        for p, prim in enumerate(mesh.get("primitives", [])):
            where = f"{doc.source}: node {i} mesh {node['mesh']} ({mesh.get('name', '')}) primitive {p}"
            V, F, J, W = _primitive(doc, prim, n_joints, where)
            if n_joints is None:
                V = V.astype(np.float64) @ place[:3, :3].T + place[:3, 3]
                J = np.full((len(V), 4), joint, dtype=np.int64)
                W = np.zeros((len(V), 4))
                W[:, 0] = 1.0
            else:
                J = maps[node["skin"]][J]
            parts.append((V, F, J, W))
    if not parts:
        raise ValueError(f"{doc.source}: the skinned meshes have no primitives")
    k = max(J.shape[1] for _, _, J, _ in parts)
    offsets = np.cumsum([0] + [len(V) for V, _, _, _ in parts])
    return SkinnedMesh(
        V=_float_array(np.vstack([V for V, _, _, _ in parts])),
        F=_int_array(np.vstack([F + o for (_, F, _, _), o in zip(parts, offsets)])),
        J=_int_array(np.vstack([np.pad(J, ((0, 0), (0, k - J.shape[1]))) for _, _, J, _ in parts])),
        W=_float_array(np.vstack([np.pad(W, ((0, 0), (0, k - W.shape[1]))) for _, _, _, W in parts])),
        inverse_bind=_float_array(np.asarray(inverse_bind, dtype=np.float64).reshape(-1, 4, 4)),
        joints=tuple(joints),
        primitive_sizes=tuple((len(V), len(F)) for V, F, _, _ in parts),
    )


def _clips(doc: _Document, bone_of: dict[int, int]) -> tuple[AnimationClip, ...]:
    clips = []
    for a, anim in enumerate(doc.json.get("animations", [])):
        name = anim.get("name") or f"clip{a}"
        channels, seen = [], set()
        for c, channel in enumerate(anim.get("channels", [])):
            target = channel.get("target", {})
            node, path = target.get("node"), target.get("path")
            if node not in bone_of or path not in PATHS:
                continue
            where = f"{doc.source}: animation {a} ({name}) channel {c}"
            if (node, path) in seen:
                raise ValueError(f"{where}: node {node} has two {path!r} channels in one animation")
            seen.add((node, path))
            samplers, index = anim.get("samplers", []), channel.get("sampler")
            if not isinstance(index, int) or not 0 <= index < len(samplers):
                raise ValueError(f"{where}: sampler {index} does not exist ({len(samplers)} samplers)")
            sampler = samplers[index]
            interpolation = sampler.get("interpolation", "LINEAR")
            if interpolation not in INTERPOLATIONS:
                raise ValueError(f"{where}: interpolation {interpolation!r}, expected one of {INTERPOLATIONS}")
            times = doc.accessor(sampler["input"], f"{where} input", ("SCALAR",), (FLOAT,))[:, 0]
            if len(times) == 0 or np.any(np.diff(times) <= 0):
                raise ValueError(f"{where}: key times must be non-empty and strictly increasing")
            d = 4 if path == "rotation" else 3
            values = doc.accessor(sampler["output"], f"{where} output", (f"VEC{d}",), _FLOATS)
            keys = 3 * len(times) if interpolation == "CUBICSPLINE" else len(times)
            if len(values) != keys:
                raise ValueError(f"{where}: {len(values)} output values for {len(times)} keys ({interpolation})")
            if interpolation == "CUBICSPLINE":
                values = values.reshape(len(times), 3, d)
            channels.append(Channel(_float_array(times), _float_array(values), bone_of[node], path, interpolation))
        clips.append(AnimationClip(tuple(channels), name=name))
    return tuple(clips)


def _read_model(doc: _Document, name: str) -> RiggedModel:
    nodes = doc.json.get("nodes", [])
    skinned = [i for i, node in enumerate(nodes) if "mesh" in node and "skin" in node]
    if not skinned:
        raise ValueError(
            f"{doc.source}: no skinned mesh (no node has both 'mesh' and 'skin'); a rigged model is expected"
        )
    parent = _parents(doc)
    rigid = _rigid_nodes(doc, skinned, parent)
    skeleton, bone_of = _skeleton(doc, skinned, rigid, parent)
    mesh = _mesh(doc, skinned, rigid, bone_of, parent)
    return RiggedModel(mesh=mesh, skeleton=skeleton, clips=_clips(doc, bone_of), name=name)


def convert_with_assimp(path: str | Path, out: str | Path | None = None) -> Path:
    """Convert a model file (FBX, COLLADA, ... anything assimp imports) to GLB with the assimp CLI.

    Runs ``assimp export path out -f glb2``. Needs the ``assimp`` executable on PATH (Debian package
    ``assimp-utils``).

    Args:
        path: str or Path, the input model file.
        out: str or Path of the GLB to write; default ``<stem>.glb`` in a new temporary directory,
            which the caller owns.

    Returns:
        The Path of the written GLB.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        RuntimeError: the ``assimp`` executable is not installed.
        ValueError: assimp could not convert the file (its output is in the message).
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file {path}")
    exe = shutil.which("assimp")
    if exe is None:
        raise RuntimeError(
            f"path: reading {path.suffix or 'this'} files needs the assimp command-line tool, which is not on PATH; "
            "install the Debian package assimp-utils (sudo apt-get install assimp-utils)"
        )
    out = Path(tempfile.mkdtemp(prefix="jaxcga-assimp-")) / f"{path.stem}.glb" if out is None else Path(out)
    proc = subprocess.run(
        [exe, "export", str(path), str(out), "-f", "glb2"],
        check=False,
        capture_output=True,
        text=True,
        errors="replace",
    )
    if proc.returncode != 0 or not out.is_file():
        log = (proc.stderr + proc.stdout).strip()[-2000:]
        raise ValueError(f"path: assimp could not convert {path} to glTF (exit code {proc.returncode}):\n{log}")
    return out


def load_model(path: str | Path, *, weld: bool = False) -> RiggedModel:
    """Read a rigged model: a glTF 2.0 file (``.gltf`` or ``.glb``), or FBX / COLLADA / ... through assimp.

    Every node with both ``mesh`` and ``skin``, and every rigid attachment (a node with a ``mesh`` and no
    ``skin`` that is a joint of a used skin or a descendant of one: it moves with the skeleton), contributes its
    primitives, in node order, to one SkinnedMesh (see ``SkinnedMesh``). A rigid attachment's vertices get weight 1
    on the nearest bone at or above its node (animated nodes in between become bones), placed in that bone's bind
    pose so that they follow the node exactly, as three.js draws them. Mesh nodes outside the skeleton (static
    scenery) are left out; a file with no skinned mesh at all is refused. Morph targets: the base positions are
    read, the weights ignored. k = 4 influences per vertex, 8 with JOINTS_1/WEIGHTS_1 (4 per
    set in general; primitives with fewer sets get zero weights). Joints are the union of (bone,
    inverse bind matrix) pairs of the skins used (identity when a skin has no inverseBindMatrices).
    Weights are kept exactly as stored (no renormalization). The skeleton holds the joints, the animated
    nodes at or above rigid attachments, and all their ancestors; animations become AnimationClips (named
    from the file, else ``clip{i}``), with CUBICSPLINE values of shape (k, 3, d). Float arrays are float64
    under x64 (else float32), integer arrays int32. Normalized integer data is dequantized. ``name`` is the file's stem.

    Args:
        path: str or Path of the model file.
        weld: merge duplicated vertices with ``weld`` (FBX exports split vertices along UV seams).

    Returns:
        The RiggedModel.

    Raises:
        FileNotFoundError: ``path`` or a buffer file it refers to does not exist.
        ValueError: the file is not glTF 2.0 or is malformed, has no skinned mesh, a float accessor or
            node transform with a NaN or infinity (named), a primitive mode other than TRIANGLES, weights
            whose rows do not sum to 1 within 1e-2, a node matrix with a shear, non-increasing key times; or
            assimp could not convert it.
        RuntimeError: a non-glTF file was given and the assimp executable is not installed.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no such file {path}")
    if path.suffix.lower() in (".gltf", ".glb"):
        model = _read_model(_Document(path, str(path)), path.stem)
    else:
        with tempfile.TemporaryDirectory(prefix="jaxcga-assimp-") as tmp:
            glb = convert_with_assimp(path, Path(tmp) / "model.glb")
            model = _read_model(_Document(glb, f"{path} (converted by assimp)"), path.stem)
    if not weld:
        return model
    return RiggedModel(mesh=_weld(model.mesh), skeleton=model.skeleton, clips=model.clips, name=model.name)


# ----------------------------------------------------------------------------------------------- welding


def _unique_rows(rows: np.ndarray, decimals: int) -> tuple[np.ndarray, np.ndarray]:
    """(first, inverse): the first row of each group of rows equal after rounding to ``decimals`` digits, in order of
    first occurrence, and each row's group (``rows[first][inverse]`` is ``rows`` rounded). The rounding is
    trimesh.grouping.float_to_int's (scaled, nudged down by 1e-6 so that halves do not go either way); numpy's
    unique instead of trimesh, whose import takes longer than a model's load."""
    as_int = np.round(rows * 10.0**decimals - 1e-6).astype(np.int64)
    _, first, inverse = np.unique(as_int, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)  # the groups renumbered by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return first[order], rank[inverse.reshape(-1)]


def weld(mesh: SkinnedMesh, decimals: int = 8) -> SkinnedMesh:
    """Merge vertices with the same position, joints and weights (host-side, numpy).

    Rows ``[V, J, W]`` are compared after rounding to ``decimals`` digits (as trimesh.grouping.unique_rows does),
    so vertices that straddle a rounding boundary stay apart; joints and weights must match in the
    same slot order. The first vertex of each group is kept, with its exact values, in order of first
    occurrence. F is re-indexed; faces whose corners become the same vertex are dropped (faces that
    keep three distinct vertices are kept, even if flat). Unreferenced vertices are kept. All
    primitives merge into one: ``primitive_sizes`` becomes ``((n', m'),)``.

    Args:
        mesh: SkinnedMesh with V (n, 3), F (m, 3), J (n, k), W (n, k).
        decimals: number of decimal digits of the comparison.

    Returns:
        The welded SkinnedMesh, V (n', 3), F (m', 3), J (n', k), W (n', k); ``inverse_bind`` and
        ``joints`` unchanged.
    """
    V, F, J, W = (np.asarray(a) for a in (mesh.V, mesh.F, mesh.J, mesh.W))
    F_dtype = F.dtype
    if V.shape[0] == 0:
        return mesh
    first, inverse = _unique_rows(np.hstack([V, J, W]).astype(np.float64), decimals)
    F = inverse[F]
    F = F[(F[:, 0] != F[:, 1]) & (F[:, 1] != F[:, 2]) & (F[:, 0] != F[:, 2])]
    # device_put of numpy arrays, as the reader's (_float_array): no compiled copy per array and shape
    return SkinnedMesh(
        V=jax.device_put(V[first]),
        F=jax.device_put(F.astype(F_dtype)),
        J=jax.device_put(J[first]),
        W=jax.device_put(W[first]),
        inverse_bind=mesh.inverse_bind,
        joints=mesh.joints,
        primitive_sizes=((len(first), len(F)),),
    )


_weld = weld  # load_model's ``weld`` keyword shadows the function


# ----------------------------------------------------------------------------------------------- writing


def save_model(model: RiggedModel, path: str | Path) -> None:
    """Write a RiggedModel as glTF 2.0: ``.glb``, or ``.gltf`` with a sibling ``<stem>.bin``.

    Bones become nodes 0..b-1 (name, translation, rotation, scale, children); a mesh node named
    ``model.name`` at the scene root, without a transform, holds one mesh with one primitive per
    ``mesh.primitive_sizes`` entry (one when empty) and the skin (``joints`` = ``mesh.joints``,
    ``inverseBindMatrices``). Attributes: POSITION (float, with min/max), indices (UNSIGNED_INT),
    JOINTS_s (UNSIGNED_SHORT) and WEIGHTS_s (FLOAT), one set per 4 influences (k is padded to a
    multiple of 4 with zero weights). Every clip with channels becomes an animation (a clip without
    channels is not written: glTF animations need one); samplers keep their interpolation.

    Buffer data (V, W, inverse_bind, key times and values) is written as float32: a float64 model is
    rounded once, a model read from a file round-trips exactly. Node TRS go into the JSON at full
    double precision. Reading back gives the bones in depth-first order, which is the order of every
    loaded skeleton; another topological order comes back reordered.

    The file (and a .gltf's buffer) is written to a temporary file beside it and renamed into place when
    complete (``_jaxcga_shared.output.replacing``): a failed write leaves an existing file as it was.

    Args:
        model: RiggedModel with mesh V (n, 3), F (m, 3), J (n, k), W (n, k), inverse_bind (j, 4, 4),
            skeleton translation (b, 3), rotation (b, 4), scale (b, 3), clips' times (t,) and values
            (t, d) or (t, 3, d).
        path: str or Path ending in ``.glb`` or ``.gltf``.
    Returns:
        None; the file is in place.
    Raises:
        ValueError: wrong suffix; ``mesh.joints`` repeats a bone (two inverse bind matrices for one
            node cannot be one glTF skin); non-finite values; key times not increasing in float32;
            faces crossing ``primitive_sizes``; an empty primitive; a ``<stem>.bin`` beside a .gltf
            ``path`` that is not that file's buffer (``buffer_file``).
        OSError: the file cannot be written (an existing one is left as it was).
    """
    write_files(model_files(model, path))


def save_models(models: Mapping[str | Path, RiggedModel]) -> None:
    """Write several RiggedModels, ``{path: model}``, as one unit (the two halves of a cut): every file is written
    beside its target first, and none replaces an existing file unless all were written.

    Args:
        models: ``{path: model}``, each as ``save_model``'s ``path`` and ``model``; two paths that name the same
            file are refused.
    Returns:
        None; every file is in place.
    Raises:
        ValueError: as ``save_model``, for any of the models; two paths naming the same file.
        OSError: a file cannot be written (every existing one is left as it was).
    """
    files: dict[Path, bytes | str] = {}
    for path, model in models.items():
        for file, data in model_files(model, path).items():
            if any(os.path.realpath(file) == os.path.realpath(other) for other in files):
                raise ValueError(f"models: {file} is written twice; give each model its own file name")
            files[file] = data
    write_files(files)
