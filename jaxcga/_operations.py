"""Products and unary operations on multivectors (cut/tear/drill paper, sections 2.2-2.4).

All products are generated from the static blade sets of their operands (``_codegen``) and
broadcast over leading batch axes.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, DTypeLike, Float

from _jaxcga_shared.checks import require
from jaxcga import _algebra as alg
from jaxcga import _codegen
from jaxcga._multivector import (
    KINDS,
    Blades,
    Multivector,
    _signs,
    as_blades,
    product,
    pseudoscalar,
)


def geometric(a: Multivector, b: Multivector) -> Multivector:
    """Geometric product ``a b``.

    Args:
        a: a multivector of any blades, batch shape broadcasting with ``b``'s.
        b: a multivector of any blades.
    Returns:
        The multivector ``a b``, on the blades that can be non-zero.
    Examples:
        >>> import jaxcga as cga
        >>> e1, e2 = cga.basis_vector("e1"), cga.basis_vector("e2")
        >>> m = cga.geometric(e1, e2)
        >>> m.names, m.values.tolist()
        (('e12',), [1.0])
    """
    return product("geometric", a, b)


def outer(a: Multivector, b: Multivector) -> Multivector:
    """Outer (wedge) product ``a ^ b``.

    Args:
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        The multivector ``a ^ b`` (grade r + s of each pair of grade-r and grade-s parts).
    Examples:
        >>> import jaxcga as cga
        >>> e1 = cga.basis_vector("e1")
        >>> cga.outer(e1, cga.basis_vector("e2")).names, cga.outer(e1, e1).names  # e1 ^ e1 has no blade
        (('e12',), ())
    """
    return product("outer", a, b)


def left_contraction(a: Multivector, b: Multivector) -> Multivector:
    """Left contraction ``a _| b``: grade s - r of the product of grade-r and grade-s parts.

    Args:
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        The multivector ``a _| b``.
    Examples:
        >>> import jaxcga as cga
        >>> m = cga.left_contraction(cga.basis_vector("e1"), cga.basis_vector("e12"))
        >>> m.names, m.values.tolist()
        (('e2',), [1.0])
    """
    return product("left_contraction", a, b)


def inner(a: Multivector, b: Multivector) -> Multivector:
    """Inner product ``a | b``: grade |r - s|, zero when either part is a scalar (clifford's ``|``).

    On vectors it is the paper's inner product (sec. 2.2): eo . einf = -1, X . Y = -|x - y|^2 / 2.

    Args:
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        The multivector ``a | b``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> a, b = cga.up(jnp.array([1.0, 0, 0])), cga.up(jnp.array([0, 2.0, 0]))
        >>> float(-2 * cga.inner(a, b).values[0])  # the squared distance
        5.0
    """
    return product("inner", a, b)


def scalar_product(a: Multivector, b: Multivector) -> Float[Array, "*batch"]:
    """Scalar part of ``a b``, as an array of batch shape.

    Args:
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        (*batch) the scalar part of ``a b``.
    Examples:
        >>> import jaxcga as cga
        >>> float(cga.scalar_product(cga.basis_vector("e12"), cga.basis_vector("e12")))
        -1.0
    """
    out = product("scalar", a, b)
    return out.values[..., 0] if out.blades else jnp.zeros(out.batch_shape, out.dtype)


def commutator(a: Multivector, b: Multivector) -> Multivector:
    """Commutator product ``(a b - b a) / 2``.

    Args:
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        The multivector ``(a b - b a) / 2``.
    Examples:
        >>> import jaxcga as cga
        >>> m = cga.commutator(cga.basis_vector("e12"), cga.basis_vector("e1"))
        >>> m.names, m.values.tolist()
        (('e2',), [-1.0])
    """
    return (product("geometric", a, b) - product("geometric", b, a)) * 0.5


def reverse(m: Multivector) -> Multivector:
    """Reverse ``~m``: grade g gets the sign (-1)^(g(g-1)/2).

    Args:
        m: a multivector.
    Returns:
        The multivector ``~m`` on the same blades.
    Examples:
        >>> import jaxcga as cga
        >>> cga.reverse(cga.basis_vector("e12")).values.tolist()
        [-1.0]
    """
    return ~m


def involution(m: Multivector) -> Multivector:
    """Grade involution: grade g gets the sign (-1)^g.

    Args:
        m: a multivector.
    Returns:
        The grade involution of ``m``, on the same blades.
    Examples:
        >>> import jaxcga as cga
        >>> e1, e12 = cga.basis_vector("e1"), cga.basis_vector("e12")
        >>> cga.involution(e1).values.tolist(), cga.involution(e12).values.tolist()
        ([-1.0], [1.0])
    """
    return Multivector(m.values * _signs(alg.involution_sign, m.blades, m.dtype, m.values.ndim), m.blades)


def conjugate(m: Multivector) -> Multivector:
    """Clifford conjugate: reverse of the grade involution.

    Args:
        m: a multivector.
    Returns:
        The Clifford conjugate of ``m``, on the same blades.
    Examples:
        >>> import jaxcga as cga
        >>> e1, e12 = cga.basis_vector("e1"), cga.basis_vector("e12")
        >>> cga.conjugate(e1).values.tolist(), cga.conjugate(e12).values.tolist()
        ([-1.0], [-1.0])
    """
    return Multivector(m.values * _signs(alg.conjugate_sign, m.blades, m.dtype, m.values.ndim), m.blades)


def dual(m: Multivector) -> Multivector:
    """The paper's dual ``m* = -m I`` (eq. 7). Since I^2 = -1 this equals ``m I^-1``, clifford's dual;
    ``dual(dual(m)) = -m`` and ``undual(dual(m)) = m``.

    Args:
        m: a multivector.
    Returns:
        The multivector ``-m I``.
    Examples:
        >>> import jaxcga as cga
        >>> m = cga.basis_vector("e1")
        >>> (cga.dual(cga.dual(m)) + m).values.tolist()
        [0.0]
    """
    return -(m * pseudoscalar(m.dtype))


def undual(m: Multivector) -> Multivector:
    """Inverse of ``dual``: ``m I``.

    Args:
        m: a multivector.
    Returns:
        The multivector ``m I``.
    Examples:
        >>> import jaxcga as cga
        >>> m = cga.basis_vector("e2")
        >>> n = cga.undual(cga.dual(m))
        >>> n.names, n.values.tolist()
        (('e2',), [1.0])
    """
    return m * pseudoscalar(m.dtype)


def meet(a: Multivector, b: Multivector) -> Multivector:
    """Regressive product ``a v b`` (clifford's ``vee``): the intersection of two objects given in
    outer-product (direct) form. Metric-free, through complements against I: ``(a v b)`` equals
    ``undual(dual(a) ^ dual(b))`` up to a grade-dependent sign.

    Args:
        a: an object in direct (outer-product) form, batch shape broadcasting with ``b``'s.
        b: an object in direct form.
    Returns:
        The multivector ``a v b``: their intersection, in direct form.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> up = lambda x: cga.up(jnp.array(x))
        >>> x_axis = cga.line(up([0.0, 0, 0]), up([1.0, 0, 0]))
        >>> plane = cga.plane_through(up([2.0, 0, 0]), up([2.0, 1, 0]), up([2.0, 0, 1]))
        >>> point = cga.meet(x_axis, plane)  # a flat point where the axis crosses x = 2
        >>> point.grade(2).names[:3]
        ('e1inf', 'e2inf', 'e3inf')
    """
    return product("regressive", a, b)


def grade(m: Multivector, *grades: int) -> Multivector:
    """Grade projection ``<m>_g``.

    Args:
        m: a multivector.
        *grades: the grades to keep (0 to 5).
    Returns:
        The multivector of ``m``'s blades of those grades.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), 0.5), jnp.array([1.0, 0, 0]))
        >>> cga.grade(M, 0).names
        ('1',)
    """
    return m.grade(*grades)


def norm2(m: Multivector) -> Float[Array, "*batch"]:
    """``<~m m>_0`` (may be negative in this mixed-signature algebra).

    Args:
        m: a multivector.
    Returns:
        (*batch) ``<~m m>_0``.
    Examples:
        >>> import jaxcga as cga
        >>> float(cga.norm2(cga.basis_vector("e1"))), float(cga.norm2(cga.basis_vector("einf")))
        (1.0, 0.0)
    """
    return scalar_product(~m, m)


def _safe_sqrt_abs(x: Float[Array, "*shape"]) -> Float[Array, "*shape"]:
    # sqrt has an infinite derivative at 0; the double where keeps gradients finite there.
    ax = jnp.abs(x)
    positive = ax > 0
    return jnp.where(positive, jnp.sqrt(jnp.where(positive, ax, 1.0)), 0.0)


def norm(m: Multivector) -> Float[Array, "*batch"]:
    """``sqrt(|<~m m>_0|)``, as clifford's ``abs``.

    Args:
        m: a multivector.
    Returns:
        (*batch) ``sqrt(|<~m m>_0|)``, with a finite gradient at zero.
    Examples:
        >>> import jaxcga as cga
        >>> float(cga.norm(2.0 * cga.basis_vector("e12")))
        2.0
    """
    return _safe_sqrt_abs(norm2(m))


def normalize(m: Multivector) -> Multivector:
    """``m / norm(m)``. Motors are normalized exactly: the result satisfies M ~M = 1, with the
    e123inf part of M ~M removed as well (it is not a scale).

    Args:
        m: a multivector of non-zero norm (checked, also inside ``jit``).
    Returns:
        ``m`` scaled to norm 1 (a motor: made exactly unit).
    Examples:
        >>> import jaxcga as cga
        >>> cga.normalize(3.0 * cga.basis_vector("e1")).values.tolist()
        [1.0]
    """
    if set(m.blades) <= set(_motor_blades()):
        return _normalize_motor(m)
    n = norm(m)
    n = require(n, (n == 0, "normalize: m has zero norm"))
    return m / n


@functools.cache
def _motor_blades() -> tuple[int, ...]:
    return KINDS["motor"]


def _normalize_motor(m: Multivector) -> Multivector:
    normalized, bad = normalize_motor_unchecked(m)
    return Multivector(
        require(normalized.values, (bad, "normalize: motor has non-positive norm M~M")), normalized.blades
    )


def normalize_motor_unchecked(m: Multivector) -> tuple[Multivector, Bool[Array, "*batch"]]:
    """``normalize`` of motors without its check, and where it fails (M ~M <= 0: NaN or inf there), for callers
    that check later: on a GPU a check is a host round trip, cheapest once the result is computed."""
    m = m.embed(_motor_blades())
    columns, bad = normalize_motor_columns([m.values[..., i] for i in range(len(m.blades))], m.batch_shape)
    return Multivector(jnp.stack(columns, axis=-1), _motor_blades()), bad


def normalize_motor_columns(m: Sequence[Array], batch_shape: tuple[int, ...]) -> tuple[list[Array], Array]:
    """``normalize_motor_unchecked`` on columns (``KINDS["motor"]`` order, arrays of ``batch_shape``): no stacked
    arrays, so that a kernel over blocks of rows evaluates it too."""
    # M ~M = s + p P with P = e123inf central and P^2 = 0 in the motor algebra, so
    # N = M (1 - p/(2s) P) / sqrt(s) gives N ~N = 1 exactly.
    blades = _motor_blades()
    scalar_p = alg.parse_blades(("1", "e123inf"))
    reverse = [c * alg.reverse_sign(b) for c, b in zip(m, blades)]
    terms = _codegen.bilinear_terms("geometric", blades, blades)
    norm_blades, norm_parts = _codegen.emit(tuple(t for t in terms if t[0] in scalar_p), (m, reverse), batch_shape)
    s, p = (dict(zip(norm_blades, norm_parts))[b] for b in scalar_p)
    alpha = 1.0 / jnp.sqrt(s)
    out_blades, out = _codegen.emit(
        _codegen.bilinear_terms("geometric", blades, scalar_p), (m, [alpha, -alpha * p / (2 * s)]), batch_shape
    )
    by_blade = dict(zip(out_blades, out))
    return [by_blade[b] for b in blades], s <= 0


def versor_inverse(v: Multivector) -> Multivector:
    """Inverse of a versor, ``~v / <v ~v>_0`` (rotors, translators, dilators, motors, similitudes).

    Args:
        v: a versor (``<v ~v>_0`` non-zero, checked).
    Returns:
        The versor ``v^-1`` on ``v``'s blades.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.translator(jnp.array([1.0, 2.0, 3.0]))
        >>> (T * cga.versor_inverse(T)).grade(0).values.tolist()
        [1.0]
    """
    n = scalar_product(v, ~v)
    n = require(n, (n == 0, "versor_inverse: v ~v is zero, v is not invertible"))
    return ~v / n


def zeros(blades: Blades, batch_shape: Sequence[int] = (), dtype: DTypeLike | None = None) -> Multivector:
    """A zero multivector on given blades.

    Args:
        blades: the blades: a kind of ``KINDS`` ("motor", ...), names ("e12", ...) or blade indices.
        batch_shape: the leading batch axes.
        dtype: the values' dtype; None: JAX's default float.
    Returns:
        The multivector, values of shape (*batch_shape, len(blades)).
    Examples:
        >>> import jaxcga as cga
        >>> m = cga.zeros("rotor", (2,))
        >>> m.names, m.values.shape
        (('1', 'e12', 'e13', 'e23'), (2, 4))
    """
    blades = as_blades(blades)
    return Multivector(jnp.zeros(tuple(batch_shape) + (len(blades),), dtype or jnp.result_type(float)), blades)


def scalar(value: Float[ArrayLike, "*batch"], dtype: DTypeLike | None = None) -> Multivector:
    """A (batch of) scalar multivector(s).

    Args:
        value: (*batch) the scalar values.
        dtype: the values' dtype; None: JAX's default float.
    Returns:
        The multivector on the blade ``1``, values of shape (*batch, 1).
    Examples:
        >>> import jaxcga as cga
        >>> cga.scalar([1.0, 2.0]).values.tolist()
        [[1.0], [2.0]]
    """
    value = jnp.asarray(value, dtype or jnp.result_type(float))
    return Multivector(value[..., None], (0,))


def basis_vector(name: str, dtype: DTypeLike | None = None) -> Multivector:
    """One basis blade by name, e.g. ``basis_vector("einf")`` or ``basis_vector("e12")``.

    Args:
        name: the blade's name: ``"1"``, ``"e1"``, ``"eo"``, ``"einf"``, ``"e12"``, ``"e123inf"``, ...
        dtype: the value's dtype; None: JAX's default float.
    Returns:
        The multivector on that blade, value 1.
    Examples:
        >>> import jaxcga as cga
        >>> cga.basis_vector("e12").names
        ('e12',)
    """
    return Multivector(jnp.ones((1,), dtype or jnp.result_type(float)), (name,))


def is_finite(m: Multivector) -> Bool[Array, ""]:
    return jnp.all(jnp.isfinite(m.values))
