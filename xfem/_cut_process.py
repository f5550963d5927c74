"""The worker process that prepares ``XFEMModel.cut_async``'s cuts (Algorithm 1 lines 1-25 without the state).

Why a process. manifold3d's Booleans and libigl's queries hold the GIL for the whole of each call, and a cut is
mostly such calls and the Python between them. Run in a thread beside the steps, it made the steps' Python parts
(dispatch, host callbacks, the small systems' CHOLMOD call) wait for it. In a process it shares only the cores:
on 2 cores, against the thread, sticks' frames while cutting were ~20% faster (1.4-1.6 ms against 1.8-1.9 ms);
thin's and accordion's slowest cut-window frames were 1.28-1.95x and 1.71-2.86x the average frame, against
1.24-1.61x and 1.71x (one scene per process, the benchmark's set-up; single runs vary by +-0.5).

How. The process holds a replica of the model's rest-space bookkeeping (subdomains, piece integrals,
enrichment, DOF numbering), made from the mesh and the cuts the model had made before it started (replayed:
the model ran them on a Manifold rebuilt from the cut's float64 mesh, as the replica does, so both sides give the
same subdomain ids). For each cut it runs ``XFEMModel._prepare`` on the replica and sends back what changed
(``XFEMModel._replica_cut``): the new and retired subdomains with the new solids' triangle meshes, the touched
pieces' integrals and enrichment, the new DOF numbering and the new system (host arrays, ``keep_on_host``). The
model's worker thread waits for the reply without the GIL, sends the next pending cut (the child works on it
meanwhile) and applies the reply (``XFEMModel._apply_remote``, which first checks the replica's id counts against
the model's). Its GIL-bound pieces (pickling, unpickling, applying, the device copy of the system) take turns with
the steps (``xfem._xfem._Turns``). From then on the model makes every cut there. The child runs on one core at the
lowest priority (``_CHILD_START``), and on all the parent's cores for a ``cut`` (parallel Booleans, the parent
waiting); a model with short steps keeps the parent's threads off that core while its cuts are pending
(``reserve_worker_core``).

Protocol: each message is a pickle (protocol 5) whose arrays of 4 kB or more travel after it, out of band: the
lengths (8 bytes each), the pickle, the buffers; over the child's stdin and a duplicate of its stdout (its own
stdout and prints go to stderr). The reader reads the whole message without the GIL, each large buffer into an
array of its own aligned to 64 bytes: unpickling makes views of them instead of copies, and the device copy of a
reply's system aliases them (XLA's CPU client does so for aligned host arrays). On sticks, in the background run,
unpickling a reply went from ~0.45 to ~0.2 ms and the device copy from 0.6-0.8 to 0.3-0.5 ms (what is left is
``device_put``'s cost per array). Requests are answered in order. The child is started as ``python -c
_CHILD_START``, not by ``multiprocessing``: its spawn start re-imports the parent's ``__main__`` (a script without
a main guard would run again), and a fork of a process running JAX threads can deadlock. The child exits when its
stdin closes (``CutProcess.close``, or the parent's exit). After an error the child exits too: its replica may
hold part of the failed cut, and the model starts a new one for its next cut.
"""

from __future__ import annotations

import contextlib
import os
import pickle
import struct
import subprocess
import sys
import threading

import numpy as np

from xfem._subdomains import MeshSolid

_PROTOCOL = 5
_LENGTH = struct.Struct("<Q")
_OUT_OF_BAND = 4096  # buffers at least this large travel after the pickle (smaller ones: copying them costs less)
_ALIGN = 64  # XLA's CPU client aliases host arrays aligned to this, instead of copying them
_NO_TURN = contextlib.nullcontext()

