"""Harmonic-coordinate cages (deformation paper sec. VI): barycentric coordinates on a one-tet cage (closed
form), partition of unity, linear precision, interpolation and non-negativity on a cube cage and a tube
cage around the built-in arm, affine and rigid invariance of the positional and motor cages, locality,
the paper's origin binding, jit / vmap / gradients by finite differences, float32, bad input."""

from __future__ import annotations

import sys

import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import deform
import jaxcga as cga
from deform import (
    blend_positions,
    cage_precompute,
    harmonic_coordinates,
    identity_motors,
    motor_about,
    motor_field_precompute,
    motor_field_solve,
    tube_cage,
)
from tests.shared import check_gradient

ARM_V = np.asarray(deform.default_arm().mesh.V, np.float64)
BOX = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
BOX_V, BOX_F = np.asarray(BOX.vertices), np.asarray(BOX.faces)
TET_V = np.array([[0.1, -0.2, 0.0], [1.3, 0.1, -0.1], [0.2, 1.1, 0.3], [0.0, 0.2, 0.9]])
TET_F = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])


TUBE_V, TUBE_F = tube_cage(ARM_V, axis=0)
BOX_POINTS = np.random.default_rng(0).uniform(-0.95, 0.95, (300, 3))
CAGES = {
    "cube": (BOX_V, BOX_F, np.concatenate([BOX_POINTS, BOX_V])),
    "arm": (TUBE_V, TUBE_F, np.concatenate([ARM_V, TUBE_V])),
}
BOUND = {name: cage_precompute(V, cage_V, cage_F) for name, (cage_V, cage_F, V) in CAGES.items()}


def _barycentric(P, X):
    """Closed-form barycentric coordinates of points X in the tetrahedron P: [P^T; 1] l = [x; 1]."""
    A = np.vstack([P.T, np.ones(4)])
    return np.linalg.solve(A, np.vstack([X.T, np.ones(len(X))])).T


def test_single_tetrahedron_cage_gives_barycentric_coordinates():
    TV, TT, H = harmonic_coordinates(TET_V, TET_F, max_tet_volume=1e-3)
    assert len(TV) > 50  # interior nodes exist, so the solve is tested
    np.testing.assert_allclose(H, _barycentric(TET_V, TV), atol=1e-10)
    X = np.random.default_rng(1).dirichlet(np.ones(4), 200) @ TET_V
    cage = cage_precompute(X, TET_V, TET_F, max_tet_volume=1e-3)
    np.testing.assert_allclose(cage.weights, _barycentric(TET_V, X), atol=1e-10)


