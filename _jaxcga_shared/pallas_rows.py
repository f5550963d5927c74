"""Row-wise GPU kernels in Pallas (Triton): each program maps a block of rows of ``(n, k)`` inputs to the same rows of
an ``(n, m)`` output. Private to the distribution.

Why: for per-point data stored interleaved (``(n, 3)`` points, ``(n, 8)`` motors), XLA:GPU's loop emitter computes
each output coordinate in its own thread, re-reading the row and recomputing the shared products three times; a
Triton program loads a block of rows once and writes the block's coordinates together (benchmarks/README.md, "On a
GPU"). On the CPU the same kernel runs in Pallas' interpret mode, so that CI checks its arithmetic
(tests/shared_layer/test_platform_kernels.py); the choice is made when the computation is lowered.

Triton neither pads nor masks a block that runs past the array, so the last block's loads and stores are masked here.
"""

from __future__ import annotations

import functools
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton as pallas_triton
from jaxtyping import Array

# A program's rows and warps (Triton wants powers of 2): 2 rows a thread. At 8, ptxas (float64, sm_90) gave the
# point map and the skinning blend 255 registers and spills; at 2 every kernel here fits without spilling, and 2
# rows' loads are still enough in flight to cover memory latency.
ROWS_PER_PROGRAM = 256
WARPS = 4

# Triton's offsets here are 32-bit: larger arrays would wrap around.
MAX_ELEMENTS = 2**31 - 1


class SharedEntries:
    """A shared array inside a kernel: ``entries[c]`` is its c-th entry (a scalar, loaded on first use; a traced
    c, the index of a loop inside the kernel, loads on every use), and ``entries.gather(index)`` its entries at a
    block of per-row indices (a gather; the caller keeps the indices within the array: Triton does not check
    them)."""

    def __init__(self, ref, size: int):
        self._ref, self._size, self._loaded = ref, size, {}

    def __len__(self) -> int:
        return self._size

    def __getitem__(self, c: int | Array) -> Array:
        if not isinstance(c, int):
            return self._ref[c]
        if not 0 <= c < self._size:
            raise IndexError(f"entry {c} of a shared array of {self._size}")
        if c not in self._loaded:
            self._loaded[c] = self._ref[c]
        return self._loaded[c]

    def gather(self, index: Array) -> Array:
        return self._ref[index]


class RowColumns(Sequence):
    """A per-row array inside a kernel: ``columns[c]`` is its c-th column over the program's block of rows, loaded
    on first use (a traced c, the index of a loop inside the kernel, loads on every use). ``len`` and unpacking
    work as on a list."""

    def __init__(self, ref, width: int, inside: Array):
        self._ref, self._width, self._inside, self._loaded = ref, width, inside, {}

    def __len__(self) -> int:
        return self._width

    def __getitem__(self, c: int | Array) -> Array:
        if not isinstance(c, int):
            return self._load(c)
        if not 0 <= c < self._width:
            raise IndexError(f"column {c} of a per-row array of {self._width}")
        if c not in self._loaded:
            self._loaded[c] = self._load(c)
        return self._loaded[c]

    def _load(self, c) -> Array:
        # Columns are (rows, 1) blocks: a column indexed by a Python int does not reach Triton's masked load.
        # Masked rows read 1, not garbage, so that nothing in them overflows; their results are not stored.
        return pallas_triton.load(self._ref.at[:, pl.ds(c, 1)], mask=self._inside, other=1)

    def __iter__(self):
        return (self[c] for c in range(self._width))


# a row function takes the per-row arrays' columns (``RowColumns`` in a kernel, or lists of columns)
RowFunction = Callable[[Sequence[Sequence[Array]], list[SharedEntries]], list[Array]]


