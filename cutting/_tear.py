"""Tearing a (skinned) triangle mesh with a scalpel: Algorithm 2 of the cut/tear/drill paper
(sec. 4.2.2), with the weights of new vertices of sec. 4.3.

The scalpel is a segment known at time steps t_0 .. t_k (``Scalpel(handle, tip)``: at t_i it runs
from ``handle[i]`` to ``tip[i]``), given by its endpoints, as a sequence of ``Scalpel``s, or as a blade
moved by motors (``scalpel_path``). Between two samples the blade's ends move linearly: it sweeps the ruled
quadrilateral handle_i, tip_i, tip_{i+1}, handle_{i+1}, and the tear is where that swept surface meets the
mesh, where the blade passed.

1. S_i, the crossing of the blade with the surface at t_i (the crossing nearest the handle to begin with;
   then the one nearest the tear's last sample, so that a tear stays on its sheet where several overlap);
2. for each step i, the plane Pi_i through S_i and the blade's endpoints at t_{i+1};
3. from S_i's face, the intersection of Pi_i with the surface is followed face by face (across
   shared edges, towards S_{i+1}) until S_{i+1}'s face: the edge points Q_j, in order on the skin;
4. weights of the tips (barycentric in their faces) and of every Q_j (on its edge), sec. 4.3;
5. the faces on the path are re-triangulated: the tips become vertices inside their faces, every Q_j is
   duplicated, one copy for each side of the tear;
6. the two copies of every Q_j are pushed apart along Pi's normal, ``opening / 2`` each.

What changed from the paper, and why. The paper takes the plane's curve from S_i to S_{i+1} whole; on a
curved character the curve of a plane through two far samples closes on itself, leaves the skin or runs far
from where the blade passed. Here the blade is sampled again halfway (its ends interpolated linearly, the
samples' times kept in ``TearTopology.sample_times``) wherever a step's curve does not join its two samples
with every tear point within 0.4 of its edge's length of the swept quadrilateral, or the plane strays from that
quadrilateral near the surface by more than a quarter of an edge (a turning blade): the planes then follow the
swept surface. At the finest sampling (the blade moving
under a quarter of an edge), a step that still cannot be followed ends the tear, which begins again at the next
crossing: a tear is one or more stretches. So a blade that leaves the skin and comes back tears the stretches
where it was on it; the tear ends at the surface's boundary (or a non-manifold edge), and before a face it
already went through (a face cut twice would lose or double area), each within a quarter of an edge; where the
blade crosses no sheet at both ends of a step, the times at which mesh edges pierce the swept quadrilateral
tell whether and where it crosses one in between. A stretch inside one face is a slit there, its middle point
duplicated (``TearTopology.inner``). A blade that barely crosses the skin (at one instant, or moving too little
inside one face for a slit without a sliver, even one ending earlier) makes a slit of at least 5% of its face's
longest edge: the shortest of _MINIMAL_LENGTHS of that edge that leaves no sliver, through the blade's crossing
along its motion (the face's longest edge for a blade that does not move across the skin), else turned, else
moved towards the face's centroid, and in a neighbouring face (not torn yet) where the face is too thin to hold
one; both its ends are at the crossing's time, offset from it in the face (``TearTopology.sample_offsets``). Only
a blade that never crosses the surface is refused.

In the face of an intermediate sample the path goes straight from the point where it enters the face to the
point where it leaves it (the paper's assumption that the tear curve is smooth between close samples). A plane
that passes within ``tolerance`` of a vertex of the path, that would put a tear point within 2% of an edge's
length from its end, or that would leave a piece of a face smaller or thinner than the sliver rule of
``_geometry.sliver_mask`` allows, is moved along its normal in steps of 5% of an edge (a gentle perturbation, as
the XFEM paper's sec. 6.1 does for cuts through vertices), so that no sliver triangle is created;
``TearTopology.shift`` records the move. Tips keep a 2% barycentric margin from their faces' edges.

For a fixed topology (``TearTopology``), the positions of the new vertices are a JAX function of the
vertices, the ``Scalpel`` and the opening (``tear_positions``), so they can be differentiated.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal, NamedTuple, overload

import igl
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_choice, check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from _jaxcga_shared.platform import EXACT
from cutting._geometry import (
    MeshEdges,
    SmallestFace,
    cross3,
    cross_rows,
    fan_triangles,
    mesh_edges,
    posed_vertices,
    rest_positions,
    segment_hits,
    skinned_mesh_like,
    sliver_mask,
)
from cutting._predicates import PREDICATES, edge_points, signed_distances
from cutting._tools import Scalpel, check_scalpel, joined_scalpel
from cutting._weights import blend_weights
from deform._model import SkinnedMesh

# A tear point keeps at least this fraction of its edge from both ends; the plane is moved (in steps
# of _SHIFT_STEP mean edge lengths of the starting face) until every point does: no sliver triangles.
_EDGE_MARGIN = 0.02
_SHIFT_STEP = 0.05
# Tip points keep at least this barycentric coordinate in their face (no sliver fan triangle when
# the scalpel meets the surface on or near an edge).
_TIP_MARGIN = 0.02
# The edge margins alone allow a corner piece of 0.02 x 0.02 of its face; each face's pieces are
# checked against the rule of ``sliver_mask`` with this headroom (the final points come from the
# predicates, which may round differently), and the plane moves on where one is a sliver.
_PIECE_HEADROOM = 1.1
# Between two samples whose plane's curve does not join them where the blade passed, the blade is sampled
# again halfway, until it moves less than _RESOLUTION of a mean edge of the faces it crosses (or _MAX_DEPTH
# halvings): then the tear ends at the first sample and begins again at the second.
_RESOLUTION = 0.25
_MAX_DEPTH = 30
# Where the blade passed: a step's plane strays less than _NEAR_SWEPT of a mean edge of its first face from the
# swept quadrilateral near the surface, and each tear point lies within _NEAR_POINT of its edge's length (plus the
# plane's move) of the quadrilateral.
_NEAR_SWEPT = 0.25
_NEAR_POINT = 0.4
# The swept quadrilateral (blade_a handle, blade_a tip, blade_c tip, blade_c handle) as two triangles.
_QUAD_TRIANGLES = np.array([[0, 1, 2], [0, 2, 3]])
# Where the blade crosses several sheets (clothing, an inner mesh), a stretch goes on over the nearest of
# them that its curve reaches: up to this many are tried.
_ALTERNATIVES = 3
# A slit inside one face that would leave a sliver piece ends earlier: at these fractions of its blade's time.
_SHORTER = (0.75, 0.5, 0.25)
# A blade that barely crosses the skin (one sample on it, or a slit too short for the sliver rule) makes the
# shortest slit of these lengths (fractions of its face's longest edge) that leaves no sliver: through its crossing
# along the blade's motion first, then turned by _MINIMAL_TURNS, then moved towards the face's centroid
# (_MINIMAL_CENTRES) where the crossing is too near an edge or corner for any of them.
_MINIMAL_LENGTHS = (0.05, 0.1, 0.2, 0.35, 0.5)
_MINIMAL_TURNS = np.pi * np.array([0.0, 1.0, -1.0, 2.0, -2.0, 3.0]) / 6.0
_MINIMAL_CENTRES = (0.0, 0.1, 0.25, 0.5, 1.0)


class TearTopology(NamedTuple):
    """The topology of a tear (``tear_topology``), and the geometry it was computed from.

    The samples here are the blade's samples that the tear went through, in time order: the scalpel's own
    and those added between them where the path needed them (s in all). The tear is one or more stretches
    of consecutive samples (one, unless the blade leaves the surface and comes back).

    Attributes:
        sample_faces: (s,) int the face crossed by the blade at each sample.
        sample_corners: (s, 3) int that face's vertices (``F[sample_faces]``).
        sample_points: (s, 3) the crossings S_i, kept 2% (barycentric) off their faces' edges (a tip is a vertex).
        sample_crossings: (s, 3) where the blade crosses each sample's face, before that margin: the planes
            pass through them.
        sample_barycentric: (s, 3) barycentric coordinates of S_i in its face.
        sample_times: (s,) each sample's time in units of the scalpel's steps: at time i + a (0 <= a <= 1)
            the blade's ends are ``(1 - a) X[i] + a X[i + 1]`` of the scalpel's handle and tip X.
        stretches: (r, 2) int the first and the last sample of each stretch; their crossings are the tear's
            tips, which stay single vertices.
        stretch_faces: (r,) int how many of ``faces`` each stretch holds (p = their sum).
        inner: (u,) int the stretches that stay inside one face (``stretch_faces`` 1): each has one interior
            point, M halfway between its tips, duplicated like the Q_j (the slit's two sides need a vertex
            each); its side's normal is the face's normal x (last tip - first tip), normalized.
        scalpel_samples: k+1, the scalpel's own samples.
        faces: (p,) int the faces on the tear path, stretch after stretch, each in order from its first
            sample's face to its last one's.
        edge_ids: (q,) int the edge (``MeshEdges`` id) carrying Q_j, between consecutive faces of a stretch
            (q = p - r).
        crossing: (q, 2) int its vertices (i, j).
        t: (q,) parameter of Q_j along its edge, ``Q = (1 - t) V_i + t V_j``.
        points: (q, 3) the Q_j before the opening.
        step: (q,) int the step i (between samples i and i + 1, plane Pi_i) that gave Q_j.
        planes: (s-1, 4) the planes Pi_i as (unit normal, d): the normal points to the tear's left
            (face normal x path direction), d includes the perturbation. Zero rows for the steps that gave
            no Q_j (both samples in one face, or a gap between stretches).
        orientation: (s-1,) +1 or -1: Pi_i's normal is ``orientation * (A - X_i) x (B - X_i)``
            normalized, with A, B the blade's ends at sample i + 1 and X_i the plane's anchor: the tip
            ``sample_points[i]`` where ``from_tip[i]``, else ``sample_crossings[i]`` (0 where the row is zero).
        shift: (s-1,) how far each plane was moved along its oriented normal (the perturbation; mostly 0):
            ``planes[i, 3] = planes[i, :3] . X_i + shift[i]``.
        from_tip: (s-1,) bool the steps that leave a stretch's first face, from its tip.
        sample_offsets: (s, 3) added to the barycentric coordinates of the blade's crossing before the margin:
            zero but at the two ends of a minimal slit (a blade that barely crosses the skin, see ``tear``),
            which lie on either side of the crossing in its face, or in a neighbour of a face too thin to hold
            one (each row sums to zero).
    """

    sample_faces: Int[np.ndarray, " s"]
    sample_corners: Int[np.ndarray, "s 3"]
    sample_points: Float[np.ndarray, "s 3"]
    sample_crossings: Float[np.ndarray, "s 3"]
    sample_barycentric: Float[np.ndarray, "s 3"]
    sample_times: Float[np.ndarray, " s"]
    stretches: Int[np.ndarray, "r 2"]
    stretch_faces: Int[np.ndarray, " r"]
    inner: Int[np.ndarray, " u"]
    scalpel_samples: int
    faces: Int[np.ndarray, " f"]
    edge_ids: Int[np.ndarray, " q"]
    crossing: Int[np.ndarray, "q 2"]
    t: Float[np.ndarray, " q"]
    points: Float[np.ndarray, "q 3"]
    step: Int[np.ndarray, " q"]
    planes: Float[np.ndarray, "k 4"]
    orientation: Float[np.ndarray, " k"]
    shift: Float[np.ndarray, " k"]
    from_tip: Bool[np.ndarray, " k"]
    sample_offsets: Float[np.ndarray, "s 3"]


def scalpel_path(blade: Float[ArrayLike, "2 3"], motors: cga.Multivector) -> Scalpel:
    """A scalpel from a blade moved by motors: the segment ``blade`` (2, 3) (handle end first)
    carried by each of the k+1 versors ``motors`` (a jaxcga Multivector of motors or similitudes with
    batch shape (k+1,), e.g. two motors for the paper's two time steps, or a motor spline sampled at
    t_0 .. t_k).

    Args:
        blade: (2, 3) the segment's handle end and tip at rest.
        motors: versors with batch shape (k+1,).
    Returns:
        The ``Scalpel`` (float64 numpy ends (k+1, 3)) that ``tear`` takes.

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> import cutting
        >>> blade = jnp.array([[0.18, 0.1, 0.0], [0.18, 0.0, 0.0]])  # handle end, tip
        >>> scalpel = cutting.scalpel_path(blade, cga.translator(jnp.array([[0.0, 0, 0], [0.04, 0, 0]])))
        >>> scalpel.tip.round(6).tolist()  # the tip at the two time steps
        [[0.18, 0.0, 0.0], [0.22, 0.0, 0.0]]
    """
    blade = np.asarray(blade, np.float64)
    if blade.shape != (2, 3) or not np.all(np.isfinite(blade)):
        raise ValueError(f"blade: expected 2 finite endpoints of shape (2, 3), got {blade.shape}")
    if not isinstance(motors, cga.Multivector) or len(motors.batch_shape) != 1 or motors.batch_shape[0] < 2:
        raise ValueError("motors: expected a jaxcga versor Multivector with batch shape (k+1,), k+1 >= 2")
    per_sample = cga.Multivector(motors.values[:, None, :], motors.blades)  # (k+1, 1) against (2,) points
    samples = np.asarray(cga.apply_to_points(per_sample, jnp.asarray(blade)), np.float64)
    return Scalpel(samples[:, 0], samples[:, 1])


def _blade(segments, time):
    """The blade (2, 3) at ``time`` in [0, k]: its two ends interpolated linearly between the samples."""
    i = min(int(np.floor(time)), len(segments) - 2)
    a = time - i
    return (1.0 - a) * segments[i] + a * segments[i + 1]


class _Crossing(NamedTuple):
    """Where the blade at ``time`` crosses the surface, kept _TIP_MARGIN off its face's edges."""

    time: float
    face: int
    barycentric: np.ndarray
    point: np.ndarray
    exact: np.ndarray  # on the blade, before the margin: the planes pass through it
    # added to the crossing's barycentric coordinates before the margin: the ends of a minimal slit (None: zero)
    offset: np.ndarray | None = None


