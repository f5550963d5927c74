"""Drilling (Algorithm 3) on real models: new points on the cylinder, the hole's area against the
analytic inscribed polygon on a flat plate, one boundary loop per hole, weights, skinning after the
drill, refinement of faces larger than the drill, posed drills, gradients by finite differences,
bad input."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from hypothesis import assume, given, settings
from hypothesis import strategies as st

import cutting
import deform
import jaxcga as cga
from tests.cutting.tools import (
    DATA,
    consistency_problems,
    drill_into,
    drill_outcome,
    drill_through_limb,
    inside_drill,
    load_models,
    mean_edge,
    piece_quality,
)
from tests.cutting.tools import area as _area
from tests.cutting.tools import diagonal as _diagonal
from tests.cutting.tools import edge_counts as _edge_counts
from tests.cutting.tools import posed as posed_arm
from tests.shared import check_gradient, grid

MODELS = load_models(weld=True)
ARM = deform.default_arm()


def _radial_distance(points, tip, base):
    axis = (tip - base) / np.linalg.norm(tip - base)
    relative = points - base
    return np.linalg.norm(relative - np.outer(relative @ axis, axis), axis=1)


def _loops(boundary_edges):
    """Number of closed loops formed by undirected edges in which every vertex has degree 2."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    vertices, local = np.unique(boundary_edges, return_inverse=True)
    local = local.reshape(-1, 2)
    degree = np.bincount(local.ravel(), minlength=len(vertices))
    assert np.all(degree == 2)
    graph = sp.coo_matrix((np.ones(len(local)), (local[:, 0], local[:, 1])), shape=(len(vertices),) * 2)
    return connected_components(graph, directed=False)[0]


@pytest.mark.slow
@settings(max_examples=12, deadline=None)
@given(
    name=st.sampled_from(sorted(MODELS)),
    seed=st.integers(0, 10_000),
    radius=st.floats(0.4, 1.0),
    depth=st.floats(0.5, 3.0),
)
def test_drill_invariants_on_real_models(name, seed, radius, depth):
    mesh = MODELS[name].mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    edge = mean_edge(V, F)
    # on Arm5, the arm itself: the fingers (y > 55) are thinner than a drill of a few edges would need
    eligible = np.flatnonzero(V[F].mean(axis=1)[:, 1] < 50) if name == "Arm5" else np.arange(len(F))
    face = np.random.default_rng(seed).choice(eligible)
    tip, base = drill_into(V, F, face, depth * edge)
    # away from the input's own boundary (Arm5 is open at both ends), narrower than the bodies: the hole gets
    # a loop of its own (a drill wider than the body severs it, with two loops; 3Cylinder4bones's thinnest part
    # has radius 0.52, 1.4 mean edges)
    before_edges, before_counts = _edge_counts(F)
    rim = V[np.unique(before_edges[before_counts == 1])]
    assume(len(rim) == 0 or np.linalg.norm(rim - V[F[face]].mean(axis=0), axis=1).min() > (radius + depth + 2) * edge)
    drilled, topology = cutting.drill(mesh, cutting.Drill(tip, base, radius * edge), return_topology=True)
    Vd, Fd = np.asarray(drilled.V, np.float64), np.asarray(drilled.F)
    diagonal = _diagonal(V)
    # new points on the cylinder; no sliver (issue 30): pieces keep 1e-3 of the smallest face's area and
    # angles of 1e-3 rad; area only removed
    assert np.all(np.abs(_radial_distance(topology.points, tip, base) - radius * edge) <= 1e-9 * diagonal)
    problems, _, _ = piece_quality(V, F, Vd, Fd, topology.kept)
    # the differentiable positions follow the topology left after dropping points
    np.testing.assert_allclose(
        np.asarray(
            cutting.drill_positions(V, topology, cutting.Drill(jnp.asarray(tip), jnp.asarray(base), radius * edge))
        ),
        topology.points,
        rtol=0,
        atol=1e-9 * diagonal,
    )
    assert not problems + consistency_problems(drilled, mesh, topology.kept)
    assert _area(Vd, Fd).sum() < _area(V, F).sum()
    # weights of new vertices (refinement midpoints and hole points)
    W = np.asarray(drilled.W)[topology.kept >= len(V)]
    np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-12)
    assert drilled.J.shape[1] == mesh.J.shape[1] and np.all(np.asarray(drilled.J) < mesh.num_joints)
    # manifold, with one new boundary loop per hole
    edges, counts = _edge_counts(Fd)
    assert counts.max() <= 2
    assert trimesh.Trimesh(Vd, Fd, process=False).is_winding_consistent
    new_loops = _loops(edges[counts == 1]) - (
        _loops(before_edges[before_counts == 1]) if np.any(before_counts == 1) else 0
    )
    assert new_loops == topology.holes >= 1
    # the input's vertices outside the hole keep their rest positions, in order
    original = topology.kept[topology.kept < len(V)]
    np.testing.assert_array_equal(Vd[: len(original)], V[original])


