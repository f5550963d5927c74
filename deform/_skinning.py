"""Skinning: matrix LBS (eq. 16), dual-quaternion skinning, and multivector skinning (eq. 17) of the
cut/tear/drill paper, with per-bone dilation.

All four take the bind-pose vertices ``V (n, 3)``, joint indices ``J (n, k)``, weights ``W (n, k)`` and
one transform per joint; they are jit-, vmap- and grad-able and batch over leading axes of the joint
transforms (poses).

* ``skin_lbs``: ``V_k[m] = sum_n w_mn T_n,k O_n v[m]`` (eq. 16, G = identity).
* ``skin_cga``: ``C_k[m] = sum_n w_mn (M_n,k B_n) c[m] (M_n,k B_n)^-1`` (eq. 17), down-projected. A
  sandwich by one fixed versor is a linear map of the conformal point (x, 1), generated from the
  versor's components by the kernel (``jaxcga.versor_to_matrix``); it is built once per joint, and the
  per-vertex sum of eq. (17) adds the mapped points. Sec. 4.3 gives two ways to down-project the sum:
  each term first, then add (the paper's implementation, "faster", and the default here), or the sum
  at once (``normalize_points=False``). They differ when the joints carry unequal dilations: the
  sandwich of a point by a normalized similitude of scale s is the point scaled by ``lambda = 1/s``
  (``D up(x) D^-1 = up(s x) / s``), so down-projecting the sum,
  ``sum_n w_mn lambda_n x_n / sum_n w_mn lambda_n``, weighs each influence by the inverse of its
  dilation (scales blend harmonically), while down-projecting each term blends the moved points with
  the weights as given (scales blend linearly, as LBS with the same similitudes). With rigid joints, or
  equal dilations, both are LBS with the same transforms.
* ``skin_cga_motor_blend``: blend the versors first, normalized, like DQS: each joint similitude is
  factored as a motor times a dilator about the origin, ``M_n D(s_n)``; per vertex the motors are
  blended (signs aligned with the first influence) and normalized, the scales are blended in log
  space, and the vertex moves by ``M D(s)``. For rigid joints this equals DQS.
* ``skin_dqs``: Kavan et al.'s dual-quaternion skinning (rigid joints only; no dilation).
"""

from __future__ import annotations

import functools
import operator

import jax
import jax.numpy as jnp
from jax import custom_batching
from jaxtyping import Array, ArrayLike, Float, Int

import jaxcga as cga
from _jaxcga_shared import pallas_rows
from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import check_vectors, require, require_around
from _jaxcga_shared.platform import EXACT, PerPlatform, per_platform
from jaxcga._multivector import KINDS, Multivector
from jaxcga._versors import fused_point_coordinates, row_coordinates, similitude_motor_log_scale_unchecked


def _check_mesh(V, J, W):
    V, J, W = check_vectors("V", V, rows="n"), jnp.asarray(J), jnp.asarray(W)
    if J.ndim != 2 or J.shape[0] != V.shape[0]:
        raise ValueError(f"J: expected shape ({V.shape[0]}, k), got {J.shape}")
    if not jnp.issubdtype(J.dtype, jnp.integer):
        raise ValueError(f"J: expected integer joint indices, got {J.dtype}")
    if W.shape != J.shape:
        raise ValueError(f"W: expected shape {J.shape} (same as J), got {W.shape}")
    return V, J, W


def _materialize(x):
    """Materialize an array that XLA:CPU would otherwise fuse into its consumers and recompute there.

    Per-joint data before the per-vertex gather: fused into the gather, every joint's map is
    recomputed at every (vertex, influence) (measured 3-30x slower). A dot separates the fusions, so
    the data goes through a product with the identity (c x c flops per row: nothing for per-joint
    tables). For large per-vertex arrays ``jax.lax.optimization_barrier`` does the same without the
    copy (``_aligned_weights``)."""
    shape = x.shape
    flat = x.reshape(-1, shape[-1])
    return jnp.matmul(flat, jnp.eye(shape[-1], dtype=x.dtype), precision=EXACT).reshape(shape)


