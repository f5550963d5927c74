"""The built-in default model: a procedurally generated rigged arm that needs no file.

The CLI and the notebooks fall back to it when no model is given. It is built on the host in numpy: a
generalized cylinder around the bone chain laid out straight, bent into the rest pose ring by ring by the
bones' rest rotations, each turned in by the same smoothstep that blends the skin weights (so the bind pose is
what blended skinning of the straight template gives, and the weights follow the mesh).
"""

from __future__ import annotations

import math

import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from scipy.interpolate import PchipInterpolator
from scipy.spatial.transform import Rotation

from deform._model import AnimationClip, Channel, RiggedModel, Skeleton, SkinnedMesh
from deform._rig import forward_kinematics_matrices, trs_to_matrix

_NAMES = ("shoulder", "upper_arm", "forearm", "hand")
_PARENTS = (-1, 0, 1, 2)
# Length of each bone along its local +y (the axis glTF exporters put along a bone); the shoulder is a stub.
_LENGTHS = np.array([0.05, 0.30, 0.27, 0.18])
# Rest rotations as rotation vectors in degrees: the root turns local +y onto world +x, the elbow is bent
# 10 degrees forward (+z) and the wrist extended 10 degrees (up, +y).
_REST = np.array([[0.0, 0.0, -90.0], [0.0, 0.0, 0.0], [10.0, 0.0, 0.0], [0.0, 0.0, 10.0]])
# Half-width (m) of the blend window around the head of bones 1, 2, 3 (shoulder joint, elbow, wrist).
_BLEND = np.array([0.04, 0.05, 0.04])
# Cross-section along the straight chain: s (m from the shoulder joint), half thickness (y), half width (z).
# Flat ends make the end caps meet the tube tangentially.
_PROFILE = np.array(
    [
        [0.00, 0.050, 0.050],
        [0.05, 0.050, 0.050],
        [0.20, 0.044, 0.046],
        [0.35, 0.040, 0.040],
        [0.43, 0.039, 0.044],
        [0.62, 0.026, 0.032],
        [0.68, 0.016, 0.042],
        [0.74, 0.013, 0.041],
        [0.77, 0.013, 0.041],
    ]
)
# Length along the chain of the rounded shoulder cap and of the fingertip cap.
_CAPS = (0.05, 0.03)


def _smoothstep(x):
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _global_matrices(translation, rotation):
    """(b, 4, 4) global matrices of the bones from local translations and (x, y, z, w) rotations (unit
    scale), by the rig's own forward kinematics (eq. 15), in float64 on the host."""
    translation, rotation = np.asarray(translation, np.float64), np.asarray(rotation, np.float64)
    local = trs_to_matrix(translation, rotation, np.ones_like(translation))
    return np.asarray(forward_kinematics_matrices(_PARENTS, local), np.float64)


def _rings(rings_per_unit):
    """Ring stations of the straight template, pole to pole: s (r,) and half thickness/width (r, 2)."""
    profile = PchipInterpolator(_PROFILE[:, 0], _PROFILE[:, 1:], axis=0)
    s0, s1 = _PROFILE[0, 0], _PROFILE[-1, 0]
    body = np.linspace(s0, s1, max(2, math.ceil(rings_per_unit * (s1 - s0)) + 1))

    def cap(c, radii):
        # quarter-ellipse meridian from the pole (angle 0) to the tube (angle pi/2, excluded)
        n = max(2, math.ceil(rings_per_unit * math.pi / 4 * (c + radii.max())))
        psi = np.linspace(0.0, math.pi / 2, n + 1)[:-1]
        return c * np.cos(psi), np.sin(psi)[:, None] * radii

    d0, r0 = cap(_CAPS[0], profile(s0))
    d1, r1 = cap(_CAPS[1], profile(s1))
    s = np.concatenate([s0 - d0, body, s1 + d1[::-1]])
    radii = np.concatenate([r0, profile(body), r1[::-1]])
    return s, radii


