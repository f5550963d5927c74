"""Tools placed on real models for the tear and drill tests: scalpels that sweep over the surface
and drills along a face's inward normal."""

from __future__ import annotations

import igl
import numpy as np


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
