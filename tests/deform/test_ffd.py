"""Free-form deformation (deformation paper sec. V, eq. 6-8): Bernstein bases and lattice weights against
scipy's BPoly, linear precision, motor FFD against classic FFD (translations, one rigid motor, the paper's
``p = M o ~M`` form), the twist as an exact analytic twist and its volume / edge-length measurements
against trimesh, jit / vmap / gradients, bad input."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.interpolate import BPoly
from scipy.spatial.transform import Rotation

import deform
import jaxcga as cga
from deform import (
    Lattice,
    blend_positions,
    bounding_lattice,
    distortion,
    ffd_precompute,
    ffd_weights,
    identity_motors,
    lattice_coordinates,
    lattice_points,
    motor_field_precompute,
    motor_field_solve,
    spline_weights,
    twist_lattice,
)
from jaxcga import KINDS, MOTOR_GENERATOR, Multivector
from tests.shared import check_gradient

ARM = deform.default_arm().mesh
# one compiled call per shape instead of op-by-op dispatch of the exp / log code (keeps the file fast)
_deform = jax.jit(motor_field_solve)
_twist = jax.jit(twist_lattice, static_argnames="axis")
# the paper's form p = M o ~M: rest lattice motors are the translators to the lattice points
_paper_form = jax.jit(lambda V, W, P0: motor_field_precompute(V, W, rest_motors=cga.translator(P0)))


def _arm():
    return np.array(ARM.V, np.float64), np.array(ARM.F, np.int64)


def _box():
    """A closed 4 x 1 x 1 box, subdivided to edges <= 0.1 (9730 vertices)."""
    box = trimesh.creation.box(extents=(4.0, 1.0, 1.0))
    V, F = trimesh.remesh.subdivide_to_size(box.vertices, box.faces, 0.1)[:2]
    return np.asarray(V, np.float64), np.asarray(F, np.int64)


def _sheared_lattice(counts):
    axes = np.array([[2.0, 0.3, 0.0], [-0.2, 1.0, 0.4], [0.1, 0.0, 1.5]])
    return Lattice(np.array([0.5, -1.0, 2.0]), axes, counts)


def _bernstein_scipy(degree, t):
    return np.stack([BPoly(np.eye(degree + 1)[:, [j]], [0.0, 1.0])(t) for j in range(degree + 1)], axis=-1)


def _broadcast(motor, k):
    return Multivector(jnp.broadcast_to(motor.values, (k, motor.values.shape[-1])), motor.blades)


def _rodrigues(points, centre, direction, angles):
    rotvec = np.asarray(direction) / np.linalg.norm(direction) * np.asarray(angles)[:, None]
    return Rotation.from_rotvec(rotvec).apply(np.asarray(points) - centre) + centre


@pytest.mark.parametrize("degree", [1, 2, 3, 5])
def test_bernstein_partition_of_unity_non_negative_and_equal_to_scipy_bpoly(degree):
    """The Bernstein basis of the lattice weights, seen through the spline's Bezier basis (the same one)."""
    t = np.concatenate([[0.0, 1.0], np.random.default_rng(degree).uniform(0, 1, 50)])
    B = np.asarray(spline_weights(jnp.asarray(t), "bezier", degree + 1))
    assert B.shape == (len(t), degree + 1)
    np.testing.assert_allclose(B, _bernstein_scipy(degree, t), atol=1e-14)
    np.testing.assert_allclose(B.sum(axis=1), 1.0, atol=1e-14)
    assert B.min() >= 0.0
    # finite derivatives at the ends (integer powers, no 0 * inf)
    d = jax.jacfwd(lambda x: spline_weights(x, "bezier", degree + 1))(jnp.asarray([0.0, 1.0]))
    assert np.all(np.isfinite(np.asarray(d)))


