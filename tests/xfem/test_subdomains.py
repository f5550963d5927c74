"""Nodal and element subdomains under cuts (XFEM paper sec. 4.2, 4.4, Algorithm 1 lines 1-19): volumes against
closed forms (a slab of thickness epsilon across the unit cube removes epsilon), piece counts against the sides
of the cut plane that a 1-ring reaches (the 1-rings of these meshes are convex), AABB culling against a numpy
box test, ids and parents."""

import igl
import manifold3d
import numpy as np
import pytest

from xfem import apply_cut, boundary_faces, box_tets, five_tet_cube, plane_cut_solid, polyhedron_moments, subdomains

EPS = 1e-3


def _plane(point, normal, extent=3.0, epsilon=EPS):
    return plane_cut_solid(np.asarray(point, np.float64), np.asarray(normal, np.float64), extent, epsilon)


def _moments(solid):
    mesh = solid.to_mesh64()
    return polyhedron_moments(np.asarray(mesh.vert_properties)[:, :3], np.asarray(mesh.tri_verts, np.int64))


def _element_pieces(sub):
    """(volume, centroid) of every current element subdomain, by the divergence theorem on its mesh."""
    pieces = []
    for e in range(sub.n_elements):
        for sid in sub.element_subdomains(e):
            m = _moments(sub.element_solid(sid))
            pieces.append((float(m.volume), np.asarray(m.first) / m.volume))
    return pieces


def _signed(X, point, normal):
    normal = np.asarray(normal, np.float64)
    return (X - np.asarray(point)) @ (normal / np.linalg.norm(normal))


def _check_ids(sub, report=None):
    """Live ids belong to their owner; every child's parent is the retired id it replaced; the arrays of ids agree
    with the lists."""
    first, counts = sub.first_node_subdomains(), sub.node_subdomain_counts()
    for i in range(sub.n_nodes):
        ids = sub.node_subdomains(i)
        assert counts[i] == len(ids) and first[i] == (ids[0] if ids else -1)
        for sid in ids:
            assert sub.node_of(sid) == i and sub.node_alive(sid)
    for e in range(sub.n_elements):
        for sid in sub.element_subdomains(e):
            assert sub.element_of(sid) == e and sub.element_alive(sid)
    owner, ids = sub.element_subdomain_arrays(np.arange(sub.n_elements)[::-1])
    listed = [(e, sid) for e in range(sub.n_elements)[::-1] for sid in sub.element_subdomains(e)]
    assert list(zip(owner.tolist(), ids.tolist())) == listed
    if report is not None:
        for old, new in report.node_children.items():
            assert not sub.node_alive(old)
            assert all(sub.node_parent(s) == old and sub.node_of(s) == sub.node_of(old) for s in new)
        for old, new in report.element_children.items():
            assert not sub.element_alive(old)
            assert all(sub.element_parent(s) == old and sub.element_of(s) == sub.element_of(old) for s in new)


def test_plane_through_the_five_tet_cube_halves_every_subdomain():
    sub = subdomains(five_tet_cube())
    report = apply_cut(sub, _plane([0.5, 0.5, 0.5], [0, 0, 1]))
    pieces = _element_pieces(sub)
    volume = sum(v for v, _ in pieces)
    assert abs(volume - (1 - EPS)) < 1e-12
    below = sum(v for v, c in pieces if c[2] < 0.5)
    assert abs(below - (0.5 - EPS / 2)) < 1e-12
    # every tet has corners at z = 0 and z = 1, so every tet and every 1-ring is halved
    assert all(len(sub.element_subdomains(e)) == 2 for e in range(5))
    assert all(len(sub.node_subdomains(i)) == 2 for i in range(8))
    assert report.candidates.tolist() == list(range(5))
    assert report.nodes_split.tolist() == list(range(8)) and report.elements_split.tolist() == list(range(5))
    assert sorted(report.node_children) == list(range(8))
    assert all(len(c) == 2 for c in report.node_children.values())
    assert report.stats.n_booleans == 5 + 8
    _check_ids(sub, report)
    # the initial ids are the node and element indices, the pieces' parents
    assert all(sub.node_parent(s) == i for i in range(8) for s in sub.node_subdomains(i))


