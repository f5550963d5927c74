"""Plane predicates of the cutting algorithm, both ways of Table 1 of the cut/tear/drill paper.

* ``"euclidean"``: side of a point ``n . x - d`` and the segment-plane point ``a + t (b - a)`` with ``t`` from
  the two signed distances.
* ``"ga"``: side of a point by the inner product of its conformal point with the plane in vector form,
  ``X . P = n . x - d`` (eq. 3, 5), and the segment-plane point by the meet of the line
  ``A ^ B ^ einf`` with the plane's direct form ``P I`` (a flat point ``lambda (x ^ einf + eo ^ einf)``).

Both run in host numpy, vectorized over the points the same way. The GA products come from the jaxcga
kernel's generated product tables (``_codegen.bilinear_tensor``): for a given plane, ``X . P`` is a linear form
in X and the flat point a bilinear form in (A, B), whose coefficients are the tables contracted with the plane's
components. Only the blades that a result needs are evaluated: the flat point's four, from the conformal points'
components that reach them (e1, e2, e3, eo; the einf component |x|^2 / 2 of ``up(x)`` meets einf . einf = 0 and
einf ^ einf = 0, so its coefficient is structurally zero and it is never formed). The two families give the same
numbers up to rounding; the benchmark times them side by side.
"""

from __future__ import annotations

import functools

import numpy as np
from jaxtyping import ArrayLike, Float

from jaxcga import _algebra as alg
from jaxcga import _codegen

PREDICATES: tuple[str, ...] = ("euclidean", "ga")
"""The predicate families of Table 1 that ``predicates=`` selects."""

# up(x) = x + |x|^2 / 2 einf + eo (eq. 3); a plane n + d einf (eq. 5) has no eo component; a flat point.
_POINT = alg.parse_blades(("e1", "e2", "e3", "eo", "einf"))
_PLANE = alg.parse_blades(("e1", "e2", "e3", "einf"))
_FLAT = alg.parse_blades(("e1inf", "e2inf", "e3inf", "eoinf"))
# the point components that the two products below use, in this order: x (e1, e2, e3), then eo = 1
_USED = alg.parse_blades(("e1", "e2", "e3", "eo"))


def _rows(blades: tuple[int, ...], wanted: tuple[int, ...]) -> list[int]:
    return [blades.index(b) for b in wanted]


@functools.cache
def _side_table() -> np.ndarray:
    """(4, 4) ``S[i, l]``: the coefficient of ``X_i P_l`` in the scalar ``X . P``, X on ``_USED``, P on ``_PLANE``."""
    blades, T = _codegen.bilinear_tensor("inner", _POINT, _PLANE)
    scalar = T[:, :, blades.index(0)]
    if np.any(scalar[_POINT.index(alg.parse_blades(("einf",))[0])]):
        raise AssertionError("X . P depends on the einf component of X")  # the module's claim, checked once
    table = np.ascontiguousarray(scalar[_rows(_POINT, _USED)])
    table.setflags(write=False)
    return table


@functools.cache
def _meet_table() -> np.ndarray:
    """(4, 4, 4, 4) ``C[j, i, k, l]``: the coefficient of ``A_i B_j P_l`` in blade ``_FLAT[k]`` of
    ``(A ^ B ^ einf) v (P I)``, A and B on ``_USED``, P on ``_PLANE``: the products of ``cga.line``,
    ``cga.undual`` and ``cga.meet`` composed."""
    einf = alg.parse_blades(("einf",))
    wedge_blades, wedge = _codegen.bilinear_tensor("outer", _POINT, _POINT)
    line_blades, line = _codegen.bilinear_tensor("outer", wedge_blades, einf)
    # the direct form P I (cga.undual): I is one blade times a coefficient
    ((pseudoscalar, coefficient),) = alg.pseudoscalar_terms().items()
    direct_blades, direct = _codegen.bilinear_tensor("geometric", _PLANE, (pseudoscalar,))
    flat_blades, flat = _codegen.bilinear_tensor("regressive", line_blades, direct_blades)
    composed = np.einsum(
        "ija,ab,lc,bck->jikl",
        wedge,
        line[:, 0, :],
        float(coefficient) * direct[:, 0, :],
        flat[:, :, _rows(flat_blades, _FLAT)],
    )
    unused = _rows(_POINT, tuple(b for b in _POINT if b not in _USED))
    if np.any(composed[unused]) or np.any(composed[:, unused]):
        raise AssertionError("the flat point depends on the einf components of A or B")
    used = _rows(_POINT, _USED)
    table = np.ascontiguousarray(composed[np.ix_(used, used)])
    table.setflags(write=False)
    return table


def _plane_vector(n: Float[np.ndarray, "3"], d: float) -> Float[np.ndarray, "4"]:
    """The plane's components on ``_PLANE``: ``n + d einf`` (eq. 5, n of unit length)."""
    return np.array([n[0], n[1], n[2], d])


def signed_distances(
    V: Float[ArrayLike, "n 3"], n: Float[np.ndarray, "3"], d: float, predicates: str = "euclidean"
) -> Float[np.ndarray, " n"]:
    """Signed distance ``n . x - d`` of every vertex (n, 3) from the plane (``n`` of unit length): with
    ``predicates="ga"`` the inner product ``up(x) . P`` of its conformal point with the plane vector."""
    V = np.asarray(V, np.float64)
    if predicates == "ga":
        # X . P = sum_i X_i (S P)_i: a linear form in the conformal point, whose eo component is 1
        form = _side_table() @ _plane_vector(n, d)
        return V @ form[:3] + form[3]
    return V @ n - d


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
    The segments must cross the plane (signed distances sA, sB of opposite signs); with
    ``predicates="ga"`` the points are the meets of the lines ``A ^ B ^ einf`` with the plane."""
    t = sA / (sA - sB)
    if predicates == "ga":
        # flat_k = sum_ij A_i B_j M_jik with M = C P and A_eo = B_eo = 1: one matrix product with B's components,
        # then a row-wise one with A's (a few numpy calls for all points; M's structural zeros cost less than a call
        # per term would)
        M = (_meet_table() @ _plane_vector(n, d)).reshape(4, 16)  # rows j, columns (i, k)
        BM = (B @ M[:3] + M[3]).reshape(len(B), 4, 4)  # sum_j B_j M_jik, (p, i, k)
        flat = np.einsum("pi,pik->pk", A, BM[:, :3]) + BM[:, 3]
        return flat[:, :3] / flat[:, 3:], t
    return A + t[:, None] * (B - A), t
