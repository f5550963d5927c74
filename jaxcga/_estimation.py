"""The motor that best aligns two point sets: Horn's closed-form quaternion method (B. K. P. Horn,
"Closed-form solution of absolute orientation using unit quaternions", 1987), as used for the rotor
fit of GA-ARAP in section VII of the deformation paper.

The rotation is the eigenvector of the largest eigenvalue of Horn's symmetric 4x4 matrix built from
the cross-covariance; ``jnp.linalg.eigh`` makes it batched and differentiable (gradients are finite
while the largest eigenvalue is simple, i.e. the points are not degenerate)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from _jaxcga_shared.checks import check_finite, check_vectors
from _jaxcga_shared.platform import EXACT
from jaxcga._multivector import Multivector
from jaxcga._versors import apply_to_points, motor, quaternion_to_rotor


def align_points(
    source: Float[ArrayLike, "... n 3"],
    target: Float[ArrayLike, "... n 3"],
    weights: Float[ArrayLike, "... n"] | None = None,
) -> Multivector:
    """Motor M minimizing sum_i w_i |M(source_i) - target_i|^2.

    Args:
        source: ``(..., n, 3)`` points, n >= 3 not collinear for a unique rotation.
        target: ``(..., n, 3)`` corresponding points.
        weights: optional ``(..., n)`` non-negative weights.
    Returns:
        a motor with batch shape ``...``.

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> source = jnp.array([[0.0, 0, 0], [1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
        >>> M = cga.motor(cga.rotor(jnp.array([1.0, 1.0, 0]), 0.7), jnp.array([0.5, -1.0, 2.0]))
        >>> found = cga.align_points(source, cga.apply_to_points(M, source))
        >>> bool(jnp.allclose(cga.apply_to_points(found, source), cga.apply_to_points(M, source), atol=1e-5))
        True
    """
    p = check_finite("source", check_vectors("source", source))
    q = check_finite("target", check_vectors("target", target))
    if p.ndim < 2 or q.ndim < 2 or p.shape[-2] != q.shape[-2]:
        raise ValueError(f"source, target: expected (..., n, 3) with equal n, got {p.shape} and {q.shape}")
    w = jnp.ones(p.shape[:-1], p.dtype) if weights is None else jnp.asarray(weights, p.dtype)
    if w.shape[-1:] != p.shape[-2:-1]:
        raise ValueError(f"weights: expected shape (..., {p.shape[-2]}), got {w.shape}")
    w = w / jnp.sum(w, axis=-1, keepdims=True)
    cp = jnp.sum(w[..., None] * p, axis=-2)
    cq = jnp.sum(w[..., None] * q, axis=-2)
    s = jnp.einsum("...n,...ni,...nj->...ij", w, p - cp[..., None, :], q - cq[..., None, :], precision=EXACT)
    sxx, sxy, sxz = s[..., 0, 0], s[..., 0, 1], s[..., 0, 2]
    syx, syy, syz = s[..., 1, 0], s[..., 1, 1], s[..., 1, 2]
    szx, szy, szz = s[..., 2, 0], s[..., 2, 1], s[..., 2, 2]
    n = jnp.stack(
        [
            jnp.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
            jnp.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
            jnp.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
            jnp.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1),
        ],
        -2,
    )
    _, vectors = jnp.linalg.eigh(n)
    quat = vectors[..., :, -1]
    quat = quat * jnp.where(quat[..., :1] < 0, -1.0, 1.0)
    r = quaternion_to_rotor(quat)
    t = cq - apply_to_points(r, cp)
    return motor(r, t)
