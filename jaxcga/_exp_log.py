"""Closed-form exponential and logarithm of motors and similitudes (cut/tear/drill paper sec. 2.4-2.5,
eq. 8-12; the paper approximates them by Taylor series, we use closed forms).

Motors. P = e123inf commutes with every even element of the motor algebra and P^2 = 0, so it plays
the dual unit of dual numbers. A motor generator (bivector) B = B_E + B_I squares to
-(theta + P d)^2, with theta^2 = |B_E|^2, hence exp(B) = cos(theta_d) + sinc(theta_d) B evaluated in
dual-number arithmetic, and log(M) = theta_d / sin(theta_d) <M>_2 with theta_d = atan2(sin, cos).

Similitudes (rotation, translation, uniform dilation). The generator B = Omega + tau + kappa eo^einf
acts on points as the vector field x' = lam x + w x x + v (lam = 2 kappa, w and v from Omega and
tau). Its flow for unit time is x -> e^lam Rot(w) x + V v with V = int_0^1 exp(s (lam I + [w]x)) ds
= a0 I + a1 W + a2 W^2 (W = [w]x); a0, a1, a2 are the real and imaginary parts of
(e^z - 1) / z at z = lam + i|w|, evaluated by series near z = 0. So exp(B) = T(V v) R(w) D(e^lam).

All scalar functions are written in the squared angle so that gradients are finite at angle 0 and
for pure translations (no sqrt(0) on any differentiated path).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import require
from _jaxcga_shared.platform import EXACT
from jaxcga import _algebra as alg
from jaxcga import _codegen
from jaxcga._multivector import KINDS, Multivector
from jaxcga._operations import normalize_motor_columns
from jaxcga._versors import dilator, similitude_dilation

MOTOR_GENERATOR = alg.parse_blades(("e12", "e13", "e23", "e1inf", "e2inf", "e3inf"))
SIMILITUDE_GENERATOR = MOTOR_GENERATOR + alg.parse_blades(("eoinf",))
_ROTATION = alg.parse_blades(("e12", "e13", "e23"))
_SCALAR_P = alg.parse_blades(("1", "e123inf"))
_PSEUDOSCALAR_INF = alg.parse_blades(("e123inf",))[0]
_SERIES_BELOW = 1e-2  # squared angle below which Taylor series replace the closed forms


def _where_small(
    x: Float[Array, "*shape"],
    small: Bool[Array, "*shape"],
    series: Callable[[Array], Array],
    closed: Callable[[Array], Array],
) -> Float[Array, "*shape"]:
    """``series(x)`` where ``small`` else ``closed(x)``, with safe inputs on both branches."""
    return jnp.where(small, series(jnp.where(small, x, 0.0)), closed(jnp.where(small, 1.0, x)))


def _cos_sinc_g(
    x: Float[Array, "*shape"],
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"], Float[Array, "*shape"]]:
    """cos(sqrt x), sin(sqrt x)/sqrt x and (cos - sinc)/x, analytic in x >= 0."""
    small = x < _SERIES_BELOW
    cos = _where_small(
        x, small, lambda y: 1 - y / 2 * (1 - y / 12 * (1 - y / 30 * (1 - y / 56))), lambda y: jnp.cos(jnp.sqrt(y))
    )
    sinc = _where_small(
        x,
        small,
        lambda y: 1 - y / 6 * (1 - y / 20 * (1 - y / 42 * (1 - y / 72))),
        lambda y: jnp.sin(jnp.sqrt(y)) / jnp.sqrt(y),
    )
    g = _where_small(
        x,
        small,
        lambda y: -1 / 3 + y / 30 - y**2 / 840 + y**3 / 45360 - y**4 / 3991680,
        lambda y: (jnp.cos(jnp.sqrt(y)) - jnp.sin(jnp.sqrt(y)) / jnp.sqrt(y)) / y,
    )
    return cos, sinc, g


def _require_generator(name: str, b: Multivector, blades: tuple[int, ...], what: str) -> None:
    if not isinstance(b, Multivector) or not set(b.blades) <= set(blades):
        raise ValueError(
            f"{name}: expected a {what} (a bivector on {[alg.blade_name(x) for x in blades]}), "
            f"got blades {list(b.names) if isinstance(b, Multivector) else type(b)}"
        )


def exp_motor(b: Multivector) -> Multivector:
    """Motor ``exp(B)`` of a bivector on {e12, e13, e23, e1inf, e2inf, e3inf}, closed form.

    Args:
        b: bivectors on the motor generators (``MOTOR_GENERATOR``: e12, e13, e23, e1inf, e2inf, e3inf).
    Returns:
        The unit motors ``exp(b)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> b = cga.Multivector(jnp.array([0.0, 0.0, 0.0, -1.0, 0.0, 0.0]), cga.MOTOR_GENERATOR)
        >>> cga.apply_to_points(cga.exp_motor(b), jnp.zeros(3)).round(6).tolist()  # exp(-t einf / 2): a translation
        [2.0, 0.0, 0.0]
    """
    _require_generator("b", b, MOTOR_GENERATOR, "motor generator")
    b = b.embed(MOTOR_GENERATOR)
    columns = exp_motor_columns([b.values[..., i] for i in range(len(MOTOR_GENERATOR))], b.batch_shape)
    return Multivector(jnp.stack(columns, axis=-1), KINDS["motor"])


def exp_motor_columns(b: Sequence[Array], batch_shape: tuple[int, ...]) -> list[Array]:
    """``exp_motor`` on columns: the six components of B (``MOTOR_GENERATOR`` order, arrays of ``batch_shape``) to
    the eight of the motor (``KINDS["motor"]`` order). No stacked arrays, so that a kernel over blocks of rows (a
    Triton program, ``deform``'s motor fields on GPUs) evaluates it too."""
    x = b[0] * b[0] + b[1] * b[1] + b[2] * b[2]  # theta^2, B_E^2 = -theta^2
    (y,) = _blade_columns(
        _codegen.bilinear_terms("geometric", MOTOR_GENERATOR, MOTOR_GENERATOR), (b, b), batch_shape, _PSEUDOSCALAR_INF
    )  # B^2 = -theta^2 + y P, y = -2 theta d
    cos, sinc, g = _cos_sinc_g(x)
    # exp(B) = (cos + 0.5 y sinc P) + (sinc - 0.5 y g P) B in dual-number arithmetic
    terms = _codegen.bilinear_terms("geometric", _SCALAR_P, MOTOR_GENERATOR)
    blades, product = _codegen.emit(terms, ([sinc, -0.5 * y * g], b), batch_shape)
    out = dict(zip(blades, product))
    for blade, value in zip(_SCALAR_P, (cos, 0.5 * y * sinc)):
        out[blade] = out[blade] + value if blade in out else value
    return [jnp.broadcast_to(out[blade], batch_shape) for blade in KINDS["motor"]]


def _blade_columns(terms, factors, batch_shape, *blades: int) -> list[Array]:
    """The columns of ``blades`` in the generated product ``terms`` of ``factors``."""
    _, columns = _codegen.emit(tuple(t for t in terms if t[0] in blades), factors, batch_shape)
    return columns


def _atan_ratio(
    u: Float[Array, "*shape"], a: Float[Array, "*shape"]
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """theta / s and (theta / s - a) / s^2 for theta = atan2(s, a), s = sqrt(u), a^2 + u = 1."""
    small = (u < _SERIES_BELOW) & (a > 0)
    safe_a = jnp.where(small, a, 1.0)

    def series(v: Array) -> tuple[Array, Array]:
        w2 = v / safe_a**2  # tan^2(theta)
        k = (1 - w2 / 3 + w2**2 / 5 - w2**3 / 7 + w2**4 / 9 - w2**5 / 11) / safe_a
        # (k - a) / u with 1 - a^2 = u substituted exactly.
        m = (
            1
            - 1 / (3 * safe_a**2)
            + v / (5 * safe_a**4)
            - v**2 / (7 * safe_a**6)
            + v**3 / (9 * safe_a**8)
            - v**4 / (11 * safe_a**10)
        ) / safe_a
        return k, m

    def closed(v: Array) -> tuple[Array, Array]:
        s = jnp.sqrt(v)
        k = jnp.arctan2(s, a) / s
        return k, (k - a) / v

    u_series = jnp.where(small, u, 0.0)
    u_closed = jnp.where(small | (u == 0), 1.0, u)
    k_s, m_s = series(u_series)
    k_c, m_c = closed(u_closed)
    return jnp.where(small, k_s, k_c), jnp.where(small, m_s, m_c)


def log_motor(m: Multivector) -> Multivector:
    """Bivector ``log(M)`` of a motor (normalized first), closed form; ``exp(log(M)) = M``.

    The rotation angle of the result is in [0, 2 pi]; a motor whose rotor part is -1 (a 2 pi turn) has
    no unique logarithm: it gets the screw axis along its translation (the e12 plane if there is none).

    Args:
        m: motors (normalized here; ``M ~M > 0``, checked).
    Returns:
        The bivectors on the motor generators.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), 0.8), jnp.array([1.0, 2.0, 3.0]))
        >>> bool(jnp.allclose(cga.exp_motor(cga.log_motor(M)).values, M.values, atol=1e-6))
        True
    """
    if not isinstance(m, Multivector) or not set(m.blades) <= set(KINDS["motor"]):
        raise ValueError("m: expected a motor Multivector")
    out, bad = log_motor_unchecked(m)
    return Multivector(require(out.values, (bad, "normalize: motor has non-positive norm M~M")), out.blades)


def log_motor_unchecked(m: Multivector) -> tuple[Multivector, Bool[Array, "*batch"]]:
    """``log_motor`` without its check, and where it fails (M ~M <= 0: NaN there), for callers that check once
    their result is computed (``deform.motor_field_solve``: on a GPU a check is a host round trip)."""
    m = m.embed(KINDS["motor"])
    columns, bad = log_motor_columns([m.values[..., i] for i in range(len(m.blades))], m.batch_shape)
    return Multivector(jnp.stack(columns, axis=-1), MOTOR_GENERATOR), bad


def log_motor_columns(m: Sequence[Array], batch_shape: tuple[int, ...]) -> tuple[list[Array], Array]:
    """``log_motor_unchecked`` on columns: the eight components of M (``KINDS["motor"]`` order, arrays of
    ``batch_shape``) to the six of log M (``MOTOR_GENERATOR`` order), and where M ~M <= 0. No stacked arrays, so
    that XLA computes it in one kernel and a kernel over blocks of rows evaluates it too."""
    m, bad = normalize_motor_columns(m, batch_shape)
    a, b4 = m[0], m[7]
    biv = m[1:7]
    rot, v = biv[:3], biv[3:]
    u = rot[0] * rot[0] + rot[1] * rot[1] + rot[2] * rot[2]  # sin^2(theta)
    (z,) = _blade_columns(
        _codegen.bilinear_terms("geometric", MOTOR_GENERATOR, MOTOR_GENERATOR),
        (biv, biv),
        batch_shape,
        _PSEUDOSCALAR_INF,
    )  # <M>_2^2 = -sin^2(theta_d): its P part
    k, mm = _atan_ratio(u, a)
    # theta_d / sin(theta_d) = k + P (-b4 + z m / 2) (dual-number division, see module docstring).
    blades, product = _codegen.emit(
        _codegen.bilinear_terms("geometric", _SCALAR_P, MOTOR_GENERATOR), ([k, -b4 + 0.5 * z * mm], biv), batch_shape
    )
    out = dict(zip(blades, product))
    out = [out[blade] for blade in MOTOR_GENERATOR]
    # For a rotation beyond pi (a < 0) the two P terms above are ~pi / sin each and cancel. With
    # w = sin(theta) u (u the axis, in e_i einf coordinates w = P <M>_2's rotation part) and v the
    # e_i einf part of M, the same value is k v_perp + a v_par - b4 w: no cancellation.
    w = [-rot[2], rot[1], -rot[0]]
    u_safe = jnp.where(u > 0, u, 1.0)
    v_par = [_dot(v, w) * wi / u_safe for wi in w]
    v_perp = [k * c / u_safe for c in _cross(w, _cross(v, w))]
    # v_perp is ill conditioned (rounding of size eps |v| times k ~ pi / sin): project once more so
    # that none of that rounding lands along the axis, where the result is well conditioned.
    along = _dot(v_perp, w)
    v_perp = [c - along * wi / u_safe for c, wi in zip(v_perp, w)]
    far = a < 0
    out_i = [jnp.where(far, vp + a * vq - b4 * wi, o) for vp, vq, wi, o in zip(v_perp, v_par, w, out[3:])]
    # A 2 pi turn (rotor part -1): M = -T(t) is the 2 pi screw about the axis along t (any axis if
    # t = 0; then e12).
    at_two_pi = (u == 0) & far
    v2 = _dot(v, v)
    length = jnp.sqrt(jnp.where(v2 > 0, v2, 1.0))
    axis = [jnp.where(v2 > 0, c / length, fallback) for c, fallback in zip(v, (0.0, 0.0, -1.0))]
    full_turn = [jnp.pi * -axis[2], jnp.pi * axis[1], jnp.pi * -axis[0]]
    out_r = [jnp.where(at_two_pi, t, o) for t, o in zip(full_turn, out[:3])]
    out_i = [jnp.where(at_two_pi, a * vi, o) for vi, o in zip(v, out_i)]
    return [jnp.broadcast_to(c, batch_shape) for c in out_r + out_i], bad


def _dot(x: Sequence[Array], y: Sequence[Array]) -> Array:
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def _cross(x: Sequence[Array], y: Sequence[Array]) -> list[Array]:
    return [x[1] * y[2] - x[2] * y[1], x[2] * y[0] - x[0] * y[2], x[0] * y[1] - x[1] * y[0]]


# ---------------------------------------------------------------- similitudes
def _rotation_vector(b_rot: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """w (the rotation vector) of a rotation generator with components (e12, e13, e23)."""
    return jnp.stack([-2 * b_rot[..., 2], 2 * b_rot[..., 1], -2 * b_rot[..., 0]], axis=-1)


def _v_coefficients(
    lam: Float[Array, "*shape"], x: Float[Array, "*shape"]
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"], Float[Array, "*shape"]]:
    """a0, a1, a2 of V = int_0^1 e^{s lam} Rot(s w) ds = a0 I + a1 W + a2 W^2, with x = |w|^2."""
    z2 = lam * lam + x
    small = z2 < 1.0
    lam_s, x_s = jnp.where(small, lam, 0.0), jnp.where(small, x, 0.0)
    # Series: a_k = sum_n c_n / (n+1)!, with z^n = Re_n + i theta P_n, Q_n = (lam^n - Re_n) / theta^2.
    re, p, q, lam_n = jnp.ones_like(lam_s), jnp.zeros_like(lam_s), jnp.zeros_like(lam_s), jnp.ones_like(lam_s)
    a0 = a1 = a2 = 0.0
    fact = 1.0
    for n in range(24):
        fact *= n + 1
        a0, a1, a2 = a0 + lam_n / fact, a1 + p / fact, a2 + q / fact
        re, p, q, lam_n = re * lam_s - p * x_s, re + p * lam_s, q * lam_s + p, lam_n * lam_s
    # Closed forms, |z| >= 1.
    lam_c, x_c = jnp.where(small, 1.0, lam), jnp.where(small, 1.0, x)
    z2_c = lam_c * lam_c + x_c
    cos, sinc, _ = _cos_sinc_g(x_c)
    one_minus_cos = _where_small(
        x_c,
        x_c < _SERIES_BELOW,
        lambda y: 0.5 - y / 24 + y**2 / 720 - y**3 / 40320,
        lambda y: (1 - jnp.cos(jnp.sqrt(y))) / y,
    )
    e = jnp.exp(lam_c)
    lam_tiny = jnp.abs(lam_c) < 1e-4
    phi0 = jnp.where(
        lam_tiny, 1 + lam_c / 2 + lam_c**2 / 6 + lam_c**3 / 24, jnp.expm1(lam_c) / jnp.where(lam_tiny, 1.0, lam_c)
    )
    c1 = (lam_c * e * sinc - e * cos + 1) / z2_c
    c2 = (e * lam_c * one_minus_cos + phi0 - e * sinc) / z2_c
    return jnp.where(small, a0, phi0), jnp.where(small, a1, c1), jnp.where(small, a2, c2)


def _apply_v(lam: Float[Array, "*batch"], w: Float[Array, "... 3"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    a0, a1, a2 = _v_coefficients(lam, jnp.sum(w * w, axis=-1))
    wv = jnp.cross(w, v)
    return a0[..., None] * v + a1[..., None] * wv + a2[..., None] * jnp.cross(w, wv)


def _v_matrix(lam: Float[Array, "*batch"], w: Float[Array, "... 3"]) -> Float[Array, "... 3 3"]:
    a0, a1, a2 = _v_coefficients(lam, jnp.sum(w * w, axis=-1))
    zero = jnp.zeros_like(w[..., 0])
    W = jnp.stack(
        [
            jnp.stack([zero, -w[..., 2], w[..., 1]], -1),
            jnp.stack([w[..., 2], zero, -w[..., 0]], -1),
            jnp.stack([-w[..., 1], w[..., 0], zero], -1),
        ],
        -2,
    )
    eye = lift_rank(jnp.eye(3, dtype=w.dtype), a0.ndim + 2)
    return a0[..., None, None] * eye + a1[..., None, None] * W + a2[..., None, None] * jnp.matmul(W, W, precision=EXACT)


def exp_similitude(b: Multivector) -> Multivector:
    """Similitude ``exp(B)`` of a bivector on the motor generators plus eo^einf (dilation).

    Args:
        b: bivectors on the motor generators and eoinf.
    Returns:
        The similitudes ``exp(b)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.similitude(cga.rotor(jnp.array([1.0, 0, 0]), 0.4), jnp.array([0, 1.0, 0]), 3.0)
        >>> bool(jnp.allclose(cga.exp_similitude(cga.log_similitude(S)).values, S.values, atol=1e-5))
        True
    """
    _require_generator("b", b, SIMILITUDE_GENERATOR, "similitude generator")
    b = b.embed(SIMILITUDE_GENERATOR)
    w = _rotation_vector(b.values[..., :3])
    v = -2.0 * b.values[..., 3:6]
    lam = 2.0 * b.values[..., 6]
    rotation = exp_motor(Multivector(b.values[..., :3], _ROTATION))
    t = _apply_v(lam, w, v)
    # T R D = R D - (t einf / 2) R D, and einf D = e^(-lam/2) einf exactly. Forming the product
    # T R D numerically instead would cancel cosh(lam/2) - sinh(lam/2) and lose ~e^|lam| ulps.
    rd = rotation * dilator(jnp.exp(lam))
    t_einf = Multivector(-0.5 * jnp.exp(-0.5 * lam)[..., None] * t, alg.parse_blades(("e1inf", "e2inf", "e3inf")))
    return (rd + t_einf * rotation).embed(KINDS["similitude"])


def log_similitude(s: Multivector) -> Multivector:
    """Bivector ``log(S)`` of a similitude ``S = T R D`` (rotation angle below 2 pi).

    Args:
        s: similitudes (``similitude``), rotation angle below 2 pi.
    Returns:
        The bivectors on the motor generators and eoinf; the eoinf part is half the log of the scale, up to sign.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.similitude(cga.rotor(jnp.array([0, 0, 1.0]), 0.0), jnp.zeros(3), 2.0)
        >>> B = cga.log_similitude(S)
        >>> round(abs(float(B.values[..., B.names.index("eoinf")])), 6) == round(float(jnp.log(2.0)) / 2, 6)
        True
    """
    if not isinstance(s, Multivector) or not set(s.blades) <= set(KINDS["similitude"]):
        raise ValueError("s: expected a similitude Multivector (even blades)")
    s = s.embed(KINDS["similitude"])
    # S = T R D = R D + x' einf with R D = R (cosh + sinh eo^einf) and x' = -(1/2) e^(-lam/2) t R on
    # (e1, e2, e3, e123); the two parts sit on disjoint blades.
    rc, c2, lam = similitude_dilation(s)
    rotor_part = Multivector(rc, KINDS["rotor"])
    # t = -2 x' ~R e^(lam/2) / |R|^2 with R = rc / cosh(lam/2): products only. (The sandwich of the
    # origin would cancel terms of size d to get ones of size 1/d and lose ~d^2 ulps.)
    x_prime = Multivector(
        jnp.stack([s[n] for n in ("e1inf", "e2inf", "e3inf", "e123inf")], axis=-1),
        alg.parse_blades(("e1", "e2", "e3", "e123")),
    )
    t_r = x_prime * ~rotor_part
    t = -((1.0 + jnp.exp(lam)) / c2)[..., None] * jnp.stack([t_r[n] for n in ("e1", "e2", "e3")], axis=-1)
    rot = log_motor(rotor_part).values[..., :3]
    w = _rotation_vector(rot)
    v = jnp.linalg.solve(_v_matrix(lam, w), t[..., None])[..., 0]
    return Multivector(jnp.concatenate([rot, -0.5 * v, 0.5 * lam[..., None]], axis=-1), SIMILITUDE_GENERATOR)


def exp(b: Multivector) -> Multivector:
    """Exponential of a motor or similitude generator (dispatch on the static blades).

    Args:
        b: bivectors: on the motor generators (a motor results) or also on eoinf (a similitude results).
    Returns:
        ``exp_motor(b)`` or ``exp_similitude(b)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 1.0, 0]), 1.0), jnp.array([0.5, 0, 0]))
        >>> half = cga.exp(0.5 * cga.log(M))  # the motor halfway along the screw motion
        >>> x = jnp.array([1.0, 2.0, 3.0])
        >>> bool(jnp.allclose(cga.apply_to_points(half * half, x), cga.apply_to_points(M, x), atol=1e-5))
        True
    """
    if isinstance(b, Multivector) and set(b.blades) <= set(MOTOR_GENERATOR):
        return exp_motor(b)
    return exp_similitude(b)


def log(v: Multivector) -> Multivector:
    """Logarithm of a motor or similitude (dispatch on the static blades).

    Args:
        v: motors (their blades a subset of the motor's) or similitudes.
    Returns:
        ``log_motor(v)`` or ``log_similitude(v)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> cga.log(cga.translator(jnp.array([2.0, 0, 0]))).names
        ('e12', 'e13', 'e23', 'e1inf', 'e2inf', 'e3inf')
    """
    if isinstance(v, Multivector) and set(v.blades) <= set(KINDS["motor"]):
        return log_motor(v)
    return log_similitude(v)
