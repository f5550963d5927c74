"""The separating axis test of tets against triangles (``xfem._subdomains``' primary culling), compiled by numba.

A cut meets thousands of (tet, triangle) pairs whose boxes overlap; in numpy each pair's 23 axes and 7
projections were arrays of their own, here they are a loop that stops at the first separating axis.
"""

from __future__ import annotations

import numba
import numpy as np

from _jaxcga_shared.mesh import TET_FACES  # a global array: numba compiles it in as a constant

_TET_EDGES = ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))


@numba.njit(nogil=True, cache=True)
def _separates(ax, ay, az, P, Q, slack):  # pragma: no cover (compiled)
    """Whether the axis (ax, ay, az) separates the tet P (4, 3) from the triangle Q (3, 3) by more than slack times
    its length."""
    p_low = p_high = ax * P[0, 0] + ay * P[0, 1] + az * P[0, 2]
    for j in range(1, 4):
        p = ax * P[j, 0] + ay * P[j, 1] + az * P[j, 2]
        p_low, p_high = min(p_low, p), max(p_high, p)
    q_low = q_high = ax * Q[0, 0] + ay * Q[0, 1] + az * Q[0, 2]
    for j in range(1, 3):
        q = ax * Q[j, 0] + ay * Q[j, 1] + az * Q[j, 2]
        q_low, q_high = min(q_low, q), max(q_high, q)
    gap = slack * np.sqrt(ax * ax + ay * ay + az * az)
    return p_high < q_low - gap or q_high < p_low - gap


@numba.njit(nogil=True, cache=True)
def tet_triangle_overlap(P, Q, slack):  # pragma: no cover (compiled)
    """(k,) whether tet P[j] (4, 3) and triangle Q[j] (3, 3) may overlap: no separating axis among the tet's face
    normals, the triangle's normal and the 18 edge-edge cross products (separating axis theorem for convex
    polytopes). Conservative: gaps below slack times the axis length count as contact."""
    out = np.empty(P.shape[0], np.bool_)
    for k in range(P.shape[0]):
        T, R = P[k], Q[k]
        separated = False
        for f in range(4):
            a, b, c = TET_FACES[f, 0], TET_FACES[f, 1], TET_FACES[f, 2]
            ux, uy, uz = T[b, 0] - T[a, 0], T[b, 1] - T[a, 1], T[b, 2] - T[a, 2]
            vx, vy, vz = T[c, 0] - T[a, 0], T[c, 1] - T[a, 1], T[c, 2] - T[a, 2]
            if _separates(uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx, T, R, slack):
                separated = True
                break
        if not separated:
            ux, uy, uz = R[1, 0] - R[0, 0], R[1, 1] - R[0, 1], R[1, 2] - R[0, 2]
            vx, vy, vz = R[2, 0] - R[1, 0], R[2, 1] - R[1, 1], R[2, 2] - R[1, 2]
            separated = _separates(uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx, T, R, slack)
        for e in range(6):
            if separated:
                break
            a, b = _TET_EDGES[e]
            ux, uy, uz = T[b, 0] - T[a, 0], T[b, 1] - T[a, 1], T[b, 2] - T[a, 2]
            for i in range(3):
                j = (i + 1) % 3
                vx, vy, vz = R[j, 0] - R[i, 0], R[j, 1] - R[i, 1], R[j, 2] - R[i, 2]
                if _separates(uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx, T, R, slack):
                    separated = True
                    break
        out[k] = not separated
    return out
