"""Closed-form exp / log of motors and similitudes.

References: scipy.linalg.expm of the 32 x 32 left-multiplication matrix of the generator (the
exponential of B is the first column of expm(L_B), since exp(B) = exp(B) * 1), scipy rotations, and
central finite differences for the derivatives."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

import jaxcga as cga
from jaxcga import Multivector

SETTINGS = settings(max_examples=25, deadline=None, derandomize=True)
seeds = st.integers(0, 2**32 - 1)
MOTOR_GEN = cga.MOTOR_GENERATOR
SIM_GEN = cga.SIMILITUDE_GENERATOR
_BASIS = Multivector(np.eye(32), cga.ALL_BLADES)  # batch of the 32 basis blades


def _a(x):
    return np.asarray(x, dtype=np.float64)


def _unit(v):
    v = _a(v)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@jax.jit
def _left_matrix(full_values):
    """L[:, j] = (B e_j).full(): the left multiplication by B, with B embedded in ALL_BLADES."""
    return (Multivector(full_values, cga.ALL_BLADES) * _BASIS).full().T


def expm_reference(b: Multivector) -> np.ndarray:
    """exp(B) as a full 32-vector: expm(L_B) applied to the scalar 1 (the first blade)."""
    L = _a(_left_matrix(b.full()))
    assert cga.ALL_BLADES[0] == 0  # column 0 is the scalar blade
    return expm(L)[:, 0]


def _rotation_generator(axis, angle):
    """(e12, e13, e23) of -(angle / 2) u I3 with u I3 = u1 e23 - u2 e13 + u3 e12 (eq. 8)."""
    u = _unit(axis)
    return -0.5 * angle * np.array([u[2], -u[1], u[0]])


def _motor(axis, angle, t):
    return cga.motor(cga.rotor(np.asarray(axis, float), angle), np.asarray(t, float))


# Jitted once per blade set and shape (unbatched inputs), then reused by every test: compiling the
# generated code costs about a second per function, a call microseconds.
_exp_jit = jax.jit(cga.exp)
_log_jit = jax.jit(cga.log)


def _exp_log(m):
    return _exp_jit(_log_jit(m))


def _log_exp(b):
    return _log_jit(_exp_jit(b))


# ---------------------------------------------------------------- exp against expm
@pytest.mark.parametrize("scale", [1e-6, 1e-2, 0.3, 1.0, 3.0])
def test_exp_motor_matches_expm(scale):
    rng = np.random.default_rng(int(scale * 1e6) % 2**32)
    for v in rng.normal(size=(6, 6)) * scale:
        b = Multivector(v, MOTOR_GEN)
        ref = expm_reference(b)
        got = _a(_exp_jit(b).full())
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


@pytest.mark.parametrize("scale", [1e-6, 1e-2, 0.3, 1.0, 3.0, 8.0])
def test_exp_similitude_matches_expm(scale):
    rng = np.random.default_rng(int(scale * 1e6) % 2**32 + 1)
    for v in rng.normal(size=(6, 7)) * scale:
        b = Multivector(v, SIM_GEN)
        ref = expm_reference(b)
        got = _a(_exp_jit(b).full())
        np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


_BOUNDARY_GENERATORS = {
    # Squared half-angle at the series threshold 1e-2 of the motor closed forms.
    "motor_series_edge_below": np.r_[_rotation_generator([1, 2, 3], 2 * np.sqrt(1e-2 - 1e-12)), 0.3, -0.2, 0.5],
    "motor_series_edge_above": np.r_[_rotation_generator([1, 2, 3], 2 * np.sqrt(1e-2 + 1e-12)), 0.3, -0.2, 0.5],
    "motor_half_turn": np.r_[_rotation_generator([0, 0, 1], np.pi), 1.0, 2.0, 3.0],
    "motor_near_full_turn": np.r_[_rotation_generator([1, -1, 0.5], 2 * np.pi - 1e-6), 1.0, 2.0, 3.0],
    "pure_translation": np.r_[0.0, 0.0, 0.0, 1e4, -2e3, 5.0],
}
_BOUNDARY_SIM_GENERATORS = {
    # |z|^2 = lam^2 + |w|^2 at the series / closed-form switch 1 of the translation coefficients
    # (lam = 2 B_eoinf, |w| = the rotation angle): 0.8^2 + 0.6^2 = 1.
    "z_below_1": np.r_[_rotation_generator([1, 0, 0], 0.6), 0.5, -1.0, 2.0, 0.5 * 0.8 * (1 - 1e-9)],
    "z_above_1": np.r_[_rotation_generator([1, 0, 0], 0.6), 0.5, -1.0, 2.0, 0.5 * 0.8 * (1 + 1e-9)],
    # |w|^2 at the 1e-2 series switch of (1 - cos |w|) / |w|^2 in the closed form.
    "w2_below_1e-2": np.r_[_rotation_generator([0, 1, 0], 0.1 * (1 - 1e-9)), 0.5, -1.0, 2.0, 0.5],
    "w2_above_1e-2": np.r_[_rotation_generator([0, 1, 0], 0.1 * (1 + 1e-9)), 0.5, -1.0, 2.0, 0.5],
    "tiny_lambda": np.r_[_rotation_generator([0, 1, 1], 2.0), 0.5, -1.0, 2.0, 1e-5],
    "pure_dilation": np.r_[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.3],
    "translation_and_dilation": np.r_[0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 0.7],
    # Large dilation with translation: exp(lam) = e^20. (Forming T R D as a product cancelled
    # cosh(lam/2) - sinh(lam/2) and lost ~1e-8 relative in the e_i einf components.)
    "large_dilation": np.r_[0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 10.0],
    "large_contraction": np.r_[0.1, 0.2, -0.3, 1.0, 2.0, 3.0, -10.0],
}


@pytest.mark.parametrize("name", sorted(_BOUNDARY_GENERATORS))
def test_exp_motor_matches_expm_at_branch_boundaries(name):
    b = Multivector(_BOUNDARY_GENERATORS[name], MOTOR_GEN)
    ref = expm_reference(b)
    got = _a(_exp_jit(b).full())
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


@pytest.mark.parametrize("name", sorted(_BOUNDARY_SIM_GENERATORS))
def test_exp_similitude_matches_expm_at_branch_boundaries(name):
    b = Multivector(_BOUNDARY_SIM_GENERATORS[name], SIM_GEN)
    ref = expm_reference(b)
    got = _a(_exp_jit(b).full())
    # Component-wise: small components of large similitudes must be right too.
    big = np.abs(ref).max()
    np.testing.assert_allclose(got, ref, rtol=1e-12, atol=1e-13 * max(1.0, big))


def test_exp_of_a_rotation_generator_matches_scipy():
    rng = np.random.default_rng(0)
    axis = _unit(rng.normal(size=3))
    angle = 2.1
    R = cga.exp(Multivector(_rotation_generator(axis, angle), ("e12", "e13", "e23")))
    x = rng.normal(size=(4, 3))
    np.testing.assert_allclose(_a(cga.apply_to_points(R, x)), Rotation.from_rotvec(angle * axis).apply(x), atol=1e-13)


@pytest.mark.slow
def test_exp_dispatch_and_log_dispatch():
    b = Multivector(np.r_[0.1, 0.2, 0.3, 1.0, 2.0, 3.0], MOTOR_GEN)
    assert _exp_jit(b).blades == cga.KINDS["motor"]
    bs = Multivector(np.r_[0.1, 0.2, 0.3, 1.0, 2.0, 3.0, 0.4], SIM_GEN)
    assert _exp_jit(bs).blades == cga.KINDS["similitude"]
    assert _log_exp(b).blades == MOTOR_GEN
    assert _log_exp(bs).blades == SIM_GEN
    # A motor generator (eo^einf part zero) through exp_similitude gives the same motor.
    gens = np.random.default_rng(9).normal(size=(ROWS, 6))
    sims = _f_exp_sim(jnp.asarray(np.concatenate([gens, np.zeros((ROWS, 1))], axis=1)))
    motors = _f_exp_motor(jnp.asarray(gens))
    np.testing.assert_allclose(
        _a(Multivector(sims, "similitude").full()), _a(Multivector(motors, "motor").full()), atol=1e-14
    )


def test_exp_log_reject_wrong_blades():
    with pytest.raises(ValueError):
        cga.exp_motor(Multivector(np.ones(2), ("e1", "e2")))
    with pytest.raises(ValueError):
        cga.exp_motor(Multivector(np.ones(1), ("eoinf",)))
    with pytest.raises(ValueError):
        cga.exp_similitude(Multivector(np.ones(1), ("e1o",)))
    with pytest.raises(ValueError):
        cga.log_motor(Multivector(np.ones(2), ("1", "eoinf")))
    with pytest.raises(ValueError):
        cga.log_similitude(Multivector(np.ones(2), ("1", "e1")))


# ---------------------------------------------------------------- exp(log(M)) = M
_AXIS = _unit(np.array([0.3, -0.5, 0.8]))
_T_SMALL = np.array([1.0, 2.0, -3.0])
_T_BIG = np.array([1e4, -2e4, 3e3])
_TRANSLATIONS = {"t0": np.zeros(3), "t_small": _T_SMALL, "t_1e4": _T_BIG}
_MOTOR_CASES = [
    pytest.param(angle, t, id=f"angle={angle:.12g}-{name}")
    for angle in [0.0, 1e-9, 1e-5, 0.1, 1.0, np.pi - 1e-9, np.pi, np.pi + 1e-9, 4.0, 2 * np.pi - 1e-3]
    for name, t in _TRANSLATIONS.items()
]


@pytest.mark.parametrize("angle,t", _MOTOR_CASES)
def test_exp_log_motor_round_trip(angle, t):
    M = _motor(_AXIS, angle, t)
    got = _a(_exp_log(M).values)
    # 1e-12 relative to the motor's magnitude (its translation part is |t| / 2).
    np.testing.assert_allclose(got, _a(M.values), rtol=0, atol=1e-12 * max(1.0, np.abs(_a(M.values)).max()))


@pytest.mark.parametrize("eps", [1e-6, 1e-9, 1e-12, 0.0])
@pytest.mark.parametrize("d", [0.0, 1.0, -1e4])
def test_exp_log_motor_round_trip_near_full_turn_screw(eps, d):
    """Rotation by 2 pi - eps with a translation d along the axis (a screw): well conditioned, so
    exact. (The closed form used to cancel two ~pi/sin terms and lost 1e-7 at eps = 1e-9; at 2 pi
    itself it returned a garbage translation.)"""
    M = _motor(_AXIS, 2 * np.pi - eps, d * _AXIS)
    got = _a(_exp_log(M).values)
    np.testing.assert_allclose(got, _a(M.values), rtol=0, atol=1e-12 * max(1.0, abs(d)))
    L = _a(_log_jit(M).values)
    # The screw's generator: rotation part of norm ~pi about the axis, translation part -d u / 2
    # along it. (Only the component along the axis is well conditioned: rounding of M off the axis
    # is amplified by ~pi / sin(eps / 2) in the log, harmlessly for exp.)
    np.testing.assert_allclose(np.linalg.norm(L[:3]), np.pi - eps / 2, rtol=1e-12)
    w = np.array([-L[2], L[1], -L[0]])
    np.testing.assert_allclose(w / np.linalg.norm(w), _AXIS, atol=1e-12)
    np.testing.assert_allclose(L[3:] @ _AXIS, -0.5 * d, atol=1e-12 * max(1.0, abs(d)))


@pytest.mark.parametrize("eps", [1e-6, 1e-9])
def test_exp_log_motor_near_full_turn_general_translation_is_backward_stable(eps):
    """With a translation off the axis, log(M) near a full turn is ill conditioned (its moment grows
    like |t| / eps), so exp(log(M)) can only be as exact as eps_machine * |log(M)|."""
    M = _motor(_AXIS, 2 * np.pi - eps, _T_SMALL)
    L = _a(_log_jit(M).values)
    assert np.abs(L).max() > 1e3  # the ill-conditioning is real
    got = _a(_exp_log(M).values)
    np.testing.assert_allclose(got, _a(M.values), rtol=0, atol=1e-14 * np.abs(L).max())


def test_log_of_minus_translator_is_a_full_turn_screw():
    """-T (rotor part exactly -1) is the 2 pi screw about the axis along t; it used to come back
    as a bare 2 pi rotation, dropping the translation."""
    t = np.array([1.0, 2.0, 3.0])
    M = -cga.translator(t).embed("motor")
    L = _a(_log_jit(M).values)
    np.testing.assert_allclose(np.linalg.norm(L[:3]), np.pi, rtol=1e-14)
    # The rotation plane is perpendicular to t: w = (-e23, e13, -e12) is parallel to t.
    w = np.array([-L[2], L[1], -L[0]])
    np.testing.assert_allclose(np.abs(w @ _unit(t)), np.pi, rtol=1e-14)
    np.testing.assert_allclose(_a(_exp_log(M).values), _a(M.values), atol=1e-14)
    # -1 itself: any plane, translation zero.
    minus_one = Multivector(np.r_[-1.0, np.zeros(7)], "motor")
    np.testing.assert_allclose(_a(_exp_log(minus_one).values), _a(minus_one.values), atol=1e-15)


def test_log_motor_of_unnormalized_motor():
    M = _exp_jit(Multivector(np.r_[0.3, -1.2, 0.4, 1.0, 2.0, -0.5], MOTOR_GEN))
    np.testing.assert_allclose(_a(_log_jit(M * 3.0).values), _a(_log_jit(M).values), atol=1e-14)
    np.testing.assert_allclose(_a(_exp_log(M * 0.2).values), _a(M.values), atol=1e-14)


_SIM_CASES = [
    pytest.param(d, angle, t, id=f"d={d:g}-angle={angle:.12g}-{name}")
    for d in (1.0, 1e-3, 1e3)
    for angle in (0.0, 1e-9, 1.0, np.pi - 1e-9, np.pi, 2 * np.pi - 1e-3)
    for name, t in _TRANSLATIONS.items()
]


@pytest.mark.parametrize("d,angle,t", _SIM_CASES)
def test_exp_log_similitude_round_trip(d, angle, t):
    S = cga.similitude(cga.rotor(_AXIS, angle), t, d)
    got = _a(_exp_log(S).values)
    ref = _a(S.values)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12 * max(1.0, np.abs(ref).max()))


@SETTINGS
@given(seeds, st.floats(-5.0, 5.0))
def test_log_exp_motor_and_similitude(seed, log_scale):
    rng = np.random.default_rng(seed)
    n = 8
    axes = _unit(rng.normal(size=(n, 3)))
    angles = rng.uniform(0.0, 2 * np.pi - 1e-3, size=n)
    rot = np.stack([_rotation_generator(a, th) for a, th in zip(axes, angles)])
    trans = rng.normal(size=(n, 3)) * np.exp(rng.uniform(-3, 3, size=(n, 1)))
    b = np.concatenate([rot, trans], axis=1)
    bs = np.concatenate([b, np.full((n, 1), 0.5 * log_scale)], axis=1)
    for k in range(n):
        got = _a(_log_exp(Multivector(b[k], MOTOR_GEN)).values)
        np.testing.assert_allclose(got, b[k], rtol=0, atol=1e-12 * (1 + np.abs(b[k]).max()))
        got_s = _a(_log_exp(Multivector(bs[k], SIM_GEN)).values)
        np.testing.assert_allclose(got_s, bs[k], rtol=0, atol=1e-12 * (1 + np.abs(bs[k]).max()))


# ---------------------------------------------------------------- derivatives
# Derivatives are checked eagerly, on batches of ROWS rows holding every base point (each with
# random directions): compiling derivatives of the generated code under jit costs seconds per
# function, while eager kernels of one batch shape are shared by all functions.
ROWS = 30


def check_derivatives(f, points, rng, h=1e-6, rtol=1e-6):
    """f maps (ROWS, n) to (ROWS, m) row by row. Row r holds base point r % len(points), a random
    direction d and a random cotangent c. Reverse mode (what jax.grad uses, and where NaN from
    unselected branches of a where would show) must be finite and match central differences:
    <J^T c, d> = <c, (f(x + h d) - f(x - h d)) / 2h>. Returns (x, c, J^T c)."""
    x = np.resize(np.asarray(points, np.float64), (ROWS, np.shape(points)[-1]))
    d = rng.normal(size=x.shape)
    c = rng.normal(size=jax.eval_shape(f, jnp.asarray(x)).shape)  # cotangent
    y, vjp_fn = jax.vjp(f, jnp.asarray(x))
    assert np.all(np.isfinite(_a(y)))
    (vj,) = vjp_fn(jnp.asarray(c))
    vj = _a(vj)
    assert np.all(np.isfinite(vj))
    fd = (_a(f(jnp.asarray(x + h * d))) - _a(f(jnp.asarray(x - h * d)))) / (2 * h)
    lhs, rhs = np.sum(vj * d, axis=-1), np.sum(c * fd, axis=-1)
    scale = np.abs(c).sum(axis=-1) * np.maximum(1.0, np.abs(fd).max(axis=-1))
    assert np.all(np.abs(lhs - rhs) <= rtol * scale), np.abs(lhs - rhs) / scale
    return x, c, vj


def _f_exp_motor(v):
    return cga.exp_motor(Multivector(v, MOTOR_GEN)).values


def _f_exp_sim(v):
    return cga.exp_similitude(Multivector(v, SIM_GEN)).values


def _f_log_motor(v):
    return cga.log_motor(Multivector(v, "motor")).values


def _f_log_sim(v):
    return cga.log_similitude(Multivector(v, "similitude")).values


#: Base points of the derivative checks, as motor generators: AT the identity (generator zero, row
#: 0 of every check), at a pure translation, near the identity, generic, and beyond a half turn (the
#: log's a < 0 branch).
_GEN_POINTS = np.array(
    [
        np.zeros(6),
        np.r_[0.0, 0.0, 0.0, 1.0, -2.0, 0.5],
        np.r_[1e-5, -2e-5, 1e-5, 1.0, -2.0, 0.5],
        np.r_[0.3, -0.4, 0.8, 1.0, -2.0, 0.5],
        np.r_[_rotation_generator([1, 2, -1], 4.5), 1.0, -2.0, 0.5],
    ]
)
_SIM_POINTS = np.concatenate(
    [
        np.concatenate([_GEN_POINTS, np.zeros((5, 1))], axis=1),
        np.concatenate([_GEN_POINTS, np.full((5, 1), 0.4)], axis=1),
    ]
)
_AT_IDENTITY_GEN = np.arange(ROWS) % len(_GEN_POINTS) == 0
_AT_IDENTITY_SIM = np.arange(ROWS) % len(_SIM_POINTS) == 0


def _motors():
    return _a(_f_exp_motor(jnp.asarray(np.resize(_GEN_POINTS, (ROWS, 6)))))


def _sims():
    return _a(_f_exp_sim(jnp.asarray(np.resize(_SIM_POINTS, (ROWS, 7)))))


def test_exp_motor_derivatives():
    x, c, vj = check_derivatives(_f_exp_motor, _GEN_POINTS, np.random.default_rng(0))
    # AT the identity (B = 0): exp(B) = 1 + B + O(B^2), the derivative is the embedding of the
    # generator blades, so J^T c picks c's bivector part.
    at = _AT_IDENTITY_GEN
    np.testing.assert_allclose(vj[at], c[at][:, 1:7], atol=1e-14)


def _embed_rows(values, blades, target):
    out = np.zeros(values.shape[:-1] + (len(target),))
    out[..., [target.index(b) for b in blades]] = values
    return out


def test_exp_similitude_derivatives():
    x, c, vj = check_derivatives(_f_exp_sim, _SIM_POINTS, np.random.default_rng(1))
    blades = cga.KINDS["similitude"]
    at = _AT_IDENTITY_SIM
    np.testing.assert_allclose(vj[at], c[at][:, [blades.index(b) for b in SIM_GEN]], atol=1e-14)


@pytest.mark.slow
def test_log_motor_derivatives():
    motors = _motors()[: len(_GEN_POINTS)]
    np.testing.assert_array_equal(motors[0], np.r_[1.0, np.zeros(7)])  # exactly the identity
    x, c, vj = check_derivatives(_f_log_motor, motors, np.random.default_rng(2))
    # AT M = 1 the log's derivative is the projection on the bivector blades (the scalar and the
    # e123inf directions only rescale / are normalized away).
    at = _AT_IDENTITY_GEN
    np.testing.assert_allclose(vj[at], _embed_rows(c[at], MOTOR_GEN, cga.KINDS["motor"]), atol=1e-14)


@pytest.mark.slow
def test_log_similitude_derivatives():
    sims = _sims()[: len(_SIM_POINTS)]
    assert sims[0, 0] == 1.0 and not np.any(sims[0, 1:])  # exactly the identity
    x, c, vj = check_derivatives(_f_log_sim, sims, np.random.default_rng(3))
    # At S = 1: the projection on the generator blades.
    at = _AT_IDENTITY_SIM
    np.testing.assert_allclose(vj[at], _embed_rows(c[at], SIM_GEN, cga.KINDS["similitude"]), atol=1e-14)


_POINT_X = np.array([0.3, -1.2, 0.7])


def test_sandwich_derivatives():
    X = cga.up(_POINT_X)
    check_derivatives(lambda v: cga.sandwich(Multivector(v, "motor"), X).values, _motors(), np.random.default_rng(4))


def test_apply_to_points_derivatives():
    rng = np.random.default_rng(5)
    x = jnp.asarray(_POINT_X)
    check_derivatives(lambda v: cga.apply_to_points(Multivector(v, "motor"), x), _motors(), rng)
    # With respect to the points, under the identity motor (even rows) and a pure translation (odd).
    M = Multivector(np.resize(_motors()[:2], (ROWS, 8)), "motor")
    check_derivatives(lambda p: cga.apply_to_points(M, p), rng.normal(size=(ROWS, 3)), rng)


def test_derivative_through_exp_and_apply_matches_closed_form():
    # d/dphi of exp(generator of a rotation by phi about e3) applied to e1, at phi = 0, is e2; at
    # phi = pi / 2 it is -e1. Reverse mode: J^T c = <c, dx/dphi>.
    def f(v):
        phi = v[..., 0]
        b = Multivector(jnp.stack([-0.5 * phi] + [0.0 * phi] * 5, -1), MOTOR_GEN)
        return cga.apply_to_points(cga.exp(b), jnp.asarray([1.0, 0.0, 0.0]))

    even = np.arange(ROWS) % 2 == 0
    phi = np.where(even, 0.0, np.pi / 2)[:, None]
    dx = np.where(even[:, None], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0])
    c = np.random.default_rng(8).normal(size=(ROWS, 3))
    _, vjp_fn = jax.vjp(f, jnp.asarray(phi))
    (g,) = vjp_fn(jnp.asarray(c))
    np.testing.assert_allclose(_a(g)[:, 0], np.sum(c * dx, axis=-1), atol=1e-14)


# ---------------------------------------------------------------- jit and vmap
@pytest.mark.slow
def test_jit_and_vmap_match_eager():
    rng = np.random.default_rng(7)
    b = rng.normal(size=(ROWS, 7))
    sims = _a(_f_exp_sim(jnp.asarray(b)))  # eager, batched
    sim_logs = _a(_f_log_sim(jnp.asarray(sims)))
    motors = _a(_f_exp_motor(jnp.asarray(b[:, :6])))
    motor_logs = _a(_f_log_motor(jnp.asarray(motors)))
    # jit (the single-versor compiled functions of the tests above) equals eager.
    for k in range(0, ROWS, 6):
        np.testing.assert_allclose(_a(_exp_jit(Multivector(b[k], SIM_GEN)).values), sims[k], rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(
            _a(_log_jit(Multivector(sims[k], "similitude")).values), sim_logs[k], rtol=1e-13, atol=1e-13
        )
        np.testing.assert_allclose(
            _a(_exp_jit(Multivector(b[k, :6], MOTOR_GEN)).values), motors[k], rtol=1e-14, atol=1e-14
        )
        np.testing.assert_allclose(
            _a(_log_jit(Multivector(motors[k], "motor")).values), motor_logs[k], rtol=1e-13, atol=1e-13
        )
    # vmap of the per-versor functions equals the natively batched ones. (Motors only: vmapping the
    # similitude code compiles a few hundred new kernels, seconds, for the same batching rules.)
    np.testing.assert_allclose(_a(jax.vmap(_f_exp_motor)(jnp.asarray(b[:, :6]))), motors, rtol=1e-14, atol=1e-14)
    np.testing.assert_allclose(_a(jax.vmap(_f_log_motor)(jnp.asarray(motors))), motor_logs, rtol=1e-13, atol=1e-13)
    # (apply_to_points under jit and vmap: test_versors.py.)
