"""Planar cut (Algorithm 1) on real models: area conservation, new vertices on the plane, weights,
manifold halves, skinning after the cut, capping (analytic volumes), posed cuts, gradients by
finite differences, both predicate families, and bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

import cutting
import deform
import jaxcga as cga
from tests.cutting.tools import area as _area
from tests.cutting.tools import consistency_problems, load_models, piece_quality, rigid_mesh
from tests.cutting.tools import diagonal as _diagonal
from tests.cutting.tools import posed as posed_arm
from tests.shared import check_gradient, load_character

MODELS = load_models(weld=False)
ARM = deform.default_arm()


def _random_plane(V, direction, offset):
    """A plane through the mesh: unit normal ``direction``, through the point at fraction ``offset``
    of the vertices' extent along it."""
    n = np.asarray(direction, np.float64)
    n /= np.linalg.norm(n)
    heights = np.asarray(V) @ n
    return cutting.Plane(n, heights.min() + offset * (heights.max() - heights.min()))


directions = st.tuples(*[st.floats(-1, 1) for _ in range(3)]).filter(lambda v: np.linalg.norm(v) > 0.1)


@pytest.mark.slow
@settings(max_examples=15, deadline=None)
@given(
    name=st.sampled_from(sorted(MODELS)),
    direction=directions,
    offset=st.floats(0.1, 0.9),
    predicates=st.sampled_from(cutting.PREDICATES),
)
def test_cut_invariants_on_real_models(name, direction, offset, predicates):
    mesh = MODELS[name].mesh
    plane = _random_plane(mesh.V, direction, offset)
    positive, negative = cutting.cut(mesh, plane, predicates=predicates)
    V = np.asarray(mesh.V)
    diagonal = _diagonal(V)
    # total area conserved
    areas = [_area(h.V, h.F) for h in (positive, negative)]
    total = _area(V, mesh.F).sum()
    assert abs(areas[0].sum() + areas[1].sum() - total) <= 1e-9 * total
    # no sliver: pieces of faces keep 1e-3 of the smallest face's area and angles of 1e-3 rad
    topology = cutting.cut_topology(V, mesh.F, plane, predicates=predicates)
    for half, keep in ((positive, topology.positive), (negative, topology.negative)):
        problems, _, _ = piece_quality(V, mesh.F, half.V, half.F, keep)
        assert not problems + consistency_problems(half, mesh, keep)
    # sides: the positive half's input vertices have n.x >= d, or were snapped onto the plane (distance
    # 0) because a crossing next to them would have left a sliver
    n, d = plane.normal, plane.distance
    for keep, sign in ((topology.positive, 1), (topology.negative, -1)):
        assert np.all(sign * topology.distances[keep[keep < len(V)]] >= 0)
    for half in (positive, negative):
        W = np.asarray(half.W)
        np.testing.assert_allclose(W.sum(axis=1)[len(V) :], 1.0, atol=1e-12)
        assert half.J.shape[1] == mesh.J.shape[1]
        assert np.all(np.asarray(half.J) < mesh.num_joints)
    # new vertices (not among the original positions) lie on the plane
    assert np.all(np.abs(topology.points @ n - d) <= 1e-9 * diagonal)
    assert np.all((topology.t > 0) & (topology.t < 1))
    # the differentiable positions follow the snapped topology
    np.testing.assert_allclose(
        np.asarray(cutting.cut_positions(V, topology, plane)), topology.points, rtol=0, atol=1e-12 * diagonal
    )


def _original_rows(half, V):
    """For each vertex of a half, the index of the identical original vertex (or -1)."""
    lookup = {tuple(v): i for i, v in enumerate(np.asarray(V).tolist())}
    return np.array([lookup.get(tuple(v), -1) for v in np.asarray(half.V).tolist()])


