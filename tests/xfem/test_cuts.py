"""Swept cut surfaces and thin cut solids (XFEM paper sec. 4.1) against closed forms, scipy rotations,
trimesh and manifold3d volumes. The sweeps share one shape (a 3-point edge, 3 keys, 5 samples per
interval) so that the blending compiles once."""

import jax.numpy as jnp
import manifold3d
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import jaxcga as cga
from xfem import cut_solid as make_cut_solid
from xfem import plane_cut_solid, sweep_between, swept_surface, thicken


def _triangle_areas(V, F):
    x = np.asarray(V)[F]
    return 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=-1)


def _translations(points):
    return cga.translator(jnp.asarray(points, jnp.float64))  # translator blades are accepted as motors


def _screws(axis, centre, angles, pitch):
    """Motors of the screw about the line (centre, axis): rotate by each angle, advance pitch * angle."""
    axis, centre = np.asarray(axis, np.float64), np.asarray(centre, np.float64)
    angles = jnp.asarray(angles, jnp.float64)
    R = cga.rotor(jnp.asarray(axis), angles)
    M = cga.motor(R, jnp.asarray(axis)[None] * (pitch * angles)[:, None])
    return (cga.translator(jnp.asarray(centre)) * M * cga.translator(jnp.asarray(-centre))).embed(cga.KINDS["motor"])


def _screw_reference(edge, axis, centre, angle, pitch):
    axis = np.asarray(axis) / np.linalg.norm(axis)
    return Rotation.from_rotvec(angle * axis).apply(edge - centre) + centre + pitch * angle * np.asarray(axis)


def test_translation_sweep_is_the_exact_rectangle():
    L, W = 1.5, 0.75
    edge = jnp.asarray([[0.0, 0.0, 0.0], [0.5, 0.0, 0.0], [L, 0.0, 0.0]])
    V, F = swept_surface(edge, _translations([[0.0, 0.0, 0.0], [0.0, W / 2, 0.0], [0.0, W, 0.0]]), 5)
    assert V.shape == (11 * 3, 3) and F.shape == (2 * 10 * 2, 3)
    np.testing.assert_allclose(np.asarray(V)[:, 2], 0.0, atol=1e-15)
    np.testing.assert_allclose(np.asarray(V)[::3, 1], np.linspace(0.0, W, 11), atol=1e-14)
    areas = _triangle_areas(V, F)
    assert areas.sum() == pytest.approx(L * W, rel=1e-14)
    # normal = edge direction (+x) x sweep direction (+y) = +z on every triangle
    x = np.asarray(V)[F]
    assert np.all(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])[:, 2] > 0)


def test_screw_sweep_samples_are_exact_fractional_screws():
    axis, centre, theta, pitch = np.array([1.0, 2.0, 2.0]) / 3, np.array([0.3, -0.2, 0.1]), 1.2, 0.25
    edge = np.array([[1.0, 0.0, 0.0], [1.5, 0.5, 0.0], [2.0, 0.5, 0.5]])
    s = 5
    # two intervals (keys at 0, theta, 2 theta): sample j is the screw by j theta / s
    V, F = swept_surface(jnp.asarray(edge), _screws(axis, centre, [0.0, theta, 2 * theta], pitch), s)
    V = np.asarray(V).reshape(2 * s + 1, 3, 3)
    for j in range(2 * s + 1):
        np.testing.assert_allclose(V[j], _screw_reference(edge, axis, centre, j * theta / s, pitch), atol=1e-13)
    assert F.shape == (2 * 2 * s * 2, 3)


def test_rotation_sweep_is_the_annular_sector():
    # an edge in the plane normal to the axis, radii 0.5 .. 1.5, rotated by theta: a flat annular sector
    theta, s = 2.0, 10
    edge = np.array([[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [1.5, 0.0, 0.0]])
    V, F = swept_surface(jnp.asarray(edge), _screws([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, theta / 2, theta], 0.0), 5)
    V = np.asarray(V)
    np.testing.assert_allclose(V[:, 2], 0.0, atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(V, axis=-1), np.tile([0.5, 1.0, 1.5], s + 1), rtol=1e-14)
    np.testing.assert_allclose(np.arctan2(V[:, 1], V[:, 0]), np.repeat(np.arange(s + 1) * theta / s, 3), atol=1e-14)
    # the polygonal sector: s wedges of chord area r^2 sin(theta / s) / 2
    wedge = 0.5 * np.sin(theta / s) * (1.5**2 - 0.5**2)
    assert _triangle_areas(V, F).sum() == pytest.approx(s * wedge, rel=1e-13)


def test_sweep_between_matches_translation_sweep():
    edge = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.2, 0.0], [2.0, 0.0, 0.3]])
    shift = jnp.asarray([0.1, 1.0, 0.2])
    Va, Fa = sweep_between(edge, edge + shift[None], 10)
    Vb, Fb = swept_surface(edge, _translations(jnp.stack([jnp.zeros(3), shift / 2, shift])), 5)
    np.testing.assert_allclose(np.asarray(Va), np.asarray(Vb), atol=1e-14)
    np.testing.assert_array_equal(Fa, Fb)


def _rectangle(L, W, nx=3, ny=2):
    edge = np.stack([np.linspace(0.0, L, nx + 1), np.zeros(nx + 1), np.zeros(nx + 1)], -1)
    return sweep_between(jnp.asarray(edge), jnp.asarray(edge + [0.0, W, 0.0]), ny)