def test_hole_in_a_flat_plate_is_the_inscribed_polygon():
    """A drill perpendicular to a flat plate removes exactly the polygon of its boundary: new points on
    the circle of radius r, and input vertices where a new point would have made a sliver (they lie
    next to the circle); its area tends to pi r^2 as the plate is refined."""
    plate = trimesh.creation.box(extents=(4.0, 4.0, 1.0))
    for _ in range(4):
        plate = plate.subdivide()
    V, F = np.asarray(plate.vertices), np.asarray(plate.faces)
    tip, base, r = np.array([0.1, 0.05, 0.0]), np.array([0.1, 0.05, 2.0]), 0.7
    drilled = cutting.drill_topology(V, F, cutting.Drill(tip, base, r))
    assert drilled.holes == 1
    top_before = _area(V, F)[V[F].mean(axis=1)[:, 2] > 0.49].sum()
    extended = np.concatenate([drilled.vertices, drilled.points])[drilled.kept]
    top_after = _area(extended, drilled.faces)[extended[drilled.faces].mean(axis=1)[:, 2] > 0.49].sum()
    rim_edges, rim_counts = _edge_counts(drilled.faces)
    rim = extended[np.unique(rim_edges[rim_counts == 1])]
    points = rim[rim[:, 2] > 0.49] - tip
    assert np.all(np.abs(np.linalg.norm(points[:, :2], axis=1) - r) <= 0.05 * r)
    order = np.argsort(np.arctan2(points[:, 1], points[:, 0]))
    x, y = points[order, 0], points[order, 1]
    polygon = 0.5 * abs(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))
    assert abs((top_before - top_after) - polygon) <= 1e-9 * polygon
    assert 0.9 * np.pi * r**2 < polygon < np.pi * r**2
    # the bottom of the plate is not reached by the drill's axis: untouched
    bottom = _area(V, F)[V[F].mean(axis=1)[:, 2] < -0.49].sum()
    assert (
        abs(_area(extended, drilled.faces)[extended[drilled.faces].mean(axis=1)[:, 2] < -0.49].sum() - bottom)
        <= 1e-12 * bottom
    )
    # a longer drill goes through both sides
    through = cutting.drill_topology(V, F, cutting.Drill(np.array([0.1, 0.05, -2.0]), base, r))
    assert through.holes == 2


