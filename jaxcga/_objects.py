"""Geometric objects of CGA (cut/tear/drill paper, sections 2.1 and 2.3).

Two representations of every object:

* vector (inner-product) form: points, spheres and planes are vectors (eq. 3-5), and the line,
  circle and point pair "seen by" two or three vectors are their outer products (e.g. the wedge of
  two plane vectors is the dual line). The paper calls this the *normal* form.
* direct (outer-product) form: the wedge of the points on the object (``circle(a, b, c)``,
  ``line(a, b)`` with einf, ``sphere_through(a, b, c, d)``). The paper calls this the *dual* form,
  because it is ``m* = -m I`` of the vector form (eq. 7), up to scale.

Every constructor returns a ``Multivector`` with a batch shape broadcast from its arguments.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, DTypeLike, Float

from _jaxcga_shared.checks import check_finite, check_vectors, require
from jaxcga import _algebra as alg
from jaxcga._multivector import Multivector, broadcast_batch
from jaxcga._operations import (
    _safe_sqrt_abs,
    basis_vector,
    dual,
    inner,
    involution,
    left_contraction,
    meet,
    outer,
    scalar_product,
    undual,
)

POINT_BLADES = alg.parse_blades(("e1", "e2", "e3", "eo", "einf"))


def _euclidean_checked(name: str, x: ArrayLike) -> Float[Array, "... 3"]:
    return check_finite(name, check_vectors(name, x))


def _vector(e123: Float[Array, "... 3"], eo: Float[ArrayLike, "*batch"], einf: Float[Array, "*batch"]) -> Multivector:
    batch = broadcast_batch("components", e123.shape[:-1], "components", jnp.shape(einf))
    e123 = jnp.broadcast_to(e123, batch + (3,))
    eo = jnp.broadcast_to(jnp.asarray(eo, e123.dtype), batch)
    einf = jnp.broadcast_to(einf, batch)
    return Multivector(jnp.concatenate([e123, eo[..., None], einf[..., None]], axis=-1), POINT_BLADES)


def up(x: Float[ArrayLike, "... 3"]) -> Multivector:
    """Up-projection of Euclidean points, X = x + |x|^2/2 einf + eo (eq. 3).

    Args:
        x: (..., 3) Euclidean points.
    Returns:
        The conformal points, vectors on (e1, e2, e3, eo, einf) of batch shape (...).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> cga.up(jnp.array([1.0, 2.0, 3.0])).values.tolist()
        [1.0, 2.0, 3.0, 1.0, 7.0]
    """
    x = _euclidean_checked("x", x)
    return _vector(x, 1.0, 0.5 * jnp.sum(x * x, axis=-1))


def down(X: Multivector) -> Float[Array, "... 3"]:
    """Euclidean point of a conformal point (any scale): x = X_e / X_eo, where X_eo = -X . einf.

    Args:
        X: conformal points (vectors; any non-zero scale).
    Returns:
        (..., 3) the Euclidean points.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> cga.down(2.0 * cga.up(jnp.array([1.0, 2.0, 3.0]))).tolist()
        [1.0, 2.0, 3.0]
    """
    _require_vector("X", X)
    w = X["eo"]
    w = require(w, (jnp.any(w == 0), "X: eo coefficient is zero (a point at infinity or a plane)"))
    return jnp.stack([X["e1"], X["e2"], X["e3"]], axis=-1) / w[..., None]


def sphere(center: Float[ArrayLike, "... 3"], radius: Float[ArrayLike, "*batch"]) -> Multivector:
    """Sphere in vector form, S = X - r^2/2 einf (eq. 4). A negative r^2 is an imaginary sphere; pass
    ``radius`` >= 0 here.

    Args:
        center: (..., 3) the centers.
        radius: (...) the radii, >= 0.
    Returns:
        The spheres as vectors, batch shape broadcast from both.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.sphere(jnp.zeros(3), 2.0)
        >>> float(cga.sphere_power(S, cga.up(jnp.array([1.0, 0, 0]))))  # (r^2 - |x - c|^2) / 2
        1.5
    """
    c = _euclidean_checked("center", center)
    r = check_finite("radius", jnp.asarray(radius, c.dtype))
    r = require(r, (jnp.any(r < 0), "radius: must be >= 0"))
    return _vector(c, 1.0, 0.5 * (jnp.sum(c * c, axis=-1) - r * r))


def plane(normal: Float[ArrayLike, "... 3"], distance: Float[ArrayLike, "*batch"]) -> Multivector:
    """Plane in vector form, P = n + d einf (eq. 5): the points x with x . n = d (n is normalized).

    Args:
        normal: (..., 3) the normals (normalized here).
        distance: (...) the signed distances from the origin along the normal.
    Returns:
        The planes as vectors (e1, e2, e3, einf).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> P = cga.plane(jnp.array([0, 0, 2.0]), 1.0)  # z = 1
        >>> P.names, P.values.tolist()
        (('e1', 'e2', 'e3', 'eo', 'einf'), [0.0, 0.0, 1.0, 0.0, 1.0])
    """
    n = _euclidean_checked("normal", normal)
    d = check_finite("distance", jnp.asarray(distance, n.dtype))
    length = jnp.linalg.norm(n, axis=-1)
    length = require(length, (jnp.any(length == 0), "normal: zero-length normal"))
    return _vector(n / length[..., None], 0.0, d)


def _require_vector(name: str, m: Multivector) -> None:
    if not isinstance(m, Multivector) or any(alg.grade_of(b) != 1 for b in m.blades):
        raise ValueError(f"{name}: expected a grade-1 Multivector (a conformal vector)")


def _require_grade(name: str, m: Multivector, grade: int, what: str) -> None:
    if not isinstance(m, Multivector) or any(alg.grade_of(b) != grade for b in m.blades):
        raise ValueError(f"{name}: expected {what}, a grade-{grade} Multivector")


def _einf(dtype: DTypeLike) -> Multivector:
    return basis_vector("einf", dtype)


# ---------------------------------------------------------------- direct (outer-product) forms
def point_pair(a: Multivector, b: Multivector) -> Multivector:
    """Point pair through two conformal points, a ^ b (grade 2).

    Args:
        a: conformal points, batch shape broadcasting with ``b``'s.
        b: conformal points.
    Returns:
        The point pairs, bivectors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.point_pair(cga.up(jnp.array([1.0, 0, 0])), cga.up(jnp.array([-1.0, 0, 0])))
        >>> (cga.point_pair_points(T) + 0.0).tolist()  # + 0.0: no negative zeros
        [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]
    """
    return outer(a, b)


def line(a: Multivector, b: Multivector) -> Multivector:
    """Line through two conformal points, a ^ b ^ einf (grade 3, sec. 2.3).

    Args:
        a: conformal points, batch shape broadcasting with ``b``'s.
        b: conformal points, distinct from ``a``.
    Returns:
        The lines, trivectors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> L = cga.line(cga.up(jnp.array([0, 1.0, 0])), cga.up(jnp.array([2.0, 1.0, 0])))
        >>> [(p + 0.0).tolist() for p in cga.line_point_direction(L)]  # + 0.0: no negative zeros
        [[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]]
    """
    return outer(outer(a, b), _einf(a.dtype))


def circle(a: Multivector, b: Multivector, c: Multivector) -> Multivector:
    """Circle through three conformal points, a ^ b ^ c (grade 3, sec. 2.3).

    Args:
        a: conformal points; ``a``, ``b`` and ``c`` broadcast together.
        b: conformal points.
        c: conformal points, not on the line through ``a`` and ``b``.
    Returns:
        The circles, trivectors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> C = cga.circle(up([1.0, 0, 0]), up([0, 1.0, 0]), up([-1.0, 0, 0]))
        >>> center, radius, normal = cga.circle_center_radius_normal(C)
        >>> [round(v, 6) + 0.0 for v in center.tolist()], round(float(radius), 6)
        ([0.0, 0.0, 0.0], 1.0)
    """
    return outer(outer(a, b), c)


def plane_through(a: Multivector, b: Multivector, c: Multivector) -> Multivector:
    """Plane through three conformal points, a ^ b ^ c ^ einf (grade 4, sec. 2.3).

    Args:
        a: conformal points; ``a``, ``b`` and ``c`` broadcast together.
        b: conformal points.
        c: conformal points, not on the line through ``a`` and ``b``.
    Returns:
        The planes in direct form, quadvectors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> P = cga.plane_through(up([0, 0, 1.0]), up([1.0, 0, 1.0]), up([0, 1.0, 1.0]))
        >>> normal, distance = cga.plane_normal_distance(P)
        >>> (normal + 0.0).tolist(), float(distance)  # + 0.0: no negative zeros
        ([0.0, 0.0, 1.0], 1.0)
    """
    return outer(outer(outer(a, b), c), _einf(a.dtype))


def sphere_through(a: Multivector, b: Multivector, c: Multivector, d: Multivector) -> Multivector:
    """Sphere through four conformal points, a ^ b ^ c ^ d (grade 4, sec. 2.3).

    Args:
        a: conformal points; ``a`` to ``d`` broadcast together.
        b: conformal points.
        c: conformal points.
        d: conformal points, not on one circle or plane with the other three.
    Returns:
        The spheres in direct form, quadvectors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> S = cga.sphere_through(up([1.0, 0, 0]), up([-1.0, 0, 0]), up([0, 1.0, 0]), up([0, 0, 1.0]))
        >>> center, radius = cga.sphere_center_radius(S)
        >>> [round(v, 6) + 0.0 for v in center.tolist()], round(float(radius), 6)
        ([0.0, 0.0, 0.0], 1.0)
    """
    return outer(outer(outer(a, b), c), d)


# ---------------------------------------------------------------- distances
def squared_distance(a: Multivector, b: Multivector) -> Float[Array, "*batch"]:
    """|x - y|^2 = -2 X . Y / (X_eo Y_eo) for conformal points of any scale (sec. 2.2).

    Args:
        a: conformal points, batch shape broadcasting with ``b``'s.
        b: conformal points.
    Returns:
        (*batch) the squared Euclidean distances.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> float(cga.squared_distance(cga.up(jnp.array([1.0, 0, 0])), 3.0 * cga.up(jnp.array([0, 2.0, 0]))))
        5.0
    """
    _require_vector("a", a)
    _require_vector("b", b)
    return -2.0 * scalar_product(a, b) / (a["eo"] * b["eo"])


def distance(a: Multivector, b: Multivector) -> Float[Array, "*batch"]:
    """Euclidean distance between two conformal points.

    Args:
        a: conformal points, batch shape broadcasting with ``b``'s.
        b: conformal points.
    Returns:
        (*batch) the Euclidean distances (a finite gradient where they are zero).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> float(cga.distance(cga.up(jnp.array([3.0, 0, 0])), cga.up(jnp.array([0, 4.0, 0]))))
        5.0
    """
    return _safe_sqrt_abs(jnp.maximum(squared_distance(a, b), 0.0))


def plane_signed_distance(plane_vector: Multivector, X: Multivector) -> Float[Array, "*batch"]:
    """Signed distance of a point from a plane given in vector form: X . P = x . n - d.

    Args:
        plane_vector: planes in vector form (``plane``), batch shape broadcasting with ``X``'s.
        X: conformal points of scale 1 (``up``).
    Returns:
        (*batch) ``x . n - d``: the signed distances for unit normals.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> P = cga.plane(jnp.array([0, 0, 1.0]), 1.0)
        >>> float(cga.plane_signed_distance(P, cga.up(jnp.array([5.0, 5.0, 3.0]))))
        2.0
    """
    _require_vector("plane_vector", plane_vector)
    return scalar_product(X, plane_vector) / X["eo"]


def sphere_power(sphere_vector: Multivector, X: Multivector) -> Float[Array, "*batch"]:
    """X . S / X_eo = (r^2 - |x - c|^2) / 2: positive inside the sphere, zero on it, negative outside.

    Args:
        sphere_vector: spheres in vector form (``sphere``), batch shape broadcasting with ``X``'s.
        X: conformal points (any non-zero scale).
    Returns:
        (*batch) the power ``(r^2 - |x - c|^2) / 2``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.sphere(jnp.zeros(3), 1.0)
        >>> float(cga.sphere_power(S, cga.up(jnp.array([2.0, 0, 0]))))  # outside
        -1.5
    """
    _require_vector("sphere_vector", sphere_vector)
    return scalar_product(X, sphere_vector) / (X["eo"] * sphere_vector["eo"])


# ---------------------------------------------------------------- extraction
def _as_vector_form(name: str, m: Multivector) -> Multivector:
    """Spheres and planes may be passed as vectors or as their direct 4-vector forms."""
    if all(alg.grade_of(b) == 4 for b in m.blades):
        return undual(m)
    _require_vector(name, m)
    return m


def sphere_center_radius(S: Multivector) -> tuple[Float[Array, "... 3"], Float[Array, "*batch"]]:
    """(center (..., 3), radius (...)) of a sphere in vector or direct form. An imaginary sphere
    (r^2 < 0) gets a negative radius: -sqrt(-r^2).

    Args:
        S: spheres in vector form (``sphere``) or direct form (``sphere_through``).
    Returns:
        (center (..., 3), radius (...)); an imaginary sphere's radius is negative.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> center, radius = cga.sphere_center_radius(cga.sphere(jnp.array([1.0, 2.0, 3.0]), 0.5))
        >>> center.tolist(), float(radius)
        ([1.0, 2.0, 3.0], 0.5)
    """
    S = _as_vector_form("S", S)
    w = S["eo"]
    w = require(w, (jnp.any(w == 0), "S: eo coefficient is zero (a plane, not a sphere)"))
    c = jnp.stack([S["e1"], S["e2"], S["e3"]], axis=-1) / w[..., None]
    r2 = jnp.sum(c * c, axis=-1) - 2.0 * S["einf"] / w
    return c, jnp.sign(r2) * _safe_sqrt_abs(r2)


def plane_normal_distance(P: Multivector) -> tuple[Float[Array, "... 3"], Float[Array, "*batch"]]:
    """(unit normal (..., 3), distance (...)) of a plane in vector or direct form, x . n = d.

    Args:
        P: planes in vector form (``plane``) or direct form (``plane_through``).
    Returns:
        (unit normal (..., 3), distance (...)) with ``x . n = d`` on the plane.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> normal, distance = cga.plane_normal_distance(cga.plane(jnp.array([0, 3.0, 0]), 2.0))
        >>> normal.tolist(), float(distance)
        ([0.0, 1.0, 0.0], 2.0)
    """
    P = _as_vector_form("P", P)
    n = jnp.stack([P["e1"], P["e2"], P["e3"]], axis=-1)
    length = jnp.linalg.norm(n, axis=-1)
    length = require(length, (jnp.any(length == 0), "P: zero normal (not a plane)"))
    return n / length[..., None], P["einf"] / length


def line_point_direction(L: Multivector) -> tuple[Float[Array, "... 3"], Float[Array, "... 3"]]:
    """(point of the line closest to the origin (..., 3), unit direction (..., 3)) of a line in
    direct form ``a ^ b ^ einf``; the direction points from a to b.

    Args:
        L: lines in direct form (``line``).
    Returns:
        (the point closest to the origin (..., 3), the unit direction (..., 3)).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> L = cga.line(cga.up(jnp.array([1.0, 0, 5.0])), cga.up(jnp.array([1.0, 0, 1.0])))
        >>> [(p + 0.0).tolist() for p in cga.line_point_direction(L)]  # + 0.0: no negative zeros
        [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0]]
    """
    _require_grade("L", L, 3, "a line in direct form")
    # The dual of a line is a bivector: its e_ij part is the direction (as I3 d), its e_i einf part
    # the moment, proportional to d x p.
    Ld = dual(L)
    d = -jnp.stack([Ld["e23"], -Ld["e13"], Ld["e12"]], axis=-1)
    m = jnp.stack([Ld["e1inf"], Ld["e2inf"], Ld["e3inf"]], axis=-1)
    length = jnp.linalg.norm(d, axis=-1)
    length = require(length, (jnp.any(length == 0), "L: not a finite line"))
    u = d / length[..., None]
    return jnp.cross(m / length[..., None], u), u


def round_radius2(X: Multivector) -> Float[Array, "*batch"]:
    """Squared radius of a round (point pair, circle or sphere) in direct form:
    <X X^> / <K K> with K = einf _| X and ^ the grade involution; negative for imaginary rounds.
    (With K^ in the denominator the sign would flip for point pairs and spheres, whose K has odd
    grade.)

    Args:
        X: rounds in direct form: point pairs (``point_pair``), circles (``circle``) or spheres (``sphere_through``).
    Returns:
        (*batch) the squared radii.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.point_pair(cga.up(jnp.array([0, 0, 0.0])), cga.up(jnp.array([4.0, 0, 0])))
        >>> round(float(cga.round_radius2(T)), 6)
        4.0
    """
    K = left_contraction(_einf(X.dtype), X)
    return scalar_product(X, involution(X)) / scalar_product(K, K)


def round_center(X: Multivector) -> Float[Array, "... 3"]:
    """Center (..., 3) of a round in direct form: X einf X is the flat point at the center.

    Args:
        X: rounds in direct form: point pairs, circles or spheres.
    Returns:
        (..., 3) the centers.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.point_pair(cga.up(jnp.array([0, 0, 0.0])), cga.up(jnp.array([4.0, 2.0, 0])))
        >>> [round(v, 6) + 0.0 for v in cga.round_center(T).tolist()]
        [2.0, 1.0, 0.0]
    """
    S = (X * _einf(X.dtype) * X).grade(1)
    center, _ = sphere_center_radius(S)
    return center


def circle_center_radius_normal(
    C: Multivector,
) -> tuple[Float[Array, "... 3"], Float[Array, "*batch"], Float[Array, "... 3"]]:
    """(center (..., 3), radius (...), unit normal (..., 3)) of a circle in direct form ``a ^ b ^ c``.

    Args:
        C: circles in direct form (``circle``).
    Returns:
        (center (..., 3), radius (...), unit normal (..., 3)); the normal follows the right-hand rule through the
        three points of ``circle(a, b, c)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> C = cga.circle(up([2.0, 0, 1.0]), up([0, 2.0, 1.0]), up([-2.0, 0, 1.0]))
        >>> center, radius, normal = cga.circle_center_radius_normal(C)
        >>> [round(v, 6) + 0.0 for v in center.tolist()], round(float(radius), 6)
        ([0.0, 0.0, 1.0], 2.0)
    """
    _require_grade("C", C, 3, "a circle in direct form")
    r2 = round_radius2(C)
    n, _ = plane_normal_distance(outer(C, _einf(C.dtype)))
    return round_center(C), jnp.sign(r2) * _safe_sqrt_abs(r2), n


def point_pair_points(T: Multivector) -> Float[Array, "... 2 3"]:
    """The two Euclidean points (..., 2, 3) of a point pair in direct form ``a ^ b``:
    (T -/+ sqrt(T . T)) (einf _| T), down-projected. Imaginary pairs give non-finite output and an
    error.

    Args:
        T: real point pairs in direct form (``point_pair``).
    Returns:
        (..., 2, 3) the two Euclidean points.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.point_pair(cga.up(jnp.array([0, 3.0, 0])), cga.up(jnp.array([0, 1.0, 0])))
        >>> (cga.point_pair_points(T).round(6) + 0.0).tolist()  # + 0.0: no negative zeros
        [[0.0, 3.0, 0.0], [0.0, 1.0, 0.0]]
    """
    _require_grade("T", T, 2, "a point pair in direct form")
    einf = _einf(T.dtype)
    s2 = scalar_product(T, T)
    s2 = require(s2, (jnp.any(s2 < 0), "T: imaginary point pair (T . T < 0)"))
    root = jnp.sqrt(s2)
    projector = inner(einf, T)  # a vector
    out = []
    for sign in (-1.0, 1.0):
        P = ((T + sign * root) * projector).grade(1)
        out.append(down(P))
    return jnp.stack(out, axis=-2)


def intersect(a: Multivector, b: Multivector) -> Multivector:
    """Intersection of two objects in direct form, by the meet (regressive product).

    Args:
        a: objects in direct form (lines, circles, planes, spheres), batch shape broadcasting with ``b``'s.
        b: objects in direct form.
    Returns:
        Their intersection in direct form: ``meet(a, b)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> S = cga.sphere_through(up([1.0, 0, 0]), up([-1.0, 0, 0]), up([0, 1.0, 0]), up([0, 0, 1.0]))
        >>> L = cga.line(up([-5.0, 0, 0]), up([5.0, 0, 0]))
        >>> T = cga.intersect(S, L)  # the point pair where the x axis crosses the unit sphere
        >>> (cga.point_pair_points(T).round(6) + 0.0).tolist()  # + 0.0: no negative zeros
        [[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]
    """
    return meet(a, b)
