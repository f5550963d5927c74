"""Tetrahedral meshes (XFEM paper sec. 3.2): generator volumes against the analytic box / cube volumes,
conformity and outward boundary faces (face counts, surface area, the divergence theorem), adjacency and
node rings against brute force, orientation repair, TetGen meshes of closed surfaces against trimesh's
volume and area, meshio round trips, gradients of the volumes, bad input."""

from __future__ import annotations

import igl
import jax
import jax.numpy as jnp
import meshio
import numpy as np
import pytest
import trimesh
from hypothesis import given, settings
from hypothesis import strategies as st

from tests.shared import check_gradient
from xfem import (
    TetMesh,
    boundary_faces,
    box_tets,
    element_adjacency,
    five_tet_cube,
    node_rings,
    one_tet,
    read_tet_mesh,
    tet_mesh,
    tet_volumes,
    tetrahedralize,
)


def _face_geometry(X, faces):
    """Centroids (k, 3) and area-weighted normals (k, 3) (length = area) of triangles."""
    p = X[faces]
    return p.mean(axis=1), np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) / 2


def _divergence_volume(X, faces):
    """The enclosed volume by the divergence theorem with div(x) = 3: (1/3) sum over faces of c . n A."""
    centroid, normal = _face_geometry(X, faces)
    return np.einsum("ij,ij->", centroid, normal) / 3


def _check_boundary(mesh: TetMesh, volume: float, area: float):
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    faces = boundary_faces(T)
    centroid, normal = _face_geometry(X, faces)
    np.testing.assert_allclose(np.linalg.norm(normal, axis=1).sum(), area, rtol=1e-12)
    np.testing.assert_allclose(_divergence_volume(X, faces), volume, rtol=1e-12)
    # outward: each face's normal points away from the centroid of its own tet
    tet, _ = np.nonzero(element_adjacency(T) < 0)
    assert len(tet) == len(faces)
    away = np.einsum("ij,ij->i", centroid - X[T[tet]].mean(axis=1), normal)
    assert away.min() > 0
    return faces