def _crossings(V, F, segments, time, faces) -> list[_Crossing]:
    """Every crossing of the blade at ``time`` with the surface (among ``faces``), from the handle end on."""
    blade = _blade(segments, time)
    faces, barycentric, along = segment_hits(V, F, blade[0], blade[1], faces)
    b = np.maximum(barycentric, _TIP_MARGIN)
    b /= b.sum(axis=1, keepdims=True)
    points = np.einsum("hk,hkc->hc", b, V[F[faces]])
    exact = blade[0] + along[:, None] * (blade[1] - blade[0])
    return [_Crossing(float(time), int(f), b[h], points[h], exact[h]) for h, f in enumerate(faces.tolist())]


def _swept_crossings(V, edges: MeshEdges, segments, step: int) -> np.ndarray:
    """The times in [step, step + 1] at which edges of the mesh pierce the surface that the blade sweeps
    between samples ``step`` and ``step + 1``: the quadrilateral handle_i, tip_i, tip_{i+1}, handle_{i+1}, as
    the two triangles on its diagonal handle_i - tip_{i+1} (sorted; empty where the swept surface misses the
    mesh)."""
    (H0, T0), (H1, T1) = segments[step], segments[step + 1]
    times = []
    # each triangle with the time (as a fraction of the step) at its corners
    for corners, at in (((H0, T0, T1), (0.0, 0.0, 1.0)), ((H0, T1, H1), (0.0, 1.0, 1.0))):
        corners = np.asarray(corners)
        # an edge with both ends beyond one side of the triangle's bounding box cannot pierce it
        below, above = V < corners.min(axis=0), V > corners.max(axis=0)
        i, j = edges.edges[:, 0], edges.edges[:, 1]
        outside = ((below[i] & below[j]) | (above[i] & above[j])).any(axis=1)
        pairs = edges.edges[~outside]
        e1, e2 = corners[1] - corners[0], corners[2] - corners[0]
        normal = np.cross(e1, e2)
        squared = float(normal @ normal)
        if not len(pairs) or squared == 0:
            continue
        A, B = V[pairs[:, 0]], V[pairs[:, 1]]
        sA, sB = (A - corners[0]) @ normal, (B - corners[0]) @ normal
        pierce = sA * sB < 0
        A, B, sA, sB = A[pierce], B[pierce], sA[pierce], sB[pierce]
        r = A + (sA / (sA - sB))[:, None] * (B - A) - corners[0]
        # r = u e1 + v e2: barycentric coordinates in the triangle
        u = cross_rows(r, np.broadcast_to(e2, r.shape)) @ normal / squared
        v = cross_rows(np.broadcast_to(e1, r.shape), r) @ normal / squared
        inside = (u >= 0) & (v >= 0) & (u + v <= 1)
        times.append(step + np.stack([1.0 - u - v, u, v], axis=1)[inside] @ np.asarray(at))
    return np.sort(np.concatenate(times)) if times else np.zeros(0)


