"""Volumes from real surfaces (``xfem.tetrahedralize_surface``, fTetWild): an open, self-intersecting, multi-part
surface's tets against manifold3d's volume of the closed parts within the envelope's bound, its parts kept apart,
the surface embedded (rest positions back, affine maps reproduced, the sparse map equal to the JAX one and its
gradient), tet quality against closed forms, the surface of a cut XFEM body in pieces, the corpus's characters,
TetGen's absence, bad input."""

from __future__ import annotations

import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp
import trimesh
from scipy.sparse.csgraph import connected_components

import xfem
from tests.shared import CHARACTERS, load_character, wild_surface

EDGE = 0.1
EPSILON = 1e-3  # tetrahedralize_surface's default envelope, over the bounding box diagonal


@pytest.fixture(scope="module")
def wild():
    V, F, volume, area = wild_surface()
    return V, F, volume, area, xfem.tetrahedralize_surface(V, F, edge_length=EDGE, threads=1)


def test_tet_quality_matches_closed_forms():
    regular = xfem.tet_mesh(
        np.array([[1.0, 1.0, 1.0], [1.0, -1.0, -1.0], [-1.0, 1.0, -1.0], [-1.0, -1.0, 1.0]]), np.array([[0, 1, 2, 3]])
    )
    q = xfem.tet_quality(regular)
    assert q.tets == 1 and q.nodes == 4
    np.testing.assert_allclose([q.min_dihedral_deg, q.max_dihedral_deg], np.degrees(np.arccos(1 / 3)), rtol=1e-12)
    np.testing.assert_allclose([q.min_volume_ratio, q.mean_volume_ratio], 1.0, rtol=1e-12)
    # the corner tet: three right angles at the edges through the origin, arccos(1/sqrt 3) at the others; its
    # volume 1/6 over (e_rms^3 / (6 sqrt 2)) with e_rms^2 = (3 * 1 + 3 * 2) / 6
    q = xfem.tet_quality(xfem.one_tet())
    np.testing.assert_allclose(q.min_dihedral_deg, np.degrees(np.arccos(1 / np.sqrt(3))), rtol=1e-12)
    np.testing.assert_allclose(q.max_dihedral_deg, 90.0, rtol=1e-12)
    np.testing.assert_allclose(q.min_volume_ratio, 6 * np.sqrt(2) / 6 / 1.5**1.5, rtol=1e-12)
    # a box's Kuhn tets: dihedral angles 45, 60 and 90 degrees
    q = xfem.tet_quality(xfem.box_tets((2, 2, 2)))
    np.testing.assert_allclose([q.min_dihedral_deg, q.max_dihedral_deg], [45.0, 90.0], rtol=1e-12)
    with pytest.raises(ValueError, match="mesh"):
        xfem.tet_quality(np.zeros((4, 3)))  # pyright: ignore[reportArgumentType]


def test_an_open_self_intersecting_multi_part_surface_gets_its_volume(wild):
    V, F, volume, area, result = wild
    diagonal = np.linalg.norm(V.max(0) - V.min(0))
    # the tets' boundary stays within the envelope (epsilon of the diagonal) of the surface: the volume between
    # them is at most the area times that width (the holes, 6 faces of ~640, change the inside by less)
    bound = area * EPSILON * diagonal
    assert abs(float(jnp.sum(result.mesh.volumes())) - volume) < bound
    # the crossing spheres make one body, the cube another: two connected parts of tets
    T = np.asarray(result.mesh.T)
    rows = np.repeat(T[:, :1], 3, axis=1).ravel()
    graph = sp.csr_matrix((np.ones(len(rows)), (rows, T[:, 1:].ravel())), shape=(result.mesh.n_nodes,) * 2)
    count, label = connected_components(graph, directed=False)
    assert count == 2
    X = np.asarray(result.mesh.X)
    assert len(np.unique(label[X[:, 0] > 2.0])) == 1 and len(np.unique(label[X[:, 0] < 2.0])) == 1
    q = result.quality
    assert q.tets == result.mesh.n_elements and q.nodes == result.mesh.n_nodes
    assert q.min_dihedral_deg > 1.0 and q.min_volume_ratio > 0.01 and result.seconds > 0


