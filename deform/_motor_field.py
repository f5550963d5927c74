"""Motor fields: every vertex moved by its own blend of key motors, ``M_i = exp(sum_j w_ij log R_j)``.

The one operation shared by the deformation paper's methods: eq. (1)-(2) (spline-aligned deformation,
the weights are spline bases of a harmonic field), sec. IV (harmonic motor handles, the weights are one
harmonic field per handle), eq. (7)-(8) (motor FFD, the weights are tensor-product Bezier bases of the
lattice coordinates) and sec. VI (motor cages, the weights are harmonic coordinates).

Binding (sec. III-A): with rest key motors ``R^0`` the rest point is carried back once,
``p'_i = ~M^0_i p_i M^0_i``, and the deformed point is ``M_i p'_i ~M_i``; the rest key motors then give
back the rest mesh exactly. With identity rest motors (``rest_motors=None``) ``p' = p`` and the key
motors are motions of space: when every key motor is the same motor G the weights sum out
(``exp(log G) = G``) and the mesh moves rigidly by G, whatever the weights. The positional counterpart,
``blend_positions``, blends control points with the same weights (classic FFD, eq. 6; positional cages).

Speed: the logarithms are taken once per key motor. On the CPU the per-vertex blend is one dense product
``W (n, k) @ logs (k, 6)``, and the per-vertex exponential and sandwich are fused elementwise code
(``jaxcga.apply_to_points(..., fused=True)``). On a GPU blend, exponential and sandwich are one Triton program per
block of vertices (``_jaxcga_shared.pallas_rows``): one kernel, like the positional blend's one product, where XLA
launched a product and a fused loop and wrote the blended logarithms in between; chosen when the computation is
lowered (``_jaxcga_shared.platform``).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga
from _jaxcga_shared import pallas_rows
from _jaxcga_shared.checks import check_vectors, checked_jit, require_around
from _jaxcga_shared.platform import EXACT, PerPlatform
from jaxcga import KINDS, MOTOR_GENERATOR, Multivector
from jaxcga._exp_log import exp_motor_columns, log_motor_unchecked
from jaxcga._versors import row_coordinates

# Up to this many key motors a GPU's Triton program unrolls the blend over the weights' columns; more go through XLA.
TRITON_MAX_KEYS = 128


def _check_weights(weights, n: int | None = None):
    weights = jnp.asarray(weights)
    if weights.ndim != 2 or (n is not None and weights.shape[0] != n):
        expected = f"({n}, k)" if n is not None else "(n, k)"
        raise ValueError(f"weights: expected shape {expected}, got {weights.shape}")
    if not jnp.issubdtype(weights.dtype, jnp.floating):
        weights = weights.astype(jnp.result_type(float))
    return weights


def _check_key_motors(name: str, motors, k: int) -> Multivector:
    if not isinstance(motors, Multivector) or motors.batch_shape[-1:] != (k,):
        got = motors.batch_shape if isinstance(motors, Multivector) else type(motors).__name__
        raise ValueError(f"{name}: expected a motor Multivector with batch shape (..., {k}), got {got}")
    if not set(motors.blades) <= set(KINDS["motor"]):
        raise ValueError(f"{name}: expected motors (rotors, translators, motors), got blades {motors.names}")
    return motors.embed(KINDS["motor"])


def motor_logs(key_motors: Multivector) -> Float[Array, "... k 6"]:
    """The six bivector components of ``log R_j`` (e12, e13, e23, e1inf, e2inf, e3inf) per key motor.

    Args:
        key_motors: motors with batch shape (..., k).

    Returns:
        (..., k, 6) the logarithms' components.

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> import deform
        >>> (deform.motor_logs(cga.translator(jnp.array([[2.0, 0, 0]]))).round(6) + 0.0).tolist()  # -t einf / 2
        [[0.0, 0.0, 0.0, -1.0, 0.0, 0.0]]
    """
    if not isinstance(key_motors, Multivector) or not set(key_motors.blades) <= set(KINDS["motor"]):
        raise ValueError("key_motors: expected a motor Multivector")
    return cga.log_motor(key_motors.embed(KINDS["motor"])).embed(MOTOR_GENERATOR).values


def blend_motors(weights: Float[ArrayLike, "n k"], key_motors: Multivector) -> Multivector:
    """Per-vertex motors ``M_i = exp(sum_j w_ij log R_j)`` (eq. 1, 7), batch shape (..., n).

    Args:
        weights: (n, k) weights (rows usually sum to one).
        key_motors: motors with batch shape (..., k); leading axes are batches (poses).

    Returns:
        The per-vertex motors, batch shape (..., n).

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> import deform
        >>> keys = cga.translator(jnp.array([[0.0, 0, 0], [2.0, 0, 0]]))  # k = 2 key motors
        >>> M = deform.blend_motors(jnp.array([[1.0, 0.0], [0.5, 0.5]]), keys)  # n = 2 vertices
        >>> (cga.apply_to_points(M, jnp.zeros((2, 3))).round(6) + 0.0).tolist()
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]]
    """
    weights = _check_weights(weights)
    key_motors = _check_key_motors("key_motors", key_motors, weights.shape[1])
    return _blend(weights, motor_logs(key_motors).astype(weights.dtype))


def _blend(weights: Float[Array, "n k"], logs: Float[Array, "... k 6"]) -> Multivector:
    return cga.exp_motor(Multivector(jnp.einsum("nk,...kc->...nc", weights, logs, precision=EXACT), MOTOR_GENERATOR))


class MotorField(eqx.Module):
    """Vertices bound to key motors through per-vertex weights (sec. III-A binding): the data of every
    motor deformation (``motor_field_precompute``, ``spline_precompute``, ``handles_precompute``,
    ``ffd_precompute``, ``cage_precompute``), the argument of ``motor_field_solve``.

    Attributes:
        weights: (n, k) weight of key motor j at vertex i.
        bound: (n, 3) the rest positions carried back by the rest motors, ``~M^0_i p_i M^0_i``.
    """

    weights: Float[Array, "n k"]
    bound: Float[Array, "n 3"]

    @property
    def num_keys(self) -> int:
        return self.weights.shape[1]


@checked_jit
def motor_field_solve(field: MotorField, key_motors: Multivector) -> Float[Array, "... n 3"]:
    """Deformed positions ``M_i p'_i ~M_i`` (eq. 2), ``M_i = exp(sum_j w_ij log R_j)``.

    Compiled on first use (``eqx.filter_jit``); a key motor of non-positive norm raises ``CheckError`` when the
    result is ready (inside the caller's jit, JAX's runtime error with the same message).

    Args:
        field: a ``MotorField``.
        key_motors: motors with batch shape (..., k); leading batch axes lead the result (vmap-free
            batches of poses).
    Returns:
        (..., n, 3) positions."""
    if not isinstance(field, MotorField):
        raise ValueError(f"field: expected a MotorField, got {type(field).__name__}")
    weights = field.weights
    logs, bad = log_motor_unchecked(_check_key_motors("key_motors", key_motors, weights.shape[1]))
    bound = field.bound.astype(weights.dtype)
    # the check on the logarithms on the CPU, on the positions on a GPU (its host round trip waits only for them)
    return require_around(
        lambda logs: _deform(weights, bound, logs),
        logs.values.astype(weights.dtype),
        (bad, "key_motors: a key motor has non-positive norm M~M"),
    )


def _deform_in_rows(weights, bound, logs):
    """GPUs: blend, exponential and sandwich in one Triton program per block of vertices, for up to
    ``TRITON_MAX_KEYS`` key motors; batches of poses are a grid axis (vmap)."""
    if weights.shape[1] > TRITON_MAX_KEYS or not pallas_rows.fits(weights, bound) or weights.shape[0] == 0:
        return _deform_in_xla(weights, bound, logs)
    return _rows_deform(weights, bound, logs)


def _deform_in_xla(weights, bound, logs):
    """The CPU (and a GPU past ``TRITON_MAX_KEYS``): the blend as one dense product, then the exponential and the
    sandwich fused by XLA."""
    return cga.apply_to_points(_blend(weights, logs), bound, fused=True)


_deform = PerPlatform("deform.motor_field", cpu=_deform_in_xla, gpu=_deform_in_rows)


def _rows_deform(weights, bound, logs):
    keys = weights.shape[1]
    coordinates = _field_coordinates(keys)

    def one_pose(flat_logs):
        return pallas_rows.rowwise(
            coordinates,
            [bound, weights],
            [flat_logs],
            3,
            otherwise=lambda b, w, f: _deform_in_xla(w, b, f.reshape(keys, 6)),
        )

    deform_poses = one_pose
    for _ in logs.shape[:-2]:
        deform_poses = jax.vmap(deform_poses)
    return deform_poses(logs.reshape(logs.shape[:-2] + (keys * 6,)))


# Key motors summed in straight-line code in one Triton program, and past that many, per step of a loop.
_UNROLLED_KEYS = 16
_KEYS_PER_STEP = 8


@functools.cache
def _field_coordinates(keys: int) -> pallas_rows.RowFunction:
    """The ``rowwise`` function: rows of (bound, weights), the key motors' logarithms shared (``keys`` x 6)."""
    apply = row_coordinates(KINDS["motor"])

    def coordinates(row_columns, shared_columns):
        bound, weights = row_columns
        (logs,) = shared_columns

        def add_keys(first: int | Array, count: int, blended):
            for j in (first + t for t in range(count)):
                blended = [b + weights[j] * logs[6 * j + c] for c, b in enumerate(blended)]
            return blended

        # the same sums in the same order as the dense product; past _UNROLLED_KEYS a loop over groups of keys
        # bounds what is live: unrolled, the compiler loads every weight column first and spills registers
        blended = add_keys(1, min(keys, _UNROLLED_KEYS) - 1, [weights[0] * logs[c] for c in range(6)])
        if keys > _UNROLLED_KEYS:
            groups, rest = divmod(keys - _UNROLLED_KEYS, _KEYS_PER_STEP)
            step = lambda g, b: add_keys(_UNROLLED_KEYS + g * _KEYS_PER_STEP, _KEYS_PER_STEP, b)  # noqa: E731
            blended = jax.lax.fori_loop(0, groups, step, blended)
            blended = add_keys(keys - rest, rest, blended)
        return apply([bound, exp_motor_columns(blended, jnp.shape(blended[0]))], [])

    return coordinates