def _face_normal(V, corners):
    return cross_rows(V[corners[1]] - V[corners[0]], V[corners[2]] - V[corners[0]])


class _NearVertex(Exception):
    """The plane passes within the tolerance of a vertex of the path, or leaves a sliver piece: move it
    and walk again."""


class _Lost(Exception):
    """The plane's curve leaves the faces being followed (after a move, it may miss the first face)."""


class _Blocked(Exception):
    """The plane's curve does not join the two samples where the blade passed: it reaches the surface's
    boundary or a face the tear already went through, closes on itself, or strays from the swept surface.
    The step is sampled more finely, or the tear ends there."""


# The pieces that a chord leaves of a face, in ``_retriangulate``'s order: a triangle and a quadrilateral, as
# slots of [corners 0-2, the points on local edges 0-2], for the chord's local edges (0, 1), (0, 2) and (1, 2).
_CHORD_TRIANGLES = np.array([[3, 1, 4], [5, 0, 3], [4, 2, 5]])
_CHORD_QUADS = np.array([[4, 2, 0, 3], [3, 1, 2, 5], [5, 0, 1, 4]])
# The boundary of a tip face with its one point (slot 3) on local edge k, fanned from the tip (slot 4).
_TIP_CYCLES = np.array([[0, 3, 1, 2], [0, 1, 3, 2], [0, 1, 2, 3]])
_TIP_FANS = np.stack([_TIP_CYCLES, np.roll(_TIP_CYCLES, -1, axis=1), np.full((3, 4), 4)], axis=2)  # (3, 4, 3)
# ``fan_triangles`` of a quadrilateral: from each apex a, the triangles (a, a+i, a+i+1), i = 1, 2 (mod 4)
_APEX = np.repeat(np.arange(4), 2)
_FAN_B = (_APEX + np.tile([1, 2], 4)) % 4
_FAN_C = (_FAN_B + 1) % 4


def _local_edges(edges: MeshEdges, faces, edge_ids):
    """The local index (0-2) of each edge in its face."""
    return np.argmax(edges.face_edges[faces] == np.asarray(edge_ids)[:, None], axis=1)


def _quad_fans(quads):
    """``fan_triangles`` of quadrilaterals (c, 4, 3), in its arithmetic: the two triangles (c, 2, 3, 3) from
    the first apex whose smaller triangle is largest."""
    apex = quads[:, _APEX]
    n = cross_rows(quads[:, _FAN_B] - apex, quads[:, _FAN_C] - apex)
    sizes = n[..., 0] * n[..., 0] + n[..., 1] * n[..., 1] + n[..., 2] * n[..., 2]
    best = np.argmax(sizes.reshape(-1, 4, 2).min(axis=2), axis=1)
    ring = np.take_along_axis(quads, ((best[:, None] + np.arange(4)) % 4)[:, :, None], axis=1)
    return np.stack([ring[:, [0, 1, 2]], ring[:, [0, 2, 3]]], axis=1)


def _slivers(V, F, edges: MeshEdges, chords, tips, smallest: SmallestFace) -> bool:
    """Whether the tear leaves a sliver piece (``sliver_mask`` with _PIECE_HEADROOM) of a face it crosses:
    the same split as ``_retriangulate``, all faces at once. ``chords``: (face, entry edge, entry point,
    exit edge, exit point) of the faces it goes through; ``tips``: (face, edge, point, tip) of the faces it
    starts or ends in, fanned from the tip."""
    pieces, parents = [], []
    if chords:
        faces, entry, entry_point, exit_, exit_point = (np.asarray(x) for x in zip(*chords))
        corners = np.take(V, F[faces], axis=0)
        smallest.near(corners)
        slots = np.concatenate([corners, np.zeros_like(corners)], axis=1)
        rows = np.arange(len(faces))
        k_in, k_out = _local_edges(edges, faces, entry), _local_edges(edges, faces, exit_)
        slots[rows, 3 + k_in] = entry_point
        slots[rows, 3 + k_out] = exit_point
        case = k_in + k_out - 1  # (0, 1) -> 0, (0, 2) -> 1, (1, 2) -> 2
        pieces += [slots[rows[:, None], _CHORD_TRIANGLES[case]], _quad_fans(slots[rows[:, None], _CHORD_QUADS[case]])]
        parents += [corners, np.repeat(corners, 2, axis=0)]
    if tips:
        faces, edge, point, tip = (np.asarray(x) for x in zip(*tips))
        corners = np.take(V, F[faces], axis=0)
        smallest.near(corners)
        slots = np.concatenate([corners, point[:, None], tip[:, None]], axis=1)
        fans = _TIP_FANS[_local_edges(edges, faces, edge)]  # (c, 4, 3)
        pieces.append(slots[np.arange(len(faces))[:, None, None], fans])
        parents.append(np.repeat(corners, 4, axis=0))
    if not pieces:
        return False
    pieces = np.concatenate([p.reshape(-1, 3, 3) for p in pieces])
    return bool(sliver_mask(pieces, np.concatenate(parents), smallest, _PIECE_HEADROOM).any())


def _slit_triangles(corners, first, last):
    """The triangles (7, 3) of a face (``corners`` (3, 3)) with a slit inside it, from the tip ``first`` to the
    tip ``last`` with its middle point M duplicated, as slots: 0-2 the face's corners, 3 the first tip, 4 the last,
    5 M's left copy, 6 its right copy (left of the slit is the face normal x (last - first) side). The slit's line
    leaves the face ahead of ``last`` and behind ``first``, over an edge (a triangle from the tip to that edge) or
    through a corner (which then belongs to both sides); a fan covers each side. None where the tips coincide."""
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    direction = last - first
    across = np.cross(normal, direction)
    scale = np.linalg.norm(across) * np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).max()
    if scale == 0:
        return None
    side = (corners - first) @ across
    side[np.abs(side) <= 1e-9 * scale] = 0.0  # a corner on the slit's line
    along = (corners - first) @ direction
    on = [k for k in range(3) if side[k] == 0]
    ahead = [k for k in on if along[k] > 0]
    behind = [k for k in on if along[k] <= 0]

    def side_corners(sign):
        # the corners strictly on one side, counter-clockwise: from the one after the line's exit ahead
        ks = [k for k in range(3) if np.sign(side[k]) == sign]
        if len(ks) == 2 and (ks[0] + 1) % 3 != ks[1]:
            ks.reverse()
        return ks

    lefts, rights = side_corners(1.0), side_corners(-1.0)
    if not lefts or not rights:
        return None
    triangles = []
    if ahead:  # the line leaves through a corner ahead: it closes both sides' rings
        lefts, rights = ahead + lefts, rights + ahead
    else:  # over the edge from the last right corner to the first left one
        triangles.append((4, rights[-1], lefts[0]))
    if behind:
        lefts, rights = lefts + behind, behind + rights
    else:
        triangles.append((3, lefts[-1], rights[0]))
    # each side a convex polygon (the face's part on that side, less the tips' triangles), counter-clockwise; its
    # fan from the apex whose smallest triangle is largest (the tips and M lie on one line, and so may a corner)
    middle = 0.5 * (first + last)
    slots = np.concatenate([corners, [first, last, middle, middle]]).tolist()
    for ring in ([3, 5, 4, *lefts], [4, 6, 3, *rights]):
        triangles += fan_triangles(ring, [slots[k] for k in ring])
    return np.asarray(triangles)


