"""Rigged-model bundles: skeleton, animation clips, skinned mesh (cut/tear/drill paper sec. 3).

Plain arrays with libigl names (``V``, ``F``, ``W``, ``J``) inside ``equinox.Module`` bundles;
names, parents and other topology are static fields, so a bundle passes through ``jit``/``vmap``
unchanged. The conventions follow glTF 2.0 (section "Skins" and "Animations"):

* quaternions are stored in glTF order ``(x, y, z, w)``;
* a bone's local transform is ``T * R * S`` (translation, rotation, scale);
* the joint matrix of joint ``i`` is ``global(bone of i) @ inverse_bind[i]`` and a skinned vertex is
  ``sum_k W[:, k] * joint_matrix[J[:, k]] @ [V, 1]``, in world space: the transform of the node that
  holds the mesh is ignored.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from deform._gltf_write import model_files

PATHS = ("translation", "rotation", "scale")
INTERPOLATIONS = ("LINEAR", "STEP", "CUBICSPLINE")
_WIDTH = {"translation": 3, "rotation": 4, "scale": 3}


def _shape_error(name: str, expected: str, got) -> ValueError:
    return ValueError(f"{name}: expected shape {expected}, got {tuple(got)}")


class Skeleton(eqx.Module):
    """Bones in topological order (every parent before its children) with their rest local TRS.

    Attributes:
        translation: (b, 3) rest translation of each bone relative to its parent.
        rotation: (b, 4) rest rotation, unit quaternion in glTF order (x, y, z, w).
        scale: (b, 3) rest scale.
        parents: static, parent index per bone, -1 for a root.
        names: static, one name per bone (unique).
    """

    translation: Float[Array, "b 3"]
    rotation: Float[Array, "b 4"]
    scale: Float[Array, "b 3"]
    parents: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        b = len(self.parents)
        if len(self.names) != b:
            raise ValueError(f"names: expected {b} names (one per bone), got {len(self.names)}")
        if len(set(self.names)) != b:
            raise ValueError("names: bone names must be unique")
        for i, p in enumerate(self.parents):
            if not -1 <= p < i:
                raise ValueError(f"parents: bone {i} has parent {p}; expected -1 or an index < {i} (topological order)")
        for name, width in (("translation", 3), ("rotation", 4), ("scale", 3)):
            shape = np.shape(getattr(self, name))
            if shape != (b, width):
                raise _shape_error(name, f"({b}, {width})", shape)

    @property
    def num_bones(self) -> int:
        return len(self.parents)

    def index(self, name: str) -> int:
        """Index of the bone called ``name`` (ValueError listing the names when absent).

        Args:
            name: the bone's name."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ValueError(f"name: no bone called {name!r}; bones are {list(self.names)}") from None