def test_weights_and_coordinates_on_a_sheared_lattice_against_bpoly():
    counts = (2, 3, 5)
    lattice = _sheared_lattice(counts)
    local = np.random.default_rng(1).uniform(0, 1, (200, 3))
    local[:3] = [[0, 0, 0], [1, 1, 1], [0, 1, 0.5]]
    V = np.asarray(lattice.origin) + local @ np.asarray(lattice.axes)
    np.testing.assert_allclose(lattice_coordinates(V, lattice), local, atol=1e-13)
    b = [_bernstein_scipy(c - 1, local[:, a]) for a, c in enumerate(counts)]
    expected = np.einsum("pa,pb,pc->pabc", *b).reshape(len(V), -1)
    W = np.asarray(ffd_weights(V, lattice))
    np.testing.assert_allclose(W, expected, atol=1e-14)
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-13)
    # row-major (a, b, c) order of the control points: the corner (1, 1, 1) is the last one
    P = np.asarray(lattice_points(lattice))
    np.testing.assert_allclose(P[-1], np.asarray(lattice.origin) + np.asarray(lattice.axes).sum(axis=0), atol=1e-14)
    np.testing.assert_allclose(P[counts[2]], np.asarray(lattice.origin) + np.asarray(lattice.axes)[1] / 2, atol=1e-14)
    np.testing.assert_allclose(blend_positions(W, P), V, atol=1e-12)


@pytest.mark.parametrize("padding", [0.0, 0.1])
def test_undeformed_lattice_reproduces_the_mesh(padding):
    V, _ = _arm()
    lattice = bounding_lattice(V, (4, 3, 5), padding)
    W = ffd_weights(V, lattice)
    np.testing.assert_allclose(blend_positions(W, lattice_points(lattice)), V, atol=1e-12)
    field = ffd_precompute(V, lattice)
    np.testing.assert_allclose(_deform(field, identity_motors(lattice.size)), V, atol=1e-12)


def test_translation_motors_equal_classic_ffd_in_both_motor_forms():
    V, _ = _arm()
    lattice = bounding_lattice(V, (4, 4, 4), 0.05)
    W = ffd_weights(V, lattice)
    P0 = lattice_points(lattice)
    d = jnp.asarray(np.random.default_rng(2).normal(0, 0.1, (lattice.size, 3)))
    classic = blend_positions(W, P0 + d)
    assert float(jnp.abs(classic - V).max()) > 0.05
    np.testing.assert_allclose(_deform(ffd_precompute(V, lattice), cga.translator(d)), classic, atol=1e-12)
    # the paper's form binds every vertex to the origin
    paper = _paper_form(V, W, P0)
    np.testing.assert_allclose(paper.bound, 0.0, atol=1e-12)
    np.testing.assert_allclose(_deform(paper, cga.translator(P0 + d)), classic, atol=1e-12)


def test_one_rigid_motor_for_the_whole_lattice_moves_the_mesh_rigidly():
    V, _ = _arm()
    lattice = bounding_lattice(V, (4, 4, 4), 0.05)
    W = ffd_weights(V, lattice)
    P0 = lattice_points(lattice)
    axis, angle, t = np.array([0.3, 1.0, 0.2]), 2.5, np.array([0.1, -0.2, 0.3])
    G = cga.motor(cga.rotor(jnp.asarray(axis), angle), jnp.asarray(t))
    rigid = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).apply(V) + t  # independent of the kernel
    np.testing.assert_allclose(_deform(ffd_precompute(V, lattice), _broadcast(G, lattice.size)), rigid, atol=1e-12)
    # classic FFD with every control point moved by G: linear precision gives G too
    P = Rotation.from_rotvec(axis / np.linalg.norm(axis) * angle).apply(np.array(P0)) + t
    np.testing.assert_allclose(blend_positions(W, P), rigid, atol=1e-12)
    # the paper's form with lattice motors G T_j gives G as well
    GT = (G * cga.translator(P0)).embed(KINDS["motor"])
    np.testing.assert_allclose(_deform(_paper_form(V, W, P0), GT), rigid, atol=1e-12)


@pytest.mark.parametrize("degrees", [90, pytest.param(180, marks=pytest.mark.slow)])
def test_twist_motors_give_the_exact_analytic_twist(degrees):
    V, _ = _box()
    lattice = bounding_lattice(V, (4, 4, 4), 0.05)
    angle = np.radians(degrees)
    P, motors = _twist(lattice, angle)
    centre = np.asarray(lattice.origin) + np.asarray(lattice.axes).sum(axis=0) / 2
    direction = np.array([1.0, 0.0, 0.0])  # the box's long edge
    P0 = np.asarray(lattice_points(lattice))
    s0 = (P0[:, 0] - float(lattice.origin[0])) / float(lattice.axes[0, 0])
    np.testing.assert_allclose(P, _rodrigues(P0, centre, direction, angle * (s0 - 0.5)), atol=1e-12)
    # every vertex turned by the blended angle, angle * (s_i - 1/2) (linear precision along the axis)
    s = (V[:, 0] - float(lattice.origin[0])) / float(lattice.axes[0, 0])
    moved = _deform(ffd_precompute(V, lattice), motors)
    np.testing.assert_allclose(moved, _rodrigues(V, centre, direction, angle * (s - 0.5)), atol=1e-12)
    # the paper's form G_j T_j blends screws about different axes: not the same twist
    W = ffd_weights(V, lattice)
    paper = _paper_form(V, W, lattice_points(lattice))
    twisted = _deform(paper, (motors * cga.translator(lattice_points(lattice))).embed(KINDS["motor"]))
    assert float(jnp.abs(twisted - moved).max()) > 5e-3


