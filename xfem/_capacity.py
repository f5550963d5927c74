"""Capacity levels and the compiled-step cache of ``XFEMModel.step``.

A cut changes the sizes of the system (DOFs, element pieces, mass entries, nonzeros), and a compiled step is
specialised to sizes. So the steps run the system padded to a capacity level: level 0 is ``_HEADROOM`` times the
uncut model's sizes (at least ``_FLOOR``), each level ``_GROWTH`` times the one below. A cut that stays within the
level reuses the compiled step; the step of the next level up is compiled in a background thread meanwhile, so that
the cut that moves the model there finds it ready. Compiled steps are kept by a ``CompiledSteps`` (keyed by capacity,
Newton iterations and the material's shapes) that the model owns, or that models of one mesh share.
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import NamedTuple

import numpy as np
from jaxtyping import Array, Float

from _jaxcga_shared.host import to_device
from xfem._assembly import CapacityError
from xfem._backward_euler import FEMSystem, State, SystemCapacity, compiled_step, fem_system
from xfem._material import Material

_HEADROOM = 1.25  # capacity level 0 over the uncut model's sizes: the first cuts stay in it
_GROWTH = 1.5  # capacity growth per level: few levels, each padding the system at most this much
# the smallest capacities (nodes, elements, mass entries, nonzeros): a small model's first cuts stay in level 0,
# and its padded step costs little (benchmarks/README.md, "XFEM: capacity levels")
_FLOOR = (128, 128, 1024, 9 * 1024)
# compiled steps a CompiledSteps keeps: a model uses its level and the next one up per set of step options, so a few
# levels and option sets stay compiled while an unbounded cache would keep every executable of a long session
_STEPS_KEPT = 8


class PaddedSystem(NamedTuple):
    """A system padded to capacity ``level``, made from ``arrays`` (the arguments of ``fem_system``,
    ``XFEMModel._system_arrays``) over n DOFs."""

    system: FEMSystem
    level: int
    arrays: tuple
    n: int


class Capacities:
    """The capacity levels of one model, from its uncut sizes.

    Args:
        base: the uncut model's (nodes, elements, mass entries, nonzeros).
    """

    def __init__(self, base: tuple[int, int, int, int]):
        self.base = tuple(int(b) for b in base)

    def capacity(self, level: int) -> SystemCapacity:
        scale = _HEADROOM * _GROWTH**level
        size = [max(f, int(np.ceil(b * scale))) for b, f in zip(self.base, _FLOOR)]
        # as many fixed rows as real nodes: padded fixed nodes cost next to nothing (the reduced system leaves
        # them out), so the fixed count, which cuts through a clamped face multiply, never forces a larger level
        fixed = size[0]
        nodes = size[0] + fixed
        # the padded free nodes' unit masses add a mass entry and a 3 x 3 block each
        return SystemCapacity(
            nodes=nodes, elements=size[1], mass_entries=size[2] + nodes, fixed=fixed, nonzeros=size[3] + 9 * nodes
        )

    def fits(self, level: int, arrays: tuple, n: int) -> bool:
        """Whether the system ``arrays`` over n DOFs fits ``level`` (its nonzeros aside)."""
        dofs, _, _, M, _, fixed = arrays
        capacity = self.capacity(level)
        return (
            n <= capacity.nodes - capacity.fixed
            and len(dofs) <= capacity.elements
            and M.nnz <= capacity.mass_entries - capacity.nodes
            and len(fixed) <= capacity.fixed
        )

    def smallest_level(self, arrays: tuple, n: int, level: int) -> int:
        """The smallest level from ``level`` up that holds the system (its nonzeros aside)."""
        while not self.fits(level, arrays, n):
            level += 1
        return level

    def pad(self, arrays: tuple, n: int, level: int) -> PaddedSystem:
        """The system ``arrays`` over n DOFs padded to the smallest level from ``level`` up that holds it."""
        level = self.smallest_level(arrays, n, level)
        while True:
            try:
                return PaddedSystem(fem_system(*arrays, capacity=self.capacity(level)), level, arrays, n)
            except CapacityError:  # more matrix nonzeros than the level holds
                level += 1

    def padded_bytes_at_least(self, arrays: tuple, n: int, level: int) -> int:
        """A lower bound of the padded system's size: its Hessian scatter map (32 int32 per element) at the
        smallest level that holds its elements, nodes and mass entries."""
        return 32 * 4 * self.capacity(self.smallest_level(arrays, n, level)).elements


class _Compilation:
    """A step compiled (or being compiled) for one capacity and set of options."""

    def __init__(self):
        self.step = None
        self.thread: threading.Thread | None = None  # the background thread building it, if any
        self.ready = threading.Event()  # set when a build has ended (step None: it failed)

    def build(
        self,
        arrays,
        capacity: SystemCapacity,
        h,
        material: Material,
        newton_iterations: int,
        system: FEMSystem | None = None,
    ):
        """Compile the step of ``system``, already padded to ``capacity``, or of ``arrays`` padded here."""
        try:
            if system is None:
                try:
                    system = fem_system(*arrays, capacity=capacity)
                except CapacityError:  # too small for this system's nonzeros: the model moves to a larger level
                    return
            zeros = to_device(np.zeros((capacity.nodes, 3)))  # only the state's shape matters
            self.step = compiled_step(system, State(zeros, zeros), h, material, newton_iterations)
        finally:
            self.ready.set()


class CompiledSteps:
    """The compiled steps of ``XFEMModel.step`` by capacity level and options, and the threads compiling the next
    level's step beside the steps. A model owns one (``xfem_model`` makes it, ``XFEMModel.close`` closes it);
    models of one mesh may share one (``xfem_model(..., steps=...)``): their steps then compile once. It keeps at
    most ``limit`` steps (the least recently used is dropped: each holds an executable and its padded system's
    buffers). ``close()`` waits for the compile threads and drops every step; a closed one compiles nothing more.
    A context manager: ``with CompiledSteps() as steps: ...`` closes it at the end.

    Args:
        limit: the steps kept at most, >= 1.
    """

    def __init__(self, limit: int = _STEPS_KEPT):
        if isinstance(limit, bool) or not isinstance(limit, int) or limit < 1:
            raise ValueError(f"limit: expected an int >= 1, got {limit!r}")
        self.limit = limit
        self._entries: OrderedDict[tuple, _Compilation] = OrderedDict()
        self._lock = threading.Lock()  # held briefly: a compilation in one thread must not stall another's lookups
        self._closed = False

    def __enter__(self) -> CompiledSteps:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """Whether ``close`` was called."""
        return self._closed

    def __len__(self) -> int:
        return len(self._entries)

    def wait(self) -> None:
        """Wait until every step compiling in a background thread (the next capacity level's) is ready: a
        compilation takes seconds of CPU beside the steps (a benchmark waits after its warm-up run, so that the
        warm-up's last compilation does not run into the timed frames)."""
        with self._lock:
            threads = [entry.thread for entry in self._entries.values() if entry.thread is not None]
        for thread in threads:
            thread.join()

    def close(self) -> None:
        """Wait for the compile threads, then drop every compiled step (idempotent)."""
        self._closed = True
        self.wait()
        with self._lock:
            self._entries.clear()

    def compiled(
        self,
        capacities: Capacities,
        padded: PaddedSystem,
        level: int,
        h: float | Float[Array, ""],
        material: Material,
        newton_iterations: int,
        background: bool,
    ) -> Callable | None:
        """The step compiled for capacity ``level`` (``compiled_step``): found here, or compiled now
        (``background=False``), or compiled in a background thread that the step needing it will wait for
        (``background=True``; returns None). ``padded``: the system it is for (a level above ``padded.level`` pads
        ``padded.arrays`` anew; nothing is compiled in the background for a level the system does not fit)."""
        if self._closed:
            raise ValueError("steps: the CompiledSteps (or the model owning them) is closed")
        capacity = capacities.capacity(level)
        key = (
            capacity,
            newton_iterations,
            np.shape(material.young),
            np.shape(material.poisson),
            material.damping is None,
        )
        system = padded.system if level == padded.level else None
        with self._lock:
            entry = self._entries.get(key)
            created = entry is None
            if created:
                if background and not capacities.fits(level, padded.arrays, padded.n):
                    return None
                entry = self._entries[key] = _Compilation()
                self._evict()
                if background:  # never run a step here: two steps' host callbacks at once can deadlock XLA
                    entry.thread = threading.Thread(
                        target=entry.build,
                        args=(padded.arrays, capacity, h, material, newton_iterations, system),
                        name="xfem-compile",
                    )
                    entry.thread.start()  # not a daemon: XLA must not be cut off at exit
            else:
                self._entries.move_to_end(key)
        if background:
            return None
        if created:
            entry.build(padded.arrays, capacity, h, material, newton_iterations, system)
        entry.ready.wait()
        if entry.step is None:  # its background build failed (e.g. too few nonzeros): build it here
            entry.build(padded.arrays, capacity, h, material, newton_iterations, system)
        return entry.step

    def _evict(self) -> None:
        """Drop the least recently used steps beyond ``limit`` (not one compiling in the background, nor the one
        just added; under the lock)."""
        for key in list(self._entries)[:-1]:
            if len(self._entries) <= self.limit:
                return
            entry = self._entries[key]
            if entry.thread is None or entry.ready.is_set():
                del self._entries[key]


def padded_state(state: State, n: int, nodes: int) -> State:
    """The state with zero rows for the padded DOF nodes, in host arrays: a compiled step takes numpy arrays at
    little cost, where a device copy of each costs more than a small body's step, and a JAX pad would compile
    anew for every size."""
    x, v = np.zeros((nodes, 3)), np.zeros((nodes, 3))
    x[:n], v[:n] = np.asarray(state.x), np.asarray(state.v)
    return State(x, v)