def _tube_faces(rings, n):
    """Faces of a tube of ``rings`` rings of ``n`` vertices closed by two poles (vertex 0 and the last)."""
    j = np.arange(n)
    jn = (j + 1) % n
    ring = 1 + n * np.arange(rings - 1)[:, None]
    a, b = ring + j, ring + jn
    side = np.stack([np.stack([a, b, a + n], -1), np.stack([b, b + n, a + n], -1)], 1).reshape(-1, 3)
    last = 1 + n * (rings - 1)
    start = np.stack([np.zeros(n, int), 1 + jn, 1 + j], -1)
    end = np.stack([last + j, last + jn, np.full(n, last + n)], -1)
    return np.concatenate([start, side, end])


def _wave_clip(rest_translation, rest_rotation, dtype):
    t = np.linspace(0.0, 2.0, 9)
    up = np.sin(np.pi * t / 2) ** 2  # 0 -> 1 -> 0
    turn = np.sin(np.pi * t)  # 0 -> 1 -> -1 -> 0

    def rotation(bone, axis, degrees):
        delta = Rotation.from_rotvec(np.radians(degrees)[:, None] * np.asarray(axis, float))
        q = (Rotation.from_quat(rest_rotation[bone]) * delta).as_quat()
        return Channel(jnp.asarray(t, dtype), jnp.asarray(q, dtype), bone, "rotation", "LINEAR")

    shrug = rest_translation[0] + 0.02 * up[:, None] * np.array([0.0, 1.0, 0.0])
    channels = (
        Channel(jnp.asarray(t, dtype), jnp.asarray(shrug, dtype), 0, "translation", "LINEAR"),
        rotation(1, (0.0, 0.0, 1.0), 45.0 * up),
        rotation(2, (1.0, 0.0, 0.0), 100.0 * up),
        rotation(3, (0.0, 1.0, 0.0), 40.0 * turn),
    )
    return AnimationClip(channels, name="wave")


