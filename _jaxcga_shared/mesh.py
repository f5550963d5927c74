"""Mesh utilities used by more than one package: the bounding-box diagonal (the unit of tolerances and fitting
errors in deform and cutting), the signed volume enclosed by a triangle mesh, and the faces of tetrahedra (xfem's
meshes, the viewer's .vtu frames). Private to the distribution."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int


def bounding_diagonal(V) -> float:
    """Length of the diagonal of the axis-aligned bounding box of the points V (n, 3), on the host (0 when
    empty)."""
    V = np.asarray(V)
    if not len(V):
        return 0.0
    # column by column: numpy's axis-0 reduction over (n, 3) rows is some 20x slower
    return float(np.sqrt(sum((V[:, k].max() - V[:, k].min()) ** 2 for k in range(V.shape[1]))))


def signed_volume(V: Float[Array, "... n 3"], F: Int[Array, "m 3"] | Int[np.ndarray, "m 3"]) -> Float[Array, "*batch"]:
    """Signed volume enclosed by a closed, consistently oriented triangle mesh, ``sum_f det(v0, v1, v2) / 6``
    (positive for outward normals); leading axes of V are batches. JAX, differentiable in V; the caller
    checks the shapes and indices."""
    a, b, c = (V[..., F[:, k], :] for k in range(3))
    return jnp.sum(a * jnp.cross(b, c), axis=(-2, -1)) / 6


# the face of a tet opposite each local vertex, ordered so that its normal points out of a positively oriented tet
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])


def tet_face_matching(T: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The outward faces (m, 4, 3) of the tets T ((m, 4) int64, checked by the caller; face a opposite local vertex
    a), the index of each face's vertex set among the distinct ones (4m,) and the number of tets using each distinct
    face; ValueError where three or more tets share a face."""
    faces = T[:, TET_FACES]
    keys = np.sort(faces.reshape(-1, 3), axis=1)
    n = int(T.max()) + 1 if T.size else 0
    if n < 2**21:  # one int64 per face: a 1-D unique is ~10x faster than unique(axis=0)
        keys = (keys[:, 0] * n + keys[:, 1]) * n + keys[:, 2]
    _, inverse, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    if len(counts) and counts.max() > 2:
        f = int(np.argmax(counts[inverse] > 2))
        raise ValueError(
            f"T: face {faces.reshape(-1, 3)[f].tolist()} is shared by {counts[inverse[f]]} "
            "tetrahedra, expected at most 2 (a non-manifold mesh)"
        )
    return faces, inverse.reshape(-1), counts


def tet_boundary_faces(T: np.ndarray) -> np.ndarray:
    """The faces of the tets T ((m, 4) int64, checked by the caller) used by exactly one tet, outward for
    positively oriented tets, in the order of the tets and then of the local vertex each face is opposite to."""
    faces, inverse, counts = tet_face_matching(T)
    return faces.reshape(-1, 3)[counts[inverse] == 1]
