"""Free-form deformation, classic (eq. 6) and with motors (eq. 7-8), sec. V of the CGA mesh-deformation paper.

A lattice is a parallelepiped (``origin`` plus three edge vectors ``axes``) holding ``l x m x n``
control points. A point ``p_i`` has local coordinates ``(s, t, u)`` in [0, 1]^3 (``p_i = origin +
s a_0 + t a_1 + u a_2``) and tensor-product Bernstein (Bezier) weights, eq. (8),

    w_i,(a,b,c) = B^{l-1}_a(s) B^{m-1}_b(t) B^{n-1}_c(u),   B^d_j(x) = C(d, j) x^j (1 - x)^(d - j),

flattened row-major over (a, b, c), the order of ``lattice_points``. The weights are non-negative and
sum to one; Bernstein bases have linear precision, so the rest control points give back the points.

Classic FFD, eq. (6): ``p_i = sum_j w_ij P_j`` (``blend_positions``), a linear map of the control points.

Motor FFD, eq. (7)-(8): the control points are replaced by motors ``R_j`` and every point moves by
``M_i = exp(sum_j w_ij log R_j)`` (``deform._motor_field``). The paper writes ``p_i = M_i o ~M_i`` with
``o`` the point at the origin: there the rest lattice motors are the translators ``T_j`` to the lattice
points, and by linear precision ``exp(sum_j w_ij log T_j)`` is the translator to ``p_i``; that is
``motor_field_precompute(V, W, rest_motors=cga.translator(lattice_points(lattice)))``, whose bound points
are the origin. ``ffd_precompute`` binds with identity rest motors instead: the lattice motors are *motions of space*,
``p_i'' = M_i p_i ~M_i``, and the identity lattice is the rest mesh.

* Translators only: both forms are the classic FFD (translators by ``d_j`` blend to the translator by
  ``sum_j w_ij d_j``, i.e. control points ``P_j + d_j``).
* One motor G for the whole lattice: both give exactly G (displacement form: ``exp(log G) = G``; the
  paper's form with lattice motors ``G T_j``: for a fixed rotation part the log of ``T_t R`` is affine
  in t, so the blend is ``G T_{p_i}``).
* Lattice motors that turn differently: the forms differ. Twisting the lattice about one line, every
  displacement-form lattice motor is a rotation about that line, their logs are multiples of one line
  bivector, and the blend is the exact twist ``p_i`` turned by ``sum_j w_ij theta_j``; the paper's form
  (``G_j T_j``) blends screws about different axes and loses volume (measured 2.4 % at 90 degrees,
  9.4 % at 180 on a 4 x 1 x 1 box, against 14 % and 44 % for the classic FFD).

``twist_lattice`` expresses one twist of the lattice both ways (rotated control points, or rotation
motors about the lattice's long axis) and ``distortion`` measures the volume and edge-length change
a deformation causes, for the comparison in the paper's Fig. 7.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_faces, check_vectors, require
from _jaxcga_shared.mesh import signed_volume
from _jaxcga_shared.platform import EXACT
from deform._motor_field import MotorField, motor_about, motor_field_precompute
from jaxcga import Multivector


def _float_array(name: str, x, shape: tuple[int, ...]):
    x = jnp.asarray(x)
    if x.shape != shape:
        raise ValueError(f"{name}: expected shape {shape}, got {x.shape}")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


MAX_DEGREE = 1029  # the largest degree whose binomial coefficients are finite in float64


class Lattice(eqx.Module):
    """An FFD lattice: the parallelepiped ``origin + [0, 1]^3 @ axes`` with ``counts`` control points per axis.

    Attributes:
        origin: (3,) the lattice corner with local coordinates (0, 0, 0).
        axes: (3, 3) the three box edges leaving ``origin``, one per row.
        counts: (l, m, n) control points per axis (static, each >= 2; the Bezier degree is count - 1).
    """

    origin: Float[Array, "3"]
    axes: Float[Array, "3 3"]
    counts: tuple[int, int, int] = eqx.field(static=True)

    def __init__(
        self, origin: Float[ArrayLike, "3"], axes: Float[ArrayLike, "3 3"], counts: Sequence[int] = (4, 4, 4)
    ) -> None:
        origin = _float_array("origin", origin, (3,))
        axes = _float_array("axes", axes, (3, 3))
        counts = tuple(int(c) for c in counts) if np.ndim(counts) == 1 else ()
        if len(counts) != 3 or min(counts) < 2 or max(counts) > MAX_DEGREE + 1:
            raise ValueError(f"counts: expected three control-point counts in [2, {MAX_DEGREE + 1}], got {counts}")
        self.origin, self.axes, self.counts = origin, axes.astype(origin.dtype), counts

    @property
    def size(self) -> int:
        """Number of control points ``l m n``."""
        return self.counts[0] * self.counts[1] * self.counts[2]


def bounding_lattice(V: Float[ArrayLike, "n 3"], counts: Sequence[int] = (4, 4, 4), padding: float = 0.0) -> Lattice:
    """The axis-aligned bounding box of ``V`` as a lattice, grown by ``padding`` times the largest box
    extent on every side (use ``padding > 0`` for a flat mesh, whose box is degenerate).

    Args:
        V: (n, 3) points.
        counts: (l, m, n) control points per axis, each >= 2.
        padding: >= 0, the margin on every side as a fraction of the largest box extent.

    Returns:
        The ``Lattice``.
    """
    V = check_vectors("V", V, rows="n")
    if padding < 0:
        raise ValueError(f"padding: expected >= 0, got {padding}")
    low, high = jnp.min(V, axis=0), jnp.max(V, axis=0)
    pad = padding * jnp.max(high - low)
    return Lattice(low - pad, jnp.diag(high - low + 2 * pad), counts)


def lattice_coordinates(V: Float[ArrayLike, "n 3"], lattice: Lattice) -> Float[Array, "n 3"]:
    """Local coordinates ``(s, t, u)`` of the points ``V`` (n, 3) in the lattice, ``V = origin + (s, t, u) @ axes``.

    A point outside [0, 1]^3 by more than rounding (``sqrt(eps)``), or a flat lattice, raises a
    ValueError (inside jit a runtime error with the message).

    Args:
        V: (n, 3) points inside the lattice.
        lattice: the Lattice.

    Returns:
        (n, 3) the coordinates (s, t, u), in [0, 1] inside the lattice.
    """
    V = check_vectors("V", V, rows="n")
    axes, origin = lattice.axes.astype(V.dtype), lattice.origin.astype(V.dtype)
    local = jnp.linalg.solve(axes.T, (V - origin[None]).T).T
    tolerance = float(np.sqrt(np.finfo(V.dtype).eps))
    outside = ~jnp.all((local >= -tolerance) & (local <= 1 + tolerance))
    return require(
        local,
        (
            outside,
            "V: points lie outside the lattice (local coordinates outside [0, 1]) or the lattice axes are degenerate",
        ),
    )


def _bernstein(degree: int, t: Float[Array, "*batch"]) -> Float[Array, "*batch degree+1"]:
    """The Bernstein basis ``B^d_j(t) = C(d, j) t^j (1 - t)^(d - j)``, j = 0..d, stacked on a last axis."""
    if int(degree) != degree or not 0 <= degree <= MAX_DEGREE:
        raise ValueError(f"degree: expected an integer in [0, {MAX_DEGREE}], got {degree}")
    degree = int(degree)
    t = jnp.asarray(t)
    if not jnp.issubdtype(t.dtype, jnp.floating):
        t = t.astype(jnp.result_type(float))
    # integer powers keep the derivative finite at t = 0 and t = 1 (no 0 * inf from t^(j - 1))
    return jnp.stack([float(math.comb(degree, j)) * t**j * (1 - t) ** (degree - j) for j in range(degree + 1)], axis=-1)


def ffd_weights(V: Float[ArrayLike, "n 3"], lattice: Lattice) -> Float[Array, "n k"]:
    """Tensor-product Bezier weights (n, l m n) of the points ``V`` in the lattice, eq. (8).

    Args:
        V: (n, 3) points inside the lattice.
        lattice: the Lattice.

    Returns:
        (n, l m n) the weights, rows summing to one.

    Examples:
        >>> import numpy as np
        >>> import deform
        >>> V = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]])
        >>> lattice = deform.bounding_lattice(V, (2, 2, 2), padding=0.1)
        >>> W = deform.ffd_weights(V, lattice)
        >>> W.shape, bool(np.allclose(W.sum(axis=1), 1.0, atol=1e-6))
        ((4, 8), True)
    """
    local = lattice_coordinates(V, lattice)
    b = [_bernstein(c - 1, local[:, axis]) for axis, c in enumerate(lattice.counts)]
    return jnp.einsum("pa,pb,pc->pabc", *b, precision=EXACT).reshape(local.shape[0], lattice.size)


def _local_grid(lattice: Lattice) -> Float[Array, "k 3"]:
    grids = jnp.meshgrid(
        *[jnp.linspace(0.0, 1.0, c, dtype=lattice.origin.dtype) for c in lattice.counts], indexing="ij"
    )
    return jnp.stack([g.ravel() for g in grids], axis=-1)


def lattice_points(lattice: Lattice) -> Float[Array, "k 3"]:
    """The rest control points (l m n, 3), row-major over the (a, b, c) grid like ``ffd_weights``.

    Args:
        lattice: the Lattice.

    Returns:
        (l m n, 3) the control points.
    """
    return lattice.origin[None] + jnp.matmul(_local_grid(lattice), lattice.axes, precision=EXACT)


def ffd_precompute(V: Float[ArrayLike, "n 3"], lattice: Lattice) -> MotorField:
    """Motor FFD, eq. (7)-(8): ``V`` bound to one motor per lattice point with identity rest motors.

    ``motor_field_solve`` on the result and lattice motors with batch shape (..., l m n) gives the deformed
    positions (..., n, 3); the identity motors give back ``V``, translators by ``d_j`` the classic FFD with
    control points ``P_j + d_j``, and the same motor G everywhere moves the mesh rigidly by G.

    Args:
        V: (n, 3) points inside the lattice.
        lattice: the Lattice.

    Returns:
        The ``MotorField`` of the lattice's motors.
    """
    V = check_vectors("V", V, rows="n")
    return motor_field_precompute(V, ffd_weights(V, lattice))


def twist_lattice(
    lattice: Lattice, angle: Float[ArrayLike, ""], axis: int | None = None
) -> tuple[Float[Array, "k 3"], Multivector]:
    """One twist of the lattice, as control points and as lattice motors.

    Every lattice point turns about the lattice's centre line along ``axes[axis]`` (default: the longest
    edge) by ``angle * (s - 1/2)``, with s its local coordinate along that axis: the ends turn by
    -angle/2 and +angle/2, so each lattice motor turns by at most half the twist and the logarithms
    blend along one branch up to a total twist of 2 pi.

    Args:
        lattice: the rest lattice.
        angle: () total twist in radians (may be traced: jit / vmap / grad over it).
        axis: 0, 1 or 2, the edge to twist about; None for the longest one.

    Returns:
        P: (l m n, 3) the turned control points (for ``blend_positions``).
        motors: (l m n,) the rotations about the centre line (for ``ffd_precompute``'s field); applied to
            ``lattice_points(lattice)`` they give ``P``.
    """
    if axis not in (0, 1, 2, None):
        raise ValueError(f"axis: expected 0, 1, 2 or None, got {axis}")
    local = _local_grid(lattice)
    # a traced index, so that the default (longest edge) also works on traced lattices
    along = jnp.argmax(jnp.linalg.norm(lattice.axes, axis=1)) if axis is None else axis
    centre = lattice.origin + 0.5 * jnp.sum(lattice.axes, axis=0)
    direction = jnp.broadcast_to(lattice.axes[along], local.shape)
    turn = jnp.asarray(angle, local.dtype) * (local[:, along] - 0.5)
    motors = motor_about(centre, cga.rotor(direction, turn))
    return cga.apply_to_points(motors, lattice_points(lattice)), motors


def distortion(
    V0: Float[ArrayLike, "n 3"], F: Int[ArrayLike, "m 3"], V1: Float[ArrayLike, "... n 3"]
) -> dict[str, Float[Array, "*batch"]]:
    """How a deformation ``V0 -> V1`` of a closed mesh (V0, F) changes volume and edge lengths.

    Args:
        V0: (n, 3) rest positions.
        F: (m, 3) int triangles of a closed mesh.
        V1: (..., n, 3) deformed positions.
    Returns:
        A dict of arrays with the batch shape of ``V1``: ``volume_ratio``, the signed volume of V1 over that of V0
        (1 for a volume-preserving map); ``edge_mean`` and ``edge_max``, the mean and max over the edges of
        ``|len_1 / len_0 - 1|``.
    """
    V0 = check_vectors("V0", V0, rows="n")
    V1 = jnp.asarray(V1)
    if V1.shape[-2:] != V0.shape:
        raise ValueError(f"V1: expected shape (..., {V0.shape[0]}, 3), got {V1.shape}")
    V1 = V1.astype(V0.dtype)
    F = check_faces("F", F, V0.shape[0])
    E = np.unique(np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1), axis=0)
    rest = jnp.linalg.norm(V0[E[:, 1]] - V0[E[:, 0]], axis=-1)
    length = jnp.linalg.norm(V1[..., E[:, 1], :] - V1[..., E[:, 0], :], axis=-1)
    change = jnp.abs(length / rest - 1)
    return {
        "volume_ratio": signed_volume(V1, jnp.asarray(F)) / signed_volume(V0, jnp.asarray(F)),
        "edge_mean": jnp.mean(change, axis=-1),
        "edge_max": jnp.max(change, axis=-1),
    }