def _slit_pieces(corners, first, last):
    """The pieces (7, 3, 3) of a face (corners (3, 3)) with a slit from ``first`` to ``last`` (a closed slit:
    both copies of M at M), or None where ``_slit_triangles`` has none."""
    triangles = _slit_triangles(corners, first, last)
    if triangles is None:
        return None
    middle = 0.5 * (first + last)
    slots = np.concatenate([corners, [first, last, middle, middle]])
    return slots[triangles]


def _walk(
    V,
    F,
    edges: MeshEdges,
    s,
    margin,
    start,
    entry_edge,
    entry_point,
    first_tip,
    origin,
    goal,
    target,
    visited,
    reach,
    smallest,
):
    """Follow the zero set of the signed distances s from face ``start`` (entered over ``entry_edge`` at
    ``entry_point``, or where the tear begins, at ``first_tip`` inside it) to face ``target``, holding the
    sample ``goal``; ``origin`` is the sample the step leaves from. Every point stays within ``reach`` of it.
    Returns the crossed edge ids and the faces entered (target last)."""
    crossed, entered = [], []
    # The faces' pieces are checked together when the walk reaches the target: a sliver in any face it went
    # through moves the plane, as a check face by face would have. The target's pieces are checked as the
    # tip of the tear, which the tear may end at.
    chords, tips = [], []

    f, e_from, point_in = start, entry_edge, entry_point
    for _ in range(len(F) + 1):
        a, b, c = s[F[f]].tolist()
        if min(abs(a), abs(b), abs(c)) <= margin:
            raise _NearVertex
        candidates = [
            int(e) for e in edges.face_edges[f] if e != e_from and s[edges.edges[e, 0]] * s[edges.edges[e, 1]] < 0
        ]
        if not candidates:
            raise _Lost
        if len(candidates) > 1:
            # only in the first face: leave it towards the next sample
            def progress(e):
                i, j = edges.edges[e]
                x = V[i] + s[i] / (s[i] - s[j]) * (V[j] - V[i])
                return float((x - origin) @ (goal - origin))

            candidates.sort(key=progress, reverse=True)
        e = candidates[0]
        i, j = edges.edges[e]
        t = s[i] / (s[i] - s[j])
        if min(t, 1.0 - t) < _EDGE_MARGIN:
            raise _NearVertex
        point_out = V[i] + t * (V[j] - V[i])
        if e_from is None:
            tips.append((f, e, point_out, first_tip))
        else:
            chords.append((f, e_from, point_in, e, point_out))
        away = point_out - origin
        if edges.edge_counts[e] != 2 or away @ away > reach * reach:
            raise _Blocked  # the surface's boundary (or a non-manifold edge); a curve that strays
        g = int(edges.edge_faces[e, 0] if edges.edge_faces[e, 0] != f else edges.edge_faces[e, 1])
        crossed.append(e)
        entered.append(g)
        if g in visited or g == start:
            raise _Blocked  # a face the tear went through (cut twice, it would lose or double area)
        visited.add(g)
        if g == target:
            tips.append((g, e, point_out, goal))
            if _slivers(V, F, edges, chords, tips, smallest):
                raise _NearVertex
            return crossed, entered
        f, e_from, point_in = g, e, point_out
    raise _Blocked