def test_a_drill_thinner_than_the_faces_splits_them_and_drills_again():
    mesh = MODELS["Arm5"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    tip, base = drill_into(V, F, 1000, mean_edge(V, F))
    radius = 0.08 * mean_edge(V, F)
    drilled, topology = cutting.drill(mesh, cutting.Drill(tip, base, radius), return_topology=True)
    assert topology.refinements >= 1 and len(topology.points) >= 6
    # the differentiable positions form the midpoints (level after level) from the input's vertices
    np.testing.assert_allclose(
        cutting.drill_positions(V, topology, cutting.Drill(tip, base, radius)),
        topology.points,
        atol=1e-9 * _diagonal(V),
    )
    with pytest.raises(ValueError, match="V: expected the"):
        cutting.drill_positions(topology.vertices, topology, cutting.Drill(tip, base, radius))
    np.testing.assert_allclose(_radial_distance(topology.points, tip, base), radius, atol=1e-9 * _diagonal(V))
    # refinement split points (of split points, level after level) sit on their parents' edges, at the
    # midpoint or at most an eighth aside
    vertices, split = topology.vertices, topology.split[:, None]
    assert np.all((split >= 0.375) & (split <= 0.625)) and np.mean(split == 0.5) > 0.5
    np.testing.assert_allclose(
        vertices[len(V) :],
        split * vertices[topology.parents[:, 0]] + (1.0 - split) * vertices[topology.parents[:, 1]],
        atol=1e-12,
    )
    kept = topology.kept
    midpoints = (kept >= len(V)) & (kept < len(vertices))
    np.testing.assert_allclose(np.asarray(drilled.V)[midpoints], vertices[kept[midpoints]], atol=1e-5)
    assert np.all(np.asarray(drilled.W)[midpoints].sum(axis=1) > 0.999)
    with pytest.raises(ValueError, match="too thin"):
        cutting.drill(mesh, cutting.Drill(tip, base, radius), max_refinements=0)


@pytest.mark.parametrize("method", deform.METHODS)
def test_skinning_the_drilled_mesh_gives_the_original_at_original_vertices(method):
    model = ARM
    V, F = np.asarray(model.mesh.V), np.asarray(model.mesh.F)
    tip, base = drill_into(V, F, 3000, 0.05)
    drilled, topology = cutting.drill(model.mesh, cutting.Drill(tip, base, 0.02), return_topology=True)
    pose = deform.sample_pose(model, 0.7, method)
    original = np.asarray(deform.skin_pose(model, pose, method))
    posed = np.asarray(deform.skin_pose(deform.RiggedModel(drilled, model.skeleton), pose, method))
    kept = topology.kept[topology.kept < len(V)]
    np.testing.assert_allclose(posed[: len(kept)], original[kept], atol=1e-12)
    assert np.all(np.isfinite(posed))


@pytest.mark.parametrize("method", ["lbs", "cga"])
def test_drill_in_a_pose_reproduces_the_hole_when_posed_again(method):
    model = ARM
    local, joints, posed = posed_arm(model, 0.9)
    F = np.asarray(model.mesh.F)
    tip, base = drill_into(posed, F, 5000, 0.05)
    drilled, topology = cutting.drill(
        model.mesh, cutting.Drill(tip, base, 0.015), joint_matrices=joints, return_topology=True
    )
    pose = local if method == "lbs" else cga.matrix_to_similitude(local)
    again = np.asarray(deform.skin_pose(deform.RiggedModel(drilled, model.skeleton), pose, method))
    new = topology.kept >= len(topology.vertices)
    # re-posed, the new points lie on the drill's cylinder again
    np.testing.assert_allclose(_radial_distance(again[new], tip, base), 0.015, atol=1e-9 * _diagonal(posed))
    later = deform.skin_pose(deform.RiggedModel(drilled, model.skeleton), deform.sample_pose(model, 1.6, "lbs"), "lbs")
    assert np.all(np.isfinite(np.asarray(later)))


@pytest.mark.slow
def test_new_vertex_positions_are_differentiable_in_the_drill():
    mesh = MODELS["3Cylinder4bones"].mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    tip, base = drill_into(V, F, 100, 0.5)
    topology = cutting.drill_topology(V, F, cutting.Drill(tip, base, 0.3))
    positions = cutting.drill_positions(V, topology, cutting.Drill(tip, base, 0.3))
    np.testing.assert_allclose(positions, topology.points, atol=1e-12)

    def loss(params):
        return jnp.sum(jnp.sin(cutting.drill_positions(V, topology, cutting.Drill(params[:3], params[3:6], params[6]))))

    params = jnp.concatenate([jnp.asarray(tip), jnp.asarray(base), jnp.array([0.3])])
    check_gradient(loss, params)


def test_bad_input():
    mesh = ARM.mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    tip, base = drill_into(V, F, 3000, 0.05)
    with pytest.raises(ValueError, match="misses the mesh"):
        cutting.drill(mesh, cutting.Drill(tip + 10.0, base + 10.0, 0.02))
    with pytest.raises(ValueError, match="drill.radius"):
        cutting.drill(mesh, cutting.Drill(tip, base, -1.0))
    with pytest.raises(ValueError, match="coincide"):
        cutting.drill(mesh, cutting.Drill(tip, tip, 0.02))
    with pytest.raises(ValueError, match="drill.tip"):
        cutting.drill(mesh, cutting.Drill([0.0, 1.0], base, 0.02))
    with pytest.raises(ValueError, match="drill.base"):
        cutting.drill(mesh, cutting.Drill(tip, [np.nan, 0.0, 0.0], 0.02))
    with pytest.raises(ValueError, match="drill: expected a cutting.Drill"):
        cutting.drill(mesh, (tip, base, 0.02))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="min_points"):
        cutting.drill(mesh, cutting.Drill(tip, base, 0.02), min_points=2)
    with pytest.raises(ValueError, match="joint_matrices"):
        cutting.drill(mesh, cutting.Drill(tip, base, 0.02), joint_matrices=np.eye(4))


