"""Cuts in the background: ``BackgroundCuts(model)`` computes a model's cuts in a worker process while the model
steps; ``commit`` makes the finished ones take effect between two steps.

A cut's work (Booleans, integrals, enrichment, the new numbering and system) depends on the rest geometry and the
earlier cuts only, never on the state, so it can run while the model steps its current system. The worker process
(``xfem._cut_process``) holds a replica of the model (``replica_model``: the same mesh, the cuts made before it
started replayed); for each cut it runs ``XFEMModel.cut`` on the replica and sends back what changed
(``XFEMModel.delta``) with the new system padded to a capacity level. A thread of this process waits for the
replies, sends the next pending cut, puts each reply's system on the device and compiles its step. ``commit``
applies the replies to the model in order (``XFEMModel.apply_delta``): the DOFs are renumbered and their x and v
copied (Algorithm 1 line 7) from the state at that moment, and the next step runs the new system. The result
equals that of ``XFEMModel.cut`` called at the moment of the commit (to the rounding of manifold3d's Booleans,
which the worker runs one at a time, leaving the other cores to the steps).

Until its commit, a cut does not touch the model: its queries answer for the committed cuts. ``XFEMModel.cut`` may
be called while no cut is pending (the replica replays it before the next one); while cuts are pending it would
make the model disagree with the replica, and the next ``commit`` raises. A failed cut (or a worker that died)
raises at its commit, the cuts after it are dropped, and the next ``submit`` starts a new worker.
"""

from __future__ import annotations

import weakref
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor, wait

import jax
import manifold3d
import numpy as np

from _jaxcga_shared.host import to_devices
from xfem._backward_euler import CapacityError, State, host_fem_system
from xfem._cut_process import CutProcess, CutProcessError, child_streams
from xfem._framing import decode, encode, portable, read_frame, write_frame
from xfem._subdomains import CutReport, MeshSolid, check_cut, solid_mesh
from xfem._tetmesh import TetMesh
from xfem._xfem import XFEMModel

_ENTRY = "xfem._background:serve"  # the worker process's entry point
# the worker sends padded systems up to this size; a larger one is padded by this process's thread from the system
# arrays, keeping a huge model's system (and its copy in the worker) out of the pipe
_SENT_SYSTEM_BYTES = 256 << 20


