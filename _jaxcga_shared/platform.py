"""Kernels whose fastest formulation differs between XLA:CPU and XLA:GPU (DESIGN.md: "choose per platform at
trace time and test both variants for equality on CPU"). Private to the distribution."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax

PLATFORM_KERNELS: dict[str, PerPlatform] = {}

# The precision of every matrix product in the library (``precision=EXACT``): on GPUs float32 products default to
# TF32 (10-bit mantissas: joint motors, rigidity checks and Hessians off by ~1e-3); float64 and the CPU are exact
# either way. tests/test_precision.py checks that no product is left to the default.
EXACT = jax.lax.Precision.HIGHEST


class PerPlatform:
    """One kernel with a ``cpu`` and a ``gpu`` formulation of the same arithmetic, chosen by
    ``jax.lax.platform_dependent`` when the computation is lowered (so AOT lowering for another platform, and a
    function jitted once and run on each, both pick the right one). ``gpu`` also serves every platform other
    than the CPU. Both variants are reachable (``variants``) so that tests compare them on the CPU.

    Call it with the array arguments (pytrees of arrays: the branches of the conditional) positionally and
    static options (Python values: shapes, kinds, flags) by keyword; the keywords are bound to both
    formulations before the choice. It passes through jit, vmap and grad as ``lax.switch`` does; called
    outside jit the platform is known at once and the formulation runs directly.

    Registered by ``name`` in ``PLATFORM_KERNELS``: tests/shared_layer/test_platform_kernels.py checks every
    registered kernel's variants against each other on the inputs it keeps under that name (and fails for a
    kernel it has none for), their vector-Jacobian products too where ``differentiated``, and in float32 where
    ``float32``."""

    def __init__(
        self,
        name: str,
        *,
        cpu: Callable,
        gpu: Callable,
        differentiated: bool = True,
        float32: bool = True,
    ):
        if name in PLATFORM_KERNELS:
            raise ValueError(f"name: a platform kernel named {name!r} is already registered")
        self.name = name
        self.variants = {"cpu": cpu, "gpu": gpu}
        self.differentiated = differentiated
        self.float32 = float32
        functools.update_wrapper(self, cpu, updated=())
        PLATFORM_KERNELS[name] = self

    def __call__(self, *args, **static):
        cpu, gpu = self.variants["cpu"], self.variants["gpu"]
        if static:
            cpu, gpu = functools.partial(cpu, **static), functools.partial(gpu, **static)
        return jax.lax.platform_dependent(*args, cpu=cpu, default=gpu)


def per_platform(
    name: str,
    *,
    gpu: Callable | None = None,
    differentiated: bool = True,
    float32: bool = True,
):
    """Decorator. With ``gpu``: the decorated function is the CPU formulation and ``gpu`` the one for GPUs
    (and other accelerators). Without: the decorated function takes a keyword-only ``cpu: bool`` and the
    variants are it with ``cpu=True`` and ``cpu=False`` (for formulations that differ in a few lines, such
    as barriers and layouts, written once). ``differentiated``, ``float32``: see ``PerPlatform``."""

    def wrap(fn: Callable) -> PerPlatform:
        if gpu is not None:
            return PerPlatform(name, cpu=fn, gpu=gpu, differentiated=differentiated, float32=float32)
        kernel = PerPlatform(
            name,
            cpu=functools.partial(fn, cpu=True),
            gpu=functools.partial(fn, cpu=False),
            differentiated=differentiated,
            float32=float32,
        )
        functools.update_wrapper(kernel, fn, updated=())
        return kernel

    return wrap