def test_the_surface_is_embedded_and_carried_by_a_sparse_linear_map(wild):
    V, F, _, _, result = wild
    embedding, mesh = result.embedding, result.mesh
    diagonal = np.linalg.norm(V.max(0) - V.min(0))
    assert embedding.n_points == len(V)
    np.testing.assert_allclose(embedding.weights.sum(axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(embedding.positions(mesh.X), V, atol=1e-12)
    # inside: the containing tet (coordinates in [0, 1]); outside: within the envelope of the tets
    inside = embedding.distance == 0
    assert inside.mean() > 0.3 and embedding.weights[inside].min() >= -1e-9
    assert embedding.distance.max() < 3 * EPSILON * diagonal
    # an affine motion of the nodes moves every embedded point by it, the outside ones too (extrapolation)
    A = np.array([[1.1, 0.2, 0.0], [-0.1, 0.9, 0.3], [0.05, 0.0, 1.2]])
    b = np.array([0.3, -0.2, 1.0])
    np.testing.assert_allclose(embedding.positions(np.asarray(mesh.X) @ A.T + b), V @ A.T + b, atol=1e-10)
    x = np.asarray(mesh.X) + np.random.default_rng(0).normal(0, 0.01, mesh.X.shape)
    M = embedding.matrix(mesh.n_nodes)
    np.testing.assert_allclose(embedding.positions(x), M @ x, atol=1e-12)
    # the gradient of a loss of the carried surface is M^T of the loss's gradient there
    w = np.random.default_rng(1).normal(size=(len(V), 3))
    grad = jax.grad(lambda x: jnp.sum(w * embedding.positions(x)))(jnp.asarray(x))
    np.testing.assert_allclose(grad, M.T @ w, atol=1e-12)
    with pytest.raises(ValueError, match="x: expected at least"):
        embedding.positions(x[:10])
    with pytest.raises(ValueError, match="n_nodes"):
        embedding.matrix(3)


def test_embed_points_finds_containing_and_nearest_tets():
    mesh = xfem.box_tets((3, 3, 3))
    P = np.random.default_rng(2).uniform(0.01, 0.99, (200, 3))
    embedding = xfem.embed_points(mesh, P)
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    assert np.all(embedding.distance == 0) and embedding.weights.min() >= -1e-12
    np.testing.assert_allclose(np.einsum("sk,skd->sd", embedding.weights, X[T[embedding.element]]), P, atol=1e-12)
    # a point off a face of the box: the nearest tet, at the distance to the face
    off = xfem.embed_points(mesh, np.array([[0.5, 0.4, 1.2], [-0.3, 0.5, 0.5]]))
    np.testing.assert_allclose(off.distance, [0.2, 0.3], atol=1e-12)
    np.testing.assert_allclose(off.positions(mesh.X), [[0.5, 0.4, 1.2], [-0.3, 0.5, 0.5]], atol=1e-12)
    with pytest.raises(ValueError, match="P"):
        xfem.embed_points(mesh, np.array([[0.0, np.nan, 0.0]]))


def test_a_cut_body_carries_its_surface_in_pieces():
    # a closed box surface, cut across x = 0.5 + a little: one side moved rigidly, the other left
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0)).subdivide().subdivide()
    V, F = np.asarray(box.vertices) + 0.5, np.asarray(box.faces)
    result = xfem.tetrahedralize_surface(V, F, edge_length=0.15, threads=1)
    model = xfem.xfem_model(result.mesh, 1e3)
    plane = 0.53
    model.cut(xfem.plane_cut_solid((plane, 0.5, 0.5), (1.0, 0.0, 0.0), 3.0, 1e-4))
    count, label = model.components()
    assert count == 2
    X = model.X[model.dof_node]
    # the sides by the nodes with one DOF: a node of a tet across the cut has one DOF per side, both at its rest
    # position (fTetWild's coarse tets span the box, so even a corner at x = 1 may carry the left side's DOF)
    single = np.bincount(model.dof_node)[model.dof_node] == 1
    right_label, left_label = (np.unique(label[single & side]) for side in (X[:, 0] > plane, X[:, 0] < plane))
    assert len(right_label) == len(left_label) == 1 and right_label[0] != left_label[0]
    right = label == right_label[0]
    shift = np.array([0.0, 0.0, 0.25])
    model.state = xfem.State(X + right[:, None] * shift, np.zeros_like(X))
    Vd, Fd, piece, vertex = xfem.cut_surface(model, result.embedding, V, F)
    assert Fd.shape == F.shape and np.array_equal(vertex[Fd], F)  # the user's triangles, in their order
    centroid_right = V[F].mean(axis=1)[:, 0] > plane
    # every triangle moves whole with the side of its centroid: the straddling ones are not stretched
    expected = V[F] + centroid_right[:, None, None] * shift
    np.testing.assert_allclose(Vd[Fd], expected, atol=1e-9)
    assert len(np.unique(piece)) == 2 and np.all(piece[centroid_right] == piece[centroid_right][0])
    # the vertices on the cut's line are duplicated, once per side
    assert len(Vd) > len(V) and len(np.unique(vertex)) == len(V)
    with pytest.raises(ValueError, match="V: expected the"):
        xfem.cut_surface(model, result.embedding, V[:-1], F)
    with pytest.raises(ValueError, match="model"):
        xfem.cut_surface(result.mesh, result.embedding, V, F)  # pyright: ignore[reportArgumentType]


