"""Kernels whose fastest formulation differs between XLA:CPU and XLA:GPU (DESIGN.md: "choose per platform at
trace time and test both variants for equality on CPU"). Private to the distribution."""

from __future__ import annotations

import functools
from collections.abc import Callable

import jax

PLATFORM_KERNELS: dict[str, "PerPlatform"] = {}


class PerPlatform:
    """One kernel with a ``cpu`` and a ``gpu`` formulation of the same arithmetic, chosen by
    ``jax.lax.platform_dependent`` when the computation is lowered (so AOT lowering for another platform, and a
    function jitted once and run on each, both pick the right one). ``gpu`` also serves every platform other
    than the CPU. Both variants are reachable (``variants``) so that tests compare them on the CPU.

    Registered by ``name`` in ``PLATFORM_KERNELS``: tests/shared_layer/test_platform_kernels.py checks every
    registered kernel's variants against each other on the examples it registers."""

    def __init__(self, name: str, *, cpu: Callable, gpu: Callable, examples: Callable[[], list[tuple]]):
        if name in PLATFORM_KERNELS:
            raise ValueError(f"name: a platform kernel named {name!r} is already registered")
        self.name = name
        self.variants = {"cpu": cpu, "gpu": gpu}
        self.examples = examples  # () -> [args, ...]: inputs on which both variants must agree
        functools.update_wrapper(self, cpu)
        PLATFORM_KERNELS[name] = self

    def __call__(self, *args):
        return jax.lax.platform_dependent(*args, cpu=self.variants["cpu"], default=self.variants["gpu"])


def per_platform(name: str, *, gpu: Callable, examples: Callable[[], list[tuple]]):
    """Decorator: the decorated function is the CPU formulation, ``gpu`` the one for GPUs (and other
    accelerators); ``examples()`` returns argument tuples on which the two must agree (to rounding)."""

    def wrap(cpu: Callable) -> PerPlatform:
        return PerPlatform(name, cpu=cpu, gpu=gpu, examples=examples)

    return wrap