class _Path:
    """The tear being built in time order (Algorithm 2, steps 1-3): stretches of samples of the blade, each
    step of a stretch followed over the surface from one sample's crossing to the next."""

    def __init__(self, V, F, edges: MeshEdges, segments, predicates, margin, smallest):
        self.V, self.F, self.edges, self.segments = V, F, edges, segments
        self.predicates, self.margin, self.smallest = predicates, margin, smallest
        self.diagonal = bounding_diagonal(V)
        # how far the blade's ends move over each step of the scalpel
        self.motion = np.linalg.norm(segments[1:] - segments[:-1], axis=2).max(axis=1)
        self.swept: dict[int, np.ndarray] = {}
        self.near: dict[int, np.ndarray] = {}
        self.lengths: dict[int, float] = {}
        self.touched = False  # whether the surface the blade sweeps meets the mesh
        self.hit = False  # whether the blade crossed a face at any time it was sampled at
        self.samples: list[_Crossing] = []
        self.stretches: list[list[int]] = []
        self.stretch_faces: list[int] = []
        self.faces: list[int] = []
        self.crossed: list[int] = []
        self.steps: list[int] = []
        # per step between consecutive samples (zero rows for steps that cross no edge and between stretches)
        self.planes: list[np.ndarray] = []
        self.orientation: list[float] = []
        self.shifts: list[float] = []
        self.from_tip: list[bool] = []
        self.point_chunks: list[np.ndarray] = []
        self.t_chunks: list[np.ndarray] = []
        self.visited: set[int] = set()
        self.inner: list[int] = []
        self.blocked = False  # whether the last step met the surface's boundary or the tear itself
        self.open = False
        self.entry_edge: int | None = None
        self.entry_point = np.zeros(3)
        self._saved = (0, 0, 0, 0)

    def crossing(self, time) -> list[_Crossing] | None:
        """The blade's crossings at ``time`` (None where it misses the surface)."""
        i = min(int(time), len(self.motion) - 1)
        if i not in self.near:
            # the faces whose bounding boxes meet that of the blade over the step (it stays in the hull of its
            # samples): not all three corners beyond one side of it (one bit per side, as _straddling_faces)
            ends = self.segments[i : i + 2].reshape(-1, 3)
            beyond = np.concatenate([self.V < ends.min(axis=0), self.V > ends.max(axis=0)], axis=1)
            codes = (beyond.astype(np.uint8) << np.arange(6, dtype=np.uint8)).sum(axis=1, dtype=np.uint8)[self.F]
            self.near[i] = np.flatnonzero((codes[:, 0] & codes[:, 1] & codes[:, 2]) == 0)
        found = _crossings(self.V, self.F, self.segments, time, self.near[i])
        self.touched |= bool(found)
        self.hit |= bool(found)
        return found or None

    def edge_length(self, face) -> float:
        if face not in self.lengths:
            corners = self.V[self.F[face]]
            self.lengths[face] = float(np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).mean())
        return self.lengths[face]

    def _row(self, plane=None, sign=0.0, shift=0.0, points=None, t=None, from_tip=False):
        self.from_tip.append(from_tip)
        self.planes.append(np.zeros(4) if plane is None else plane)
        self.orientation.append(sign)
        self.shifts.append(shift)
        self.point_chunks.append(np.zeros((0, 3)) if points is None else points)
        self.t_chunks.append(np.zeros(0) if t is None else t)

    def start(self, found: list[_Crossing]):
        """Begin a stretch at the crossing nearest the handle whose face is not torn yet."""
        c = next((c for c in found if c.face not in self.visited), None)
        if c is None:
            return
        self._saved = (len(self.samples), len(self.faces), len(self.crossed), len(self.planes))
        if self.samples:
            self._row()  # the gap between two stretches
        self.samples.append(c)
        self.stretches.append([len(self.samples) - 1] * 2)
        self.stretch_faces.append(1)
        self.faces.append(c.face)
        self.visited.add(c.face)
        self.open, self.entry_edge, self.entry_point = True, None, c.point

    def close(self):
        """End the open stretch at its last sample. One that crossed no edge stays inside its face: a slit there,
        shortened (ending at an earlier time of the blade) where it would leave a sliver piece, and dropped where
        even that does (a blade that hardly moved)."""
        if not self.open:
            return
        self.open = False
        samples, faces, crossed, rows = self._saved
        if len(self.crossed) > crossed:
            return
        first_index = self.stretches[-1][0]
        first, last = self.samples[first_index], self.samples[-1]
        if self._slit_fits(first.face, first.point, last.point):
            self.inner.append(len(self.stretches) - 1)
            return
        for fraction in _SHORTER:
            time = first.time + fraction * (last.time - first.time)
            end = next((c for c in self.crossing(time) or [] if c.face == first.face), None)
            if end is not None and self._slit_fits(first.face, first.point, end.point):
                del self.samples[first_index + 1 :]
                self._truncate(first_index)
                self.samples.append(end)
                self.stretches[-1][1] = first_index + 1
                self._row()
                self.inner.append(len(self.stretches) - 1)
                return
        # a blade that barely crossed: the shortest slit without a sliver in its face, or in a neighbour of a face too
        # thin to hold one
        neighbours = self.edges.edge_faces[self.edges.face_edges[first.face]].ravel()
        neighbours = [int(g) for g in neighbours if g >= 0 and g != first.face and g not in self.visited]
        for face in [first.face, *neighbours]:
            ends = self._minimal_slit(first, face)
            if ends is not None:
                self.visited.discard(self.faces[-1])
                self.faces[-1] = face
                self.visited.add(face)
                del self.samples[first_index:]
                self._truncate(first_index)
                self.samples += ends
                self.stretches[-1][1] = first_index + 1
                self._row()
                self.inner.append(len(self.stretches) - 1)
                return
        self.visited.discard(self.faces[-1])
        del self.samples[samples:], self.faces[faces:], self.stretches[-1], self.stretch_faces[-1]
        self._truncate(rows)

    def _minimal_slit(self, c: _Crossing, face: int) -> list[_Crossing] | None:
        """The two ends of the shortest slit in ``face`` that leaves no sliver (_MINIMAL_LENGTHS of its longest edge),
        both at c's time: through the blade's crossing with the face's plane, along the blade's motion there (or,
        where none fits, turned, then nearer the face's centroid: _MINIMAL_TURNS, _MINIMAL_CENTRES); None where no
        candidate fits."""
        corners = self.V[self.F[face]]
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        squared = float(normal @ normal)
        blade = _blade(self.segments, c.time)
        along = float(normal @ (blade[1] - blade[0]))
        if squared == 0 or along == 0:
            return None
        unit_normal = normal / np.sqrt(squared)
        sides = np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1)
        longest = float(sides.max())
        # where tear_positions puts the crossing: the blade's line meets the face's plane (outside a neighbour)
        crossing = blade[0] + float(normal @ (corners[0] - blade[0])) / along * (blade[1] - blade[0])

        def barycentric(points):
            return np.stack(
                [
                    cross_rows(corners[(k + 1) % 3] - points, corners[(k + 2) % 3] - points) @ normal / squared
                    for k in range(3)
                ],
                axis=-1,
            )

        # the blade's motion at c's time (its ends' mean), in the face's plane; a blade that does not move across
        # it: the face's longest edge
        i = min(int(c.time), len(self.motion) - 1)
        motion = (self.segments[i + 1] - self.segments[i]).mean(axis=0)
        motion -= (motion @ unit_normal) * unit_normal
        if np.linalg.norm(motion) <= 1e-9 * longest:
            k = int(np.argmax(sides))
            motion = corners[k] - corners[k - 1]
        motion /= np.linalg.norm(motion)
        side = np.cross(unit_normal, motion)
        reference = barycentric(crossing[None])[0]
        for towards in _MINIMAL_CENTRES:
            centre = (1.0 - towards) * crossing + towards * corners.mean(axis=0)
            for turn in _MINIMAL_TURNS:
                direction = np.cos(turn) * motion + np.sin(turn) * side
                for length in _MINIMAL_LENGTHS:
                    half = 0.5 * length * longest * direction
                    ends = barycentric(np.stack([centre - half, centre + half]))
                    # inside the tip margin, where tear_positions' margin leaves them as they are
                    if ends.min() < 1.5 * _TIP_MARGIN:
                        continue
                    first, last = ends @ corners
                    if self._slit_fits(face, first, last):
                        return [
                            _Crossing(c.time, face, b, point, crossing, b - reference)
                            for b, point in zip(ends, (first, last))
                        ]
        return None

    def _truncate(self, rows: int):
        for chunk in (self.planes, self.orientation, self.shifts, self.from_tip, self.point_chunks, self.t_chunks):
            del chunk[rows:]

    def _slit_fits(self, face: int, first, last) -> bool:
        """Whether a slit in ``face`` from the point ``first`` to ``last`` (3,) leaves no sliver piece."""
        corners = self.V[self.F[face]]
        pieces = _slit_pieces(corners, first, last)
        if pieces is None:
            return False
        self.smallest.near(corners[None])
        return not sliver_mask(pieces, np.broadcast_to(corners, pieces.shape), self.smallest, _PIECE_HEADROOM).any()

    def step(self, found: list[_Crossing]) -> bool:
        """Extend the open stretch to one of the blade's crossings ``found``: the one nearest the stretch's last
        sample that the plane's curve joins where the blade passed (the same sheet, where several overlap)."""
        a = self.samples[-1]
        nearest = sorted(found, key=lambda c: float(np.sum((c.exact - a.exact) ** 2)))
        self.blocked = False
        return any(self._step(c) for c in nearest[:_ALTERNATIVES])

    def _step(self, c: _Crossing) -> bool:
        V, F, edges = self.V, self.F, self.edges
        a = self.samples[-1]
        if c.face == self.faces[-1]:
            if self.entry_edge is not None and _slivers(
                V, F, edges, [], [(c.face, self.entry_edge, self.entry_point, c.point)], self.smallest
            ):
                return True  # as the tear's tip, c would leave a sliver: the stretch goes on from its last sample
            self.samples.append(c)
            self.stretches[-1][1] = len(self.samples) - 1
            self._row()
            return True
        if c.face in self.visited:
            self.blocked = True
            return False
        # Pi through the blade's crossing at a and the blade at c: through the tip S_a where the step leaves the tip's
        # face (its pieces are fanned from it), else through the crossing before the margin (on the swept surface;
        # the margin would tilt the planes of short steps)
        from_tip = self.entry_edge is None
        anchor = a.point if from_tip else a.exact
        blade_a, blade_c = _blade(self.segments, a.time), _blade(self.segments, c.time)
        normal = cross_rows(blade_c[0] - anchor, blade_c[1] - anchor)
        length = np.linalg.norm(normal)
        if length <= 1e-12 * self.diagonal**2:
            return False  # the blade passes through S_a: no plane
        n = normal / length
        d = float(n @ anchor)
        chord = float(np.linalg.norm(c.exact - anchor))
        local = self.edge_length(self.faces[-1])
        # how far the plane strays from the quadrilateral swept over the step near the surface, where the tear
        # points lie (0 for a blade that translates): at the ends of the stretch of blade_a within a chord and an
        # edge of S_a
        direction = blade_a[1] - blade_a[0]
        along = (anchor - blade_a[0]) @ direction / (direction @ direction)
        spread = (chord + local) / np.sqrt(direction @ direction)
        ends = blade_a[0] + np.clip([along - spread, along + spread], 0.0, 1.0)[:, None] * direction
        deviation = float(np.abs((ends - anchor) @ n).max())
        if deviation > _NEAR_SWEPT * local:
            return False  # a turning blade: sampled more finely until the plane follows its swept surface
        reach = chord + 2.0 * local + deviation  # how far the walk may go before it has strayed
        unit = _SHIFT_STEP * local
        first_tip = self.samples[self.stretches[-1][0]].point
        # a shifted plane's sides from the plane's: n . x - (d + shift), or with GA X . (P + shift einf) = X . P - shift
        # (X . einf = -1 for a conformal point)
        base = signed_distances(V, n, d, self.predicates)
        blocked = False
        tried_sides, walked = set(), None
        for shift in unit * np.array([0.0, 1.0, -1.0, 2.0, -2.0, 3.0, -3.0, 4.0, -4.0]):
            if np.sign(shift) in tried_sides:
                continue
            s = base - shift
            try:
                walked = _walk(
                    V,
                    F,
                    edges,
                    s,
                    self.margin,
                    self.faces[-1],
                    self.entry_edge,
                    self.entry_point,
                    first_tip,
                    anchor,
                    c.point,
                    c.face,
                    set(self.visited),
                    reach,
                    self.smallest,
                )
                break
            except (_NearVertex, _Lost):
                continue
            except _Blocked:
                # a move the other way may pass on the other side of a vertex next to the path; moving on the same
                # way, or at all when the plane as given is blocked (a boundary, another sheet), would not help
                blocked = True
                if shift == 0:
                    break
                tried_sides.add(np.sign(shift))
        if walked is None:
            self.blocked |= blocked
            return False
        step_edges, step_faces = walked
        pairs = edges.edges[step_edges]
        points, t = edge_points(
            V[pairs[:, 0]], V[pairs[:, 1]], s[pairs[:, 0]], s[pairs[:, 1]], n, d + shift, self.predicates
        )
        # where the blade passed: every point near the swept quadrilateral (its two triangles)
        quad = np.stack([blade_a[0], blade_a[1], blade_c[1], blade_c[0]])
        squared, _, _ = igl.point_mesh_squared_distance(points, quad, _QUAD_TRIANGLES)
        lengths = np.linalg.norm(V[pairs[:, 1]] - V[pairs[:, 0]], axis=1)
        if np.any(np.sqrt(squared) > abs(shift) + _NEAR_POINT * lengths):
            return False
        # Orient the normal to the left of the path: face normal x direction of travel.
        left = cross_rows(_face_normal(V, F[self.faces[-1]]), points[0] - self.entry_point)
        sign = 1.0 if n @ left >= 0 else -1.0
        self.visited.update(step_faces)
        self.samples.append(c)
        self.stretches[-1][1] = len(self.samples) - 1
        self.stretch_faces[-1] += len(step_faces)
        self.faces += step_faces
        self.crossed += step_edges
        self.steps += [len(self.samples) - 2] * len(step_edges)
        self._row(np.append(sign * n, sign * (d + shift)), sign, sign * shift, points, t, from_tip)
        self.entry_edge, self.entry_point = step_edges[-1], points[-1]
        return True

    def _finer(self, ta, ca, tb, cb, depth) -> bool:
        """Whether the interval [ta, tb] is sampled more finely: until the blade moves under a quarter of an
        edge of the faces it crosses at its ends."""
        present = [c[0].face for c in (ca, cb) if c is not None]
        local = min(self.edge_length(f) for f in present)
        return depth < _MAX_DEPTH and (tb - ta) * self.motion[min(int(ta), len(self.motion) - 1)] > _RESOLUTION * local

    def follow(self, ta, ca, tb, cb, depth=0):
        """Tear along the blade's path from time ta to tb (within one step of the scalpel), given its crossings
        there (None: the blade misses the surface). An open stretch ends at ca on entry (or at a sample before it,
        where ca was left out), and at cb on exit (or before it)."""
        if ca is not None and cb is not None and self.open and self.step(cb):
            return
        if ca is None and cb is None:
            # the blade may still cross the surface in between: where edges pierce the surface it sweeps
            i = min(int(ta), len(self.motion) - 1)
            if i not in self.swept:
                self.swept[i] = _swept_crossings(self.V, self.edges, self.segments, i)
            inside = self.swept[i][(self.swept[i] > ta) & (self.swept[i] < tb)]
            if len(inside) and depth < _MAX_DEPTH:
                self.touched = True
                tm = float(inside[len(inside) // 2])
                cm = self.crossing(tm)
                self.follow(ta, ca, tm, cm, depth + 1)
                self.follow(tm, cm, tb, cb, depth + 1)
            return
        if self._finer(ta, ca, tb, cb, depth):
            tm = 0.5 * (ta + tb)
            cm = self.crossing(tm)
            self.follow(ta, ca, tm, cm, depth + 1)
            self.follow(tm, cm, tb, cb, depth + 1)
            return
        # at the finest sampling: a sample next to the stretch's end that its curve cannot reach only because it
        # passes by a vertex or would leave a sliver is left out, and the next one tried; else the tear ends at ca
        # (the blade leaves the surface, or its curve cannot join the next sample) and begins again at cb
        if self.open and cb is not None and not self.blocked:
            end = self.samples[-1]
            if min(float(np.linalg.norm(c.point - end.point)) for c in cb) <= self.edge_length(end.face):
                return
        self.close()
        if cb is not None:
            self.start(cb)


def tear_topology(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    scalpel: Scalpel | Sequence[Scalpel],
    *,
    predicates: str = "ga",
    tolerance: float = 1e-6,
    edges: MeshEdges | None = None,
) -> TearTopology:
    """The tear path of a scalpel moving over the mesh (V, F) (Algorithm 2, steps 1-3).

    Args:
        V: (n, 3) vertex positions (rest pose or posed).
        F: (m, 3) int faces.
        scalpel: the ``Scalpel``: handle and tip ends (k+1, 3) at k+1 >= 2 time steps, or a sequence of
            ``Scalpel``s (each of one sample, (3,) ends, or several) joined in order.
        predicates: ``"ga"`` or ``"euclidean"`` (Table 1) for the side of a vertex and the edge points.
        tolerance: planes passing closer than ``tolerance`` times the bounding-box diagonal to a path
            vertex are moved away from it (see the module docstring).
        edges: ``mesh_edges(F)``, precomputed once per topology.
    Returns:
        The ``TearTopology`` (its attributes say what it holds), which ``tear`` applies to a ``SkinnedMesh`` and
        ``tear_positions`` to the vertices.
    Raises:
        ValueError: a blade that never crosses the surface (neither its samples' segments nor the surface it
            sweeps meets the mesh). A blade that barely crosses it makes a minimal slit (module docstring); one
            that crosses it only in faces where no slit fits without a sliver, nor in their neighbours (a
            degenerate patch of the surface), is refused too, with a message that says so.

    Examples:
        >>> import numpy as np
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> blade = cutting.Scalpel([[0.18, 0.1, 0.0], [0.22, 0.1, 0.0]], [[0.18, 0.0, 0.0], [0.22, 0.0, 0.0]])
        >>> topology = cutting.tear_topology(np.asarray(mesh.V), np.asarray(mesh.F), blade)
        >>> topology.points.shape[1]  # the edge points of the tear
        3
    """
    check_choice("predicates", predicates, PREDICATES)
    V, F = check_triangle_mesh(V, F, min_faces=0)
    segments = check_scalpel(scalpel)
    if not tolerance >= 0:
        raise ValueError(f"tolerance: expected a non-negative number, got {tolerance}")
    edges = mesh_edges(F) if edges is None else edges
    if edges.face_edges.shape != F.shape:
        raise ValueError(f"edges: computed for another mesh (face_edges {edges.face_edges.shape}, F {F.shape})")
    path = _Path(V, F, edges, segments, predicates, tolerance * bounding_diagonal(V), SmallestFace(V, F))
    crossings = [path.crossing(float(i)) for i in range(len(segments))]
    if crossings[0] is not None:
        path.start(crossings[0])
    for i in range(len(segments) - 1):
        path.follow(float(i), crossings[i], float(i + 1), crossings[i + 1])
    path.close()
    if not path.stretches:
        if not path.touched:
            raise ValueError(
                f"scalpel: the scalpel never crosses the surface: none of its {len(segments)} samples' segments, "
                "nor the surface it sweeps, meets the mesh"
            )
        if not path.hit:  # found at the times where edges pierce the swept surface, the blade met no face
            raise ValueError(
                "scalpel: the scalpel never crosses the surface: the surface it sweeps only grazes the mesh's edges, "
                "its blade meets no face"
            )
        raise ValueError(
            "scalpel: the blade crosses the surface only in faces where no slit fits without a sliver triangle, "
            "nor in their neighbours (degenerate faces); move the scalpel or clean up the mesh there"
        )
    crossed = np.asarray(path.crossed, np.int64)
    sample_faces = np.array([c.face for c in path.samples])
    return TearTopology(
        sample_faces,
        F[sample_faces],
        np.array([c.point for c in path.samples]),
        np.array([c.exact for c in path.samples]),
        np.array([c.barycentric for c in path.samples]),
        np.array([c.time for c in path.samples]),
        np.asarray(path.stretches, np.int64),
        np.asarray(path.stretch_faces, np.int64),
        np.asarray(path.inner, np.int64),
        len(segments),
        np.asarray(path.faces, np.int64),
        crossed,
        edges.edges[crossed],
        np.concatenate(path.t_chunks),
        np.concatenate(path.point_chunks),
        np.asarray(path.steps, np.int64),
        np.asarray(path.planes).reshape(-1, 4),
        np.asarray(path.orientation),
        np.asarray(path.shifts),
        np.asarray(path.from_tip, bool),
        np.array([np.zeros(3) if c.offset is None else c.offset for c in path.samples]),
    )


def _retriangulate(V, F, edges: MeshEdges, topology: TearTopology, n_vertices: int):
    """Triangles replacing the path faces (Algorithm 2, step 5). Vertex ids: the input's, then the first and
    last sample of each stretch (n + 2r, n + 2r + 1), the left copies of the Q_j and then of the inner stretches'
    middle points (n + 2s + j, s stretches), the right copies (n + 2s + q + u + j). Per path face in plain
    Python: a path crosses few faces, and small arrays cost more than they save."""
    q = len(topology.t) + len(topology.inner)
    first_copy = n_vertices + 2 * len(topology.stretches)
    inner = {r: len(topology.t) + m for m, r in enumerate(topology.inner.tolist())}
    point_of_edge = {e: j for j, e in enumerate(topology.edge_ids.tolist())}
    corners_of = F[topology.faces].tolist()
    position = dict(zip(np.ravel(corners_of).tolist(), V[np.ravel(corners_of)].tolist()))
    points = topology.points.tolist()
    tip_points = topology.sample_points[topology.stretches.ravel()].tolist()
    local_edges = edges.face_edges[topology.faces].tolist()

    def sub(a, b):
        return (a[0] - b[0], a[1] - b[1], a[2] - b[2])

    def dot(a, b):
        return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]

    def is_left(normal, origin, direction, corner):
        # the corner lies left of the directed path (face normal x direction)
        return dot(cross3(normal, direction), sub(position[corner], origin)) > 0

    def copy(j, left):
        return first_copy + j if left else first_copy + q + j

    triangles = []
    at, j0 = 0, 0  # the stretch's first face on the path and its first point
    for r, count in enumerate(topology.stretch_faces.tolist()):
        last = at + count - 1
        if r in inner:  # a slit inside one face
            first_tip, last_tip = topology.sample_points[topology.stretches[r]]
            slots = [*F[topology.faces[at]].tolist(), n_vertices + 2 * r, n_vertices + 2 * r + 1]
            slots += [copy(inner[r], True), copy(inner[r], False)]
            slit = _slit_triangles(V[F[topology.faces[at]]], first_tip, last_tip)
            triangles += np.asarray(slots)[slit].tolist()
            at += 1
            continue
        for face in range(at, last + 1):
            corners, local = corners_of[face], local_edges[face]
            a, b, c = (position[v] for v in corners)
            normal = cross3(sub(b, a), sub(c, a))
            # the points on the edges where the path enters and leaves the face (the stretch's j-th face
            # lies between its points j - 1 and j)
            entry = j0 + face - at - 1 if face > at else None
            exit_ = j0 + face - at if face < last else None
            # the face's boundary in winding order, with its path points on their edges
            cycle = []
            for k in range(3):
                cycle.append(("corner", corners[k]))
                j = point_of_edge.get(local[k])
                if j is not None and j in (entry, exit_):
                    cycle.append(("point", j))
            if entry is None or exit_ is None:  # a tip face: fan from the tip S inside it
                tip = n_vertices + 2 * r + (0 if entry is None else 1)
                j = exit_ if entry is None else entry
                tip_point = tip_points[tip - n_vertices]
                direction = sub(points[j], tip_point) if entry is None else sub(tip_point, points[j])
                for m in range(len(cycle)):
                    x, y = cycle[m], cycle[(m + 1) % len(cycle)]
                    if "point" in (x[0], y[0]):
                        corner = y[1] if x[0] == "point" else x[1]
                        copied = copy(j, is_left(normal, points[j], direction, corner))
                        ids = [copied if z[0] == "point" else z[1] for z in (x, y)]
                    else:
                        ids = [x[1], y[1]]
                    triangles.append((ids[0], ids[1], tip))
                continue
            # a chord face: the segment entry -> exit splits it into two convex pieces
            start = cycle.index(("point", entry))
            cycle = cycle[start:] + cycle[:start]
            stop = cycle.index(("point", exit_))
            direction = sub(points[exit_], points[entry])
            for piece in (cycle[: stop + 1], cycle[stop:] + cycle[:1]):
                corner = next(z[1] for z in piece if z[0] == "corner")
                left = is_left(normal, points[entry], direction, corner)
                ids = [copy(z[1], left) if z[0] == "point" else z[1] for z in piece]
                coordinates = [points[z[1]] if z[0] == "point" else position[z[1]] for z in piece]
                triangles += fan_triangles(ids, coordinates)
        at, j0 = last + 1, j0 + count - 1
    return np.asarray(triangles, np.int64).reshape(-1, 3)


def _blend(J, W, corners, coefficients):
    """``blend_weights``, also of no points."""
    if not len(corners):
        return np.zeros((0, J.shape[1]), J.dtype), np.zeros((0, W.shape[1]), W.dtype)
    return blend_weights(J, W, corners, coefficients)


@overload
def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel | Sequence[Scalpel],
    *,
    opening: float = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[False] = ...,
) -> SkinnedMesh: ...