@pytest.mark.parametrize("name", ["cube", "arm"])
def test_partition_of_unity_linear_precision_and_interpolation(name):
    cage_V, _, V = CAGES[name]
    coords = np.asarray(BOUND[name].weights)
    np.testing.assert_allclose(coords.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(coords @ cage_V, V, atol=1e-10)
    c = len(cage_V)
    np.testing.assert_allclose(coords[-c:], np.eye(c), atol=1e-12)  # the cage vertices were appended to V


@pytest.mark.parametrize("name", ["cube", "arm"])
def test_coordinates_are_nonnegative_on_well_shaped_cages(name):
    # piecewise-linear harmonic functions keep the maximum principle only on well-shaped tets: measured
    # minimum 0 on both cages here; a convex hull of the arm (848 vertices, thin faces) gives about -0.4
    cage_V, cage_F, _ = CAGES[name]
    _, _, H = harmonic_coordinates(cage_V, cage_F)
    assert H.min() >= -1e-12 and H.max() <= 1.0 + 1e-12
    assert BOUND[name].weights.min() >= -1e-12


def test_inward_oriented_cage_gives_the_same_coordinates():
    flipped = cage_precompute(BOX_POINTS, BOX_V, BOX_F[:, ::-1])
    np.testing.assert_allclose(flipped.weights, BOUND["cube"].weights[: len(BOX_POINTS)], atol=1e-12)


def test_points_on_the_cage_up_to_round_off_take_the_face_coordinates():
    on_face = np.array([[1.0, 0.3, -0.2], [0.1, -1.0, 0.7]])
    normals = np.array([[1.0, 0, 0], [0, -1.0, 0]])
    exact = cage_precompute(on_face, BOX_V, BOX_F).weights
    outside = cage_precompute(on_face + 1e-13 * normals, BOX_V, BOX_F).weights
    np.testing.assert_allclose(outside, exact, atol=1e-12)
    np.testing.assert_allclose(np.asarray(outside) @ BOX_V, on_face, atol=1e-12)


@pytest.mark.parametrize("name", ["cube", "arm"])
def test_affine_map_of_the_cage_moves_the_mesh_by_it(name):
    cage_V, _, V = CAGES[name]
    rng = np.random.default_rng(2)
    A, b = np.eye(3) + 0.3 * rng.normal(size=(3, 3)), rng.normal(size=3)
    np.testing.assert_allclose(blend_positions(BOUND[name].weights, cage_V @ A.T + b), V @ A.T + b, atol=1e-10)


def _random_motor(rng):
    logs = rng.normal(size=6)
    return cga.exp_motor(cga.Multivector(jnp.asarray(logs), cga.MOTOR_GENERATOR))


@pytest.mark.parametrize("name", ["cube", "arm"])
def test_same_motor_on_every_cage_vertex_moves_the_mesh_rigidly(name):
    cage = BOUND[name]
    V = CAGES[name][2]
    motor_deform = jax.jit(motor_field_solve)
    np.testing.assert_allclose(motor_deform(cage, identity_motors(cage.num_keys)), V, atol=1e-12)
    G = _random_motor(np.random.default_rng(3))
    motors = cga.Multivector(jnp.broadcast_to(G.values, (cage.num_keys, G.values.shape[-1])), G.blades)
    np.testing.assert_allclose(motor_deform(cage, motors), cga.apply_to_points(G, jnp.asarray(V)), atol=1e-10)


@pytest.mark.slow
def test_translator_cage_motors_equal_the_positional_cage_in_both_bindings():
    cage = BOUND["arm"]
    d = np.random.default_rng(4).normal(scale=0.05, size=TUBE_V.shape)
    positional = blend_positions(cage.weights, TUBE_V + d)
    np.testing.assert_allclose(motor_field_solve(cage, cga.translator(jnp.asarray(d))), positional, atol=1e-10)
    # the paper's p_i = M_i o ~M_i: rest motors T_{P_j} carry the origin to the vertices
    paper = motor_field_precompute(
        jnp.asarray(CAGES["arm"][2]), cage.weights, rest_motors=cga.translator(jnp.asarray(TUBE_V))
    )
    np.testing.assert_allclose(paper.bound, 0.0, atol=1e-12)
    np.testing.assert_allclose(
        motor_field_solve(paper, cga.translator(jnp.asarray(TUBE_V + d))), positional, atol=1e-10
    )


@pytest.mark.slow
def test_local_motor_moves_points_near_its_cage_vertex_most():
    cage, V = BOUND["arm"], ARM_V
    j = 3 * 8 + 2  # a vertex of the middle ring
    turn = motor_about(jnp.asarray(TUBE_V[j]), cga.rotor(jnp.array([0.0, 0.0, 1.0]), 0.6), jnp.array([0.0, 0.05, 0.0]))
    values = identity_motors(len(TUBE_V)).values.at[j].set(turn.values)
    moved = np.asarray(motor_field_solve(cage, cga.Multivector(values, turn.blades)))[: len(V)]
    displacement = np.linalg.norm(moved - V, axis=1)
    distance = np.linalg.norm(V - TUBE_V[j], axis=1)
    near, far = distance < np.quantile(distance, 0.05), distance > np.quantile(distance, 0.5)
    assert displacement[near].mean() > 10 * displacement[far].mean()
    assert distance[np.argmax(displacement)] < np.quantile(distance, 0.05)


@pytest.mark.slow
def test_jit_and_vmap_over_batches_of_cage_positions_and_motors():
    cage = BOUND["cube"]
    rng = np.random.default_rng(5)
    P = jnp.asarray(BOX_V + rng.normal(scale=0.1, size=(4, 8, 3)))
    expected = np.stack([np.asarray(cage.weights) @ np.asarray(p) for p in P])
    np.testing.assert_allclose(blend_positions(cage.weights, P), expected, atol=1e-12)
    np.testing.assert_allclose(jax.jit(blend_positions)(cage.weights, P), expected, atol=1e-12)
    np.testing.assert_allclose(jax.vmap(lambda p: blend_positions(cage.weights, p))(P), expected, atol=1e-12)
    logs = jnp.asarray(rng.normal(scale=0.3, size=(4, 8, 6)))
    motors = cga.exp_motor(cga.Multivector(logs, cga.MOTOR_GENERATOR))
    deform_one = jax.jit(motor_field_solve)
    one_by_one = np.stack([deform_one(cage, cga.Multivector(m, motors.blades)) for m in motors.values])
    np.testing.assert_allclose(deform_one(cage, motors), one_by_one, atol=1e-12)  # batch axes lead
    vmapped = jax.jit(jax.vmap(motor_field_solve, in_axes=(None, 0)))
    np.testing.assert_allclose(vmapped(cage, motors), one_by_one, atol=1e-12)


@pytest.mark.slow
def test_gradients_against_finite_differences():
    cage = cage_precompute(BOX_POINTS[:20], BOX_V, BOX_F)
    target = jnp.asarray(BOX_POINTS[:20] + 0.1)
    check_gradient(
        jax.jit(lambda p: jnp.sum(jnp.sin(blend_positions(cage.weights, p.reshape(8, 3)) - target) ** 2)),
        jnp.asarray(BOX_V).ravel() * 1.1,
    )

    @jax.jit
    def motor_loss(logs):
        motors = cga.exp_motor(cga.Multivector(logs.reshape(8, 6), cga.MOTOR_GENERATOR))
        return jnp.sum((motor_field_solve(cage, motors) - target) ** 2)

    check_gradient(motor_loss, jnp.asarray(np.random.default_rng(6).normal(scale=0.3, size=48)))


def test_float32_cage():
    cage = jax.tree.map(lambda a: a.astype(jnp.float32), BOUND["arm"])
    P = jnp.asarray(TUBE_V * 1.1, jnp.float32)
    assert blend_positions(cage.weights, P).dtype == jnp.float32
    # float32 on every backend: the library's products are at the highest precision, not a GPU's default TF32
    np.testing.assert_allclose(
        blend_positions(cage.weights, P), blend_positions(BOUND["arm"].weights, TUBE_V * 1.1), atol=1e-5
    )
    motors = cga.exp_motor(cga.Multivector(jnp.full((len(TUBE_V), 6), 0.1, jnp.float32), cga.MOTOR_GENERATOR))
    motor_deform = jax.jit(motor_field_solve)
    out = motor_deform(cage, motors)
    assert out.dtype == jnp.float32
    reference = motor_deform(BOUND["arm"], jax.tree.map(lambda a: a.astype(jnp.float64), motors))
    np.testing.assert_allclose(out, reference, atol=1e-5)


def test_bad_input():
    with pytest.raises(ValueError, match="cage_F: the cage must be a closed"):
        cage_precompute(BOX_POINTS, BOX_V, BOX_F[:-1])
    with pytest.raises(ValueError, match="V: 1 vertices lie outside the cage, the first is vertex 2"):
        cage_precompute(np.array([[0.0, 0, 0], [0.5, 0.5, 0.5], [1.5, 0, 0]]), BOX_V, BOX_F)
    with pytest.raises(ValueError, match=r"cage_V: expected finite positions of shape \(c, 3\)"):
        cage_precompute(BOX_POINTS, BOX_V[:, :2], BOX_F)
    with pytest.raises(ValueError, match=r"V: expected finite positions of shape \(n, 3\)"):
        cage_precompute(BOX_POINTS[:, :2], BOX_V, BOX_F)
    with pytest.raises(ValueError, match="cage_F: expected integer faces"):
        cage_precompute(BOX_POINTS, BOX_V, BOX_F.astype(float))
    with pytest.raises(ValueError, match="max_tet_volume"):
        cage_precompute(BOX_POINTS, BOX_V, BOX_F, max_tet_volume=2.0)
    with pytest.raises(ValueError, match="subdivisions"):
        cage_precompute(BOX_POINTS, BOX_V, BOX_F, subdivisions=-1)
    with pytest.raises(ValueError, match="cage_V: vertex 8 is on no face"):
        cage_precompute(BOX_POINTS, np.concatenate([BOX_V, [[0.0, 0, 0]]]), BOX_F)
    cage = BOUND["cube"]
    with pytest.raises(ValueError, match=r"P: expected shape \(\.\.\., 8, 3\)"):
        blend_positions(cage.weights, jnp.zeros((7, 3)))
    with pytest.raises(ValueError, match="key_motors"):
        motor_field_solve(cage, identity_motors(7))


def test_tube_cage_is_closed_encloses_the_mesh_and_follows_the_axis():
    cage_V, cage_F = tube_cage(ARM_V, segments=4, sides=6)
    mesh = trimesh.Trimesh(cage_V, cage_F, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    assert cage_V.shape == (5 * 6 + 2, 3)
    assert np.all(np.asarray(igl.winding_number(cage_V, cage_F, ARM_V)) > 0.5)
    along_z, _ = tube_cage(ARM_V[:, [1, 2, 0]], axis=2)  # the same mesh turned: the rings follow z
    np.testing.assert_allclose(
        np.sort(np.unique(along_z[:, 2].round(12))),
        np.sort(np.unique(tube_cage(ARM_V, axis=0)[0][:, 0].round(12))),
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="axis"):
        tube_cage(ARM_V, axis=3)
    with pytest.raises(ValueError, match="segments"):
        tube_cage(ARM_V, sides=2)


def test_tetgen_failure_on_a_subdivided_cylinder_cage_falls_back_to_fewer_subdivisions():
    # TetGen's boundary recovery failed on this cage subdivided 3 times ("finddirection"); the coordinates
    # are still computed (on a coarser surface) and keep linear precision
    cylinder = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=16).subdivide().subdivide()
    V = np.asarray(cylinder.vertices)
    cage_V, cage_F = tube_cage(V)
    cage = cage_precompute(V, cage_V, cage_F, subdivisions=3)
    np.testing.assert_allclose(np.asarray(cage.weights) @ cage_V, V, atol=1e-10)


def test_without_tetgen_cages_use_ftetwild(monkeypatch):
    # TetGen is an optional extra: with its import blocked, the interior is fTetWild's tets with their boundary
    # nodes moved onto the cage, and the coordinates keep their defining properties
    monkeypatch.setitem(sys.modules, "tetgen", None)
    TV, TT, H = harmonic_coordinates(TET_V, TET_F, max_tet_volume=1e-3)
    assert len(TT) > 50
    np.testing.assert_allclose(H, _barycentric(TET_V, TV), atol=1e-10)  # linear data: exact on any tets
    for name, mean_difference in (("cube", 0.01), ("arm", 0.02)):
        cage_V, cage_F, V = CAGES[name]
        coords = np.asarray(cage_precompute(V, cage_V, cage_F).weights)
        np.testing.assert_allclose(coords.sum(axis=1), 1.0, atol=1e-12)
        np.testing.assert_allclose(coords @ cage_V, V, atol=1e-10)
        c = len(cage_V)
        np.testing.assert_allclose(coords[-c:], np.eye(c), atol=1e-12)
        # another discretization of the same harmonic functions: close to TetGen's on average
        assert np.abs(coords - np.asarray(BOUND[name].weights)).mean() < mean_difference