def _blend_joints(J, weights, data, joint_axis: int = -2):
    """``sum_k weights[k] * data[..., J[:, k], :]`` (..., n, c); ``weights`` holds one (n,) or (..., n)
    array per influence (``_influence_weights`` or ``_aligned_weights``). With ``joint_axis=-1`` the
    joints are the last axis of ``data`` (..., c1, c2, j) and the result is (..., c1, c2, n). Written
    elementwise over the k influences so that XLA fuses the gathers into one loop: a gather-then-einsum
    materializes (..., n, k, c) and was measured 100x slower at 100k vertices (and runs out of memory
    under vmap over 1,000 poses)."""
    if joint_axis not in (-1, -2):
        raise ValueError(f"joint_axis: expected -1 or -2, got {joint_axis!r}")
    acc = None
    for k, w in enumerate(weights):
        w = w.astype(data.dtype)
        gathered = data[..., J[:, k]] if joint_axis == -1 else data[..., J[:, k], :]
        term = lift_rank(w if joint_axis == -1 else w[..., None], gathered.ndim) * gathered
        acc = term if acc is None else acc + term
    if acc is None:
        raise ValueError("J: expected at least one influence per vertex (k >= 1)")
    return acc


def _influence_weights(W):
    return [W[:, k] for k in range(W.shape[1])]


def _aligned_weights(J, W, rotors: Float[Array, "... j 4"], log_scales: Float[Array, "... j"] | None, *, cpu: bool):
    """The weights of a versor blend, one (..., n) row per influence, with each influence's sign
    flipped when its rotor (or quaternion) points away from the first influence's: V and -V are the
    same transformation. With ``log_scales``, one more row: the blended log scales (unsigned).

    The signs come from a joint-by-joint table of rotor dot products (a tiny dot; flattened, so a
    lookup takes one index). On the CPU (``cpu``) all rows are written in one pass, coordinate-major
    (..., rows, n), and kept by ``jax.lax.optimization_barrier``: left to XLA:CPU, every influence's
    lookup became its own pass over the vertices, and under vmap over poses laid out vertex-major
    (n, poses) against the pose-major loops that read it (benchmarks/README.md, "Kernel and deformers").
    Elsewhere the rows are left to fuse into the blend that reads them."""
    joints = rotors.shape[-2]
    dots = jnp.einsum("...ac,...bc->...ab", rotors, rotors, precision=EXACT).reshape(
        rotors.shape[:-2] + (joints * joints,)
    )
    rows = [jnp.broadcast_to(W[:, 0].astype(rotors.dtype), rotors.shape[:-2] + W.shape[:1])]
    for k in range(1, J.shape[1]):
        w = W[:, k].astype(rotors.dtype)
        rows.append(jnp.where(dots[..., J[:, 0] * joints + J[:, k]] < 0, -w, w))
    if log_scales is not None:
        rows.append(_blend_joints(J, _influence_weights(W), log_scales[..., None])[..., 0])
    if not cpu:
        return rows
    stacked = jax.lax.optimization_barrier(jnp.stack(rows, axis=-2))
    return [stacked[..., r, :] for r in range(len(rows))]


def _coordinates_last(coordinates, *, cpu: bool):
    """Stack three (..., n) coordinates as (..., n, 3). On the CPU coordinate-major, then moved last:
    XLA:CPU's transpose emitter runs that 1.3x faster than a stack along the last axis (for per-vertex
    blended motors); elsewhere the plain stack."""
    if cpu:
        return jnp.moveaxis(jnp.stack(coordinates, axis=-2), -2, -1)
    return jnp.stack(coordinates, axis=-1)


# Up to this many joints a batch of poses blends its dilations through a dense (joints, vertices) weight
# matrix (see ``_blend_dilations``); it costs joints multiply-adds per vertex and pose and joints x vertices
# floats, so large skeletons keep the per-influence gather.
DENSE_DILATION_BLEND_MAX_JOINTS = 64


def _blend_dilations_sparse(J, W, dilations):
    return _blend_joints(J, _influence_weights(W), dilations[..., None])[..., 0]


def _blend_dilations_dense(J, W, dilations):
    n, k = J.shape
    vertex = jnp.broadcast_to(jnp.arange(n), (k, n))
    dense = jnp.zeros((dilations.shape[-1], n), dilations.dtype).at[J.T, vertex].add(W.T.astype(dilations.dtype))
    return jnp.matmul(dilations, dense, precision=EXACT)


@custom_batching.custom_vmap
def _blend_dilations_by_batching(J, W, dilations):
    if dilations.ndim > 1 and dilations.shape[-1] <= DENSE_DILATION_BLEND_MAX_JOINTS:
        return _blend_dilations_dense(J, W, dilations)
    return _blend_dilations_sparse(J, W, dilations)