def _plate_with_a_fin():
    """A flat 10 x 10 grid in z = 0 with a fin standing on the row y = 0.5 between x = 0.3 and 0.7:
    the row's edges there carry three faces (non-manifold)."""
    V, F = grid()
    index = np.arange(121).reshape(11, 11)
    fin = []
    for i in range(3, 7):
        V = np.vstack([V, [(i + 0.5) / 10, 0.5, 0.3]])
        fin.append([index[i, 5], index[i + 1, 5], len(V) - 1])
    return V, np.concatenate([F, np.asarray(fin)])


def test_non_manifold_input():
    V, F = _plate_with_a_fin()
    # far from the fin the plate drills normally; across it the drill is refused
    away = cutting.drill_topology(V, F, cutting.Drill(np.array([0.25, 0.2, -1.0]), np.array([0.25, 0.2, 1.0]), 0.12))
    assert away.holes == 1 and len(away.points) >= 6
    with pytest.raises(ValueError, match="non-manifold"):
        cutting.drill_topology(V, F, cutting.Drill(np.array([0.5, 0.52, -1.0]), np.array([0.5, 0.52, 1.0]), 0.12))
    # a tear ends at the fin's edges and begins again past them: one stretch on each side, no fin edge torn
    scalpel = cutting.Scalpel(
        np.array([[0.52, 0.3, 1.0], [0.52, 0.7, 1.0]]), np.array([[0.52, 0.3, -1.0], [0.52, 0.7, -1.0]])
    )
    path = cutting.tear_topology(V, F, scalpel)
    assert len(path.stretches) == 2
    assert np.all(cutting.mesh_edges(F).edge_counts[path.edge_ids] == 2)
    assert path.sample_points[path.stretches[0, 1], 1] < 0.5 < path.sample_points[path.stretches[1, 0], 1]
    # a cut goes through (it works face by face)
    topology = cutting.cut_topology(V, F, cutting.Plane([1.0, 0.0, 0.0], 0.55))
    assert len(topology.points) > 0


