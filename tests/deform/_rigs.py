"""Small hand-made rigs for tests: random skeletons, poses and skinned point clouds."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

import deform
import jaxcga as cga


def unit_quaternions(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def random_model(seed=0, parents=(-1, 0, 1, 1, 3), n=40, influences=4, rest_scale=None):
    """A random rig: rest TRS with (optionally) uniform scales, random weights over the joints."""
    rng = np.random.default_rng(seed)
    b = len(parents)
    scale = (
        np.ones((b, 3))
        if rest_scale is None
        else np.repeat(rng.uniform(rest_scale[0], rest_scale[1], (b, 1)), 3, axis=1)
    )
    skeleton = deform.Skeleton(
        jnp.asarray(rng.normal(size=(b, 3))),
        jnp.asarray(unit_quaternions(rng, b)),
        jnp.asarray(scale),
        tuple(parents),
        tuple(f"bone{i}" for i in range(b)),
    )
    joints = tuple(range(1, b)) if b > 1 else (0,)
    bind = deform.forward_kinematics_matrices(skeleton.parents, deform.local_matrices(skeleton))
    inverse_bind = jnp.linalg.inv(bind[jnp.asarray(joints)])
    V = jnp.asarray(rng.normal(size=(n, 3)))
    J = jnp.asarray(rng.integers(0, len(joints), size=(n, influences)), jnp.int32)
    W = rng.random((n, influences))
    W[:, -1] = 0.0  # an unused slot, as in real files
    W = jnp.asarray(W / W.sum(axis=1, keepdims=True))
    F = jnp.asarray(np.arange(n - n % 3).reshape(-1, 3), jnp.int32)
    mesh = deform.SkinnedMesh(V, F, J, W, inverse_bind, joints, ((n, F.shape[0]),))
    return deform.RiggedModel(mesh, skeleton, name=f"random{seed}")


def random_pose(seed, b, scale_range=None):
    """Random local similitudes, batch (b,)."""
    rng = np.random.default_rng(seed)
    scale = np.ones(b) if scale_range is None else rng.uniform(scale_range[0], scale_range[1], b)
    q = unit_quaternions(rng, b)
    return cga.similitude(
        cga.quaternion_to_rotor(jnp.asarray(q)), jnp.asarray(rng.normal(size=(b, 3))), jnp.asarray(scale)
    )


def scaled_keys_model(path, seed=7):
    """A random rig whose clip keys translation, rotation and a uniform scale (0.5 .. 2.5) on every bone
    (LINEAR, irregular key times), written to ``path`` (.glb) and read back: the model and the file
    then hold the same float32 data for an independent reader."""
    rng = np.random.default_rng(seed)
    model = random_model(seed, n=60, rest_scale=(0.8, 1.25))
    times = jnp.asarray([0.0, 0.4, 1.1, 1.5])
    channels = []
    for bone in range(model.skeleton.num_bones):
        scale = np.repeat(rng.uniform(0.5, 2.5, (4, 1)), 3, axis=1)
        channels += [
            deform.Channel(times, jnp.asarray(rng.normal(size=(4, 3))), bone, "translation", "LINEAR"),
            deform.Channel(times, jnp.asarray(unit_quaternions(rng, 4)), bone, "rotation", "LINEAR"),
            deform.Channel(times, jnp.asarray(scale), bone, "scale", "LINEAR"),
        ]
    clip = deform.AnimationClip(tuple(channels), "scaled")
    deform.save_model(deform.RiggedModel(model.mesh, model.skeleton, (clip,), "scaled_keys"), path)
    return deform.load_model(path)
