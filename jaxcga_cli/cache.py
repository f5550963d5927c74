"""JAX's persistent compilation cache for the command line: a second run of a command loads what the first
compiled instead of compiling it again. The command line owns its process, so it may set JAX's global
configuration; the library never does (it leaves that choice to its caller)."""

from __future__ import annotations

import os
import sys
from pathlib import Path

NO_CACHE = "JAXCGA_NO_CACHE"  # set (to anything but "", "0" or "false"): compile afresh, write nothing
CACHE_DIR = "JAXCGA_CACHE_DIR"  # another directory for the cache than the user's cache directory


def directory() -> Path:
    """Where the cache lives: ``$JAXCGA_CACHE_DIR``, else ``jax`` in the user's cache directory (platformdirs:
    ``$XDG_CACHE_HOME/jaxcga`` or ``~/.cache/jaxcga`` on Linux, ``~/Library/Caches/jaxcga`` on macOS)."""
    chosen = os.environ.get(CACHE_DIR)
    if chosen:
        return Path(chosen).expanduser()
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("jaxcga")) / "jax"


def disabled_by_environment() -> bool:
    """Whether ``$JAXCGA_NO_CACHE`` turns the cache off."""
    return os.environ.get(NO_CACHE, "").strip().lower() not in ("", "0", "false", "no")


def help_text() -> str:
    """The paragraph of ``jaxcga --help`` about the cache."""
    return (
        f"compiled code is cached in {directory()} (JAX's persistent compilation cache; ${CACHE_DIR} moves it), "
        f"so that a command's second run skips most of its compilation; --no-cache or {NO_CACHE}=1 turns the "
        "cache off, and deleting the directory empties it"
    )


def enable(command: str, no_cache: bool) -> Path | None:
    """Turn JAX's persistent compilation cache on in ``directory()`` (before anything is compiled), unless
    ``no_cache``, ``$JAXCGA_NO_CACHE`` or the caller's own JAX cache configuration (``JAX_COMPILATION_CACHE_DIR``)
    decides otherwise. A directory that cannot be made or written costs one warning line, not the command.
    Returns the directory in use, or None."""
    import jax

    if no_cache or disabled_by_environment():
        return None
    configured = getattr(jax.config, "jax_compilation_cache_dir", None)
    if configured:  # the user configured JAX's cache: theirs to keep
        return Path(configured)
    path = directory()
    try:
        path.mkdir(parents=True, exist_ok=True)
        # a file written and removed: permissions, a read-only file system, a full disk all show here
        probe = path / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        reason = error.strerror or type(error).__name__
        print(
            f"jaxcga {command}: warning: the compilation cache {path} is not writable ({reason}); compiling "
            f"afresh (set {CACHE_DIR} elsewhere or {NO_CACHE}=1 to silence this)",
            file=sys.stderr,
        )
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # every executable: a command compiles many small ones (eager operations of the precomputations), which
    # together take seconds and read back in milliseconds
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    return path
