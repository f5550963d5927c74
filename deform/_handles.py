"""Harmonic motor handles: sec. IV of the CGA mesh-deformation paper (deformation based on generalized
barycentric coordinates).

Each handle H_j (a set of vertices; the fixed region is a handle whose motor stays the identity) gets
a harmonic field lambda_j: 1 on H_j, 0 on every other handle, harmonic elsewhere (sec. VIII,
``deform.harmonic_fields``). The fields sum to one at every vertex: they are harmonic coordinates of
the vertices with respect to the handle motors, computed on the surface. A vertex then moves by
``M_i = exp(sum_j lambda_j^i log R_j)`` (``deform.motor_field_solve``): vertices of H_j move rigidly by R_j,
the rest blend the handle motions, rotations included.
"""

from __future__ import annotations

from collections.abc import Sequence

from jaxtyping import ArrayLike, Float, Int

from deform._harmonic import harmonic_fields
from deform._motor_field import MotorField, motor_field_precompute


def handles_precompute(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    handles: Sequence[Int[ArrayLike, "*k"]],
    *,
    laplacian: str = "cotangent",
    unhandled: str = "follow",
) -> MotorField:
    """Bind a mesh to motor handles through one harmonic field per handle (sec. IV).

    Args:
        V: (n, 3) rest positions.
        F: (m, 3) int faces.
        handles: h >= 1 disjoint, non-empty vertex index arrays; include the fixed region as a handle
            (its motor the identity), or every vertex follows the moving handles.
        laplacian: ``"cotangent"`` or ``"mean_value"`` (the paper's choice).
        unhandled: ``"follow"`` (default) or ``"error"``: what a connected part of the mesh without a handle
            does; following, it takes the fields of the part it is attached or nearest to (``deform.mesh_parts``),
            so a rigid motion of every handle moves it by that motion.
    Returns:
        A ``MotorField``: ``motor_field_solve`` on it and h handle motors (batch shape (..., h); identity
        motors give the rest mesh) gives the deformed positions (..., n, 3)."""
    fields = harmonic_fields(V, F, handles, laplacian=laplacian, unhandled=unhandled)
    return motor_field_precompute(V, fields)
