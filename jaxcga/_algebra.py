"""The algebra G(4,1) in the null basis {e1, e2, e3, eo, einf}: blades and exact product tables.

Section 2 of the cut/tear/drill paper (eq. 1): eo = (e- - e+)/2, einf = e- + e+, with e+^2 = 1,
e-^2 = -1. A blade is a bitmask over the null basis vectors (bit 0 = e1, 1 = e2, 2 = e3, 3 = eo,
4 = einf) and stands for the *outer* product of its vectors in that order, so ``eo^einf`` is a grade-2
blade (not the geometric product eo einf = -1 + eo^einf).

Product tables are generated once, exactly (``fractions.Fraction``), by expanding each null blade in
the orthonormal basis {e1, e2, e3, e+, e-}, where the metric is diagonal and the product of two
blades is one signed blade, multiplying there, and mapping the result back. In the null basis one
blade product can give several terms with coefficients such as 1/2; the tables carry all of them.
Nothing here touches JAX: the tables feed the code generator in ``_products``.
"""

from __future__ import annotations

import functools
import itertools
from collections.abc import Iterable, Iterator
from fractions import Fraction

import numpy as np

N_VECTORS = 5
N_BLADES = 32
VECTOR_NAMES = ("1", "2", "3", "o", "inf")

# Orthonormal reference basis: bits 0..4 = e1, e2, e3, e+, e-.
_ORTHO_METRIC = (1, 1, 1, 1, -1)
# Null basis vectors written in the orthonormal basis (paper eq. 1).
_NULL_VECTOR_IN_ORTHO = (
    {0b00001: Fraction(1)},
    {0b00010: Fraction(1)},
    {0b00100: Fraction(1)},
    {0b01000: Fraction(-1, 2), 0b10000: Fraction(1, 2)},  # eo = (e- - e+)/2
    {0b01000: Fraction(1), 0b10000: Fraction(1)},  # einf = e- + e+
)


def grade_of(blade: int) -> int:
    return bin(blade).count("1")


def blade_name(blade: int) -> str:
    """The name of a basis blade: ``"1"``, ``"e1"``, ``"e12"``, ``"eoinf"``, ... (over e1, e2, e3, eo, einf).

    Args:
        blade: the blade's index, a bit mask over (e1, e2, e3, eo, einf).
    Returns:
        The name, as ``Multivector.names`` gives it.
    Examples:
        >>> import jaxcga as cga
        >>> cga.blade_name(0), cga.blade_name(0b00011), cga.blade_name(0b11000)
        ('1', 'e12', 'eoinf')
    """
    if blade == 0:
        return "1"
    return "e" + "".join(VECTOR_NAMES[i] for i in range(N_VECTORS) if blade >> i & 1)


def _canonical_key(blade: int) -> tuple[int, list[int]]:
    return (grade_of(blade), [i for i in range(N_VECTORS) if blade >> i & 1])


#: All 32 blades, by grade and then lexicographically by basis vector.
ALL_BLADES: tuple[int, ...] = tuple(sorted(range(N_BLADES), key=_canonical_key))
BLADE_BY_NAME: dict[str, int] = {blade_name(b): b for b in ALL_BLADES}


def sort_blades(blades: Iterable[int]) -> tuple[int, ...]:
    """A set of blades in canonical order, without repeats."""
    return tuple(sorted(set(blades), key=_canonical_key))


def blades_of_grades(*grades: int) -> tuple[int, ...]:
    return tuple(b for b in ALL_BLADES if grade_of(b) in grades)


def parse_blades(names: Iterable[str]) -> tuple[int, ...]:
    """Blade names such as ``("1", "e12", "e1inf")`` to bitmasks, keeping the given order."""
    try:
        return tuple(BLADE_BY_NAME[n] for n in names)
    except KeyError as err:
        raise ValueError(
            f"blades: unknown blade name {err.args[0]!r}; names look like 'e12', 'e3inf', 'eoinf'"
        ) from None


def _reorder_sign(a: int, b: int) -> int:
    """Sign from moving the vectors of blade b past those of blade a into canonical order."""
    a >>= 1
    swaps = 0
    while a:
        swaps += bin(a & b).count("1")
        a >>= 1
    return -1 if swaps & 1 else 1


def _ortho_blade_product(a: int, b: int) -> tuple[int, int]:
    sign = _reorder_sign(a, b)
    common = a & b
    for i in range(N_VECTORS):
        if common >> i & 1:
            sign *= _ORTHO_METRIC[i]
    return a ^ b, sign


def _ortho_product(x: dict, y: dict, keep_grade=None) -> dict:
    """Geometric product of two orthonormal-basis multivectors (dicts blade -> coefficient), keeping
    only result blades whose grade satisfies ``keep_grade(grade_x, grade_y, grade_out)``."""
    out: dict[int, Fraction] = {}
    for a, ca in x.items():
        for b, cb in y.items():
            c, sign = _ortho_blade_product(a, b)
            if keep_grade is not None and not keep_grade(grade_of(a), grade_of(b), grade_of(c)):
                continue
            out[c] = out.get(c, 0) + sign * ca * cb
    return {k: v for k, v in out.items() if v != 0}


