"""Versors of jaxcga (rotors, translators, dilators, motors, similitudes), their action on points and
their conversions, against scipy.spatial.transform.Rotation and numpy closed forms."""

from __future__ import annotations

import jax
import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import jaxcga as cga
from tests.jaxcga._helpers import SETTINGS, _a, _unit, seeds


def _qmul(p, q):
    """Hamilton product of (w, x, y, z) quaternions, numpy."""
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return np.array(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def _random_rotation(rng):
    axis = _unit(rng.normal(size=3))
    angle = rng.uniform(-2 * np.pi, 2 * np.pi)
    return axis, angle


@jax.jit
def _sandwich_down_jit(v, x):
    return cga.down(cga.sandwich(v, cga.up(x)))


def _sandwich_down(v, x):
    """The reference action: down(V up(x) V^-1) through the generic sandwich."""
    return _a(_sandwich_down_jit(v, x))


_apply_jit = jax.jit(cga.apply_to_points)
_to_matrix = jax.jit(cga.versor_to_matrix)
_to_dual_quaternion = jax.jit(cga.motor_to_dual_quaternion)
_from_dual_quaternion = jax.jit(cga.dual_quaternion_to_motor)


def _apply(v, x):
    return _a(_apply_jit(v, x))


# ---------------------------------------------------------------- rotors
@SETTINGS
@given(seeds)
def test_rotor_matches_scipy_rotvec(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    scale = rng.uniform(0.1, 10.0)  # the axis is normalized by rotor()
    x = rng.normal(size=(6, 3)) * 3
    R = cga.rotor(axis * scale, angle)
    ref = Rotation.from_rotvec(angle * axis).apply(x)
    np.testing.assert_allclose(_apply(R, x), ref, atol=1e-13)
    np.testing.assert_allclose(_sandwich_down(R, x), ref, atol=1e-13)
    # Unit rotor: R ~R = 1.
    RR = R * ~R
    np.testing.assert_allclose(_a(RR["1"]), 1.0, rtol=1e-15)
    for name in RR.names:
        if name != "1":
            assert abs(float(RR[name])) <= 1e-15


def test_rotor_convention_quarter_turn_about_z():
    # +90 degrees about e3 maps e1 to e2 (right-handed), and R = cos(pi/4) - sin(pi/4) e12 (eq. 8).
    R = cga.rotor(np.array([0.0, 0.0, 1.0]), np.pi / 2)
    np.testing.assert_allclose(_apply(R, np.array([1.0, 0, 0])), [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(_a(R["1"]), np.cos(np.pi / 4), rtol=1e-15)
    np.testing.assert_allclose(_a(R["e12"]), -np.sin(np.pi / 4), rtol=1e-15)


@SETTINGS
@given(seeds)
def test_rotor_from_bivector(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    # u I3 = u1 e23 - u2 e13 + u3 e12, so the bivector (e12, e13, e23) of the plane is (u3, -u2, u1).
    b = np.array([axis[2], -axis[1], axis[0]]) * rng.uniform(0.1, 5.0)
    R = cga.rotor_from_bivector(b, angle)
    np.testing.assert_allclose(_a(R.values), _a(cga.rotor(axis, angle).values), atol=1e-15)
    x = rng.normal(size=(4, 3))
    np.testing.assert_allclose(_apply(R, x), Rotation.from_rotvec(angle * axis).apply(x), atol=1e-13)
    # R = exp(-b angle / 2) for the unit b: compare with the exponential.
    bu = b / np.linalg.norm(b)
    E = cga.exp(cga.Multivector(-0.5 * angle * bu, ("e12", "e13", "e23")))
    np.testing.assert_allclose(_a(E["1"]), _a(R["1"]), atol=1e-14)
    np.testing.assert_allclose(
        [_a(E[n]) for n in ("e12", "e13", "e23")], [_a(R[n]) for n in ("e12", "e13", "e23")], atol=1e-14
    )


def test_rotor_composition_matches_scipy():
    rng = np.random.default_rng(11)
    (a1, t1), (a2, t2) = _random_rotation(rng), _random_rotation(rng)
    R1, R2 = cga.rotor(a1, t1), cga.rotor(a2, t2)
    x = rng.normal(size=(6, 3))
    # R2 R1 applies R1 first (eq. 14).
    ref = (Rotation.from_rotvec(t2 * a2) * Rotation.from_rotvec(t1 * a1)).apply(x)
    np.testing.assert_allclose(_apply(R2 * R1, x), ref, atol=1e-13)


# ---------------------------------------------------------------- translators and dilators
@SETTINGS
@given(seeds, st.floats(1e-3, 1e4))
def test_translator(seed, scale):
    rng = np.random.default_rng(seed)
    t = rng.normal(size=3) * scale
    x = rng.normal(size=(6, 3))
    T = cga.translator(t)
    np.testing.assert_allclose(_a(T.values), np.r_[1.0, -0.5 * t], rtol=1e-15)  # eq. 10
    np.testing.assert_allclose(_apply(T, x), x + t, rtol=1e-13, atol=1e-13 * scale)
    np.testing.assert_allclose(_sandwich_down(T, x), x + t, rtol=1e-13, atol=1e-13 * scale)


# Scales up to 1e2 only: see test_large_dilation_keeps_precision for the precision loss beyond.
@SETTINGS
@given(seeds, st.floats(1e-3, 1e2))
def test_dilator_scales_about_origin(seed, d):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(6, 3))
    D = cga.dilator(d)
    np.testing.assert_allclose(_apply(D, x), d * x, rtol=1e-11)
    np.testing.assert_allclose(_sandwich_down(D, x), d * x, rtol=1e-11)
    # Normalized: D ~D = 1, D = cosh(ln d / 2) + sinh(ln d / 2) eo^einf.
    np.testing.assert_allclose(_a((D * ~D)["1"]), 1.0, rtol=1e-12)
    np.testing.assert_allclose(_a(D.values), [np.cosh(np.log(d) / 2), np.sinh(np.log(d) / 2)], rtol=1e-12)


@SETTINGS
@given(seeds, st.floats(1e-3, 1e2))
def test_dilator_paper_and_its_inverse(seed, d):
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(6, 3))
    Dp = cga.dilator_paper(d)
    # eq. 12: D = 1 + (1 - d)/(1 + d) einf^eo = 1 + (d - 1)/(d + 1) eo^einf.
    np.testing.assert_allclose(_a(Dp.values), [1.0, (d - 1) / (d + 1)], rtol=1e-14, atol=1e-16)
    np.testing.assert_allclose(_apply(Dp, x), d * x, rtol=1e-11)
    np.testing.assert_allclose(_sandwich_down(Dp, x), d * x, rtol=1e-11)
    # The normalized dilator is eq. 12 times (1 + d) / (2 sqrt d) (module docstring).
    np.testing.assert_allclose(
        _a(Dp.values) * (1 + d) / (2 * np.sqrt(d)), _a(cga.dilator(d).values), rtol=1e-12, atol=1e-14
    )
    # eq. 13: D^-1 = (1 + d)^2 / (4 d) + (d^2 - 1) / (4 d) einf^eo; our blade eoinf = -einf^eo.
    inv = cga.inverse(Dp)
    np.testing.assert_allclose(_a(inv["1"]), (1 + d) ** 2 / (4 * d), rtol=1e-10)
    np.testing.assert_allclose(_a(inv["eoinf"]), -(d * d - 1) / (4 * d), rtol=1e-10, atol=1e-12)
    for name in inv.names:
        if name not in ("1", "eoinf"):
            assert abs(float(inv[name])) <= 1e-12 * (1 + d + 1 / d)
    prod = Dp * inv
    np.testing.assert_allclose(_a(prod["1"]), 1.0, rtol=1e-12)
    np.testing.assert_allclose(_a(prod["eoinf"]), 0.0, atol=1e-12)
    # versor_inverse agrees.
    vinv = cga.versor_inverse(Dp)
    np.testing.assert_allclose(_a(vinv["1"]), (1 + d) ** 2 / (4 * d), rtol=1e-10)
    np.testing.assert_allclose(_a(vinv["eoinf"]), -(d * d - 1) / (4 * d), rtol=1e-10, atol=1e-12)


# Scales of 1e-4 .. 1e4: the point map is evaluated in the factored components of the dilation
# (jaxcga._versors._point_map), so its entries of size d and 1/d never come out of terms that cancel.
SCALES = [1e-4, 3e-4, 1e-3, 1e-2, 0.3, 1.0, 7.0, 1e2, 1e3, 4e3, 1e4]


def _representation_limit(d):
    """What the 16 stored components determine: the two halves of a dilation by d are ~sqrt(d)/2 and
    their difference, 1/sqrt(d), keeps ~max(d, 1/d) ulps."""
    return 8 * np.finfo(np.float64).eps * max(d, 1 / d)


@pytest.mark.parametrize("d", SCALES)
def test_similitude_keeps_precision_at_any_scale(d):
    rng = np.random.default_rng(int(np.log10(d) * 100) % 1000)
    x = rng.normal(size=(50, 3))
    for _ in range(5):
        axis, angle = _random_rotation(rng)
        t = rng.normal(size=3) * 5 * d
        rotation = Rotation.from_rotvec(angle * axis)
        S = cga.similitude(cga.rotor(axis, angle), t, d)
        ref = d * rotation.apply(x) + t
        error = np.linalg.norm(_apply(S, x) - ref, axis=1) / np.linalg.norm(ref, axis=1)
        assert error.max() <= max(1e-13, _representation_limit(d)), (d, error.max())
        H = _a(_to_matrix(S))
        np.testing.assert_allclose(
            H[:3, :3], d * rotation.as_matrix(), rtol=0, atol=max(1e-13, _representation_limit(d)) * d
        )
    for D in (cga.dilator(d), cga.dilator_paper(d)):
        np.testing.assert_allclose(_apply(D, x), d * x, rtol=max(1e-13, _representation_limit(d)))


# ---------------------------------------------------------------- motors and similitudes
@SETTINGS
@given(seeds)
def test_motor_rotates_then_translates(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 5
    x = rng.normal(size=(6, 3))
    M = cga.motor(cga.rotor(axis, angle), t)
    ref = Rotation.from_rotvec(angle * axis).apply(x) + t
    np.testing.assert_allclose(_apply(M, x), ref, atol=1e-12)
    np.testing.assert_allclose(_sandwich_down(M, x), ref, atol=1e-12)
    # motor(R, t) = T R: the same multivector as the product.
    TR = (cga.translator(t) * cga.rotor(axis, angle)).embed("motor")
    np.testing.assert_allclose(_a(M.values), _a(TR.values), atol=1e-14)
    # motor_rotor_translation splits it back.
    r, tt = cga.motor_rotor_translation(M)
    np.testing.assert_allclose(_a(tt), t, atol=1e-12)
    np.testing.assert_allclose(_a(r.values), _a(cga.rotor(axis, angle).values), atol=1e-14)


@SETTINGS
@given(seeds, st.floats(1e-2, 1e2))
def test_similitude_maps_x_to_d_R_x_plus_t(seed, d):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 5
    x = rng.normal(size=(6, 3))
    S = cga.similitude(cga.rotor(axis, angle), t, d)
    assert S.names == tuple(cga.Multivector(np.zeros(16), "similitude").names)
    ref = d * Rotation.from_rotvec(angle * axis).apply(x) + t
    np.testing.assert_allclose(_apply(S, x), ref, rtol=1e-11, atol=1e-11 * (1 + d))
    np.testing.assert_allclose(_sandwich_down(S, x), ref, rtol=1e-11, atol=1e-11 * (1 + d))
    H = _a(_to_matrix(S))
    np.testing.assert_allclose(H[:3, :3], d * Rotation.from_rotvec(angle * axis).as_matrix(), atol=1e-11 * (1 + d))
    np.testing.assert_allclose(H[:3, 3], t, atol=1e-11 * (1 + d))
    np.testing.assert_allclose(H[3], [0, 0, 0, 1], atol=0)


@SETTINGS
@given(seeds, st.floats(1e-2, 1e2), st.floats(-3.0, 3.0).filter(lambda k: abs(k) > 1e-2))
def test_similitude_splits_into_its_motor_and_log_scale(seed, d, k):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 5
    # any scalar factor k, negative included: the split is of the transformation
    S = cga.similitude(cga.rotor(axis, angle), t, d) * k
    M, lam = cga.similitude_motor_log_scale(S)
    np.testing.assert_allclose(float(lam), np.log(d), atol=1e-12)
    assert M.names == tuple(cga.Multivector(np.zeros(8), "motor").names)
    rotor = _a(M.values[:4])
    np.testing.assert_allclose(np.sum(rotor**2), 1.0, atol=1e-14)
    # M = +-motor(R, t) (unit rotor, same translation), and S's points are M's after scaling by e^lam
    M_ref = _a(cga.motor(cga.rotor(axis, angle), t).values)
    np.testing.assert_allclose(_a(M.values) * np.sign(rotor @ M_ref[:4]), M_ref, atol=1e-11 * (1 + d))
    x = rng.normal(size=(6, 3))
    ref = d * Rotation.from_rotvec(angle * axis).apply(x) + t
    np.testing.assert_allclose(_apply(M, np.exp(float(lam)) * x), ref, rtol=1e-11, atol=1e-11 * (1 + d))


def test_similitude_split_refuses_non_similitudes_and_has_finite_differences():
    with pytest.raises(ValueError, match="s: expected a similitude"):
        cga.similitude_motor_log_scale(cga.Multivector(np.ones(2), ("1", "e1")))
    with pytest.raises(ValueError, match="s: not a similitude versor"):
        cga.similitude_motor_log_scale(cga.Multivector(np.array([1.0, 2.0]), "dilator"))
    # derivatives against central differences, in the similitude's components
    S = cga.similitude(cga.rotor(np.array([0.0, 0.6, 0.8]), 0.7), np.array([1.0, -2.0, 0.5]), 1.7)

    def split(values):
        M, lam = cga.similitude_motor_log_scale(cga.Multivector(values, S.blades))
        return jax.numpy.concatenate([M.values, lam[None]])

    jac = np.asarray(jax.jacfwd(split)(S.values))
    eps = 1e-6
    for i in range(S.values.shape[0]):
        step = np.zeros(S.values.shape[0])
        step[i] = eps
        fd = (np.asarray(split(S.values + step)) - np.asarray(split(S.values - step))) / (2 * eps)
        np.testing.assert_allclose(jac[:, i], fd, atol=1e-8)


def _make_versor(rng, kind):
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 3
    d = float(np.exp(rng.uniform(-2, 2)))
    if kind == "rotor":
        return cga.rotor(axis, angle)
    if kind == "translator":
        return cga.translator(t)
    if kind == "dilator":
        return cga.dilator(d)
    if kind == "dilator_paper":
        return cga.dilator_paper(d)
    if kind == "motor":
        return cga.motor(cga.rotor(axis, angle), t)
    if kind == "similitude":
        return cga.similitude(cga.rotor(axis, angle), t, d)
    assert kind == "unnormalized_motor"
    return cga.motor(cga.rotor(axis, angle), t) * 2.5


@pytest.mark.parametrize(
    "kind", ["rotor", "translator", "dilator", "dilator_paper", "motor", "similitude", "unnormalized_motor"]
)
def test_apply_to_points_equals_sandwich_for_every_kind_and_broadcast(kind):
    rng = np.random.default_rng(sum(map(ord, kind)))
    # One versor for all points.
    V = _make_versor(rng, kind)
    x = rng.normal(size=(6, 3)) * 2
    single = _apply(V, x)
    np.testing.assert_allclose(single, _sandwich_down(V, x), rtol=1e-12, atol=1e-12)
    # One versor per point: a batch of 6 versors against 6 points.
    zoo = [_make_versor(rng, kind) for _ in range(6)]
    Vb = cga.Multivector(np.stack([_a(v.values) for v in zoo]), zoo[0].blades)
    got = _apply(Vb, x)
    assert got.shape == (6, 3)
    np.testing.assert_allclose(got, _sandwich_down(Vb, x), rtol=1e-12, atol=1e-12)
    for k in range(6):
        np.testing.assert_allclose(got[k], _apply(zoo[k], x)[k], rtol=1e-13, atol=1e-13)
    # Broadcasting: versors (2, 1) against points (1, 6) -> (2, 6, 3).
    V2 = cga.Multivector(_a(Vb.values)[:2, None, :], Vb.blades)
    got2 = _apply(V2, x[None])
    assert got2.shape == (2, 6, 3)
    for k in range(2):
        np.testing.assert_allclose(got2[k], _apply(zoo[k], x), rtol=1e-13, atol=1e-13)


def test_apply_to_points_rejects_bad_input():
    M = cga.motor(cga.rotor(np.array([0.0, 0, 1]), 0.3), np.zeros(3))
    with pytest.raises(ValueError):
        cga.apply_to_points(M, np.zeros((4, 2)))
    with pytest.raises(ValueError):
        cga.apply_to_points(np.eye(4), np.zeros((4, 3)))  # pyright: ignore[reportArgumentType]
    Mb = cga.Multivector(np.tile(_a(M.values), (3, 1)), M.blades)
    with pytest.raises(ValueError):
        cga.apply_to_points(Mb, np.zeros((4, 3)))  # batch shapes (3,) and (4,) do not broadcast


# ---------------------------------------------------------------- matrices
@SETTINGS
@given(seeds)
def test_versor_to_matrix_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 5
    M = cga.motor(cga.rotor(axis, angle), t)
    H = _a(_to_matrix(M))
    np.testing.assert_allclose(_a(cga.versor_to_matrix(M)), H, atol=1e-15)  # eager, as jitted
    assert H.shape == (4, 4)
    np.testing.assert_allclose(H[:3, :3], Rotation.from_rotvec(angle * axis).as_matrix(), atol=1e-14)
    np.testing.assert_allclose(H[:3, 3], t, atol=1e-13)
    np.testing.assert_array_equal(H[3], [0.0, 0.0, 0.0, 1.0])
    x = rng.normal(size=(4, 3))
    np.testing.assert_allclose(x @ H[:3, :3].T + H[:3, 3], _apply(M, x), atol=1e-12)


@jax.jit
def _matrix_round_trip(H, x):
    M = cga.matrix_to_motor(H)
    return M, cga.versor_to_matrix(M), cga.apply_to_points(M, x), cga.matrix_to_quaternion(H[:3, :3])


def _rigid(rotation_matrix, t):
    H = np.eye(4)
    H[:3, :3] = rotation_matrix
    H[:3, 3] = t
    return H


@SETTINGS
@given(seeds)
def test_matrix_to_motor_round_trip(seed):
    rng = np.random.default_rng(seed)
    Rm = Rotation.random(rng=rng).as_matrix()
    t = rng.normal(size=3) * 4
    H = _rigid(Rm, t)
    M, H2, x2, q = _matrix_round_trip(H, np.zeros((2, 3)))
    np.testing.assert_allclose(_a(H2), H, atol=1e-13)
    np.testing.assert_allclose(_a(x2), np.tile(t, (2, 1)), atol=1e-13)
    q = _a(q)
    qs = Rotation.from_matrix(Rm).as_quat(scalar_first=True)
    qs = qs if qs[0] >= 0 else -qs
    assert q[0] >= 0
    np.testing.assert_allclose(q, qs, atol=1e-13)


def test_matrix_to_motor_accepts_3x4():
    H = _rigid(Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix(), np.array([1.0, 2.0, 3.0]))
    M = _matrix_round_trip(H, np.zeros((2, 3)))[0]
    np.testing.assert_allclose(_a(cga.matrix_to_motor(H[:3]).values), _a(M.values), atol=1e-15)


_NEAR_PI_AXES = [
    np.array([1.0, 0, 0]),  # Shepperd branch m00
    np.array([0, 1.0, 0]),  # m11
    np.array([0, 0, 1.0]),  # m22
    _unit(np.array([1.0, 1.0, 1.0])),
    _unit(np.array([0.2, -0.9, 0.4])),
    _unit(np.array([1.0, 1e-9, 0.0])),
]


@pytest.mark.parametrize("angle", [0.0, 1e-9, 1.0, np.pi / 2, np.pi - 1e-6, np.pi - 1e-9, np.pi])
@pytest.mark.parametrize("axis_index", range(len(_NEAR_PI_AXES)))
def test_matrix_to_motor_near_pi(angle, axis_index):
    axis = _NEAR_PI_AXES[axis_index]
    rot = Rotation.from_rotvec(angle * axis)
    t = np.array([0.3, -2.0, 1.5])
    H = _rigid(rot.as_matrix(), t)
    x = np.array([[1.0, 2.0, 3.0], [-0.5, 0.1, 0.0]])
    M, H2, x2, q = _matrix_round_trip(H, x)
    np.testing.assert_allclose(_a(H2), H, atol=2e-15 * 8)
    np.testing.assert_allclose(_a(x2), rot.apply(x) + t, atol=1e-14 * 8)
    # The quaternion of the rotation block, up to sign, and w >= 0.
    q = _a(q)
    qs = rot.as_quat(scalar_first=True)
    assert q[0] >= 0
    assert min(np.abs(q - qs).max(), np.abs(q + qs).max()) <= 1e-14
    np.testing.assert_allclose(np.linalg.norm(q), 1.0, rtol=1e-15)


def test_matrix_to_quaternion_batched():
    # the legacy keyword keeps the seeded stream (scipy's signature names only rng)
    rots = Rotation.random(6, random_state=4)  # pyright: ignore[reportCallIssue]
    q = _a(cga.matrix_to_quaternion(rots.as_matrix()))
    qs = rots.as_quat(scalar_first=True)
    qs = qs * np.where(qs[:, :1] < 0, -1.0, 1.0)
    np.testing.assert_allclose(q, qs, atol=1e-14)


def test_matrix_to_motor_rejects_bad_input():
    with pytest.raises(ValueError):
        cga.matrix_to_motor(np.eye(3))
    with pytest.raises(ValueError):
        cga.matrix_to_motor(np.zeros(4))
    reflection = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(Exception, match="not a rigid motion"):
        cga.matrix_to_motor(reflection)


# ---------------------------------------------------------------- quaternions
@SETTINGS
@given(seeds)
def test_rotor_to_quaternion_matches_scipy_exactly(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    R = cga.rotor(axis, angle)
    # Same sign: both are cos(angle/2) + sin(angle/2) (axis) for angles of either sign.
    np.testing.assert_allclose(
        _a(cga.rotor_to_quaternion(R)), Rotation.from_rotvec(angle * axis).as_quat(scalar_first=True), atol=1e-15
    )
    # Motors: the quaternion of the rotor part (motor blades accepted).
    M = cga.motor(R, rng.normal(size=3))
    np.testing.assert_allclose(_a(cga.rotor_to_quaternion(M)), _a(cga.rotor_to_quaternion(R)), atol=1e-15)


@SETTINGS
@given(seeds)
def test_quaternion_to_rotor_matches_scipy(seed):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=4)  # not normalized: quaternion_to_rotor normalizes
    rot = Rotation.from_quat(q, scalar_first=True)
    R = cga.quaternion_to_rotor(q)
    x = rng.normal(size=(6, 3))
    np.testing.assert_allclose(_apply(R, x), rot.apply(x), atol=1e-13)
    np.testing.assert_allclose(_a(cga.rotor_to_quaternion(R)), q / np.linalg.norm(q), atol=1e-15)
    # Products correspond: R2 R1 <-> q2 q1 (Hamilton).
    q2 = _unit(rng.normal(size=4))
    R2 = cga.quaternion_to_rotor(q2)
    np.testing.assert_allclose(_a(cga.rotor_to_quaternion(R2 * R)), _qmul(q2, q / np.linalg.norm(q)), atol=1e-14)


def test_quaternion_to_rotor_rejects_bad_shape():
    with pytest.raises(ValueError):
        cga.quaternion_to_rotor(np.zeros(3))


# ---------------------------------------------------------------- dual quaternions
@SETTINGS
@given(seeds)
def test_dual_quaternion_round_trip_and_action(seed):
    rng = np.random.default_rng(seed)
    axis, angle = _random_rotation(rng)
    t = rng.normal(size=3) * 3
    M = cga.motor(cga.rotor(axis, angle), t)
    dq = _a(_to_dual_quaternion(M))
    assert dq.shape == (8,)
    qr, qd = dq[:4], dq[4:]
    qc = qr * np.array([1.0, -1, -1, -1])
    # Unit dual quaternion: |qr| = 1, <qr, qd> = 0; translation t = 2 qd qr^*.
    np.testing.assert_allclose(np.linalg.norm(qr), 1.0, rtol=1e-14)
    np.testing.assert_allclose(qr @ qd, 0.0, atol=1e-14)
    tq = 2 * _qmul(qd, qc)
    np.testing.assert_allclose(tq, np.r_[0.0, t], atol=1e-13)
    # The dual quaternion transforms points the standard way: x -> qr x qr^* + t.
    for x in rng.normal(size=(3, 3)):
        xr = _qmul(_qmul(qr, np.r_[0.0, x]), qc)[1:] + tq[1:]
        np.testing.assert_allclose(xr, _apply(M, x), atol=1e-12)
    # Round trip.
    np.testing.assert_allclose(_a(_from_dual_quaternion(dq).values), _a(M.values), atol=1e-14)
    # Scaled dual quaternions give the same motor.
    np.testing.assert_allclose(_a(_from_dual_quaternion(2.0 * dq).values), _a(M.values), atol=1e-14)


def test_jit_and_vmap_of_apply_to_points():
    rng = np.random.default_rng(5)
    S = cga.similitude(cga.rotor(rng.normal(size=3), 0.7), rng.normal(size=3), 1.7)
    x = rng.normal(size=(6, 3))
    eager = _a(cga.apply_to_points(S, x))
    np.testing.assert_allclose(_apply(S, x), eager, rtol=1e-14, atol=1e-14)  # jit
    per_point = _a(jax.vmap(cga.apply_to_points, in_axes=(None, 0))(S, x))
    np.testing.assert_allclose(per_point, eager, rtol=1e-14, atol=1e-14)
    Sb = cga.Multivector(np.tile(_a(S.values), (6, 1)), S.blades)
    per_both = _a(jax.vmap(cga.apply_to_points)(Sb, x))
    np.testing.assert_allclose(per_both, eager, rtol=1e-14, atol=1e-14)
