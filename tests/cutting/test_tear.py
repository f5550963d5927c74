"""Tearing (Algorithm 2) on real models: area kept by a closed slit, tear points on their planes, a
slit whose two sides part by the opening, weights, manifold result with one new boundary loop,
skinning after the tear, successive samples, posed tears, gradients by finite differences, bad input."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import example, given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

import cutting
import deform
import jaxcga as cga
from tests.cutting.tools import (
    DATA,
    check_torn,
    load_models,
    mean_edge,
    random_surface_point,
    rigid_mesh,
    scalpel_of,
    scalpels_over,
)
from tests.cutting.tools import area as _area
from tests.cutting.tools import diagonal as _diagonal
from tests.cutting.tools import posed as posed_arm
from tests.shared import check_gradient, grid

MODELS = load_models(weld=True)
ARM = deform.default_arm()


@settings(max_examples=15, deadline=None)
@given(
    name=st.sampled_from(sorted(MODELS)),
    seed=st.integers(0, 10_000),
    samples=st.integers(2, 4),
    steps=st.floats(1.5, 4.0),
    predicates=st.sampled_from(cutting.PREDICATES),
)
# its first step passes through the last sample's face: the tear ends before it, where the path would cross itself
@example(name="Arm5", seed=74, samples=3, steps=3.96875, predicates="euclidean")
def test_tear_invariants_on_real_models(name, seed, samples, steps, predicates):
    mesh = MODELS[name].mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    rng = np.random.default_rng(seed)
    scalpels = scalpels_over(V, F, rng.integers(len(F)), rng.normal(size=3), samples, steps * mean_edge(V, F))
    torn, path = cutting.tear(mesh, scalpels, predicates=predicates, return_topology=True)
    check_torn(mesh, scalpels, torn, path)


def test_the_tear_follows_the_swept_surface_where_the_plane_of_a_step_would_not():
    """Arm5 seed 74: the curve of the first step's plane runs through the last sample's face (the blade turns a
    lot over the step). Sampled finely, the tear follows the surface the blade swept: one stretch over the whole
    path, each face once, its points near the swept surface (``check_torn``)."""
    mesh = MODELS["Arm5"].mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    rng = np.random.default_rng(74)
    scalpels = scalpels_over(V, F, rng.integers(len(F)), rng.normal(size=3), 3, 3.96875 * mean_edge(V, F))
    torn, path = cutting.tear(mesh, scalpels, return_topology=True)
    check_torn(mesh, scalpels, torn, path)
    assert path.sample_times[path.stretches].tolist() == [[0.0, 2.0]]
    assert len(path.sample_times) > 3
    assert len(np.unique(path.faces)) == len(path.faces)


def test_opening_parts_the_two_sides_along_the_plane_normal():
    mesh = MODELS["Arm5"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    scalpels = scalpels_over(V, F, 2000, [0.0, 1.0, 0.0], 3, 3 * mean_edge(V, F))
    torn, path = cutting.tear(mesh, scalpels, opening=0.4, return_topology=True)
    q, n = len(path.t), len(V)
    left, right = np.asarray(torn.V)[n + 2 : n + 2 + q], np.asarray(torn.V)[n + 2 + q :]
    np.testing.assert_allclose(np.linalg.norm(left - right, axis=1), 0.4, rtol=1e-6)
    np.testing.assert_allclose(left - right, 0.4 * path.planes[path.step, :3], atol=1e-6)
    # the tips stay where the scalpel met the surface
    np.testing.assert_allclose(np.asarray(torn.V)[[n, n + 1]], path.sample_points[[0, -1]], atol=1e-6)


@pytest.mark.parametrize("method", deform.METHODS)
def test_skinning_the_torn_mesh_gives_the_original_at_original_vertices(method):
    model = ARM
    V, F = np.asarray(model.mesh.V), np.asarray(model.mesh.F)
    scalpels = scalpels_over(V, F, 3000, [1.0, 0.0, 0.0], 3, 3 * mean_edge(V, F))
    torn = cutting.tear(model.mesh, scalpels, opening=0.01)
    pose = deform.sample_pose(model, 0.7, method)
    original = np.asarray(deform.skin_pose(model, pose, method))
    posed = np.asarray(deform.skin_pose(deform.RiggedModel(torn, model.skeleton), pose, method))
    np.testing.assert_allclose(posed[: len(V)], original, atol=1e-12)
    assert np.all(np.isfinite(posed))


def test_successive_samples_make_one_tear_along_the_path():
    mesh = MODELS["3Cylinder4bones"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    step = 2 * mean_edge(V, F)
    short = cutting.tear_topology(V, F, scalpels_over(V, F, 100, [0.0, 1.0, 0.0], 2, step))
    long = cutting.tear_topology(V, F, scalpels_over(V, F, 100, [0.0, 1.0, 0.0], 5, step))
    assert len(long.t) > len(short.t)
    assert set(np.unique(long.step)) > {0}
    # consecutive path faces share the edge of the tear point between them
    for j in range(len(long.t)):
        shared = set(F[long.faces[j]]) & set(F[long.faces[j + 1]])
        assert set(long.crossing[j]) == shared


@pytest.mark.parametrize("method", ["lbs", "cga"])
def test_tear_in_a_pose_reproduces_the_tear_when_posed_again(method):
    model = ARM
    local, joints, posed = posed_arm(model, 0.9)
    F = np.asarray(model.mesh.F)
    scalpels = scalpels_over(posed, F, 5000, [0.0, 1.0, 1.0], 3, 3 * mean_edge(posed, F))
    torn, path = cutting.tear(model.mesh, scalpels, opening=0.004, joint_matrices=joints, return_topology=True)
    pose = local if method == "lbs" else cga.matrix_to_similitude(local)
    again = np.asarray(deform.skin_pose(deform.RiggedModel(torn, model.skeleton), pose, method))
    n, q = len(posed), len(path.t)
    normals = path.planes[path.step, :3]
    expected = np.concatenate(
        [path.sample_points[[0, -1]], path.points + 0.002 * normals, path.points - 0.002 * normals]
    )
    np.testing.assert_allclose(again[n:], expected, atol=1e-9 * _diagonal(posed))
    np.testing.assert_allclose(again[:n], posed, atol=1e-12)
    later = deform.skin_pose(deform.RiggedModel(torn, model.skeleton), deform.sample_pose(model, 1.6, "lbs"), "lbs")
    assert np.all(np.isfinite(np.asarray(later))) and q > 0


@pytest.mark.slow
def test_new_vertex_positions_are_differentiable_in_the_scalpel():
    mesh = MODELS["3Cylinder4bones"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    scalpels = scalpels_over(V, F, 100, [0.0, 1.0, 0.0], 3, 2 * mean_edge(V, F))
    path = cutting.tear_topology(V, F, scalpels)
    tips, left, right = cutting.tear_positions(V, path, scalpels, opening=0.1)
    np.testing.assert_allclose(left - 0.05 * path.planes[path.step, :3], path.points, atol=1e-12)
    np.testing.assert_allclose(tips, path.sample_points[[0, -1]], atol=1e-12)
    shape = scalpels.handle.shape

    def loss(params):
        scalpel = cutting.Scalpel(params[:-1].reshape(2, *shape)[0], params[:-1].reshape(2, *shape)[1])
        tips, left, right = cutting.tear_positions(V, path, scalpel, opening=params[-1])
        return jnp.sum(jnp.sin(tips)) + jnp.sum(left**2) + jnp.sum(jnp.cos(right))

    params = jnp.concatenate(
        [jnp.asarray(scalpels.handle).ravel(), jnp.asarray(scalpels.tip).ravel(), jnp.array([0.1])]
    )
    check_gradient(loss, params)
    with pytest.raises(ValueError, match="scalpel: expected handle and tip ends of shape"):
        cutting.tear_positions(V, path, cutting.Scalpel(scalpels.handle[:2], scalpels.tip[:2]))


def test_bad_input():
    mesh = ARM.mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    good = scalpels_over(V, F, 3000, [1.0, 0.0, 0.0], 2, 3 * mean_edge(V, F))
    far = cutting.Scalpel(good.handle + np.array([0.0, 0.0, 100.0]), good.tip + np.array([0.0, 0.0, 100.0]))
    with pytest.raises(ValueError, match="scalpel: the scalpel never crosses the surface: none of its 2 samples'"):
        cutting.tear(mesh, far)
    with pytest.raises(ValueError, match="scalpel: expected handle and tip ends"):
        cutting.tear(mesh, cutting.Scalpel(good.handle[0], good.tip[0]))
    with pytest.raises(ValueError, match="scalpel: expected a cutting.Scalpel"):
        cutting.tear(mesh, np.stack([good.handle, good.tip], axis=1))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="finite"):
        cutting.tear(mesh, cutting.Scalpel(np.full((2, 3), np.nan), np.full((2, 3), np.nan)))
    with pytest.raises(ValueError, match="equal handle and tip"):
        cutting.tear(mesh, cutting.Scalpel(good.handle, good.handle))
    with pytest.raises(ValueError, match="opening"):
        cutting.tear(mesh, good, opening=-1.0)
    with pytest.raises(ValueError, match="side_weight"):
        cutting.tear(mesh, good, side_weight=2.0)
    with pytest.raises(ValueError, match="predicates"):
        cutting.tear(mesh, good, predicates="exact")
    with pytest.raises(ValueError, match="joint_matrices"):
        cutting.tear(mesh, good, joint_matrices=np.eye(4))


def test_a_tear_along_a_row_of_vertices_makes_no_slivers():
    """The tear plane x = 0.5 holds a row of grid vertices: it is moved off them (gentle perturbation)."""
    V, F = grid()
    mesh = rigid_mesh(V, F)
    scalpels = scalpel_of([[[0.5, 0.23, 1.0], [0.5, 0.23, -1.0]], [[0.5, 0.77, 1.0], [0.5, 0.77, -1.0]]])
    torn, path = cutting.tear(mesh, scalpels, return_topology=True)
    assert abs(path.shift[0]) > 0
    Vt, Ft = np.asarray(torn.V), np.asarray(torn.F)
    # no sliver: every piece keeps a share of its face (a tear point stays 2% of an edge from its ends)
    assert _area(Vt, Ft).min() > 1e-4 * 0.005
    assert abs(_area(Vt, Ft).sum() - 1.0) <= 1e-12
    n, d = path.planes[0, :3], path.planes[0, 3]
    assert np.all(np.abs(path.points @ n - d) <= 1e-12)
    assert np.all(np.abs(path.points[:, 0] - 0.5) <= 0.02 + 1e-12)  # moved by 5% steps of a 0.1 edge


def test_tear_positions_follow_a_perturbed_plane():
    """With the plane moved off a row of vertices, the differentiable positions still reproduce the
    tear points (the recorded shift is along the oriented normal)."""
    V, F = grid()
    segments = np.array([[[0.5, 0.23, 1.0], [0.5, 0.23, -1.0]], [[0.5, 0.77, 1.0], [0.5, 0.77, -1.0]]])
    path = cutting.tear_topology(V, F, scalpel_of(segments))
    assert path.shift[0] != 0
    np.testing.assert_allclose(
        path.planes[0, 3], path.planes[0, :3] @ path.sample_points[0] + path.shift[0], atol=1e-12
    )
    _, left, _ = cutting.tear_positions(V, path, scalpel_of(segments))
    np.testing.assert_allclose(left, path.points, atol=1e-9)
    # the mirrored scalpel reverses the path's direction, and so the orientation of its plane
    flipped = cutting.tear_topology(V, F, scalpel_of(segments[::-1]))
    _, left, _ = cutting.tear_positions(V, flipped, scalpel_of(segments[::-1]))
    np.testing.assert_allclose(left, flipped.points, atol=1e-9)


def test_a_blade_moved_by_two_motors_gives_the_same_tear_as_its_segments():
    mesh = MODELS["3Cylinder4bones"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    segments = scalpels_over(V, F, 100, [0.0, 1.0, 0.0], 2, 2 * mean_edge(V, F))
    blade = np.stack([segments.handle[0], segments.tip[0]])
    # the motor T R taking the blade onto the second sample: R turns its direction, T its midpoint
    moved = np.stack([segments.handle[1], segments.tip[1]])
    axis = np.cross(blade[1] - blade[0], moved[1] - moved[0])
    angle = np.arctan2(np.linalg.norm(axis), np.dot(blade[1] - blade[0], moved[1] - moved[0]))
    rotation = cga.rotor(jnp.asarray(axis / np.linalg.norm(axis)), angle)
    turned_middle = np.asarray(cga.apply_to_points(rotation, jnp.asarray(blade.mean(axis=0))))
    second = cga.motor(rotation, jnp.asarray(moved.mean(axis=0) - turned_middle))
    first = cga.motor(cga.rotor(jnp.array([0.0, 0.0, 1.0]), 0.0), jnp.zeros(3))
    motors = cga.Multivector(jnp.stack([first.values, second.values]), first.blades)
    samples = cutting.scalpel_path(blade, motors)
    np.testing.assert_allclose(np.stack([samples.handle[0], samples.tip[0]]), blade, atol=1e-12)
    np.testing.assert_allclose(samples.tip[1] - samples.handle[1], moved[1] - moved[0], atol=1e-9)
    np.testing.assert_allclose(0.5 * (samples.handle[1] + samples.tip[1]), moved.mean(axis=0), atol=1e-9)
    np.testing.assert_allclose(
        cutting.tear_topology(V, F, samples).points, cutting.tear_topology(V, F, segments).points, atol=1e-9
    )
    with pytest.raises(ValueError, match="motors"):
        cutting.scalpel_path(blade, first)


def _open_plate():
    """The top of a subdivided 2 x 2 box (z = 0.05): an open square plate of 32 triangles, as a SkinnedMesh."""
    plate = trimesh.creation.box(extents=(2, 2, 0.1)).subdivide()
    V, F = np.asarray(plate.vertices), np.asarray(plate.faces)
    top = F[V[F].mean(axis=1)[:, 2] > 0.04]
    used, F = np.unique(top, return_inverse=True)
    return rigid_mesh(V[used], F.reshape(-1, 3))


def test_a_blade_that_leaves_the_surface_tears_where_it_was_on_it():
    """A blade moving off an open plate tears up to its boundary edge (within a quarter of an edge of the faces
    there); one whose samples both miss the plate but whose swept surface crosses it tears across it; one that
    crosses a gap between two plates tears both, one stretch each."""
    mesh = _open_plate()
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    edge = mean_edge(V, F)
    off = scalpel_of([[[0.1, 0.13, 1.0], [0.1, 0.13, 0.0]], [[3.0, 0.13, 1.0], [3.0, 0.13, 0.0]]])
    torn, path = cutting.tear(mesh, off, return_topology=True)
    check_torn(mesh, off, torn, path)
    assert len(path.stretches) == 1 and 1.0 - 0.25 * edge <= path.sample_points[path.stretches[0, 1], 0] < 1.0
    across = scalpel_of([[[-3.0, 0.13, 1.0], [-3.0, 0.13, 0.0]], [[3.0, 0.13, 1.0], [3.0, 0.13, 0.0]]])
    torn, path = cutting.tear(mesh, across, return_topology=True)
    check_torn(mesh, across, torn, path)
    assert len(path.stretches) == 1
    np.testing.assert_allclose(np.abs(path.sample_points[path.stretches[0], 0]), 1.0, atol=0.25 * edge)
    # two plates side by side with a gap: x in [-1, 1] and [1.5, 3.5]
    twin = rigid_mesh(np.concatenate([V, V + [2.5, 0.0, 0.0]]), np.concatenate([F, F + len(V)]))
    wide = scalpel_of([[[0.1, 0.13, 1.0], [0.1, 0.13, 0.0]], [[3.0, 0.13, 1.0], [3.0, 0.13, 0.0]]])
    torn, path = cutting.tear(twin, wide, return_topology=True)
    check_torn(twin, wide, torn, path)
    assert len(path.stretches) == 2
    ends = path.sample_points[path.stretches, 0]
    assert ends[0, 1] > 1.0 - 0.25 * edge and ends[1, 0] < 1.5 + 0.25 * edge


def test_a_short_blade_motion_inside_one_face_makes_a_slit_there():
    """Both samples in one face of the grid: a slit with its middle point duplicated, 7 triangles in place of the
    face; the slit's two sides part by the opening along the face normal x the slit's direction."""
    V, F = grid()
    mesh = rigid_mesh(V, F)
    scalpel = scalpel_of([[[0.52, 0.51, 1.0], [0.52, 0.51, -1.0]], [[0.57, 0.53, 1.0], [0.57, 0.53, -1.0]]])
    torn, path = cutting.tear(mesh, scalpel, return_topology=True)
    check_torn(mesh, scalpel, torn, path)
    assert len(path.stretches) == 1 and list(path.inner) == [0] and len(path.t) == 0
    assert len(torn.F) == len(F) + 6
    torn, path = cutting.tear(mesh, scalpel, opening=0.01, return_topology=True)
    n = len(V)
    left, right = np.asarray(torn.V)[n + 2], np.asarray(torn.V)[n + 3]
    direction = np.array([0.05, 0.02, 0.0]) / np.linalg.norm([0.05, 0.02])
    np.testing.assert_allclose(left - right, 0.01 * np.cross([0.0, 0.0, 1.0], direction), atol=1e-12)
    np.testing.assert_allclose(0.5 * (left + right), [0.545, 0.52, 0.0], atol=1e-12)
    tips, left_copies, _ = cutting.tear_positions(V, path, scalpel, opening=0.01)
    np.testing.assert_allclose(np.asarray(left_copies)[0], left, atol=1e-12)
    np.testing.assert_allclose(np.asarray(tips), np.asarray(torn.V)[[n, n + 1]], atol=1e-12)


def test_a_sequence_of_scalpels_is_one_scalpel_of_their_samples():
    mesh = MODELS["3Cylinder4bones"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    scalpel = scalpels_over(V, F, 100, [0.0, 1.0, 0.0], 4, 2 * mean_edge(V, F))
    parts = [cutting.Scalpel(h, t) for h, t in zip(scalpel.handle, scalpel.tip)]
    whole = cutting.tear_topology(V, F, scalpel)
    joined = cutting.tear_topology(V, F, parts)
    np.testing.assert_array_equal(whole.edge_ids, joined.edge_ids)
    np.testing.assert_array_equal(whole.points, joined.points)
    mixed = [cutting.Scalpel(scalpel.handle[:2], scalpel.tip[:2]), *parts[2:]]
    np.testing.assert_array_equal(cutting.tear_topology(V, F, mixed).points, whole.points)
    _, left, _ = cutting.tear_positions(V, whole, parts)
    np.testing.assert_allclose(left, whole.points, atol=1e-9)
    with pytest.raises(ValueError, match="scalpel: expected a sequence of cutting.Scalpel"):
        cutting.tear_topology(V, F, [parts[0], np.zeros((2, 3))])  # type: ignore[list-item]
    with pytest.raises(ValueError, match=r"scalpel\[1\]: expected handle and tip ends of shape"):
        cutting.tear_topology(V, F, [parts[0], cutting.Scalpel(np.zeros((2, 2)), np.ones((2, 2)))])
    with pytest.raises(ValueError, match="k\\+1 >= 2"):
        cutting.tear_topology(V, F, parts[:1])


@pytest.mark.parametrize("name", ["CesiumMan", "Arm5"])
def test_tears_placed_on_the_skin_of_characters_all_succeed(name):
    """Issue 51's placement: a blade across the skin at a random surface point, moving 5% of the diagonal along it
    over 2 samples (and 1% or 20% over 2 to 5): every tear succeeds, follows the swept surface, leaves no sliver,
    and the torn character animates its original vertices where they were."""
    model = deform.load_model(DATA / f"{name}.glb", weld=True)
    mesh = model.mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    edges = cutting.mesh_edges(F)
    rng = np.random.default_rng(51)
    # any joint matrices: each joint turned and moved at random
    joints = np.tile(np.eye(4), (mesh.num_joints, 1, 1))
    # the legacy keyword keeps the seeded stream (scipy's signature names only rng)
    joints[:, :3, :3] = Rotation.random(mesh.num_joints, random_state=51).as_matrix()  # pyright: ignore[reportCallIssue]
    joints[:, :3, 3] = rng.normal(scale=0.1 * _diagonal(V), size=(mesh.num_joints, 3))

    def skin(m):  # linear blend skinning as the glTF specification writes it
        homogeneous = np.concatenate([np.asarray(m.V, np.float64), np.ones((len(m.V), 1))], axis=1)
        return np.einsum(
            "nk,nkij,nj->ni", np.asarray(m.W, np.float64), joints[np.asarray(m.J)][..., :3, :], homogeneous
        )

    posed = skin(mesh)
    for trial in range(30):
        face, _, _ = random_surface_point(V, F, rng)
        samples, span = (2, 0.05) if trial < 20 else (int(rng.integers(2, 6)), [0.01, 0.2][trial % 2])
        scalpel = scalpels_over(V, F, face, rng.normal(size=3), samples, span * _diagonal(V) / (samples - 1))
        torn, path = cutting.tear(mesh, scalpel, edges=edges, return_topology=True)
        check_torn(mesh, scalpel, torn, path)
        again = skin(torn)
        np.testing.assert_array_equal(again[: len(V)], posed)
        assert np.all(np.isfinite(again))


def test_positions_of_a_finely_sampled_tear_follow_the_scalpel():
    """On CesiumMan the blade turns with the body: the tear samples it between the scalpel's samples. The positions
    reproduce the topology's points, and their gradient with respect to the scalpel's handle ends (through the
    samples interpolated between them) matches central differences."""
    mesh = deform.load_model(DATA / "CesiumMan.glb", weld=True).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    scalpel = scalpels_over(V, F, 1000, [0.0, 1.0, 0.3], 3, 0.05 * _diagonal(V))
    path = cutting.tear_topology(V, F, scalpel)
    assert len(path.sample_times) > 3 and np.any(path.sample_times % 1 != 0)
    tips, left, right = cutting.tear_positions(V, path, scalpel)
    np.testing.assert_allclose(left, path.points, atol=1e-12)
    np.testing.assert_allclose(tips, path.sample_points[path.stretches.ravel()], atol=1e-12)
    tip = jnp.asarray(scalpel.tip)

    def loss(handle):
        tips, left, _ = cutting.tear_positions(V, path, cutting.Scalpel(handle.reshape(-1, 3), tip), opening=0.01)
        return jnp.sum(left**2) + jnp.sum(jnp.sin(tips))

    check_gradient(loss, jnp.asarray(scalpel.handle).ravel())


def _barely_crossing(case):
    """A mesh and a scalpel whose blade barely crosses it: ``still`` (it does not move), ``poke`` (it moves along
    itself, crossing the grid at its last sample only), ``thin`` (it moves 1% of an edge inside a face of 1.9
    degrees, as on a low-poly character's thin faces), ``sliver`` (it does not move, in a face of 0.06 degrees, face
    0, that holds no slit without a sliver piece)."""
    if case == "sliver":
        V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [0.5, 0.0005, 0.0]])
        blade = np.array([[0.5, 0.0002, 1.0], [0.5, 0.0002, -1.0]])
        return V, np.array([[0, 1, 4], [0, 4, 3], [4, 1, 2], [4, 2, 3]]), scalpel_of([blade, blade])
    V, F = grid()
    point = np.array([0.52, 0.51])
    if case == "thin":
        V[:, 1] *= 0.033
        point = np.array([0.55, 0.033 * 0.52])
    blade = np.array([[*point, 1.0], [*point, -1.0]])
    if case == "still":
        return V, F, scalpel_of([blade, blade])
    if case == "poke":
        return V, F, scalpel_of([blade + [0.0, 0.0, 1.5], blade])
    return V, F, scalpel_of([blade, blade + [0.001, 0.0, 0.0]])


@pytest.mark.parametrize("case", ["still", "poke", "thin", "sliver"])
def test_a_blade_that_barely_crosses_the_skin_makes_a_minimal_slit(case):
    """A blade that crosses the skin only momentarily, or along one thin face, tears it: a slit in the face it crossed,
    through its crossing, along its motion (the face's longest edge for a blade that does not move across the
    skin), of the shortest length in 5%, 10%, ... of that edge that leaves no sliver (in a neighbour of a face too
    thin to hold one); its tips as tear_positions gives them, differentiable in the scalpel."""
    V, F, scalpel = _barely_crossing(case)
    mesh = rigid_mesh(V, F)
    torn, path = cutting.tear(mesh, scalpel, return_topology=True)
    check_torn(mesh, scalpel, torn, path)
    assert len(path.stretches) == 1 and list(path.inner) == [0] and len(path.t) == 0
    first, last = path.stretches[0]
    face = path.sample_faces[first]
    assert path.sample_faces[last] == face and path.sample_times[first] == path.sample_times[last]
    corners = V[F[face]]
    sides = np.roll(corners, -1, axis=0) - corners
    longest = sides[np.argmax(np.linalg.norm(sides, axis=1))]
    tips = path.sample_points[[first, last]]
    if case == "sliver":  # in a neighbour of the sliver face, the slit's tips kept off its edges
        assert face in (1, 2) and np.all(path.sample_barycentric[[first, last]] >= 0.03 - 1e-12)
    # through the blade's crossing (a vertical blade: its x, y at the sample's time), but in a neighbour
    time = path.sample_times[first]
    crossing = (1 - time) * scalpel.handle[0] + time * scalpel.handle[1]
    if case != "sliver":
        np.testing.assert_allclose(tips.mean(axis=0)[:2], crossing[:2], atol=1e-12)
    direction = tips[1] - tips[0]
    length = np.linalg.norm(direction)
    if case == "thin":  # along its motion, x
        np.testing.assert_allclose(direction / length, [1.0, 0.0, 0.0], atol=1e-12)
    else:  # a blade that does not move across the skin: along the face's longest edge
        assert abs(direction @ longest) == pytest.approx(length * np.linalg.norm(longest), rel=1e-12)
    # 5% of the edge in the thin face would leave a piece under the sliver rule's angle there
    fraction = 0.1 if case == "thin" else 0.05
    assert length == pytest.approx(fraction * np.linalg.norm(longest), rel=1e-12)
    n = len(V)
    torn_tips, _, _ = cutting.tear_positions(V, path, scalpel)
    np.testing.assert_allclose(np.asarray(torn_tips), np.asarray(torn.V)[[n, n + 1]], atol=1e-12)

    def loss(params):
        moved = cutting.Scalpel(params.reshape(2, 2, 3)[0], params.reshape(2, 2, 3)[1])
        tips, left, right = cutting.tear_positions(V, path, moved, opening=0.01)
        return jnp.sum(jnp.sin(3.0 * tips)) + jnp.sum(left**2) + jnp.sum(jnp.cos(right))

    check_gradient(loss, jnp.concatenate([jnp.asarray(scalpel.handle).ravel(), jnp.asarray(scalpel.tip).ravel()]))