def test_only_the_1_rings_the_plane_crosses_are_split():
    mesh = box_tets((2, 2, 2))
    sub = subdomains(mesh)
    point, normal = [0.5, 0.5, 0.3], [0.0, 0.0, 1.0]
    report = apply_cut(sub, _plane(point, normal))
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    offsets, elements = sub.ring_offsets, sub.ring_elements
    for i in range(sub.n_nodes):
        ring = T[elements[offsets[i] : offsets[i + 1]]]
        d = _signed(X[np.unique(ring)], point, normal)
        crossed = d.min() < -EPS / 2 and d.max() > EPS / 2  # the ring reaches both sides of the slab
        assert len(sub.node_subdomains(i)) == (2 if crossed else 1), i
        assert sub.node_built(i) == (d.min() < EPS / 2)
        # nodal pieces lose what the element pieces of the ring's tets lose
        kept = sum(_moments(sub.node_solid(s)).volume for s in sub.node_subdomains(i))
        ring_tets = elements[offsets[i] : offsets[i + 1]]
        element_kept = sum(_moments(sub.element_solid(s)).volume for e in ring_tets for s in sub.element_subdomains(e))
        assert abs(kept - element_kept) < 1e-13
    assert set(report.nodes_split.tolist()) == set(np.flatnonzero(X[:, 2] < 0.6).tolist())
    assert abs(sum(v for v, _ in _element_pieces(sub)) - (1 - EPS)) < 1e-12
    _check_ids(sub, report)


def test_a_cut_outside_the_body_touches_nothing():
    sub = subdomains(box_tets((2, 2, 2)))
    report = apply_cut(sub, _plane([0.5, 0.5, 5.0], [0, 0, 1]))
    assert len(report.boxed) == len(report.candidates) == report.stats.n_booleans == 0
    assert len(report.elements_touched) == 0 and len(report.nodes_touched) == 0
    assert report.node_children == {} and report.element_children == {}
    assert not any(sub.node_built(i) for i in range(sub.n_nodes))
    assert not any(sub.element_built(e) for e in range(sub.n_elements))


def test_perpendicular_cuts_give_four_pieces():
    sub = subdomains(five_tet_cube())
    first = apply_cut(sub, _plane([0.5, 0.5, 0.5], [0, 0, 1]))
    second = apply_cut(sub, _plane([0.5, 0.5, 0.5], [1, 0, 0]))
    pieces = _element_pieces(sub)
    assert abs(sum(v for v, _ in pieces) - (1 - 2 * EPS + EPS**2)) < 1e-12
    quadrant = {(a, b): 0.0 for a in (0, 1) for b in (0, 1)}
    for v, c in pieces:
        quadrant[int(c[0] > 0.5), int(c[2] > 0.5)] += v
    for v in quadrant.values():
        assert abs(v - (0.5 - EPS / 2) ** 2) < 1e-12
    # the tets and 1-rings of this mesh are convex (a 1-ring is a corner tet or the cube minus one corner tet):
    # one piece per quadrant that holds one of their corners
    X, T = np.asarray(sub.X), np.asarray(sub.T)

    def quadrants(nodes):
        return len({(X[k, 0] > 0.5, X[k, 2] > 0.5) for k in nodes})

    assert [len(sub.element_subdomains(e)) for e in range(5)] == [quadrants(t) for t in T] == [4, 3, 3, 3, 3]
    for i in range(8):
        ring = np.unique(T[sub.ring_elements[sub.ring_offsets[i] : sub.ring_offsets[i + 1]]])
        assert len(sub.node_subdomains(i)) == quadrants(ring) == (4 if i in (0, 3, 5, 6) else 3)
    assert set(second.node_children) <= {s for c in first.node_children.values() for s in c}
    for i in range(8):
        for s in sub.node_subdomains(i):
            chain = [s]
            while chain[-1] >= 0:
                chain.append(sub.node_parent(chain[-1]))
            assert chain[-2] == i and len(chain) == (4 if s in sum(second.node_children.values(), ()) else 3)
    _check_ids(sub, second)


