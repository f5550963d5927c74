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

    ``alpha`` broadcasts against the batch shape (an array of alphas gives a batch of blends).

    Args:
        m1: versors (or any multivectors), batch shape broadcasting with ``m2``'s and ``alpha``'s.
        m2: versors on the same kind of blades.
        alpha: (...) blend parameters, 0 gives ``m1``, 1 gives ``m2``.
        renormalize: normalize the blend (``normalize``).
    Returns:
        The blends.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T1, T2 = cga.translator(jnp.zeros(3)), cga.translator(jnp.array([2.0, 0, 0]))
        >>> cga.apply_to_points(cga.blend_linear(T1, T2, 0.25), jnp.zeros(3)).round(6).tolist()
        [0.5, 0.0, 0.0]
    """
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
    (m1, alpha) with (m2, 1 - alpha).

    Args:
        m1: motors or similitudes, batch shape broadcasting with ``m2``'s and ``alpha``'s.
        m2: motors or similitudes.
        alpha: (...) blend parameters, 0 gives ``m1``, 1 gives ``m2``.
    Returns:
        The blends, along the screw motion from ``m1`` to ``m2``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> R0, R1 = cga.rotor(jnp.array([0, 0, 1.0]), 0.0), cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2)
        >>> R = cga.blend_log(R0, R1, 0.5)  # an eighth of a turn
        >>> [round(v, 6) + 0.0 for v in cga.apply_to_points(R, jnp.array([1.0, 0, 0])).tolist()]
        [0.707107, 0.707107, 0.0]
    """
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
        weights: ``(..., k)`` blending weights (not required to sum to one; they usually do).

    Returns:
        The blended versors, batch shape (...).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> keys = cga.translator(jnp.array([[0.0, 0, 0], [4.0, 0, 0]]))  # k = 2 key versors
        >>> M = cga.blend_weighted(keys, jnp.array([0.75, 0.25]))
        >>> cga.apply_to_points(M, jnp.zeros(3)).round(6).tolist()
        [1.0, 0.0, 0.0]
    """
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
