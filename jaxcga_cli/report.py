"""What the command line tells its user on stderr: status lines around steps longer than about two seconds, a
progress bar whose rate and ETA leave out compilation, warnings and errors on one line each."""

from __future__ import annotations

import contextlib
import contextvars
import logging
import sys
import time
import warnings
from collections.abc import Iterator

_QUIET = contextvars.ContextVar("jaxcga_cli_quiet", default=False)


def say(command: str, text: str, always: bool = False) -> None:
    """``jaxcga COMMAND: TEXT`` on stderr (stdout keeps the command's one-line summary); inside ``quiet()`` only
    with ``always`` (warnings)."""
    if always or not _QUIET.get():
        print(f"jaxcga {command}: {text}", file=sys.stderr, flush=True)


@contextlib.contextmanager
def quiet() -> Iterator[None]:
    """Leave out the status lines and progress bars of the commands run inside (``jaxcga demo`` runs other
    commands' code and tells its own story); warnings and errors still print."""
    token = _QUIET.set(True)
    try:
        yield
    finally:
        _QUIET.reset(token)


@contextlib.contextmanager
def status(command: str, doing: str) -> Iterator[None]:
    """A status line ``jaxcga COMMAND: DOING ...`` before the block and ``DOING: done in X s`` after it (not after
    an error: the error line says what happened)."""
    say(command, f"{doing} ...")
    start = time.perf_counter()
    yield
    say(command, f"{doing}: done in {time.perf_counter() - start:.1f} s")


class StepProgress:
    """A progress bar over ``total`` steps of a compiled loop (at most ``total`` where the loop may stop early).
    The first step compiles: it runs under a status line, and the bar starts after it, so that its rate and ETA
    count step time only; with ``compiled`` (the loop was compiled ahead) the bar starts at once. Call
    ``step(**postfix)`` after each step (``postfix``: values shown after the bar, e.g. a residual) and ``close()``
    at the end (or use it as a context manager)."""

    def __init__(self, command: str, total: int, unit: str, desc: str, compiled: bool = False):
        self.command, self.total, self.unit, self.desc = command, total, unit, desc
        self.bar = None
        self.quiet = _QUIET.get()  # read here: step() runs on JAX's callback thread, outside this context
        self.start = time.perf_counter()
        if compiled:
            self.bar = self._bar(0)
        else:
            say(command, f"compiling (the first {unit} includes compilation) ...")

    def _bar(self, initial: int):
        from tqdm import tqdm

        return tqdm(
            total=self.total, initial=initial, desc=self.desc, unit=self.unit, file=sys.stderr, disable=self.quiet
        )

    def step(self, **postfix) -> None:
        if self.bar is None:
            if not self.quiet:
                say(self.command, f"first {self.unit} done in {time.perf_counter() - self.start:.1f} s")
            # initial=1: tqdm's rate counts the steps made since the bar started, the compiled ones
            self.bar = self._bar(1)
        else:
            self.bar.update(1)
        if postfix:
            self.bar.set_postfix(postfix, refresh=False)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()

    def __enter__(self) -> StepProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def error_line(error: BaseException) -> str:
    """The message of ``error`` on one line; for an error raised inside compiled code the check's own message,
    without the banner and the traceback around it."""
    from _jaxcga_shared.checks import compiled_error_message

    text = str(error).strip()
    return compiled_error_message(error) or (text.splitlines()[0] if text else type(error).__name__)


def error_message(error: BaseException) -> str:
    """The one line ``jaxcga CMD: error: ...`` reports: an OSError as ``FILE: reason``, else ``error_line``."""
    if isinstance(error, OSError) and error.strerror:
        files = [str(f) for f in (error.filename, error.filename2) if f is not None]
        return f"{' -> '.join(files)}: {error.strerror}" if files else error.strerror
    return error_line(error)


@contextlib.contextmanager
def one_line_reports(command: str) -> Iterator[None]:
    """Warnings (a mesh welded on load, ...) as one line each, and JAX's log of a failed host callback (the
    traceback of a failed check under ``jax.jit``) muted: that error reaches ``main`` and is printed on
    one line."""
    logger = logging.getLogger("jax._src.callback")
    disabled, logger.disabled = logger.disabled, True
    try:
        with warnings.catch_warnings():
            warnings.showwarning = lambda message, *_, **__: say(command, f"warning: {message}", always=True)
            yield
    finally:
        logger.disabled = disabled
