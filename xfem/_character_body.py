"""A simulated body from a rigged model: its tets, skinning weights on the tet nodes, the nodes the skeleton drives,
and the model's own surface embedded in the tets (``character_body``; ``xfem._character`` plays clips on it).

Spaces. The tets are made (fTetWild, ``tetrahedralize_surface``) from the model's surface in its mesh space, where
skinning starts (``SkinnedMesh.V``); ``CharacterBody.nodes`` keeps them there, and ``node_model`` is the model with
the tet nodes as its mesh, so ``deform.skin_model(body.node_model, t, method)`` skins the nodes by any method. The
body's rest configuration (``tets.X``: masses, volumes and the planes of cuts) is the nodes at the skeleton's rest
pose in world coordinates (``deform.rest_pose``, linear blend), where the model stands as a viewer shows it.

Weights (the transfer rule). A node takes the skinning weights of the closest point of the surface: the barycentric
blend of the weights of that point's triangle corners, trimmed to the ``influences`` largest and normalized. Inside
a limb the closest surface point is on that limb, so the node follows the limb's bones.

Driven nodes (the core rule). Bone j's core is the set of points within ``core * r_j`` of its segments (from the
joint to each child joint; a leaf joint is a point), where ``r_j`` is the median distance from those segments of
the surface vertices whose largest weight is j's: the limb's radius there. A node is driven when it lies in some
bone's core. Bones whose vertices are fewer than 4 have no core.

Anchors. A cut that severs a limb severs its bones too: the pieces that keep the skeleton's root are driven on, the
others fall. The anchors are the driven nodes of the bones closest to the skeleton's root (the fewest parents up)
among the bones with a core; ``simulate_character`` releases the driven nodes of every piece without an anchor.
"""

from __future__ import annotations

from typing import NamedTuple

import igl
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
from jaxtyping import Float, Int

import deform
from _jaxcga_shared.checks import check_real
from _jaxcga_shared.mesh import bounding_diagonal
from xfem._surface_tets import EDGE_LENGTH, EPSILON, SurfaceEmbedding, TetQuality, embed_points, tet_quality
from xfem._surface_tets import tetrahedralize_surface
from xfem._tetmesh import TetMesh, tet_mesh

CORE = 0.5  # the default core radius, as a fraction of the limb's radius about the bone
INFLUENCES = 4  # joints per node, as glTF's JOINTS_0/WEIGHTS_0
_MIN_VERTICES = 4  # a bone with fewer surface vertices (by largest weight) has no core