@_blend_dilations_by_batching.def_vmap
def _blend_dilations_vmap(axis_size, in_batched, J, W, dilations):
    """Under vmap over poses (J, W shared) the call sees its batch axis: the dense path."""
    J_batched, W_batched, dilations_batched = in_batched
    if J_batched or W_batched:  # a batch of meshes: the gather, vmapped
        axes = tuple(0 if b else None for b in in_batched)
        return jax.vmap(_blend_dilations_sparse, in_axes=axes)(J, W, dilations), True
    return _blend_dilations_by_batching(J, W, dilations), dilations_batched


@jax.custom_jvp
def _blend_dilations_cpu(J, W, dilations: Float[Array, "... j"]) -> Float[Array, "... n"]:
    """``sum_k W[:, k] * dilations[..., J[:, k]]``: the eo-coefficient (lambda) row of eq. (17)'s sum.

    The per-vertex loop divides by it, so it is computed once per vertex and pose beforehand. For one
    pose that is a gather. For a batch of poses, natively or under vmap, the gather makes XLA:CPU lay
    the array out vertex-major (n, poses) while the loop writes pose-major, and every read misses the
    cache (measured 1.2-1.3x slower at 100k vertices and 300 poses); written as
    ``dilations @ dense_weights`` the product keeps the pose axis first. For one pose that product is
    slower than the gather (building the dense weights is not amortized), so the choice is made by
    batching (``custom_vmap``); derivatives go through the gather (``custom_jvp``), which is linear in
    W and in the dilations. That is for XLA:CPU's layouts: elsewhere (GPUs) the gather, which fuses into
    the per-vertex loop for any batch, is the formulation chosen (``_blend_dilations``)."""
    return _blend_dilations_by_batching(J, W, dilations)


@_blend_dilations_cpu.defjvp
def _blend_dilations_jvp(primals, tangents):
    J, W, dilations = primals
    _, W_dot, dilations_dot = tangents  # J's tangent: integers have none
    out = _blend_dilations_cpu(J, W, dilations)
    return out, _blend_dilations_sparse(J, W_dot, dilations) + _blend_dilations_sparse(J, W, dilations_dot)


_blend_dilations = PerPlatform("deform.blend_dilations", cpu=_blend_dilations_cpu, gpu=_blend_dilations_sparse)


def _blend_affine(V, J, W, maps: Float[Array, "... j r 4"]) -> Float[Array, "... n 3"]:
    """``sum_k W[:, k] * (maps[J[:, k]] @ [V, 1])`` for every vertex; batch axes lead ``maps``. With
    4-row maps (last row (0, 0, 0, lambda)) the result is down-projected: divided by the blended
    lambda (``_blend_dilations``).

    The (3, 4) maps are blended with the joint axis last and contracted with (x, y, z, 1) coordinate-
    major, (..., 3, n), then the coordinate axis is moved last. Stacking the three rows of a flat
    12-column table along the last axis instead was slower (benchmarks/README.md, "Kernel and deformers"),
    and with lambda as a 13th column XLA recomputed its blend for every row."""
    joints = maps.shape[-3]
    table = _materialize(maps[..., :3, :].reshape(maps.shape[:-3] + (joints, 12)))
    table = jnp.moveaxis(table, -2, -1).reshape(maps.shape[:-3] + (3, 4, joints))
    blended = _blend_joints(J, _influence_weights(W), table, joint_axis=-1)  # (..., 3, 4, n)
    x, y, z = (lift_rank(V[:, i].astype(maps.dtype), blended.ndim - 1) for i in range(3))
    out = blended[..., 0, :] * x + blended[..., 1, :] * y + blended[..., 2, :] * z + blended[..., 3, :]
    if maps.shape[-2] == 4:
        out = out / _blend_dilations(J, W, maps[..., 3, 3])[..., None, :]
    return jnp.moveaxis(out, -2, -1)


def skin_lbs(
    V: Float[ArrayLike, "n 3"],
    J: Int[ArrayLike, "n k"],
    W: Float[ArrayLike, "n k"],
    joint_matrices: Float[ArrayLike, "... j 4 4"],
) -> Float[Array, "... n 3"]:
    """Linear blend skinning, eq. (16).

    Args:
        V: (n, 3) bind-pose positions.
        J: (n, k) int joint indices.
        W: (n, k) weights (rows sum to one).
        joint_matrices: (..., j, 4, 4) or (..., j, 3, 4) joint matrices ``T_n,k O_n``.
    Returns:
        (..., n, 3) skinned positions."""
    V, J, W = _check_mesh(V, J, W)
    joint_matrices = jnp.asarray(joint_matrices)
    if joint_matrices.ndim < 3 or joint_matrices.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"joint_matrices: expected shape (..., j, 4, 4), got {joint_matrices.shape}")
    return _blend_affine(V, J, W, joint_matrices[..., :3, :])