@pytest.mark.slow
@pytest.mark.parametrize("name", sorted(set(CHARACTERS) - {"QuaterniusWorkerDense"}))  # the dense one: ~2 min
def test_corpus_characters_are_tetrahedralized(name):
    # open seams, several skins, parts inside parts, clothing: every character gets tets, its skin rides on them
    mesh = load_character(name).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    result = xfem.tetrahedralize_surface(V, F)
    diagonal = float(np.linalg.norm(V.max(0) - V.min(0)))
    q = result.quality
    assert q.tets == result.mesh.n_elements > 200 and q.min_dihedral_deg > 1.0 and q.min_volume_ratio > 0.01
    np.testing.assert_allclose(result.embedding.positions(result.mesh.X), V, atol=1e-9 * diagonal)
    # most of the skin within a few envelopes of the tets (open sheets, if any, lie farther)
    assert np.quantile(result.embedding.distance, 0.99) < 5 * EPSILON * diagonal


def test_tetgen_is_optional(monkeypatch):
    monkeypatch.setitem(sys.modules, "tetgen", None)  # ``import tetgen`` now raises ImportError
    sphere = trimesh.creation.icosphere(subdivisions=1)
    with pytest.raises(ModuleNotFoundError, match=r"jaxcga\[tetgen\]"):
        xfem.tetrahedralize(sphere.vertices, sphere.faces)
    result = xfem.tetrahedralize_surface(sphere.vertices, sphere.faces, edge_length=0.2, threads=1)
    assert abs(float(jnp.sum(result.mesh.volumes())) - sphere.volume) < EPSILON * 2 * sphere.area
    # inward faces: fTetWild's inside is the same
    result = xfem.tetrahedralize_surface(sphere.vertices, sphere.faces[:, ::-1], edge_length=0.2, threads=1)
    assert abs(float(jnp.sum(result.mesh.volumes())) - sphere.volume) < EPSILON * 2 * sphere.area


def test_bad_input():
    sphere = trimesh.creation.icosphere(subdivisions=1)
    V, F = sphere.vertices, sphere.faces
    for kwargs, name in (
        ({"edge_length": 0.0}, "edge_length"),
        ({"edge_length": np.nan}, "edge_length"),
        ({"epsilon": -1e-3}, "epsilon"),
        ({"stop_quality": 2.0}, "stop_quality"),
        ({"max_iterations": -1}, "max_iterations"),
        ({"threads": 0}, "threads"),
    ):
        with pytest.raises(ValueError, match=name):
            xfem.tetrahedralize_surface(V, F, **kwargs)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="F"):
        xfem.tetrahedralize_surface(V, F + 100)
    sheet = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.1], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="encloses no volume"):  # an open sheet: no inside
        xfem.tetrahedralize_surface(sheet, np.array([[0, 1, 2], [0, 2, 3]]), edge_length=0.3, threads=1)
