"""A simulated body from a rigged model: its tets, skinning weights on the tet nodes, the nodes the skeleton drives,
and the model's own surface embedded in the tets (``character_body``; ``xfem._character`` plays clips on it).

Spaces. The tets are made (fTetWild, ``tetrahedralize_surface``) from the surface in the REST CONFIGURATION: the
skeleton's rest pose by linear blending, ``r_p = sum_j w_pj G_j p`` (``deform.rest_pose(model, "lbs")``; ``p`` in
mesh space, ``G_j`` joint j's rest matrix, its bone's global rest matrix ``B_j`` times its inverse bind), world
coordinates, where every skin of a model stands together (the mesh spaces of several skins need not agree, nor a
bind pose equal the rest pose). ``CharacterBody.nodes == tets.X`` are the nodes there. Their mesh space is the
model's (``node_model`` keeps its inverse binds): node a's mesh-space position is the ``y_a`` that the rest pose
takes to ``x_a`` by linear blending, ``sum_j W_aj G_j y_a = x_a``, so ``deform.skin_model(node_model, t, method)``
moves it to ``sum_j W_aj P_j(t) IB_j y_a`` (``P_j(t)``: bone j's posed global matrix, ``IB_j`` its inverse bind),
and by linear blending the rest pose gives ``x_a`` back exactly.

Parts (``per_part``, the default). The surface falls into parts, the connected sets of its triangles (a rifle, a
clothing layer, a robot's plate, an inner mesh of joints). Where two parts of different bones touch or overlap, a
tet that holds both blends their motions, and no refinement separates surfaces that touch. So each part gets tets
of its own, which share no node with another part's: fTetWild meshes the parts in groups, the parts of a group
having bounding boxes at least 4 envelopes (``epsilon``) apart, so that their tets cannot join (fTetWild's tets
end within an envelope of the surface). Each connected set of tets belongs to the part most of its boundary nodes
lie nearest to (the same rule for saved ``tets``), and each part's vertices are embedded in its own tets; a part
that encloses no volume (an open sheet) has no tets, and its vertices take the nearest tets of any part. Nested
parts (the joints inside Xbot's skin, a body inside its clothes) overlap in volume: their masses add.

Weights (the transfer rule). Skinned directly, a surface vertex goes to ``sum_j w_pj P_j IB_j p``; embedded (its
barycentric coordinates ``b_pa`` in the rest tets), to ``sum_a b_pa sum_j W_aj P_j IB_j y_a``. The two agree in
every pose when, for each joint j, ``sum_a b_pa W_aj = w_pj`` (the weight) and ``sum_a b_pa W_aj (y_a - p) = 0``
(its first moment about the vertex, in mesh space). The node weights of joint j minimize, over the surface's
vertices, ``sum_p l^2 (sum_a b_pa W_aj - w_pj)^2 + |sum_a b_pa W_aj (y_a - p)|^2 + mu W_j^T K W_j``, with ``l`` =
0.1 diagonal (the lever arm that weighs a weight's error against a moment's), ``K`` the tets' cotangent stiffness
(their Dirichlet energy: nodes far from the surface get harmonic weights) and ``mu`` 1e-2 of the data's trace over
K's; one sparse factorization serves every joint, and the rows sum to 1 (the constant solves the summed problem).
The weights are then clamped to [0, 1], cut to the ``influences`` largest and normalized. The ``y_a`` depend on the
weights: the first fit takes the moments in the rest configuration (``x_a - r_p`` against ``w_pj (G_j p - r_p)``,
the same fit where the bind pose is the rest pose, ``G_j`` equal for a vertex's joints), and where it is not, two
more fits in mesh space follow, each with the ``y_a`` of the previous weights. (Fitted in the rest configuration
alone, a vertex blending joints whose rest images ``G_j p`` lie apart needs weights that change by that distance
over a tet, beyond [0, 1] in small tets: refinement made it worse.) Refinement (``refine``, fTetWild's tets by
default): linear tets cannot follow weights that change inside a tet, so the embedded surface is checked against
the directly skinned one (linear blending) at probe poses (at least 16 times spread over each of the model's first
4 clips, 64 in all; without clips, 64 random poses turning every bone by 45 degrees). The tets of the vertices off
by more than 0.8 ``tolerance`` diagonals are bisected at their longest edges (Rivara's longest-edge propagation
path: the mesh stays conforming, the parts' tets apart, and the shapes do not degrade) to 0.7 of their longest
edge, not below 1/64 of the initial median, and the weights are fitted again, for at most 12 rounds and 8 times
fTetWild's tets, the worst vertices' tets first; a vertex whose error fell by less than a tenth since its tet was
last refined sits out the next round. A vertex outside the tets (where fTetWild's filter cut a thin feature off)
by more than a quarter of its tet's longest edge is not refined (it follows its tet's linear map extrapolated, and a
smaller tet would amplify the fit's errors by the distance over its size): up to two such edges out it becomes a
node instead, the apex of a tet of its own on the nearest boundary face of its part (one a face, and none that would
hold another node), so that it is embedded at that node, whose weights are its own. Where surfaces of different
bones touch inside one part (an arm against the chest in the rest pose, then raised), tets holding both blend them
and no refinement separates them; nor does it reach a vertex whose error stopped falling, or one left when the rounds
or the budget are spent. Such vertices are pinned (``_pin_vertices``), for at most 16 more rounds, the worst first:
each becomes a node, placed by re-coning the star of a simplex of its tet: every tet around that simplex has one of
the simplex's corners replaced by the vertex in turn (a 1-4 split inside a tet, 2-6 across a face, two tets for each
around an edge, a node moved to the vertex next to it). The simplex chosen is the one that leaves the thinnest new
tet thickest, among those that keep the region the tets fill (inside the mesh, or with the vertex on it), else among
boundary simplices, which move the boundary towards the vertex (on the surface) by at most half a tet's height; and
only where each new tet keeps a volume ratio of 0.1 (``tet_quality``'s) or its parent's. A vertex no star of
which keeps that bound tries 0.05 (a dense surface's vertices crowd the tets), and one that finds none at 0.05
either (or whose node is pinned already) has its tet bisected, beyond the budget by at most 32 tets for each, to be
tried again in the next round among smaller simplices (a bisected piece may be somewhat thinner than its parent).
The mesh stays conforming, and a pinned node's weights are the vertex's own (after each fit), so the vertex follows
its directly skinned self exactly in every pose; the others' weights are fitted around the pinned ones. Tets given
as they are (a saved body's) are not re-coned, but a vertex above the tolerance that lies at one of their nodes (a
pin of the saved body) is pinned there where that lowers the largest error at the probe poses. A vertex that still
cannot be pinned (two vertices of different bones nearly coincide) keeps its error, and a ``UserWarning`` gives the
error reached. Where the tets still miss ``tolerance`` at the end (coarse tets of a low-poly model that spent the
budget), the weights are fitted again with a tenth and a hundredth of the smoothness, and the fit
closest at the probe poses is kept; the probe poses choose among the fits for tets given as they are too, so a saved
body's tets give its weights back.

Driven nodes (the core rule). Bone j's core is the set of points within ``core * r_j`` of its segments (from the
joint to each child joint; a leaf joint is a point), where ``r_j`` is the median distance from those segments of
the surface vertices whose largest weight is j's: the limb's radius there. A node is driven when it lies in some
bone's core and not on the tets' boundary (the skin: a bone may run there, as a tail's or an ear's does); a bone
whose core holds no such node (a thin limb on coarse tets) drives its nearest interior nodes instead, those within
twice the nearest one's distance and within ``r_j``. Bones whose vertices are fewer than 4 have no core. A part of
the surface (a connected set of its triangles) whose tets hold no driven node (an accessory away from the bones: a
rifle held out in a hand, a robot's plate) has every node of those tets driven: it follows its bones as skinned,
instead of hanging on flesh alone.

Every connected set of tets holds a driven node: one without (a part meshed on its own that embeds no vertex) has
all its nodes driven.

Anchors. A cut that severs a limb severs its bones too: the pieces that keep the skeleton's root are driven on, the
others fall. The anchors are, in each connected set of tets (one per part meshed on its own), the driven nodes of
the bones closest to the skeleton's root (the fewest parents up) among the bones with a core and driven nodes
there; ``simulate_character`` releases the driven nodes of every piece without an anchor. So every part follows
the rig from the start, and a part that a cut does not cross (an inner joint mesh or a held rifle beyond the cut)
keeps following its bones: the parts do not hold each other.
"""