def _check_versors(name: str, versors):
    if not isinstance(versors, Multivector) or not versors.batch_shape:
        raise ValueError(f"{name}: expected a versor Multivector with batch shape (..., j)")
    if not set(versors.blades) <= set(KINDS["similitude"]):
        raise ValueError(f"{name}: expected motors or similitudes, got blades {versors.names}")


def skin_cga(
    V: Float[ArrayLike, "n 3"],
    J: Int[ArrayLike, "n k"],
    W: Float[ArrayLike, "n k"],
    joint_versors: Multivector,
    normalize_points: bool = True,
) -> Float[Array, "... n 3"]:
    """Multivector skinning, eq. (17): blend after the sandwich, with per-bone dilation.

    Args:
        V: (n, 3) bind-pose positions.
        J: (n, k) int joint indices.
        W: (n, k) weights (rows sum to one).
        joint_versors: motors or similitudes ``M_n,k B_n``, batch shape (..., j).
        normalize_points: True (default): down-project (normalize) every sandwiched conformal point,
            then blend: the paper's evaluation (sec. 4.3). False: blend the conformal points and
            down-project the sum, eq. (17) read literally, which weighs each influence by the inverse
            of its joint's dilation (module docstring); one more gather and a division per vertex.
    Returns:
        (..., n, 3) skinned positions."""
    V, J, W = _check_mesh(V, J, W)
    _check_versors("joint_versors", joint_versors)
    maps = cga.versor_to_matrix(joint_versors, normalized=normalize_points)
    return _blend_affine(V, J, W, maps[..., :3, :] if normalize_points else maps)  # it materializes the table


def _motor_and_log_scale(versors: Multivector):
    """Factor similitudes as ``M D(s)`` (motor, then the dilator about the origin): (..., 8), (...), and where a
    versor is not a similitude (unchecked)."""
    if set(versors.blades) <= set(KINDS["motor"]):
        return versors.embed(KINDS["motor"]).values, jnp.zeros(versors.batch_shape, versors.dtype), False
    motors, log_scale, bad = similitude_motor_log_scale_unchecked(versors)
    return motors.values, log_scale, bad


def skin_cga_motor_blend(
    V: Float[ArrayLike, "n 3"], J: Int[ArrayLike, "n k"], W: Float[ArrayLike, "n k"], joint_versors: Multivector
) -> Float[Array, "... n 3"]:
    """Multivector skinning with the versors blended first (normalized, like DQS) and per-bone
    dilation blended in log space.

    Args:
        V: (n, 3) bind-pose positions.
        J: (n, k) int joint indices.
        W: (n, k) weights (rows sum to one).
        joint_versors: motors or similitudes ``M_n,k B_n``, batch shape (..., j).
    Returns:
        (..., n, 3) skinned positions."""
    return _skin_motor_blend(V, J, W, joint_versors, _blend_motors_and_apply)


def _skin_motor_blend(V, J, W, joint_versors: Multivector, blend_and_apply) -> Float[Array, "... n 3"]:
    """``skin_cga_motor_blend`` with the blend of its joints' table given (a platform's kernel)."""
    V, J, W = _check_mesh(V, J, W)
    _check_versors("joint_versors", joint_versors)
    table, bad = motor_blend_joints(joint_versors)
    # the check on the joints' table on the CPU, on the positions on a GPU (its host round trip waits only for them)
    return require_around(
        lambda table: blend_and_apply(V, J, W, table),
        table,
        (bad, "joint_versors: not similitude versors (dilated part too large)"),
    )


_TABLE_WIDTH = 9  # a joint's row of the motor blend's table: its motor's 8 components, then its log scale


def motor_blend_joints(joint_versors: Multivector) -> tuple[Float[Array, "... j 9"], Array | bool]:
    """The table that ``skin_cga_motor_blend`` blends: per joint its motor's 8 components, then its log scale,
    materialized (``_materialize``); and where a joint's versor is not a similitude (unchecked)."""
    motors, log_scale, bad = _motor_and_log_scale(joint_versors)
    # one table: a product with a 1x1 identity is simplified away, and the log scale's arctanh then ran per
    # vertex and influence
    return _materialize(jnp.concatenate([motors, log_scale[..., None]], axis=-1)), bad


