"""Algebraic properties of the kernel, checked with hypothesis on random inputs."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

import jaxcga
from jaxcga import Multivector

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
#: hypothesis draws a small batch per example: eager cost is per call, not per element.
B = 2

_floats = st.floats(-2.0, 2.0, allow_nan=False, allow_infinity=False, width=64)


def coefficients(k: int, batch=(B,)):
    return arrays(np.float64, tuple(batch) + (k,), elements=_floats)


def multivectors(kind: str):
    """A batch of B multivectors on the blade set ``kind``."""
    blades = jaxcga.KINDS[kind]
    return coefficients(len(blades)).map(lambda v: Multivector(jnp.asarray(v), blades))


def points(batch=(B,)):
    return arrays(np.float64, tuple(batch) + (3,), elements=st.floats(-5.0, 5.0, allow_nan=False, width=64))


def unit_vectors(batch=(B,)):
    return (
        arrays(np.float64, tuple(batch) + (3,), elements=_floats)
        .filter(lambda v: np.all(np.linalg.norm(v, axis=-1) > 0.3))
        .map(lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True))
    )


def _scalars(lo, hi):
    return arrays(np.float64, (B,), elements=st.floats(lo, hi, width=64))


@st.composite
def motors(draw):
    """A batch of normalized general motors: 8 random components (so M ~M has an e123inf part
    before normalization), normalized by ``jaxcga.normalize``."""
    v = draw(coefficients(8))
    assume(np.all(np.sum(v[..., :4] ** 2, axis=-1) > 0.1))  # rotor part: M ~M = that sum
    return jaxcga.normalize(Multivector(jnp.asarray(v), "motor"))


VERSOR_KINDS = ["rotor", "translator", "dilator", "motor", "similitude", "dilator_paper"]


@st.composite
def versors(draw):
    """A batch of B versors of one randomly chosen type, from jaxcga's constructors, carried on the
    similitude blade set (one generated product per test instead of one per versor type; the
    per-type blade sets are checked against clifford in test_products)."""
    which = draw(st.sampled_from(VERSOR_KINDS))
    axis, angle = draw(unit_vectors()), draw(_scalars(-3.0, 3.0))
    t, scale = draw(points()), draw(_scalars(0.25, 4.0))
    R = jaxcga.rotor(axis, angle)
    return {
        "rotor": lambda: R,
        "translator": lambda: jaxcga.translator(t),
        "dilator": lambda: jaxcga.dilator(scale),
        "motor": lambda: jaxcga.motor(R, t),
        "similitude": lambda: jaxcga.similitude(R, t, scale),
        "dilator_paper": lambda: jaxcga.dilator_paper(scale),
    }[which]().embed("similitude")


def _close(a: Multivector, b: Multivector, tol=1e-10):
    fa, fb = np.broadcast_arrays(np.asarray(a.full()), np.asarray(b.full()))
    scale = 1.0 + max(np.max(np.abs(fa)), np.max(np.abs(fb)))
    np.testing.assert_allclose(fa, fb, atol=tol * scale, rtol=0)


# ---------------------------------------------------------------- algebra
@SETTINGS
@given(multivectors("full"), multivectors("full"), multivectors("full"))
def test_geometric_product_is_associative(a, b, c):
    _close((a * b) * c, a * (b * c))


@SETTINGS
@given(multivectors("even"), multivectors("vector"), multivectors("bivector"))
def test_geometric_product_is_associative_on_sparse_sets(a, b, c):
    _close((a * b) * c, a * (b * c))
    _close((b * c) * a, b * (c * a))


@SETTINGS
@given(multivectors("vector"), multivectors("vector"))
def test_vector_product_splits_into_inner_and_outer(a, b):
    _close(a * b, (a | b) + (a ^ b))
    _close(jaxcga.left_contraction(a, b), a | b)


@SETTINGS
@given(multivectors("full"))
def test_dual_twice_is_minus_and_undual_inverts(m):
    _close(jaxcga.dual(jaxcga.dual(m)), -m)
    _close(jaxcga.undual(jaxcga.dual(m)), m)
    _close(jaxcga.dual(jaxcga.undual(m)), m)


def _left_multiplication_matrix(m: Multivector) -> np.ndarray:
    """[out blade, basis blade j] of m * e_j, on all 32 blades (m unbatched)."""
    basis = Multivector(jnp.eye(32), jaxcga.ALL_BLADES)  # batch of the 32 basis blades
    return np.asarray((m * basis).full()).T


@pytest.mark.slow
@SETTINGS
@given(coefficients(32, ()))
def test_inverse_is_inverse(v):
    m = Multivector(jnp.asarray(v), "full")
    try:
        inv = jaxcga.inverse(m)
    except ValueError as err:
        # hypothesis likes sparse inputs such as a null vector: then m must really be singular
        assert "not invertible" in str(err)
        assert np.linalg.cond(_left_multiplication_matrix(m)) > 1e8
        return
    one = Multivector(jnp.ones(1), ("1",))
    # the residual scales with |m| |m^-1|
    cond = 1.0 + float(jnp.max(jnp.abs(m.values))) * float(jnp.max(jnp.abs(inv.values)))
    _close(m * inv, one, tol=1e-10 * cond)
    _close(inv * m, one, tol=1e-10 * cond)


def test_inverse_of_sparse_invertible_inputs():
    """Single blades and simple sums that are invertible (non-null)."""
    for blades, values in [(("eo", "einf"), [1.0, 0.5]), (("eoinf",), [3.0]), (("1", "e1inf"), [2.0, 5.0])]:
        m = Multivector(jnp.asarray(values), blades)
        inv = jaxcga.inverse(m)
        _close(m * inv, Multivector(jnp.ones(1), ("1",)), tol=1e-12)


# ---------------------------------------------------------------- versors
@SETTINGS
@given(motors(), points(), points())
def test_normalized_motor_preserves_distances(M, x, y):
    mm = M * ~M
    _close(mm, Multivector(jnp.ones(1), ("1",)), tol=1e-12)
    X, Y = jaxcga.up(jnp.asarray(x)), jaxcga.up(jnp.asarray(y))
    MX, MY = M >> X, M >> Y
    # X . Y = -|x - y|^2 / 2, and normalized points stay normalized (eo coefficient 1)
    np.testing.assert_allclose(
        np.asarray(jaxcga.scalar_product(MX, MY)), np.asarray(jaxcga.scalar_product(X, Y)), atol=1e-9
    )
    np.testing.assert_allclose(
        np.asarray(jaxcga.scalar_product(MX, MY)), -0.5 * np.sum((x - y) ** 2, axis=-1), atol=1e-9
    )
    np.testing.assert_allclose(np.asarray(MX["eo"]), 1.0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(jaxcga.scalar_product(MX, MX)), 0.0, atol=1e-9)  # still null


@SETTINGS
@given(versors(), multivectors("vector"), multivectors("bivector"))
def test_sandwich_keeps_grade(V, x, biv):
    """V x V^-1 computed with full geometric products has no parts outside x's grade, and equals the
    (grade-projected) sandwich."""
    Vinv = jaxcga.versor_inverse(V)
    for m, g in ((x, 1), (biv, 2)):
        full = V * m * Vinv
        out = V >> m
        assert {bin(b).count("1") for b in out.blades} == {g}
        others = [k for k in range(6) if k != g]
        _close(full.grade(*others), Multivector(jnp.zeros(1), ("1",)))
        _close(full.grade(g), out)


@SETTINGS
@given(versors(), versors(), points())
def test_sandwich_composes(V, W, x):
    X = jaxcga.up(jnp.asarray(x))
    _close((V * W) >> X, V >> (W >> X), tol=1e-9)


# ---------------------------------------------------------------- meet of two planes
def _plane_points(n, d, offsets):
    """Three non-collinear points (batches (B, 3)) on the planes x . n = d, n (B, 3) unit."""
    helper = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    a = np.cross(n, helper)
    a /= np.linalg.norm(a, axis=-1, keepdims=True)
    b = np.cross(n, a)
    base = d[:, None] * n + offsets[:, :1] * a + offsets[:, 1:] * b
    return [jaxcga.up(jnp.asarray(p)) for p in (base, base + 2.0 * a, base + 1.5 * b - 0.5 * a)]


@SETTINGS
@given(
    unit_vectors(),
    unit_vectors(),
    _scalars(-3.0, 3.0),
    _scalars(-3.0, 3.0),
    arrays(np.float64, (B, 2), elements=_floats),
    arrays(np.float64, (B, 2), elements=_floats),
)
def test_meet_of_two_planes_is_their_line(n1, n2, d1, d2, off1, off2):
    u = np.cross(n1, n2)
    assume(np.all(np.linalg.norm(u, axis=-1) > 0.3))
    P1 = jaxcga.plane_through(*_plane_points(n1, d1, off1))
    P2 = jaxcga.plane_through(*_plane_points(n2, d2, off2))
    assert {bin(b).count("1") for b in P1.blades} == {4}
    L = jaxcga.meet(P1, P2)
    # the intersection line, computed analytically: direction n1 x n2 through p0
    uu = np.sum(u * u, axis=-1, keepdims=True)
    p0 = (d1[:, None] * np.cross(n2, u) + d2[:, None] * np.cross(u, n1)) / uu
    np.testing.assert_allclose(np.sum(n1 * p0, axis=-1), d1, atol=1e-9)
    np.testing.assert_allclose(np.sum(n2 * p0, axis=-1), d2, atol=1e-9)
    expected = jaxcga.line(jaxcga.up(jnp.asarray(p0)), jaxcga.up(jnp.asarray(p0 + u)))
    got, want = np.asarray(L.full()), np.asarray(expected.full())
    assert np.all(np.linalg.norm(got, axis=-1) > 1e-6)
    got = got / np.linalg.norm(got, axis=-1, keepdims=True)
    want = want / np.linalg.norm(want, axis=-1, keepdims=True)
    got = got * np.sign(np.sum(got * want, axis=-1, keepdims=True))  # sign-insensitive
    np.testing.assert_allclose(got, want, atol=1e-9)
    # and a point of the line lies on both planes: X ^ L = 0
    X = jaxcga.up(jnp.asarray(p0 + 0.7 * u))
    np.testing.assert_allclose(np.asarray((X ^ L).full()), 0.0, atol=1e-9 * np.max(np.abs(L.values)))


# ---------------------------------------------------------------- jit / vmap agree with eager
def _batch(kind, n, seed):
    rng = np.random.default_rng(seed)
    return Multivector(rng.normal(size=(n, len(jaxcga.KINDS[kind]))), kind)


PRODUCTS = {
    "geometric": jaxcga.geometric,
    "outer": jaxcga.outer,
    "left_contraction": jaxcga.left_contraction,
    "meet": jaxcga.meet,
}


@pytest.mark.parametrize("op", list(PRODUCTS))
def test_jit_and_vmap_match_eager_for_products(op):
    f = PRODUCTS[op]
    a, b = _batch("rotor", B, 0), _batch("vector", B, 1)
    eager = f(a, b)
    jitted = jax.jit(f)(a, b)
    vmapped = jax.vmap(f)(a, b)
    assert jitted.blades == eager.blades == vmapped.blades
    np.testing.assert_allclose(np.asarray(jitted.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(vmapped.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    # eager on a batch is the per-element result
    one = f(Multivector(a.values[1], a.blades), Multivector(b.values[1], b.blades))
    np.testing.assert_allclose(np.asarray(eager.values[1]), np.asarray(one.values), atol=1e-12, rtol=1e-12)


def test_jit_and_vmap_match_eager_for_scalar_product_and_sandwich():
    a, b = _batch("full", B, 2), _batch("full", B, 3)
    eager = jaxcga.scalar_product(a, b)
    np.testing.assert_allclose(np.asarray(jax.jit(jaxcga.scalar_product)(a, b)), np.asarray(eager), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(jax.vmap(jaxcga.scalar_product)(a, b)), np.asarray(eager), rtol=1e-12)

    rng = np.random.default_rng(4)
    M = jaxcga.motor(jaxcga.rotor(rng.normal(size=(B, 3)), rng.normal(size=B)), rng.normal(size=(B, 3)))
    X = jaxcga.up(rng.normal(size=(B, 3)))
    eager = M >> X
    jitted = jax.jit(jaxcga.sandwich)(M, X)
    vmapped = jax.vmap(jaxcga.sandwich)(M, X)
    np.testing.assert_allclose(np.asarray(jitted.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(vmapped.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    # one versor for all elements (vmap over x only)
    M0 = Multivector(M.values[0], M.blades)
    vm = jax.vmap(lambda x: M0 >> x)(X)
    np.testing.assert_allclose(np.asarray(vm.values), np.asarray((M0 >> X).values), atol=1e-12, rtol=1e-12)


def test_jit_and_vmap_match_eager_for_inverse():
    # "rotor" (a closed 4-blade subalgebra) rather than "full": the jit compile time of the
    # 32 x 32 system is large
    m = _batch("rotor", B, 6)
    eager = jaxcga.inverse(m)
    jitted = jax.jit(jaxcga.inverse)(m)
    vmapped = jax.vmap(jaxcga.inverse)(m)
    np.testing.assert_allclose(np.asarray(jitted.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    np.testing.assert_allclose(np.asarray(vmapped.values), np.asarray(eager.values), atol=1e-12, rtol=1e-12)
    one = Multivector(m.values[1], m.blades)
    np.testing.assert_allclose(np.asarray(eager.values[1]), np.asarray(jaxcga.inverse(one).values), atol=1e-12)
    # versor inverse too
    M = jaxcga.normalize(_batch("motor", B, 7))
    np.testing.assert_allclose(
        np.asarray(jax.vmap(jaxcga.versor_inverse)(M).values), np.asarray(jaxcga.versor_inverse(M).values), rtol=1e-12
    )