@pytest.mark.parametrize("mesh", ["box", "arm"])
@pytest.mark.parametrize("degrees", [90, 180])
def test_motor_ffd_keeps_volume_and_edges_better_than_classic_ffd_on_a_twist(mesh, degrees):
    V, F = _box() if mesh == "box" else _arm()
    assert trimesh.Trimesh(V, F, process=False).is_watertight
    lattice = bounding_lattice(V, (4, 4, 4), 0.05)
    P, motors = _twist(lattice, np.radians(degrees))
    classic = np.asarray(blend_positions(ffd_weights(V, lattice), P))
    moved = np.asarray(_deform(ffd_precompute(V, lattice), motors))
    measured = {}
    for name, V1 in [("classic", classic), ("motor", moved)]:
        d = {k: float(v) for k, v in distortion(V, F, V1).items()}
        rest, bent = trimesh.Trimesh(V, F, process=False), trimesh.Trimesh(V1, F, process=False)
        change = np.abs(bent.edges_unique_length / rest.edges_unique_length - 1)
        np.testing.assert_allclose(d["volume_ratio"], bent.volume / rest.volume, rtol=1e-12)
        np.testing.assert_allclose([d["edge_mean"], d["edge_max"]], [change.mean(), change.max()], rtol=1e-12)
        measured[name] = d
    # measured: classic keeps 86 % (90 deg) / 54-56 % (180 deg) of the volume, motor 1 +- 1e-3
    assert abs(measured["motor"]["volume_ratio"] - 1) < 2e-3
    assert measured["classic"]["volume_ratio"] < (0.9 if degrees == 90 else 0.6)
    # measured: mean edge change 1-6 % for the motor FFD, 5-15 % for the classic one; max 7-18 % against 8-36 %
    assert measured["motor"]["edge_mean"] < 0.6 * measured["classic"]["edge_mean"]
    assert measured["motor"]["edge_max"] < 0.9 * measured["classic"]["edge_max"]


def test_jit_and_vmap_over_batches_of_lattice_motors_and_control_points():
    V, _ = _arm()
    lattice = bounding_lattice(V, (4, 4, 4), 0.05)
    field = ffd_precompute(V, lattice)
    W = ffd_weights(V, lattice)
    angles = jnp.asarray([0.3, 1.0, 2.0])
    P, motors = jax.jit(jax.vmap(twist_lattice, in_axes=(None, 0)))(lattice, angles)
    assert motors.batch_shape == (3, lattice.size) and P.shape == (3, lattice.size, 3)
    loop = np.stack([np.asarray(_deform(field, Multivector(motors.values[b], motors.blades))) for b in range(3)])
    np.testing.assert_allclose(_deform(field, motors), loop, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.vmap(motor_field_solve, in_axes=(None, 0)))(field, motors), loop, atol=1e-12)
    loop = np.stack([np.asarray(W @ P[b]) for b in range(3)])
    np.testing.assert_allclose(jax.jit(blend_positions)(W, P), loop, atol=1e-12)
    np.testing.assert_allclose(jax.vmap(blend_positions, in_axes=(None, 0))(W, P), loop, atol=1e-12)


def _small_case():
    lattice = _sheared_lattice((2, 2, 3))
    local = np.random.default_rng(3).uniform(0, 1, (40, 3))
    V = np.asarray(lattice.origin) + local @ np.asarray(lattice.axes)
    target = V + np.random.default_rng(4).normal(0, 0.2, V.shape)
    return lattice, V, jnp.asarray(target)


