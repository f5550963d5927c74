"""Mesh utilities used by more than one package: the bounding-box diagonal (the unit of tolerances and fitting
errors in deform and cutting) and the signed volume enclosed by a triangle mesh. Private to the distribution."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int


def bounding_diagonal(V) -> float:
    """Length of the diagonal of the axis-aligned bounding box of the points V (n, 3), on the host (0 when
    empty)."""
    V = np.asarray(V)
    if not len(V):
        return 0.0
    # column by column: numpy's axis-0 reduction over (n, 3) rows is some 20x slower
    return float(np.sqrt(sum((V[:, k].max() - V[:, k].min()) ** 2 for k in range(V.shape[1]))))


def signed_volume(V: Float[Array, "... n 3"], F: Int[Array, "m 3"]) -> Float[Array, ...]:
    """Signed volume enclosed by a closed, consistently oriented triangle mesh, ``sum_f det(v0, v1, v2) / 6``
    (positive for outward normals); leading axes of V are batches. JAX, differentiable in V; the caller
    checks the shapes and indices."""
    a, b, c = (V[..., F[:, k], :] for k in range(3))
    return jnp.sum(a * jnp.cross(b, c), axis=(-2, -1)) / 6
