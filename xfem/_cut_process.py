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
model's worker thread, which waits for the reply without the GIL, applies it (``XFEMModel._apply_remote``,
which first checks the replica's id counts against the model's). From then on the model makes every cut there.

Protocol: pickles over the child's stdin and a duplicate of its stdout (its own stdout and prints go to
stderr). The child is started as ``python -c "from xfem._cut_process import main; main()"``, not by
``multiprocessing``: its spawn start re-imports the parent's ``__main__`` (a script without a main guard would
run again), and a fork of a process running JAX threads can deadlock. The child exits when its stdin closes
(``CutProcess.close``, or the parent's exit). After an error the child exits too: its replica may hold part of
the failed cut, and the model starts a new one for its next cut.
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
import threading

import numpy as np

from xfem._subdomains import MeshSolid

_PROTOCOL = 5


class CutProcessError(RuntimeError):
    """The cut worker process exited or its replica disagrees with the model."""


class CutProcess:
    """The parent's end: start the child with a model's construction arguments and its past cuts; then one
    request and one reply at a time (``request``, from the model's worker thread)."""

    def __init__(self, init: dict):
        env = dict(os.environ)
        env["JAX_PLATFORMS"] = "cpu"  # the replica builds host systems only; never take an accelerator
        env["PYTHONPATH"] = os.pathsep.join(p for p in sys.path if p)  # the parent's imports, from any directory
        self._child = subprocess.Popen([sys.executable, "-c", "from xfem._cut_process import main; main()"],
                                       stdin=subprocess.PIPE, stdout=subprocess.PIPE, env=env)
        self._lock = threading.Lock()
        self._ready = False
        self._send(init)

    def _send(self, message) -> None:
        try:
            pickle.dump(message, self._child.stdin, protocol=_PROTOCOL)
            self._child.stdin.flush()
        except (BrokenPipeError, OSError) as error:
            raise CutProcessError(f"the cut worker process exited (code {self._child.poll()}; see its stderr)") \
                from error

    def _receive(self):
        try:
            kind, payload = pickle.load(self._child.stdout)  # the read waits without the GIL
        except (EOFError, OSError, pickle.UnpicklingError) as error:
            raise CutProcessError(f"the cut worker process exited (code {self._child.poll()}; see its stderr)") \
                from error
        if kind == "error":
            raise payload
        return payload

    def wait_ready(self) -> None:
        """Wait until the child has built its replica (the first reply)."""
        with self._lock:
            if not self._ready:
                self._receive()
                self._ready = True

    def request(self, message):
        """Send a request and return the child's reply; raises the error the child raised, if any."""
        self.wait_ready()
        with self._lock:
            self._send(message)
            return self._receive()

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
        pickle.dump((kind, payload), outbox, protocol=_PROTOCOL)
        outbox.flush()

    init = pickle.load(inbox)
    import jax

    jax.config.update("jax_enable_x64", init["x64"])
    from jaxcga._support import keep_on_host
    from xfem._xfem import replica_model

    keep_on_host()  # the systems it builds go to the parent, which puts them on its device

    try:
        model = replica_model(init)
    except BaseException as error:  # noqa: BLE001 (any failure goes back to the parent)
        reply("error", _portable(error))
        return
    reply("ready", None)
    while True:
        try:
            message = pickle.load(inbox)
        except EOFError:
            return
        try:
            reply("ok", model._replica_cut(*message))
        except BaseException as error:  # noqa: BLE001
            reply("error", _portable(error))
            return  # its bookkeeping may be partial: the parent starts a new replica


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