def test_one_tet():
    mesh = one_tet()
    np.testing.assert_array_equal(mesh.X, [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    np.testing.assert_allclose(mesh.volumes(), [1 / 6], rtol=1e-15)
    assert (mesh.n_nodes, mesh.n_elements) == (4, 1)
    _check_boundary(mesh, 1 / 6, 1.5 + np.sqrt(3) / 2)


@pytest.mark.parametrize(
    "cells, size, origin",
    [((1, 1, 1), (1.0, 1.0, 1.0), (0.0, 0.0, 0.0)), ((3, 2, 4), (2.0, 3.0, 0.5), (-1.0, 0.5, 2.0))],
)
def test_box_tets_volumes_faces_and_conformity(cells, size, origin):
    mesh = box_tets(cells, size, origin)
    n, m, k = cells
    assert mesh.n_nodes == (n + 1) * (m + 1) * (k + 1) and mesh.n_elements == 6 * n * m * k
    X = np.asarray(mesh.X)
    np.testing.assert_allclose(X.min(axis=0), origin, rtol=1e-15)
    np.testing.assert_allclose(X.max(axis=0), np.add(origin, size), rtol=1e-15)
    i, j, l_ = 1 % (n + 1), 1 % (m + 1), 1 % (k + 1)  # the documented node numbering
    np.testing.assert_allclose(
        X[(i * (m + 1) + j) * (k + 1) + l_], np.add(origin, np.multiply((i, j, l_), size) / np.array(cells)), rtol=1e-15
    )
    volume = np.prod(size)
    volumes = np.asarray(mesh.volumes())
    np.testing.assert_allclose(volumes, volume / (6 * n * m * k), rtol=1e-13)
    np.testing.assert_allclose(volumes.sum(), volume, rtol=1e-14)
    a, b, c = size
    faces = _check_boundary(mesh, volume, 2 * (a * b + b * c + c * a))
    # conforming: every face is either on the box surface (2 triangles per cell face there) or shared by
    # exactly two tets; a non-conforming split would leave unmatched faces inside
    assert len(faces) == 2 * (n * m + m * k + n * k) * 2
    on_surface = np.isclose(X[faces], X.min(axis=0)) | np.isclose(X[faces], X.max(axis=0))
    assert np.all(np.all(on_surface, axis=1).any(axis=1))  # the three corners share a box face


@settings(max_examples=25, deadline=None)
@given(
    cells=st.tuples(*[st.integers(1, 3)] * 3),
    size=st.tuples(*[st.floats(0.1, 10.0)] * 3),
    origin=st.tuples(*[st.floats(-5.0, 5.0)] * 3),
)
def test_box_tets_invariants(cells, size, origin):
    mesh = box_tets(cells, size, origin)
    T = np.asarray(mesh.T)
    adjacency = element_adjacency(T)
    X = np.asarray(mesh.X)
    edges = X[T[:, 1:]] - X[T[:, :1]]
    volumes = np.linalg.det(edges) / 6  # numpy, not JAX: no compilation per hypothesis example
    assert volumes.min() > 0
    np.testing.assert_allclose(volumes.sum(), np.prod(size), rtol=1e-12)
    np.testing.assert_allclose(_divergence_volume(X, boundary_faces(T)), np.prod(size), rtol=1e-10)
    e, a = np.nonzero(adjacency >= 0)
    assert np.all((adjacency[adjacency[e, a]] == e[:, None]).sum(axis=1) == 1)  # symmetric, listed once


def test_five_tet_cube():
    mesh = five_tet_cube(2.0, origin=(1.0, -1.0, 0.5))
    np.testing.assert_allclose(mesh.volumes(), 8.0 * np.array([1 / 3, 1 / 6, 1 / 6, 1 / 6, 1 / 6]), rtol=1e-14)
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    central = X[T[0]]
    edges = np.linalg.norm(central[:, None] - central[None], axis=2)[np.triu_indices(4, 1)]
    np.testing.assert_allclose(edges, 2.0 * np.sqrt(2.0), rtol=1e-15)  # regular
    faces = _check_boundary(mesh, 8.0, 24.0)
    assert len(faces) == 12
    assert set(element_adjacency(T)[0]) == {1, 2, 3, 4}  # the central tet touches every corner tet
    assert np.all((element_adjacency(T)[1:] >= 0).sum(axis=1) == 1)


def _brute_force_adjacency(T):
    adjacency = np.full(T.shape, -1)
    for e in range(len(T)):
        for a in range(4):
            face = set(T[e]) - {T[e, a]}
            for f in range(len(T)):
                if f != e and face <= set(T[f]):
                    adjacency[e, a] = f
    return adjacency


def test_element_adjacency_and_node_rings_against_brute_force():
    mesh = box_tets((2, 2, 1))
    T = np.asarray(mesh.T)
    np.testing.assert_array_equal(element_adjacency(T), _brute_force_adjacency(T))
    offsets, elements = node_rings(T, n=mesh.n_nodes + 2)
    assert offsets.shape == (mesh.n_nodes + 3,) and elements.shape == (4 * len(T),)
    for i in range(mesh.n_nodes + 2):
        np.testing.assert_array_equal(elements[offsets[i] : offsets[i + 1]], np.flatnonzero((T == i).any(axis=1)))
    np.testing.assert_array_equal(node_rings(T)[0], offsets[:-2])
    # node indices too large for the one-int64 face keys take the row-wise path
    np.testing.assert_array_equal(element_adjacency(T + 2**21), element_adjacency(T))
    np.testing.assert_array_equal(boundary_faces(T + 2**21), boundary_faces(T) + 2**21)


def test_tet_mesh_reorients_and_keeps_vertex_sets():
    mesh = box_tets((2, 1, 1), size=(1.0, 2.0, 3.0))
    T = np.asarray(mesh.T)
    flip = np.random.default_rng(0).random(len(T)) < 0.5
    flipped = np.where(flip[:, None], T[:, [1, 0, 2, 3]], T)
    fixed = tet_mesh(mesh.X, flipped)
    assert fixed.X.dtype == jnp.float64 and jnp.issubdtype(fixed.T.dtype, jnp.integer)
    np.testing.assert_array_equal(np.sort(np.asarray(fixed.T), axis=1), np.sort(T, axis=1))
    np.testing.assert_array_equal(np.asarray(fixed.T)[~flip], T[~flip])
    np.testing.assert_allclose(fixed.volumes(), mesh.volumes(), rtol=1e-14)


X4 = np.vstack([np.zeros(3), np.eye(3)])


@pytest.mark.parametrize(
    "X, T, match",
    [
        (X4[:, :2], [[0, 1, 2, 3]], "X: expected finite positions of shape"),
        (np.where(X4 == 1, np.nan, X4), [[0, 1, 2, 3]], "X: non-finite"),
        (X4, [[0, 1, 2]], r"T: expected integer tets of shape \(m, 4\)"),
        (X4, [[0.0, 1.0, 2.0, 3.0]], "T: expected integer tets"),
        (X4, [[0, 1, 2, 4]], r"T: node indices must lie in \[0, 4\)"),
        (X4, np.zeros((0, 4), int), "T: expected at least one"),
        (X4, [[0, 1, 2, 2]], "T: 1 degenerate"),
        (np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float), [[0, 1, 2, 3]], "T: 1 degenerate"),
        (np.vstack([X4, [[5.0, 5.0, 5.0]]]), [[0, 1, 2, 3]], r"X: nodes \[4\] \(1 in all\) are in no tetrahedron"),
    ],
)
def test_tet_mesh_bad_input(X, T, match):
    with pytest.raises(ValueError, match=match):
        tet_mesh(X, T)


def test_generators_bad_input():
    with pytest.raises(ValueError, match="cells: expected three ints >= 1"):
        box_tets((0, 1, 1))
    with pytest.raises(ValueError, match="cells: expected three ints"):
        box_tets((1, 1))
    with pytest.raises(ValueError, match="size: expected three positive extents"):
        box_tets(size=(1.0, -1.0, 1.0))
    with pytest.raises(ValueError, match="origin: expected a finite point"):
        box_tets(origin=(0.0, np.inf, 0.0))
    with pytest.raises(ValueError, match="size: expected a positive edge length"):
        five_tet_cube(0.0)


def test_topology_bad_input():
    with pytest.raises(ValueError, match="T: expected integer tets"):
        boundary_faces(np.zeros((2, 3), int))
    with pytest.raises(ValueError, match="T: node indices must lie in"):
        element_adjacency([[0, 1, 2, -1]])
    with pytest.raises(ValueError, match=r"n: expected an int >= T.max\(\) \+ 1 = 4"):
        node_rings([[0, 1, 2, 3]], n=3)
    three = [[0, 1, 2, 3], [0, 1, 2, 4], [0, 2, 1, 5]]  # face {0, 1, 2} in three tets
    with pytest.raises(ValueError, match="shared by 3 tetrahedra"):
        element_adjacency(three)


@pytest.mark.slow
def test_tet_volumes_gradient_and_jit():
    mesh = box_tets((1, 1, 2), size=(1.0, 2.0, 1.0))
    T = mesh.T
    X = mesh.X + 0.05 * jnp.asarray(np.random.default_rng(1).normal(size=mesh.X.shape))

    @jax.jit
    def loss(flat):
        return jnp.sum(jnp.sin(tet_volumes(flat.reshape(-1, 3), T)))

    check_gradient(loss, X.ravel())
    # closed form: dV/dX3 = ((X1 - X0) x (X2 - X0)) / 6
    x = X[T[0]]
    grad = jax.grad(lambda X: tet_volumes(X, T)[0])(X)
    np.testing.assert_allclose(grad[T[0, 3]], jnp.cross(x[1] - x[0], x[2] - x[0]) / 6, rtol=1e-13)
    np.testing.assert_allclose(jax.jit(tet_volumes)(X, T), tet_volumes(X, T), rtol=1e-14)
    with pytest.raises(ValueError, match=r"T: node indices must lie in \[0, 12\)"):
        tet_volumes(X, jnp.asarray(T).at[0, 0].set(12))
    # a check under jit: JAX raises a RuntimeError, or a ValueError when the executable was cached (on a GPU when
    # the result is ready)
    with pytest.raises((RuntimeError, ValueError), match="T: node indices must lie in"):
        jax.block_until_ready(jax.jit(tet_volumes)(X, jnp.asarray(T).at[0, 0].set(12)))
    with pytest.raises(ValueError, match="X: expected float positions"):
        tet_volumes(jnp.ones((12, 3), int), T)


def _surface_checks(mesh: TetMesh, V, F):
    surface = trimesh.Trimesh(V, F, process=False)
    X = np.asarray(mesh.X)
    np.testing.assert_array_equal(X[: len(V)], V)  # the input vertices come first, unchanged
    np.testing.assert_allclose(np.asarray(mesh.volumes()).sum(), surface.volume, rtol=1e-10)
    faces = _check_boundary(mesh, surface.volume, surface.area)
    # the boundary faces lie on the input surface
    distance2 = np.asarray(igl.point_mesh_squared_distance(X[faces].reshape(-1, 3), V, F)[0])
    assert np.sqrt(distance2.max()) < 1e-12 * surface.scale
    return faces


def test_tetrahedralize_icosphere_and_box():
    sphere = trimesh.creation.icosphere(subdivisions=2)
    V, F = np.asarray(sphere.vertices), np.asarray(sphere.faces)
    coarse = tetrahedralize(V, F)
    _surface_checks(coarse, V, F)
    fine = tetrahedralize(V, F, max_volume=0.01)
    _surface_checks(fine, V, F)
    assert fine.n_elements > coarse.n_elements
    assert np.median(np.asarray(fine.volumes())) < 0.01

    box = trimesh.creation.box(extents=(1.0, 2.0, 3.0))
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    plain = tetrahedralize(V, F, quality=False)
    _surface_checks(plain, V, F)
    assert plain.n_nodes <= 9  # no refinement: at most one Steiner point (with -M the face diagonals are constraints)
    refined = tetrahedralize(V, F, max_volume=0.05)
    faces = _surface_checks(refined, V, F)
    assert len(faces) > len(F)  # TetGen split the box faces, yet the boundary covers them exactly
    assert np.asarray(refined.volumes()).max() < 2 * 0.05


def test_tetrahedralize_bad_input():
    box = trimesh.creation.box()
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    with pytest.raises(ValueError, match="F: the surface is not closed"):
        tetrahedralize(V, F[:-1])
    with pytest.raises(ValueError, match=r"V: vertices \[8\]"):
        tetrahedralize(np.vstack([V, np.zeros(3)]), F)
    with pytest.raises(ValueError, match="F: expected integer faces"):
        tetrahedralize(V, F[:, :2])
    with pytest.raises(ValueError, match=r"F: vertex indices must lie in \[0, 8\)"):
        tetrahedralize(V, F + 1)
    with pytest.raises(ValueError, match="V: non-finite"):
        tetrahedralize(np.where(V > 0, np.nan, V), F)
    with pytest.raises(ValueError, match="max_volume: expected None or a positive volume"):
        tetrahedralize(V, F, max_volume=-1.0)
    with pytest.raises(ValueError, match="V: duplicate vertex positions"):
        tetrahedralize(np.vstack([V, V]), np.vstack([F, F + 8]))
    other = V + np.array([0.5, 0.3, 0.2])  # two closed, interpenetrating boxes
    with pytest.raises(ValueError, match="F: the surface intersects itself"):
        tetrahedralize(np.vstack([V, other]), np.vstack([F, F + 8]))


@pytest.mark.parametrize("suffix", [".vtu", ".msh"])
def test_read_tet_mesh_round_trip(tmp_path, suffix):
    mesh = box_tets((2, 1, 1), size=(2.0, 1.0, 1.0), origin=(0.5, 0.0, 0.0))
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    path = tmp_path / f"box{suffix}"
    meshio.write(path, meshio.Mesh(X, [("tetra", T)]))
    back = read_tet_mesh(path)
    np.testing.assert_array_equal(back.X, X)
    np.testing.assert_array_equal(back.T, T)
    # a node in no tet (first) and a triangle block: the node is dropped, the rest renumbered
    extra = tmp_path / f"extra{suffix}"
    meshio.write(
        extra,
        meshio.Mesh(
            np.vstack([[9.0, 9.0, 9.0], X]),
            [("triangle", np.array([[0, 1, 2]])), ("tetra", T[:6] + 1), ("tetra", T[6:] + 1)],
        ),
    )
    back = read_tet_mesh(extra)
    np.testing.assert_array_equal(back.X, X)
    np.testing.assert_array_equal(back.T, T)


def test_read_tet_mesh_errors(tmp_path):
    path = tmp_path / "surface.vtu"
    meshio.write(path, meshio.Mesh(np.eye(3), [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(ValueError, match=r"path: '.*surface\.vtu' has no tetra cells \(cell types: \['triangle'\]\)"):
        read_tet_mesh(path)
    with pytest.raises(ValueError, match="path: meshio cannot read '.*missing.vtu'"):
        read_tet_mesh(tmp_path / "missing.vtu")
    broken = tmp_path / "broken.vtu"
    broken.write_text("not xml")
    with pytest.raises(ValueError, match="path: meshio cannot read '.*broken.vtu'"):
        read_tet_mesh(broken)