def test_a_drill_through_grid_vertices_makes_no_slivers():
    """A cylinder whose radius is exactly the distance to grid vertices: they are snapped onto it. Without a
    rim tolerance the rim is the inscribed polygon. With the default one, chords of the 0.1 grid stray too far
    and the faces along the rim are split until its chords keep within 5e-4 of the diagonal of the circle;
    where the circle runs along an edge (it touches the grid lines at these radii) a split point next to it
    makes the sliver rule snap the rim to it, within 1.5 sqrt(1e-3 x the smallest doubled area) = 0.0047
    (``_rim_bound``)."""
    V, F = grid()
    centre = np.array([0.5, 0.5, 0.0])
    limit, snap = 5e-4 * np.sqrt(2.0), 1.5 * np.sqrt(1e-3 * 0.01)
    for radius in (0.2, 0.1 * np.sqrt(5.0), 0.3 + 1e-12):
        drill = cutting.Drill(centre - [0, 0, 1], centre + [0, 0, 1], radius)
        for rim_tolerance, bounds, atol in (
            (np.inf, (0.8 * np.pi * radius**2, np.pi * radius**2), 1e-6),
            (5e-4, (np.pi * (radius - limit) ** 2, np.pi * (radius + snap) ** 2), snap),
        ):
            hole = cutting.drill_topology(V, F, drill, rim_tolerance=rim_tolerance)
            assert (hole.refinements > 0) == (rim_tolerance < np.inf)
            extended = np.concatenate([hole.vertices, hole.points])[hole.kept]
            problems, _, _ = piece_quality(V, F, extended, hole.faces, hole.kept)
            assert not problems
            removed = 1.0 - _area(extended, hole.faces).sum()
            assert bounds[0] < removed < bounds[1]
            rim_edges, rim_counts = _edge_counts(hole.faces)
            rim_edges = rim_edges[rim_counts == 1]
            on_hole = np.linalg.norm(extended[rim_edges].mean(axis=1)[:, :2] - 0.5, axis=1) < 0.45
            rim = extended[np.unique(rim_edges[on_hole])]
            np.testing.assert_allclose(np.linalg.norm(rim[:, :2] - 0.5, axis=1), radius, atol=atol)
            chords = rim_edges[on_hole & np.all(hole.kept[rim_edges] >= len(hole.vertices), axis=1)]
            middle = extended[chords].mean(axis=1)[:, :2] - 0.5
            assert np.all(radius - np.linalg.norm(middle, axis=1) <= (limit if rim_tolerance < np.inf else 0.02))


def test_a_drill_wider_than_what_it_meets_says_so_not_too_thin():
    """A small plate and a far one: a radius wider than the small plate, or than the whole mesh, is named as
    such (it used to read "the drill is too thin ... raise the radius")."""
    V = np.array(
        [
            [-0.05, -0.05, 0],
            [0.05, -0.05, 0],
            [0.05, 0.05, 0],
            [-0.05, 0.05, 0],
            [5, 5, 0],
            [6, 5, 0],
            [6, 6, 0],
            [5, 6, 0.0],
        ]
    )
    F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])
    tip, base = np.array([0.0, 0.0, -1.0]), np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match=r"drill.radius: 0.2 is wider than the part of the model the drill meets"):
        cutting.drill_topology(V, F, cutting.Drill(tip, base, 0.2))
    with pytest.raises(ValueError, match=r"drill.radius: 20 exceeds the model's size: every vertex lies within 8.485 "):
        cutting.drill_topology(V, F, cutting.Drill(tip, base, 20.0))
    fitting = cutting.drill_topology(V, F, cutting.Drill(tip, base, 0.01), max_refinements=8)
    assert len(fitting.points) >= 6  # a fitting radius drills


# --- Drills through layers (issue 51, item 2) --------------------------------------------------------------


def _layered_scene():
    """A closed tube (radius 1, along x) around a closed tube (radius 0.5), a separate ball above them, a speck
    smaller than the drill above the ball and an open sheet above everything: (V, F, part of each vertex)."""
    rotate = trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0])
    outer = trimesh.creation.cylinder(radius=1.0, height=4.0, sections=48).apply_transform(rotate)
    inner = trimesh.creation.cylinder(radius=0.5, height=3.0, sections=32).apply_transform(rotate)
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.35).apply_translation([0.3, 0.1, 1.6])
    speck = trimesh.creation.icosphere(subdivisions=0, radius=0.05).apply_translation([0.3, 0.1, 2.3])
    V, F = grid(12)
    sheet = trimesh.Trimesh(V * 3.0 + [-1.5, -1.5, 2.6], F, process=False)
    parts = [outer, inner, ball, speck, sheet]
    scene = trimesh.util.concatenate(parts)
    assert isinstance(scene, trimesh.Trimesh)
    labels = np.concatenate([np.full(len(p.vertices), k) for k, p in enumerate(parts)])
    return np.asarray(scene.vertices, np.float64), np.asarray(scene.faces), labels


