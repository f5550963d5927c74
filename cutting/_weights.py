"""Skinning weights of new vertices (cut/tear/drill paper, sec. 4.3).

A new vertex X on a face or an edge gets the barycentric blend of its corners' weights,
``w = p w_A + q w_B + r w_C`` over the union of their bones; when more than ``k`` bones remain, the
``k`` largest are kept and renormalized to sum to one ("weight of X via barycentric coordinates").
"""

from __future__ import annotations

import numpy as np
from jaxtyping import ArrayLike, Float, Int


def blend_weights(
    J: Int[ArrayLike, "n k"],
    W: Float[ArrayLike, "n k"],
    corners: Int[ArrayLike, "p c"],
    coefficients: Float[ArrayLike, "p c"],
    influences: int | None = None,
) -> tuple[Int[np.ndarray, "p i"], Float[np.ndarray, "p i"]]:
    """Barycentric blend of vertex weights, the top ``influences`` bones kept and renormalized.

    Args:
        J: (n, k) int joint indices per vertex.
        W: (n, k) weights per vertex.
        corners: (p, c) int vertex indices whose weights are blended (c = 2 for an edge point,
            3 for a face point).
        coefficients: (p, c) blending coefficients (barycentric coordinates, rows summing to one).
        influences: bones kept per new vertex (default k, the input's width).
    Returns:
        (J_new (p, influences) int, W_new (p, influences) float): rows sum to one, unused slots
        have weight 0 and joint 0.

    Examples:
        >>> import numpy as np
        >>> import cutting
        >>> J, W = np.array([[0, 1], [1, 2]]), np.array([[0.5, 0.5], [1.0, 0.0]])  # two vertices, 2 influences
        >>> J_new, W_new = cutting.blend_weights(J, W, np.array([[0, 1]]), np.array([[0.5, 0.5]]))  # their midpoint
        >>> J_new.tolist(), W_new.tolist()
        ([[1, 0]], [[0.75, 0.25]])
    """
    J, W = np.asarray(J), np.asarray(W)
    corners, coefficients = np.asarray(corners), np.asarray(coefficients, dtype=np.float64)
    if corners.ndim != 2 or coefficients.shape != corners.shape:
        raise ValueError(f"coefficients: expected shape {corners.shape} (same as corners), got {coefficients.shape}")
    k = J.shape[1]
    influences = k if influences is None else influences
    p = corners.shape[0]
    # Every (new vertex, corner, slot) contributes coefficient * weight to its joint: flatten, then
    # sum equal joints per new vertex by sorting (no dense (p, joints) table).
    joints = J[corners].reshape(p, -1)
    weights = (coefficients[:, :, None] * W[corners]).reshape(p, -1)
    order = np.argsort(joints, axis=1, kind="stable")
    joints = np.take_along_axis(joints, order, axis=1)
    weights = np.take_along_axis(weights, order, axis=1)
    # Merge runs of equal joints: keep the run's first slot with the run's total.
    start = np.ones_like(joints, dtype=bool)
    start[:, 1:] = joints[:, 1:] != joints[:, :-1]
    run = np.cumsum(start, axis=1) - 1
    totals = np.zeros_like(weights)
    np.add.at(totals, (np.repeat(np.arange(p), joints.shape[1]), run.ravel()), weights.ravel())
    merged_joints = np.zeros_like(joints)
    merged_joints[np.nonzero(start)[0], run[start]] = joints[start]
    top = np.argsort(-totals, axis=1, kind="stable")[:, :influences]
    W_new = np.take_along_axis(totals, top, axis=1)
    J_new = np.take_along_axis(merged_joints, top, axis=1)
    W_new = np.where(W_new > 0, W_new, 0.0)
    J_new = np.where(W_new > 0, J_new, 0)
    total = W_new.sum(axis=1, keepdims=True)
    if np.any(total <= 0):
        raise ValueError("W: a new vertex's corners carry no positive weight")
    return J_new.astype(J.dtype), (W_new / total).astype(W.dtype)
