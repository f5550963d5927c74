"""Writes characters/QuaterniusWorkerDense.glb (tests/data/README.md): QuaterniusWorker.glb welded, every face split
into four at its edge midpoints, twice. The surface is the same; a midpoint gets the weights of its edge's two ends
averaged (per joint), the four largest kept and scaled to sum to one.

Run from the repository root: ``python tests/data/make_dense_character.py``.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse

import deform

HERE = Path(__file__).resolve().parent / "characters"


def split(V, J, W, F, joints: int):
    """Every face of (V, F) split into four at its edge midpoints; (V, J, W, F) of the result."""
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    unique, inverse = np.unique(edges, axis=0, return_inverse=True)
    a, b = unique[:, 0], unique[:, 1]
    rows = np.repeat(np.arange(len(unique)), 2 * J.shape[1])
    per_joint = scipy.sparse.coo_matrix(
        (0.5 * np.concatenate([W[a], W[b]], axis=1).ravel(), (rows, np.concatenate([J[a], J[b]], axis=1).ravel())),
        shape=(len(unique), joints),
    ).toarray()  # duplicates summed: a joint of both ends gets both halves
    J_mid = np.argsort(-per_joint, axis=1, kind="stable")[:, : J.shape[1]]
    W_mid = np.take_along_axis(per_joint, J_mid, axis=1)
    W_mid /= W_mid.sum(axis=1, keepdims=True)
    mid = len(V) + inverse.reshape(3, -1).T  # (m, 3): the midpoints of edges 01, 12, 20 of each face
    (f0, f1, f2), (m01, m12, m20) = F.T, mid.T
    F = np.concatenate([np.stack(c, axis=1) for c in ((f0, m01, m20), (m01, f1, m12), (m20, m12, f2), (m01, m12, m20))])
    return (
        np.concatenate([V, 0.5 * (V[a] + V[b])]),
        np.concatenate([J, J_mid]),
        np.concatenate([W, W_mid]),
        F,
    )


def main():
    jax.config.update("jax_enable_x64", True)
    model = deform.load_model(HERE / "QuaterniusWorker.glb", weld=True)
    mesh = model.mesh
    V, J, W, F = (np.asarray(x) for x in (mesh.V, mesh.J, mesh.W, mesh.F))
    for _ in range(2):
        V, J, W, F = split(V, J, W, F, mesh.num_joints)
    dense = deform.SkinnedMesh(
        V=jnp.asarray(V),
        F=jnp.asarray(F, mesh.F.dtype),
        J=jnp.asarray(J, mesh.J.dtype),
        W=jnp.asarray(W),
        inverse_bind=mesh.inverse_bind,
        joints=mesh.joints,
        primitive_sizes=((len(V), len(F)),),
    )
    out = deform.RiggedModel(mesh=dense, skeleton=model.skeleton, clips=model.clips, name="QuaterniusWorkerDense")
    deform.save_model(out, HERE / "QuaterniusWorkerDense.glb")


if __name__ == "__main__":
    main()
