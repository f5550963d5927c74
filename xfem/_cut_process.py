"""The cut worker process of ``xfem._background``: its start, requests and replies, its end.

Why a process. manifold3d's Booleans and libigl's queries hold the GIL for the whole of each call, and a cut is
mostly such calls and the Python between them: in a thread beside the steps it makes the steps' Python parts
(dispatch, host callbacks, the small systems' CHOLMOD call) wait for it. In a process it shares only the cores.

The child is started as ``python -c _CHILD_START``, not by ``multiprocessing``: its spawn start re-imports the
parent's ``__main__`` (a script without a main guard would run again), and a fork of a process running JAX
threads can deadlock. It keeps the parent's priority and CPUs (at the lowest priority it starved beside other
processes on a loaded machine and its cuts missed their commits: benchmarks/README.md, "XFEM: cuts in the
background"); it changes nothing in the parent, whose threads, priorities and settings are the user's. It runs
the entry point it was given, which talks over its stdin and a duplicate of its
stdout (``xfem._framing``; its own stdout and prints go to stderr). It exits when its stdin closes
(``CutProcess.close``, or the parent's exit).
"""

from __future__ import annotations

import os
import pickle
import subprocess
import sys

from xfem._framing import decode, encode, read_frame, write_frame

_CHILD_START = """
from {module} import {function}
{function}()
"""


class CutProcessError(RuntimeError):
    """The cut worker process exited or its replica disagrees with the model."""


class CutProcess:
    """The parent's end: start the child running ``entry`` and send it ``init``; then requests and their replies,
    in order (``send``, ``receive``; from one thread).

    Args:
        init: the first message (the child's entry reads it).
        entry: "module:function", the child's entry point; it answers ("ready", None) to ``init`` first, then
            ("ok", payload) or ("error", exception) to each request.
        env: environment variables for the child (added to a copy of this process's).
    """

    def __init__(self, init: dict, entry: str, env: dict[str, str] | None = None):
        module, function = entry.split(":")
        # the child's environment only (a copy): the replica builds host systems and must never take an
        # accelerator; it imports what the parent imports, from any directory
        env = {
            **os.environ,
            **(env or {}),
            "JAX_PLATFORMS": "cpu",
            "PYTHONPATH": os.pathsep.join(p for p in sys.path if p),
        }
        self._child = subprocess.Popen(
            [sys.executable, "-c", _CHILD_START.format(module=module, function=function)],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            env=env,
        )
        self._ready = False
        self.send(init)

    @property
    def pid(self) -> int:
        return self._child.pid

    def send(self, message) -> None:
        """Send a request. The child answers requests in order, one at a time."""
        encoded = encode(message)
        try:
            write_frame(self._child.stdin, *encoded)
        except (BrokenPipeError, OSError) as error:
            raise CutProcessError(
                f"the cut worker process exited (code {self._child.poll()}; see its stderr)"
            ) from error

    def receive(self):
        """The next reply (after the child's ready message); raises the error the child raised, if any."""
        self.wait_ready()
        return self._receive()

    def _receive(self):
        try:
            kind, payload = decode(*read_frame(self._child.stdout))  # waits for the whole reply, without the GIL
        except (EOFError, OSError, pickle.UnpicklingError) as error:
            raise CutProcessError(
                f"the cut worker process exited (code {self._child.poll()}; see its stderr)"
            ) from error
        if kind == "error":
            raise payload
        return payload

    def wait_ready(self) -> None:
        """Wait until the child has handled ``init`` (its first reply)."""
        if not self._ready:
            self._receive()
            self._ready = True

    def kill(self) -> None:
        """End the child at once (tests: a worker that dies)."""
        self._child.kill()
        self._child.wait()

    def close(self) -> None:
        """Close the child's stdin (it exits) and wait for it; kill it if it does not exit in 10 s."""
        if self._child.poll() is None:
            try:
                self._child.stdin.close()  # pyright: ignore[reportOptionalMemberAccess]  # Popen(stdin=PIPE)
            except OSError:
                pass
            try:
                self._child.wait(10)
            except subprocess.TimeoutExpired:
                self._child.kill()
                self._child.wait()
        for pipe in (self._child.stdin, self._child.stdout):
            try:
                pipe.close()  # pyright: ignore[reportOptionalMemberAccess]  # Popen(stdin=PIPE, stdout=PIPE)
            except OSError:
                pass


def child_streams():
    """In the child: (inbox, outbox), its requests' and replies' streams; from now on its prints and native writes
    to stdout go to stderr, never into the replies."""
    outbox = os.fdopen(os.dup(1), "wb")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    return sys.stdin.buffer, outbox