def motor_field_precompute(
    V: Float[ArrayLike, "n 3"], weights: Float[ArrayLike, "n k"], *, rest_motors: Multivector | None = None
) -> MotorField:
    """Bind rest positions to key motors (sec. III-A): ``p'_i = ~M^0_i p_i M^0_i`` with
    ``M^0_i = exp(sum_j w_ij log R^0_j)``; ``rest_motors=None`` means identity rest motors (p' = p).

    Args:
        V: (n, 3) rest positions.
        weights: (n, k) weights.
        rest_motors: None or motors with batch shape (k,).
    Returns:
        a ``MotorField``, the argument of ``motor_field_solve``.
    """
    V = check_vectors("V", V, rows="n")
    weights = _check_weights(weights, V.shape[0])
    V = V.astype(weights.dtype)
    if rest_motors is None:
        return MotorField(weights, V)
    rest_motors = _check_key_motors("rest_motors", rest_motors, weights.shape[1])
    if rest_motors.batch_shape != (weights.shape[1],):
        raise ValueError(f"rest_motors: expected batch shape ({weights.shape[1]},), got {rest_motors.batch_shape}")
    rest = blend_motors(weights, rest_motors)
    return MotorField(weights, cga.apply_to_points(cga.reverse(rest), V))


def identity_motors(k: int, dtype: DTypeLike = jnp.float64) -> Multivector:
    """k identity motors (batch shape (k,)).

    Args:
        k: the number of motors.
        dtype: their float dtype.

    Returns:
        The motors, batch shape (k,).

    Examples:
        >>> import deform
        >>> M = deform.identity_motors(3)
        >>> M.batch_shape, M.values[:, 0].tolist()
        ((3,), [1.0, 1.0, 1.0])
    """
    values = jnp.zeros((k, 8), dtype).at[:, 0].set(1.0)
    return Multivector(values, KINDS["motor"])