def test_a_repeated_cut_splits_pieces_again_and_the_same_cut_twice_is_a_no_op():
    sub = subdomains(five_tet_cube())
    apply_cut(sub, _plane([0.5, 0.5, 0.5], [0, 0, 1]))
    second = apply_cut(sub, _plane([0.5, 0.5, 0.25], [0, 0, 1]))
    layers = [0.0, 0.0, 0.0]
    for v, c in _element_pieces(sub):
        layers[int(c[2] > 0.25) + int(c[2] > 0.5)] += v
    np.testing.assert_allclose(layers, [0.25 - EPS / 2, 0.25 - EPS, 0.5 - EPS / 2], rtol=0, atol=1e-12)
    assert len(second.element_children) > 0
    assert all(sub.element_parent(sub.element_parent(s)) >= 0 for s in sum(second.element_children.values(), ()))
    again = apply_cut(sub, _plane([0.5, 0.5, 0.25], [0, 0, 1]))
    assert len(again.candidates) == 5 and again.stats.n_booleans > 0
    assert len(again.elements_touched) == 0 and len(again.nodes_touched) == 0
    assert again.node_children == {} and again.element_children == {}


def test_aabb_culling_and_touched_sets_on_a_3x3x3_box():
    mesh = box_tets((3, 3, 3))
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    sub = subdomains(mesh)
    point, normal = [0.47, 0.52, 0.6], [0.05, 0.08, 1.0]  # within 0.54 < z < 0.66 in the cube
    cut = _plane(point, normal, extent=1.8)  # spans the cube; its box reaches the top layer of cells
    report = apply_cut(sub, cut)
    corners = np.asarray(cut.to_mesh64().vert_properties)[:, :3]
    low, high = corners.min(axis=0), corners.max(axis=0)
    boxes_meet = np.all((X[T].min(axis=1) <= high) & (X[T].max(axis=1) >= low), axis=1)
    assert report.boxed.tolist() == np.flatnonzero(boxes_meet).tolist()
    d = _signed(X, point, normal)
    dt = d[T]
    meets = (dt.min(axis=1) < EPS / 2) & (dt.max(axis=1) > -EPS / 2)
    assert np.abs(np.abs(d) - EPS / 2).min() > 1e-6  # no node near the slab's faces: meets is unambiguous
    assert report.candidates.tolist() == report.elements_touched.tolist() == np.flatnonzero(meets).tolist()
    assert 0 < meets.sum() < boxes_meet.sum() < len(T)  # the box test is conservative but culls
    assert report.nodes_touched.tolist() == np.unique(T[meets]).tolist()
    # meshes are built for the touched tets and 1-rings only
    assert [sub.element_built(e) for e in range(len(T))] == meets.tolist()
    assert [sub.node_built(i) for i in range(sub.n_nodes)] == np.isin(np.arange(sub.n_nodes), T[meets]).tolist()
    for i in range(sub.n_nodes):
        ring = d[np.unique(T[sub.ring_elements[sub.ring_offsets[i] : sub.ring_offsets[i + 1]]])]
        assert len(sub.node_subdomains(i)) == (2 if ring.min() < -EPS / 2 and ring.max() > EPS / 2 else 1)
    _check_ids(sub, report)
    # the Boolean count: one per candidate element, one per touched node (each had one subdomain)
    assert report.stats.n_booleans == len(report.candidates) + len(report.nodes_touched)


def test_gentle_perturbation_moves_an_aligned_cut_off_the_nodes():
    mesh = box_tets((2, 2, 2))
    aligned = _plane([0.5, 0.5, 0.5 + EPS / 2], [0, 0, 1])  # its lower face holds the nodes at z = 0.5
    sub = subdomains(mesh)
    report = apply_cut(sub, aligned, perturb=1e-7, seed=1)
    assert not np.allclose(report.motion, np.eye(4)[:3], rtol=0, atol=1e-9)
    moved = aligned.transform(report.motion)
    mesh64 = moved.to_mesh64()
    distance2 = np.asarray(
        igl.point_mesh_squared_distance(
            np.asarray(mesh.X), np.asarray(mesh64.vert_properties)[:, :3], np.asarray(mesh64.tri_verts, np.int64)
        )[0]
    )
    assert distance2.min() >= 1e-18  # farther than perturb / 100
    # a rigid motion keeps the slab's thickness; the tilt changes its section by ~1e-14
    assert abs(sum(v for v, _ in _element_pieces(sub)) - (1 - EPS)) < 1e-12
    # the nodes on the slab's face are now off it: their 1-rings are halved (the others may lose slivers)
    assert all(len(sub.node_subdomains(int(i))) == 2 for i in np.flatnonzero(np.asarray(mesh.X)[:, 2] == 0.5))
    plain = subdomains(mesh)
    assert np.allclose(apply_cut(plain, _plane([0.5, 0.5, 0.3], [0, 0, 1]), perturb=1e-7).motion, np.eye(4)[:3])


