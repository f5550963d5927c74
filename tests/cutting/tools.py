"""Shared by the cutting tests: the real models, measures of meshes (areas, edge counts), a posed
arm, and tools placed on real models (scalpels that sweep over the surface, drills along a face's
inward normal)."""

from __future__ import annotations

from pathlib import Path

import igl
import numpy as np

import deform

DATA = Path(__file__).resolve().parents[1] / "data"


def load_models(weld: bool):
    """Arm5 and 3Cylinder4bones. Welded: glTF splits vertices along UV seams, and a tear or a drill
    walks across faces."""
    return {name: deform.load_model(DATA / f"{name}.glb", weld=weld) for name in ("Arm5", "3Cylinder4bones")}


def area(V, F):
    """Per-face areas."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def diagonal(V) -> float:
    V = np.asarray(V)
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def edge_counts(F):
    """(unique undirected edges, how many faces each has)."""
    F = np.asarray(F)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def _frame(V, F, face):
    V, F = np.asarray(V, np.float64), np.asarray(F)
    corners = V[F[face]]
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    return corners.mean(axis=0), normal / np.linalg.norm(normal)


def mean_edge(V, F) -> float:
    V, F = np.asarray(V, np.float64), np.asarray(F)
    return float(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1).mean())


def scalpels_over(V, F, face, direction, samples: int, step: float, depth: float | None = None):
    """(samples, 2, 3) scalpel positions walking over the surface: from ``face``'s centre, each sample
    moves ``step`` along ``direction`` (projected onto the tangent plane) and back onto the surface
    (closest point); the scalpel is the segment along the surface normal there, handle outside."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    point, normal = _frame(V, F, face)
    depth = 0.5 * step if depth is None else depth
    direction = np.asarray(direction, np.float64)
    scalpels = []
    for i in range(samples):
        if i:
            tangent = direction - (direction @ normal) * normal
            if np.linalg.norm(tangent) < 1e-6 * np.linalg.norm(direction):  # along the normal: any tangent
                tangent = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
            tangent /= np.linalg.norm(tangent)
            _, faces, closest = igl.point_mesh_squared_distance((point + step * tangent)[None], V, F)
            direction = closest[0] - point  # keep going the same way over the curved surface
            point, normal = closest[0], _frame(V, F, faces[0])[1]
        scalpels.append([point + depth * normal, point - depth * normal])
    return np.asarray(scalpels)


def drill_into(V, F, face, depth: float):
    """(tip, base) of a drill entering the surface at ``face``'s centre along its inward normal."""
    centre, normal = _frame(V, F, face)
    return centre - depth * normal, centre + depth * normal


def posed(model, t: float):
    """(local matrices, joint matrices, LBS positions) of ``model``'s clip at time t: a tool is then
    given in that pose's world space."""
    local = deform.sample_pose(model, t, "lbs")
    joints = deform.joint_matrices(model.mesh, deform.forward_kinematics_matrices(model.skeleton.parents, local))
    return local, joints, np.asarray(deform.skin_pose(model, local, "lbs"))