def _outer_rule(r: int, s: int, g: int) -> bool:
    return g == r + s


@functools.cache
def _null_to_ortho() -> tuple[dict, ...]:
    """Orthonormal expansion of each null blade (outer product of its vectors)."""
    table = []
    for blade in range(N_BLADES):
        acc = {0: Fraction(1)}
        for i in range(N_VECTORS):
            if blade >> i & 1:
                acc = _ortho_product(acc, _NULL_VECTOR_IN_ORTHO[i], _outer_rule)
        table.append(acc)
    return tuple(table)


@functools.cache
def _ortho_to_null() -> np.ndarray:
    """Inverse change of basis, as an exact object array [null_blade, ortho_blade]."""
    forward = np.zeros((N_BLADES, N_BLADES))
    for blade, expansion in enumerate(_null_to_ortho()):
        for ortho, coef in expansion.items():
            forward[ortho, blade] = float(coef)
    inverse = np.linalg.inv(forward)
    exact = np.empty_like(inverse, dtype=object)
    for idx, value in np.ndenumerate(inverse):
        exact[idx] = Fraction(float(value)).limit_denominator(64)
    return exact


def _to_null(ortho: dict) -> dict:
    inverse = _ortho_to_null()
    out: dict[int, Fraction] = {}
    for ortho_blade, coef in ortho.items():
        for null_blade in range(N_BLADES):
            c = inverse[null_blade, ortho_blade]
            if c != 0:
                out[null_blade] = out.get(null_blade, 0) + coef * c
    return {k: v for k, v in out.items() if v != 0}


# Which output grades each product keeps, given the operand grades r, s (grades are basis-free, so
# they can be selected in the orthonormal basis).
GRADE_RULES = {
    "geometric": None,
    "outer": _outer_rule,
    "left_contraction": lambda r, s, g: s >= r and g == s - r,
    "right_contraction": lambda r, s, g: r >= s and g == r - s,
    "inner": lambda r, s, g: r > 0 and s > 0 and g == abs(r - s),
    "scalar": lambda r, s, g: g == 0,
    "regressive": None,  # computed through complements, see blade_product
}


_FULL_MASK = N_BLADES - 1


def _ortho_complement(x: dict, right: bool) -> dict:
    """Metric-free complement against I = e1^e2^e3^e+^e-: right, x ^ rc(x) = I; left, lc(x) ^ x = I
    (the convention of clifford's ``vee``)."""
    out = {}
    for blade, coef in x.items():
        comp = _FULL_MASK ^ blade
        sign = _reorder_sign(blade, comp) if right else _reorder_sign(comp, blade)
        out[comp] = sign * coef
    return out


def _regressive(x: dict, y: dict) -> dict:
    """Regressive (vee) product: lc(rc(x) ^ rc(y)), independent of the metric."""
    wedge = _ortho_product(_ortho_complement(x, True), _ortho_complement(y, True), _outer_rule)
    return _ortho_complement(wedge, False)


@functools.cache
def blade_product(kind: str, a: int, b: int) -> tuple[tuple[int, Fraction], ...]:
    """Product of two null-basis blades as exact terms ((blade, coefficient), ...)."""
    x, y = _null_to_ortho()[a], _null_to_ortho()[b]
    if kind == "regressive":
        return tuple(sorted(_to_null(_regressive(x, y)).items()))
    rule = GRADE_RULES[kind]
    keep = None if rule is None else (lambda r, s, g: rule(grade_of(a), grade_of(b), g))
    return tuple(sorted(_to_null(_ortho_product(x, y, keep)).items()))


def reverse_sign(blade: int) -> int:
    g = grade_of(blade)
    return -1 if (g * (g - 1) // 2) % 2 else 1


def involution_sign(blade: int) -> int:
    return -1 if grade_of(blade) % 2 else 1


def conjugate_sign(blade: int) -> int:
    return reverse_sign(blade) * involution_sign(blade)


PSEUDOSCALAR = 0b11111  # e1^e2^e3^eo^einf


def pseudoscalar_terms() -> dict[int, Fraction]:
    """The paper's I = e1^e2^e3^e+^e- = e1^e2^e3^einf^eo (eq. 6) in our blade e123oinf."""
    # einf^eo = -eo^einf, so I = -e123oinf.
    return {PSEUDOSCALAR: Fraction(-1)}


def all_pairs(
    blades_a: tuple[int, ...], blades_b: tuple[int, ...]
) -> Iterator[tuple[tuple[int, int], tuple[int, int]]]:
    return itertools.product(enumerate(blades_a), enumerate(blades_b))
