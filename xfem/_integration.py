"""Exact integration over element subdomains bounded by triangle meshes: sec. 3.5 and 4.3 of the XFEM paper,
eq. 13 (mass), 14 (body force) and 19-21 (element and subdomain integrals by the divergence theorem).

Moments by the divergence theorem (eq. 21). A homogeneous polynomial f of degree k is the divergence of
``F(X) = X f(X) / (3 + k)`` (Euler: ``X . grad f = k f``). On a flat triangle (v0, v1, v2) with
``N = (v1 - v0) x (v2 - v0)``, ``X . N = v0 . N = det[v0 v1 v2]`` is constant, so the flux of F is
``det / (2 A (3 + k)) int_T f dS`` with the exact triangle integrals ``int_T 1 = A``, ``int_T X = A s / 3``,
``int_T X X^T = A (s s^T + sum_a v_a v_a^T) / 12`` (``s = v0 + v1 + v2``; from ``int_T l_a l_b = A (1 +
delta_ab) / 12`` for barycentric l). Summed over the outward-oriented triangles of a closed mesh:

    volume = sum det / 6,   int X = sum det s / 24,   int X X^T = sum det (s s^T + sum_a v_a v_a^T) / 120.

These are exact (the cone of each triangle over the origin is a tet, and these are its closed-form moments),
so mass entries (degree 2) and loads (degree 1) of linear tets are exact on any polyhedral piece. Moments are
taken about a chosen origin: near the piece (the centroid of its tet) the products above stay small and the
rounding stays relative to the piece's size, not to its distance from the world origin. The mass then has a
relative error of a few ulps times the tet's aspect ratio (about 1e-15 for fair tets, 1e-14 for slivers with
diam^3 / volume ~ 300).

Mass and load of a piece. With linear shape functions ``N_a(X) = c_a + g_a . (X - o)`` of the piece's tet,
``int N_a N_b = c_a c_b V + c_a g_b . m1 + c_b g_a . m1 + g_a^T m2 g_b`` and ``int N_a = c_a V + g_a . m1``
for the piece's moments (V, m1, m2) about o: eq. 13 restricted to the piece (times rho; the enrichment
``psi`` is 1 on it) and eq. 14 per unit body force. The elastic energy of a piece is ``psi(F) V`` (sec. 4.3),
F constant on it. On a whole tet these give the FEM closed forms ``rho V (1 + delta_ab) / 20`` and ``V / 4``.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

from _jaxcga_shared.checks import check_positive, check_real

_CLOSED_MESSAGE = (
    "F: each piece must be a closed, consistently oriented triangle mesh (every directed edge "
    "(a, b) matched by an edge (b, a) of the same piece)"
)


class Moments(NamedTuple):
    """Integrals over solids (host numpy, float64), about an origin o.

    Attributes:
        volume: (...,) ``int 1``.
        first: (..., 3) ``int (X - o)``.
        second: (..., 3, 3) ``int (X - o)(X - o)^T``, symmetric.
    """

    volume: Float[np.ndarray, "*batch"]
    first: Float[np.ndarray, "*batch 3"]
    second: Float[np.ndarray, "*batch 3 3"]


def _host_index(x, shape: tuple, bound: int, name: str, what: str) -> np.ndarray:
    x = np.asarray(x)
    if (
        x.ndim != len(shape)
        or any(s is not None and s != d for s, d in zip(shape, x.shape))
        or not np.issubdtype(x.dtype, np.integer)
    ):
        expected = ", ".join("m" if s is None else str(s) for s in shape)
        raise ValueError(f"{name}: expected integer {what} of shape ({expected}), got {x.dtype} {x.shape}")
    x = x.astype(np.int64)
    if x.size and (x.min() < 0 or x.max() >= bound):
        raise ValueError(f"{name}: {what} must lie in [0, {bound}), got [{x.min()}, {x.max()}]")
    return x


def _check_closed(F: np.ndarray, piece: np.ndarray) -> None:
    """ValueError unless the directed edges of each piece pair up with their reverses (closed and oriented)."""
    p = np.repeat(piece, 3)
    a, b = F.ravel(), F[:, [1, 2, 0]].ravel()
    forward = np.stack([p, a, b], axis=1)
    backward = np.stack([p, b, a], axis=1)
    # equal multisets of rows: sort both lexicographically and compare
    forward = forward[np.lexsort(forward.T[::-1])]
    backward = backward[np.lexsort(backward.T[::-1])]
    if not np.array_equal(forward, backward):
        bad = forward[np.argmax(np.any(forward != backward, axis=1))]
        raise ValueError(f"{_CLOSED_MESSAGE}; piece {bad[0]} has an unmatched edge near ({bad[1]}, {bad[2]})")


def moments_of_pieces(
    V: Float[npt.ArrayLike, "n 3"],
    F: Int[npt.ArrayLike, "m 3"],
    piece: Int[npt.ArrayLike, " m"],
    n_pieces: int,
    origin: Float[npt.ArrayLike, " 3"] | Float[npt.ArrayLike, "n_pieces 3"] | None = None,
) -> Moments:
    """Volume, first and second moments of many closed triangle meshes at once (eq. 21, exact).

    All pieces share the vertex array; triangle t belongs to piece ``piece[t]``. One vectorized pass
    (per-triangle closed forms, then one ``np.bincount``), for the thousands of small element
    subdomains that the Booleans of sec. 4.3 produce. A piece with no triangles gets zeros.

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int triangles, outward oriented (counter-clockwise seen from outside); each piece closed.
        piece: (m,) int piece index of each triangle, in [0, n_pieces).
        n_pieces: number of pieces.
        origin: None (the world origin), (3,) or (n_pieces, 3): the point o about which each piece's
            moments are taken; a point near the piece (its tet's centroid) keeps them accurate.
    Returns:
        ``Moments`` with volume (n_pieces,), first (n_pieces, 3) ``int (X - o)``, second (n_pieces, 3, 3)
        ``int (X - o)(X - o)^T``, float64.
    Raises:
        ValueError: bad shapes or indices, non-finite values, a piece that is not closed and consistently
        oriented, or one oriented inward (negative volume).
    """
    if not isinstance(n_pieces, (int, np.integer)) or isinstance(n_pieces, bool) or n_pieces < 0:
        raise ValueError(f"n_pieces: expected a non-negative int, got {n_pieces!r}")
    n_pieces = int(n_pieces)
    V = check_real("V", V, (None, 3), "real positions")
    F = _host_index(F, (None, 3), len(V), "F", "triangle vertex indices")
    piece = _host_index(piece, (len(F),), n_pieces, "piece", "piece indices")
    if origin is None:
        origin = np.zeros((n_pieces, 3))
    else:
        origin = np.asarray(origin)
        shape = (3,) if origin.ndim == 1 else (n_pieces, 3)
        origin = np.broadcast_to(check_real("origin", origin, shape, "points"), (n_pieces, 3))
    _check_closed(F, piece)

    values, det = triangle_moment_terms(np, V[F] - origin[piece][:, None, :])
    # one bincount over (piece, column) pairs: faster than np.add.at
    slots = (piece[:, None] * 13 + np.arange(13)).ravel()
    sums = np.bincount(slots, weights=values.ravel(), minlength=13 * n_pieces).reshape(n_pieces, 13)
    scale = np.bincount(piece, weights=np.abs(det) / 6, minlength=n_pieces)
    volume = sums[:, 0]
    inward = volume < -1e-12 * scale  # rounding of a flat piece may give a tiny negative volume
    if np.any(inward):
        k = int(np.argmax(inward))
        raise ValueError(f"F: piece {k} is oriented inward (volume {volume[k]:.3g}); flip its triangles")
    second = sums[:, 4:].reshape(n_pieces, 3, 3)
    return Moments(volume, sums[:, 1:4], (second + np.swapaxes(second, 1, 2)) / 2)


def triangle_moment_terms(xp, v):
    """The closed forms of eq. 21 per boundary triangle: the moments of the tet (o, v0, v1, v2), signed.

    Args:
        xp: the array namespace, numpy or jax.numpy (``xfem._cut_system`` differentiates them).
        v: (m, 3 corners, 3) the triangles' corners relative to the origin o.
    Returns:
        (m, 13) volume, first moment (3) and second moment (9, row-major) of each triangle's cone, and the
        (m,) determinants (6 times the signed volumes).
    """
    det = xp.einsum("ij,ij->i", v[:, 0], xp.cross(v[:, 1], v[:, 2]))
    s = v.sum(axis=1)
    outer = s[:, :, None] * s[:, None, :] + xp.matmul(xp.swapaxes(v, 1, 2), v)  # matmul: faster than einsum here
    values = xp.concatenate(
        [det[:, None] / 6, det[:, None] * s / 24, (det[:, None, None] * outer / 120).reshape(-1, 9)], axis=1
    )
    return values, det


def polyhedron_moments(
    V: Float[npt.ArrayLike, "n 3"], F: Int[npt.ArrayLike, "m 3"], origin: Float[npt.ArrayLike, " 3"] | None = None
) -> Moments:
    """Volume, first and second moments of the solid bounded by one closed triangle mesh (eq. 21, exact).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int triangles, closed and outward oriented.
        origin: None (the world origin) or (3,): the point o about which the moments are taken.
    Returns:
        ``Moments`` with volume (), first (3,) ``int (X - o)``, second (3, 3) ``int (X - o)(X - o)^T``.
    Raises:
        ValueError: as ``moments_of_pieces``.
    """
    F = np.asarray(F)
    if origin is not None:
        origin = check_real("origin", origin, (3,), "a point")
    moments = moments_of_pieces(V, F, np.zeros(F.shape[:1], np.int64), 1, origin)
    return Moments(*(m[0] for m in moments))


def linear_shape_coefficients(Xe, origin=None) -> tuple[np.ndarray, np.ndarray]:
    """Coefficients of the linear shape functions ``N_a(X) = c_a + g_a . (X - o)`` of tets (eq. 5).

    ``c_a = N_a(o)`` are the barycentric coordinates of o, ``g_a = grad N_a``.

    Args:
        Xe: (..., 4, 3) the tets' corner positions.
        origin: None (the world origin) or (..., 3): the point o of each tet, the same as the ``origin``
            its pieces' moments are taken about.
    Returns:
        c (..., 4), g (..., 4, 3), float64.
    Raises:
        ValueError: bad shapes, non-finite values, a degenerate (zero-volume) tet.
    """
    Xe = np.asarray(Xe)
    if Xe.ndim < 2:
        raise ValueError(f"Xe: expected tet corners of shape (..., 4, 3), got {Xe.shape}")
    Xe = check_real("Xe", Xe, Xe.shape[:-2] + (4, 3), "tet corners")
    origin = (
        np.zeros(Xe.shape[:-2] + (3,))
        if origin is None
        else check_real("origin", origin, Xe.shape[:-2] + (3,), "points")
    )
    a, b, c = (Xe[..., k, :] - Xe[..., 0, :] for k in (1, 2, 3))
    bc, ca, ab = np.cross(b, c), np.cross(c, a), np.cross(a, b)
    det = np.sum(a * bc, axis=-1)
    if np.any(~(np.abs(det) > 0)):
        raise ValueError("Xe: every tet needs a non-zero volume")
    rows = np.stack([bc, ca, ab], axis=-2) / det[..., None, None]
    g = np.concatenate([-rows.sum(axis=-2, keepdims=True), rows], axis=-2)
    lam = np.einsum("...aj,...j->...a", rows, origin - Xe[..., 0, :])
    return np.concatenate([1 - lam.sum(axis=-1, keepdims=True), lam], axis=-1), g


def element_piece_integrals(
    c: Float[npt.ArrayLike, "*#batch 4"],
    g: Float[npt.ArrayLike, "*#batch 4 3"],
    moments: Moments,
    density: float | Float[npt.ArrayLike, "*#batch"] = 1.0,
) -> tuple[Float[np.ndarray, "*batch 4 4"], Float[np.ndarray, "*batch 4"], Float[np.ndarray, "*batch"]]:
    """Exact mass (eq. 13) and load (eq. 14) integrals of a tet's linear shape functions over its pieces.

    The batch shapes ``...`` of the arguments broadcast: one tet's (c, g) with (k,) pieces' moments
    gives its k pieces at once.

    Args:
        c: (..., 4) shape-function values at the origin o (``linear_shape_coefficients``).
        g: (..., 4, 3) shape-function gradients.
        moments: ``Moments`` of each piece about the same o: volume (...,), first (..., 3), second (..., 3, 3).
        density: scalar or (...,) mass density rho of each piece.
    Returns:
        mass (..., 4, 4) ``rho int N_a N_b`` (times ``I_3`` for eq. 13's blocks), load (..., 4)
        ``int N_a`` (times the body force density b for eq. 14), volume (...,).
    Raises:
        ValueError: shapes that do not match or broadcast, a non-positive density.
    """
    c, g = np.asarray(c, np.float64), np.asarray(g, np.float64)
    volume, first, second = (np.asarray(m, np.float64) for m in moments)
    tails = (
        ("c", c, (4,)),
        ("g", g, (4, 3)),
        ("moments.volume", volume, ()),
        ("moments.first", first, (3,)),
        ("moments.second", second, (3, 3)),
    )
    for name, x, tail in tails:
        if x.ndim < len(tail) or x.shape[x.ndim - len(tail) :] != tail:
            raise ValueError(f"{name}: expected shape (..., {', '.join(map(str, tail))}), got {x.shape}")
    try:
        batch = np.broadcast_shapes(*(x.shape[: x.ndim - len(tail)] for _, x, tail in tails))
    except ValueError:
        raise ValueError(
            "c, g, moments: batch shapes "
            + ", ".join(str(x.shape[: x.ndim - len(tail)]) for _, x, tail in tails)
            + " do not broadcast"
        ) from None
    rho = check_positive("density", density, ((), batch))
    mass, load = shape_function_integrals(np, c, g, volume, first, second)
    return (
        np.broadcast_to(rho[..., None, None] * mass, batch + (4, 4)),
        np.broadcast_to(load, batch + (4,)),
        np.broadcast_to(volume, batch),
    )


def shape_function_integrals(xp, c, g, volume, first, second):
    """``int N_a N_b`` (..., 4, 4) and ``int N_a`` (..., 4) over solids with moments (volume, first, second) about
    the origin of the shape coefficients (c, g) (module docstring); xp: numpy or jax.numpy."""
    gm = xp.einsum("...aj,...j->...a", g, first)
    cross = c[..., :, None] * gm[..., None, :]
    mass = (
        c[..., :, None] * c[..., None, :] * volume[..., None, None]
        + cross
        + xp.swapaxes(cross, -1, -2)
        + xp.einsum("...ai,...ij,...bj->...ab", g, second, g)
    )
    return mass, c * volume[..., None] + gm