# The child's first statements, before its imports start the thread pools of numpy's OpenBLAS, XLA and
# manifold3d's TBB, which size themselves by the CPU affinity. It takes one core, the last the parent may use
# (``XFEM_CUT_WORKER_CORE``; its pools run one thread each; a background cut is one thread's work anyway,
# ``parallel=False``), at the lowest priority. Measured on sticks (2 cores, latency 100), the slowest frame while
# cutting over the average frame: median 3.2 with neither, 2.2 with the core, 2.2-2.5 with both (15 runs each).
# Under Linux's EEVDF scheduler the priority does not keep the steps' threads from waiting behind the child on its
# core (``reserve_worker_core``): nice 19, SCHED_IDLE and a 0.1 ms slice alternated in 16 runs each gave medians
# 2.3, 2.1 and 2.5, all with runs of 4-12x; SCHED_IDLE on any core starved the child (median 9, its cuts late).
_CHILD_START = """
import os
if hasattr(os, "sched_setaffinity") and os.environ.get("XFEM_CUT_WORKER_CORE"):
    os.sched_setaffinity(0, {int(os.environ["XFEM_CUT_WORKER_CORE"])})
if hasattr(os, "nice"):
    os.nice(19)
from xfem._cut_process import main
main()
"""


class CutProcessError(RuntimeError):
    """The cut worker process exited or its replica disagrees with the model."""


class CutProcess:
    """The parent's end: start the child with a model's construction arguments and its past cuts; then requests
    and their replies, in order (``send``, ``receive``; from one thread, the model's worker thread)."""

    def __init__(self, init: dict):
        env = dict(os.environ)
        env["JAX_PLATFORMS"] = "cpu"  # the replica builds host systems only; never take an accelerator
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)  # the parent's imports, from any directory
        cores = parent_cores()
        if cores:
            env["XFEM_CUT_WORKER_CORE"] = str(worker_core(cores))
        self._child = subprocess.Popen([sys.executable, "-c", _CHILD_START], stdin=subprocess.PIPE,
                                       stdout=subprocess.PIPE, env=env)
        self._ready = False
        self.send({**init, "cores": cores})

    def send(self, message, turn: contextlib.AbstractContextManager | None = None) -> None:
        """Send a request. The child answers requests in order, one at a time; the model sends the next cut's
        request when a reply arrives, so that the child works on it while the model applies that reply.

        Args:
            turn: a context the pickling runs in (it holds the GIL: the model's steps wait for it instead of sharing
                the GIL with it, ``xfem._xfem._Turns``); the write runs outside.
        """
        with turn or _NO_TURN:
            encoded = _encode(message)
        try:
            _write_frame(self._child.stdin, *encoded)
        except (BrokenPipeError, OSError) as error:
            raise CutProcessError(f"the cut worker process exited (code {self._child.poll()}; see its stderr)") \
                from error

    def receive(self, turn: contextlib.AbstractContextManager | None = None):
        """The next reply (after the child's ready message); raises the error the child raised, if any.

        Args:
            turn: as ``send``, for the unpickling; the wait for the child and the read run outside.
        """
        self.wait_ready()
        return self._receive(turn)

    def _receive(self, turn: contextlib.AbstractContextManager | None = None):
        try:
            data, buffers = _read_frame(self._child.stdout)  # waits for the whole reply, without the GIL
            with turn or _NO_TURN:
                kind, payload = pickle.loads(data, buffers=buffers)
        except (EOFError, OSError, pickle.UnpicklingError) as error:
            raise CutProcessError(f"the cut worker process exited (code {self._child.poll()}; see its stderr)") \
                from error
        if kind == "error":
            raise payload
        return payload

    def wait_ready(self) -> None:
        """Wait until the child has built its replica (the first reply)."""
        if not self._ready:
            self._receive()
            self._ready = True

    def close(self) -> None:
        """Close the child's stdin (it exits) and wait for it; kill it if it does not exit in 10 s."""
        if self._child.poll() is None:
            try:
                self._child.stdin.close()
            except OSError:
                pass
            try:
                self._child.wait(10)
            except subprocess.TimeoutExpired:
                self._child.kill()
                self._child.wait()
        for pipe in (self._child.stdin, self._child.stdout):
            try:
                pipe.close()
            except OSError:
                pass


def _encode(message) -> tuple[bytes, list[memoryview]]:
    """A message's pickle and its out-of-band buffers (views of the message's arrays, not copies)."""
    buffers = []

    def out_of_band(buffer: pickle.PickleBuffer) -> bool:
        raw = buffer.raw()
        if raw.nbytes < _OUT_OF_BAND:
            return True  # in band
        buffers.append(raw)
        return False

    return pickle.dumps(message, protocol=_PROTOCOL, buffer_callback=out_of_band), buffers