def test_bad_input():
    sub = subdomains(five_tet_cube())
    with pytest.raises(ValueError, match="mesh"):
        subdomains(np.zeros((4, 3)))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="sub"):
        apply_cut("sub", _plane([0.5, 0.5, 0.5], [0, 0, 1]))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="cut"):
        apply_cut(sub, np.zeros(3))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="cut"):
        apply_cut(sub, manifold3d.Manifold())
    with pytest.raises(ValueError, match="perturb"):
        apply_cut(sub, _plane([0.5, 0.5, 0.5], [0, 0, 1]), perturb=-1.0)
    apply_cut(sub, _plane([0.5, 0.5, 0.5], [0, 0, 1]))
    with pytest.raises(ValueError, match="sid"):
        sub.node_solid(0)  # split into two children


def test_subdomains_inside_a_thick_cut_disappear():
    mesh = box_tets((2, 2, 2))
    X = np.asarray(mesh.X)
    sub = subdomains(mesh)
    # the lower layer of cells lies inside the block and meets none of its faces (the winding-number culling)
    block = manifold3d.Manifold.cube((1.2, 1.2, 0.7)).translate((-0.1, -0.1, -0.1))
    report = apply_cut(sub, block)
    lower = np.flatnonzero(X[np.asarray(mesh.T)][:, :, 2].max(axis=1) <= 0.5).tolist()
    assert len(lower) == 24 and set(lower) <= set(report.candidates.tolist())
    assert all(sub.element_subdomains(e) == [] and report.element_children[e] == () for e in lower)
    assert abs(sum(v for v, _ in _element_pieces(sub)) - 0.4) < 1e-12
    for i in range(sub.n_nodes):
        # rings at z = 0 are gone, the others lose their lower part and keep their id (one piece each)
        assert sub.node_subdomains(i) == ([] if X[i, 2] == 0 else [i])
    _check_ids(sub, report)
    assert report.nodes_split.tolist() == []
    assert {k for k, v in report.node_children.items() if v == ()} == set(np.flatnonzero(X[:, 2] == 0).tolist())


def test_batch_built_solids_are_the_rings_and_tets():
    """``apply_cut`` builds the initial 1-ring and tet solids of a cut in one vectorized pass: vertex for vertex
    and triangle for triangle the boundary of each ring's tets (``boundary_faces``) and each tet's faces."""
    mesh = box_tets((3, 2, 2))
    sub = subdomains(mesh)
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    nodes, elements = list(range(sub.n_nodes)), list(range(sub.n_elements))
    sub._build_initial(nodes, elements)
    assert all(sub.node_built(i) for i in nodes) and all(sub.element_built(e) for e in elements)
    pairs = [
        (sub.node_solid(i), boundary_faces(T[sub.ring_elements[sub.ring_offsets[i] : sub.ring_offsets[i + 1]]]))
        for i in nodes
    ]
    pairs += [(sub.element_solid(e), T[e][[[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]]) for e in elements]
    for solid, faces in pairs:  # against the Manifold of the same mesh built directly (it orders its output)
        used, local = np.unique(faces, return_inverse=True)
        reference = manifold3d.Manifold(
            manifold3d.Mesh64(vert_properties=X[used], tri_verts=local.reshape(-1, 3).astype(np.uint64))
        )
        built, expected = solid.to_mesh64(), reference.to_mesh64()
        np.testing.assert_array_equal(np.asarray(built.vert_properties), np.asarray(expected.vert_properties))
        np.testing.assert_array_equal(np.asarray(built.tri_verts), np.asarray(expected.tri_verts))