def test_thickened_rectangle_is_the_exact_slab():
    L, W, eps = 1.5, 0.75, 0.01
    V, F = _rectangle(L, W)
    V2, F2 = thicken(V, F, eps)
    mesh = trimesh.Trimesh(np.asarray(V2), F2, process=False)
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    assert mesh.volume == pytest.approx(L * W * eps, rel=1e-12)  # signed: positive means outward
    np.testing.assert_allclose(mesh.bounds, [[0.0, 0.0, -eps / 2], [L, W, eps / 2]], atol=1e-15)
    solid = make_cut_solid(V, F, eps)
    assert solid.status() == manifold3d.Error.NoError
    assert solid.volume() == pytest.approx(L * W * eps, rel=1e-12)
    assert solid.genus() == 0


def test_thickened_helicoid_is_a_closed_thin_solid():
    eps = 0.02
    edge = np.array([[0.5, 0.0, 0.0], [1.0, 0.0, 0.0], [1.5, 0.0, 0.0]])
    V, F = swept_surface(jnp.asarray(edge), _screws([0.0, 0.0, 1.0], [0.0, 0.0, 0.0], [0.0, 0.75, 1.5], 0.3), 5)
    V2, F2 = thicken(V, F, eps)
    mesh = trimesh.Trimesh(np.asarray(V2), F2, process=False)
    assert mesh.is_watertight and mesh.is_volume
    # curved: volume = area * eps up to the cosine between face and vertex normals
    assert mesh.volume == pytest.approx(_triangle_areas(V, F).sum() * eps, rel=2e-2)
    solid = make_cut_solid(V, F, eps)
    assert solid.status() == manifold3d.Error.NoError
    assert solid.volume() == pytest.approx(mesh.volume, rel=1e-12)


def test_plane_cut_splits_the_unit_cube():
    eps = 0.01
    cube = manifold3d.Manifold.cube([1.0, 1.0, 1.0])
    cut = plane_cut_solid(np.array([0.5, 0.5, 0.5]), np.array([0.0, 0.0, 2.0]), 2.0, eps)
    assert cut.volume() == pytest.approx(4.0 * eps, rel=1e-13)
    parts = (cube - cut).decompose()
    assert len(parts) == 2
    np.testing.assert_allclose(sorted(p.volume() for p in parts), [0.5 - eps / 2] * 2, rtol=1e-13)
    lows = sorted(p.bounding_box()[2] for p in parts)
    np.testing.assert_allclose(lows, [0.0, 0.5 + eps / 2], atol=1e-14)


def test_oblique_plane_cut_is_oriented():
    normal = np.array([1.0, -2.0, 0.5])
    cut = plane_cut_solid(np.array([0.1, 0.2, 0.3]), normal, 1.0, 0.05)
    assert cut.volume() == pytest.approx(0.05, rel=1e-13)
    # the slab's extent along the normal is epsilon
    V = cut.to_mesh64().vert_properties[:, :3]
    heights = V @ (normal / np.linalg.norm(normal))
    assert np.ptp(heights) == pytest.approx(0.05, rel=1e-12)


def test_bad_input():
    edge = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    keys = _translations([[0.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    with pytest.raises(ValueError, match="edge"):
        swept_surface(edge[:1], keys)
    with pytest.raises(ValueError, match="motors"):
        swept_surface(edge, keys[:1])
    with pytest.raises(ValueError, match="motors"):
        swept_surface(edge, cga.dilator(jnp.asarray([1.0, 2.0])))
    with pytest.raises(ValueError, match="samples_per_interval"):
        swept_surface(edge, keys, 0)
    with pytest.raises(ValueError, match="edge_b"):
        sweep_between(edge, jnp.zeros((3, 3)))
    V, F = _rectangle(1.0, 1.0)
    for eps in (0.0, -0.1, float("nan")):
        with pytest.raises(ValueError, match="epsilon"):
            thicken(V, F, eps)
    box = trimesh.creation.box()
    with pytest.raises(ValueError, match="closed"):
        thicken(jnp.asarray(box.vertices), box.faces, 0.1)
    flipped = F.copy()
    flipped[0] = flipped[0, ::-1]
    with pytest.raises(ValueError, match="F: non-manifold or inconsistently"):
        thicken(V, flipped, 0.1)
    # three triangles on one edge
    fan = jnp.asarray([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.5, -1.0, 0.0], [0.5, 0.0, 1.0]])
    with pytest.raises(ValueError, match="F: non-manifold"):
        thicken(fan, np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]]), 0.1)
    with pytest.raises(ValueError, match="V: every vertex"):
        thicken(jnp.concatenate([V, jnp.zeros((1, 3))]), F, 0.1)
    with pytest.raises(ValueError, match="F: degenerate"):
        thicken(V.at[5].set((V[0] + V[1]) / 2), F, 0.1)  # triangle (0, 1, 5) collapses
    # a half cylinder of radius 0.1 folds too tightly for a thickness of 0.5 (the inner offset passes the axis)
    phi = np.linspace(0.0, np.pi, 4)
    arc = np.stack([0.1 * np.cos(phi), np.zeros(4), 0.1 * np.sin(phi)], -1)
    Vc, Fc = sweep_between(jnp.asarray(arc), jnp.asarray(arc + [0.0, 1.0, 0.0]), 2)  # the shapes of V, F
    thicken(Vc, Fc, 0.1)
    with pytest.raises(ValueError, match="epsilon: an offset copy flips"):
        thicken(Vc, Fc, 0.5)
    with pytest.raises(ValueError, match="normal"):
        plane_cut_solid(np.zeros(3), np.zeros(3), 1.0, 0.1)
    with pytest.raises(ValueError, match="extent"):
        plane_cut_solid(np.zeros(3), np.ones(3), 0.0, 0.1)
