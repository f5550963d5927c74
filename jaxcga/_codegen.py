"""Trace-time code generation of sparse products from static blade sets.

Every product of two multivectors is a bilinear map whose structure depends only on the two static
blade sets. ``bilinear_terms`` lists, for each output blade, the exact terms ``c * a[i] * b[j]`` that
are structurally non-zero; ``sandwich_terms`` does the same for ``V X ~V`` as one expression,
quadratic in V, with the symmetric pairs V_i V_j = V_j V_i merged so that terms which cancel in exact
arithmetic are never emitted. ``emit`` turns such term lists into JAX operations on the last axis;
XLA fuses them into one elementwise loop, which is what makes a per-point sandwich fast.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from fractions import Fraction
from typing import Protocol

import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array

from jaxcga import _algebra as alg

Terms = tuple[tuple[int, tuple[tuple[tuple[int, ...], float], ...]], ...]


class Columns(Protocol):
    """A factor of the generated terms: its idx-th component (an array of batch shape) by ``columns[idx]``."""

    def __getitem__(self, idx: int, /) -> Array: ...


@functools.cache
def bilinear_terms(kind: str, blades_a: tuple[int, ...], blades_b: tuple[int, ...]) -> Terms:
    """((out_blade, ((ia, ib), coef), ...), ...) for the product ``kind`` of the two blade sets."""
    acc: dict[int, dict[tuple[int, int], Fraction]] = {}
    for (ia, a), (ib, b) in alg.all_pairs(blades_a, blades_b):
        for c, coef in alg.blade_product(kind, a, b):
            acc.setdefault(c, {})
            acc[c][(ia, ib)] = acc[c].get((ia, ib), 0) + coef
    return _finish(acc)


@functools.cache
def bilinear_tensor(
    kind: str, blades_a: tuple[int, ...], blades_b: tuple[int, ...]
) -> tuple[tuple[int, ...], np.ndarray]:
    """The same product as a dense structure tensor: (out_blades, T) with ``T[ia, ib, k]`` the
    coefficient of ``out_blades[k]`` in ``a[ia] b[ib]`` (for ``table_product``)."""
    terms = bilinear_terms(kind, blades_a, blades_b)
    table = np.zeros((len(blades_a), len(blades_b), len(terms)))
    for k, (_, blade_terms) in enumerate(terms):
        for (ia, ib), coef in blade_terms:
            table[ia, ib, k] = coef
    table.setflags(write=False)
    return tuple(b for b, _ in terms), table


@functools.cache
def sandwich_terms(blades_v: tuple[int, ...], blades_x: tuple[int, ...]) -> Terms:
    """Terms of <V X ~V> projected on the grades of X, as ((out, ((i, j, l), coef), ...), ...),
    meaning sum coef * V[i] * V[j] * X[l] with i <= j."""
    grades = {alg.grade_of(b) for b in blades_x}
    acc: dict[int, dict[tuple[int, int, int], Fraction]] = {}
    for (i, vi), (l, xl) in alg.all_pairs(blades_v, blades_x):
        for m, c1 in alg.blade_product("geometric", vi, xl):
            for j, vj in enumerate(blades_v):
                c_rev = alg.reverse_sign(vj)
                for out, c2 in alg.blade_product("geometric", m, vj):
                    if alg.grade_of(out) not in grades:
                        continue
                    key = (min(i, j), max(i, j), l)
                    acc.setdefault(out, {})
                    acc[out][key] = acc[out].get(key, 0) + c1 * c2 * c_rev
    return _finish(acc)


def _finish(acc: dict[int, dict]) -> Terms:
    out = []
    for blade in alg.sort_blades(acc):
        terms = tuple((key, float(c)) for key, c in sorted(acc[blade].items()) if c != 0)
        if terms:
            out.append((blade, terms))
    return tuple(out)


def emit(terms: Terms, factors: Sequence[Columns], shape_hint: tuple[int, ...]) -> tuple[tuple[int, ...], list[Array]]:
    """Evaluate generated terms. ``factors[p][idx]`` is the idx-th component (an array) of the p-th
    factor of each term. Returns the tuple of output blades and one array per output blade.

    Terms sharing a coefficient magnitude are summed first and scaled once (most coefficients are
    +-1 or +-2), which saves a multiply per term on the hot path."""
    used = sorted({(p, i) for _, blade_terms in terms for key, _ in blade_terms for p, i in enumerate(key)})
    raw = {pi: jnp.asarray(factors[pi[0]][pi[1]]) for pi in used}
    dtype = jnp.result_type(*raw.values()) if raw else jnp.result_type(float)
    # the components at the output's shape and dtype, once each: the terms are then lax's own operations, bound
    # directly (numpy-style operators would wrap each of the thousands of them in a jitted function to trace)
    cols = {pi: _at(x, shape_hint, dtype) for pi, x in raw.items()}
    columns = []
    for _, blade_terms in terms:
        groups: dict[float, Array] = {}
        for key, coef in blade_terms:
            prod = cols[0, key[0]]
            for p in range(1, len(key)):
                prod = lax.mul(prod, cols[p, key[p]])
            mag = abs(coef)
            if mag in groups:
                groups[mag] = lax.add(groups[mag], prod) if coef > 0 else lax.sub(groups[mag], prod)
            else:
                groups[mag] = prod if coef > 0 else lax.neg(prod)
        scaled = [
            total if mag == 1.0 else lax.mul(total, lax.convert_element_type(mag, dtype))
            for mag, total in groups.items()
        ]
        columns.append(functools.reduce(lax.add, scaled))
    return tuple(b for b, _ in terms), columns


def _at(x: Array, shape: tuple[int, ...], dtype) -> Array:
    """``x`` broadcast to ``shape`` (numpy's rules) in ``dtype``."""
    if x.dtype != dtype:
        x = lax.convert_element_type(x, dtype)
    if x.shape != shape:
        x = lax.broadcast_in_dim(x, shape, tuple(range(len(shape) - x.ndim, len(shape))))
    return x


class LazyColumns:
    """``values[..., i]`` on first use, so unused components of a factor cost nothing."""

    def __init__(self, values: Array):
        self._values = values
        self._cache: dict[int, Array] = {}

    def __getitem__(self, i: int) -> Array:
        if i not in self._cache:
            self._cache[i] = lax.index_in_dim(self._values, i, axis=-1, keepdims=False)
        return self._cache[i]
