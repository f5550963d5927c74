"""The rig in matrix and multivector form (cut/tear/drill paper sec. 3, eq. 15, and sec. 4.1).

A bone's local transform is ``t = T R S`` (eq. 15). In the multivector form it becomes the
similitude ``T R D``: translator, rotor and a dilator for a uniform scale (sec. 4.1, "the multivector
M_i,k ... can be replaced with M_i,k D_i,k"). A non-uniform scale has no versor: it raises a ValueError
(inside jit a runtime error with the message); the matrix path (``local_matrices`` + ``skin_lbs``) handles it.

Sampling a clip:

* ``sample_trs`` follows the glTF 2.0 specification (Appendix "Interpolation"): translation and
  scale lerped, rotation slerped along the shortest arc, STEP holds the key, CUBICSPLINE is the
  Hermite spline with tangents scaled by the key interval (rotation normalized afterwards);
* ``sample_versors`` is the paper's sampling (``interpolation="log"`` of ``deform.skin_model``; the
  default ``"gltf"`` is ``sample_trs`` for every method): each channel's keys become versors
  (translators, rotors, dilators) blended logarithmically, ``m1 exp(a log(m1^-1 m2))`` (sec. 2.5).
  For translators this is the lerp and for rotors (sign-aligned) the slerp of the specification,
  exactly; for dilators it interpolates the scale geometrically, ``s1^(1-a) s2^a``, where the
  specification lerps (equal at the keys and when the scale is constant). CUBICSPLINE channels are
  evaluated by the specification's Hermite spline, then turned into versors.

User-made keyframes (``Keyframes``) are blended linearly and renormalized, the paper's choice for
frames generated on the fly (sec. 2.5).

Times outside a clip's key range are clamped to its first / last key.
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga
from _jaxcga_shared.broadcast import same_rank
from _jaxcga_shared.checks import require
from _jaxcga_shared.platform import EXACT, PerPlatform
from deform._model import PATHS, AnimationClip, Channel, Skeleton, SkinnedMesh
from jaxcga._multivector import KINDS, Multivector

_SIMILITUDE = KINDS["similitude"]


# ---------------------------------------------------------------- TRS -> matrix / versor
def quaternion_xyzw_to_matrix(q: Float[Array | np.ndarray, "... 4"]) -> Float[Array | np.ndarray, "... 3 3"]:
    """Rotation matrices (..., 3, 3) of unit quaternions (a numpy array for a numpy array).

    Args:
        q: (..., 4) unit quaternions in glTF order (x, y, z, w).

    Returns:
        (..., 3, 3) the rotation matrices, numpy for numpy ``q``, else JAX.

    Examples:
        >>> import jax.numpy as jnp
        >>> import deform
        >>> deform.quaternion_xyzw_to_matrix(jnp.array([0, 0, 0, 1.0])).tolist()
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    """
    # numpy in, numpy out: the glTF loader's host arithmetic dispatches no JAX operation
    xp = np if isinstance(q, np.ndarray) else jnp
    x, y, z, w = (q[..., i] for i in range(4))
    return xp.stack(
        [
            xp.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
            xp.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
            xp.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
        ],
        axis=-2,
    )


def trs_to_matrix(
    translation: Float[Array | np.ndarray, "... 3"],
    rotation: Float[Array | np.ndarray, "... 4"],
    scale: Float[Array | np.ndarray, "... 3"],
) -> Float[Array, "... 4 4"]:
    """Homogeneous matrix ``T R S`` (eq. 15) of a local TRS.

    Args:
        translation: (..., 3) translations.
        rotation: (..., 4) unit quaternions in glTF order (x, y, z, w).
        scale: (..., 3) per-axis scales.

    Returns:
        (..., 4, 4) the matrices.

    Examples:
        >>> import jax.numpy as jnp
        >>> import deform
        >>> A = deform.trs_to_matrix(jnp.array([1.0, 2.0, 3.0]), jnp.array([0, 0, 0, 1.0]), jnp.ones(3))
        >>> A.tolist()
        [[1.0, 0.0, 0.0, 1.0], [0.0, 1.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    rs = quaternion_xyzw_to_matrix(rotation) * scale[..., None, :]
    top = jnp.concatenate([rs, translation[..., :, None]], axis=-1)
    bottom = jnp.broadcast_to(jnp.asarray([0, 0, 0, 1], rs.dtype), top.shape[:-2] + (1, 4))
    return jnp.concatenate([top, bottom], axis=-2)


def _rotor_xyzw(q) -> Multivector:
    return cga.quaternion_to_rotor(jnp.concatenate([q[..., 3:], q[..., :3]], axis=-1))


def uniform_scale(scale: Float[Array | np.ndarray, "... 3"], tolerance: float = 1e-5) -> Float[Array, "*batch"]:
    """The common factor of a uniform scale (..., 3); non-uniform (relative spread > tolerance) or
    non-positive scales raise a ValueError (inside jit a runtime error with the message): a dilator is a uniform
    scaling (eq. 12).

    Args:
        scale: (..., 3) per-axis scales.
        tolerance: the largest relative spread of the three accepted as uniform.
    Returns:
        (...,) the common factors."""
    s = jnp.mean(scale, axis=-1)
    spread = jnp.max(jnp.abs(scale - s[..., None]), axis=-1, initial=0.0) / jnp.abs(s)
    s = require(
        s,
        (
            jnp.any(spread > tolerance) | jnp.any(s <= 0),
            "scale: non-uniform or non-positive bone scale has no versor (dilators scale uniformly); "
            "use the matrix path (local_matrices / skin_lbs) for such rigs",
        ),
    )
    return s


def trs_to_versor(
    translation: Float[Array | np.ndarray, "... 3"],
    rotation: Float[Array | np.ndarray, "... 4"],
    scale: Float[Array | np.ndarray, "... 3"],
) -> Multivector:
    """Similitude ``T R D`` of a local TRS (the multivector form of eq. 15, sec. 4.1), batch shape (...,).

    Args:
        translation: (..., 3) translations.
        rotation: (..., 4) unit quaternions in glTF order (x, y, z, w).
        scale: (..., 3) uniform scales (see ``uniform_scale``).

    Returns:
        The similitudes, batch shape (...).

    Examples:
        >>> import jax.numpy as jnp
        >>> import deform
        >>> S = deform.trs_to_versor(jnp.array([1.0, 2.0, 3.0]), jnp.array([0, 0, 0, 1.0]), jnp.full(3, 2.0))
        >>> [(x.round(6) + 0.0).tolist() for x in deform.versor_to_trs(S)]  # back to translation, rotation, scale
        [[1.0, 2.0, 3.0], [0.0, 0.0, 0.0, 1.0], [2.0, 2.0, 2.0]]
    """
    return cga.similitude(_rotor_xyzw(rotation), translation, uniform_scale(scale))


def local_matrices(skeleton: Skeleton) -> Float[Array, "b 4 4"]:
    """Rest local matrices ``T R S`` (b, 4, 4) of every bone.

    Args:
        skeleton: the Skeleton (its rest TRS).

    Returns:
        (b, 4, 4) the matrices.

    Examples:
        >>> import deform
        >>> deform.local_matrices(deform.default_arm().skeleton).shape  # 4 bones
        (4, 4, 4)
    """
    return trs_to_matrix(skeleton.translation, skeleton.rotation, skeleton.scale)


def local_versors(skeleton: Skeleton) -> Multivector:
    """Rest local similitudes of every bone, batch shape (b,).

    Args:
        skeleton: the Skeleton (its rest TRS).

    Returns:
        The similitudes, batch shape (b,).

    Examples:
        >>> import deform
        >>> deform.local_versors(deform.default_arm().skeleton).batch_shape
        (4,)
    """
    return trs_to_versor(skeleton.translation, skeleton.rotation, skeleton.scale)


# ---------------------------------------------------------------- forward kinematics
def _doubling_rounds(parents, n: int) -> int:
    """Rounds of ``_chains_by_doubling``: ceil(log2(depth + 1)) for the deepest bone of static ``parents``;
    for traced ones the bound for ``n`` bones (a chain of depth n - 1)."""
    if isinstance(parents, Tracer):
        return max(n - 1, 0).bit_length()
    depth: list[int] = []
    for i, p in enumerate(np.asarray(parents).tolist()):
        if p >= i:
            raise ValueError(f"parents: bone {i} has parent {p}; expected -1 or an index < {i} (topological order)")
        depth.append(0 if p < 0 else depth[p] + 1)
    return max(depth, default=0).bit_length()


def _chains_in_a_loop(local, parents, *, compose, rounds: int):
    """``_compose_chains`` as a scan over the bones in order, one product per bone (XLA:CPU: the fewest
    products)."""
    del rounds

    def step(globals_, inputs):
        i, parent, l_i = inputs
        g = compose(globals_[jnp.maximum(parent, 0)], l_i)
        return globals_.at[i].set(jnp.where(parent >= 0, g, l_i)), None

    out, _ = jax.lax.scan(step, jnp.zeros_like(local), (jnp.arange(local.shape[0]), parents, local))
    return out


def _chains_by_doubling(local, parents, *, compose, rounds: int):
    """``_compose_chains`` by pointer doubling (GPUs, where each step of a loop costs kernel launches).

    ``acc[i]`` holds the product of the locals from bone ``up[i]``'s child down to ``i``; a round composes
    ``acc[up[i]] * acc[i]`` for every bone at once and jumps ``up[i]`` to ``up[up[i]]``, so ``rounds`` =
    ceil(log2(depth + 1)) batched products give every global."""
    up, acc = parents, local
    for _ in range(rounds):
        has_up = up >= 0
        above = jnp.maximum(up, 0)
        acc = jnp.where(has_up.reshape((-1,) + (1,) * (acc.ndim - 1)), compose(acc[above], acc), acc)
        up = jnp.where(has_up, up[above], -1)
    return acc


_CHAINS = PerPlatform("deform.forward_kinematics", cpu=_chains_in_a_loop, gpu=_chains_by_doubling)


def _compose_chains(parents, local, compose):
    """Globals ``G_i = G_parent(i) * L_i`` of bones in topological order. ``local`` has the bone axis first:
    (b, *rest); ``parents`` (b,) may be traced (packed rigs)."""
    rounds = _doubling_rounds(parents, local.shape[0])
    return _CHAINS(local, jnp.asarray(parents, jnp.int32), compose=compose, rounds=rounds)


@functools.cache
def _versor_product(blades: tuple[int, ...]):
    def compose(a, b):
        # the structure-tensor contraction, not one kernel per blade
        return cga.table_product("geometric", Multivector(a, blades), Multivector(b, blades)).embed(blades).values

    return compose


_MATRIX_PRODUCT = functools.partial(jnp.matmul, precision=EXACT)


def _check_bones(name: str, parents, n: int):
    if n != len(parents):
        raise ValueError(f"{name}: expected {len(parents)} bones on the last batch axis, got {n}")


def forward_kinematics(parents: tuple[int, ...], local: Multivector) -> Multivector:
    """Global bone versors ``M_i = M_parent(i) L_i`` (sec. 3, with multivectors as in sec. 4.1).

    Args:
        parents: the skeleton's parents (topological order, -1 for roots).
        local: local versors (motors or similitudes), batch shape (..., b).
    Returns:
        global versors with the same blades and batch shape (similitudes when ``local`` is)."""
    if not isinstance(local, Multivector) or not local.batch_shape:
        raise ValueError("local: expected a Multivector with batch shape (..., b)")
    _check_bones("local", parents, local.batch_shape[-1])
    values = jnp.moveaxis(local.values, -2, 0)
    globals_ = _compose_chains(parents, values, _versor_product(local.blades))
    return Multivector(jnp.moveaxis(globals_, 0, -2), local.blades)


def forward_kinematics_matrices(
    parents: tuple[int, ...], local: Float[ArrayLike, "... b 4 4"]
) -> Float[Array, "... b 4 4"]:
    """Global bone matrices ``T_i = T_parent(i) t_i`` (sec. 3).

    Args:
        parents: each bone's parent index (-1 for a root), parents before children.
        local: (..., b, 4, 4) local bone matrices.
    Returns:
        (..., b, 4, 4) global bone matrices."""
    local = jnp.asarray(local)
    if local.ndim < 3 or local.shape[-2:] != (4, 4):
        raise ValueError(f"local: expected shape (..., b, 4, 4), got {local.shape}")
    _check_bones("local", parents, local.shape[-3])
    values = jnp.moveaxis(local, -3, 0)
    out = _compose_chains(parents, values, _MATRIX_PRODUCT)
    return jnp.moveaxis(out, 0, -3)


def joint_matrices(mesh: SkinnedMesh, global_matrices: Float[Array, "... b 4 4"]) -> Float[Array, "... j 4 4"]:
    """glTF joint matrices ``global(bone of joint) @ inverse_bind`` (the ``T_n,k O_n`` of eq. 16).

    Args:
        mesh: the SkinnedMesh (its joints' bones and inverse bind matrices (j, 4, 4)).
        global_matrices: (..., b, 4, 4) global bone matrices (``forward_kinematics_matrices``).
    Returns:
        (..., j, 4, 4) joint matrices."""
    return joint_matrices_of(jnp.asarray(mesh.joints, jnp.int32), mesh.inverse_bind, global_matrices)


def joint_matrices_of(joint_bones: Array, inverse_bind: Array, global_matrices: Array) -> Array:
    """``joint_matrices`` from the joints' bone indices (j,) and inverse bind matrices (j, 4, 4) as arrays."""
    bones = global_matrices[..., joint_bones, :, :]
    # elementwise, one fused loop: XLA:CPU's batched dot of 4x4 matrices took 0.07 against 0.02 ms
    # for 23 joints
    return jnp.multiply(*same_rank(bones[..., :, :, None], inverse_bind[..., None, :, :])).sum(-2)


def inverse_bind_versors(mesh: SkinnedMesh) -> Multivector:
    """The inverse-bind versors ``B_n`` of eq. (17), batch shape (j,), from the inverse bind matrices.

    Args:
        mesh: the SkinnedMesh (its inverse bind matrices (j, 4, 4)).

    Returns:
        The versors ``B_n``, batch shape (j,).
    """
    return cga.matrix_to_similitude(mesh.inverse_bind)


def joint_versors(
    mesh: SkinnedMesh, global_versors: Multivector, inverse_bind: Multivector | None = None
) -> Multivector:
    """Joint versors ``M_n,k B_n`` of eq. (17), batch shape (..., j).

    Args:
        mesh: the skinned mesh (its joints and inverse bind matrices).
        global_versors: global bone versors, batch shape (..., b) (``forward_kinematics``).
        inverse_bind: the versors ``B_n`` (``inverse_bind_versors(mesh)``), batch shape (j,). Pass them
            when posing a mesh many times: otherwise every call converts the inverse bind matrices
            again (a determinant, a rigidity check and a quaternion extraction per joint).

    Returns:
        The joint versors, batch shape (..., j).
    """
    if inverse_bind is None:
        inverse_bind = inverse_bind_versors(mesh)
    elif not isinstance(inverse_bind, Multivector) or inverse_bind.batch_shape[-1:] != (len(mesh.joints),):
        raise ValueError(
            f"inverse_bind: expected versors with batch shape ({len(mesh.joints)},), "
            f"got {getattr(inverse_bind, 'batch_shape', type(inverse_bind).__name__)}"
        )
    return joint_versors_of(jnp.asarray(mesh.joints, jnp.int32), inverse_bind, global_versors)


def joint_versors_of(joint_bones: Array, inverse_bind: Multivector, global_versors: Multivector) -> Multivector:
    """``joint_versors`` from the joints' bone indices (j,) as an array and their inverse-bind versors (j,)."""
    bones = global_versors[..., joint_bones]
    return cga.table_product("geometric", bones, inverse_bind).embed(_SIMILITUDE)


# ---------------------------------------------------------------- sampling a clip
# Channels that share (path, interpolation) are stacked, padded with their last key, and sampled
# together: one vectorized evaluation per group keeps compile time independent of the channel count.
def _locate(times, t, counts=None):
    """Key interval k and fraction alpha of time t for every row of ``times`` (..., K) (clamped to
    each row's key range; ``counts`` (...,) are the rows' real key counts, padding repeats the last)."""
    times = jnp.asarray(times)
    K = times.shape[-1]
    counts = jnp.full(times.shape[:-1], K) if counts is None else jnp.asarray(counts)
    last = jnp.take_along_axis(times, (counts - 1)[..., None], axis=-1)[..., 0]
    t = jnp.clip(jnp.asarray(t, times.dtype), times[..., 0], last)
    k = jnp.sum(times <= t[..., None], axis=-1) - 1
    k = jnp.clip(k, 0, jnp.maximum(counts - 2, 0).astype(k.dtype))
    k1 = jnp.minimum(k + 1, K - 1)
    t0 = jnp.take_along_axis(times, k[..., None], axis=-1)[..., 0]
    t1 = jnp.take_along_axis(times, k1[..., None], axis=-1)[..., 0]
    span = t1 - t0
    alpha = jnp.where(span > 0, (t - t0) / jnp.where(span > 0, span, 1), 0)
    return k, k1, alpha


def _slerp(a, b, alpha):
    """glTF slerp of unit quaternions along the shortest arc (lerp + normalize when nearly equal)."""
    d = jnp.sum(a * b, axis=-1)
    b = jnp.where((d < 0)[..., None], -b, b)
    d = jnp.abs(d)
    near = d > 0.9995
    theta = jnp.arccos(jnp.where(near, 0.5, jnp.minimum(d, 1.0)))
    sin_theta = jnp.sin(theta)
    wa = jnp.where(near, 1 - alpha, jnp.sin((1 - alpha) * theta) / sin_theta)
    wb = jnp.where(near, alpha, jnp.sin(alpha * theta) / sin_theta)
    q = wa[..., None] * a + wb[..., None] * b
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


class StackedChannels(NamedTuple):
    """The channels of one (path, interpolation) group, stacked and padded with their last key: times (c, K),
    values (c, K, ...), counts (c,) of real keys, bones (c,) (a bone index past the skeleton is a padding row,
    dropped when written; ``deform.pack_models`` pads groups to shared capacities)."""

    path: str
    interpolation: str
    times: Array
    values: Array
    counts: Array
    bones: Array


def _stack(channels: list[Channel]):
    """times (c, K), values (c, K, ...), counts (c,), bones (c,) of channels padded with their last key."""
    K = max(c.times.shape[0] for c in channels)

    def pad(x):
        return jnp.concatenate([x, jnp.repeat(x[-1:], K - x.shape[0], axis=0)], axis=0)

    times = jnp.stack([pad(c.times) for c in channels])
    values = jnp.stack([pad(c.values) for c in channels])
    return times, values, np.array([c.times.shape[0] for c in channels]), np.array([c.bone for c in channels])


def _groups(clip: AnimationClip):
    groups: dict[tuple[str, str], list[Channel]] = {}
    for channel in clip.channels:
        groups.setdefault((channel.path, channel.interpolation), []).append(channel)
    return groups


def stacked_channels(clip: AnimationClip) -> tuple[StackedChannels, ...]:
    """The clip's channels grouped by (path, interpolation), each group stacked (``StackedChannels``)."""
    return tuple(
        StackedChannels(path, interpolation, *(jnp.asarray(x) for x in _stack(channels)))
        for (path, interpolation), channels in _groups(clip).items()
    )


def _rows(x, k):
    """x[c, k[c]] for every row c."""
    return jnp.take_along_axis(x, k.reshape(k.shape + (1,) * (x.ndim - 1)), axis=1)[:, 0]


def _sample_rows(path: str, interpolation: str, times, values, counts, t):
    """Values of stacked channels (c, d) at time t per the glTF specification."""
    k, k1, alpha = _locate(times, t, counts)
    if interpolation == "CUBICSPLINE":
        # p = (2s^3-3s^2+1) v_k + td (s^3-2s^2+s) b_k + (-2s^3+3s^2) v_k+1 + td (s^3-s^2) a_k+1
        td = (_rows(times, k1) - _rows(times, k))[:, None]
        s = alpha[:, None]
        s2, s3 = s**2, s**3
        vk, vk1 = _rows(values, k), _rows(values, k1)
        value = (
            (2 * s3 - 3 * s2 + 1) * vk[:, 1]
            + td * (s3 - 2 * s2 + s) * vk[:, 2]
            + (-2 * s3 + 3 * s2) * vk1[:, 1]
            + td * (s3 - s2) * vk1[:, 0]
        )
        return value / jnp.linalg.norm(value, axis=-1, keepdims=True) if path == "rotation" else value
    if interpolation == "STEP":
        return _rows(values, jnp.where(alpha >= 1, k1, k))
    a, b = _rows(values, k), _rows(values, k1)
    if path == "rotation":
        return _slerp(a, b, alpha)
    return (1 - alpha[:, None]) * a + alpha[:, None] * b


def sample_channel(channel: Channel, t: Float[ArrayLike, ""]) -> Float[Array, " d"]:
    """Value (d,) of one channel at time t per the glTF specification.

    Args:
        channel: the Channel.
        t: () the time (clamped to the key range).

    Returns:
        (d,) the channel's value.
    """
    times, values, counts, _ = _stack([channel])
    return _sample_rows(channel.path, channel.interpolation, times, values, counts, t)[0]


def sample_trs(
    skeleton: Skeleton, clip: AnimationClip, t: Float[ArrayLike, ""]
) -> tuple[Float[Array, "b 3"], Float[Array, "b 4"], Float[Array, "b 3"]]:
    """Local TRS of every bone at time t per the glTF specification (unanimated properties keep
    the rest value). Returns translation (b, 3), rotation (b, 4) in (x, y, z, w), scale (b, 3).

    Args:
        skeleton: the Skeleton (its rest TRS).
        clip: the AnimationClip.
        t: () the time (clamped to the key range).

    Returns:
        (translation (b, 3), rotation (b, 4) in (x, y, z, w), scale (b, 3)).

    Examples:
        >>> import deform
        >>> arm = deform.default_arm()
        >>> [x.shape for x in deform.sample_trs(arm.skeleton, arm.clips[0], 0.5)]
        [(4, 3), (4, 4), (4, 3)]
    """
    return sample_stacked_trs((skeleton.translation, skeleton.rotation, skeleton.scale), stacked_channels(clip), t)


def sample_stacked_trs(rest: tuple[Array, Array, Array], groups: tuple[StackedChannels, ...], t):
    """``sample_trs`` on a rest TRS (b, 3), (b, 4), (b, 3) and stacked channel groups (``stacked_channels``)."""
    trs: dict[str, Array] = dict(zip(PATHS, rest, strict=True))
    for group in groups:
        value = _sample_rows(group.path, group.interpolation, group.times, group.values, group.counts, t)
        trs[group.path] = trs[group.path].at[group.bones].set(value.astype(trs[group.path].dtype), mode="drop")
    return trs["translation"], trs["rotation"], trs["scale"]


def sample_matrices(skeleton: Skeleton, clip: AnimationClip, t: Float[ArrayLike, ""]) -> Float[Array, "b 4 4"]:
    """Local matrices ``T R S`` (eq. 15) of every bone at time t (specification sampling).

    Args:
        skeleton: the Skeleton (its rest TRS).
        clip: the AnimationClip.
        t: () the time (clamped to the key range).

    Returns:
        (b, 4, 4) the local matrices.
    """
    return trs_to_matrix(*sample_trs(skeleton, clip, t))


_PART_BLADES = {"translation": KINDS["translator"], "rotation": KINDS["rotor"], "scale": KINDS["dilator"]}


def _key_versors(path: str, values) -> Multivector:
    if path == "translation":
        return cga.translator(values)
    if path == "rotation":
        return _rotor_xyzw(values)
    return cga.dilator(uniform_scale(values))


def _project(m: Multivector, blades) -> Multivector:
    """Keep the components on ``blades`` (the blend of two rotors is a rotor, though log/exp carry it
    in the motor's blades)."""
    columns = [m.blades.index(b) for b in blades]
    return Multivector(m.values[..., jnp.asarray(columns)], blades)


def _versor_rows(path: str, interpolation: str, times, values, counts, t) -> Multivector:
    """Versors of stacked channels at time t: LINEAR keys blended logarithmically (sec. 2.5)."""
    if interpolation != "LINEAR":
        return _key_versors(path, _sample_rows(path, interpolation, times, values, counts, t))
    k, k1, alpha = _locate(times, t, counts)
    a, b = _rows(values, k), _rows(values, k1)
    if path == "rotation":
        # Shortest arc, as the specification's slerp: q and -q are the same rotation.
        b = jnp.where((jnp.sum(a * b, axis=-1) < 0)[:, None], -b, b)
    return _project(cga.blend_log(_key_versors(path, a), _key_versors(path, b), alpha), _PART_BLADES[path])


def sample_versors(skeleton: Skeleton, clip: AnimationClip, t: Float[ArrayLike, ""]) -> Multivector:
    """Local similitudes ``T R D`` of every bone at time t, keys blended logarithmically (sec. 2.5,
    4.1). Batch shape (b,).

    Args:
        skeleton: the Skeleton (its rest TRS).
        clip: the AnimationClip.
        t: () the time (clamped to the key range).

    Returns:
        The local similitudes, batch shape (b,).
    """
    return sample_stacked_versors((skeleton.translation, skeleton.rotation, skeleton.scale), stacked_channels(clip), t)


def sample_stacked_versors(rest: tuple[Array, Array, Array], groups: tuple[StackedChannels, ...], t) -> Multivector:
    """``sample_versors`` on a rest TRS (b, 3), (b, 4), (b, 3) and stacked channel groups (``stacked_channels``)."""
    translation, rotation, scale = rest
    parts = {
        "translation": cga.translator(translation).values,
        "rotation": _rotor_xyzw(rotation).values,
        "scale": cga.dilator(uniform_scale(scale)).values,
    }
    for group in groups:
        versors = _versor_rows(group.path, group.interpolation, group.times, group.values, group.counts, t)
        values = versors.embed(_PART_BLADES[group.path]).values.astype(parts[group.path].dtype)
        parts[group.path] = parts[group.path].at[group.bones].set(values, mode="drop")
    t_, r_, d_ = (Multivector(parts[p], _PART_BLADES[p]) for p in ("translation", "rotation", "scale"))
    return (t_ * r_ * d_).embed(_SIMILITUDE)


# ---------------------------------------------------------------- user keyframes
class Keyframes(eqx.Module):
    """User-made keyframes: local versors of every bone at increasing times, blended linearly and
    renormalized between keys (sec. 2.5: the paper's choice for frames generated on the fly).

    Attributes:
        times: (K,) strictly increasing times.
        poses: local similitudes, batch shape (K, b).
    """

    times: Float[Array, " K"]
    poses: Multivector

    def __check_init__(self):
        if not isinstance(self.poses, Multivector) or len(self.poses.batch_shape) != 2:
            raise ValueError("poses: expected a Multivector with batch shape (K, b)")
        if jnp.shape(self.times) != self.poses.batch_shape[:1]:
            raise ValueError(f"times: expected shape ({self.poses.batch_shape[0]},), got {jnp.shape(self.times)}")


def sample_keyframes(keyframes: Keyframes, t: Float[ArrayLike, ""]) -> Multivector:
    """Local versors at time t, batch shape (b,): linear blending of the two surrounding keys, renormalized.

    Args:
        keyframes: the Keyframes.
        t: () the time (clamped to the key range).

    Returns:
        The local versors, batch shape (b,).
    """
    poses = keyframes.poses.embed(_SIMILITUDE)
    if keyframes.times.shape[0] == 1:
        return poses[0]
    k, _, alpha = _locate(keyframes.times, t)
    a, b = poses[k], poses[k + 1]
    # Align each bone's key with the previous one (V and -V are the same transformation).
    dot = jnp.sum(a.values * b.values, axis=-1, keepdims=True)
    b = Multivector(jnp.where(dot < 0, -b.values, b.values), b.blades)
    return cga.blend_linear(a, b, alpha)


# ---------------------------------------------------------------- versors back to TRS / clips
def versor_to_trs(versors: Multivector) -> tuple[Float[Array, "... 3"], Float[Array, "... 4"], Float[Array, "... 3"]]:
    """Translation (..., 3), glTF quaternion (..., 4) and uniform scale (..., 3) of motors or
    similitudes: the inverse of ``trs_to_versor``.

    Args:
        versors: motors or similitudes, batch shape (...,).

    Returns:
        (translation (..., 3), rotation (..., 4) in glTF order (x, y, z, w), scale (..., 3)).
    """
    matrix = cga.versor_to_matrix(versors)
    scale = jnp.cbrt(jnp.linalg.det(matrix[..., :3, :3]))
    wxyz = cga.matrix_to_quaternion(matrix[..., :3, :3] / scale[..., None, None])
    rotation = jnp.concatenate([wxyz[..., 1:], wxyz[..., :1]], axis=-1)
    return matrix[..., :3, 3], rotation, jnp.repeat(scale[..., None], 3, axis=-1)


def clip_from_poses(
    times: Float[Array, " K"], local: Multivector, name: str = "clip", scale: bool | None = None
) -> AnimationClip:
    """A LINEAR AnimationClip with translation, rotation (and scale) channels on every bone, keyed by
    local versors (batch shape (K, b)) at ``times``; consecutive quaternions are sign-aligned so the
    glTF slerp follows the versors' shortest arcs.

    Args:
        times: (K,) strictly increasing key times.
        local: local versors of every bone at each key, batch shape (K, b).
        name: clip name.
        scale: write scale channels (default: only when some scale differs from 1 by > 1e-9).

    Returns:
        The ``AnimationClip``.
    """
    if not isinstance(local, Multivector) or len(local.batch_shape) != 2:
        raise ValueError("local: expected a Multivector with batch shape (K, b)")
    times = jnp.asarray(times, local.dtype)
    if times.shape != local.batch_shape[:1]:
        raise ValueError(f"times: expected shape ({local.batch_shape[0]},), got {times.shape}")
    translation, rotation, scales = versor_to_trs(local)
    # Flip each key's quaternion to the hemisphere of the previous one (a cumulative sign).
    dots = jnp.sum(rotation[1:] * rotation[:-1], axis=-1)
    flips = jnp.concatenate([jnp.ones_like(dots[:1]), jnp.where(dots < 0, -1.0, 1.0).astype(dots.dtype)])
    rotation = rotation * jnp.cumprod(flips, axis=0)[..., None]
    if scale is None:
        scale = bool(jnp.max(jnp.abs(scales - 1.0)) > 1e-9)
    channels = []
    for bone in range(local.batch_shape[1]):
        channels.append(Channel(times, translation[:, bone], bone, "translation", "LINEAR"))
        channels.append(Channel(times, rotation[:, bone], bone, "rotation", "LINEAR"))
        if scale:
            channels.append(Channel(times, scales[:, bone], bone, "scale", "LINEAR"))
    return AnimationClip(tuple(channels), name)