class Channel(eqx.Module):
    """One animated property of one bone (a glTF animation channel with its sampler).

    Attributes:
        times: (k,) strictly increasing key times in seconds.
        values: (k, d) key values, d = 3 (translation, scale) or 4 (rotation, glTF quaternion order);
            for CUBICSPLINE (k, 3, d): in-tangent, value, out-tangent per key (glTF layout).
        bone: static, index of the animated bone in the skeleton.
        path: static, "translation", "rotation" or "scale".
        interpolation: static, "LINEAR", "STEP" or "CUBICSPLINE".
    """

    times: Float[Array, " k"]
    values: Float[Array, "k ..."]
    bone: int = eqx.field(static=True)
    path: str = eqx.field(static=True)
    interpolation: str = eqx.field(static=True)

    def __check_init__(self):
        if self.path not in PATHS:
            raise ValueError(f"path: expected one of {PATHS}, got {self.path!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"interpolation: expected one of {INTERPOLATIONS}, got {self.interpolation!r}")
        k = np.shape(self.times)
        if len(k) != 1 or k[0] < 1:
            raise _shape_error("times", "(k,) with k >= 1", k)
        d = _WIDTH[self.path]
        expected = (k[0], 3, d) if self.interpolation == "CUBICSPLINE" else (k[0], d)
        if np.shape(self.values) != expected:
            raise _shape_error(f"values ({self.path}, {self.interpolation})", str(expected), np.shape(self.values))


class AnimationClip(eqx.Module):
    """An animation clip: channels over the skeleton's bones (morph-target weights are not kept).

    Attributes:
        channels: tuple of Channel; at most one per (bone, path).
        name: static clip name.
    """

    channels: tuple[Channel, ...]
    name: str = eqx.field(static=True, default="clip")

    def __check_init__(self):
        seen = set()
        for c in self.channels:
            key = (c.bone, c.path)
            if key in seen:
                raise ValueError(f"channels: bone {c.bone} has two {c.path!r} channels")
            seen.add(key)

    @property
    def start(self) -> float:
        return float(min(np.asarray(c.times)[0] for c in self.channels)) if self.channels else 0.0

    @property
    def end(self) -> float:
        return float(max(np.asarray(c.times)[-1] for c in self.channels)) if self.channels else 0.0


class SkinnedMesh(eqx.Module):
    """A triangle mesh bound to joints (all skinned primitives of a file, concatenated in file order).

    Attributes:
        V: (n, 3) bind-pose vertex positions (glTF POSITION, in the mesh's own space).
        F: (m, 3) triangle vertex indices.
        J: (n, k) joint indices per vertex into ``joints`` (k = 4, or 8 with JOINTS_1/WEIGHTS_1).
        W: (n, k) weights per vertex, summing to one.
        inverse_bind: (j, 4, 4) inverse bind matrix per joint.
        joints: static, skeleton bone index of each joint.
        primitive_sizes: static, (vertex count, face count) of each primitive in file order.
    """

    V: Float[Array, "n 3"]
    F: Int[Array, "m 3"]
    J: Int[Array, "n k"]
    W: Float[Array, "n k"]
    inverse_bind: Float[Array, "j 4 4"]
    joints: tuple[int, ...] = eqx.field(static=True)
    primitive_sizes: tuple[tuple[int, int], ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        n = np.shape(self.V)[0] if np.ndim(self.V) == 2 else -1
        if np.shape(self.V) != (n, 3):
            raise _shape_error("V", "(n, 3)", np.shape(self.V))
        if np.ndim(self.F) != 2 or np.shape(self.F)[1] != 3:
            raise _shape_error("F", "(m, 3)", np.shape(self.F))
        if np.ndim(self.J) != 2 or np.shape(self.J)[0] != n:
            raise _shape_error("J", f"({n}, k)", np.shape(self.J))
        if np.shape(self.W) != np.shape(self.J):
            raise _shape_error("W", str(tuple(np.shape(self.J))), np.shape(self.W))
        j = len(self.joints)
        if np.shape(self.inverse_bind) != (j, 4, 4):
            raise _shape_error("inverse_bind", f"({j}, 4, 4)", np.shape(self.inverse_bind))
        if self.primitive_sizes:
            nv = sum(s[0] for s in self.primitive_sizes)
            nf = sum(s[1] for s in self.primitive_sizes)
            if (nv, nf) != (n, np.shape(self.F)[0]):
                raise ValueError(f"primitive_sizes: sizes add up to {(nv, nf)}, mesh has {(n, np.shape(self.F)[0])}")

    @property
    def num_vertices(self) -> int:
        return int(np.shape(self.V)[0])

    @property
    def num_joints(self) -> int:
        return len(self.joints)

    def with_normalized_weights(self) -> SkinnedMesh:
        """The same mesh with every weight row divided by its sum (files often store sums of
        0.998..1.002; the glTF specification asks for 1)."""
        total = jnp.sum(self.W, axis=-1, keepdims=True)
        if bool(jnp.any(total <= 0)):
            raise ValueError("W: a vertex has no positive weight; cannot normalize")
        return eqx.tree_at(lambda m: m.W, self, self.W / total)


class RiggedModel(eqx.Module):
    """A skinned mesh with its skeleton and animation clips.

    Attributes:
        mesh: the SkinnedMesh.
        skeleton: the Skeleton (joints and their non-joint ancestors, topologically ordered).
        clips: tuple of AnimationClip (possibly empty).
        name: static model name.
    """

    mesh: SkinnedMesh
    skeleton: Skeleton
    clips: tuple[AnimationClip, ...] = ()
    name: str = eqx.field(static=True, default="model")

    def __check_init__(self):
        b = self.skeleton.num_bones
        if any(not 0 <= j < b for j in self.mesh.joints):
            raise ValueError(f"mesh.joints: every joint must be a bone index in [0, {b})")
        for clip in self.clips:
            if any(not 0 <= c.bone < b for c in clip.channels):
                raise ValueError(f"clips: clip {clip.name!r} animates a bone outside [0, {b})")

    def to_glb(self) -> bytes:
        """The model as a glTF binary (.glb), as ``deform.save_model`` writes it: for ``deform.view(model)``
        and anything else that takes glTF bytes."""
        (data,) = model_files(self, "model.glb").values()
        assert isinstance(data, bytes)
        return data

    def clip(self, name: str | int = 0) -> AnimationClip:
        """The clip called ``name`` (or at that position).

        Args:
            name: the clip's name, or its index in ``clips``."""
        # errors say "clip": every public function that takes one (skin_model, sample_pose, ...) calls it so
        if isinstance(name, int):
            if not -len(self.clips) <= name < len(self.clips):
                raise ValueError(f"clip: model has {len(self.clips)} clips, no clip {name}")
            return self.clips[name]
        for c in self.clips:
            if c.name == name:
                return c
        raise ValueError(f"clip: no clip called {name!r}; clips are {[c.name for c in self.clips]}")
