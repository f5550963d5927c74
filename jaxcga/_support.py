"""Host-side helpers shared by the packages built on the kernel (deform, cutting, xfem); not algebra and
not part of jaxcga's public API."""

from __future__ import annotations

import contextlib
import os
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def to_device(a, dtype=None) -> jax.Array:
    """A host array (or list) on the device, ``dtype`` if given. ``jax.device_put`` of a numpy array, not
    ``jnp.asarray``, which compiles a copy for every new shape (it adds up where shapes change per call)."""
    return jax.device_put(np.asarray(a, dtype))


_HOST = {"only": False}


def keep_on_host() -> None:
    """Make ``to_devices`` return numpy arrays in this process from now on: for a process that builds host data
    for another one (the XFEM cut worker process), where a device copy would be made only to be read back."""
    _HOST["only"] = True


def to_devices(*arrays) -> tuple:
    """Host arrays on the device in one batched ``jax.device_put`` (half the cost of one call each: ~40 us per
    array instead of ~80 us, a large part of building a small system); numpy arrays after ``keep_on_host``."""
    if _HOST["only"]:
        return tuple(np.asarray(a) for a in arrays)
    return tuple(jax.device_put([np.asarray(a) for a in arrays]))


def require(x, *checks):
    """Value checks, pairs ``(bad, message)``: a ``ValueError`` on concrete input; inside jit or grad
    (traced flags) ``eqx.error_if`` on ``x``. Returns ``x`` (to be used, so the traced check is kept)."""
    for bad, message in checks:
        if isinstance(bad, jax.core.Tracer):
            x = eqx.error_if(jnp.asarray(x), jnp.any(bad), message)  # python scalars have nothing to thread on
        elif bool(jnp.any(bad)):
            raise ValueError(message)
    return x


@contextlib.contextmanager
def quiet_stdout():
    """Silence output written to file descriptor 1 by C code, e.g. TetGen (Python's sys.stdout is untouched)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        with open(os.devnull, "w") as devnull:
            os.dup2(devnull.fileno(), 1)
            yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
