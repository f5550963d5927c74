"""Plane predicates of the cutting algorithm, both ways of Table 1 of the cut/tear/drill paper.

* ``"euclidean"``: side of a point ``n . x - d`` and the segment-plane parameter from the two signed
  distances, in numpy.
* ``"ga"``: side of a point by the inner product of its conformal point with the plane in vector form,
  ``X . P = n . x - d`` (eq. 3, 5), and the segment-plane intersection by the meet of the line
  ``X_i ^ X_j ^ einf`` with the plane's direct form (a flat point ``x ^ einf + eo ^ einf``, scaled),
  evaluated by the jaxcga kernel.

Both return the same numbers up to rounding; the benchmark times them side by side.
"""

from __future__ import annotations

from typing import cast

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga

PREDICATES: tuple[str, ...] = ("euclidean", "ga")
"""The predicate families of Table 1 that ``predicates=`` selects."""


@jax.jit
def _ga_side(V, plane_values):
    plane = cga.Multivector(plane_values, cga.plane(jnp.ones(3), jnp.zeros(())).blades)
    return cga.plane_signed_distance(plane, cga.up(V))


@jax.jit
def _ga_edge_points(A, B, plane_values):
    plane = cga.Multivector(plane_values, cga.plane(jnp.ones(3), jnp.zeros(())).blades)
    flat = cga.meet(cga.line(cga.up(A), cga.up(B)), cga.undual(plane))
    # A flat point is lambda (x ^ einf + eo ^ einf): divide out lambda.
    x = jnp.stack([_coefficient(flat, f"e{i}inf") for i in (1, 2, 3)], axis=-1)
    return x / _coefficient(flat, "eoinf")[..., None]


def _coefficient(m: cga.Multivector, blade: str) -> Array:
    # a blade name selects its coefficient array (Multivector.__getitem__ is not annotated)
    return cast(Array, m[blade])


def signed_distances(
    V: Float[ArrayLike, "n 3"], n: Float[np.ndarray, "3"], d: float, predicates: str = "euclidean"
) -> Float[np.ndarray, " n"]:
    """Signed distance ``n . x - d`` of every vertex (n, 3) from the plane."""
    if predicates == "ga":
        plane = cga.plane(jnp.asarray(n), jnp.asarray(d))
        return np.asarray(_ga_side(jnp.asarray(V, jnp.float64), plane.values))
    return np.asarray(V, np.float64) @ n - d


def edge_points(
    A: Float[np.ndarray, "p 3"],
    B: Float[np.ndarray, "p 3"],
    sA: Float[np.ndarray, " p"],
    sB: Float[np.ndarray, " p"],
    n: Float[np.ndarray, "3"],
    d: float,
    predicates: str = "euclidean",
) -> tuple[Float[np.ndarray, "p 3"], Float[np.ndarray, " p"]]:
    """Intersection of the segments A-B (p, 3) with the plane, and their parameters t along A->B.
    The segments must cross the plane (signed distances sA, sB of opposite signs)."""
    t = sA / (sA - sB)
    if predicates == "ga":
        plane = cga.plane(jnp.asarray(n), jnp.asarray(d))
        X = np.asarray(_ga_edge_points(jnp.asarray(A), jnp.asarray(B), plane.values))
        return X, t
    return A + t[:, None] * (B - A), t
