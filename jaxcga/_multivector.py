"""The multivector: a pytree of ``values: Array[..., k]`` and a static tuple of k blades.

Leading axes are batch axes and broadcast like numpy. Products are generated at trace time from the
two static blade sets (``_codegen``) and compute only structurally non-zero terms. The inverse of a
multivector is here too, with the division ``a / b`` that needs it.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence
from types import EllipsisType
from typing import Any, overload

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, DTypeLike, Float

from _jaxcga_shared.broadcast import lift_rank, same_rank
from _jaxcga_shared.checks import check_choice, require
from _jaxcga_shared.platform import EXACT, per_platform
from jaxcga import _algebra as alg
from jaxcga import _codegen

#: Named blade sets (DESIGN.md "The kernel").
KINDS: dict[str, tuple[int, ...]] = {
    "scalar": (0,),
    "vector": alg.blades_of_grades(1),
    "bivector": alg.blades_of_grades(2),
    "trivector": alg.blades_of_grades(3),
    "quadvector": alg.blades_of_grades(4),
    "pseudoscalar": alg.blades_of_grades(5),
    "rotor": alg.parse_blades(("1", "e12", "e13", "e23")),
    "translator": alg.parse_blades(("1", "e1inf", "e2inf", "e3inf")),
    "motor": alg.parse_blades(("1", "e12", "e13", "e23", "e1inf", "e2inf", "e3inf", "e123inf")),
    "dilator": alg.parse_blades(("1", "eoinf")),
    "similitude": alg.blades_of_grades(0, 2, 4),
    "even": alg.blades_of_grades(0, 2, 4),
    "odd": alg.blades_of_grades(1, 3, 5),
    "full": alg.ALL_BLADES,
}


#: A blade set as the constructors take it: a kind name, blade names or bitmasks.
Blades = str | Sequence[str] | Sequence[int]
#: What indexes a multivector's batch axes (as numpy indexes an array).
BatchIndex = int | slice | EllipsisType | None | ArrayLike | tuple[Any, ...]


def as_blades(blades: Blades) -> tuple[int, ...]:
    """A kind name, a sequence of blade names, or a sequence of blade bitmasks, as bitmasks."""
    if isinstance(blades, str):
        if blades not in KINDS:
            raise ValueError(f"blades: unknown kind {blades!r}; expected one of {sorted(KINDS)}")
        return KINDS[blades]
    items = tuple(blades)
    names = [b for b in items if isinstance(b, str)]
    if len(names) == len(items):
        items = alg.parse_blades(names)
    elif not all(isinstance(b, (int, np.integer)) and 0 <= b < alg.N_BLADES for b in items):
        raise ValueError(f"blades: expected blade names or bitmasks in [0, 32), got {items!r}")
    bits = tuple(int(b) for b in items)
    if len(set(bits)) != len(bits):
        raise ValueError(f"blades: repeated blade in {bits!r}")
    return bits


def _float_array(values: ArrayLike) -> Array:
    values = jnp.asarray(values)
    if not jnp.issubdtype(values.dtype, jnp.floating):
        values = values.astype(jnp.result_type(float))
    return values


def broadcast_batch(name_a: str, shape_a: Sequence[int], name_b: str, shape_b: Sequence[int]) -> tuple[int, ...]:
    try:
        return tuple(np.broadcast_shapes(tuple(shape_a), tuple(shape_b)))
    except ValueError:
        raise ValueError(
            f"{name_a} and {name_b}: batch shapes {tuple(shape_a)} and {tuple(shape_b)} do not broadcast"
        ) from None


class Multivector(eqx.Module):
    """A batch of multivectors of G(4,1) in the null basis {e1, e2, e3, eo, einf}.

    Args:
        values: array of shape ``(..., k)``; leading axes are batch axes.
        blades: the k blades, as a kind name (``"motor"``, ``"vector"``, ...), blade names
            (``("1", "e12")``) or bitmasks. Static: part of the pytree structure, not of its leaves.

    Operators: ``a * b`` geometric product, ``a ^ b`` outer, ``a | b`` inner (grade |r - s|, zero for
    scalars, as in ``clifford``), ``~a`` reverse, ``v >> x`` sandwich ``v x v^-1``, ``+``, ``-``, and
    scaling by numbers or arrays of batch shape.
    """

    values: Float[Array, "... k"]
    blades: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, values: Float[ArrayLike, "... k"], blades: Blades):
        blades = as_blades(blades)
        values = _float_array(values)
        if values.ndim == 0 or values.shape[-1] != len(blades):
            raise ValueError(
                f"values: expected last axis of length {len(blades)} for blades "
                f"{[alg.blade_name(b) for b in blades]}, got shape {values.shape}"
            )
        self.values = values
        self.blades = blades

    # ---------------------------------------------------------------- structure
    @property
    def batch_shape(self) -> tuple[int, ...]:
        return self.values.shape[:-1]

    @property
    def dtype(self) -> np.dtype:
        return self.values.dtype

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(alg.blade_name(b) for b in self.blades)

    @overload
    def __getitem__(self, name: str) -> Float[Array, "*batch"]: ...

    @overload
    def __getitem__(self, name: BatchIndex) -> Multivector: ...

    def __getitem__(self, name: str | BatchIndex) -> Float[Array, "*batch"] | Multivector:
        """``m["e12"]``: the coefficient of one blade (zero if the blade is not carried).
        Anything else indexes the batch axes: ``m[0]``, ``m[:, None]``, ``m[mask]``."""
        if not isinstance(name, str):
            index = name if isinstance(name, tuple) else (name,)
            return Multivector(self.values[index + (slice(None),)], self.blades)
        blade = alg.parse_blades((name,))[0]
        if blade in self.blades:
            return self.values[..., self.blades.index(blade)]
        return jnp.zeros(self.batch_shape, self.dtype)

    def embed(self, blades: Blades) -> Multivector:
        """The same multivector carried on a larger blade set (missing blades get zeros)."""
        blades = as_blades(blades)
        missing = set(self.blades) - set(blades)
        if missing:
            raise ValueError(f"blades: cannot embed, {[alg.blade_name(b) for b in missing]} not in target set")
        return Multivector(_gather(self.values, self.blades, blades), blades)

    def full(self) -> Float[Array, "... 32"]:
        """Plain ``(..., 32)`` array in the canonical blade order ``ALL_BLADES``."""
        return _gather(self.values, self.blades, alg.ALL_BLADES)

    @classmethod
    def from_full(cls, values: Float[ArrayLike, "... 32"]) -> Multivector:
        return cls(values, alg.ALL_BLADES)

    def grade(self, *grades: int) -> Multivector:
        """Grade projection <m>_g (several grades: their sum)."""
        keep = [i for i, b in enumerate(self.blades) if alg.grade_of(b) in grades]
        return Multivector(self.values[..., keep], tuple(self.blades[i] for i in keep))

    def scalar(self) -> Float[Array, "*batch"]:
        """The scalar part as an array of batch shape."""
        return self["1"]

    def __repr__(self) -> str:
        return f"Multivector(blades={list(self.names)}, values={self.values!r})"

    # ---------------------------------------------------------------- linear
    def __add__(self, other: Multivector | ArrayLike) -> Multivector:
        other = _coerce(other, self)
        broadcast_batch("a", self.batch_shape, "b", other.batch_shape)
        a, b = aligned(self, other)
        blades = alg.sort_blades(a.blades + b.blades)
        if blades == a.blades == b.blades:
            return Multivector(a.values + b.values, blades)
        return Multivector(_gather(a.values, a.blades, blades) + _gather(b.values, b.blades, blades), blades)

    __radd__ = __add__

    def __neg__(self) -> Multivector:
        return Multivector(-self.values, self.blades)

    def __sub__(self, other: Multivector | ArrayLike) -> Multivector:
        return self + (-_coerce(other, self))

    def __rsub__(self, other: ArrayLike) -> Multivector:
        return _coerce(other, self) - self

    def __truediv__(self, other: Multivector | ArrayLike) -> Multivector:
        if isinstance(other, Multivector):
            return self * inverse(other)
        return Multivector(jnp.divide(*same_rank(self.values, _scalar_field(other))), self.blades)

    # ---------------------------------------------------------------- products
    def __mul__(self, other: Multivector | ArrayLike) -> Multivector:
        if not isinstance(other, Multivector):
            return Multivector(jnp.multiply(*same_rank(self.values, _scalar_field(other))), self.blades)
        return product("geometric", self, other)

    def __rmul__(self, other: ArrayLike) -> Multivector:
        return Multivector(jnp.multiply(*same_rank(_scalar_field(other), self.values)), self.blades)

    def __xor__(self, other: Multivector | ArrayLike) -> Multivector:
        return product("outer", self, _coerce(other, self))

    def __rxor__(self, other: ArrayLike) -> Multivector:
        return product("outer", _coerce(other, self), self)

    def __or__(self, other: Multivector | ArrayLike) -> Multivector:
        return product("inner", self, _coerce(other, self))

    def __ror__(self, other: ArrayLike) -> Multivector:
        return product("inner", _coerce(other, self), self)

    def __invert__(self) -> Multivector:
        return Multivector(
            self.values * _signs(alg.reverse_sign, self.blades, self.dtype, self.values.ndim), self.blades
        )

    def __rshift__(self, other: Multivector) -> Multivector:
        return sandwich(self, other)


def _scalar_field(s: ArrayLike) -> Array:
    s = jnp.asarray(s)
    return s[..., None]


def aligned(*mvs: Multivector) -> tuple[Multivector, ...]:
    """The multivectors with as many batch axes each (leading unit axes added), as numpy would broadcast them."""
    n = max(m.values.ndim for m in mvs)
    return tuple(m if m.values.ndim == n else Multivector(lift_rank(m.values, n), m.blades) for m in mvs)


def _coerce(x: Multivector | ArrayLike, like: Multivector) -> Multivector:
    if isinstance(x, Multivector):
        return x
    return Multivector(jnp.asarray(x, like.dtype)[..., None], (0,))


def _signs(rule: Callable[[int], int], blades: tuple[int, ...], dtype: DTypeLike, ndim: int = 1) -> Array:
    """The sign of each blade under ``rule``, shaped (1, ..., 1, k) with ``ndim`` axes to multiply values of as many."""
    signs = np.array([rule(b) for b in blades], dtype=float).reshape((1,) * (ndim - 1) + (-1,))
    return jnp.asarray(signs, dtype)


def _gather(values: Array, source: tuple[int, ...], target: tuple[int, ...]) -> Array:
    """Reorder / zero-pad the last axis from blade set ``source`` to ``target`` (a superset)."""
    if source == target:
        return values
    index = {b: i for i, b in enumerate(source)}
    zero = jnp.zeros(values.shape[:-1], values.dtype)
    return jnp.stack([values[..., index[b]] if b in index else zero for b in target], axis=-1)


def stack_columns(columns: Sequence[Array], batch_shape: tuple[int, ...], dtype: DTypeLike) -> Array:
    if not columns:
        return jnp.zeros(tuple(batch_shape) + (0,), dtype)
    return jnp.stack(columns, axis=-1)


def product(kind: str, a: Multivector, b: Multivector) -> Multivector:
    """The product ``kind`` (see ``_algebra.GRADE_RULES``) of a and b, generated for their blades."""
    check_choice("kind", kind, sorted(alg.GRADE_RULES))
    batch = broadcast_batch("a", a.batch_shape, "b", b.batch_shape)
    a, b = aligned(a, b)
    dtype = jnp.result_type(a.dtype, b.dtype)
    terms = _codegen.bilinear_terms(kind, a.blades, b.blades)
    blades, columns = _codegen.emit(terms, (_codegen.LazyColumns(a.values), _codegen.LazyColumns(b.values)), batch)
    return Multivector(stack_columns(columns, batch, dtype), blades)


def sandwich(v: Multivector, x: Multivector) -> Multivector:
    """``v x v^-1`` (eq. 14) as one generated expression, bilinear in v, projected on the grades of x.

    ``v`` is a versor; ``v^-1 = ~v / <v ~v>_0``, so un-normalized versors (e.g. the paper's dilator
    of eq. 12) act correctly too.

    Args:
        v: versors, batch shape broadcasting with ``x``'s.
        x: multivectors (points, spheres, planes, other versors, ...).
    Returns:
        ``v x v^-1`` on the grades of ``x`` (also written ``v >> x``).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.translator(jnp.array([0, 0, 1.0]))
        >>> S = cga.sandwich(T, cga.sphere(jnp.zeros(3), 1.0))  # the sphere moved up by 1
        >>> [p.round(6).tolist() for p in cga.sphere_center_radius(S)]
        [[0.0, 0.0, 1.0], 1.0]
    """
    if not isinstance(v, Multivector) or not isinstance(x, Multivector):
        raise ValueError("sandwich: v and x must be Multivectors")
    batch = broadcast_batch("v", v.batch_shape, "x", x.batch_shape)
    v, x = aligned(v, x)
    vc = _codegen.LazyColumns(v.values)
    terms = _codegen.sandwich_terms(v.blades, x.blades)
    blades, columns = _codegen.emit(terms, (vc, vc, _codegen.LazyColumns(x.values)), batch)
    scale = product("scalar", v, ~v).values[..., 0]  # a versor's <v ~v>_0 is never structurally zero
    out = Multivector(stack_columns(columns, batch, jnp.result_type(v.dtype, x.dtype)), blades)
    return out / scale


@functools.cache
def _closure(blades: tuple[int, ...]) -> tuple[int, ...]:
    """Smallest blade set containing 1 and ``blades`` that is closed under the geometric product."""
    closed = set(blades) | {0}
    while True:
        new = {c for a in closed for b in closed for c, _ in alg.blade_product("geometric", a, b)} | closed
        if new == closed:
            return alg.sort_blades(closed)
        closed = new


def inverse(m: Multivector) -> Multivector:
    """Inverse of any invertible multivector: solves ``m x = 1`` in the subalgebra generated by m's
    blades (a linear system of at most 32 unknowns). Non-invertible input raises (inside jit too).

    Args:
        m: an invertible multivector (checked, also inside ``jit``).
    Returns:
        ``m^-1``, on the blades of the subalgebra that ``m``'s blades generate.
    Examples:
        >>> import jaxcga as cga
        >>> m = 1.0 + 2.0 * cga.basis_vector("e1")
        >>> [round(v, 6) for v in cga.inverse(m).values.tolist()]
        [-0.333333, 0.666667]
    """
    blades = _closure(m.blades)
    n = len(blades)
    # Left-multiplication matrix L[k, j]: component k of m * (blade j).
    terms = _codegen.bilinear_terms("geometric", m.blades, blades)
    out_index = {b: k for k, b in enumerate(blades)}
    cols = _codegen.LazyColumns(m.values)
    zero = jnp.zeros(m.batch_shape, m.dtype)
    rows = [[zero] * n for _ in range(n)]
    for out_blade, blade_terms in terms:
        k = out_index[out_blade]
        for (ia, j), coef in blade_terms:
            rows[k][j] = rows[k][j] + coef * cols[ia]
    matrix = jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)
    rhs = jnp.zeros(m.batch_shape + (n,), m.dtype).at[..., blades.index(0)].set(1.0)
    x = jnp.linalg.solve(matrix, rhs[..., None])[..., 0]
    residual = jnp.einsum("...kj,...j->...k", matrix, x, precision=EXACT) - rhs
    scale = 1.0 + jnp.max(jnp.abs(matrix)) * jnp.max(jnp.abs(x), initial=0.0)
    bad = ~jnp.all(jnp.isfinite(x)) | (jnp.max(jnp.abs(residual), initial=0.0) > 1e-6 * scale)
    x = require(x, (bad, "inverse: multivector is not invertible"))
    return Multivector(x, blades)


def _generated_product(a: Multivector, b: Multivector, *, kind: str) -> Multivector:
    dtype = jnp.result_type(a.dtype, b.dtype)
    return product(kind, Multivector(a.values.astype(dtype), a.blades), Multivector(b.values.astype(dtype), b.blades))


@per_platform("table_product", gpu=_generated_product)
def _contracted_product(a: Multivector, b: Multivector, *, kind: str) -> Multivector:
    a, b = aligned(a, b)
    dtype = jnp.result_type(a.dtype, b.dtype)
    blades, table = _codegen.bilinear_tensor(kind, a.blades, b.blades)
    values = jnp.einsum(
        "...i,ijk,...j->...k",
        a.values.astype(dtype),
        jnp.asarray(table, dtype),
        b.values.astype(dtype),
        precision=EXACT,
    )
    return Multivector(values, blades)


def table_product(kind: str, a: Multivector, b: Multivector) -> Multivector:
    """The same product as ``product``, evaluated as one contraction with the structure tensor of the
    two blade sets (``a_i T_ijk b_j``) instead of generated per-blade expressions.

    For small batches: per-joint data such as forward kinematics and joint versors. There XLA:CPU
    compiles the generated expressions into one kernel per output blade plus a concatenate (17
    kernels for two similitudes), and the contraction into two dots: forward kinematics takes about
    half the time (benchmarks/README.md, "Kernel and deformers"). For large batches (a versor per point)
    use ``product``: it skips the structural zeros (for two similitudes the tensor holds 256 non-zeros among 4,096
    entries). The choice is made per platform when the computation is lowered: elsewhere than on the
    CPU (GPUs, where XLA fuses the generated expressions into one kernel) this is ``product``.

    Args:
        kind: the product: "geometric", "outer", "inner", "left_contraction", "regressive", ... (as ``product``).
        a: a multivector, batch shape broadcasting with ``b``'s.
        b: a multivector.
    Returns:
        The product, equal to ``product(kind, a, b)``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), 0.3), jnp.array([1.0, 0, 0]))
        >>> bool(jnp.allclose(cga.table_product("geometric", M, M).values, (M * M).values))
        True
    """
    check_choice("kind", kind, sorted(alg.GRADE_RULES))
    broadcast_batch("a", a.batch_shape, "b", b.batch_shape)
    return _contracted_product(a, b, kind=kind)


@functools.cache
def _pseudoscalar() -> tuple[tuple[int, ...], np.ndarray]:
    terms = alg.pseudoscalar_terms()
    return tuple(terms), np.array([float(c) for c in terms.values()])


def pseudoscalar(dtype: DTypeLike | None = None) -> Multivector:
    """The paper's pseudoscalar I = e1^e2^e3^e+^e- (eq. 6); I * I = -1.

    Args:
        dtype: the value's dtype; None: JAX's default float.
    Returns:
        I, a multivector on the one blade e123oinf (e1^e2^e3^eo^einf).
    Examples:
        >>> import jaxcga as cga
        >>> I = cga.pseudoscalar()
        >>> I.names, (I * I).values.tolist()
        (('e123oinf',), [-1.0])
    """
    blades, values = _pseudoscalar()
    return Multivector(jnp.asarray(values, dtype or jnp.result_type(float)), blades)
