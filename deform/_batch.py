"""Batches of different rigged models: packed to shared capacities, skinned under one jit, split over devices.

JAX has no ragged arrays, so a batch of characters with different vertex, bone, joint, influence, clip, channel
and key counts is padded to shared capacities. The layout keeps padded work small where it costs:

* vertices of all models are concatenated along one axis per *block* (the packed form of PyTorch3D's ``Meshes``),
  with joint indices offset into one joint table per block, so the per-vertex pass (the skinning kernels of
  ``_skinning``, unchanged) pays only for the rounding of the block's total vertex count, not for the largest
  model;
* per-model rig data (bones, joints, clips and their channel groups) are padded to the largest model; that work
  is per bone, not per vertex;
* capacities are rounded up to levels (``capacity``: four per octave) so that another batch of similar size has
  the same shapes and reuses the compiled function; ``pack_models(..., at_least=packed.capacities)`` forces it.

A block is the unit of distribution: models are spread over ``blocks`` blocks with balanced vertex counts, and
``skin_packed(..., mesh=mesh)`` maps the blocks over a ``jax.sharding.Mesh`` axis ``"models"`` (and the frames
over an axis ``"time"``) with ``jax.shard_map``: every device skins whole models, and the host calls of the value
checks stay on the device that raised them. With several processes (``jax.distributed``) each process holds the
blocks of its devices (``unpack_local``).

Padding rows are inert: a padded vertex is bound with weight one to a joint of its block, a padded influence has
weight zero, a padded bone is an identity with no parent, a padded channel writes to a bone index past the
skeleton (dropped by the scatter). Each model is computed by the functions ``skin_model`` uses, so the unpacked
results equal skinning each model alone.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_choice, plain_errors
from deform import _pose, _rig
from deform._model import PATHS, RiggedModel

MODEL_AXIS = "models"
TIME_AXIS = "time"
_IDENTITY_TRS = {"translation": (0.0, 0.0, 0.0), "rotation": (0.0, 0.0, 0.0, 1.0), "scale": (1.0, 1.0, 1.0)}


def capacity(n: int) -> int:
    """The smallest level >= n: every count up to 8, then four levels per octave (5, 6, 7, 8 times a power of
    two), so that padding adds at most a quarter.

    Args:
        n: a count >= 0.

    Returns:
        The level, >= n.

    Examples:
        >>> import deform
        >>> deform.capacity(9), deform.capacity(100)
        (10, 112)
    """
    if n <= 8:
        return max(int(n), 1)
    step = 1 << ((int(n) - 1).bit_length() - 3)
    return -(-int(n) // step) * step


class Capacities(NamedTuple):
    """The padded sizes of a packed batch: equal capacities give equal array shapes (one compiled function).

    Attributes:
        blocks: blocks (devices along the model axis).
        models: model slots per block.
        vertices: vertex slots per block (all its models' vertices, concatenated).
        influences: joint influences per vertex.
        bones: bones per model.
        joints: joints per model.
        clips: clips per model.
        channels: per channel group ``(path, interpolation, channels, keys)``.
    """

    blocks: int
    models: int
    vertices: int
    influences: int
    bones: int
    joints: int
    clips: int
    channels: tuple[tuple[str, str, int, int], ...]

    def union(self, other: Capacities) -> Capacities:
        """The larger of two capacities in every size (the channel groups of both)."""
        if self.blocks != other.blocks:
            raise ValueError(f"at_least: packed for {other.blocks} blocks, asked for {self.blocks}")
        groups = {(p, i): (c, k) for p, i, c, k in self.channels}
        for p, i, c, k in other.channels:
            c0, k0 = groups.get((p, i), (0, 0))
            groups[(p, i)] = (max(c, c0), max(k, k0))
        return Capacities(
            blocks=self.blocks,
            models=max(self.models, other.models),
            vertices=max(self.vertices, other.vertices),
            influences=max(self.influences, other.influences),
            bones=max(self.bones, other.bones),
            joints=max(self.joints, other.joints),
            clips=max(self.clips, other.clips),
            channels=tuple((p, i, c, k) for (p, i), (c, k) in sorted(groups.items())),
        )


class PackedRigs(eqx.Module):
    """The arrays of a packed batch; leading axes (blocks, models per block) for per-model data and (blocks,
    vertices per block) for per-vertex data.

    Attributes:
        V: (D, N, 3) bind-pose positions, the block's models concatenated.
        J: (D, N, K) joint indices into the block's joint table (``slot * joints + joint``).
        W: (D, N, K) weights.
        parents: (D, M, B) parent of each bone, -1 for a root.
        translation, rotation, scale: (D, M, B, 3 | 4 | 3) rest TRS of each bone.
        joint_bones: (D, M, Jc) bone of each joint.
        inverse_bind: (D, M, Jc, 4, 4) inverse bind matrices.
        has_clip: (D, M) whether the model has a clip (without one it is posed at rest, as ``skin_model``).
        channel_times, channel_values, channel_counts, channel_bones: one array per channel group, with
            axes (D, M, clips, channels, keys, ...) (counts and bones without the key axis).
        groups: static, the channel groups' ``(path, interpolation)``.
    """

    V: Float[Array, "D N 3"]
    J: Int[Array, "D N K"]
    W: Float[Array, "D N K"]
    parents: Int[Array, "D M B"]
    translation: Float[Array, "D M B 3"]
    rotation: Float[Array, "D M B 4"]
    scale: Float[Array, "D M B 3"]
    joint_bones: Int[Array, "D M Jc"]
    inverse_bind: Float[Array, "D M Jc 4 4"]
    has_clip: Array
    channel_times: tuple[Array, ...]
    channel_values: tuple[Array, ...]
    channel_counts: tuple[Array, ...]
    channel_bones: tuple[Array, ...]
    groups: tuple[tuple[str, str], ...] = eqx.field(static=True)


class PackedModels(eqx.Module):
    """Models of different sizes packed to shared capacities (``pack_models``): a pytree of arrays (``rigs``)
    and where every model lies in it (host data).

    Attributes:
        rigs: the PackedRigs.
        capacities: static, the Capacities.
        names: static, the models' names in the order given.
        block: static, the block of each model.
        slot: static, the model slot of each model in its block.
        vertex_offset: static, the first vertex slot of each model in its block.
        vertex_count: static, each model's vertex count.
        influence_count: static, each model's joint influences per vertex.
        clip_names: static, each model's clip names.
        clip_ranges: static, each model's clips' (start, end) times.
        bone_count: static, each model's bone count.
    """

    rigs: PackedRigs
    capacities: Capacities = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)
    block: tuple[int, ...] = eqx.field(static=True)
    slot: tuple[int, ...] = eqx.field(static=True)
    vertex_offset: tuple[int, ...] = eqx.field(static=True)
    vertex_count: tuple[int, ...] = eqx.field(static=True)
    influence_count: tuple[int, ...] = eqx.field(static=True)
    clip_names: tuple[tuple[str, ...], ...] = eqx.field(static=True)
    clip_ranges: tuple[tuple[tuple[float, float], ...], ...] = eqx.field(static=True)
    bone_count: tuple[int, ...] = eqx.field(static=True)

    @property
    def num_models(self) -> int:
        return len(self.names)

    @property
    def padding(self) -> float:
        """Padded per-vertex work over real work: vertex-influence slots of the packed batch over those of
        the models (the per-vertex pass is the cost that grows with the models)."""
        c = self.capacities
        real = sum(n * k for n, k in zip(self.vertex_count, self.influence_count, strict=True))
        return c.blocks * c.vertices * c.influences / real

    def clip_indices(self, clip: int | str | npt.ArrayLike = 0) -> np.ndarray:
        """Each model's clip index (M,) for ``clip``: one index or name for all, or one per model. A model without
        clips takes index 0 (it is posed at rest).

        Args:
            clip: a clip index or name, or a sequence of them (one per model)."""
        clips = [clip] * self.num_models if isinstance(clip, (int, str, np.integer)) else list(clip)  # type: ignore[arg-type]
        if len(clips) != self.num_models:
            raise ValueError(f"clip: expected one clip or {self.num_models} (one per model), got {len(clips)}")
        out = np.zeros(self.num_models, np.int32)
        for m, (c, names) in enumerate(zip(clips, self.clip_names, strict=True)):
            if not names:
                if c not in (0, -1):
                    raise ValueError(f"clip: model {m} ({self.names[m]!r}) has no clip, asked for {c!r}")
                continue
            if isinstance(c, str):
                if c not in names:
                    raise ValueError(f"clip: model {m} ({self.names[m]!r}) has no clip {c!r}; clips are {list(names)}")
                out[m] = names.index(c)
            elif not -len(names) <= int(c) < len(names):
                raise ValueError(f"clip: model {m} ({self.names[m]!r}) has {len(names)} clips, no clip {c}")
            else:
                out[m] = int(c) % len(names)
        return out

    def frame_times(self, frames: int, clip: int | str | ArrayLike = 0) -> np.ndarray:
        """(M, frames) times spread evenly over each model's clip (zeros for a model without clips).

        Args:
            frames: frames per model (>= 1).
            clip: the clip of each model (``clip_indices``)."""
        if not isinstance(frames, (int, np.integer)) or frames < 1:
            raise ValueError(f"frames: expected an int >= 1, got {frames!r}")
        dtype = np.asarray(self.rigs.V).dtype
        times = np.zeros((self.num_models, int(frames)), dtype)
        for m, c in enumerate(self.clip_indices(clip)):
            if self.clip_ranges[m]:
                start, end = self.clip_ranges[m][c]
                times[m] = np.linspace(start, end, int(frames), dtype=dtype)
        return times

    def unpack_local(self, positions: jax.Array | np.ndarray) -> dict[int, np.ndarray]:
        """The frames (T, n, 3) of every model whose block lies on this process's devices, by model index, from
        the output of ``skin_packed`` (all models in one process).

        Args:
            positions: (D, T, N, 3) positions from ``skin_packed``."""
        c = self.capacities
        if np.ndim(positions) != 4 or np.shape(positions)[0] != c.blocks or np.shape(positions)[2:] != (c.vertices, 3):
            raise ValueError(
                f"positions: expected shape ({c.blocks}, T, {c.vertices}, 3) from skin_packed, "
                f"got {np.shape(positions)}"
            )
        frames = np.shape(positions)[1]
        blocks: dict[int, np.ndarray] = {}
        if isinstance(positions, jax.Array) and not positions.is_fully_addressable:
            pieces: dict[int, dict[int, np.ndarray]] = {}
            for shard in positions.addressable_shards:
                if shard.replica_id:
                    continue
                data = np.asarray(shard.data)
                first_block = shard.index[0].start or 0
                first_frame = shard.index[1].start or 0
                for i in range(data.shape[0]):
                    pieces.setdefault(first_block + i, {})[first_frame] = data[i]
            for b, by_frame in pieces.items():
                stacked = np.concatenate([by_frame[f] for f in sorted(by_frame)], axis=0)
                if stacked.shape[0] == frames:
                    blocks[b] = stacked
        else:
            host = np.asarray(positions)
            blocks = {b: host[b] for b in range(c.blocks)}
        return {
            m: blocks[b][:, o : o + n]
            for m, (b, o, n) in enumerate(zip(self.block, self.vertex_offset, self.vertex_count, strict=True))
            if b in blocks
        }

    def unpack(self, positions: jax.Array | np.ndarray) -> list[np.ndarray]:
        """The frames (T, n, 3) of every model, in the order given to ``pack_models``.

        Args:
            positions: (D, T, N, 3) positions from ``skin_packed`` (on this process's devices: with several
                processes use ``unpack_local``)."""
        local = self.unpack_local(positions)
        if len(local) != self.num_models:
            raise ValueError("positions: some blocks lie on other processes' devices; use unpack_local")
        return [local[m] for m in range(self.num_models)]


def _balanced_blocks(vertex_counts: list[int], blocks: int) -> list[list[int]]:
    """Models spread over blocks with balanced vertex totals (largest first to the lightest block), each block's
    models in the order given."""
    load = [0] * blocks
    members: list[list[int]] = [[] for _ in range(blocks)]
    for m in sorted(range(len(vertex_counts)), key=lambda m: (-vertex_counts[m], m)):
        b = min(range(blocks), key=lambda b: (load[b], len(members[b]), b))
        load[b] += vertex_counts[m]
        members[b].append(m)
    return [sorted(ms) for ms in members]


def _check_models(models: Sequence[RiggedModel] | RiggedModel) -> list[RiggedModel]:
    models = list(models) if not isinstance(models, RiggedModel) else [models]
    if not models:
        raise ValueError("models: expected at least one RiggedModel")
    for i, model in enumerate(models):
        if not isinstance(model, RiggedModel):
            raise ValueError(f"models: item {i} is a {type(model).__name__}, expected a RiggedModel")
    dtypes = {np.asarray(m.mesh.V).dtype for m in models}
    if len(dtypes) != 1:
        raise ValueError(f"models: every model needs the same float dtype, got {sorted(str(d) for d in dtypes)}")
    return models


def _model_capacities(models: list[RiggedModel], blocks: int, members: list[list[int]]) -> Capacities:
    groups: dict[tuple[str, str], tuple[int, int]] = {}
    for model in models:
        for clip in model.clips:
            for (path, interpolation), channels in _rig._groups(clip).items():
                c, k = groups.get((path, interpolation), (0, 0))
                keys = max(ch.times.shape[0] for ch in channels)
                groups[(path, interpolation)] = (max(c, len(channels)), max(k, keys))
    return Capacities(
        blocks,
        capacity(max(len(ms) for ms in members)),
        capacity(max(sum(models[m].mesh.num_vertices for m in ms) for ms in members)),
        max(int(np.shape(m.mesh.J)[1]) for m in models),
        capacity(max(m.skeleton.num_bones for m in models)),
        capacity(max(m.mesh.num_joints for m in models)),
        capacity(max(len(m.clips) for m in models)) if any(m.clips for m in models) else 1,
        tuple((p, i, capacity(c), capacity(k)) for (p, i), (c, k) in sorted(groups.items())),
    )


def pack_models(
    models: Sequence[RiggedModel] | RiggedModel, *, blocks: int = 1, at_least: Capacities | None = None
) -> PackedModels:
    """Pack rigged models of different sizes into one batch (``PackedModels``) for ``skin_packed``.

    Args:
        models: RiggedModels (any vertex, bone, joint, influence, clip, channel and key counts; one float dtype).
        blocks: how many blocks to spread the models over: the size of the mesh axis ``"models"`` they will be
            sharded over (1 on one device).
        at_least: capacities to pad to at least (``packed.capacities`` of an earlier batch, so that this one
            reuses its compiled function).
    Returns:
        the PackedModels."""
    models = _check_models(models)
    if not isinstance(blocks, (int, np.integer)) or blocks < 1:
        raise ValueError(f"blocks: expected an int >= 1, got {blocks!r}")
    members = _balanced_blocks([m.mesh.num_vertices for m in models], int(blocks))
    caps = _model_capacities(models, int(blocks), members)
    if at_least is not None:
        if not isinstance(at_least, Capacities):
            raise ValueError(f"at_least: expected the Capacities of a packed batch, got {type(at_least).__name__}")
        caps = caps.union(at_least)
    dtype = np.asarray(models[0].mesh.V).dtype
    D, M, N, K, B, Jc, L = caps[:7]
    V = np.zeros((D, N, 3), dtype)
    J = np.zeros((D, N, K), np.int32)
    W = np.zeros((D, N, K), dtype)
    W[..., 0] = 1.0  # padded vertices follow joint 0 of their block: finite, and dropped when unpacked
    parents = np.full((D, M, B), -1, np.int32)
    rest = {p: np.broadcast_to(np.asarray(v, dtype), (D, M, B, len(v))).copy() for p, v in _IDENTITY_TRS.items()}
    joint_bones = np.zeros((D, M, Jc), np.int32)
    inverse_bind = np.broadcast_to(np.eye(4, dtype=dtype), (D, M, Jc, 4, 4)).copy()
    has_clip = np.zeros((D, M), bool)
    groups = tuple((p, i) for p, i, _, _ in caps.channels)
    times, values, counts, bones = [], [], [], []
    for path, interpolation, C, keys in caps.channels:
        width = len(_IDENTITY_TRS[path])
        shape = (D, M, L, C, keys) + ((3, width) if interpolation == "CUBICSPLINE" else (width,))
        times.append(np.zeros((D, M, L, C, keys), dtype))
        values.append(np.broadcast_to(np.asarray(_IDENTITY_TRS[path], dtype), shape).copy())
        counts.append(np.ones((D, M, L, C), np.int32))
        bones.append(np.full((D, M, L, C), B, np.int32))  # past the skeleton: the scatter drops padded rows
    block, slot, offset = [0] * len(models), [0] * len(models), [0] * len(models)
    for b, ms in enumerate(members):
        start = 0
        for s, m in enumerate(ms):
            model = models[m]
            mesh, skeleton = model.mesh, model.skeleton
            n, k, nb, nj = mesh.num_vertices, int(np.shape(mesh.J)[1]), skeleton.num_bones, mesh.num_joints
            block[m], slot[m], offset[m] = b, s, start
            V[b, start : start + n] = np.asarray(mesh.V)
            J[b, start : start + n, :k] = np.asarray(mesh.J) + s * Jc
            J[b, start : start + n, k:] = s * Jc
            W[b, start : start + n, :k] = np.asarray(mesh.W)
            W[b, start : start + n, k:] = 0.0
            start += n
            parents[b, s, :nb] = skeleton.parents
            for path in PATHS:
                rest[path][b, s, :nb] = np.asarray(getattr(skeleton, path))
            joint_bones[b, s, :nj] = mesh.joints
            inverse_bind[b, s, :nj] = np.asarray(mesh.inverse_bind)
            has_clip[b, s] = bool(model.clips)
            for c, clip in enumerate(model.clips):
                # the layout of _rig.stacked_channels, written on the host: each channel's keys padded with its
                # last key (eager JAX stacking took about a second for 64 models)
                for (path, interpolation), channels in _rig._groups(clip).items():
                    g = groups.index((path, interpolation))
                    for row, channel in enumerate(channels):
                        key_times, key_values = np.asarray(channel.times), np.asarray(channel.values)
                        kk = key_times.shape[0]
                        times[g][b, s, c, row, :kk], times[g][b, s, c, row, kk:] = key_times, key_times[-1]
                        values[g][b, s, c, row, :kk], values[g][b, s, c, row, kk:] = key_values, key_values[-1]
                        counts[g][b, s, c, row] = kk
                        bones[g][b, s, c, row] = channel.bone
    rigs = PackedRigs(
        V=jnp.asarray(V),
        J=jnp.asarray(J),
        W=jnp.asarray(W),
        parents=jnp.asarray(parents),
        translation=jnp.asarray(rest["translation"]),
        rotation=jnp.asarray(rest["rotation"]),
        scale=jnp.asarray(rest["scale"]),
        joint_bones=jnp.asarray(joint_bones),
        inverse_bind=jnp.asarray(inverse_bind),
        has_clip=jnp.asarray(has_clip),
        channel_times=tuple(jnp.asarray(x) for x in times),
        channel_values=tuple(jnp.asarray(x) for x in values),
        channel_counts=tuple(jnp.asarray(x) for x in counts),
        channel_bones=tuple(jnp.asarray(x) for x in bones),
        groups=groups,
    )
    return PackedModels(
        rigs,
        caps,
        tuple(m.name for m in models),
        tuple(block),
        tuple(slot),
        tuple(offset),
        tuple(m.mesh.num_vertices for m in models),
        tuple(int(np.shape(m.mesh.J)[1]) for m in models),
        tuple(tuple(c.name for c in m.clips) for m in models),
        tuple(tuple((c.start, c.end) for c in m.clips) for m in models),
        tuple(m.skeleton.num_bones for m in models),
    )


# ---------------------------------------------------------------------------------------------------------
# skinning a packed batch


def _per_model(rigs: PackedRigs):
    """The per-model arrays of a block, each with the model axis first."""
    return (
        (rigs.translation, rigs.rotation, rigs.scale),
        rigs.parents,
        rigs.joint_bones,
        rigs.inverse_bind,
        rigs.has_clip,
        (rigs.channel_times, rigs.channel_values, rigs.channel_counts, rigs.channel_bones),
    )


def _model_joints(groups, model, times, clip, method: str, interpolation: str):
    """Joint transforms of one model at its times (T,): versors (T, Jc) or matrices (T, Jc, 4, 4), by the
    functions ``skin_model`` uses."""
    rest, parents, joint_bones, inverse_bind, has_clip, channels = model
    stacked = tuple(
        _rig.StackedChannels(path, interpolation_, *(x[clip] for x in arrays))
        for (path, interpolation_), *arrays in zip(groups, *channels, strict=True)
    )

    def local_at(t):
        local = _pose.sample_stacked_pose(rest, stacked, t, method, "gltf")
        if interpolation == "log":
            # a model without clips is posed at rest, as skin_model does: the specification's sampling with no
            # channels is its rest TRS, the log one a product of versors (equal only up to rounding)
            log = _pose.sample_stacked_pose(rest, stacked, t, method, "log")
            local = jax.tree.map(lambda a, b: jnp.where(has_clip, a, b), log, local)
        return local

    local = jax.vmap(local_at)(times)
    return _pose.joint_transforms(parents, joint_bones, inverse_bind, local)


def _skin_block(rigs: PackedRigs, times, clip, method: str, interpolation: str):
    """Positions (T, N, 3) of one block: its models' times (M, T) and clip indices (M,)."""
    joints = jax.vmap(lambda model, t, c: _model_joints(rigs.groups, model, t, c, method, interpolation))(
        _per_model(rigs), times, clip
    )
    return skin_joint_tables(rigs, joints, method)


def skin_joint_tables(rigs: PackedRigs, joints, method: str):
    """Positions (T, N, 3) of one block from its models' joint transforms (M, T, Jc, ...) (``deform.fit_packed``
    shares it)."""
    # (M, T, Jc, ...) -> (T, M * Jc, ...): one joint table per frame, indexed by J
    joints = jax.tree.map(lambda x: jnp.moveaxis(x, 0, 1).reshape((x.shape[1], -1) + x.shape[3:]), joints)
    return _pose.skin_with_joints(rigs.V, rigs.J, rigs.W, joints, method)


@eqx.filter_jit
def _skin_blocks(rigs: PackedRigs, times, clip, method: str, interpolation: str):
    # one block after the other (lax.map), not vmapped: a block axis on the per-vertex pass (size one on every
    # device of a mesh) made XLA:CPU's skinning loops slower
    return jax.lax.map(
        lambda block: _skin_block(block[0], block[1], block[2], method, interpolation), (rigs, times, clip)
    )


def _block_layout(packed: PackedModels, per_model: np.ndarray, fill) -> np.ndarray:
    """A per-model host array (M, ...) laid out by block and slot (D, models per block, ...)."""
    c = packed.capacities
    out = np.full((c.blocks, c.models) + per_model.shape[1:], fill, per_model.dtype)
    out[np.asarray(packed.block), np.asarray(packed.slot)] = per_model
    return out


def _global_array(x: np.ndarray, mesh: Mesh, spec: PartitionSpec) -> jax.Array:
    """A host array (the same on every process) as a global array sharded by ``spec``: each process places the
    pieces of its own devices."""
    return jax.make_array_from_callback(x.shape, NamedSharding(mesh, spec), lambda index: x[index])


def _mesh_sizes(mesh: Mesh) -> tuple[int, int]:
    unknown = set(mesh.axis_names) - {MODEL_AXIS, TIME_AXIS}
    if unknown:
        raise ValueError(f"mesh: expected axes named {MODEL_AXIS!r} and {TIME_AXIS!r}, got {mesh.axis_names}")
    shape = dict(mesh.shape)
    return shape.get(MODEL_AXIS, 1), shape.get(TIME_AXIS, 1)


@plain_errors
def skin_packed(
    packed: PackedModels,
    times: Float[ArrayLike, "M T"] | Float[ArrayLike, " T"],
    method: str = "cga",
    *,
    clip: int | str | ArrayLike = 0,
    interpolation: str = "gltf",
    mesh: Mesh | None = None,
) -> Float[Array, "D T N 3"]:
    """Skinned positions of every model of a packed batch at its own times, under one jit: each model equal to
    ``skin_model`` of it alone. ``packed.unpack(result)`` gives each model's (T, n, 3) frames. Called from Python
    with host times (it lays them out by block on the host); the compiled call inside is one jit.

    Args:
        packed: the PackedModels (``pack_models``).
        times: (M, T) times of each model (e.g. ``packed.frame_times(T)``), or (T,) for every model.
        method: one of ``deform.METHODS``.
        clip: each model's clip: an index or name for all, or one per model (``PackedModels.clip_indices``).
        interpolation: ``"gltf"`` or ``"log"`` (``deform.skin_model``).
        mesh: a ``jax.sharding.Mesh`` with axes ``"models"`` (the blocks: pack with ``blocks`` = its size)
            and optionally ``"time"`` (the frames, a multiple of its size); with several processes
            (``jax.distributed``) a mesh over all their devices. None: the default device.
    Returns:
        (D, T, N, 3) positions by block (``packed.unpack`` / ``unpack_local``)."""
    if not isinstance(packed, PackedModels):
        raise ValueError(f"packed: expected the PackedModels of pack_models, got {type(packed).__name__}")
    check_choice("method", method, _pose.METHODS)
    check_choice("interpolation", interpolation, _pose.INTERPOLATIONS)
    M = packed.num_models
    dtype = np.asarray(packed.rigs.V).dtype
    times = np.asarray(times, dtype)
    if times.ndim == 1:
        times = np.broadcast_to(times, (M,) + times.shape)
    if times.ndim != 2 or times.shape[0] != M or times.shape[1] < 1:
        raise ValueError(f"times: expected shape ({M}, T) or (T,) with T >= 1, got {times.shape}")
    if not np.all(np.isfinite(times)):
        raise ValueError("times: contains NaN or infinity")
    block_times = _block_layout(packed, times, 0)
    block_clip = _block_layout(packed, packed.clip_indices(clip), 0)
    if mesh is None:
        return _skin_blocks(packed.rigs, jnp.asarray(block_times), jnp.asarray(block_clip), method, interpolation)
    if not isinstance(mesh, Mesh):
        raise ValueError(f"mesh: expected a jax.sharding.Mesh, got {type(mesh).__name__}")
    model_shards, time_shards = _mesh_sizes(mesh)
    if model_shards != packed.capacities.blocks:
        raise ValueError(
            f"mesh: its {MODEL_AXIS!r} axis has {model_shards} devices; pack the models with blocks={model_shards} "
            f"(packed with {packed.capacities.blocks})"
        )
    if times.shape[1] % time_shards:
        raise ValueError(f"times: {times.shape[1]} frames do not split over the {time_shards} devices of axis 'time'")
    rigs = jax.tree.map(lambda x: _global_array(np.asarray(x), mesh, PartitionSpec(MODEL_AXIS)), packed.rigs)
    block_times = _global_array(block_times, mesh, PartitionSpec(MODEL_AXIS, None, TIME_AXIS))
    block_clip = _global_array(block_clip, mesh, PartitionSpec(MODEL_AXIS))
    return _sharded_skin(mesh, method, interpolation)(rigs, block_times, block_clip)


@functools.lru_cache(maxsize=32)
def _sharded_skin(mesh: Mesh, method: str, interpolation: str):
    spec = PartitionSpec(MODEL_AXIS)
    # check_vma off: a value check's host call sits in a lax.cond whose branches differ in how they vary over the
    # mesh, which the check would refuse though each device raises for its own blocks
    return jax.jit(
        jax.shard_map(
            lambda rigs, times, clip: _skin_blocks(rigs, times, clip, method, interpolation),
            mesh=mesh,
            in_specs=(spec, PartitionSpec(MODEL_AXIS, None, TIME_AXIS), spec),
            out_specs=PartitionSpec(MODEL_AXIS, TIME_AXIS),
            check_vma=False,
        )
    )