def _write_frame(stream, data: bytes, buffers: list = ()) -> None:
    """One message: the number of buffers, the pickle's and the buffers' lengths, the pickle, the buffers."""
    lengths = [len(data), *(memoryview(b).nbytes for b in buffers)]
    stream.write(struct.pack(f"<{len(lengths) + 1}Q", len(buffers), *lengths))
    stream.write(data)
    for buffer in buffers:
        stream.write(buffer)
    stream.flush()


def _read_frame(stream) -> tuple[bytes, list[np.ndarray]]:
    """The next message's pickle and buffers, read whole (the blocking reads release the GIL), each buffer in a
    byte array of its own aligned to ``_ALIGN``; EOFError at the stream's end."""
    head = stream.read(_LENGTH.size)
    if not head:
        raise EOFError("the stream ended")
    count = _LENGTH.unpack(head + _read_exactly(stream, _LENGTH.size - len(head)))[0]
    lengths = struct.unpack(f"<{count + 1}Q", _read_exactly(stream, _LENGTH.size * (count + 1)))
    data = _read_exactly(stream, lengths[0])
    buffers = []
    for size in lengths[1:]:
        block = np.empty(size + _ALIGN, np.uint8)
        start = -block.ctypes.data % _ALIGN
        buffer = block[start:start + size]
        view, done = memoryview(buffer), 0
        while done < size:
            got = stream.readinto(view[done:])
            if not got:
                raise EOFError("the stream ended within a message")
            done += got
        buffers.append(buffer)
    return data, buffers


def _read_exactly(stream, size: int) -> bytes:
    data = stream.read(size)
    if len(data) < size:
        raise EOFError("the stream ended within a message")
    return data


def _portable(error: BaseException) -> BaseException:
    """The error itself if it pickles (ValueError and friends), else a RuntimeError with its text."""
    try:
        pickle.loads(pickle.dumps(error, protocol=_PROTOCOL))
        return error
    except Exception:
        return RuntimeError(f"{type(error).__name__}: {error}")


def _serve(inbox, outbox) -> None:
    """The child: build the replica, replay the past cuts, then answer cut requests until stdin closes."""

    def reply(kind, payload) -> None:
        _write_frame(outbox, *_encode((kind, payload)))

    def receive():
        data, buffers = _read_frame(inbox)
        return pickle.loads(data, buffers=buffers)

    init = receive()
    one_core, all_cores = _cores(), init["cores"]
    import jax

    jax.config.update("jax_enable_x64", init["x64"])
    from jaxcga._support import keep_on_host
    from xfem._xfem import replica_model

    keep_on_host()  # the systems it builds go to the parent, which puts them on its device

    try:
        _use_cores(all_cores)  # the replay runs the past cuts' parallel Booleans on the parent's cores
        model = replica_model(init)
        _use_cores(one_core)
    except BaseException as error:  # noqa: BLE001 (any failure goes back to the parent)
        reply("error", _portable(error))
        return
    reply("ready", None)
    while True:
        try:
            message = receive()
        except EOFError:
            return
        try:
            parallel = message[2] if isinstance(message, tuple) and len(message) > 2 else False
            _use_cores(all_cores if parallel else one_core)  # a cut's parallel Booleans: the parent waits for them
            reply("ok", model._replica_cut(*message))
        except BaseException as error:  # noqa: BLE001
            reply("error", _portable(error))
            return  # its bookkeeping may be partial: the parent starts a new replica


def worker_core(cores: set[int]) -> int:
    """The core the worker process runs on, of the parent's cores: the last."""
    return max(cores)


