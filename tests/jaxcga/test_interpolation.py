"""Blending of versors (linear, logarithmic, weighted) against scipy's Slerp / rotation vectors and
closed forms; derivatives against central finite differences."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation, Slerp

import jaxcga as cga
from jaxcga import Multivector

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
seeds = st.integers(0, 2**32 - 1)
MOTOR_GEN = cga.MOTOR_GENERATOR
SIM_GEN = cga.SIMILITUDE_GENERATOR
ROWS = 30  # one batch shape for all eager derivative checks (shared kernels)
_IDENTITY = np.r_[1.0, np.zeros(7)]


def _a(x):
    return np.asarray(x, dtype=np.float64)


def _unit(v):
    v = _a(v)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _random_motor_values(rng, n=None):
    shape = () if n is None else (n,)
    axis = _unit(rng.normal(size=shape + (3,)))
    angle = rng.uniform(-3.0, 3.0, size=shape)
    t = rng.normal(size=shape + (3,)) * 2
    return _a(cga.motor(cga.rotor(axis, angle), t).values)


def _random_motor(rng):
    return Multivector(_random_motor_values(rng), "motor")


def _random_similitude(rng):
    axis = _unit(rng.normal(size=3))
    return cga.similitude(cga.rotor(axis, rng.uniform(-3, 3)), rng.normal(size=3), float(np.exp(rng.uniform(-1, 1))))


def _same_up_to_sign(u, v, atol):
    u, v = _a(u), _a(v)
    return min(np.abs(u - v).max(), np.abs(u + v).max()) <= atol


_blend_log_jit = jax.jit(cga.blend_log)
_blend_linear_jit = jax.jit(cga.blend_linear, static_argnames="renormalize")
_apply_jit = jax.jit(cga.apply_to_points)


# ---------------------------------------------------------------- linear
@SETTINGS
@given(seeds, st.floats(0.0, 1.0))
def test_blend_linear_endpoints_and_unit_result(seed, alpha):
    rng = np.random.default_rng(seed)
    m1, m2 = _random_motor(rng), _random_motor(rng)
    np.testing.assert_allclose(_a(_blend_linear_jit(m1, m2, 0.0).values), _a(m1.values), atol=1e-14)
    np.testing.assert_allclose(_a(_blend_linear_jit(m1, m2, 1.0).values), _a(m2.values), atol=1e-14)
    b = _blend_linear_jit(m1, m2, alpha)
    bb = b * ~b  # M ~M = 1: scalar 1, every other part (the e123inf part included) zero
    np.testing.assert_allclose(_a(bb["1"]), 1.0, rtol=1e-13)
    for name in bb.names:
        if name != "1":
            assert abs(float(bb[name])) <= 1e-13, name
    # Without renormalization it is the plain affine combination.
    raw = _blend_linear_jit(m1, m2, alpha, renormalize=False)
    np.testing.assert_allclose(_a(raw.full()), (1 - alpha) * _a(m1.full()) + alpha * _a(m2.full()), atol=1e-15)
    # Renormalizing only rescales (and removes the e123inf part of raw ~raw): same rigid motion.
    x = rng.normal(size=(6, 3))
    np.testing.assert_allclose(_a(_apply_jit(b, x)), _a(_apply_jit(raw, x)), atol=1e-12)


def test_blend_linear_of_translations_interpolates_the_translation():
    t1, t2 = np.array([1.0, -2.0, 0.5]), np.array([-3.0, 4.0, 2.0])
    alphas = np.linspace(0, 1, ROWS)
    b = cga.blend_linear(cga.translator(t1), cga.translator(t2), alphas)
    assert b.batch_shape == (ROWS,)
    got = _a(cga.apply_to_points(b, np.zeros(3)))
    np.testing.assert_allclose(got, (1 - alphas)[:, None] * t1 + alphas[:, None] * t2, atol=1e-14)


# ---------------------------------------------------------------- logarithmic
@SETTINGS
@given(seeds, st.floats(0.0, 1.0))
def test_blend_log_endpoints_and_symmetry(seed, alpha):
    rng = np.random.default_rng(seed)
    m1, m2 = _random_motor(rng), _random_motor(rng)
    assert _same_up_to_sign(_blend_log_jit(m1, m2, 0.0).values, m1.values, 1e-12)
    assert _same_up_to_sign(_blend_log_jit(m1, m2, 1.0).values, m2.values, 1e-12)
    a = _blend_log_jit(m1, m2, alpha)
    b = _blend_log_jit(m2, m1, 1.0 - alpha)
    assert _same_up_to_sign(a.values, b.values, 1e-11)
    # The result is a unit motor.
    np.testing.assert_allclose(_a((a * ~a)["1"]), 1.0, rtol=1e-12)
    np.testing.assert_allclose(_a((a * ~a)["e123inf"]), 0.0, atol=1e-12)


def test_blend_log_same_axis_rotations_match_slerp():
    axis = _unit(np.array([1.0, 2.0, -0.5]))
    th1, th2 = 0.3, 2.5
    R1 = cga.rotor(axis, th1).embed("motor")
    R2 = cga.rotor(axis, th2).embed("motor")
    alphas = np.linspace(0.0, 1.0, ROWS)
    b = cga.blend_log(R1, R2, alphas)  # batched alphas
    assert b.batch_shape == (ROWS,)
    slerp = Slerp([0.0, 1.0], Rotation.from_rotvec(np.stack([th1 * axis, th2 * axis])))(alphas)
    x = np.random.default_rng(0).normal(size=(ROWS, 3))
    np.testing.assert_allclose(_a(cga.apply_to_points(b, x)), slerp.apply(x), atol=1e-13)
    # It is the rotation by the interpolated angle.
    ref = cga.rotor(np.tile(axis, (ROWS, 1)), (1 - alphas) * th1 + alphas * th2).embed("motor")
    np.testing.assert_allclose(_a(b.values), _a(ref.values), atol=1e-13)


@SETTINGS
@given(seeds)
def test_blend_log_general_rotations_match_slerp(seed):
    rng = np.random.default_rng(seed)
    r1, r2 = Rotation.random(2, rng=rng)
    q1, q2 = r1.as_quat(scalar_first=True), r2.as_quat(scalar_first=True)
    if q1 @ q2 < 0:  # Slerp takes the short way; so does blend_log when the rotors are in one hemisphere
        q2 = -q2
    R1, R2 = cga.quaternion_to_rotor(q1).embed("motor"), cga.quaternion_to_rotor(q2).embed("motor")
    alphas = np.array([0.0, 0.3, 0.5, 0.9, 1.0])
    slerp = Slerp([0.0, 1.0], Rotation.from_quat(np.stack([q1, q2]), scalar_first=True))(alphas)
    x = rng.normal(size=(5, 3))
    np.testing.assert_allclose(_a(_apply_jit(_blend_log_jit(R1, R2, alphas), x)), slerp.apply(x), atol=1e-12)


def test_blend_log_of_translations_and_screws():
    t1, t2 = np.array([1.0, -2.0, 0.5]), np.array([-3.0, 4.0, 2.0])
    alphas = np.linspace(0.0, 1.0, ROWS)
    b = cga.blend_log(cga.translator(t1).embed("motor"), cga.translator(t2).embed("motor"), alphas)
    np.testing.assert_allclose(
        _a(cga.apply_to_points(b, np.zeros(3))), (1 - alphas)[:, None] * t1 + alphas[:, None] * t2, atol=1e-14
    )
    # A screw about e3: rotation by alpha * phi together with translation alpha * h along e3.
    phi, h = 2.0, 3.0
    screw = cga.motor(cga.rotor(np.array([0.0, 0.0, 1.0]), phi), np.array([0.0, 0.0, h]))
    one = Multivector(np.r_[1.0, np.zeros(7)], "motor")
    s = cga.blend_log(one, screw, alphas)
    x = np.array([1.0, 0.0, 0.0])
    expected = np.stack([np.cos(alphas * phi), np.sin(alphas * phi), alphas * h], axis=-1)
    np.testing.assert_allclose(_a(cga.apply_to_points(s, x)), expected, atol=1e-14)


def test_blend_log_similitudes():
    rng = np.random.default_rng(3)
    s1, s2 = _random_similitude(rng), _random_similitude(rng)
    alphas = np.linspace(0.0, 1.0, ROWS)
    forward = _a(cga.blend_log(s1, s2, alphas).values)
    backward = _a(cga.blend_log(s2, s1, 1.0 - alphas).values)
    assert _same_up_to_sign(forward[0], s1.values, 1e-12)
    assert _same_up_to_sign(forward[-1], s2.values, 1e-12)
    for k in range(ROWS):
        assert _same_up_to_sign(forward[k], backward[k], 1e-12)
    # Pure dilations interpolate the scale geometrically.
    d1, d2 = 0.5, 8.0
    b = cga.blend_log(cga.dilator(d1), cga.dilator(d2), alphas)
    assert b.blades == cga.KINDS["similitude"]
    x = np.array([1.0, -2.0, 3.0])
    scale = d1 ** (1 - alphas) * d2**alphas
    np.testing.assert_allclose(_a(cga.apply_to_points(b, x)), scale[:, None] * x, rtol=1e-13)


def test_blend_rejects_non_multivectors_and_bad_batches():
    m = Multivector(np.r_[1.0, np.zeros(7)], "motor")
    with pytest.raises(ValueError):
        cga.blend_log(m, np.zeros(8), 0.5)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError):
        cga.blend_linear(np.zeros(8), m, 0.5)  # pyright: ignore[reportArgumentType]
    mb3 = Multivector(np.tile(_a(m.values), (3, 1)), "motor")
    mb4 = Multivector(np.tile(_a(m.values), (4, 1)), "motor")
    with pytest.raises(ValueError):
        cga.blend_linear(mb3, mb4, 0.5)


# ---------------------------------------------------------------- weighted
# Weighted blends use ROWS keys (a key batch of the shape of the derivative checks: shared kernels).
def test_blend_weighted_one_hot_returns_the_key():
    rng = np.random.default_rng(4)
    keys = Multivector(_random_motor_values(rng, ROWS), "motor")
    for k in (0, 7, ROWS - 1):
        w = np.eye(ROWS)[k]
        assert _same_up_to_sign(cga.blend_weighted(keys, w).values, _a(keys.values)[k], 1e-12)


def test_blend_weighted_commuting_motors_sum_the_generators():
    # Rotations about one axis (with translations along it) commute: the weighted blend is the screw
    # by the weighted sums of the angles and the translations.
    rng = np.random.default_rng(5)
    axis = _unit(np.array([0.2, -1.0, 0.4]))
    angles = rng.uniform(-3.0, 3.0, size=ROWS)
    shifts = rng.normal(size=ROWS)
    keys = cga.motor(cga.rotor(np.tile(axis, (ROWS, 1)), angles), shifts[:, None] * axis)
    w = rng.dirichlet(np.ones(ROWS))
    out = cga.blend_weighted(keys, w)
    x = rng.normal(size=(4, 3))
    expected = Rotation.from_rotvec((w @ angles) * axis).apply(x) + (w @ shifts) * axis
    np.testing.assert_allclose(_a(cga.apply_to_points(out, x)), expected, atol=1e-13)
    # The same as exp of the weighted sum of the logs (deformation paper eq. 1).
    gens = _a(cga.log(keys).values)
    ref = cga.exp(Multivector(w @ gens, MOTOR_GEN))
    np.testing.assert_allclose(_a(out.values), _a(ref.values), atol=1e-14)


def test_blend_weighted_rejects_bad_input():
    keys = Multivector(np.tile(_IDENTITY, (3, 1)), "motor")
    with pytest.raises(ValueError):
        cga.blend_weighted(keys, np.ones(4))
    with pytest.raises(ValueError):
        cga.blend_weighted(Multivector(np.r_[1.0, np.zeros(7)], "motor"), np.ones(1))


# ---------------------------------------------------------------- derivatives
def check_derivatives(f, points, rng, h=1e-6, rtol=1e-6):
    """f maps (ROWS, n) to (ROWS, ...) row by row; row r holds base point r % len(points), a random
    direction d and a random cotangent c. Reverse mode (as jax.grad) must be finite and match central
    differences: <J^T c, d> = <c, (f(x + h d) - f(x - h d)) / 2h>. Returns (x, c, J^T c)."""
    x = np.resize(np.asarray(points, np.float64), (ROWS, np.shape(points)[-1]))
    d = rng.normal(size=x.shape)
    y, vjp_fn = jax.vjp(f, jnp.asarray(x))
    assert np.all(np.isfinite(_a(y)))
    c = rng.normal(size=np.shape(y))
    (vj,) = vjp_fn(jnp.asarray(c))
    vj = _a(vj)
    assert np.all(np.isfinite(vj))
    fd = (_a(f(jnp.asarray(x + h * d))) - _a(f(jnp.asarray(x - h * d)))).reshape(ROWS, -1) / (2 * h)
    c = c.reshape(ROWS, -1)
    lhs, rhs = np.sum(vj * d, axis=-1), np.sum(c * fd, axis=-1)
    scale = np.abs(c).sum(axis=-1) * np.maximum(1.0, np.abs(fd).max(axis=-1))
    assert np.all(np.abs(lhs - rhs) <= rtol * scale), np.abs(lhs - rhs) / scale
    return x, c, vj


_TRANSLATION = _a(cga.translator(np.array([1.0, -2.0, 0.5])).embed("motor").values)
_GENERIC = _a(cga.motor(cga.rotor(np.array([1.0, 2.0, 3.0]), 1.2), np.array([0.5, 0.0, -1.0])).values)
_GENERIC2 = _a(cga.motor(cga.rotor(np.array([-1.0, 0.5, 0.0]), 2.5), np.array([0.0, 2.0, 1.0])).values)
#: (m1, m2, alpha) rows: AT the identity (m1 = m2 = 1), at pure translations, mixed, generic, and
#: (last) the start of the blend from 1 to a generic motor.
_PAIRS = np.array(
    [
        np.r_[_IDENTITY, _IDENTITY, 0.3],
        np.r_[_TRANSLATION, _TRANSLATION, 0.6],
        np.r_[_IDENTITY, _TRANSLATION, 0.5],
        np.r_[_TRANSLATION, _GENERIC, 0.2],
        np.r_[_GENERIC, _GENERIC2, 0.7],
        np.r_[_IDENTITY, _GENERIC, 0.0],
    ]
)


def _split(v):
    return Multivector(v[..., :8], "motor"), Multivector(v[..., 8:16], "motor"), v[..., 16]


def test_blend_log_derivatives():
    x, c, vj = check_derivatives(lambda v: cga.blend_log(*_split(v)).values, _PAIRS, np.random.default_rng(0))
    # d/dalpha blend_log(1, M, alpha) at alpha = 0 is log(M) (exp(alpha B) = 1 + alpha B + ...), so
    # the alpha entry of J^T c is <c, log(M)> on the bivector blades.
    rows = np.arange(ROWS) % len(_PAIRS) == len(_PAIRS) - 1
    gen = _a(cga.log(Multivector(_GENERIC, "motor")).values)
    np.testing.assert_allclose(vj[rows, 16], c[rows][:, 1:7] @ gen, atol=1e-12)


def test_blend_linear_derivatives():
    check_derivatives(lambda v: cga.blend_linear(*_split(v)).values, _PAIRS, np.random.default_rng(1))


@pytest.mark.slow
def test_blend_weighted_derivatives():
    # One blend of ROWS keys; its input (the keys and their weights) is one (ROWS, 9) array. Base
    # points: AT the identity (every key 1), pure translations, and generic keys.
    rng = np.random.default_rng(2)
    bases = [
        np.tile(_IDENTITY, (ROWS, 1)),
        _a(cga.translator(rng.normal(size=(ROWS, 3))).embed("motor").values),
        np.concatenate([_random_motor_values(rng, ROWS - 10), np.tile(_IDENTITY, (10, 1))]),
    ]

    def f(v):
        return cga.blend_weighted(Multivector(v[:, :8], "motor"), v[:, 8]).values

    h = 1e-6
    for keys in bases:
        x = np.concatenate([keys, rng.dirichlet(np.ones(ROWS))[:, None]], axis=1)
        y, vjp_fn = jax.vjp(f, jnp.asarray(x))
        assert np.all(np.isfinite(_a(y)))
        d = rng.normal(size=x.shape)
        c = rng.normal(size=8)
        (vj,) = vjp_fn(jnp.asarray(c))
        assert np.all(np.isfinite(_a(vj)))
        fd = (_a(f(jnp.asarray(x + h * d))) - _a(f(jnp.asarray(x - h * d)))) / (2 * h)
        scale = np.abs(c).sum() * max(1.0, np.abs(fd).max())
        assert abs(np.sum(_a(vj) * d) - c @ fd) <= 1e-6 * scale


def test_blend_linear_of_similitudes_is_a_similitude():
    """Renormalized linear blending of similitudes projects back onto similitudes: W ~W = 1 with no
    grade-2/4 part, so an equilateral triangle stays equilateral (the raw sum distorts it)."""
    s1 = cga.similitude(cga.rotor(jnp.array([0.0, 0, 1]), -0.3), jnp.zeros(3), 1.5)
    s2 = cga.similitude(cga.rotor(jnp.array([0.3, 0.2, 1.0]), 2.8), jnp.array([1.0, 0.5, 4.0]), 0.5)
    tri = jnp.array([[1.0, 0, 0], [-0.5, 3**0.5 / 2, 0], [-0.5, -(3**0.5) / 2, 0]])
    for alpha in (0.25, 0.5, 0.8):
        w = cga.blend_linear(s1, s2, alpha)
        ww = w * ~w
        np.testing.assert_allclose(float(ww["1"]), 1.0, atol=1e-12)
        assert float(jnp.max(jnp.abs(ww.grade(2, 4).values))) < 1e-12
        p = cga.apply_to_points(w, tri)
        sides = np.linalg.norm(np.asarray(p - jnp.roll(p, 1, axis=0)), axis=-1)
        np.testing.assert_allclose(sides, sides[0], rtol=1e-12)
    raw = cga.blend_linear(s1, s2, 0.5, renormalize=False)
    p = cga.apply_to_points(raw, tri)
    sides = np.linalg.norm(np.asarray(p - jnp.roll(p, 1, axis=0)), axis=-1)
    assert np.ptp(sides) > 1e-3
