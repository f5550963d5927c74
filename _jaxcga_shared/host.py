"""Host machinery used by every package of the distribution: device transfers, the host call from compiled
code (built on JAX internals, pinned in pyproject.toml and checked by tests/shared_layer/test_jax_internals.py),
and silencing C libraries' output. Private to the distribution."""

from __future__ import annotations

import contextlib
import ctypes
import functools
import os
import sys

import jax
import jax._src.callback
import jax._src.dispatch
import jax.core
import jax.extend.core
import jax.interpreters.batching
import jax.interpreters.mlir
import jax.numpy as jnp
import numpy as np


def to_device(a, dtype=None) -> jax.Array:
    """A host array (or list) on the device, ``dtype`` if given. ``jax.device_put`` of a numpy array, not
    ``jnp.asarray``, which compiles a copy for every new shape (it adds up where shapes change per call)."""
    return jax.device_put(np.asarray(a, dtype))


def to_devices(*arrays, on_host: bool = False) -> tuple:
    """Host arrays on the device in one batched ``jax.device_put`` (about half the cost of one call each, a large
    part of building a small system); with ``on_host`` the numpy arrays, for data built for another process (the
    XFEM cut worker's systems), where a device copy would be made only to be read back."""
    if on_host:
        return tuple(np.asarray(a) for a in arrays)
    return tuple(jax.device_put([np.asarray(a) for a in arrays]))


# ---------------------------------------------------------------------------------------------------------
# host calls from compiled code

# ``jax.pure_callback`` (JAX 0.10) puts its callback's inputs on the CPU device before the call, and an input XLA
# hands over unaligned is copied there asynchronously, by XLA's intra-op thread pool. On a machine with one core
# (``taskset -c 0``, a one-CPU container) that pool has one thread, and it is the one running the callback when
# the callback follows a parallel op (a scatter-add, as the Newton system's assembly): reading the input waited
# for a copy that could never start, and the XFEM step hung for good (accordion scene; also a 20-line jit of a
# scatter and a callback). ``host_call`` hands the callback XLA's numpy arrays as they are: no device copy, no
# wait, and one copy less of every input (the accordion's Newton system is 16 MB).
_host_call_p = jax.extend.core.Primitive("jaxcga_host_call")
jax._src.dispatch.prim_requires_devices_during_lowering.add(_host_call_p)  # the lowering asks for the backend
_host_call_p.def_impl(functools.partial(jax._src.dispatch.apply_primitive, _host_call_p))


@_host_call_p.def_abstract_eval
def _host_call_abstract(*avals, fn, result):
    return result


def _host_call_lowering(ctx, *operands, fn, result):
    def call(*arrays):
        # the result's dtype as asked (emit_python_callback checks shapes and dtypes, with a clear error)
        return (np.asarray(fn(*arrays), result.dtype),)

    outputs, _, _ = jax._src.callback.emit_python_callback(
        ctx, call, None, list(operands), ctx.avals_in, ctx.avals_out, has_side_effect=False, returns_token=False
    )
    return outputs


jax.interpreters.mlir.register_lowering(_host_call_p, _host_call_lowering, cacheable=False)


def _host_call_batched(args, dims, *, fn, result):
    """vmap: one call per batch element, in order (``jax.lax.map``), as ``vmap_method="sequential"``."""
    size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)  # None: an unbatched argument
    args = [
        jnp.moveaxis(a, d, 0) if d is not None else jnp.broadcast_to(a, (size, *np.shape(a)))
        for a, d in zip(args, dims)
    ]
    return jax.lax.map(lambda xs: _host_call_p.bind(*xs, fn=fn, result=result), args), 0


jax.interpreters.batching.primitive_batchers[_host_call_p] = _host_call_batched


def host_call(fn, result: jax.ShapeDtypeStruct, *args):
    """``fn(*args)`` on the host from traced code, with numpy arrays, like ``jax.pure_callback`` (a pure function;
    vmap calls it once per batch element) but without its device copy of the inputs, which could hang a one-core
    machine (above). ``fn`` is a hashable callable (a module-level function, a ``functools.partial``); it returns
    an array of ``result``'s shape, cast to its dtype. Not differentiable (wrap it in a ``jax.custom_vjp``)."""
    args = [jnp.asarray(a) if isinstance(a, (jax.Array, jax.core.Tracer)) else np.asarray(a) for a in args]
    return _host_call_p.bind(*args, fn=fn, result=jax.core.ShapedArray(result.shape, result.dtype))


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
        # C's stdio buffers what it writes to a pipe (TetGen's printf): flush it while fd 1 is still /dev/null
        with contextlib.suppress(OSError, AttributeError):  # no C library to load by that name (Windows)
            ctypes.CDLL(None).fflush(None)
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