class CharacterBody(NamedTuple):
    """A rigged model made into a tet body (``character_body``).

    Attributes:
        model: the ``deform.RiggedModel`` it was made from (weights normalized).
        node_model: the same skeleton and clips with the tet nodes as its mesh (mesh space, transferred weights):
            ``deform.skin_model(node_model, t, method)`` skins the nodes.
        tets: the ``TetMesh`` in the rest configuration (world coordinates, the skeleton's rest pose).
        nodes: (n, 3) float64 the tet nodes in the model's mesh space (``node_model.mesh.V``).
        driven: (nd,) int64 sorted indices of the nodes the skeleton drives.
        anchors: (na,) int64 the driven nodes whose pieces stay driven after a cut (module docstring).
        surface: (s, 3) float64 the model's surface in the rest configuration.
        faces: (f, 3) int64 its triangles.
        embedding: the ``SurfaceEmbedding`` of ``surface`` in ``tets``.
        density: the mass density (per unit volume of the rest configuration).
        gravity: (3,) float64 the gravitational acceleration, world coordinates.
        diagonal: the bounding-box diagonal of ``surface``.
        quality: the ``TetQuality`` of ``tets``.
        seconds: the wall time of the tetrahedralization (0 for tets given).
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
    corners = V[F[face]]
    bary = igl.barycentric_coordinates(
        np.ascontiguousarray(closest), *(np.ascontiguousarray(corners[:, k]) for k in range(3))
    )
    bary = np.clip(bary, 0, None)
    bary /= bary.sum(axis=1, keepdims=True)
    weights = np.asarray(weights, np.float64)
    return np.einsum("nk,nkj->nj", bary, weights[F[face]])


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


def _depths(parents: tuple[int, ...]) -> np.ndarray:
    depth = np.zeros(len(parents), np.int64)
    for bone, parent in enumerate(parents):
        depth[bone] = 0 if parent < 0 else depth[parent] + 1
    return depth


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
        tets: None (tetrahedralize), or a ``TetMesh`` of the surface in the model's mesh space (e.g. a saved one,
            as fTetWild is not deterministic).
        threads: fTetWild's threads; None: every core.
    Returns:
        The ``CharacterBody``.
    """
    if not isinstance(model, deform.RiggedModel):
        raise ValueError(f"model: expected a deform.RiggedModel (deform.load_model), got {type(model).__name__}")
    density = float(check_real("density", density, (), "a positive density"))
    if not density > 0:
        raise ValueError(f"density: expected a positive density, got {density}")
    gravity = np.asarray(check_real("gravity", gravity, (3,), "a finite acceleration"), np.float64)
    if not (isinstance(core, (int, float)) and 0 < core <= 1):
        raise ValueError(f"core: expected a fraction in (0, 1], got {core!r}")
    if int(influences) != influences or influences < 1:
        raise ValueError(f"influences: expected an int >= 1, got {influences!r}")
    mesh = model.mesh.with_normalized_weights()
    model = deform.RiggedModel(mesh, model.skeleton, model.clips, model.name)
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    seconds = 0.0
    if tets is None:
        made = tetrahedralize_surface(V, F, edge_length=edge_length, epsilon=epsilon, threads=threads)
        tets, seconds = made.mesh, made.seconds
    elif not isinstance(tets, TetMesh):
        raise ValueError(f"tets: expected None or a TetMesh, got {type(tets).__name__}")
    nodes, T = np.asarray(tets.X, np.float64), np.asarray(tets.T, np.int64)
    dense = transfer_weights(V, F, _dense_weights(mesh), nodes)
    J, W = _trim(dense, int(influences))
    node_mesh = deform.SkinnedMesh(
        jnp.asarray(nodes), jnp.zeros((0, 3), jnp.int32), jnp.asarray(J), jnp.asarray(W), mesh.inverse_bind, mesh.joints
    )
    node_model = deform.RiggedModel(node_mesh, model.skeleton, model.clips, model.name)
    try:
        rest = tet_mesh(np.asarray(deform.rest_pose(node_model, "lbs"), np.float64), T)
    except ValueError as error:
        raise ValueError(f"model: its rest pose flattens tets ({error}); pass tets made in that pose") from None
    surface = np.asarray(deform.rest_pose(model, "lbs"), np.float64)
    embedding = embed_points(rest, surface)
    X = np.asarray(rest.X, np.float64)
    distance = _bone_distances(model, X)
    owner = np.argmax(_dense_weights(mesh), axis=1)
    surface_distance = _bone_distances(model, surface)
    radius = np.full(mesh.num_joints, np.nan)
    for j in range(mesh.num_joints):
        mine = owner == j
        if mine.sum() >= _MIN_VERTICES:
            radius[j] = np.median(surface_distance[mine, j])
    has_core = np.isfinite(radius) & (radius > 0)
    inside = np.where(has_core[None], distance <= core * np.where(has_core, radius, 0)[None], False)
    if isinstance(driven, str):
        if driven != "all":
            raise ValueError(f"driven: expected None, 'all' or node indices, got {driven!r}")
        driven_nodes = np.arange(len(X))
    elif driven is None:
        driven_nodes = np.flatnonzero(inside.any(axis=1))
    else:
        driven_nodes = np.asarray(driven)
        if (
            driven_nodes.ndim != 1
            or not np.issubdtype(driven_nodes.dtype, np.integer)
            or (driven_nodes.size and (driven_nodes.min() < 0 or driven_nodes.max() >= len(X)))
            or len(np.unique(driven_nodes)) != len(driven_nodes)
        ):
            raise ValueError(f"driven: expected distinct int node indices in [0, {len(X)})")
        driven_nodes = np.sort(driven_nodes)
    if len(driven_nodes) == 0:
        raise ValueError(f"core: no node lies in a bone's core at core={core}; raise it or pass driven")
    # anchors: the driven nodes of the bones nearest the root (among the bones whose cores hold driven nodes)
    depth = _depths(model.skeleton.parents)[np.asarray(mesh.joints)]
    nearest = np.argmin(np.where(has_core[None], distance / np.where(has_core, radius, 1)[None], np.inf), axis=1)
    node_depth = depth[nearest[driven_nodes]]
    anchors = driven_nodes[node_depth == node_depth.min()]
    return CharacterBody(
        model=model,
        node_model=node_model,
        tets=rest,
        nodes=nodes,
        driven=driven_nodes.astype(np.int64),
        anchors=np.sort(anchors).astype(np.int64),
        surface=surface,
        faces=F,
        embedding=embedding,
        density=density,
        gravity=gravity,
        diagonal=bounding_diagonal(surface),
        quality=tet_quality(rest),
        seconds=seconds,
    )
