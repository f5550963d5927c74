"""No sliver faces from any cut, tear or drill (issue 30): random tools on Arm5 and CesiumMan (welded),
seeded. Every face that a tool makes keeps at least 1e-3 of the input's smallest face area and no
angle under 1e-3 rad unless the input face it comes from has one (``tools.piece_quality``); new points
lie on the tool's surface to 1e-9 of the diagonal; the result is a consistent mesh (no repeated corner,
no duplicate face, no edge on more than two faces, consistent winding, no unused vertex) whose new
vertices have non-negative weights summing to one and whose input vertices keep theirs
(``tools.consistency_problems``)."""

from __future__ import annotations

import numpy as np
import pytest

import deform
from tests.cutting.tools import DATA, TOOL_REFUSALS, fuzz


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Arm5", "CesiumMan"])
@pytest.mark.parametrize("tool, count", [("plane", 1000), ("drill", 200), ("tear", 200)])
def test_random_tools_make_no_slivers(name, tool, count):
    mesh = deform.load_model(DATA / f"{name}.glb", weld=True).mesh
    stats = fuzz(mesh, tool, count, seed=30)
    assert stats["runs"] == count, stats["refused"][:5]
    assert stats["failures"] == []
    # a plane through the mesh and a drill along a surface normal are never declined; a tear declines
    # a scalpel whose path it cannot follow (and another one is drawn)
    allowed = TOOL_REFUSALS if tool == "tear" else ()
    assert all(any(reason in message for reason in allowed) for message in stats["refused"]), stats["refused"][:5]


def test_sliver_mask_is_the_rule_in_full():
    # Its bounds only skip work (the input's smallest face, exact angles): the same answer as the rule computed
    # directly, on pieces of Arm5's faces from tiny to whole and from needle-thin to fat.
    from cutting._geometry import PIECE_ANGLE, PIECE_AREA, SmallestFace, sliver_mask, triangle_quality  # the rule

    mesh = deform.load_model(DATA / "Arm5.glb", weld=True).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    all_corners = V[F]
    doubled = np.linalg.norm(
        np.cross(all_corners[:, 1] - all_corners[:, 0], all_corners[:, 2] - all_corners[:, 0]), axis=1
    )
    rng = np.random.default_rng(5)
    count = 4000
    corners = all_corners[rng.integers(len(F), size=count)]
    # barycentric corners of each piece: near the face's corners (small pieces) or near a chord's midpoint (thin)
    near = np.eye(3)[None] + 10 ** rng.uniform(-5, 0, (count, 1, 1)) * rng.dirichlet(np.ones(3), (count, 3))
    thin = near.copy()
    thin[:, 2] = 0.5 * (thin[:, 0] + thin[:, 1]) + 10 ** rng.uniform(-6, -1, (count, 1)) * rng.normal(size=(count, 3))
    weights = np.where(rng.random((count, 1, 1)) < 0.5, near, thin)
    pieces = np.einsum("tkj,tjc->tkc", weights / weights.sum(axis=2, keepdims=True), corners)
    area, angle = triangle_quality(pieces[:, 0], pieces[:, 1], pieces[:, 2])
    _, face_angle = triangle_quality(corners[:, 0], corners[:, 1], corners[:, 2])
    # corner pieces of about the smallest area allowed, A, A + s (B - A), A + s (C - A), checked one at a time
    # (a bound below the smallest face would pass them)
    at_limit = rng.integers(len(F), size=200)
    scale = np.sqrt(PIECE_AREA * doubled.min() * rng.uniform(0.95, 1.15, 200) / doubled[at_limit])[:, None]
    A, B, C = all_corners[at_limit].transpose(1, 0, 2)
    limit_pieces = np.stack([A, A + scale * (B - A), A + scale * (C - A)], axis=1)
    limit_area, _ = triangle_quality(A, limit_pieces[:, 1], limit_pieces[:, 2])
    for headroom in (1.0, 1.1):
        small = area < headroom * PIECE_AREA * doubled.min()
        sharp = angle < np.minimum(headroom * PIECE_ANGLE, face_angle)
        assert small.sum() > 50 and (sharp & ~small).sum() > 50 and (~small & ~sharp).sum() > 50
        for bound in (corners[:20], all_corners):  # a loose bound, and the exact value
            smallest = SmallestFace(V, F)
            smallest.near(bound)
            assert np.array_equal(sliver_mask(pieces, corners, smallest, headroom), small | sharp)
            assert smallest.value() == doubled.min()
        expected = limit_area < headroom * PIECE_AREA * doubled.min()
        assert 20 < expected.sum() < 180
        for piece, face, poor in zip(limit_pieces, all_corners[at_limit], expected):
            smallest = SmallestFace(V, F)
            smallest.near(all_corners)
            assert sliver_mask(piece[None], face[None], smallest, headroom)[0] == poor


def test_the_tears_vectorized_fans_are_fan_triangles():
    # The tear checks its pieces in arrays (_tear._quad_fans) and builds them face by face (fan_triangles): the
    # check holds only if both pick the same apex, also for quadrilaterals with a point on an edge (collinear).
    from cutting._geometry import fan_triangles  # the per-face rule
    from cutting._tear import _quad_fans  # the tear's vectorized copy of it

    rng = np.random.default_rng(3)
    quads = rng.normal(size=(500, 4, 3))
    t = rng.uniform(0.001, 0.999, size=(250, 1))
    quads[:250, 1] = quads[:250, 0] + t * (quads[:250, 2] - quads[:250, 0])  # a point on the chord 0-2
    fans = _quad_fans(quads)
    for quad, fan in zip(quads, fans):
        expected = fan_triangles(list(range(4)), quad.tolist())
        np.testing.assert_array_equal(fan, quad[np.asarray(expected)])
