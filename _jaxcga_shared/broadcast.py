"""Numpy's rank promotion made explicit: every package broadcasts arrays of different ranks by adding leading unit
axes itself, so that it also runs where a caller makes implicit rank promotion raise
(``jax_numpy_rank_promotion="raise"``, as the test suite does). Private to the distribution."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike


def lift_rank(a: ArrayLike, ndim: int) -> Array:
    """``a`` with leading unit axes up to ``ndim`` axes (unchanged if it has as many or more).

    Args:
        a: an array of any shape.
        ndim: the number of axes wanted.
    Returns:
        ``a`` reshaped to ``(1, ..., 1, *a.shape)``, numpy's broadcast of ``a`` against an array of ``ndim`` axes."""
    a = jnp.asarray(a)
    return a.reshape((1,) * (ndim - a.ndim) + a.shape) if a.ndim < ndim else a


def same_rank(a: ArrayLike, b: ArrayLike) -> tuple[Array, Array]:
    """``a`` and ``b`` with as many axes each (leading unit axes added to the one with fewer)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    n = max(a.ndim, b.ndim)
    return lift_rank(a, n), lift_rank(b, n)
