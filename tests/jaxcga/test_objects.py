"""Geometric objects of jaxcga (points, spheres, planes, lines, circles, point pairs, meets) against
numpy closed forms: circumspheres and circumcircles by linear solves, plane normals by cross
products, distances by norms.

The jaxcga side of each property test is one jitted function (compiled once, then called for every
example): eager execution of the generated products would compile hundreds of small kernels."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import jaxcga as cga
from tests.jaxcga._helpers import SETTINGS, _a, _unit, seeds


def _well_spread(rng, n, min_gap=0.3, scale=1.0):
    """n random points (n <= 4) in general position: no pair closer than min_gap, not coplanar /
    collinear to within a margin."""
    while True:
        p = rng.normal(size=(n, 3)) * scale
        d = np.linalg.norm(p[:, None] - p[None], axis=-1) + np.eye(n) * 1e9
        if d.min() < min_gap * scale:
            continue
        if n >= 3:
            area = np.linalg.norm(np.cross(p[1] - p[0], p[2] - p[0]))
            if area < 0.2 * scale**2:
                continue
        if n == 4:
            vol = abs(np.linalg.det(p[1:] - p[0]))
            if vol < 0.2 * scale**3:
                continue
        return p


def circumsphere(p):
    """Center and radius of the sphere through 4 points: |x - c|^2 equal for all -> linear system."""
    A = 2.0 * (p[1:] - p[0])
    b = np.sum(p[1:] ** 2, axis=1) - np.sum(p[0] ** 2)
    c = np.linalg.solve(A, b)
    return c, np.linalg.norm(p[0] - c)


def circumcircle(p):
    """Center, radius and unit normal of the circle through 3 points (center in their plane)."""
    a, b, c = p
    n = np.cross(b - a, c - a)
    A = np.stack([2 * (b - a), 2 * (c - a), n])
    rhs = np.array([b @ b - a @ a, c @ c - a @ a, n @ a])
    center = np.linalg.solve(A, rhs)
    return center, np.linalg.norm(a - center), n / np.linalg.norm(n)


def assert_proportional(u, v, tol=1e-12):
    """u = k v for some non-zero scalar k (full-array check, k by least squares)."""
    u, v = _a(u).ravel(), _a(v).ravel()
    assert np.linalg.norm(v) > 0 and np.linalg.norm(u) > 0
    k = (u @ v) / (v @ v)
    assert abs(k) > 1e-12
    np.testing.assert_allclose(u, k * v, atol=tol * float(np.linalg.norm(u)))


def assert_same_up_to_sign(u, v, atol):
    u, v = _a(u), _a(v)
    err = min(np.abs(u - v).max(), np.abs(u + v).max())
    assert err <= atol, (u, v)


# ---------------------------------------------------------------- points
@jax.jit
def _points(x):
    X = cga.up(x)
    einf = cga.basis_vector("einf")
    return X, cga.down(X), cga.scalar_product(X, X), cga.scalar_product(X, einf), cga.down(X * -3.5)


@SETTINGS
@given(seeds, st.floats(1e-3, 1e3))
def test_up_down_round_trip_and_null(seed, scale):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(7, 3)) * scale
    X, down, xx, xe, down_scaled = _points(x)
    assert X.batch_shape == (7,)
    np.testing.assert_allclose(_a(down), x, rtol=0, atol=1e-14 * scale)
    # X = x + |x|^2/2 einf + eo (eq. 3): a null vector with X . einf = -1.
    np.testing.assert_array_equal(_a(X["eo"]), 1.0)
    np.testing.assert_allclose(_a(X["einf"]), 0.5 * np.sum(x * x, axis=1), rtol=1e-15)
    np.testing.assert_allclose(_a(xx), 0.0, atol=1e-13 * scale**2)
    np.testing.assert_allclose(_a(xe), -1.0, rtol=1e-15)
    # down accepts any scale of the point.
    np.testing.assert_allclose(_a(down_scaled), x, rtol=0, atol=1e-14 * scale)


def test_up_rejects_bad_shape():
    with pytest.raises(ValueError):
        cga.up(np.zeros((4, 2)))
    with pytest.raises(ValueError):
        cga.up(np.float64(1.0))


def test_down_rejects_non_vector():
    with pytest.raises(ValueError):
        cga.down(cga.rotor(np.array([0.0, 0.0, 1.0]), 0.3))


# ---------------------------------------------------------------- distances
@jax.jit
def _distances(x, y):
    X, Y = cga.up(x), cga.up(y)
    return (
        cga.squared_distance(X, Y),
        cga.distance(X, Y),
        cga.squared_distance(X * 2.5, Y * -0.3),
        cga.distance(cga.up(x[0]), Y),
        cga.distance(X, X),
    )


@SETTINGS
@given(seeds)
def test_squared_distance_and_distance(seed):
    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=(2, 5, 3)) * 3
    ref2 = np.sum((x - y) ** 2, axis=1)
    d2, d, d2_scaled, d_broadcast, d_self = _distances(x, y)
    np.testing.assert_allclose(_a(d2), ref2, rtol=1e-12)
    np.testing.assert_allclose(_a(d), np.sqrt(ref2), rtol=1e-12)
    # Any scale of the conformal points (sec. 2.2).
    np.testing.assert_allclose(_a(d2_scaled), ref2, rtol=1e-12)
    # Broadcast one point against many.
    np.testing.assert_allclose(_a(d_broadcast), np.linalg.norm(x[0] - y, axis=1), rtol=1e-12)
    np.testing.assert_allclose(_a(d_self), 0.0, atol=1e-7)


# ---------------------------------------------------------------- spheres
@jax.jit
def _sphere_vector(c, radius, x, on):
    S = cga.sphere(c, radius)
    return (
        cga.sphere_center_radius(S),
        cga.sphere_center_radius(S * -4.0),
        cga.sphere_power(S, cga.up(x)),
        cga.sphere_power(S, cga.up(on)),
        cga.sphere_power(S * 3.0, cga.up(x) * 0.5),
    )


@SETTINGS
@given(seeds, st.floats(0.01, 100.0))
def test_sphere_vector_form_center_radius_and_power(seed, radius):
    rng = np.random.default_rng(seed)
    c = rng.normal(size=3) * 2
    x = rng.normal(size=(6, 3)) * 3
    on = c + radius * _unit(rng.normal(size=(4, 3)))
    (center, r), (center2, r2), power, power_on, power_scaled = _sphere_vector(c, radius, x, on)
    np.testing.assert_allclose(_a(center), c, atol=1e-13)
    np.testing.assert_allclose(_a(r), radius, rtol=1e-10)
    # Scale invariance of the extraction.
    np.testing.assert_allclose(_a(center2), c, atol=1e-13)
    np.testing.assert_allclose(_a(r2), radius, rtol=1e-10)
    # Power: (r^2 - |x - c|^2) / 2, positive inside, zero on, negative outside.
    ref = 0.5 * (radius**2 - np.sum((x - c) ** 2, axis=1))
    np.testing.assert_allclose(_a(power), ref, rtol=1e-10, atol=1e-10 * max(1.0, radius**2))
    np.testing.assert_allclose(_a(power_on), 0.0, atol=1e-12 * max(1.0, radius**2 + c @ c))
    np.testing.assert_allclose(_a(power_scaled), ref, rtol=1e-10, atol=1e-10 * max(1.0, radius**2))


@jax.jit
def _sphere_through(p, c_ref, r_ref):
    S = cga.sphere_through(*[cga.up(p[k]) for k in range(4)])
    S_swapped = cga.sphere_through(*[cga.up(p[k]) for k in (1, 0, 2, 3)])
    return (
        S,
        cga.sphere_center_radius(S),
        cga.sphere_center_radius(S_swapped),
        cga.undual(S).full(),
        cga.sphere(c_ref, r_ref).full(),
        cga.round_center(S),
        cga.round_radius2(S),
    )


@SETTINGS
@given(seeds, st.floats(0.1, 10.0))
def test_sphere_through_four_points(seed, scale):
    rng = np.random.default_rng(seed)
    p = _well_spread(rng, 4, scale=scale)
    c_ref, r_ref = circumsphere(p)
    S, (center, r), (center_p, r_p), undual_s, vector_s, round_c, round_r2 = _sphere_through(p, c_ref, r_ref)
    assert S.names and S.grade(4).names == S.names  # grade-4 direct form
    np.testing.assert_allclose(_a(center), c_ref, rtol=1e-8, atol=1e-9 * scale)
    np.testing.assert_allclose(_a(r), r_ref, rtol=1e-8)
    # Orientation of the 4 points does not change the result (odd permutation flips the sign of S).
    np.testing.assert_allclose(_a(center_p), c_ref, rtol=1e-8, atol=1e-9 * scale)
    np.testing.assert_allclose(_a(r_p), r_ref, rtol=1e-8)
    # Direct and vector forms agree up to scale: undual(S) ~ sphere(c, r).
    assert_proportional(undual_s, vector_s, tol=1e-8)
    # round_center / round_radius2 on the direct form.
    np.testing.assert_allclose(_a(round_c), c_ref, rtol=1e-8, atol=1e-9 * scale)
    assert abs(float(round_r2) - r_ref**2) <= 1e-8 * r_ref**2


def test_imaginary_sphere_has_negative_radius():
    c = np.array([1.0, 2.0, 3.0])
    S = cga.up(c) + cga.basis_vector("einf") * (0.5 * 4.0)  # X + r^2/2 einf: r^2 = -4
    center, r = cga.sphere_center_radius(S)
    np.testing.assert_allclose(_a(center), c, atol=1e-14)
    np.testing.assert_allclose(_a(r), -2.0, rtol=1e-14)


# ---------------------------------------------------------------- planes
@jax.jit
def _plane_vector(n, dist, x):
    P = cga.plane(n, dist)
    return (
        cga.plane_normal_distance(P),
        cga.plane_signed_distance(P, cga.up(x)),
        cga.plane_signed_distance(P, cga.up(x) * -2.0),
    )


@SETTINGS
@given(seeds, st.floats(-50.0, 50.0))
def test_plane_vector_form_normal_distance_and_signed_distance(seed, dist):
    rng = np.random.default_rng(seed)
    n = rng.normal(size=3) * rng.uniform(0.1, 10)
    x = rng.normal(size=(5, 3)) * 4
    (nn, d), signed, signed_scaled = _plane_vector(n, dist, x)
    np.testing.assert_allclose(_a(nn), _unit(n), atol=1e-15)
    np.testing.assert_allclose(_a(d), dist, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(_a(signed), x @ _unit(n) - dist, atol=1e-12 * (1 + abs(dist)))
    # Any scale of the point.
    np.testing.assert_allclose(_a(signed_scaled), x @ _unit(n) - dist, atol=1e-12 * (1 + abs(dist)))


@jax.jit
def _plane_through(p, n_ref, d_ref):
    P = cga.plane_through(cga.up(p[0]), cga.up(p[1]), cga.up(p[2]))
    n, d = cga.plane_normal_distance(P)
    swapped = cga.plane_through(cga.up(p[1]), cga.up(p[0]), cga.up(p[2]))
    return (
        (n, d),
        P.full(),
        cga.dual(cga.plane(n_ref, d_ref)).full(),
        cga.plane_signed_distance(cga.plane(n, d), cga.up(p)),
        cga.plane_normal_distance(swapped),
    )


@SETTINGS
@given(seeds)
def test_plane_through_three_points(seed):
    rng = np.random.default_rng(seed)
    p = _well_spread(rng, 3)
    n_ref = _unit(np.cross(p[1] - p[0], p[2] - p[0]))
    (n, d), direct, dual_of_vector, on_plane, (n2, d2) = _plane_through(p, n_ref, n_ref @ p[0])
    # The orientation is that of (b - a) x (c - a).
    np.testing.assert_allclose(_a(n), n_ref, atol=1e-12)
    np.testing.assert_allclose(_a(d), n_ref @ p[0], atol=1e-12)
    # Direct form = dual of the vector form up to scale (eq. 7).
    assert_proportional(direct, dual_of_vector, tol=1e-10)
    # All three points lie on the plane; reversing the orientation flips the normal.
    np.testing.assert_allclose(_a(on_plane), 0.0, atol=1e-12)
    np.testing.assert_allclose(_a(n2), -n_ref, atol=1e-12)
    np.testing.assert_allclose(_a(d2), -(n_ref @ p[0]), atol=1e-12)


def test_plane_batched():
    n = np.array([[0.0, 0.0, 2.0], [3.0, 0.0, 0.0]])
    d = np.array([1.5, -2.0])
    nn, dd = cga.plane_normal_distance(cga.plane(n, d))
    np.testing.assert_allclose(_a(nn), [[0, 0, 1], [1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(_a(dd), d, atol=1e-15)


# ---------------------------------------------------------------- lines
@jax.jit
def _line(a, b, on, off):
    L = cga.line(cga.up(a), cga.up(b))
    return (
        L,
        cga.line_point_direction(L),
        cga.line_point_direction(cga.line(cga.up(b), cga.up(a))),
        (cga.up(on) ^ L).values,
        (cga.up(off) ^ L).values,
    )


@SETTINGS
@given(seeds, st.floats(0.01, 100.0))
def test_line_point_direction(seed, scale):
    rng = np.random.default_rng(seed)
    a, b = _well_spread(rng, 2, scale=scale)
    u_ref = _unit(b - a)
    p_ref = a - (a @ u_ref) * u_ref  # closest point to the origin
    on = a + rng.normal(size=(3, 1)) * (b - a)
    off = p_ref + scale * _unit(np.cross(u_ref, rng.normal(size=3)))
    L, (p, u), (_, u2), on_wedge, off_wedge = _line(a, b, on, off)
    np.testing.assert_allclose(_a(u), u_ref, atol=1e-12)
    np.testing.assert_allclose(_a(p), p_ref, atol=1e-11 * scale)
    # The reversed line points the other way.
    np.testing.assert_allclose(_a(u2), -u_ref, atol=1e-12)
    # Points on the line satisfy X ^ L = 0; a point off the line does not.
    lnorm = np.linalg.norm(_a(L.values))
    assert np.abs(_a(on_wedge)).max() <= 1e-10 * lnorm * max(1.0, scale**2)
    assert np.abs(_a(off_wedge)).max() > 1e-3 * lnorm


# ---------------------------------------------------------------- circles
@jax.jit
def _circle(p, q):
    C = cga.circle(cga.up(p[0]), cga.up(p[1]), cga.up(p[2]))
    return C, cga.circle_center_radius_normal(C), (cga.up(q) ^ C).values


@SETTINGS
@given(seeds, st.floats(0.1, 10.0))
def test_circle_center_radius_normal(seed, scale):
    rng = np.random.default_rng(seed)
    p = _well_spread(rng, 3, scale=scale)
    c_ref, r_ref, n_ref = circumcircle(p)
    # Another point of the circumcircle.
    e1 = _unit(p[0] - c_ref)
    e2 = np.cross(n_ref, e1)
    ang = rng.uniform(0, 2 * np.pi)
    q = c_ref + r_ref * (np.cos(ang) * e1 + np.sin(ang) * e2)
    C, (c, r, n), q_wedge = _circle(p, q)
    np.testing.assert_allclose(_a(c), c_ref, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(_a(r), r_ref, rtol=1e-9)
    np.testing.assert_allclose(_a(n), n_ref, atol=1e-9)
    # ... lies on C.
    cnorm = np.linalg.norm(_a(C.values))
    assert np.abs(_a(q_wedge)).max() <= 1e-9 * cnorm * max(1.0, scale**2)


# ---------------------------------------------------------------- point pairs
@jax.jit
def _point_pair(a, b):
    T = cga.point_pair(cga.up(a), cga.up(b))
    return cga.point_pair_points(T), cga.round_center(T), cga.round_radius2(T)


@SETTINGS
@given(seeds, st.floats(0.01, 100.0))
def test_point_pair_points(seed, scale):
    rng = np.random.default_rng(seed)
    a, b = _well_spread(rng, 2, scale=scale)
    pts, center, radius2 = _point_pair(a, b)
    pts = _a(pts)
    assert pts.shape == (2, 3)
    tol = 1e-9 * scale
    if np.abs(pts - np.stack([a, b])).max() > tol:
        np.testing.assert_allclose(pts, np.stack([b, a]), atol=tol)
    # Round of the point pair: center at the midpoint, radius^2 = |a - b|^2 / 4.
    np.testing.assert_allclose(_a(center), (a + b) / 2, atol=tol)
    np.testing.assert_allclose(_a(radius2), np.sum((a - b) ** 2) / 4, rtol=1e-9)


def test_point_pair_points_batched():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(4, 3))
    b = a + rng.normal(size=(4, 3)) + 0.5
    pts = _a(_point_pair(a, b)[0])
    assert pts.shape == (4, 2, 3)
    for k in range(4):
        got = {tuple(np.round(pts[k, i], 9)) for i in range(2)}
        assert got == {tuple(np.round(a[k], 9)), tuple(np.round(b[k], 9))}


# ---------------------------------------------------------------- intersections (meet)
@jax.jit
def _two_planes(n1, d1, n2, d2):
    P1, P2 = cga.plane(n1, d1), cga.plane(n2, d2)
    L = cga.meet(cga.dual(P1), cga.dual(P2))
    p, u = cga.line_point_direction(L)
    L2 = cga.line(cga.up(p - 1.3 * u), cga.up(p + 0.7 * u))
    return (
        L.names == cga.intersect(cga.dual(P1), cga.dual(P2)).names,
        (p, u),
        cga.dual(L).full(),
        cga.dual(L2).full(),
        (P1 ^ P2).full(),
    )


@SETTINGS
@given(seeds)
def test_meet_of_two_planes_is_their_line(seed):
    rng = np.random.default_rng(seed)
    n1, n2 = _unit(rng.normal(size=(2, 3)))
    if np.linalg.norm(np.cross(n1, n2)) < 0.2:
        n2 = _unit(n2 + 2 * np.cross(n1, n2) + np.cross(n1, rng.normal(size=3)))
    d1, d2 = rng.normal(size=2) * 2
    same_names, (p, u), dual_l, dual_l2, wedge = _two_planes(n1, d1, n2, d2)
    assert same_names  # intersect is the meet
    p, u = _a(p), _a(u)
    # Points on the line satisfy both planes.
    for s in (-3.0, 0.0, 2.5):
        q = p + s * u
        np.testing.assert_allclose([q @ n1 - d1, q @ n2 - d2], 0.0, atol=1e-11)
    assert_same_up_to_sign(u, _unit(np.cross(n1, n2)), 1e-12)
    # Closest point to the origin: perpendicular to the direction.
    assert abs(p @ u) < 1e-11
    # Dual form: dual(L) is proportional to P1 ^ P2, and so is dual(line(a, b)) through two of its
    # points.
    assert_proportional(dual_l, wedge, tol=1e-11)
    assert_proportional(dual_l2, wedge, tol=1e-11)


@jax.jit
def _sphere_plane(cs, r, n, d, q):
    S, P = cga.sphere(cs, r), cga.plane(n, d)
    C = cga.meet(cga.dual(S), cga.dual(P))
    return (
        C,
        cga.circle_center_radius_normal(C),
        cga.plane_normal_distance(C ^ cga.basis_vector("einf")),
        (cga.up(q) ^ C).values,
    )


@SETTINGS
@given(seeds, st.floats(0.0, 0.95))
def test_meet_of_sphere_and_plane_is_circle(seed, frac):
    rng = np.random.default_rng(seed)
    cs = rng.normal(size=3)
    r = rng.uniform(0.5, 3.0)
    n = _unit(rng.normal(size=3))
    h = frac * r * rng.choice([-1.0, 1.0])  # signed distance of the center from the plane
    d = cs @ n - h
    # Points of the analytic circle.
    e1 = _unit(np.cross(n, rng.normal(size=3)))
    e2 = np.cross(n, e1)
    ang = rng.uniform(0, 2 * np.pi, size=(3, 1))
    q = (cs - h * n) + np.sqrt(r * r - h * h) * (np.cos(ang) * e1 + np.sin(ang) * e2)
    C, (c, rad, nc), (n_c, d_c), q_wedge = _sphere_plane(cs, r, n, d, q)
    np.testing.assert_allclose(_a(c), cs - h * n, atol=1e-10)
    np.testing.assert_allclose(_a(rad), np.sqrt(r * r - h * h), rtol=1e-9)
    assert_same_up_to_sign(nc, n, 1e-10)
    # The circle lies in the plane: its carrier C ^ einf is the plane (direct form).
    sign = np.sign(_a(n_c) @ n)
    np.testing.assert_allclose(sign * _a(n_c), n, atol=1e-10)
    np.testing.assert_allclose(sign * _a(d_c), d, atol=1e-10)
    # The points of the analytic circle lie on C.
    cnorm = np.linalg.norm(_a(C.values))
    assert np.abs(_a(q_wedge)).max() <= 1e-10 * cnorm * 10


def test_meet_of_sphere_and_plane_that_miss_is_imaginary():
    args = (np.zeros(3), 1.0, np.array([0.0, 0.0, 1.0]), np.float64(2.0), np.zeros((3, 3)))  # as in the test above
    _, (_, rad, _), _, _ = _sphere_plane(*args)
    # r^2 - h^2 = 1 - 4 = -3: imaginary circle, reported as a negative radius.
    np.testing.assert_allclose(_a(rad), -np.sqrt(3.0), rtol=1e-12)


@jax.jit
def _line_plane(a, b, n, d, x_ref):
    F = cga.meet(cga.line(cga.up(a), cga.up(b)), cga.dual(cga.plane(n, d)))
    return F, F.full(), (cga.up(x_ref) ^ cga.basis_vector("einf")).full()


@SETTINGS
@given(seeds)
def test_meet_of_line_and_plane_is_flat_point(seed):
    rng = np.random.default_rng(seed)
    a, b = _well_spread(rng, 2)
    u = _unit(b - a)
    n = _unit(rng.normal(size=3))
    if abs(n @ u) < 0.2:
        n = _unit(n + u)
    d = rng.normal()
    # Analytic intersection of the line a + s u with x . n = d.
    x_ref = a + (d - a @ n) / (u @ n) * u
    F, F_full, flat = _line_plane(a, b, n, d, x_ref)
    # Flat point: k (x ^ einf) = k (x_i e_i einf + eo^einf); no other components.
    w = _a(F["eoinf"])
    assert abs(w) > 1e-6
    x = np.array([_a(F["e1inf"]), _a(F["e2inf"]), _a(F["e3inf"])]) / w
    np.testing.assert_allclose(x, x_ref, atol=1e-10 * (1 + np.abs(x_ref).max()))
    assert_proportional(F_full, flat, tol=1e-10)
