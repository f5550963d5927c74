"""Blending of versors (cut/tear/drill paper sec. 2.5; deformation paper eq. 1).

* linear: ``(1 - a) m1 + a m2``, optionally renormalized (the paper's choice for frames generated
  on the fly);
* logarithmic: ``m1 exp(a log(m1^-1 m2))`` (the paper's choice for a model's animation data);
* weighted: ``exp(sum_j w_j log R_j)`` over many key motors (deformation paper eq. 1).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import ArrayLike, Float

from jaxcga._exp_log import exp, log
from jaxcga._multivector import KINDS, Multivector, broadcast_batch
from jaxcga._operations import normalize, versor_inverse


def _check_pair(m1: Multivector, m2: Multivector) -> None:
    if not isinstance(m1, Multivector) or not isinstance(m2, Multivector):
        raise ValueError("m1, m2: expected Multivectors")
    broadcast_batch("m1", m1.batch_shape, "m2", m2.batch_shape)


def blend_linear(
    m1: Multivector, m2: Multivector, alpha: Float[ArrayLike, "*batch"], renormalize: bool = True
) -> Multivector:
    """``(1 - alpha) m1 + alpha m2``; with ``renormalize`` the result is a unit versor again.

    ``alpha`` broadcasts against the batch shape (an array of alphas gives a batch of blends)."""
    _check_pair(m1, m2)
    alpha = jnp.asarray(alpha, m1.dtype)
    out = m1 * (1 - alpha) + m2 * alpha
    if not renormalize:
        return out
    if set(out.blades) <= set(KINDS["motor"]):
        return normalize(out)
    # A sum of similitudes is not a similitude; project it back (rotor normalized, dilation from the
    # tanh ratio, translation from the einf part) through log / exp, which read exactly those parts.
    return exp(log(out.embed(KINDS["similitude"])))


def blend_log(m1: Multivector, m2: Multivector, alpha: Float[ArrayLike, "*batch"]) -> Multivector:
    """``m1 exp(alpha log(m1^-1 m2))`` for motors or similitudes; symmetric under swapping
    (m1, alpha) with (m2, 1 - alpha)."""
    _check_pair(m1, m2)
    alpha = jnp.asarray(alpha, m1.dtype)
    relative = versor_inverse(m1) * m2
    kind = set(m1.blades) | set(m2.blades)
    blades = KINDS["motor"] if kind <= set(KINDS["motor"]) else KINDS["similitude"]
    step = exp(log(relative.embed(blades)) * alpha)
    return (m1 * step).embed(blades)


def blend_weighted(versors: Multivector, weights: Float[ArrayLike, "... k"]) -> Multivector:
    """``exp(sum_j w_j log V_j)`` (deformation paper eq. 1).

    Args:
        versors: motors or similitudes with batch shape ``(..., k)``: k key versors.
        weights: ``(..., k)`` blending weights (not required to sum to one; they usually do)."""
    if not isinstance(versors, Multivector) or not versors.batch_shape:
        raise ValueError("versors: expected a Multivector with batch shape (..., k)")
    weights = jnp.asarray(weights, versors.dtype)
    if weights.ndim == 0 or weights.shape[-1] != versors.batch_shape[-1]:
        raise ValueError(
            f"weights: expected shape (..., {versors.batch_shape[-1]}) to match versors, got {weights.shape}"
        )
    logs = log(versors)
    combined = jnp.sum(logs.values * weights[..., None], axis=-2)
    return exp(Multivector(combined, logs.blades))