def rowwise(
    fn: RowFunction,
    per_row: Sequence[Array],
    shared: Sequence[Array],
    out_width: int,
    *,
    otherwise: Callable[..., Array] | None = None,
    rows_per_program: int = ROWS_PER_PROGRAM,
    warps: int = WARPS,
) -> Array:
    """``out[i] = fn(rows i of per_row, shared)`` for every row i, as one kernel.

    ``per_row``: arrays of shape ``(n, k_j)``, the same n; ``shared``: arrays of shape ``(k_j,)``, the same for
    every row. ``fn(row_columns, shared_columns)`` gets, for each ``per_row`` array, its k_j columns (each an
    array over a block of rows) and, for each ``shared`` array, its entries (``SharedEntries``: scalars by
    index, and gathers by per-row indices), and returns the ``out_width`` output columns, written elementwise
    (no reductions across rows). The output has the floating inputs' promoted dtype and shape
    ``(n, out_width)``.

    The platform is chosen when the computation is lowered: Triton on CUDA and ROCm GPUs, Pallas' interpret mode
    on the CPU (tests), and elsewhere (TPUs) ``otherwise(*per_row, *shared)``, the same computation without
    Pallas (default: interpret mode there too). With ``otherwise`` the result is differentiable in both modes:
    a Triton kernel has no transpose, so its JVP is ``otherwise``'s (``jax.custom_jvp``)."""
    if not per_row:
        raise ValueError("per_row: at least one per-row array is needed (it sets n)")
    n = per_row[0].shape[0]
    for j, a in enumerate(per_row):
        if a.ndim != 2 or a.shape[0] != n:
            raise ValueError(f"per_row[{j}]: expected shape ({n}, k), got {a.shape}")
    for j, a in enumerate(shared):
        if a.ndim != 1:
            raise ValueError(f"shared[{j}]: expected shape (k,), got {a.shape}")
    if not fits(*per_row, rows_per_program=rows_per_program):
        raise ValueError(f"per_row: arrays over {MAX_ELEMENTS} elements (with a block to spare) need 64-bit offsets")
    if rows_per_program & (rows_per_program - 1) or warps & (warps - 1):
        raise ValueError(f"rows_per_program, warps: Triton needs powers of 2, got {rows_per_program}, {warps}")
    # integer inputs (indices for gathers) do not decide the output's type
    floating = [a for a in (*per_row, *shared) if jnp.issubdtype(a.dtype, jnp.inexact)]
    dtype = jnp.result_type(*(floating or (*per_row, *shared)))
    out_shape = jax.ShapeDtypeStruct((n, out_width), dtype)
    if n == 0:
        return jnp.zeros(out_shape.shape, dtype)
    widths = [a.shape[1] for a in per_row], [a.shape[0] for a in shared]
    kernel = functools.partial(_kernel, fn, n, rows_per_program, widths, out_width)
    in_specs = [pl.BlockSpec((rows_per_program, a.shape[1]), lambda i: (i, 0)) for a in per_row] + [
        pl.BlockSpec((a.shape[0],), lambda i: (0,)) for a in shared
    ]
    call = functools.partial(
        pl.pallas_call,
        kernel,
        out_shape=out_shape,
        grid=(pl.cdiv(n, rows_per_program),),
        in_specs=in_specs,
        out_specs=pl.BlockSpec((rows_per_program, out_width), lambda i: (i, 0)),
        name=getattr(fn, "__name__", "rowwise"),
    )

    def on_gpu(*args):
        return call(compiler_params=pallas_triton.CompilerParams(num_warps=warps))(*args)

    def interpreted(*args):
        return call(interpret=True)(*args)

    def kernel_call(*args):
        return jax.lax.platform_dependent(
            *args, cpu=interpreted, cuda=on_gpu, rocm=on_gpu, default=otherwise or interpreted
        )

    if otherwise is None:
        return kernel_call(*per_row, *shared)
    differentiable = jax.custom_jvp(kernel_call)
    differentiable.defjvp(lambda primals, tangents: (kernel_call(*primals), jax.jvp(otherwise, primals, tangents)[1]))
    return differentiable(*per_row, *shared)


def fits(*per_row: Array, rows_per_program: int = ROWS_PER_PROGRAM) -> bool:
    """Whether ``rowwise`` takes these per-row arrays (rows along the leading axes, columns along the last): their
    offsets, a last partial block included, within 32 bits."""
    return all(a.size + rows_per_program * a.shape[-1] <= MAX_ELEMENTS for a in per_row)


def _kernel(fn, n, rows_per_program, widths, out_width, *refs):
    per_row_widths, shared_widths = widths
    per_row_refs = refs[: len(per_row_widths)]
    shared_refs = refs[len(per_row_widths) : len(per_row_widths) + len(shared_widths)]
    out_ref = refs[-1]
    rows = pl.program_id(0) * rows_per_program + jax.lax.broadcasted_iota(jnp.int32, (rows_per_program, 1), 0)
    inside = rows < n
    row_columns = [RowColumns(ref, k, inside) for ref, k in zip(per_row_refs, per_row_widths)]
    shared_columns = [SharedEntries(ref, k) for ref, k in zip(shared_refs, shared_widths)]
    outputs = fn(row_columns, shared_columns)
    if len(outputs) != out_width:
        raise ValueError(f"fn: returned {len(outputs)} columns, expected out_width={out_width}")
    for c, value in enumerate(outputs):
        value = jnp.broadcast_to(value, (rows_per_program, 1)).astype(out_ref.dtype)
        pallas_triton.store(out_ref.at[:, pl.ds(c, 1)], value, mask=inside)