from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import igl
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Float, Int
from scipy.sparse.csgraph import connected_components

import deform
from _jaxcga_shared.checks import check_real
from _jaxcga_shared.mesh import bounding_diagonal, tet_face_matching
from _jaxcga_shared.tetmeshing import embed, ftetwild
from xfem._surface_tets import (
    EDGE_LENGTH,
    EPSILON,
    SurfaceEmbedding,
    TetQuality,
    tet_quality,
    tetrahedralize_surface,
    volume_ratios,
)
from xfem._tetmesh import TetMesh, tet_mesh

CORE = 0.5  # the default core radius, as a fraction of the limb's radius about the bone
INFLUENCES = 8  # joints per node: refined tets near joints blend more bones than a surface vertex
_MIN_VERTICES = 4  # a bone with fewer surface vertices (by largest weight) has no core
_LENGTH = 0.1
_SMOOTHNESS = 1e-2
_WEAKER = (0.1, 0.01)  # the smoothness's fractions tried where the refined tets still miss the tolerance
_PROBES = 64
_PER_CLIP = 16
_CLIPS = 4
_PROBE_ANGLE = np.pi / 4
_SEED = 0
_ROUNDS = 12
_FINEST = 1 / 64
_MARGIN = 0.8
_GROWTH = 8  # the refinement stops at this many times fTetWild's tets
_SHRINK = 0.7
_STUCK = 0.9  # a vertex whose error fell by less after a refinement of its tet sits out a round
LIMIT = 1e-3  # the surface limit the tets are refined to, a fraction of the diagonal
_OUTSIDE = 0.25  # a vertex farther outside its tet than this fraction of the tet's longest edge: not refined
_CAP_REACH = 2.0  # ... and given a tet of its own up to this many of those edges outside
_BIND_FITS = 2  # the fits in mesh space, each with the mesh-space nodes of the previous weights
_BIND_SPREAD = (
    1e-6  # a vertex's joints' rest images further apart (diagonals; closer: float32 rounding): fit in mesh space
)
_KEEP = 0.1  # the tets that pinning makes keep this volume ratio (tet_quality's), or their parent's where lower
_FLAT = 1e-3  # a capping tet's height above its face, a fraction of the face's longest edge, at least
_NEAR = 0.5  # a pinned vertex re-cones the star of a boundary simplex it lies this near (its other coordinates' sum)
_ON = 1e-9  # a vertex whose coordinates off a simplex sum to at most this lies on it
_PIN_ROUNDS = 16  # rounds that pin vertices after the refinement has ended
_PIN_SPLIT = 32  # the tets a round may add beyond the budget for each tet of a vertex that could not be pinned
_APART = 4  # parts whose bounding boxes lie this many envelopes apart are meshed in one fTetWild call


class CharacterBody(NamedTuple):
    """A rigged model made into a tet body (``character_body``).

    Attributes:
        model: the ``deform.RiggedModel`` it was made from (weights normalized).
        node_model: the same skeleton, clips and inverse binds with the tet nodes as its mesh (in the model's mesh
            space, where its rest pose by linear blending puts them at ``nodes``; the transferred weights):
            ``deform.skin_model(node_model, t, method)`` skins the nodes.
        tets: the ``TetMesh`` in the rest configuration (world coordinates, the skeleton's rest pose).
        nodes: (n, 3) float64 the tet nodes (``node_model.mesh.V``, equal to ``tets.X``).
        driven: (nd,) int64 sorted indices of the nodes the skeleton drives.
        anchors: (na,) int64 the driven nodes whose pieces stay driven after a cut (module docstring).
        surface: (s, 3) float64 the model's surface in the rest configuration.
        faces: (f, 3) int64 its triangles.
        embedding: the ``SurfaceEmbedding`` of ``surface`` in ``tets``.
        density: the mass density (per unit volume of the rest configuration).
        gravity: (3,) float64 the gravitational acceleration, world coordinates.
        diagonal: the bounding-box diagonal of ``surface``.
        quality: the ``TetQuality`` of ``tets``.
        seconds: the wall time of making the tets and their weights (fTetWild, the fits and the refinement).
    """

    model: deform.RiggedModel
    node_model: deform.RiggedModel
    tets: TetMesh
    nodes: Float[np.ndarray, "n 3"]
    driven: Int[np.ndarray, " nd"]
    anchors: Int[np.ndarray, " na"]
    surface: Float[np.ndarray, "s 3"]
    faces: Int[np.ndarray, "f 3"]
    embedding: SurfaceEmbedding
    density: float
    gravity: Float[np.ndarray, " 3"]
    diagonal: float
    quality: TetQuality
    seconds: float


def _dense_weights(mesh: deform.SkinnedMesh) -> np.ndarray:
    """(v, j) the vertices' weights over the mesh's joints."""
    J, W = np.asarray(mesh.J), np.asarray(mesh.W, np.float64)
    dense = np.zeros((len(J), mesh.num_joints))
    np.add.at(dense, (np.repeat(np.arange(len(J)), J.shape[1]), J.ravel()), W.ravel())
    return dense


def _trim(dense: np.ndarray, influences: int) -> tuple[np.ndarray, np.ndarray]:
    """The ``influences`` largest weights of each row (indices, weights normalized to sum 1)."""
    k = min(influences, dense.shape[1])
    J = np.argsort(-dense, axis=1, kind="stable")[:, :k]
    W = np.take_along_axis(dense, J, axis=1)
    W = W / W.sum(axis=1, keepdims=True)
    if k < influences:  # pad to the glTF width with zero weights on joint 0
        J = np.concatenate([J, np.zeros((len(J), influences - k), J.dtype)], axis=1)
        W = np.concatenate([W, np.zeros((len(W), influences - k))], axis=1)
    return J.astype(np.int32), W


