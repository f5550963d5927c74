"""Independent reference: conversion between jaxcga multivectors and ``clifford``'s G(4,1) (g3c).

clifford works in the orthonormal basis e1, e2, e3, e4 = e+ (square +1), e5 = e- (square -1). The
null vectors are built there, eo = (e- - e+)/2 and einf = e- + e+, and a jaxcga blade (bit i = i-th
vector of e1, e2, e3, eo, einf) is the clifford *outer* product of its vectors in bit order. Nothing
here uses jaxcga's product tables: only clifford's own arithmetic.

clifford costs a few seconds to import, so import this module once per test module (it is cached by
Python's module system) rather than inside tests.
"""

from __future__ import annotations

import functools

import numpy as np
from clifford import g3c

import jaxcga
from jaxcga import Multivector

LAYOUT = g3c.layout
BLADES = g3c.blades
# float64 values throughout: clifford's numba kernels compile once per dtype signature, and its
# basis blades carry int64 values
E1, E2, E3, E4, E5 = (LAYOUT.MultiVector(BLADES[f"e{i}"].value.astype(np.float64)) for i in range(1, 6))
EO = 0.5 * (E5 - E4)
EINF = E5 + E4
NULL_VECTORS = (E1, E2, E3, EO, EINF)
#: clifford's unit pseudoscalar e1^e2^e3^e+^e- (the paper's I).
I5 = E1 ^ E2 ^ E3 ^ E4 ^ E5


@functools.cache
def _blade_matrix() -> np.ndarray:
    """[bitmask, clifford component]: clifford value array of each null-basis blade."""
    out = np.zeros((32, LAYOUT.gaDims))
    for mask in range(32):
        mv = 1.0 + 0 * E1
        for i in range(5):
            if mask >> i & 1:
                mv = mv ^ NULL_VECTORS[i]
        out[mask] = mv.value
    return out


def to_clifford_values(m: Multivector) -> np.ndarray:
    """clifford value arrays, shape batch + (32,), of a jaxcga multivector."""
    values = np.asarray(m.values, dtype=np.float64)
    if not m.blades:
        return np.zeros(values.shape[:-1] + (LAYOUT.gaDims,))
    rows = _blade_matrix()[list(m.blades)]  # (k, 32)
    return values @ rows


def to_clifford(m: Multivector):
    """A single (unbatched) jaxcga multivector as a clifford MultiVector."""
    values = to_clifford_values(m)
    if values.ndim != 1:
        raise ValueError(f"to_clifford: expected an unbatched multivector, got batch {values.shape[:-1]}")
    return LAYOUT.MultiVector(values)


def to_clifford_list(m: Multivector) -> list:
    """A batch of jaxcga multivectors as a flat list of clifford MultiVectors (C order)."""
    values = to_clifford_values(m)
    return [LAYOUT.MultiVector(v) for v in values.reshape(-1, LAYOUT.gaDims)]


@functools.cache
def _inverse_blade_matrix() -> np.ndarray:
    return np.linalg.inv(_blade_matrix())


def null_coefficients(values) -> np.ndarray:
    """Coefficients (..., 32), indexed by blade bitmask, of clifford value arrays (..., 32)."""
    return np.asarray(values) @ _inverse_blade_matrix()


def from_clifford(mv) -> Multivector:
    """A clifford MultiVector as a jaxcga multivector on all 32 blades (in ``ALL_BLADES`` order)."""
    by_mask = null_coefficients(mv.value)
    return Multivector(by_mask[list(jaxcga.ALL_BLADES)], jaxcga.ALL_BLADES)


def random_multivector(rng: np.random.Generator, kind, batch=()) -> Multivector:
    blades = jaxcga.KINDS[kind] if isinstance(kind, str) else tuple(kind)
    return Multivector(rng.normal(size=tuple(batch) + (len(blades),)), blades)


def assert_mv_close(actual, expected, atol=1e-12, rtol=1e-12, err_msg=""):
    """Compare a jaxcga multivector (any blade set, batched or not) with a clifford MultiVector, a
    list of them, or a clifford value array."""
    got = to_clifford_values(actual)
    if isinstance(expected, list):
        want = np.stack([np.asarray(e.value) for e in expected]).reshape(got.shape)
    elif hasattr(expected, "value"):
        want = np.asarray(expected.value)
    else:
        want = np.asarray(expected)
    np.testing.assert_allclose(got, want, atol=atol, rtol=rtol, err_msg=err_msg)