def _extended_labels(topology, labels):
    """The part of every vertex of the drilled mesh (split points and new points take their edge's)."""
    extended = np.concatenate([labels, np.zeros(len(topology.parents) + len(topology.points), labels.dtype)])
    n = len(labels)
    for k, (i, _) in enumerate(topology.parents):  # in order: a split point's parents precede it
        extended[n + k] = extended[i]
    extended[len(topology.vertices) :] = extended[topology.crossing[:, 0]]
    return extended[topology.kept]


def _tube_hole_area(R, centre, a):
    """Area of the tube y^2 + z^2 = R^2 inside the vertical cylinder of radius a about (x0, y0) = centre,
    both sides: over the angle t (y = R sin t) the width along x is 2 sqrt(a^2 - (R sin t - y0)^2)."""
    from scipy.integrate import quad

    y0 = centre[1]
    limits = np.arcsin(np.clip([(y0 - a) / R, (y0 + a) / R], -1.0, 1.0))
    width, _ = quad(lambda t: 2.0 * np.sqrt(max(a * a - (R * np.sin(t) - y0) ** 2, 0.0)) * R, *limits, limit=200)
    return 2.0 * width


def test_a_drill_through_layers_holes_every_sheet_in_its_way():
    """Every sheet in the drill's way gets its own hole (both sides of each tube, both sides of the ball, the
    sheet), the speck inside the drill is removed whole, no input vertex stays strictly inside the drilled
    volume, the rims keep within the rim tolerance of the cylinder, and each part loses the analytic area
    (tubes: the integral over the angle; ball: two spherical caps; sheet: the disc)."""
    V, F, labels = _layered_scene()
    centre, a = np.array([0.3, 0.1]), 0.2
    drill = cutting.Drill([*centre, -1.6], [*centre, 3.0], a)  # from above the sheet to below the outer tube
    # vertices of the ball, the speck and the sheet lie in the drill's way; the tubes' long faces cross it with
    # no vertex inside (the drill meets them through their edges only)
    in_the_way = np.bincount(labels[inside_drill(V, drill, 1e-6 * _diagonal(V))], minlength=5)
    assert np.all(in_the_way[[2, 3, 4]] > 0) and np.all(in_the_way[[0, 1]] == 0)
    topology = cutting.drill_topology(V, F, drill)
    assert (topology.holes, topology.removed) == (7, 1)
    inside, rim, middle = drill_outcome(V, F, drill, topology)
    diagonal = _diagonal(V)
    assert inside == 0 and rim <= 5e-4 + 1e-12 and middle <= 5e-4 + 1e-12
    assert topology.rim_distance <= 5e-4 * diagonal * (1 + 1e-9)
    extended = np.concatenate([topology.vertices, topology.points])[topology.kept]
    problems, _, _ = piece_quality(V, F, extended, topology.faces, topology.kept)
    assert not problems
    edges, counts = _edge_counts(topology.faces)
    assert counts.max() <= 2 and trimesh.Trimesh(extended, topology.faces, process=False).is_winding_consistent
    part = _extended_labels(topology, labels)
    assert not np.any(part == 3)  # the speck is gone
    before = np.bincount(labels[F[:, 0]], weights=_area(V, F), minlength=5)
    after = np.bincount(part[topology.faces[:, 0]], weights=_area(extended, topology.faces), minlength=5)
    # new boundary loops per part (the sheet keeps its own border besides)
    rim_edges = edges[counts == 1]
    loops = [_loops(rim_edges[part[rim_edges[:, 0]] == k]) for k in (0, 1, 2, 4)]
    assert loops == [2, 2, 2, 2]
    # areas against closed forms, on faceted surfaces: the ratio removed / total of the part
    sections = {0: 48, 1: 32}
    for k, R in ((0, 1.0), (1, 0.5)):
        facet = np.sin(2 * np.pi / sections[k]) / (2 * np.pi / sections[k])  # polygon area / circle's
        expected = _tube_hole_area(R, centre, a) * facet
        np.testing.assert_allclose(before[k] - after[k], expected, rtol=0.02)
    ball_radius = 0.35
    caps = 2 * 2 * np.pi * ball_radius * (ball_radius - np.sqrt(ball_radius**2 - a**2))
    np.testing.assert_allclose((before[2] - after[2]) / before[2], caps / (4 * np.pi * ball_radius**2), rtol=0.03)
    limit = 5e-4 * diagonal
    assert np.pi * (a - limit) ** 2 < before[4] - after[4] < np.pi * (a + limit) ** 2