@overload
def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel | Sequence[Scalpel],
    *,
    opening: float = ...,
    predicates: str = ...,
    side_weight: float = ...,
    tolerance: float = ...,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = ...,
    edges: MeshEdges | None = ...,
    return_topology: Literal[True],
) -> tuple[SkinnedMesh, TearTopology]: ...


def tear(
    mesh: SkinnedMesh,
    scalpel: Scalpel | Sequence[Scalpel],
    *,
    opening: float = 0.0,
    predicates: str = "ga",
    side_weight: float = 0.0,
    tolerance: float = 1e-6,
    joint_matrices: Float[ArrayLike, "j 4 4"] | None = None,
    edges: MeshEdges | None = None,
    return_topology: bool = False,
) -> SkinnedMesh | tuple[SkinnedMesh, TearTopology]:
    """Tear a skinned mesh with a scalpel moving through its samples (Algorithm 2).

    Args:
        mesh: the SkinnedMesh (``deform``). A tear ends at the surface's boundary: weld a mesh whose vertices are
            split along UV seams (``deform.weld``, ``load_model(..., weld=True)``), or it ends at every seam.
        scalpel: the ``Scalpel``: its handle and tip ends (k+1, 3) at time steps t_0 .. t_k, in the
            space of the mesh as torn: the bind pose, or the pose of ``joint_matrices``; or a sequence of
            ``Scalpel``s (one sample each, (3,) ends, or more) joined in order. Two samples are the paper's
            ``scalpel_0, scalpel_1``; more make one tear along the whole path.
        opening: the distance between the two copies of every interior tear point (each is pushed
            ``opening / 2`` along the tear plane's normal, away from it); 0 leaves a closed slit.
        predicates: ``"ga"`` or ``"euclidean"`` (Table 1).
        side_weight: in [0, 1]; 0 gives both copies of a tear point the barycentric weights of its
            edge (sec. 4.3); towards 1 each copy leans to the weights of its own side's endpoint.
        tolerance: see ``tear_topology``.
        joint_matrices: (j, 4, 4) joint matrices of a pose (``deform.joint_matrices``): tear the mesh
            *in that pose*, the scalpel in world space. New vertices get the rest positions whose LBS
            image in that pose is their torn position (exact for LBS).
        edges: ``mesh_edges(mesh.F)``, precomputed.
        return_topology: also return the ``TearTopology`` (for ``tear_positions``).
    Returns:
        The torn SkinnedMesh (the input's vertices first, in order; then the tips, the first and last
        crossing of each stretch (S_0 and S_k when the blade stays on the surface), the left copies of the
        Q_j, the right copies), and the TearTopology when ``return_topology``.
    Raises:
        ValueError: bad arguments, or a blade that never crosses the surface (see ``tear_topology``).

    Examples:
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> blade = cutting.Scalpel([[0.18, 0.1, 0.0], [0.22, 0.1, 0.0]], [[0.18, 0.0, 0.0], [0.22, 0.0, 0.0]])
        >>> torn = cutting.tear(mesh, blade)  # handle above the skin, tip inside, moved 4 cm along the arm
        >>> torn.V.shape[0] > mesh.V.shape[0]
        True
    """
    if not 0.0 <= side_weight <= 1.0:
        raise ValueError(f"side_weight: expected a number in [0, 1], got {side_weight}")
    if not (np.isfinite(opening) and opening >= 0):
        raise ValueError(f"opening: expected a finite non-negative distance, got {opening}")
    F = np.asarray(mesh.F)
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    space, joint_matrices = posed_vertices(mesh, joint_matrices)
    edges = mesh_edges(F) if edges is None else edges
    topology = tear_topology(space, F, scalpel, predicates=predicates, tolerance=tolerance, edges=edges)
    n_vertices = len(space)

    tips = topology.stretches.ravel()
    J_tips, W_tips = blend_weights(J, W, topology.sample_corners[tips], topology.sample_barycentric[tips])
    # the duplicated points: the Q_j on their edges, then the middle points of the slits inside one face
    ends = topology.stretches[topology.inner]
    middle_corners = topology.sample_corners[ends[:, 0]]
    middle_barycentric = 0.5 * topology.sample_barycentric[ends].sum(axis=1)
    J_q, W_q = (
        np.concatenate(parts)
        for parts in zip(
            _blend(J, W, topology.crossing, np.stack([1.0 - topology.t, topology.t], axis=1)),
            _blend(J, W, middle_corners, middle_barycentric),
        )
    )
    middle = 0.5 * topology.sample_points[ends].sum(axis=1)
    slit = cross_rows(
        _face_normal(space, middle_corners.T), topology.sample_points[ends[:, 1]] - topology.sample_points[ends[:, 0]]
    )
    points = np.concatenate([topology.points, middle])
    normals = np.concatenate([topology.planes[topology.step, :3], slit / np.linalg.norm(slit, axis=1, keepdims=True)])
    q = len(points)
    copies_J, copies_W = [], []
    for side in (1.0, -1.0):
        if side_weight > 0 and q:
            # each copy leans to the corner farthest on its side: an edge's end, or a face's corner
            ids = np.concatenate([np.pad(topology.crossing, ((0, 0), (0, 1)), mode="edge"), middle_corners])
            lean = side * np.einsum("ijk,ik->ij", space[ids] - points[:, None], normals)
            own = np.take_along_axis(ids, np.argmax(lean, axis=1)[:, None], axis=1)[:, 0]
            Jc, Wc = blend_weights(
                np.concatenate([J, J_q]),
                np.concatenate([W, W_q]),
                np.stack([n_vertices + np.arange(q), own], axis=1),
                np.broadcast_to([1.0 - side_weight, side_weight], (q, 2)),
            )
        else:
            Jc, Wc = J_q, W_q
        copies_J.append(Jc)
        copies_W.append(Wc)
    J_new = np.concatenate([J_tips] + copies_J)
    W_new = np.concatenate([W_tips] + copies_W)
    world = np.concatenate(
        [topology.sample_points[tips], points + 0.5 * opening * normals, points - 0.5 * opening * normals]
    )
    rest = rest_positions(J_new, W_new, world, joint_matrices)

    keep = np.ones(len(F), bool)
    keep[topology.faces] = False
    triangles = _retriangulate(space, F, edges, topology, n_vertices)
    torn = skinned_mesh_like(
        mesh,
        np.concatenate([np.asarray(mesh.V, np.float64), rest]),
        np.concatenate([np.compress(keep, F, axis=0), triangles]),
        np.concatenate([J, J_new]),
        np.concatenate([W, W_new]),
    )
    return (torn, topology) if return_topology else torn