# one method in the fast suite, the others in the slow job
@pytest.mark.parametrize(
    "method", [m if m == "cga" else pytest.param(m, marks=pytest.mark.slow) for m in deform.METHODS]
)
def test_skinning_the_halves_gives_the_original_at_original_vertices(method):
    model = deform.default_arm()
    plane = _random_plane(model.mesh.V, [1.0, 0.3, 0.2], 0.55)
    pose = deform.sample_pose(model, 0.7, method)
    original = np.asarray(deform.skin_pose(model, pose, method))
    for half in cutting.cut(model.mesh, plane):
        rows = _original_rows(half, model.mesh.V)
        assert np.any(rows >= 0) and np.any(rows < 0)
        posed = np.asarray(deform.skin_pose(deform.RiggedModel(half, model.skeleton), pose, method))
        np.testing.assert_allclose(posed[rows >= 0], original[rows[rows >= 0]], atol=1e-12)
        assert np.all(np.isfinite(posed))


def test_halves_are_manifold_and_caps_close_them_with_the_right_volume():
    cylinder = trimesh.creation.cylinder(radius=1.0, height=4.0, sections=64)
    V, F = np.asarray(cylinder.vertices), np.asarray(cylinder.faces)
    mesh = rigid_mesh(V, F)
    for plane, lower in ((cutting.Plane([0.0, 0.0, 1.0], 0.5), 2.5), (cutting.Plane([0.0, 0.3, 1.0], 0.2), None)):
        positive, negative = cutting.cut(mesh, plane, cap=True)
        halves = [trimesh.Trimesh(np.asarray(h.V), np.asarray(h.F), process=False) for h in (positive, negative)]
        merged = [trimesh.Trimesh(np.asarray(h.V), np.asarray(h.F)) for h in (positive, negative)]
        for h in merged:
            assert h.is_watertight and h.is_winding_consistent and h.volume > 0
        assert abs(merged[0].volume + merged[1].volume - cylinder.volume) <= 1e-9 * cylinder.volume
        if lower is not None:  # a horizontal cut of the polygonal prism: exact prism volumes
            assert abs(merged[1].volume - cylinder.volume * lower / 4.0) <= 1e-9 * cylinder.volume
        # uncapped halves: open, and every edge shared by at most two faces
        for h in cutting.cut(mesh, plane):
            edges = trimesh.Trimesh(np.asarray(h.V), np.asarray(h.F)).edges_sorted
            _, counts = np.unique(edges, axis=0, return_counts=True)
            assert counts.max() == 2 and counts.min() == 1
        assert all(len(h.faces) for h in halves)


def test_capping_an_open_mesh_is_refused():
    mesh = MODELS["Arm5"].mesh  # Arm5 is open at the shoulder
    with pytest.raises(ValueError, match="not closed"):
        cutting.cut(mesh, _random_plane(mesh.V, [1.0, 0.0, 0.0], 0.5), cap=True)


def test_cap_of_the_builtin_arm():
    positive, negative = cutting.cut(ARM.mesh, _random_plane(ARM.mesh.V, [1.0, 0.1, 0.0], 0.5), cap=True)
    whole = trimesh.Trimesh(np.asarray(ARM.mesh.V), np.asarray(ARM.mesh.F))
    volumes = [trimesh.Trimesh(np.asarray(h.V), np.asarray(h.F)).volume for h in (positive, negative)]
    assert min(volumes) > 0
    assert abs(sum(volumes) - whole.volume) <= 1e-9 * whole.volume