def _rim_bound(V, F) -> float:
    """How far from the cylinder a rim may lie, relative to the diagonal: 1e-3 (issue 51), or where the sliver
    rule keeps the splits from getting there (a mesh whose smallest face is large against the diagonal), 1.5 x
    sqrt(1e-3 x its doubled area): the distance of a vertex that the rule snaps the rim to (a piece between it
    and the cylinder would be smaller than the rule allows). 1e-3 on every real character here."""
    corners = np.asarray(V)[np.asarray(F)]
    doubled = np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
    return max(1e-3, 1.5 * np.sqrt(1e-3 * doubled.min()) / _diagonal(V))


def _octasphere(subdivisions: int):
    """The octahedron, its faces split ``subdivisions`` times, vertices pushed onto the unit sphere."""
    octahedron = trimesh.Trimesh(
        np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], np.float64),
        np.array([[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]]),
        process=False,
    )
    for _ in range(subdivisions):
        octahedron = octahedron.subdivide()
    V = np.asarray(octahedron.vertices)
    return V / np.linalg.norm(V, axis=1, keepdims=True), np.asarray(octahedron.faces)


@pytest.mark.parametrize(
    "surface, radii",
    [
        ("octasphere 512 faces", (0.15, 0.4)),
        ("uv sphere 576 faces", (0.05, 0.15, 0.4)),  # the coarseness of a 576-face low-poly animal
        ("icosphere 5120 faces", (0.05, 0.15, 0.4)),
    ],
)
def test_the_rim_keeps_on_the_cylinder_at_any_resolution(surface, radii):
    """Drills through a unit sphere at three resolutions, from faces larger than the drill to small ones: two
    holes, no input vertex inside, rim vertices and rim edge midpoints within ``_rim_bound`` of the cylinder
    (the faces the rim crosses are split as often as that needs), no sliver."""
    if surface.startswith("octasphere"):
        V, F = _octasphere(3)
    elif surface.startswith("uv"):
        sphere = trimesh.creation.uv_sphere(radius=1.0, count=[13, 12])
        V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    else:
        sphere = trimesh.creation.icosphere(4)
        V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    rng = np.random.default_rng(7)
    for radius in radii:
        for _ in range(2):
            axis = rng.normal(size=3)
            axis /= np.linalg.norm(axis)
            offset = 0.2 * rng.normal(size=3)
            offset -= (offset @ axis) * axis
            drill = cutting.Drill(offset - 1.5 * axis, offset + 1.5 * axis, radius)
            topology = cutting.drill_topology(V, F, drill)
            inside, rim, middle = drill_outcome(V, F, drill, topology)
            assert topology.holes == 2 and inside == 0
            assert max(rim, middle) <= _rim_bound(V, F), (radius, rim, middle, topology.refinements)
            np.testing.assert_allclose(topology.rim_distance / _diagonal(V), max(rim, middle), rtol=1e-9, atol=1e-15)
            extended = np.concatenate([topology.vertices, topology.points])[topology.kept]
            problems, _, _ = piece_quality(V, F, extended, topology.faces, topology.kept)
            assert not problems