# While a model with short steps has background cuts pending, every thread of the parent process stays off the
# worker's core (``reserve_worker_core``). A step's thread that wakes behind the worker on its core can wait for the
# scheduler's next tick, whatever the worker's priority: Linux's EEVDF scheduler lets a task that is owed CPU time
# (as a low-priority task often preempted is) run out its slice (traced on sticks: the step's thread runnable for
# 3.4-5.4 ms behind the worker, the other core idle; 4 ms ticks). That is 2-4x a 1.5 ms frame. Alternated over
# 20 runs each (sticks, latency 100), the slowest frame while cutting over the average: median 2.16 without, 2.04
# with the reservation; runs above 3x: 8 without, 2 with. The average frame stayed (1.59 and 1.56 ms). Made before
# the worker thread wakes (``XFEMModel._submit``): made after, the step's thread was caught behind the child once.
_reservation: dict = {"count": 0, "saved": None, "cores": None}
_RESERVATION_LOCK = threading.Lock()


def parent_cores() -> set[int] | None:
    """The CPUs the parent's threads may use outside a reservation (None where the platform does not say)."""
    with _RESERVATION_LOCK:
        return set(_reservation["cores"]) if _reservation["cores"] is not None else _cores()


def reserve_worker_core(reserve: bool) -> None:
    """Count the models that keep the worker's core free: the first moves every thread of this process off it (if
    it has another core), the last moves each back to the CPUs it had (threads started meanwhile: to all the
    process's)."""
    with _RESERVATION_LOCK:
        _reservation["count"] += 1 if reserve else -1
        if reserve and _reservation["count"] == 1:
            cores = _cores()
            if cores is None or len(cores) < 2 or not os.path.isdir("/proc/self/task"):
                return
            worker = worker_core(cores)
            saved = _set_thread_cores(lambda thread, had: had - {worker} or had)
            _reservation.update(saved=saved, cores=cores)
        elif not reserve and _reservation["count"] == 0 and _reservation["saved"] is not None:
            saved, cores = _reservation["saved"], _reservation["cores"]
            _set_thread_cores(lambda thread, had: saved.get(thread, cores))
            _reservation.update(saved=None, cores=None)


def _set_thread_cores(cores_of) -> dict[int, set[int]]:
    """Give each thread of this process the CPUs ``cores_of(thread id, its CPUs)``; returns the CPUs each had. A
    thread that ends meanwhile is left out."""
    had = {}
    for thread in (int(t) for t in os.listdir("/proc/self/task")):
        try:
            had[thread] = os.sched_getaffinity(thread)
            os.sched_setaffinity(thread, cores_of(thread, had[thread]))
        except OSError:  # a thread that has just ended
            pass
    return had


def _cores() -> set[int] | None:
    """The CPUs this process may run on (None where the platform does not say)."""
    return set(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None


def _use_cores(cores: set[int] | None) -> None:
    """Let every thread of this process (the Boolean threads, the pools started so far) run on ``cores``."""
    if cores is None or not hasattr(os, "sched_setaffinity") or not os.path.isdir("/proc/self/task"):
        return
    _set_thread_cores(lambda thread, had: cores)


def main() -> None:
    """The child's entry point."""
    outbox = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)  # prints and native writes to stdout go to stderr, never into the protocol
    sys.stdout = sys.stderr
    _serve(sys.stdin.buffer, outbox)


def pack_meshes(meshes: list[MeshSolid]) -> tuple:
    """``MeshSolid``s as a few flat arrays (one pickle of thousands of small arrays holds the GIL for long)."""
    if not meshes:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), \
            np.zeros(0)
    return (np.concatenate([m.V for m in meshes]), np.concatenate([m.F for m in meshes]),
            np.array([len(m.V) for m in meshes]), np.array([len(m.F) for m in meshes]),
            np.array([m.tolerance for m in meshes], np.float64))


def unpack_meshes(packed: tuple) -> list[MeshSolid]:
    """``pack_meshes`` undone (views into the flat arrays)."""
    V, F, vertex_counts, face_counts, tolerances = packed
    vertex_ends, face_ends = np.cumsum(vertex_counts).tolist(), np.cumsum(face_counts).tolist()
    return [MeshSolid(V[v_end - nv:v_end], F[f_end - nf:f_end], tol) for v_end, nv, f_end, nf, tol in
            zip(vertex_ends, vertex_counts.tolist(), face_ends, face_counts.tolist(), tolerances.tolist())]

