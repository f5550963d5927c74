"""An independent reference for glTF 2.0 skinning, written from the specification in plain numpy and
scipy (no code shared with ``deform``): accessors, node transforms, sampler interpolation, joint
matrices ``global(joint) @ inverseBindMatrix`` and linear blend skinning in world space; a mesh without a skin on a
node that is a joint of a used skin, or below one, is drawn rigidly with its node's world transform."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

from tests.shared import read_gltf

_COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class Reference:
    def __init__(self, path):
        self.gltf = read_gltf(path)
        blob = self.gltf.binary_blob()
        if blob is None:
            raise ValueError(f"path: {path} has no binary buffer; the reference reads .glb files")
        self.blob: bytes = blob

    def accessor(self, index):
        acc = self.gltf.accessors[index]
        view = self.gltf.bufferViews[acc.bufferView]
        dtype = np.dtype(_COMPONENTS[acc.componentType])
        width = _WIDTH[acc.type]
        start = (view.byteOffset or 0) + (acc.byteOffset or 0)
        stride = view.byteStride or dtype.itemsize * width
        rows = [np.frombuffer(self.blob, dtype, width, start + i * stride) for i in range(acc.count)]
        out = np.array(rows, dtype=np.float64 if dtype == np.float32 else dtype)
        if acc.normalized:
            out = np.maximum(out / np.iinfo(dtype).max, -1.0)
        return out

    def local(self, i, overrides=None):
        node = self.gltf.nodes[i]
        if node.matrix is not None:
            return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T
        t = np.array(node.translation or [0, 0, 0], float)
        r = np.array(node.rotation or [0, 0, 0, 1], float)
        s = np.array(node.scale or [1, 1, 1], float)
        if overrides:
            t = overrides.get((i, "translation"), t)
            r = overrides.get((i, "rotation"), r)
            s = overrides.get((i, "scale"), s)
        m = np.eye(4)
        m[:3, :3] = Rotation.from_quat(r).as_matrix() * s
        m[:3, 3] = t
        return m

    def globals(self, overrides=None):
        parent = {c: p for p, n in enumerate(self.gltf.nodes) for c in (n.children or [])}
        out = {}

        def glob(i):
            if i not in out:
                m = self.local(i, overrides)
                out[i] = glob(parent[i]) @ m if i in parent else m
            return out[i]

        for i in range(len(self.gltf.nodes)):
            glob(i)
        return out

    def sample(self, animation, t):
        overrides = {}
        anim = self.gltf.animations[animation]
        for ch in anim.channels:
            if ch.target.path not in ("translation", "rotation", "scale"):
                continue
            sampler = anim.samplers[ch.sampler]
            times = self.accessor(sampler.input).ravel()
            values = self.accessor(sampler.output)
            tc = np.clip(t, times[0], times[-1])
            k = int(np.clip(np.searchsorted(times, tc, side="right") - 1, 0, max(len(times) - 2, 0)))
            if len(times) == 1:
                v = values[0]
            elif sampler.interpolation == "STEP":
                v = values[k + 1] if tc >= times[k + 1] else values[k]
            elif ch.target.path == "rotation":
                v = Slerp(times[k : k + 2], Rotation.from_quat(values[k : k + 2]))([tc]).as_quat()[0]
            else:
                a = (tc - times[k]) / (times[k + 1] - times[k])
                v = (1 - a) * values[k] + a * values[k + 1]
            overrides[(ch.target.node, ch.target.path)] = v
        return overrides

    def joint_matrices(self, animation=None, t=0.0, skin=0):
        """World-space joint matrices ``global(joint) @ inverseBindMatrix`` (j, 4, 4) of one skin."""
        overrides = self.sample(animation, t) if animation is not None else None
        g = self.globals(overrides)
        skin = self.gltf.skins[skin]
        joints = skin.joints or []
        if skin.inverseBindMatrices is None:  # the specification: identity matrices
            ibm = np.broadcast_to(np.eye(4), (len(joints), 4, 4))
        else:
            ibm = self.accessor(skin.inverseBindMatrices).reshape(-1, 4, 4).transpose(0, 2, 1)
        return np.stack([g[j] @ ibm[k] for k, j in enumerate(joints)])

    def rigid_nodes(self):
        """Nodes with a mesh and no skin that are, or descend from, a joint of a skin some mesh node uses."""
        nodes = self.gltf.nodes
        joints = {
            j for n in nodes if n.mesh is not None and n.skin is not None for j in self.gltf.skins[n.skin].joints or []
        }
        parent = {c: p for p, n in enumerate(nodes) for c in (n.children or [])}
        out = set()
        for i, n in enumerate(nodes):
            if n.mesh is None or n.skin is not None:
                continue
            j = i
            while j not in joints and j in parent:
                j = parent[j]
            if j in joints:
                out.add(i)
        return out

    def skin(self, animation=None, t=0.0):
        """World-space positions of every skinned primitive (linear blend skinning) and every rigid primitive
        (``global(node) @ position``), concatenated in node order."""
        overrides = self.sample(animation, t) if animation is not None else None
        g = self.globals(overrides)
        rigid = self.rigid_nodes()
        out = []
        for i, node in enumerate(self.gltf.nodes):
            if node.mesh is None or (node.skin is None and i not in rigid):
                continue
            if node.skin is not None:
                joint = self.joint_matrices(animation, t, node.skin)
            for prim in self.gltf.meshes[node.mesh].primitives:
                v = self.accessor(prim.attributes.POSITION)
                if node.skin is None:
                    out.append(v @ g[i][:3, :3].T + g[i][:3, 3])
                    continue
                j = self.accessor(prim.attributes.JOINTS_0).astype(int)
                w = self.accessor(prim.attributes.WEIGHTS_0)
                blended = np.einsum("nk,nkij->nij", w, joint[j])
                out.append(np.einsum("nij,nj->ni", blended[:, :3, :3], v) + blended[:, :3, 3])
        return np.concatenate(out)