def default_arm(
    *, ring_vertices: int = 24, rings_per_unit: float = 150.0, dtype: DTypeLike | None = None
) -> RiggedModel:
    """The built-in default model: a rigged human-like right arm, generated procedurally.

    Skeleton (glTF conventions, every bone's local +y runs along the bone; world +y up, +z forward):

    * ``shoulder`` (root, at the origin, 0.05 m stub; rest rotation -90 degrees about z so the arm lies
      along +x),
    * ``upper_arm`` (head at x = 0.05, 0.30 m),
    * ``forearm`` (elbow at x = 0.35, 0.27 m, rest bend 10 degrees forward about its local x),
    * ``hand`` (wrist, 0.18 m, finger-less, rest extension 10 degrees up about its local z).

    Mesh: a closed, watertight, outward-oriented triangle tube around the chain, from a rounded shoulder cap
    (pole at x = -0.05) to a rounded fingertip at x = 0.79: radius about 0.05 at the shoulder, 0.04 at the
    elbow, 0.03 at the wrist, and a flat hand (half thickness 0.013, half width 0.041). Default 3266 vertices
    and 6528 faces (``2 + rings * ring_vertices`` and ``2 * rings * ring_vertices``). Vertices are in the
    rest pose, which is the bind pose. Skin weights blend neighbouring bones with a smoothstep over +-0.04 m
    (shoulder joint, wrist) and +-0.05 m (elbow) along the chain: at most two influences per vertex, unused
    slots weight 0 with joint 0; all four bones are joints.

    Clip ``"wave"`` (2 s, 9 LINEAR keys every 0.25 s, rigid only, no scale): a 2 cm shoulder shrug
    (root translation), a 45 degree arm raise (upper_arm about local z) and an extra 100 degree elbow
    flexion (forearm about local x), all 0 -> max (t = 1 s) -> 0 as sin^2; and a wrist twist of +-40 degrees about the
    hand's axis (a full sine period).

    Args:
        ring_vertices: vertices per cross-section ring (>= 3).
        rings_per_unit: cross-section rings per metre along the arm (> 0).
        dtype: float dtype of the arrays; default the default JAX float (float64 under x64). Integer arrays
            are int32.

    Returns:
        RiggedModel named ``"default_arm"`` with one clip.
    """
    if isinstance(ring_vertices, bool) or not isinstance(ring_vertices, int) or ring_vertices < 3:
        raise ValueError(f"ring_vertices: expected an int >= 3, got {ring_vertices!r}")
    if not np.isfinite(rings_per_unit) or rings_per_unit <= 0:
        raise ValueError(f"rings_per_unit: expected a finite number > 0, got {rings_per_unit!r}")
    dtype = jnp.result_type(float) if dtype is None else jnp.dtype(dtype)
    if not jnp.issubdtype(dtype, jnp.floating):
        raise ValueError(f"dtype: expected a floating dtype, got {dtype}")

    b = len(_PARENTS)
    translation = np.zeros((b, 3))
    translation[1:, 1] = _LENGTHS[:-1]
    rest = Rotation.from_rotvec(np.radians(_REST))
    rotation = rest.as_quat()
    G = _global_matrices(translation, rotation)

    # The straight template: the chain with only the root's rotation, so every bone lies along +x.
    straight = _global_matrices(translation, np.where(np.arange(b)[:, None] == 0, rotation, [0.0, 0.0, 0.0, 1.0]))
    heads = straight[:, 0, 3]
    s, radii = _rings(rings_per_unit)
    theta = 2 * np.pi * np.arange(ring_vertices) / ring_vertices
    rings = np.stack(
        [
            np.broadcast_to(s[1:-1, None], (len(s) - 2, ring_vertices)),
            radii[1:-1, :1] * np.cos(theta),
            radii[1:-1, 1:] * np.sin(theta),
        ],
        -1,
    ).reshape(-1, 3)
    points = np.concatenate([[[s[0], 0.0, 0.0]], rings, [[s[-1], 0.0, 0.0]]])
    s_points = np.concatenate([s[:1], np.repeat(s[1:-1], ring_vertices), s[-1:]])

    # blend[:, k]: how far joint k (head of bone k + 1) has turned in, per vertex
    blend = _smoothstep((s_points[:, None] - heads[1:] + _BLEND) / (2 * _BLEND))
    # Bend the template: each joint's rest rotation about its straight head, turned in by the blend, outer first.
    T = np.tile(np.eye(4), (len(points), 1, 1))
    for k in range(1, b):
        R = np.tile(np.eye(4), (len(points), 1, 1))
        R[:, :3, :3] = Rotation.from_rotvec(blend[:, k - 1, None] * rest[k].as_rotvec()).as_matrix()
        T = T @ straight[k] @ R @ np.linalg.inv(straight[k])
    V = np.einsum("nij,nj->ni", T[:, :3, :3], points) + T[:, :3, 3]
    F = _tube_faces(len(s) - 2, ring_vertices)

    # Weights telescope: bone k gets blend_k - blend_{k+1}; sort the influences so unused slots come last.
    cumulative = np.concatenate([np.ones((len(V), 1)), blend, np.zeros((len(V), 1))], 1)
    weights = cumulative[:, :-1] - cumulative[:, 1:]
    order = np.argsort(-weights, axis=1, kind="stable")[:, :4]
    W = np.take_along_axis(weights, order, 1)
    J = np.where(W > 0, order, 0)

    def float_(x):
        return jnp.asarray(x, dtype=dtype)

    mesh = SkinnedMesh(
        V=float_(V),
        F=jnp.asarray(F, jnp.int32),
        J=jnp.asarray(J, jnp.int32),
        W=float_(W),
        inverse_bind=float_(np.linalg.inv(G)),
        joints=tuple(range(b)),
        primitive_sizes=((len(V), len(F)),),
    )
    skeleton = Skeleton(float_(translation), float_(rotation), float_(np.ones((b, 3))), _PARENTS, _NAMES)
    return RiggedModel(mesh, skeleton, (_wave_clip(translation, rotation, dtype),), name="default_arm")