def _blend_motors_in_xla(V, J, W, table: Float[Array, "... j 9"], *, cpu: bool) -> Float[Array, "... n 3"]:
    """The motor blend of ``skin_cga_motor_blend`` (the joints' ``motor_blend_joints`` table) left to XLA: on the
    CPU (``cpu``) with barriers and coordinate-major output, elsewhere without."""
    motors = table[..., :8]
    *weights, log_scale = _aligned_weights(J, W, motors[..., :4], table[..., 8], cpu=cpu)
    scale = jnp.exp(log_scale)
    if cpu:  # exp in a loop of its own, where it vectorizes: inside the gather loop it ran scalar
        scale = jax.lax.optimization_barrier(scale)
    # XLA writes the blend once per vertex by itself (one (..., n, 8) pass, as for DQS); a barrier
    # there measured within the run-to-run noise at 300 poses.
    blended = Multivector(_blend_joints(J, weights, motors), KINDS["motor"])
    # No explicit normalization: the generated point map of M up(x) ~M divides by the eo row, the
    # scalar part of M ~M, and the e123inf part of M ~M does not reach points, so the unnormalized
    # blend moves points exactly as ``jaxcga.normalize(M)`` does (tested), inside one fused loop.
    coordinates = fused_point_coordinates(blended, lift_rank(V, scale.ndim + 1) * scale[..., None], blended.batch_shape)
    return _coordinates_last(coordinates, cpu=cpu)


def _blend_motors_in_rows(V, J, W, table):
    """GPUs: one Triton program per block of vertices gathers each influence's motor and log scale, blends them and
    applies the blend, writing the vertex's three coordinates together (``_jaxcga_shared.pallas_rows``): XLA
    computes each output coordinate in its own thread and redoes the blend and the point map for each. Batches of
    poses are a grid axis (vmap); mixed dtypes and arrays past 32-bit offsets take the XLA formulation."""
    if not V.dtype == W.dtype == table.dtype or V.shape[0] == 0 or not pallas_rows.fits(V, J, W):
        return _blend_motors_in_xla(V, J, W, table, cpu=False)
    joints, influences = table.shape[-2], J.shape[1]
    coordinates = _motor_blend_coordinates(influences, joints)

    def in_xla(V, J, W, flat):
        return _blend_motors_in_xla(V, J, W, flat.reshape(joints, _TABLE_WIDTH), cpu=False)

    def one_pose(flat):
        return pallas_rows.rowwise(coordinates, [V, J.astype(jnp.int32), W], [flat], 3, otherwise=in_xla)

    skin_poses = one_pose
    for _ in table.shape[:-2]:
        skin_poses = jax.vmap(skin_poses)
    return skin_poses(table.reshape(table.shape[:-2] + (joints * _TABLE_WIDTH,)))


@functools.cache
def _motor_blend_coordinates(influences: int, joints: int) -> pallas_rows.RowFunction:
    """The ``rowwise`` function of ``_blend_motors_in_rows``: rows of (V, J, W), the joints' table shared."""
    apply = row_coordinates(KINDS["motor"])

    def coordinates(row_columns, shared_columns):
        V, J, W = row_columns
        (table,) = shared_columns
        # clamped as XLA's gathers clamp: Triton reads whatever an index points at
        rows = [jnp.clip(J[k], 0, joints - 1) * _TABLE_WIDTH for k in range(influences)]
        gathered = [[table.gather(row + c) for c in range(_TABLE_WIDTH)] for row in rows]
        first = gathered[0]
        blend, log_scale = [W[0] * first[c] for c in range(8)], W[0] * first[8]
        for k in range(1, influences):
            # V and -V are the same transformation: an influence whose rotor points away from the first's flips
            facing = functools.reduce(operator.add, [first[c] * gathered[k][c] for c in range(4)])
            signed = jnp.where(facing < 0, -W[k], W[k])
            blend = [b + signed * m for b, m in zip(blend, gathered[k][:8])]
            log_scale = log_scale + W[k] * gathered[k][8]
        scale = jnp.exp(log_scale)
        return apply([[x * scale for x in V], blend], [])

    return coordinates