def tear_positions(
    V: Float[ArrayLike, "n 3"],
    topology: TearTopology,
    scalpel: Scalpel | Sequence[Scalpel],
    *,
    opening: Float[ArrayLike, ""] = 0.0,
) -> tuple[Float[Array, "t 3"], Float[Array, "q 3"], Float[Array, "q 3"]]:
    """Positions of a tear's new vertices as a JAX function of the vertices, the scalpel and the
    opening, for a fixed topology: differentiable with respect to all three (``jax.grad`` over a
    ``Scalpel`` gives a ``Scalpel``). Each sample S_i is the blade's crossing with its face's plane at the
    sample's time (the blade interpolated linearly between the scalpel's samples), its barycentric
    coordinates moved by ``topology.sample_offsets`` (the ends of a minimal slit) and kept the same 2% off the
    face's edges as in ``tear_topology``.

    Args:
        V: (n, 3) vertex positions, as torn (posed, when torn with ``joint_matrices``).
        topology: the tear's ``TearTopology``.
        scalpel: the ``Scalpel`` (or sequence of them), with as many samples (k+1) as the topology was
            computed from.
        opening: () the distance between the two copies of every Q_j (see ``tear``).
    Returns:
        (tips (2r, 3): the first and last crossing of each of the r stretches (S_0 and S_k for one), left
        (q + u, 3), right (q + u, 3): the two copies of every Q_j, then of the middle point of each of the u
        slits inside one face).

    Examples:
        >>> import numpy as np
        >>> import deform, cutting
        >>> mesh = deform.default_arm().mesh
        >>> V, F = np.asarray(mesh.V), np.asarray(mesh.F)
        >>> blade = cutting.Scalpel([[0.18, 0.1, 0.0], [0.22, 0.1, 0.0]], [[0.18, 0.0, 0.0], [0.22, 0.0, 0.0]])
        >>> tips, left, right = cutting.tear_positions(V, cutting.tear_topology(V, F, blade), blade)
        >>> left.shape == right.shape  # the two copies of each edge point (apart with an opening)
        True
    """
    V = jnp.asarray(V)
    scalpel = joined_scalpel(scalpel)
    handle, tip = jnp.asarray(scalpel.handle), jnp.asarray(scalpel.tip)
    if handle.shape != (topology.scalpel_samples, 3) or tip.shape != handle.shape:
        raise ValueError(
            f"scalpel: expected handle and tip ends of shape ({topology.scalpel_samples}, 3) (the "
            f"topology's samples), got {handle.shape}, {tip.shape}"
        )
    # the blade at each sample's time
    times = np.asarray(topology.sample_times)
    i = np.minimum(np.floor(times).astype(np.int64), topology.scalpel_samples - 2)
    a = jnp.asarray(times - i)[:, None]
    X0, X1 = (1.0 - a) * handle[i] + a * handle[i + 1], (1.0 - a) * tip[i] + a * tip[i + 1]
    corners = V[jnp.asarray(topology.sample_corners)]  # (s, 3, 3)
    face_normals = jnp.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    s = jnp.sum(face_normals * (corners[:, 0] - X0), -1) / jnp.sum(face_normals * (X1 - X0), -1)
    crossings = X0 + s[:, None] * (X1 - X0)
    # barycentric coordinates in the face, with tear_topology's margin (piecewise smooth in the tool)
    squared = jnp.sum(face_normals * face_normals, -1)
    barycentric = (
        jnp.stack(
            [
                jnp.sum(
                    face_normals * jnp.cross(corners[:, (k + 1) % 3] - crossings, corners[:, (k + 2) % 3] - crossings),
                    -1,
                )
                for k in range(3)
            ],
            axis=-1,
        )
        / squared[:, None]
    )
    barycentric = jnp.maximum(barycentric + jnp.asarray(topology.sample_offsets), _TIP_MARGIN)
    barycentric = barycentric / jnp.sum(barycentric, -1, keepdims=True)
    samples = jnp.einsum("sk,skc->sc", barycentric, corners, precision=EXACT)
    # the planes of the steps that gave tear points only (the others may have none)
    used, step = np.unique(topology.step, return_inverse=True)
    origin = jnp.where(jnp.asarray(topology.from_tip[used])[:, None], samples[used], crossings[used])
    normals = jnp.cross(X0[used + 1] - origin, X1[used + 1] - origin)
    normals = (
        jnp.asarray(topology.orientation[used])[:, None] * normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    )
    offsets = jnp.sum(normals * origin, -1) + jnp.asarray(topology.shift[used])
    n, d = normals[step], offsets[step]
    A, B = V[topology.crossing[:, 0]], V[topology.crossing[:, 1]]
    sA, sB = jnp.sum(A * n, -1) - d, jnp.sum(B * n, -1) - d
    Q = A + (sA / (sA - sB))[:, None] * (B - A)
    # the middle points of the slits inside one face, on the left of face normal x (last tip - first tip)
    first, last = samples[topology.stretches[topology.inner, 0]], samples[topology.stretches[topology.inner, 1]]
    slit = jnp.cross(face_normals[topology.stretches[topology.inner, 0]], last - first)
    points = jnp.concatenate([Q, 0.5 * (first + last)])
    normals = jnp.concatenate([n, slit / jnp.linalg.norm(slit, axis=-1, keepdims=True)])
    half = 0.5 * opening * normals
    return samples[jnp.asarray(topology.stretches.ravel())], points + half, points - half