def test_planes_through_vertices_and_along_edges_make_no_slivers():
    grid = trimesh.creation.box(extents=(2, 2, 2)).subdivide().subdivide()
    V, F = np.asarray(grid.vertices), np.asarray(grid.faces)
    for n, d in (([1.0, 0.0, 0.0], 0.0), ([1.0, 1.0, 0.0], 0.0), ([0.0, 0.0, 1.0], 0.5), ([1.0, 0.0, 0.0], 1e-12)):
        topology = cutting.cut_topology(V, F, cutting.Plane(n, d))
        for keep, faces in ((topology.positive, topology.positive_faces), (topology.negative, topology.negative_faces)):
            ext = np.concatenate([V, topology.points])[keep]
            assert _area(ext, faces).min() > 1e-6
            assert abs(_area(ext, faces).sum()) > 0
        total = _area(V, F).sum()
        pieces = sum(
            _area(np.concatenate([V, topology.points])[k], f).sum()
            for k, f in ((topology.positive, topology.positive_faces), (topology.negative, topology.negative_faces))
        )
        assert abs(pieces - total) <= 1e-12 * total


def test_ga_and_euclidean_predicates_agree():
    mesh = MODELS["Arm5"].mesh
    plane = _random_plane(mesh.V, [0.2, 1.0, 0.4], 0.4)
    a = cutting.cut_topology(mesh.V, mesh.F, plane, predicates="euclidean")
    b = cutting.cut_topology(mesh.V, mesh.F, plane, predicates="ga")
    np.testing.assert_array_equal(a.crossing, b.crossing)
    np.testing.assert_allclose(a.points, b.points, atol=1e-9 * _diagonal(mesh.V))
    # the plane as a jaxcga plane vector, and through a point
    c = cutting.cut_topology(
        mesh.V, mesh.F, cutting.Plane.from_multivector(cga.plane(jnp.asarray(plane.normal), plane.distance))
    )
    np.testing.assert_array_equal(a.positive_faces, c.positive_faces)
    point = plane.distance * plane.normal + np.cross(plane.normal, [0.3, -0.2, 0.5])  # on the plane
    through = cutting.Plane.through(point, 2.0 * plane.normal)
    np.testing.assert_allclose(through.distance, 2.0 * plane.distance, rtol=1e-12)
    np.testing.assert_array_equal(a.crossing, cutting.cut_topology(mesh.V, mesh.F, through).crossing)


@pytest.mark.parametrize("name", ["Arm5", "3Cylinder4bones", "RobotExpressive", "Fox"])
def test_both_predicate_families_make_the_same_cut(name):
    """Table 1's GA and Euclidean predicates cut the models the same way: the plane across the longest extent (the
    benchmark's) and random planes; the new points agree to rounding."""
    mesh = MODELS[name].mesh if name in MODELS else load_character(name, weld=False).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    rng = np.random.default_rng(52)
    longest = np.full(3, 0.1)
    longest[np.argmax(np.ptp(V, axis=0))] = 1.0
    planes = [_random_plane(V, longest, 0.5)]
    planes += [_random_plane(V, rng.normal(size=3), rng.uniform(0.2, 0.8)) for _ in range(6)]
    edges = cutting.mesh_edges(F)
    for plane in planes:
        euclidean = cutting.cut_topology(V, F, plane, predicates="euclidean", edges=edges)
        ga = cutting.cut_topology(V, F, plane, predicates="ga", edges=edges)
        for field in ("crossing", "positive", "positive_faces", "negative", "negative_faces"):
            np.testing.assert_array_equal(getattr(ga, field), getattr(euclidean, field), err_msg=field)
        np.testing.assert_allclose(ga.distances, euclidean.distances, rtol=0, atol=1e-14 * _diagonal(V))
        np.testing.assert_allclose(ga.points, euclidean.points, rtol=0, atol=1e-13 * _diagonal(V))