def motor_about(
    center: Float[ArrayLike, "... 3"], rotation: Multivector, translation: Float[ArrayLike, "... 3"] | None = None
) -> Multivector:
    """The motor that rotates by ``rotation`` about ``center`` (then translates by ``translation``):
    ``T_t T_c R T_-c``; the way to turn a lattice point, handle or cage vertex in place.

    Args:
        center: (..., 3) the centres of rotation.
        rotation: rotors, batch shape broadcasting with (...,).
        translation: (..., 3) translations applied after the rotation, or None.
    Returns:
        motors, batch shape (...,)."""
    center = jnp.asarray(center)
    shift = cga.translator(center)
    turn = (shift * rotation * cga.reverse(shift)).embed(KINDS["motor"])
    if translation is None:
        return turn
    return (cga.translator(jnp.asarray(translation, center.dtype)) * turn).embed(KINDS["motor"])


def blend_positions(weights: Float[ArrayLike, "n k"], P: Float[ArrayLike, "... k 3"]) -> Float[Array, "... n 3"]:
    """Positions ``p_i = sum_j w_ij P_j`` (classic FFD, eq. 6; the positional cage of sec. VI with harmonic
    coordinates); leading axes of the control points ``P`` are batches.

    Args:
        weights: (n, k) weights.
        P: (..., k, 3) control points.

    Returns:
        (..., n, 3) the blended positions.

    Examples:
        >>> import jax.numpy as jnp
        >>> import deform
        >>> deform.blend_positions(jnp.array([[0.5, 0.5]]), jnp.array([[0.0, 0, 0], [2.0, 0, 0]])).tolist()
        [[1.0, 0.0, 0.0]]
    """
    weights = jnp.asarray(weights)
    if weights.ndim != 2:
        raise ValueError(f"weights: expected shape (n, k), got {weights.shape}")
    P = jnp.asarray(P)
    if P.ndim < 2 or P.shape[-2:] != (weights.shape[1], 3):
        raise ValueError(f"P: expected shape (..., {weights.shape[1]}, 3), got {P.shape}")
    return jnp.einsum("nk,...kc->...nc", weights, P.astype(weights.dtype), precision=EXACT)