class BackgroundCuts:
    """A model's cuts computed in a worker process while the model steps (module docstring).

    Args:
        model: the ``XFEMModel``.
    """

    def __init__(self, model: XFEMModel):
        if not isinstance(model, XFEMModel):
            raise ValueError(f"model: expected an XFEMModel, got {type(model).__name__}")
        self.model = model
        self._thread = ThreadPoolExecutor(1, thread_name_prefix="xfem-cut")
        self._process: CutProcess | None = None
        self._process_closer: weakref.finalize | None = None
        self._pending: deque[tuple[Future, dict]] = deque()  # submitted cuts, in order, with what they prepared
        self._unsent: deque[tuple] = deque()  # the pending cuts' requests not yet sent to the worker
        self._replica_cuts = 0  # the cuts the replica has made (replayed, sent)
        self._failed = False  # a cut failed: the ones after it are dropped until commit raises
        self._committed: weakref.WeakSet[Future] = weakref.WeakSet()

    @property
    def pending(self) -> int:
        """The submitted cuts not yet committed."""
        return len(self._pending)

    def start(self, wait: bool = True) -> None:
        """Start the worker process now (``submit`` starts it when needed; it takes a few seconds: the imports, the
        replica of the model, the replay of the cuts made so far). No-op while cuts are pending.

        Args:
            wait: return once it is ready (its errors, if any, raised here).
        """
        if self._pending:
            return
        log = tuple(self.model.cuts)
        future = self._thread.submit(lambda: self._sync(log).wait_ready())
        if wait:
            future.result()

    def submit(self, solid: manifold3d.Manifold, perturb: float = 0.0) -> Future:
        """Start a cut in the worker process; the model keeps stepping its current system until ``commit``.

        Args:
            solid: as ``XFEMModel.cut`` (checked now).
            perturb: see ``solid``.
        Returns:
            A ``concurrent.futures.Future`` of the cut's ``CutReport``, done when the cut is prepared; it takes
            effect at ``commit``.
        """
        check_cut(solid, perturb)
        # the model's cuts the replica has not seen (the cuts before it, or ``XFEMModel.cut`` since): replayed first
        log = None if self._pending else tuple(self.model.cuts)
        request = (solid_mesh(solid), float(perturb), False, True)
        prepared: dict = {}
        self._unsent.append(request)
        try:
            future = self._thread.submit(self._prepare, request, log, prepared)
        except BaseException:
            self._unsent.pop()
            raise
        self._pending.append((future, prepared))
        return future

    def commit(self, until: Future | None = None) -> list[CutReport]:
        """Make submitted cuts take effect, in order: wait for each and apply it to the model
        (``XFEMModel.apply_delta``: new DOFs, x and v copied from the current state, the new system).

        Args:
            until: a cut's future: commit it and the cuts submitted before it (later ones stay pending); nothing
                if it is committed already; None: all pending cuts.
        Returns:
            The committed cuts' ``CutReport``s, in order. A cut that failed raises its error here (the cuts after
            it are dropped: they were prepared on its partial bookkeeping).
        """
        if until is not None and all(future is not until for future, _ in self._pending):
            if until in self._committed:
                return []
            raise ValueError("until: expected a cut of this BackgroundCuts (a submit future)")
        reports = []
        while self._pending:
            future, prepared = self._pending.popleft()
            try:
                report = future.result()
                self.model.apply_delta(prepared["delta"], prepared["padded"])
            except BaseException:
                for later, _ in self._pending:
                    later.cancel()
                wait([later for later, _ in self._pending])  # one already running stops at once (``_failed``)
                self._pending.clear()
                self._unsent.clear()
                self._failed = False
                self._drop_process()  # its replica ran part of the failed cut, or disagrees with the model
                raise
            self._committed.add(future)
            reports.append(report)
            if future is until:
                break
        return reports

    def close(self) -> None:
        """Drop the pending cuts and stop the worker process (it also stops when this object is collected)."""
        for future, _ in self._pending:
            future.cancel()
        self._failed = True
        wait([future for future, _ in self._pending])
        self._pending.clear()
        self._unsent.clear()
        self._failed = False
        self._drop_process()
        self._thread.shutdown()

    # ---------------------------------------------------------------------------------------------------
    # the worker thread

    def _sync(self, log: tuple | None) -> CutProcess:
        """The worker process, started if there is none, with the model's cuts of ``log`` made in the replica
        (None: cuts were pending at the submit, the replica is in step)."""
        if self._process is None:
            if log is None:
                raise CutProcessError("the cut worker process was lost")
            model = self.model
            self._process = CutProcess(
                dict(
                    X=np.asarray(model.X),
                    T=np.asarray(model.T),
                    rho=model.rho,
                    gravity=model.gravity,
                    fixed=model.fixed_nodes,
                    log=list(log),
                    sent_system_bytes=_SENT_SYSTEM_BYTES,
                ),
                _ENTRY,
                # JAX defines its Config flags at run time
                {"JAX_ENABLE_X64": "1" if jax.config.jax_enable_x64 else "0"},  # pyright: ignore[reportAttributeAccessIssue]
            )
            self._process_closer = weakref.finalize(self, self._process.close)
            self._replica_cuts = len(log)
        elif log is not None:
            for cut, perturb, parallel in log[self._replica_cuts :]:
                self._process.send((cut, perturb, parallel, False))
                self._process.receive()
            self._replica_cuts = len(log)
        return self._process

    def _send(self, process: CutProcess, request: tuple) -> None:
        process.send(request)
        self._replica_cuts += 1

    def _prepare(self, request: tuple, log: tuple | None, prepared: dict) -> CutReport:
        """A cut made by the worker process: send it (unless it went with the last reply), wait for what it
        changed, send the next pending cut (the worker makes it meanwhile), and make the new system ready to step
        (``XFEMModel.prepare_step``); ``prepared`` gets the delta and the system."""
        if self._failed:
            raise CutProcessError("an earlier background cut failed: this one, prepared after it, was dropped")
        try:
            process = self._sync(log)
            if any(r is request for r in self._unsent):
                while self._unsent[0] is not request:  # requests of cuts cancelled after a failure
                    self._unsent.popleft()
                self._send(process, self._unsent.popleft())
            report, delta, (arrays, n, system, level) = process.receive()
            if self._unsent:
                try:
                    self._send(process, self._unsent.popleft())
                except CutProcessError:  # the child exited after its reply: that cut's receive raises it
                    pass
            if system is not None:
                system = jax.tree.unflatten(jax.tree.structure(system), to_devices(*jax.tree.leaves(system)))
            prepared["delta"] = delta
            prepared["padded"] = self.model.prepare_step(arrays, n, system, level)
        except BaseException:
            self._failed = True
            self._drop_process()
            raise
        return report

    def _drop_process(self) -> None:
        """Stop the worker process (a new one starts with the next submit, from the model's cuts)."""
        if self._process_closer is not None:
            self._process_closer()
        self._process = self._process_closer = None