def test_ga_predicates_are_the_kernels_inner_product_and_meet():
    """The GA predicates (host numpy over the kernel's product tables) against the jaxcga kernel's own products:
    ``up(x) . P`` for the sides and ``(A ^ B ^ einf) v (P I)`` for the new points, and against the closed form."""
    mesh = MODELS["3Cylinder4bones"].mesh
    V = np.asarray(mesh.V, np.float64)
    plane = _random_plane(V, [0.3, -0.5, 1.0], 0.45)
    topology = cutting.cut_topology(V, mesh.F, plane, predicates="ga")
    P = cga.plane(jnp.asarray(plane.normal), jnp.asarray(plane.distance))
    off = topology.distances != 0  # not snapped onto the plane
    assert off.sum() > 0.9 * len(V)
    sides = np.asarray(cga.scalar_product(cga.up(jnp.asarray(V)), P))
    np.testing.assert_allclose(topology.distances[off], sides[off], rtol=0, atol=1e-14 * _diagonal(V))
    A, B = (V[topology.crossing[:, k]] for k in (0, 1))
    flat = cga.meet(cga.line(cga.up(jnp.asarray(A)), cga.up(jnp.asarray(B))), cga.undual(P))
    meets = np.stack([flat[f"e{i}inf"] for i in (1, 2, 3)], axis=1) / np.asarray(flat["eoinf"])[:, None]
    np.testing.assert_allclose(topology.points, meets, rtol=0, atol=1e-13 * _diagonal(V))
    n, d = np.asarray(plane.normal), float(plane.distance)
    closed_form = A + ((d - A @ n) / ((B - A) @ n))[:, None] * (B - A)
    np.testing.assert_allclose(topology.points, closed_form, rtol=0, atol=1e-13 * _diagonal(V))
    assert len(topology.points) > 10


def test_new_vertex_weights_are_the_barycentric_blend():
    J = np.array([[0, 1, 2, 3], [4, 1, 5, 6]])
    W = np.array([[0.4, 0.3, 0.2, 0.1], [0.5, 0.2, 0.2, 0.1]])
    J_new, W_new = cutting.blend_weights(J, W, np.array([[0, 1]]), np.array([[0.5, 0.5]]))
    dense = np.zeros(7)
    np.add.at(dense, J_new[0], W_new[0])
    # union {0..6}: 0.2, 0.25, 0.1, 0.05, 0.25, 0.1, 0.05 -> top 4: joints 1, 4, 0 and one of 2/5
    expected = {1: 0.25, 4: 0.25, 0: 0.2}
    for j, w in expected.items():
        assert abs(dense[j] - w / 0.8) < 1e-12
    assert abs(W_new.sum() - 1) < 1e-12 and np.count_nonzero(W_new) == 4


def test_side_weight_favours_each_halfs_own_side():
    mesh = ARM.mesh
    plane = _random_plane(mesh.V, [1.0, 0.0, 0.0], 0.5)
    (positive, negative), topology = cutting.cut(mesh, plane, side_weight=1.0, return_topology=True)
    np.testing.assert_array_equal(topology.crossing, cutting.cut_topology(mesh.V, mesh.F, plane).crossing)
    V = np.asarray(mesh.V)
    rows = _original_rows(positive, V)
    new_positions = np.asarray(positive.V)[rows < 0]
    # with side_weight 1 each copy carries exactly its own endpoint's weights
    own = np.where(topology.distances[topology.crossing[:, 0]] > 0, topology.crossing[:, 0], topology.crossing[:, 1])
    index = {tuple(p): k for k, p in enumerate(topology.points.tolist())}
    k = np.array([index[tuple(p)] for p in new_positions.tolist()])
    dense = lambda J, W: np.stack([np.bincount(j, w, minlength=mesh.num_joints) for j, w in zip(J, W)])  # noqa: E731
    np.testing.assert_allclose(
        dense(np.asarray(positive.J)[rows < 0], np.asarray(positive.W)[rows < 0]),
        dense(np.asarray(mesh.J)[own[k]], np.asarray(mesh.W)[own[k]]),
        atol=1e-12,
    )
    with pytest.raises(ValueError, match="side_weight"):
        cutting.cut(mesh, plane, side_weight=1.5)


