"""Generalized winding numbers (Jacobson et al. 2013: the solid angles of a closed mesh's triangles at a point, over
4 pi) of many points, each against its own small mesh, in one call compiled by numba.

eq. 16's nearest nodal subdomain (``xfem._xfem._nearest_subdomain``) asks, after a cut, whether each of some
hundred thousand piece points lies inside one of its node's few subdomain solids (about 20 triangles each). One
libigl call per node spent its time in the call, not the sums; here all of a cut's queries are one loop.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(nogil=True, cache=True)
def winding_numbers(V, F, vertex_start, face_start, mesh, points):  # pragma: no cover (compiled)
    """The winding number of each query point with respect to its mesh.

    Args:
        V: (v, 3) float64 the vertices of every mesh, mesh after mesh.
        F: (f, 3) int64 the triangles of every mesh, mesh after mesh, indices into the mesh's own vertices.
        vertex_start: (meshes + 1,) int64 where each mesh's vertices and triangles start.
        face_start: see ``vertex_start``.
        mesh: (q,) int64 the mesh of each query.
        points: (q, 3) float64 the query points.
    Returns:
        (q,) float64 the winding numbers: 1 inside a closed outward mesh, 0 outside.
    """
    out = np.empty(mesh.shape[0])
    for q in range(mesh.shape[0]):
        s = mesh[q]
        base = vertex_start[s]
        px, py, pz = points[q, 0], points[q, 1], points[q, 2]
        total = 0.0
        for f in range(face_start[s], face_start[s + 1]):
            i, j, k = base + F[f, 0], base + F[f, 1], base + F[f, 2]
            ax, ay, az = V[i, 0] - px, V[i, 1] - py, V[i, 2] - pz
            bx, by, bz = V[j, 0] - px, V[j, 1] - py, V[j, 2] - pz
            cx, cy, cz = V[k, 0] - px, V[k, 1] - py, V[k, 2] - pz
            la = np.sqrt(ax * ax + ay * ay + az * az)
            lb = np.sqrt(bx * bx + by * by + bz * bz)
            lc = np.sqrt(cx * cx + cy * cy + cz * cz)
            det = ax * (by * cz - bz * cy) - ay * (bx * cz - bz * cx) + az * (bx * cy - by * cx)
            dots = (ax * bx + ay * by + az * bz) * lc + (bx * cx + by * cy + bz * cz) * la
            dots += (cx * ax + cy * ay + cz * az) * lb
            total += 2.0 * np.arctan2(det, la * lb * lc + dots)  # van Oosterom and Strackee's solid angle
        out[q] = total / (4.0 * np.pi)
    return out