# -------------------------------------------------------------------------------------------------------------
# the worker process


def replica_model(init: dict) -> XFEMModel:
    """The worker process's replica of a model: made from its construction arguments, then its past cuts
    replayed."""
    X = np.asarray(init["X"], np.float64)
    zeros = np.zeros_like(X)
    model = XFEMModel(
        TetMesh(X=X, T=np.asarray(init["T"], np.int64)),
        init["rho"],
        init["gravity"],
        init["fixed"],
        State(zeros, zeros),
    )
    model.replay(init["log"])
    return model


def replica_cut(model: XFEMModel, cut: MeshSolid, perturb: float, parallel: bool, delta: bool, sent_system_bytes: int):
    """A cut made on the replica, and what it changed.

    Returns:
        The ``CutReport``; None where ``delta`` is False (a replay), else the ``CutDelta`` and (arrays, n, system,
        level): the new system's arrays over n DOFs and, up to ``sent_system_bytes``, the system padded to
        capacity ``level`` in host arrays (else None: the model pads it).
    """
    mark = model.mark() if delta else None
    report = model.cut(cut, perturb, parallel)
    if not delta:
        return report, None, None
    arrays, n = model._system_arrays(), len(model.dof_sid)
    system, level = None, 0
    if model._capacities.padded_bytes_at_least(arrays, n, model._level) <= sent_system_bytes:
        system, level = _host_padded_system(model, arrays, n)
    return report, model.delta(mark), (arrays, n, system, level)  # pyright: ignore[reportArgumentType]  # marked: delta


def _host_padded_system(model: XFEMModel, arrays: tuple, n: int):
    """The system of ``arrays`` over n DOFs padded as ``XFEMModel.padded_system`` pads it (the smallest capacity
    level, not below the replica's last one, that holds it), in numpy arrays: the parent puts it on its device, so a
    device copy here would only be read back for the pipe. Returns (system, level)."""
    capacities = model._capacities
    level = capacities.smallest_level(arrays, n, model._level)
    while True:
        try:
            system = host_fem_system(*arrays, capacity=capacities.capacity(level), on_host=True)
            break
        except CapacityError:  # more matrix nonzeros than the level holds
            level += 1
    model._level = level  # as padded_system: the replica's levels only grow, as the parent's
    return system, level


def serve() -> None:
    """The worker process's entry point: build the replica, then answer cut requests until stdin closes. After an
    error it exits: its replica may hold part of the failed cut."""
    inbox, outbox = child_streams()

    def reply(kind, payload) -> None:
        write_frame(outbox, *encode((kind, payload)))

    init = decode(*read_frame(inbox))
    try:
        model = replica_model(init)
    except BaseException as error:  # noqa: BLE001 (any failure goes back to the parent)
        reply("error", portable(error))
        return
    reply("ready", None)
    with model:  # its Boolean threads end with the worker
        while True:
            try:
                message = decode(*read_frame(inbox))
            except EOFError:
                return
            try:
                reply("ok", replica_cut(model, *message, sent_system_bytes=init["sent_system_bytes"]))
            except BaseException as error:  # noqa: BLE001
                reply("error", portable(error))
                return