@pytest.mark.parametrize("method", ["lbs", "cga"])
def test_cut_in_a_pose_reproduces_the_cut_when_posed_again(method):
    """After animation: the plane is given in world space at a pose; re-posing the halves puts the
    new vertices back on that plane (exact for LBS, and for eq. (17) with rigid joints)."""
    model = ARM
    local, joints, posed = posed_arm(model, 0.9)
    plane = _random_plane(posed, [0.3, 1.0, 0.2], 0.5)
    positive, negative = cutting.cut(model.mesh, plane, joint_matrices=joints)
    pose = local if method == "lbs" else cga.matrix_to_similitude(local)
    for half in (positive, negative):
        again = np.asarray(deform.skin_pose(deform.RiggedModel(half, model.skeleton), pose, method))
        rows = _original_rows(half, model.mesh.V)
        assert np.all(np.abs(again[rows < 0] @ plane.normal - plane.distance) <= 1e-9 * _diagonal(posed))
        # animating on keeps working: another time of the clip gives finite positions
        later = deform.skin_pose(deform.RiggedModel(half, model.skeleton), deform.sample_pose(model, 1.6, "lbs"), "lbs")
        assert np.all(np.isfinite(np.asarray(later)))


def test_new_vertex_positions_are_differentiable_in_the_plane():
    mesh = MODELS["3Cylinder4bones"].mesh
    plane = _random_plane(mesh.V, [0.1, 1.0, 0.2], 0.5)
    topology = cutting.cut_topology(mesh.V, mesh.F, plane)
    positions = cutting.cut_positions(mesh.V, topology, plane)
    np.testing.assert_allclose(positions, topology.points, atol=1e-12)

    def loss(params):
        return jnp.sum(cutting.cut_positions(mesh.V, topology, cutting.Plane(params[:3], params[3])) ** 2)

    params = jnp.append(jnp.asarray(plane.normal), plane.distance)
    check_gradient(loss, params, rtol=1e-6)
    # the gradient with respect to the Plane itself is a Plane holding the same numbers
    grad = jax.grad(lambda tool: jnp.sum(cutting.cut_positions(mesh.V, topology, tool) ** 2))(
        cutting.Plane(jnp.asarray(plane.normal), jnp.asarray(plane.distance))
    )
    np.testing.assert_allclose(jnp.append(grad.normal, grad.distance), jax.grad(loss)(params), rtol=1e-12)
    with pytest.raises(ValueError, match="V: expected the"):
        cutting.cut_positions(mesh.V[:-1], topology, plane)


def test_bad_input():
    mesh = ARM.mesh
    x = cutting.Plane([1.0, 0.0, 0.0], 0.0)
    with pytest.raises(ValueError, match="misses the mesh"):
        cutting.cut(mesh, cutting.Plane([1.0, 0.0, 0.0], 1e6))
    with pytest.raises(ValueError, match="plane: expected a cutting.Plane"):
        cutting.cut(mesh, [1.0, 0.0, 0.0, 0.0])  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="plane: expected a .3,. normal"):
        cutting.cut(mesh, cutting.Plane([1.0, 0.0], 0.0))
    with pytest.raises(ValueError, match="zero-length"):
        cutting.cut(mesh, cutting.Plane([0.0, 0.0, 0.0], 1.0))
    with pytest.raises(ValueError, match="finite"):
        cutting.cut(mesh, cutting.Plane([np.nan, 0.0, 1.0], 0.0))
    with pytest.raises(ValueError, match="predicates"):
        cutting.cut(mesh, x, predicates="exact")
    with pytest.raises(ValueError, match="joint_matrices"):
        cutting.cut(mesh, x, joint_matrices=np.eye(4))
    with pytest.raises(ValueError, match="F"):
        cutting.cut_topology(np.zeros((3, 3)), np.array([[0, 1, 5]]), x)
    with pytest.raises(ValueError, match="V"):
        cutting.cut_topology(np.full((3, 3), np.inf), np.array([[0, 1, 2]]), x)
    with pytest.raises(ValueError, match="edges"):
        cutting.cut_topology(mesh.V, mesh.F, x, edges=cutting.mesh_edges(np.array([[0, 1, 2]])))