def transfer_weights(
    V: Float[npt.ArrayLike, "v 3"],
    F: Int[npt.ArrayLike, "f 3"],
    weights: Float[npt.ArrayLike, "v j"],
    points: Float[npt.ArrayLike, "n 3"],
) -> Float[np.ndarray, "n j"]:
    """Weights at points from a surface's vertex weights: those of each point's closest surface point (the
    barycentric blend of its triangle's corners; host, libigl).

    Args:
        V: (v, 3) surface vertices; F: (f, 3) its triangles.
        weights: (v, j) weights per vertex.
        points: (n, 3) the points.
    Returns:
        (n, j) float64 weights (rows sum to what the vertices' rows sum to).
    """
    V, F = np.asarray(V, np.float64), np.asarray(F, np.int64)
    points = np.asarray(points, np.float64)
    _, face, closest = igl.point_mesh_squared_distance(points, V, F)
    face = np.asarray(face, np.int64)
    corners = V[F[face]]
    bary = igl.barycentric_coordinates(
        np.ascontiguousarray(closest), *(np.ascontiguousarray(corners[:, k]) for k in range(3))
    )
    bary = np.clip(bary, 0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    weights = np.asarray(weights, np.float64)
    return np.einsum("nk,nkj->nj", bary, weights[F[face]])


def _rest_joint_matrices(model: deform.RiggedModel) -> tuple[np.ndarray, np.ndarray]:
    """The skin joints' bones' global rest matrices (j, 4, 4) and their joint matrices at rest ``G_j`` (global times
    inverse bind: mesh space to the rest configuration), float64."""
    skeleton = model.skeleton
    local = deform.local_matrices(skeleton)
    world = np.asarray(deform.forward_kinematics_matrices(skeleton.parents, local), np.float64)
    bones = world[np.asarray(model.mesh.joints)]
    return bones, bones @ np.asarray(model.mesh.inverse_bind, np.float64)


def fit_weights(
    X: np.ndarray,
    T: np.ndarray,
    embedding: SurfaceEmbedding,
    surface: np.ndarray,
    targets: np.ndarray,
    moments: np.ndarray,
    length: float,
    smoothness: float,
    fixed: tuple[np.ndarray, np.ndarray] | None = None,
) -> np.ndarray:
    """Node weights whose barycentric blend reproduces the surface's linear blend skinning (module docstring).

    Args:
        X: (n, 3) the nodes (rest configuration); T: (t, 4) the tets.
        embedding: the surface's points in the tets.
        surface: (s, 3) the points (rest configuration).
        targets: (s, j) the points' weights ``w_pj``.
        moments: (s, j, 3) ``w_pj (G_j p - r_p)``: the weighted offsets of each joint's rest image of the point.
        length: the length that weighs a weight's error against a moment's.
        smoothness: the weight of the tets' Dirichlet energy, relative to the data's (scale free).
        fixed: None, or (nodes (p,), their weights (p, j)): weights the others are fitted around (pinned vertices').
    Returns:
        (n, j) the least-squares weights, unclamped (rows sum to 1 up to the solve's rounding).
    """
    import scipy.sparse as sparse
    import scipy.sparse.linalg as sparse_linalg

    n, s = len(X), len(surface)
    rows = np.repeat(np.arange(s), 4)
    cols = embedding.nodes.ravel()
    b = embedding.weights.ravel()
    blocks = [sparse.csr_matrix((length * b, (rows, cols)), shape=(s, n))]
    offsets = X[embedding.nodes] - surface[:, None]  # (s, 4, 3)
    for d in range(3):
        blocks.append(sparse.csr_matrix((b * offsets[..., d].ravel(), (rows, cols)), shape=(s, n)))
    M = sparse.vstack(blocks).tocsr()
    Y = np.concatenate([length * targets, moments[..., 0], moments[..., 1], moments[..., 2]], axis=0)
    normal = (M.T @ M).tocsc()
    K = -igl.cotmatrix(X, T)
    scale = smoothness * normal.diagonal().sum() / max(K.diagonal().sum(), 1e-300)
    system = (normal + scale * K).tocsc()
    rhs = np.asarray(M.T @ Y)
    if fixed is None or not len(fixed[0]):
        return sparse_linalg.splu(system).solve(rhs)
    nodes, values = fixed
    free = np.setdiff1d(np.arange(n), nodes)
    weights = np.empty((n, rhs.shape[1]))
    weights[nodes] = values
    A = system[free][:, free].tocsc()
    weights[free] = sparse_linalg.splu(A).solve(rhs[free] - system[free][:, nodes] @ values)
    return weights


def _bind_positions(Y: np.ndarray, G: np.ndarray, J: np.ndarray, W: np.ndarray) -> np.ndarray:
    """(n, 3) the nodes' mesh-space positions ``y_a``: those that linear blending of the joints' rest matrices G
    (j, 4, 4) with the nodes' weights (J, W) (n, k) takes to the rest positions Y (n, 3), ``sum_j W_aj G_j y_a =
    x_a``."""
    blend = np.einsum("nk,nkab->nab", W, G[J][:, :, :3])  # (n, 3, 4)
    return np.linalg.solve(blend[:, :, :3], (Y - blend[:, :, 3])[..., None])[..., 0]


def _probe_poses(model: deform.RiggedModel) -> np.ndarray:
    """(k, j, 4, 4) the posed global matrices of the skin joints' bones in the poses the refinement checks: at
    least ``_PER_CLIP`` times spread over each of the model's first ``_CLIPS`` clips (``_PROBES`` in all), or, for a
    model without
    clips, ``_PROBES`` random poses, each bone turned about a random axis by ``_PROBE_ANGLE`` from its rest."""
    skeleton = model.skeleton
    clips = model.clips[:_CLIPS]  # each clip compiles its own sampler: the first few (clip 0 is the default)
    if clips:
        each = max(_PER_CLIP, -(-_PROBES // len(clips)))
        posed = np.stack(
            [
                np.asarray(deform.sample_pose(model, t, "lbs", clip=c), np.float64)
                for c, clip in enumerate(clips)
                for t in np.linspace(clip.start, clip.end, each)
            ]
        )
    else:
        local = np.asarray(deform.local_matrices(skeleton), np.float64)
        rng = np.random.default_rng(_SEED)
        axes = rng.normal(size=(_PROBES, len(local), 3))
        axes /= np.linalg.norm(axes, axis=2, keepdims=True)
        K = np.zeros((_PROBES, len(local), 3, 3))
        K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -axes[..., 2], axes[..., 1], -axes[..., 0]
        K -= np.swapaxes(K, -1, -2)
        turn = np.eye(3) + np.sin(_PROBE_ANGLE) * K + (1 - np.cos(_PROBE_ANGLE)) * K @ K  # Rodrigues
        posed = np.repeat(local[None], _PROBES, axis=0)
        posed[..., :3, :3] = local[..., :3, :3] @ turn
    world = np.asarray(deform.forward_kinematics_matrices(skeleton.parents, jnp.asarray(posed)), np.float64)
    return world[:, np.asarray(model.mesh.joints)]


def _probe_errors(
    node_motions: np.ndarray, Y: np.ndarray, J: np.ndarray, W: np.ndarray, embedding: SurfaceEmbedding, targets: list
) -> np.ndarray:
    """(s,) the largest distance over the probe poses between the embedded surface (its nodes ``Y`` skinned by
    linear blending of (J, W) with the joint matrices ``node_motions`` (k, j, 4, 4)) and ``targets`` (k of (s, 3):
    the surface skinned by its own weights)."""
    worst = np.zeros(len(embedding.element))
    for motion, target in zip(node_motions, targets):
        blend = np.einsum("nk,nkab->nab", W, motion[J][..., :3, :])  # (n, 3, 4)
        nodes = np.einsum("nab,nb->na", blend[..., :3], Y) + blend[..., 3]
        embedded = np.einsum("sk,skd->sd", embedding.weights, nodes[embedding.nodes])
        worst = np.maximum(worst, np.linalg.norm(embedded - target, axis=1))
    return worst


def bisect_tets(
    X: np.ndarray,
    T: np.ndarray,
    marked: np.ndarray,
    shrink: float | np.ndarray,
    shortest: float,
    most: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Refine tets by longest-edge bisection (Rivara's LEPP): each marked tet is split until its pieces' longest
    edges are at most ``shrink`` times its own (and no shorter than ``shortest``). Bisecting an edge splits every tet
    around it, so the mesh stays conforming, and only an edge that is the longest of all its tets is bisected
    (following the longest-edge propagation path), which keeps the tets' shapes from degrading.

    Args:
        X: (n, 3) nodes; T: (t, 4) positively oriented tets.
        marked: (m,) int distinct tets to refine, the most urgent last (they are refined first).
        shrink: (m,) or one factor in (0, 1): the fraction of its longest edge each marked tet is refined to.
        shortest: the edge length below which a tet is not refined.
        most: stop once there are this many tets (None: no limit).
    Returns:
        (X', T'): the nodes (X first, then the edges' midpoints) and the tets.
    """
    points = [np.asarray(p, np.float64) for p in X]
    tets = [list(t) for t in np.asarray(T, np.int64)]
    alive = [True] * len(tets)
    edges: dict[tuple[int, int], set[int]] = {}

    def tet_edges(t):
        c = tets[t]
        return [(min(c[i], c[j]), max(c[i], c[j])) for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))]

    tops: dict[int, tuple[float, int, int]] = {}  # each tet's longest edge (tets never change, they are replaced)

    def longest(t):
        if t not in tops:
            tops[t] = max(_edge_key_list(points, a, b) for a, b in tet_edges(t))
        return tops[t]

    for t in range(len(tets)):
        for e in tet_edges(t):
            edges.setdefault(e, set()).add(t)
    target: dict[int, float] = {}
    marked = np.asarray(marked, np.int64)
    factors = np.broadcast_to(np.asarray(shrink, np.float64), marked.shape)
    for t, factor in zip(marked.tolist(), factors.tolist()):
        length = np.sqrt(longest(t)[0])
        if length > shortest:
            target[t] = max(factor * length, shortest) ** 2
    queue = list(target)
    count = len(tets)
    while queue and (most is None or count < most):
        t = queue.pop()
        if not alive[t] or t not in target:
            continue
        key = longest(t)
        if key[0] <= target[t]:
            del target[t]
            continue
        while True:  # the longest-edge propagation path: to an edge that is the longest of all its tets
            longer = [longest(u) for u in edges[key[1:]]]
            top = max(longer)
            if top == key:
                break
            key = top
        a, b = key[1:]
        points.append(0.5 * (points[a] + points[b]))
        m = len(points) - 1
        for u in list(edges[(a, b)]):
            alive[u] = False
            for e in tet_edges(u):
                edges[e].discard(u)
            for old in (b, a):
                tets.append([m if c == old else c for c in tets[u]])
                alive.append(True)
                child = len(tets) - 1
                for e in tet_edges(child):
                    edges.setdefault(e, set()).add(child)
                if u in target:
                    target[child] = target[u]
                    queue.append(child)
            target.pop(u, None)
            count += 1
        del edges[(a, b)]
        if alive[t]:
            queue.append(t)
    keep = [c for c, live in zip(tets, alive) if live]
    return np.asarray(points), np.asarray(keep, np.int64)


def _edge_key_list(points: list, a: int, b: int) -> tuple[float, int, int]:
    d = points[a] - points[b]
    return float(d @ d), a, b


def _segments_distance(points: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(n, s) the distance of each point to each segment [a_s, b_s] (a point where a == b)."""
    ab = b - a
    length2 = np.maximum(np.sum(ab**2, axis=1), 1e-300)
    t = np.clip(np.einsum("nsd,sd->ns", points[:, None] - a[None], ab) / length2, 0, 1)
    closest = a[None] + t[..., None] * ab[None]
    return np.linalg.norm(points[:, None] - closest, axis=2)


def _bone_distances(model: deform.RiggedModel, points: np.ndarray) -> np.ndarray:
    """(n, j) the distance of each point to each skin joint's bone segments (rest pose, world)."""
    skeleton = model.skeleton
    local = deform.local_matrices(skeleton)
    world = np.asarray(deform.forward_kinematics_matrices(skeleton.parents, local))[:, :3, 3]
    children: dict[int, list[int]] = {}
    for bone, parent in enumerate(skeleton.parents):
        children.setdefault(parent, []).append(bone)
    distance = np.full((len(points), model.mesh.num_joints), np.inf)
    for j, bone in enumerate(model.mesh.joints):
        ends = [world[c] for c in children.get(bone, [])] or [world[bone]]
        a = np.repeat(world[bone][None], len(ends), axis=0)
        distance[:, j] = _segments_distance(points, a, np.stack(ends)).min(axis=1)
    return distance


def _hold_loose_parts(
    driven: np.ndarray, surface: np.ndarray, F: np.ndarray, embedded_in: np.ndarray, T: np.ndarray
) -> np.ndarray:
    """The driven nodes (sorted indices) of the core rule's mask ``driven``, with every node of the tets that hold a
    part of the surface (a connected set of its triangles) none of whose tets has a driven node: an accessory away
    from the bones (a rifle held out in a hand, a plate of a robot) would otherwise hang on flesh alone and swing
    off; it follows its bones as it was skinned. So does a connected set of the tets T with no driven node (a part
    meshed on its own that embeds no vertex), which would otherwise fall from the start."""
    count, label = connected_components(
        sp.coo_matrix((np.ones(F.size), (np.repeat(F[:, 0], 3), F.ravel())), shape=(len(surface),) * 2),
        directed=False,
    )
    held = driven.copy()
    used = np.zeros(len(surface), bool)
    used[F.ravel()] = True
    for part in range(count):
        nodes = np.unique(embedded_in[(label == part) & used])
        if nodes.size and not driven[nodes].any():
            held[nodes] = True
    pieces, piece = _components(T, len(held))
    holding = np.zeros(pieces, bool)
    holding[piece[held]] = True
    held |= ~holding[piece]
    return np.flatnonzero(held)


def _boundary_faces(T: np.ndarray) -> np.ndarray:
    """(f, 3) the faces of the tets T (t, 4) that lie in one tet only."""
    faces = T[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    _, first, counts = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    return faces[first[counts == 1]]


def _depths(parents: tuple[int, ...]) -> np.ndarray:
    depth = np.zeros(len(parents), np.int64)
    for bone, parent in enumerate(parents):
        depth[bone] = 0 if parent < 0 else depth[parent] + 1
    return depth


def _components(T: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """The connected components of n nodes joined by the tets T (t, 4): their count and each node's label."""
    rows = np.repeat(T[:, :1], 3, axis=1).ravel()
    return connected_components(sp.coo_matrix((np.ones(len(rows)), (rows, T[:, 1:].ravel())), shape=(n, n)), False)


def _surface_parts(V: np.ndarray, F: np.ndarray) -> tuple[int, np.ndarray, np.ndarray]:
    """The parts of a surface, the connected sets of its triangles: their count, each vertex's part (s,) (a vertex
    on no triangle takes the part of its nearest triangle) and each triangle's part (f,)."""
    adjacency = sp.coo_matrix((np.ones(F.size), (np.repeat(F[:, 0], 3), F.ravel())), shape=(len(V),) * 2)
    label = connected_components(adjacency, directed=False)[1]
    parts, face_part = np.unique(label[F[:, 0]], return_inverse=True)
    vertex_part = np.full(len(V), -1, np.int64)
    vertex_part[F] = face_part.reshape(-1, 1)
    loose = np.flatnonzero(vertex_part < 0)
    if len(loose):
        face = np.asarray(igl.point_mesh_squared_distance(V[loose], V, F)[1], np.int64)
        vertex_part[loose] = face_part[face]
    return len(parts), vertex_part, face_part.astype(np.int64)


def _meshing_groups(V: np.ndarray, F: np.ndarray, face_part: np.ndarray, count: int, margin: float) -> list:
    """The parts in groups that one fTetWild call can mesh without joining them: greedily, largest first, a part
    joins the first group none of whose parts' bounding boxes comes within ``margin`` of its own (touching, nested
    and overlapping parts go to different calls)."""
    corners = V[F].reshape(-1, 3)
    part = np.repeat(face_part, 3)
    low, high = np.full((count, 3), np.inf), np.full((count, 3), -np.inf)
    np.minimum.at(low, part, corners)
    np.maximum.at(high, part, corners)
    near = np.all(low[:, None] - margin <= high[None], axis=2) & np.all(low[None] - margin <= high[:, None], axis=2)
    groups: list[list[int]] = []
    for p in np.argsort(-np.bincount(face_part, minlength=count), kind="stable").tolist():
        group = next((g for g in groups if not near[p, g].any()), None)
        if group is None:
            groups.append([p])
        else:
            group.append(p)
    return [np.asarray(g, np.int64) for g in groups]


def _part_tets(V, F, face_part, count, diagonal, edge_length, epsilon, threads) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild's tets of each part of the surface on its own (module docstring), parts far apart meshed in one
    call, as one mesh of disjoint node sets: (X (n, 3), T (t, 4))."""
    nodes, tets, offset = [], [], 0
    for group in _meshing_groups(V, F, face_part, count, _APART * epsilon * diagonal):
        used, local = np.unique(F[np.isin(face_part, group)], return_inverse=True)
        size = bounding_diagonal(V[used])
        # the lengths are the whole surface's: fTetWild takes them relative to the group's diagonal
        TV, TT = ftetwild(
            V[used], local.reshape(-1, 3), edge_length * diagonal / size, epsilon * diagonal / size, threads=threads
        )
        if len(TT) == 0:  # open sheets: no volume, their vertices take the nearest tets (_embed_parts)
            continue
        kept, TT = np.unique(TT, return_inverse=True)
        nodes.append(TV[kept])
        tets.append(TT.reshape(-1, 4) + offset)
        offset += len(kept)
    if not tets:
        raise ValueError("model: its surface encloses no volume (fTetWild kept no tet of any of its parts)")
    return np.concatenate(nodes), np.concatenate(tets)


def _tet_parts(
    X: np.ndarray, T: np.ndarray, surface: np.ndarray, F: np.ndarray, face_part: np.ndarray, count: int
) -> np.ndarray:
    """(t,) the surface part each tet belongs to: a connected set of tets belongs to the part most of its boundary
    nodes lie nearest to (fTetWild's tets of a part end within the envelope of that part's surface)."""
    components, label = _components(T, len(X))
    boundary = np.unique(_boundary_faces(T))
    face = np.asarray(igl.point_mesh_squared_distance(X[boundary], surface, F)[1], np.int64)
    votes = sp.coo_matrix((np.ones(len(boundary)), (label[boundary], face_part[face])), shape=(components, count))
    return np.asarray(votes.toarray().argmax(axis=1), np.int64)[label[T[:, 0]]]


def _bisect_parts(Y, T, tet_part, marked, shortest: float, most: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``bisect_tets`` of tets of parts ``tet_part`` (at ``_SHRINK``), with the parts of the refined tets: a bisection
    keeps T's nodes and splits edges inside one connected set of tets, so each connected set of the refined tets holds
    nodes of T, of one part. Returns (Y', T', tet_part')."""
    refined_Y, refined_T = bisect_tets(Y, T, marked, _SHRINK, shortest, most)
    node_part = np.full(len(refined_Y), -1, np.int64)
    node_part[T] = tet_part[:, None]
    components, label = _components(refined_T, len(refined_Y))
    part = np.full(components, -1, np.int64)
    np.maximum.at(part, label, node_part)
    return refined_Y, refined_T, part[label[refined_T[:, 0]]]


def _cap_outside(
    Y, T, tet_part, points, vertex_part, vertices, pinned: dict[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, int]]:
    """Tets of their own for surface vertices that lie outside their part's tets (fTetWild's envelope cut a thin
    feature off): each of ``vertices`` (worst first) becomes a node, the apex of a new tet on the boundary face of
    its part nearest to it, so that it is embedded at that node, whose weights are fitted to its own, instead of in
    a tet whose linear map it extrapolates (its coordinates outside [0, 1] amplify the fit's errors). A face takes
    one apex a round, and a tet that would hold another node or lie on the inner side of its face is not made.
    ``pinned`` (vertex -> node) grows by the vertices given a tet. Returns (Y, T, tet_part, pinned)."""
    faces, inverse, counts = tet_face_matching(T)
    flat = faces.reshape(-1, 3)
    boundary = np.flatnonzero(counts[inverse] == 1)
    owner = boundary // 4
    nodes, tets, parts, used = [], [], [], set()
    pinned = dict(pinned)
    for part in np.unique(vertex_part[vertices]):
        mine = vertices[vertex_part[vertices] == part]
        candidates = boundary[tet_part[owner] == part]
        if not len(candidates):
            continue
        nearest = candidates[np.asarray(igl.point_mesh_squared_distance(points[mine], Y, flat[candidates])[1])]
        for v, f in zip(mine.tolist(), nearest.tolist()):
            if f in used:
                continue
            a, b, c = flat[f]
            opposite = T[f // 4, f % 4]  # the face's own tet's fourth node: the apex must lie across the face
            normal = np.cross(Y[b] - Y[a], Y[c] - Y[a])
            height = np.dot(normal, points[v] - Y[a])
            if height * np.dot(normal, Y[opposite] - Y[a]) >= 0:
                continue
            # a flat tet (the vertex on its face's plane, or at a corner) would make the mass matrix singular
            if abs(height) <= _FLAT * np.linalg.norm(normal) * np.linalg.norm([Y[b] - Y[a], Y[c] - Y[a]], axis=1).max():
                continue
            corners = np.stack([Y[a], Y[b], Y[c], points[v]])
            edges = (corners[1:] - corners[0]).T
            near = np.flatnonzero(np.all((Y >= corners.min(0)) & (Y <= corners.max(0)), axis=1))
            near = near[~np.isin(near, (a, b, c))]
            if len(near):
                lam = np.linalg.solve(edges, (Y[near] - corners[0]).T).T
                if np.any((lam >= 0).all(axis=1) & (lam.sum(axis=1) <= 1)):
                    continue
            used.add(f)
            index = len(Y) + len(nodes)
            nodes.append(points[v])
            pinned[v] = index
            # positively oriented, as every tet of the mesh
            tets.append((a, b, c, index) if np.linalg.det(edges) > 0 else (b, a, c, index))
            parts.append(tet_part[f // 4])
    if not tets:
        return Y, T, tet_part, pinned
    Y = np.concatenate([Y, np.asarray(nodes)])
    T = np.concatenate([T, np.asarray(tets, T.dtype)])
    return Y, T, np.concatenate([tet_part, np.asarray(parts, tet_part.dtype)]), pinned


def _pin_vertices(
    Y, T, tet_part, points, vertex_part, vertices, pinned: dict[int, int], keep: float = _KEEP
) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[int, int], np.ndarray]:
    """Nodes at surface vertices that refinement does not bring within the tolerance (module docstring): each of
    ``vertices`` (worst first) is placed by re-coning the star of a simplex of its tet (the k corners of its largest
    barycentric coordinates, k = 1..4; each tet around the simplex has one of its corners replaced by the vertex in
    turn, so the mesh stays conforming), the k whose thinnest new tet is thickest (``_star_shape``), where every new tet
    keeps a volume ratio of ``keep`` or its parent's: among the simplices whose re-coning keeps the region the tets
    fill, else among boundary simplices the vertex lies near (its other coordinates sum to at most ``_NEAR``). A vertex
    whose star meets a tet already re-coned this round, or whose nearest node (k = 1) is pinned already, waits.
    ``pinned`` (vertex -> node) grows by the vertices placed. Returns (Y, T, tet_part, pinned, stuck), ``stuck`` the
    vertices no star of which keeps the bound (not those that waited)."""
    embedding = _embed_parts(Y, T, tet_part, points[vertices], vertex_part[vertices])
    node_tets = sp.csr_matrix(
        (np.ones(T.size, bool), (T.ravel(), np.repeat(np.arange(len(T)), 4))), shape=(len(Y), len(T))
    ).tolil()
    Y, pinned = Y.copy(), dict(pinned)
    taken = set(pinned.values())
    on_boundary = np.zeros(len(Y), bool)
    on_boundary[_boundary_faces(T).ravel()] = True
    touched: set[int] = set()
    new_tets, new_parts, new_nodes, stuck = [], [], [], []
    for v, t, b in zip(vertices.tolist(), embedding.element, embedding.weights):
        # the simplex: the corners of the largest coordinates, as many as make the thickest star (1: the node moves).
        # Re-coning about a simplex inside the mesh, or with the vertex on it, keeps the region the tets fill; about
        # a boundary simplex with the vertex off it, it moves the boundary towards the vertex (on the surface): only
        # where no region-keeping star is thick enough, and the vertex near (its other coordinates sum to _NEAR)
        best: dict[bool, tuple] = {}
        waits = False
        order = np.argsort(-b, kind="stable")
        for k in range(1, 5):
            simplex = T[t][order[:k]]
            off = float(b[order[k:]].sum())
            keeps = not on_boundary[simplex].all() or off <= _ON
            if (not keeps and off > _NEAR) or (k == 1 and int(simplex[0]) in taken):
                continue
            star = set(node_tets.rows[simplex[0]]).intersection(*(node_tets.rows[c] for c in simplex[1:]))
            if star & touched:
                waits = True
                continue
            star_list = sorted(star)
            shape = _star_shape(Y, T[star_list], points[v], simplex, keep)
            if shape >= 1 and (keeps not in best or shape > best[keeps][0]):
                best[keeps] = (shape, simplex, star, star_list)
        if not best:
            if not waits:
                stuck.append(v)
            continue
        _, simplex, star, star_list = best.get(True) or best[False]
        touched |= star
        if len(simplex) == 1:  # the node itself moves to the vertex
            node = int(simplex[0])
            Y[node] = points[v]
        else:
            node = len(Y) + len(new_nodes)
            new_nodes.append(points[v])
        pinned[v] = node
        taken.add(node)
        for u in star_list:
            for c in simplex:
                new_tets.append(np.where(T[u] == c, node, T[u]))
                new_parts.append(tet_part[u])
    stuck = np.asarray(stuck, np.int64)
    if not touched:
        return Y, T, tet_part, pinned, stuck
    alive = np.ones(len(T), bool)
    alive[sorted(touched)] = False
    Y = np.concatenate([Y, np.asarray(new_nodes).reshape(-1, 3)])
    T = np.concatenate([T[alive], np.asarray(new_tets, T.dtype).reshape(-1, 4)])
    return Y, T, np.concatenate([tet_part[alive], np.asarray(new_parts, tet_part.dtype)]), pinned, stuck


def _star_shape(Y: np.ndarray, star: np.ndarray, point: np.ndarray, simplex: np.ndarray, keep: float) -> float:
    """How much worse than ``keep`` re-coning the tets ``star`` (k, 4) about ``simplex`` at ``point`` leaves them: the
    smallest over the new tets of their volume ratio (``volume_ratios``) over the smaller of ``keep`` and their
    parent's ratio (>= 1: none is thinner than the bound, or than its parent)."""
    x = Y[star]
    parent = volume_ratios(x)
    worst = np.inf
    for c in simplex:
        k, corner = np.nonzero(star == c)
        y = x[k].copy()
        y[np.arange(len(k)), corner] = point
        worst = min(worst, float(np.min(volume_ratios(y) / np.minimum(keep, parent[k]))))
    return worst


def _embed_parts(X, T, tet_part, points, vertex_part) -> SurfaceEmbedding:
    """The surface's vertices embedded each in the tets of its own part (``embed_points`` restricted to them), so
    that no tet holds two parts; the vertices of a part without tets (an open sheet) in the nearest tets."""
    element = np.zeros(len(points), np.int64)
    weights = np.zeros((len(points), 4))
    distance = np.zeros(len(points))
    owned = np.zeros(int(max(vertex_part.max(), tet_part.max())) + 1, bool)
    owned[tet_part] = True
    order = np.argsort(tet_part, kind="stable")
    bounds = np.searchsorted(tet_part[order], np.arange(len(owned) + 1))
    rows_of = np.argsort(vertex_part, kind="stable")
    row_bounds = np.searchsorted(vertex_part[rows_of], np.arange(len(owned) + 1))
    for p in np.flatnonzero(owned):
        rows = rows_of[row_bounds[p] : row_bounds[p + 1]]
        if len(rows):
            mine = order[bounds[p] : bounds[p + 1]]
            e, weights[rows], distance[rows] = embed(X, T[mine], points[rows])
            element[rows] = mine[e]
    rows = np.flatnonzero(~owned[vertex_part])
    if len(rows):
        element[rows], weights[rows], distance[rows] = embed(X, T, points[rows])
    return SurfaceEmbedding(element, T[element], weights, distance)


def _build(
    model, dense, V, F, G, diagonal, edge_length, epsilon, threads, tets, influences, tolerance, refine, per_part
):
    """The tets of the rest configuration (fTetWild's or ``tets``), refined, with their weights (module docstring):
    (Y (n, 3) nodes, T (t, 4) tets, J and W (n, influences) weights, the surface's embedding).

    Args:
        model: the model (weights normalized); dense: (s, j) its weights; V: (s, 3) its mesh-space vertices; F: its
            triangles; G: (j, 4, 4) its joints' rest matrices; diagonal: the rest surface's; the others as
            ``character_body``'s.
    """
    Vh = np.concatenate([V, np.ones((len(V), 1))], axis=1)
    images = np.einsum("jab,sb->sja", G[:, :3], Vh)  # (s, j, 3) each joint's rest image of each vertex
    placed = np.einsum("sj,sja->sa", dense, images)
    moments = dense[..., None] * (images - placed[:, None])
    # the joints' rest images of a vertex differ where the bind pose is not the rest pose (module docstring)
    bind = bool(np.abs(moments).max() > _BIND_SPREAD * diagonal)
    zero = np.zeros_like(moments)
    count, vertex_part, face_part = _surface_parts(placed, F)
    if tets is not None:
        mesh = tets
    elif per_part and count > 1:
        mesh = tet_mesh(*_part_tets(placed, F, face_part, count, diagonal, edge_length, epsilon, threads))
    else:
        mesh = tetrahedralize_surface(placed, F, edge_length=edge_length, epsilon=epsilon, threads=threads).mesh
    Y, T = np.asarray(mesh.X, np.float64), np.asarray(mesh.T, np.int64)
    tet_part = _tet_parts(Y, T, placed, F, face_part, count)
    # the probe poses (also for tets given as they are: the fit's smoothness is chosen by them, below): the nodes'
    # joint matrices, and the surface skinned directly
    inverse_bind = np.asarray(model.mesh.inverse_bind, np.float64)
    poses = _probe_poses(model)
    node_motions = poses @ inverse_bind[None]
    k = len(G)
    targets = [
        np.einsum("sab,sb->sa", (dense @ (pose @ inverse_bind)[:, :3].reshape(k, 12)).reshape(-1, 3, 4), Vh)
        for pose in poses
    ]
    lengths = np.linalg.norm(Y[T[:, [0, 0, 0, 1, 1, 2]]] - Y[T[:, [1, 2, 3, 2, 3, 3]]], axis=2).max(axis=1)
    shortest = _FINEST * float(np.median(lengths))
    budget = _GROWTH * len(T)
    previous = np.full(len(V), np.inf)  # each vertex's error when its tet was last refined
    pinned: dict[int, int] = {}  # surface vertex -> the node at it, whose weights are the vertex's own
    pinning = 0  # the rounds that pinned vertices, once refining has ended
    kept = None  # tets given as they are: the fit before the last pins
    for round_ in range(_ROUNDS + _PIN_ROUNDS + 1):
        embedding = _embed_parts(Y, T, tet_part, placed, vertex_part)
        if round_ == 0 and tets is not None:
            far = embedding.distance > 3 * float(np.median(lengths))
            if far.mean() > 0.1:
                raise ValueError(
                    f"tets: {far.mean():.0%} of the surface's vertices lie more than 3 edge lengths from the tets; "
                    "expected tets of the surface in the rest configuration (the skeleton's rest pose, world "
                    "coordinates, as CharacterBody.tets)"
                )

        pinned_vertices = np.fromiter(pinned, np.int64, len(pinned))
        pinned_nodes = np.fromiter(pinned.values(), np.int64, len(pinned))
        own = _trim(dense[pinned_vertices], influences)

        def fitted_weights(fitted):  # clamped, trimmed, and a pinned node's weights its vertex's own
            J, W = _trim(np.clip(fitted, 0.0, 1.0), influences)
            J[pinned_nodes], W[pinned_nodes] = own
            return J, W

        fixed = (pinned_nodes, dense[pinned_vertices])

        def fit(smoothness):
            fitted = fit_weights(Y, T, embedding, placed, dense, moments, _LENGTH * diagonal, smoothness, fixed)
            J, W = fitted_weights(fitted)
            bound = _bind_positions(Y, G, J, W)
            for _ in range(_BIND_FITS if bind else 0):  # the moments in mesh space are zero (module docstring)
                fitted = fit_weights(bound, T, embedding, V, dense, zero, _LENGTH * diagonal, smoothness, fixed)
                J, W = fitted_weights(fitted)
                bound = _bind_positions(Y, G, J, W)
            return J, W, bound

        J, W, bound = fit(_SMOOTHNESS)
        error = _probe_errors(node_motions, bound, J, W, embedding, targets)
        if error.max() > tolerance * diagonal:
            # coarse tets (a low-poly model's, or before the refinement has reached a joint) may follow the weights
            # closer with less smoothing: a weaker fit is kept only where the probe poses show it closer
            for smoothness in _SMOOTHNESS * np.asarray(_WEAKER):
                J_s, W_s, bound_s = fit(smoothness)
                error_s = _probe_errors(node_motions, bound_s, J_s, W_s, embedding, targets)
                if error_s.max() < error.max():
                    J, W, bound, error = J_s, W_s, bound_s, error_s
        if not refine:
            # tets given as they are: a vertex above the tolerance that lies at a node (a saved body's pinned ones)
            # is pinned there, which changes no tet, where that brings the probe poses' largest error down
            if kept is not None and error.max() >= kept[3].max():
                J, W, bound, error = kept
                break
            kept = (J, W, bound, error)
            at = (error > tolerance * diagonal) & (embedding.weights.max(axis=1) >= 1 - _ON) & (embedding.distance == 0)
            at[pinned_vertices] = False
            at = np.flatnonzero(at)
            nodes = embedding.nodes[at, np.argmax(embedding.weights[at], axis=1)]
            free = ~np.isin(nodes, pinned_nodes)
            at, nodes = at[free], nodes[free]
            first = np.unique(nodes, return_index=True)[1]  # one vertex a node
            if not len(first) or round_ >= _PIN_ROUNDS:
                break
            pinned.update(zip(at[first].tolist(), nodes[first].tolist()))
            continue
        off = error > _MARGIN * tolerance * diagonal
        x = Y[embedding.nodes]
        size = np.linalg.norm(x[:, [0, 0, 0, 1, 1, 2]] - x[:, [1, 2, 3, 2, 3, 3]], axis=2).max(axis=1)
        if not pinning:
            bad = off.copy()
            # a vertex whose error hardly fell when its tet was refined sits where surfaces of different bones meet:
            # refining on would spend the budget there for nothing (it is pinned once refining ends)
            stuck = bad & (error > _STUCK * previous)
            previous = np.where(bad & ~stuck, error, np.inf)
            bad &= ~stuck
            # a vertex outside the tets (where fTetWild's filter cut a thin feature) follows its tet's linear map
            # extrapolated: refining that tet amplifies the fit's errors by the distance over the tet's size, so it
            # gets a tet of its own instead (_cap_outside)
            outside = bad & (embedding.distance > _OUTSIDE * size)
            bad &= ~outside
            outside &= embedding.distance <= _CAP_REACH * size  # farther, a tet of its own would be a spike
            if (bad.any() or outside.any()) and round_ < _ROUNDS and len(T) < budget:
                count = len(pinned)
                if outside.any():
                    worst_first = np.flatnonzero(outside)[np.argsort(-error[outside], kind="stable")]
                    Y, T, tet_part, pinned = _cap_outside(Y, T, tet_part, placed, vertex_part, worst_first, pinned)
                if bad.any():
                    # the worst vertices' tets last: the bisection takes them first, so a spent budget went where it
                    # did most
                    order: dict[int, None] = {}
                    for t in embedding.element[bad][np.argsort(error[bad], kind="stable")].tolist():
                        order.pop(t, None)
                        order[t] = None
                    marked = np.fromiter(order, np.int64, len(order))
                    Y, T, tet_part = _bisect_parts(Y, T, tet_part, marked, shortest, budget)
                    continue
                if len(pinned) > count:
                    continue
            pinning = 1  # refining has ended: the vertices still off (the stuck ones among them) become nodes
        # those above the tolerance itself (refining aims below it, by _MARGIN); farther outside than _CAP_REACH
        # edges, a node at the vertex would make a spike
        left = np.flatnonzero((error > tolerance * diagonal) & (embedding.distance <= _CAP_REACH * size))
        left = left[~np.isin(left, pinned_vertices)]
        if not len(left) or pinning > _PIN_ROUNDS:
            break
        count = len(pinned)
        worst_first = left[np.argsort(-error[left], kind="stable")]
        # a tet of its own for a vertex well outside (_cap_outside); nearer, a cap would be a sliver
        outside_first = worst_first[embedding.distance[worst_first] > _OUTSIDE * size[worst_first]]
        Y, T, tet_part, pinned = _cap_outside(Y, T, tet_part, placed, vertex_part, outside_first, pinned)
        worst_first = worst_first[~np.isin(worst_first, np.fromiter(pinned, np.int64, len(pinned)))]
        # the vertices no star of which keeps the bound try half of it (a dense surface's vertices crowd the tets),
        # and the tets of those that still find none are bisected, beyond the budget by a few tets a vertex, so that
        # the next round tries them among more, smaller simplices; the vertices that waited for a star re-coned this
        # round try again in the next
        Y, T, tet_part, pinned, stuck = _pin_vertices(Y, T, tet_part, placed, vertex_part, worst_first, pinned)
        if len(stuck):
            Y, T, tet_part, pinned, stuck = _pin_vertices(Y, T, tet_part, placed, vertex_part, stuck, pinned, _KEEP / 2)
        before = len(T)
        if len(stuck):
            marked = np.unique(_embed_parts(Y, T, tet_part, placed[stuck], vertex_part[stuck]).element)
            Y, T, tet_part = _bisect_parts(Y, T, tet_part, marked, shortest, len(T) + _PIN_SPLIT * len(marked))
        if len(pinned) == count and len(T) == before:
            break
        pinning += 1
    if error.max() > tolerance * diagonal:
        warnings.warn(
            f"tolerance: the embedded surface misses the directly skinned one by up to {error.max() / diagonal:.2g} "
            f"of the diagonal at the probe poses ({int((error > tolerance * diagonal).sum())} of {len(error)} "
            f"vertices above {tolerance:g}; {len(T)} tets, "
            + (f"at most {_GROWTH} times fTetWild's" if refine else "given, not refined (refine=True refines them)")
            + "): surfaces of different bones meet there inside one part of the surface (or across parts, "
            "per_part=False), and the tets that hold both blend them",
            stacklevel=3,
        )
    return Y, T, J, W, embedding, bound


def character_body(
    model: deform.RiggedModel,
    *,
    density: float = 1000.0,
    gravity: Float[npt.ArrayLike, " 3"] = (0.0, -9.81, 0.0),
    edge_length: float = EDGE_LENGTH,
    epsilon: float = EPSILON,
    core: float = CORE,
    driven: Int[npt.ArrayLike, " nd"] | str | None = None,
    influences: int = INFLUENCES,
    tets: TetMesh | None = None,
    threads: int | None = None,
    tolerance: float = LIMIT,
    refine: bool | None = None,
    per_part: bool = True,
) -> CharacterBody:
    """A tet body of a rigged model: fTetWild's tets of its surface, the surface's skinning weights carried to the
    tet nodes, the nodes the skeleton drives and the surface embedded in the tets (module docstring: the rules).

    Args:
        model: the ``deform.RiggedModel``.
        density: the mass density, per unit volume of the rest configuration (1000: water, in kg/m^3 for a model in
            metres).
        gravity: (3,) the gravitational acceleration in world coordinates (glTF is y-up, in metres).
        edge_length: the tets' target edge length and envelope, fractions of the surface's bounding-box
            diagonal (``tetrahedralize_surface``).
        epsilon: see ``edge_length``.
        core: the core radius of each bone, a fraction in (0, 1] of the limb's radius about it.
        driven: None (the core rule), ``"all"`` (every node: the body is skinned, nothing is simulated), or the
            (nd,) int indices of the driven nodes.
        influences: the joints each node keeps (>= 1).
        tets: None (tetrahedralize), or a ``TetMesh`` of the surface in the rest configuration (e.g. a saved
            ``CharacterBody.tets``, as fTetWild is not deterministic).
        threads: fTetWild's threads; None: every core.
        tolerance: the surface limit the tets are refined to and the weights fitted to, a fraction in (0, 1) of
            the diagonal (module docstring); a body that misses it warns.
        refine: whether to refine the tets to ``tolerance``; None: fTetWild's yes, ``tets`` given no (a saved
            body's are refined already).
        per_part: True: each part of the surface (a connected set of its triangles) gets tets of its own, which
            share no node with another part's (module docstring); False: one fTetWild mesh of the whole surface,
            whose tets may hold several parts.
    Returns:
        The ``CharacterBody``.
    """
    if not isinstance(model, deform.RiggedModel):
        raise ValueError(f"model: expected a deform.RiggedModel (deform.load_model), got {type(model).__name__}")
    if model.mesh.num_joints == 0 or model.mesh.num_vertices == 0:
        raise ValueError("model: its mesh has no skin joints or no vertices; a body needs a skinned mesh")
    density = float(check_real("density", density, (), "a positive density"))
    if not density > 0:
        raise ValueError(f"density: expected a positive density, got {density}")
    gravity = np.asarray(check_real("gravity", gravity, (3,), "a finite acceleration"), np.float64)
    if isinstance(core, bool) or not (isinstance(core, (int, float, np.integer, np.floating)) and 0 < core <= 1):
        raise ValueError(f"core: expected a fraction in (0, 1], got {core!r}")
    if isinstance(influences, bool) or not isinstance(influences, (int, np.integer)) or influences < 1:
        raise ValueError(f"influences: expected an int >= 1, got {influences!r}")
    if isinstance(tolerance, bool) or not isinstance(tolerance, (int, float, np.floating)) or not 0 < tolerance < 1:
        raise ValueError(f"tolerance: expected a fraction of the diagonal in (0, 1), got {tolerance!r}")
    for name, value, high in (("edge_length", edge_length, 1.0), ("epsilon", epsilon, 0.1)):
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not 0 < value <= high:
            raise ValueError(f"{name}: expected a fraction of the bounding box diagonal in (0, {high}], got {value!r}")
    if not isinstance(per_part, bool):
        raise ValueError(f"per_part: expected True or False, got {per_part!r}")
    if refine is not None and not isinstance(refine, bool):
        raise ValueError(f"refine: expected None, True or False, got {refine!r}")
    if refine is None:
        refine = tets is None
    if tets is not None and not isinstance(tets, TetMesh):
        raise ValueError(f"tets: expected None or a TetMesh, got {type(tets).__name__}")
    if isinstance(driven, str) and driven != "all":
        raise ValueError(f"driven: expected None, 'all' or node indices, got {driven!r}")
    mesh = model.mesh.with_normalized_weights()
    model = deform.RiggedModel(mesh, model.skeleton, model.clips, model.name)
    F = np.asarray(mesh.F, np.int64)
    surface = np.asarray(deform.rest_pose(model, "lbs"), np.float64)
    diagonal = bounding_diagonal(surface)
    start = time.perf_counter()
    _, G = _rest_joint_matrices(model)
    dense = _dense_weights(mesh)
    V = np.asarray(mesh.V, np.float64)
    Y, T, J, W, embedding, bound = _build(
        model,
        dense,
        V,
        F,
        G,
        diagonal,
        edge_length,
        epsilon,
        threads,
        tets,
        int(influences),
        tolerance,
        refine,
        per_part,
    )
    X = Y
    rest = tet_mesh(X, T)
    seconds = time.perf_counter() - start
    # the nodes' mesh space is the model's: its inverse binds, the nodes where its rest pose takes them to the tets'
    node_mesh = deform.SkinnedMesh(
        jnp.asarray(bound), jnp.zeros((0, 3), jnp.int32), jnp.asarray(J), jnp.asarray(W), mesh.inverse_bind, mesh.joints
    )
    node_model = deform.RiggedModel(node_mesh, model.skeleton, model.clips, model.name)
    distance = _bone_distances(model, X)
    owner = np.argmax(dense, axis=1)
    surface_distance = _bone_distances(model, surface)
    radius = np.full(mesh.num_joints, np.nan)
    for j in range(mesh.num_joints):
        mine = owner == j
        if mine.sum() >= _MIN_VERTICES:
            radius[j] = np.median(surface_distance[mine, j])
    has_core = np.isfinite(radius) & (radius > 0)
    # a node on the tets' boundary (the skin) is never driven, even where a bone runs there (a tail, an ear)
    reach = np.where(has_core, radius, 0.0)[None]
    interior = np.ones(len(X), bool)
    interior[_boundary_faces(T).ravel()] = False
    inside = has_core[None] & (distance <= core * reach) & interior[:, None]
    # a bone whose core holds no node (a thin limb on coarse tets) drives its nearest interior nodes within its radius
    for j in np.flatnonzero(has_core & ~inside.any(axis=0)):
        near = np.where(interior, distance[:, j], np.inf)
        if near.min() <= radius[j]:
            inside[:, j] = near <= min(radius[j], 2 * near.min())
    if isinstance(driven, str):
        driven_nodes = np.arange(len(X))
    elif driven is None:
        driven_nodes = _hold_loose_parts(np.asarray(inside.any(axis=1)), surface, F, embedding.nodes, T)
    else:
        driven_nodes = np.asarray(driven)
        if (
            driven_nodes.ndim != 1
            or not np.issubdtype(driven_nodes.dtype, np.integer)
            or (driven_nodes.size and (driven_nodes.min() < 0 or driven_nodes.max() >= len(X)))
            or len(np.unique(driven_nodes)) != len(driven_nodes)
        ):
            raise ValueError(f"driven: expected distinct int node indices in [0, {len(X)})")
        if driven_nodes.size == 0:
            raise ValueError("driven: expected at least one node (a body with none has nothing to hold it)")
        driven_nodes = np.sort(driven_nodes)
    if len(driven_nodes) == 0:
        raise ValueError(f"core: no node lies in a bone's core at core={core}; raise it or pass driven")
    # anchors: the driven nodes of the bones nearest the root (among the bones whose cores hold driven nodes)
    depth = _depths(model.skeleton.parents)[np.asarray(mesh.joints)]
    nearest = np.argmin(np.where(has_core[None], distance / np.where(has_core, radius, 1)[None], np.inf), axis=1)
    node_depth = depth[nearest[driven_nodes]]
    # in each connected set of tets (the parts meshed on their own are several from the start): each must follow
    # the rig until a cut severs it
    pieces, piece = _components(T, len(X))
    shallowest = np.full(pieces, np.iinfo(np.int64).max)
    np.minimum.at(shallowest, piece[driven_nodes], node_depth)
    anchors = driven_nodes[node_depth == shallowest[piece[driven_nodes]]]
    return CharacterBody(
        model=model,
        node_model=node_model,
        tets=rest,
        nodes=Y,
        driven=driven_nodes.astype(np.int64),
        anchors=np.sort(anchors).astype(np.int64),
        surface=surface,
        faces=F,
        embedding=embedding,
        density=density,
        gravity=gravity,
        diagonal=diagonal,
        quality=tet_quality(rest),
        seconds=seconds,
    )
