"""``xfem.simulate_character``: clips played on a character's tet body with secondary dynamics and cuts (issue items:
the all-driven and stiff limits, a severed limb's free fall, the surface carried with its pieces, gradients with
respect to the material, the damping and the cut planes, at the defaults: converged steps)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
import xfem
from tests.shared import character_body_of, check_gradient

FPS = 30.0


@pytest.fixture(scope="module")
def body() -> xfem.CharacterBody:
    """CesiumMan (metres, one clip) on coarse unrefined tets (about 3k): the dynamics' properties do not depend on
    how closely the embedded surface follows the direct skinning (tests/xfem/test_character_body.py checks that)."""
    return character_body_of("CesiumMan", edge_length=0.08, refine=False)


@pytest.fixture(scope="module")
def driven_body(body) -> xfem.CharacterBody:
    """The same tets with every node driven."""
    driven = xfem.character_body(body.model, driven="all", tets=body.tets, refine=False)
    assert np.array_equal(driven.tets.T, body.tets.T)  # the same tets (already refined)
    return driven


def _arm_plane(body: xfem.CharacterBody) -> tuple[np.ndarray, np.ndarray]:
    """A plane across the arm on the +x side, where a user would cut it off: 80% of the way out along x (the
    model stands in a T-pose, arms along x)."""
    lo, hi = body.surface.min(axis=0), body.surface.max(axis=0)
    point = (lo + hi) / 2
    point[0] = lo[0] + 0.8 * (hi[0] - lo[0])
    return point, np.array([1.0, 0.0, 0.0])


def _clear_of_nodes(body: xfem.CharacterBody, point, normal, thickness: float) -> np.ndarray:
    """``point`` moved along ``normal`` (by at most ``thickness``) to where the faces of the slab centred there lie
    farthest from every rest node: fTetWild's nodes differ from run to run, and a face crossing a node under a finite
    difference's step would make a jump of the cut's topology, not a derivative."""
    distance = (np.asarray(body.tets.X) - point) @ normal
    shifts = np.linspace(-thickness, thickness, 401)
    faces = shifts[:, None] + np.array([-thickness / 2, thickness / 2])[None]
    clearance = np.abs(distance[None, None, :] - faces[:, :, None]).min(axis=(1, 2))
    return point + shifts[np.argmax(clearance)] * normal


def _rig_nodes(body: xfem.CharacterBody, times, method: str = "cga") -> np.ndarray:
    return np.asarray(jax.vmap(lambda t: deform.skin_model(body.node_model, t, method))(jnp.asarray(times)))


def test_every_node_driven_is_the_skinned_body(driven_body):
    motion = xfem.simulate_character(driven_body, 0, 0.2, FPS, material=xfem.Material(1e5, 0.4))
    (segment,) = motion.segments
    nodes = _rig_nodes(driven_body, motion.times)
    assert motion.frames == 7 and segment.states.x.shape == nodes.shape
    np.testing.assert_allclose(np.asarray(segment.states.x), nodes, rtol=0, atol=1e-12)
    # the surface is the barycentric interpolation of those nodes
    interpolated = np.stack([np.asarray(driven_body.embedding.positions(x)) for x in nodes])
    np.testing.assert_allclose(np.asarray(segment.surface), interpolated, rtol=0, atol=1e-12)
    V, F, piece = motion.surface(3)
    assert V.shape == (len(driven_body.surface), 3) and np.array_equal(F, driven_body.faces) and np.all(piece == 0)


@pytest.mark.slow
def test_driven_nodes_follow_the_rig_and_the_flesh_lags(body):
    motion = xfem.simulate_character(body, 0, 0.3, FPS, material=xfem.Material(1e5, 0.4, damping=0.01))
    (segment,) = motion.segments
    assert bool(jnp.all(segment.states.stats.converged))
    nodes = _rig_nodes(body, motion.times)
    x = np.asarray(segment.states.x)
    np.testing.assert_allclose(x[:, body.driven], nodes[:, body.driven], rtol=0, atol=1e-12)
    free = np.setdiff1d(np.arange(len(body.nodes)), body.driven)
    lag = np.abs(x[:, free] - nodes[:, free]).max() / body.diagonal
    assert 1e-5 < lag < 0.2  # the flesh moves off the rig, and stays with it


@pytest.mark.slow
def test_a_stiff_body_tends_to_the_driven_one(body, driven_body):
    skinned = np.asarray(
        xfem.simulate_character(driven_body, 0, 0.2, FPS, material=xfem.Material(1e5, 0.4)).segments[0].surface
    )
    differences = []
    for young in (1e4, 1e6, 1e8):
        motion = xfem.simulate_character(body, 0, 0.2, FPS, material=xfem.Material(young, 0.4))
        differences.append(np.abs(np.asarray(motion.segments[0].surface) - skinned).max() / body.diagonal)
    assert differences[0] > differences[1] > differences[2]
    assert differences[2] < 1e-3


@pytest.mark.slow
def test_a_severed_arm_falls_at_g_and_the_rest_follows_the_clip(body):
    point, normal = _arm_plane(body)
    motion = xfem.simulate_character(
        body, 0, 0.3, FPS, material=xfem.Material(1e5, 0.4, damping=0.01), plane_cuts=[(3, point, normal, 0.01)]
    )
    first, cut = motion.segments
    assert (first.first, cut.first) == (0, 3) and first.pieces == 1 and cut.pieces == 2
    assert list(motion.pieces_per_frame) == [1, 1, 1, 2, 2, 2, 2, 2, 2, 2]
    assert bool(jnp.all(cut.states.stats.converged))
    system = cut.system
    assert system is not None  # a segment of a full (not reduced) run carries its system
    mass = np.bincount(np.asarray(system.mass_rows), np.asarray(system.mass_values), minlength=system.n)
    x = np.asarray(cut.states.x)
    nodes = _rig_nodes(body, motion.times[3:])
    released = 0
    for piece in range(cut.pieces):
        mine = cut.dof_piece == piece
        if cut.driven[mine].any():  # a piece that keeps driven DOFs follows the clip
            driven = mine & cut.driven
            np.testing.assert_allclose(x[:, driven], nodes[:, cut.dof_node[driven]], rtol=0, atol=1e-12)
            continue
        released += 1
        centroid = np.einsum("n,fnd->fd", mass[mine], x[:, mine]) / mass[mine].sum()
        acceleration = (centroid[2:] - 2 * centroid[1:-1] + centroid[:-2]) * FPS**2
        np.testing.assert_allclose(acceleration, np.broadcast_to(body.gravity, acceleration.shape), rtol=0, atol=1e-6)
        # the released piece is the arm beyond the plane (its DOFs' nodes at rest, to within a tet)
        assert np.all(np.asarray(body.tets.X)[cut.dof_node[mine], 0] > point[0] - 0.2)
    assert released == 1
    # the surface is carried in pieces: the severed arm's triangles lie beyond the plane at rest
    V, F, piece = motion.surface(-1)
    assert len(np.unique(piece)) == 2 and V.shape[0] >= len(body.surface)


@pytest.mark.slow
def test_solid_and_blade_cuts(body):
    point, normal = _arm_plane(body)
    solid = xfem.plane_cut_solid(point, normal, 2 * body.diagonal, 0.01)
    motion = xfem.simulate_character(body, 0, 0.1, FPS, material=xfem.Material(1e5, 0.4), cuts=[(2, solid)])
    assert [s.pieces for s in motion.segments] == [1, 2]
    # a blade along the arm's top, the scalpel's samples as cutting.Scalpel holds them: a slit, no severed part
    lo, hi = body.surface.min(axis=0), body.surface.max(axis=0)
    y = lo[1] + 0.85 * (hi[1] - lo[1])
    handle = np.array([[point[0] - 0.1, y + 0.2, 0.0], [point[0] + 0.05, y + 0.2, 0.0]])
    tip = handle - np.array([0.0, 0.4, 0.0])
    blade = xfem.blade_solid(handle, tip, 0.005)
    motion = xfem.simulate_character(body, 0, 0.1, FPS, material=xfem.Material(1e5, 0.4), cuts=[(1, blade)])
    assert len(motion.segments) == 2 and motion.segments[-1].pieces >= 1


@pytest.mark.slow
def test_gradients_in_the_material_and_the_damping(body):
    def loss(young, damping):
        motion = xfem.simulate_character(body, 0, 0.1, FPS, material=xfem.Material(young, 0.4, damping=damping))
        return jnp.sum(motion.segments[0].surface[..., 1] ** 2)

    check_gradient(lambda p: loss(p[0] * 1e5, p[1]), jnp.array([1.0, 0.02]), rtol=1e-5)


@pytest.mark.slow
def test_gradients_in_the_cut_plane(body):
    point, normal = _arm_plane(body)
    normal = np.array([0.96, 0.2, 0.2])
    normal /= np.linalg.norm(normal)
    tangents = np.linalg.svd(normal[None])[2][1:]  # two unit vectors across the normal

    point = _clear_of_nodes(body, point, normal, 0.01)

    def loss(shift, turn):
        n = normal + turn @ tangents
        motion = xfem.simulate_character(
            body,
            0,
            0.2,
            FPS,
            material=xfem.Material(1e5, 0.4, damping=0.01),
            plane_cuts=[(2, point + shift, n / jnp.linalg.norm(n), 0.01)],
        )
        return sum(jnp.sum(s.surface[..., 1]) for s in motion.segments)

    # steps of 1e-5 m and 1e-5 rad: central differences of converged steps (Newton stops at 1e-10 of the size) are
    # below 1e-5 of the derivative there, and the slab's faces, a millimetre or so from every node, cross none
    check_gradient(lambda p: loss(p[:3] * 1e-3, p[3:] * 1e-3), jnp.zeros(5), rtol=1e-5, step=1e-2)


def test_errors(body):
    material = xfem.Material(1e5, 0.4)
    with pytest.raises(ValueError, match="body"):
        xfem.simulate_character(body.model, material=material)
    with pytest.raises(ValueError, match="material"):
        xfem.simulate_character(body, material=(1e5, 0.4))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="fps"):
        xfem.simulate_character(body, 0, 1.0, 0.0, material=material)
    with pytest.raises(ValueError, match="seconds"):
        xfem.simulate_character(body, 0, -1.0, material=material)
    with pytest.raises(ValueError, match="method"):
        xfem.simulate_character(body, 0, 0.1, material=material, method="linear")
    with pytest.raises(ValueError, match="clip"):
        xfem.simulate_character(body, "no such clip", 0.1, material=material)
    with pytest.raises(ValueError, match="cuts"):
        xfem.simulate_character(body, 0, 0.1, material=material, cuts=[(99, None)])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="plane_cuts"):
        xfem.simulate_character(body, 0, 0.1, material=material, plane_cuts=[(0, [0, 0, 0], [1, 0, 0], 0.01)])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="damping"):
        xfem.Material(1e5, 0.4, damping=-1.0)
    with pytest.warns(UserWarning, match="outside the clip"):
        xfem.simulate_character(body, 0, 1.0, 2.0, material=material, start=body.model.clips[0].end - 0.5)
