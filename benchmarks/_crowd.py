"""Random animated characters for the batch benchmark and notebook 02: a random skeleton (a chain with branches),
a tube around every bone, four skinning influences per vertex, and a clip of a few keys per bone.

``random_rig(seed, vertices)`` builds one in JAX's default float dtype (as ``deform.load_model`` reads the test
models: float32, float64 with x64 enabled); ``animate(model, seed)`` gives any model a random clip (Arm5 has
none); ``test_models()`` loads the three rigged test models, each animated."""

from __future__ import annotations

from pathlib import Path

import jax.numpy as jnp
import numpy as np

import deform

DATA = Path(__file__).resolve().parents[1] / "tests" / "data"
TEST_MODELS = ("CesiumMan", "RiggedSimple", "Arm5")


def _quaternion_product(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton products of glTF (x, y, z, w) quaternions, broadcast."""
    (px, py, pz, pw), (qx, qy, qz, qw) = np.moveaxis(p, -1, 0), np.moveaxis(q, -1, 0)
    return np.stack(
        [
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
            pw * qw - px * qx - py * qy - pz * qz,
        ],
        axis=-1,
    )


def _random_rotations(rng: np.random.Generator, shape: tuple[int, ...], angle: float) -> np.ndarray:
    """Quaternions (x, y, z, w) about random axes by angles uniform in [-angle, angle]."""
    axis = rng.normal(size=shape + (3,))
    axis /= np.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * rng.uniform(-angle, angle, shape)[..., None]
    return np.concatenate([np.sin(half) * axis, np.cos(half)], axis=-1)


def animate(model: deform.RiggedModel, seed: int, keys: int | None = None, angle: float = 0.4) -> deform.RiggedModel:
    """``model`` with one LINEAR clip (its only clip): every bone turns about random axes in its own frame, by up
    to ``angle`` radians, at ``keys`` evenly spaced keys (default 3 to 6) over 1 to 3 seconds; the roots
    translate too."""
    rng = np.random.default_rng(seed)
    skeleton = model.skeleton
    dtype = np.asarray(model.mesh.V).dtype
    keys = int(rng.integers(3, 7)) if keys is None else keys
    times = np.linspace(0.0, rng.uniform(1.0, 3.0), keys).astype(dtype)
    rest_q, rest_t = np.asarray(skeleton.rotation, np.float64), np.asarray(skeleton.translation, np.float64)
    turned = _quaternion_product(rest_q[None], _random_rotations(rng, (keys, skeleton.num_bones), angle))
    size = float(np.linalg.norm(np.ptp(np.asarray(model.mesh.V), axis=0)))
    channels = []
    for bone, parent in enumerate(skeleton.parents):
        channels.append(
            deform.Channel(jnp.asarray(times), jnp.asarray(turned[:, bone], dtype), bone, "rotation", "LINEAR")
        )
        if parent < 0:
            moved = rest_t[bone] + 0.05 * size * rng.normal(size=(keys, 3))
            channels.append(
                deform.Channel(jnp.asarray(times), jnp.asarray(moved, dtype), bone, "translation", "LINEAR")
            )
    clip = deform.AnimationClip(tuple(channels), f"random{seed}")
    return deform.RiggedModel(model.mesh, model.skeleton, (clip,), model.name)


def _bind_matrices(parents: list[int], translation: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """(b, 4, 4) global rest matrices of unscaled bones, on the host: the library's are jitted per skeleton, and
    every rig here has its own."""
    x, y, z, w = np.moveaxis(rotation, -1, 0)
    local = np.zeros((len(parents), 4, 4))
    local[:, :3, :3] = np.stack(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    ).transpose(2, 0, 1)
    local[:, :3, 3], local[:, 3, 3] = translation, 1.0
    bind = local.copy()
    for i, p in enumerate(parents):
        if p >= 0:
            bind[i] = bind[p] @ local[i]
    return bind


def _segment_distances(X: np.ndarray, heads: np.ndarray, tails: np.ndarray) -> np.ndarray:
    """(n, b) distance of every point to every segment head -> tail."""
    axis = tails - heads
    s = np.einsum("nbk,bk->nb", X[:, None] - heads[None], axis) / np.maximum(np.sum(axis * axis, axis=1), 1e-12)
    closest = heads[None] + np.clip(s, 0.0, 1.0)[..., None] * axis[None]
    return np.linalg.norm(X[:, None] - closest, axis=-1)


def random_rig(seed: int, vertices: int, bones: tuple[int, int] = (12, 40), influences: int = 4) -> deform.RiggedModel:
    """A random animated character of about ``vertices`` vertices (within one ring of a tube).

    The skeleton has ``bones`` (a range) bones: mostly a chain, a quarter of them branching off an earlier bone,
    with small random rest rotations. Around each bone, from its head to its first child's head (a leaf's
    continues its direction), a tube whose radius swells along it; a vertex takes the ``influences`` nearest
    bones, weighted by inverse distance to the fourth power. Every bone is a joint, bound in the rest pose; the
    clip is ``animate``'s."""
    rng = np.random.default_rng(seed)
    b = int(rng.integers(bones[0], bones[1] + 1))
    parents = [-1] + [i - 1 if rng.random() < 0.75 else int(rng.integers(0, i)) for i in range(1, b)]
    direction = np.array([0.0, 1.0, 0.0]) + 0.5 * rng.normal(size=(b, 3))
    translation = direction / np.linalg.norm(direction, axis=1, keepdims=True) * rng.uniform(0.4, 1.0, (b, 1))
    translation[0] = 0.0
    rotation = _random_rotations(rng, (b,), 0.25)
    skeleton = deform.Skeleton(
        jnp.asarray(translation),
        jnp.asarray(rotation),
        jnp.ones((b, 3)),
        tuple(parents),
        tuple(f"bone{i}" for i in range(b)),
    )
    bind = _bind_matrices(parents, translation, rotation)
    heads = bind[:, :3, 3]
    tails = heads + bind[:, :3, :3] @ np.array([0.0, 0.5, 0.0])
    for child in range(b - 1, 0, -1):  # the first child wins
        tails[parents[child]] = heads[child]
    lengths = np.maximum(np.linalg.norm(tails - heads, axis=1), 1e-3)
    sides = int(np.clip(np.sqrt(vertices / (4 * b)), 6, 48))
    share = vertices / sides * lengths / lengths.sum()
    rings = np.maximum(np.floor(share).astype(int), 2)
    rings[np.argsort(share - np.floor(share))[::-1][: max(vertices // sides - rings.sum(), 0)]] += 1
    V, F = [], []
    theta = 2 * np.pi * np.arange(sides) / sides
    for i in range(b):
        axis = (tails[i] - heads[i]) / lengths[i]
        u = np.cross(axis, rng.normal(size=3))
        u /= np.linalg.norm(u)
        v = np.cross(axis, u)
        s = np.linspace(0.0, 1.0, rings[i])
        radius = 0.12 * (1.0 + 0.5 * np.sin(np.pi * s) + 0.1 * rng.random())
        ring = np.cos(theta)[:, None] * u + np.sin(theta)[:, None] * v
        points = heads[i] + s[:, None, None] * (tails[i] - heads[i]) + radius[:, None, None] * ring[None]
        start = sum(len(x) for x in V)
        V.append(points.reshape(-1, 3))
        a = start + np.arange(rings[i] - 1)[:, None] * sides + np.arange(sides)[None]
        c = start + np.arange(rings[i] - 1)[:, None] * sides + (np.arange(sides)[None] + 1) % sides
        F.append(np.stack([a, c, a + sides, c, c + sides, a + sides], axis=-1).reshape(-1, 3))
    V, F = np.concatenate(V), np.concatenate(F)
    distance = _segment_distances(V, heads, tails)
    J = np.argsort(distance, axis=1)[:, :influences]
    W = 1.0 / (np.take_along_axis(distance, J, axis=1) + 1e-3) ** 4
    mesh = deform.SkinnedMesh(
        jnp.asarray(V),
        jnp.asarray(F, jnp.int32),
        jnp.asarray(J, jnp.int32),
        jnp.asarray(W / W.sum(axis=1, keepdims=True)),
        jnp.asarray(np.linalg.inv(bind)),
        tuple(range(b)),
        ((V.shape[0], F.shape[0]),),
    )
    return animate(deform.RiggedModel(mesh, skeleton, name=f"rig{seed}"), seed)


def test_models() -> list[deform.RiggedModel]:
    """CesiumMan, RiggedSimple and Arm5 from tests/data, each with a clip (Arm5's a random one: it has none)."""
    models = [deform.load_model(DATA / f"{name}.glb") for name in TEST_MODELS]
    return [model if model.clips else animate(model, seed=5) for model in models]


def crowd(count: int, seed: int, vertices: tuple[int, int] = (1_000, 50_000), shrink: float = 1.0) -> list:
    """``count`` random rigs with vertex counts spread geometrically over ``vertices`` (shuffled), each count
    times ``shrink`` (a second batch that fits the first one's capacities: 0.95)."""
    rng = np.random.default_rng(seed)
    sizes = rng.permutation(np.geomspace(*vertices, count)) * shrink
    return [random_rig(seed * 1_000 + i, int(n)) for i, n in enumerate(sizes)]
