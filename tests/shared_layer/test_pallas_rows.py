"""Row-wise Pallas kernels (``_jaxcga_shared.pallas_rows``): on the CPU the kernel runs in Pallas' interpret mode and
must equal the same arithmetic in jax.numpy, on partial last blocks, with per-row and shared inputs, in float64 and
float32 and under vmap; lowered for CUDA it is one Triton call. ``apply_to_points``' GPU variant, which uses it, is
checked against the CPU variant in test_platform_kernels.py, and so are the motor fields' (``deform.motor_field``)
and the motor blend skinning's (``deform.skin_cga_motor_blend``)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga as cga
from _jaxcga_shared.pallas_rows import rowwise
from _jaxcga_shared.platform import PLATFORM_KERNELS
from deform._motor_field import TRITON_MAX_KEYS
from jaxcga import _versors
from tests.shared import import_library

import_library()  # the kernels read from PLATFORM_KERNELS are registered when their modules load


def _affine_then_divide(row_columns, shared_columns):
    (a0, a1, a2), (b0, b1) = row_columns
    (s0, s1) = shared_columns[0]
    return [a0 * s0 + b0, a1 * b1 - s1, a2 / (1.0 + b1 * b1)]


def _expected(a, b, s):
    return jnp.stack([a[:, 0] * s[0] + b[:, 0], a[:, 1] * b[:, 1] - s[1], a[:, 2] / (1.0 + b[:, 1] ** 2)], axis=-1)


@pytest.mark.parametrize("n", [1, 7, 64, 65, 200])
@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_rows_equal_jax_numpy_on_partial_blocks(n, dtype):
    rng = np.random.default_rng(n)
    a, b = (jnp.asarray(rng.normal(size=(n, k)), dtype) for k in (3, 2))
    s = jnp.asarray([2.0, -0.5], dtype)
    got = jax.jit(lambda a, b, s: rowwise(_affine_then_divide, [a, b], [s], 3, rows_per_program=64))(a, b, s)
    assert got.shape == (n, 3) and got.dtype == dtype
    np.testing.assert_allclose(got, _expected(a, b, s), rtol=1e-14, atol=1e-6 if dtype == jnp.float32 else 1e-15)


def test_vmap_adds_a_grid_axis():
    rng = np.random.default_rng(0)
    a, b = jnp.asarray(rng.normal(size=(3, 100, 3))), jnp.asarray(rng.normal(size=(3, 100, 2)))
    s = jnp.asarray([1.5, 0.25])
    got = jax.vmap(lambda a, b: rowwise(_affine_then_divide, [a, b], [s], 3, rows_per_program=64))(a, b)
    np.testing.assert_allclose(got, jax.vmap(lambda a, b: _expected(a, b, s))(a, b), rtol=1e-14, atol=1e-15)


def test_no_rows():
    out = rowwise(_affine_then_divide, [jnp.zeros((0, 3)), jnp.zeros((0, 2))], [jnp.ones(2)], 3)
    assert out.shape == (0, 3)


def test_bad_arguments_are_named():
    a = jnp.zeros((4, 3))
    with pytest.raises(ValueError, match="per_row: at least one"):
        rowwise(_affine_then_divide, [], [jnp.ones(2)], 3)
    with pytest.raises(ValueError, match=r"per_row\[1\]: expected shape \(4, k\)"):
        rowwise(_affine_then_divide, [a, jnp.zeros((5, 2))], [jnp.ones(2)], 3)
    with pytest.raises(ValueError, match=r"shared\[0\]: expected shape \(k,\)"):
        rowwise(_affine_then_divide, [a, jnp.zeros((4, 2))], [jnp.ones((1, 2))], 3)
    with pytest.raises(ValueError, match="rows_per_program, warps: Triton needs powers of 2"):
        rowwise(_affine_then_divide, [a, jnp.zeros((4, 2))], [jnp.ones(2)], 3, rows_per_program=100)
    huge = jax.ShapeDtypeStruct((2**30, 4), jnp.float64)  # traced only: nothing is allocated
    with pytest.raises(ValueError, match="per_row: arrays over 2147483647 elements"):
        jax.eval_shape(lambda h: rowwise(_affine_then_divide, [h[:, :3], h[:, :2]], [jnp.ones(2)], 3), huge)
    with pytest.raises(ValueError, match="fn: returned 3 columns, expected out_width=2"):
        rowwise(_affine_then_divide, [a, jnp.zeros((4, 2))], [jnp.ones(2)], 2)


def _gather_rows(row_columns, shared_columns):
    """Per-row integer indices into a shared (4 x 3) table, flattened; the index column first."""
    ((index,), (a,)) = row_columns
    (table,) = shared_columns
    row = jnp.clip(index, 0, 3) * 3
    return [a * table.gather(row) + table.gather(row + 2), table[1] - table.gather(row + 1)]


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_gathers_from_a_shared_table_by_per_row_indices(dtype):
    rng = np.random.default_rng(8)
    index = jnp.asarray(rng.integers(-1, 5, size=(150, 1)), jnp.int32)  # out of range: clamped by the function
    a = jnp.asarray(rng.normal(size=(150, 1)), dtype)
    table = jnp.asarray(rng.normal(size=12), dtype)
    got = jax.jit(lambda i, a, t: rowwise(_gather_rows, [i, a], [t], 2, rows_per_program=64))(index, a, table)
    assert got.shape == (150, 2) and got.dtype == dtype  # the integer indices do not decide the output's type
    rows = np.asarray(table).reshape(4, 3)[np.clip(np.asarray(index[:, 0]), 0, 3)]
    expected = np.stack([np.asarray(a[:, 0]) * rows[:, 0] + rows[:, 2], float(table[1]) - rows[:, 1]], axis=-1)
    tolerance = 1e-6 if dtype == jnp.float32 else 1e-15
    np.testing.assert_allclose(got, expected, rtol=tolerance, atol=tolerance)
    text = _cuda_text(lambda i, a, t: rowwise(_gather_rows, [i, a], [t], 2), index, a, table)
    assert text.count("xla.gpu.triton") == 1


def _cuda_text(fn, *args):
    try:
        return jax.jit(fn).trace(*args).lower(lowering_platforms=("cuda",)).as_text()
    except Exception as error:  # noqa: BLE001 (any failure: this JAX cannot lower for CUDA without a GPU)
        pytest.skip(f"this JAX cannot lower for CUDA here: {error}")


def test_lowered_for_cuda_it_is_one_triton_call():
    """Lowering for CUDA runs the Pallas-to-Triton lowering (Triton's power-of-2 rule, supported operations) on the
    CPU; compiling and timing it need a GPU (benchmarks/gpu)."""
    a, b, s = jnp.zeros((1000, 3)), jnp.zeros((1000, 2)), jnp.ones(2)
    text = _cuda_text(lambda a, b, s: rowwise(_affine_then_divide, [a, b], [s], 3), a, b, s)
    assert text.count("xla.gpu.triton") == 1


@pytest.mark.parametrize("one_for_all", [False, True], ids=["one motor per point", "one motor for all"])
def test_apply_to_points_on_cuda_is_the_triton_kernel(one_for_all):
    """Stored versors, one per point or one for all, go through the Triton kernel; a broadcast between batch shapes
    stays with XLA."""
    rng = np.random.default_rng(3)
    motors = cga.exp_motor(cga.Multivector(rng.normal(size=(1 if one_for_all else 50, 6)), cga.MOTOR_GENERATOR))
    motors = motors[0] if one_for_all else motors
    x = jnp.asarray(rng.normal(size=(50, 3)))
    assert _cuda_text(cga.apply_to_points, motors, x).count("xla.gpu.triton") == 1
    rotors = cga.rotor(rng.normal(size=(4, 1, 3)), rng.normal(size=(4, 1)))
    assert "xla.gpu.triton" not in _cuda_text(cga.apply_to_points, rotors, x[:5])


@pytest.mark.parametrize("keys", [5, TRITON_MAX_KEYS + 1])
def test_motor_fields_on_cuda_are_one_triton_kernel_up_to_a_number_of_keys(keys):
    """The motor field's dispatch lowered for CUDA: blend, exponential and sandwich in one Triton call for a batch of
    poses up to ``TRITON_MAX_KEYS`` key motors, XLA's formulation beyond. (``motor_field_solve`` itself takes the
    key motors' logarithms behind a runtime check, which lowers for CUDA only where there is one.)"""
    rng = np.random.default_rng(6)
    weights, bound = jnp.asarray(rng.dirichlet(np.ones(keys), size=40)), jnp.asarray(rng.normal(size=(40, 3)))
    logs = jnp.asarray(rng.normal(size=(2, keys, 6)) * 0.3)
    text = _cuda_text(PLATFORM_KERNELS["deform.motor_field"], weights, bound, logs)
    assert text.count("xla.gpu.triton") == (1 if keys <= TRITON_MAX_KEYS else 0)


def test_motor_blend_skinning_on_cuda_is_one_triton_kernel():
    """``skin_cga_motor_blend``'s GPU variant lowered for CUDA: gathers, blend, scale and sandwich in one Triton call,
    for one pose and for a batch of poses (a grid axis), and so is its gradient's forward pass."""
    rng = np.random.default_rng(9)
    n, joints = 60, 5
    V, W = jnp.asarray(rng.normal(size=(n, 3))), jnp.asarray(rng.dirichlet(np.ones(3), size=n))
    J = jnp.asarray(rng.integers(0, joints, size=(n, 3)), jnp.int32)
    motors = cga.exp_motor(cga.Multivector(rng.normal(size=(2, joints, 6)), cga.MOTOR_GENERATOR)).values
    kernel = PLATFORM_KERNELS["deform.skin_cga_motor_blend"]
    tables = jnp.concatenate([motors, jnp.zeros(motors.shape[:-1] + (1,))], axis=-1)  # log scales 0
    for table in (tables[0], tables):
        assert _cuda_text(lambda t: kernel(V, J, W, t), table).count("xla.gpu.triton") == 1
    loss = jax.grad(lambda t: jnp.sum(kernel(V, J, W, t) ** 2))
    assert _cuda_text(loss, tables[0]).count("xla.gpu.triton") == 1


def test_apply_to_points_gpu_variant_forward_mode():
    """The Triton kernel has no transpose or JVP of its own: its custom JVP is XLA's formulation, so forward mode
    (here) and reverse mode (test_platform_kernels.py, vector-Jacobian products) equal the CPU variant's."""
    rng = np.random.default_rng(4)
    values = cga.exp_motor(cga.Multivector(rng.normal(size=(20, 6)), cga.MOTOR_GENERATOR)).values
    x = jnp.asarray(rng.normal(size=(20, 3)))
    tangents = (jnp.asarray(rng.normal(size=values.shape)), jnp.asarray(rng.normal(size=x.shape)))

    def jvp(variant):
        return jax.jit(
            lambda v, p, dv, dp: jax.jvp(lambda a, b: variant(cga.Multivector(a, "motor"), b), (v, p), (dv, dp))
        )

    gpu, cpu = (jvp(f)(values, x, *tangents) for f in (_versors._rows_of_points, _versors._component_major))
    for g, c in zip(gpu, cpu):
        np.testing.assert_allclose(g, c, rtol=1e-12, atol=1e-12)


def test_other_platforms_compute_without_pallas():
    """On platforms without Triton (TPUs) the kernel's ``otherwise`` runs: here, lowered for TPU, no Pallas call."""
    rng = np.random.default_rng(5)
    motors = cga.exp_motor(cga.Multivector(rng.normal(size=(30, 6)), cga.MOTOR_GENERATOR))
    x = jnp.asarray(rng.normal(size=(30, 3)))
    try:
        text = jax.jit(cga.apply_to_points).trace(motors, x).lower(lowering_platforms=("tpu",)).as_text()
    except Exception as error:  # noqa: BLE001 (any failure: this JAX cannot lower for TPU here)
        pytest.skip(f"this JAX cannot lower for TPU here: {error}")
    assert "tpu_custom_call" not in text and "triton" not in text