_blend_motors_and_apply = PerPlatform(
    "deform.skin_cga_motor_blend",
    cpu=functools.partial(_blend_motors_in_xla, cpu=True),
    gpu=_blend_motors_in_rows,
)


def matrices_to_dual_quaternions(
    matrices: Float[ArrayLike, "... 4 4"], tolerance: float = 1e-5
) -> Float[Array, "... 8"]:
    """Unit dual quaternions (real w, x, y, z; dual w, x, y, z) of rigid 4x4 matrices; a matrix with a
    scale or shear raises inside jit (DQS cannot represent a dilation, the paper's sec. 3).

    Args:
        matrices: (..., 4, 4) or (..., 3, 4) rigid matrices.
        tolerance: the largest entry of ``|R^T R - I|`` accepted, R the upper-left 3x3 block.
    Returns:
        (..., 8) unit dual quaternions."""
    matrices = jnp.asarray(matrices)
    if matrices.ndim < 2 or matrices.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"matrices: expected shape (..., 4, 4), got {matrices.shape}")
    rot = matrices[..., :3, :3]
    err = jnp.max(
        jnp.abs(
            jnp.matmul(jnp.swapaxes(rot, -1, -2), rot, precision=EXACT)
            - lift_rank(jnp.eye(3, dtype=rot.dtype), rot.ndim)
        ),
        initial=0.0,
    )
    rot = require(
        rot,
        (
            err > tolerance,
            "matrices: dual-quaternion skinning needs rigid joint transforms "
            "(no scale or shear); use skin_cga for dilations",
        ),
    )
    return cga.motor_to_dual_quaternion(cga.matrix_to_motor(matrices.at[..., :3, :3].set(rot)))


def skin_dqs(
    V: Float[ArrayLike, "n 3"],
    J: Int[ArrayLike, "n k"],
    W: Float[ArrayLike, "n k"],
    joint_dual_quaternions: Float[ArrayLike, "... j 8"],
) -> Float[Array, "... n 3"]:
    """Dual-quaternion skinning (Kavan et al. 2008): blend, normalize by the real part's norm, apply.

    Args:
        V: (n, 3) bind-pose positions.
        J: (n, k) int joint indices.
        W: (n, k) weights (rows sum to one).
        joint_dual_quaternions: (..., j, 8) unit dual quaternions of the joint transforms.
    Returns:
        (..., n, 3) skinned positions."""
    V, J, W = _check_mesh(V, J, W)
    dq = jnp.asarray(joint_dual_quaternions)
    if dq.ndim < 2 or dq.shape[-1] != 8:
        raise ValueError(f"joint_dual_quaternions: expected shape (..., j, 8), got {dq.shape}")
    return _blend_dual_quaternions(V, J, W, _materialize(dq))


@per_platform("deform.skin_dqs")
def _blend_dual_quaternions(V, J, W, d: Float[Array, "... j 8"], *, cpu: bool) -> Float[Array, "... n 3"]:
    b = _blend_joints(J, _aligned_weights(J, W, d[..., :4], None, cpu=cpu), d)
    w, x, y, z = (b[..., i] for i in range(4))
    dw, dx, dy, dz = (b[..., 4 + i] for i in range(4))
    inv = 1.0 / (w * w + x * x + y * y + z * z)
    vx, vy, vz = (lift_rank(V[:, i].astype(d.dtype), w.ndim) for i in range(3))
    # Rotation by the unnormalized real part and translation 2 q_d q_r^*, both divided by |q_r|^2;
    # written per component (no stacked temporaries) so that XLA fuses the whole vertex loop.
    out_x = (w * w + x * x - y * y - z * z) * vx + 2 * (x * y - w * z) * vy + 2 * (x * z + w * y) * vz
    out_y = 2 * (x * y + w * z) * vx + (w * w - x * x + y * y - z * z) * vy + 2 * (y * z - w * x) * vz
    out_z = 2 * (x * z - w * y) * vx + 2 * (y * z + w * x) * vy + (w * w - x * x - y * y + z * z) * vz
    t_x = 2 * (-dw * x + dx * w - dy * z + dz * y)
    t_y = 2 * (-dw * y + dx * z + dy * w - dz * x)
    t_z = 2 * (-dw * z - dx * y + dy * x + dz * w)
    return _coordinates_last([(out_x + t_x) * inv, (out_y + t_y) * inv, (out_z + t_z) * inv], cpu=cpu)