@pytest.mark.slow
def test_gradient_with_respect_to_lattice_motor_logs():
    lattice, V, target = _small_case()
    field = ffd_precompute(V, lattice)

    def loss(logs):
        motors = cga.exp_motor(Multivector(logs.reshape(lattice.size, 6), MOTOR_GENERATOR))
        return jnp.sum((motor_field_solve(field, motors) - target) ** 2)

    logs = jnp.asarray(np.random.default_rng(5).normal(0, 0.3, lattice.size * 6))
    check_gradient(jax.jit(loss), logs)


def test_gradient_with_respect_to_control_points_and_embedded_points():
    lattice, V, target = _small_case()
    W = ffd_weights(V, lattice)
    P0 = np.asarray(lattice_points(lattice))
    bent = jnp.asarray(P0 + np.random.default_rng(6).normal(0, 0.2, P0.shape))
    check_gradient(jax.jit(lambda p: jnp.sum((blend_positions(W, p.reshape(-1, 3)) - target) ** 2)), bent.ravel())
    # through the weights: the points' local coordinates move with them (strictly inside the lattice)
    local = np.random.default_rng(7).uniform(0.2, 0.8, (5, 3))
    inner = jnp.asarray(np.asarray(lattice.origin) + local @ np.asarray(lattice.axes))
    check_gradient(
        jax.jit(lambda x: jnp.sum(blend_positions(ffd_weights(x.reshape(-1, 3), lattice), bent) ** 2)), inner.ravel()
    )


@pytest.mark.slow
def test_float32():
    V, F = _arm()
    lattice = bounding_lattice(V.astype(np.float32), (4, 4, 4), 0.05)
    W = ffd_weights(V.astype(np.float32), lattice)
    assert W.dtype == jnp.float32
    P, motors = _twist(lattice, 1.0)
    field = ffd_precompute(V.astype(np.float32), lattice)
    moved = _deform(field, Multivector(motors.values.astype(jnp.float32), motors.blades))
    assert moved.dtype == jnp.float32 and blend_positions(W, P).dtype == jnp.float32
    lattice64 = bounding_lattice(V, (4, 4, 4), 0.05)
    np.testing.assert_allclose(moved, _deform(ffd_precompute(V, lattice64), _twist(lattice64, 1.0)[1]), atol=2e-5)


def test_bad_input():
    V, F = _arm()
    lattice = bounding_lattice(V, (4, 4, 4))
    with pytest.raises(ValueError, match="origin"):
        Lattice(np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="axes"):
        Lattice(np.zeros(3), np.eye(3)[:2])
    with pytest.raises(ValueError, match="counts"):
        Lattice(np.zeros(3), np.eye(3), (1, 4, 4))
    with pytest.raises(ValueError, match="counts"):
        Lattice(np.zeros(3), np.eye(3), (4, 4))
    with pytest.raises(ValueError, match="padding"):
        bounding_lattice(V, padding=-0.1)
    with pytest.raises(ValueError, match="V: expected shape"):
        ffd_weights(V[:, :2], lattice)
    with pytest.raises(ValueError, match="outside the lattice"):
        ffd_weights(V + np.array([0.01, 0.0, 0.0]), lattice)
    with pytest.raises((eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError), match="outside the lattice"):
        jax.block_until_ready(jax.jit(lattice_coordinates)(V + np.array([0.01, 0.0, 0.0]), lattice))
    flat = np.c_[V[:, :2], np.zeros(len(V))]
    with pytest.raises(ValueError, match="degenerate"):
        ffd_weights(flat, bounding_lattice(flat))
    assert ffd_weights(flat, bounding_lattice(flat, padding=0.1)).shape == (len(V), 64)
    W = ffd_weights(V, lattice)
    with pytest.raises(ValueError, match="P: expected shape"):
        blend_positions(W, jnp.zeros((63, 3)))
    with pytest.raises(ValueError, match="weights"):
        blend_positions(W[0], jnp.zeros((64, 3)))
    with pytest.raises(ValueError, match="key_motors"):
        motor_field_solve(ffd_precompute(V, lattice), identity_motors(63))
    with pytest.raises(ValueError, match="axis"):
        twist_lattice(lattice, 1.0, axis=3)
    with pytest.raises(ValueError, match="F"):
        distortion(V, F + len(V), V)
    with pytest.raises(ValueError, match="F"):
        distortion(V, F.astype(np.float64), V)
    with pytest.raises(ValueError, match="V1"):
        distortion(V, F, V[:-1])