def test_on_an_octahedron_the_sliver_rule_bounds_the_rim():
    """On the octahedron itself (8 faces of doubled area sqrt(3)) a piece must keep 1e-3 sqrt(3): the faces along
    the rim are split only that far, and the rim passes through vertices within about sqrt(1e-3 sqrt(3)) of the
    cylinder (``_rim_bound``: 0.018 of the diagonal); ``rim_distance`` says how far it is, and no sliver is
    made."""
    V, F = _octasphere(0)
    drill = cutting.Drill([0.1, -0.05, -1.5], [0.1, -0.05, 1.5], 0.3)
    topology = cutting.drill_topology(V, F, drill)
    inside, rim, middle = drill_outcome(V, F, drill, topology)
    assert topology.holes == 2 and inside == 0 and topology.refinements > 0
    np.testing.assert_allclose(topology.rim_distance / _diagonal(V), max(rim, middle), rtol=1e-9)
    assert max(rim, middle) <= _rim_bound(V, F)
    extended = np.concatenate([topology.vertices, topology.points])[topology.kept]
    problems, _, _ = piece_quality(V, F, extended, topology.faces, topology.kept)
    assert not problems


@pytest.mark.parametrize("name", ["CesiumMan", "Arm5"])
def test_drills_through_the_limbs_of_real_characters(name):
    """Drills placed as a user places them (a random skin point, along the inward normal, through the limb,
    radius 5-30% of the limb's thickness) on committed characters, welded: every one drills, leaves no input
    vertex inside, keeps its rims within 1e-3 of the diagonal of the cylinder, makes no sliver and a consistent
    mesh whose input vertices skin where they did."""
    model = deform.load_model(DATA / f"{name}.glb", weld=True)
    mesh = model.mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    edges = cutting.mesh_edges(F)
    rng = np.random.default_rng(51)
    # a pose: the clip's (CesiumMan), or every bone turned a little about a random axis (Arm5 has no clip)
    if model.clips:
        pose = deform.sample_pose(model, 0.5, "lbs")
    else:
        turns = [trimesh.transformations.rotation_matrix(0.3, rng.normal(size=3)) for _ in model.skeleton.names]
        pose = np.asarray(deform.local_matrices(model.skeleton)) @ np.stack(turns)
    original = np.asarray(deform.skin_pose(model, pose, "lbs"))
    for _ in range(8):
        drill, _ = drill_through_limb(V, F, rng)
        drilled, topology = cutting.drill(mesh, drill, edges=edges, return_topology=True)
        inside, rim, middle = drill_outcome(V, F, drill, topology)
        assert topology.holes >= 1 and inside == 0 and max(rim, middle) <= 1e-3
        problems, _, _ = piece_quality(V, F, drilled.V, drilled.F, topology.kept)
        assert not problems + consistency_problems(drilled, mesh, topology.kept)
        posed = np.asarray(deform.skin_pose(deform.RiggedModel(drilled, model.skeleton), pose, "lbs"))
        kept = topology.kept[topology.kept < len(V)]
        np.testing.assert_allclose(posed[: len(kept)], original[kept], rtol=0, atol=1e-12 * _diagonal(V))


def test_the_new_points_after_splits_aside_are_differentiable_in_the_drill():
    """On a coarse sphere the faces along the rim are split (some edges aside of their midpoints): for that
    fixed topology the new points are the drill's, and their gradient with respect to the drill (tip, base,
    radius) matches central differences."""
    sphere = trimesh.creation.uv_sphere(radius=1.0, count=[13, 12])
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    tip, base, radius = np.array([0.13, -0.07, -1.5]), np.array([0.1, 0.05, 1.5]), 0.15
    topology = cutting.drill_topology(V, F, cutting.Drill(tip, base, radius))
    assert topology.refinements > 0 and np.any(topology.split != 0.5)
    np.testing.assert_allclose(
        cutting.drill_positions(V, topology, cutting.Drill(tip, base, radius)), topology.points, atol=1e-12
    )

    def loss(params):
        drill = cutting.Drill(params[:3], params[3:6], params[6])
        return jnp.sum(jnp.sin(3.0 * cutting.drill_positions(V, topology, drill)))

    check_gradient(loss, jnp.concatenate([jnp.asarray(tip), jnp.asarray(base), jnp.array([radius])]))
