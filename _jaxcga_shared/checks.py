"""Argument and value checks shared by every package: a ``CheckError`` (a ``ValueError``) naming the argument on
concrete input, a runtime error carrying the same message inside jit, on every backend; and the host-side checks of
points, faces and index arrays that every package takes. Private to the distribution, but for ``CheckError``, which
``jaxcga`` exports."""

from __future__ import annotations

import dataclasses
import functools
import re
import threading
from collections.abc import Callable, Collection
from typing import TypeVar

import equinox as eqx
import jax
import jax.core
import jax.extend.core
import jax.numpy as jnp
import numpy as np
from jax.core import Tracer
from jax.typing import ArrayLike as JaxArrayLike
from jaxtyping import Array, Float
from numpy.typing import ArrayLike

from _jaxcga_shared.host import host_call

_T = TypeVar("_T")


class CheckError(ValueError):
    """A value check of a function's input failed; the message names the argument and says what is wrong with it.

    Raised on concrete input by the check itself, and by the functions that wait for their compiled result (the
    pose and batch functions of ``deform``) when the check failed inside it. Inside code compiled by the caller
    (``jax.jit``) a failed check surfaces as JAX's runtime error, whose text carries this error's message.
    A ``ValueError``: ``except ValueError`` catches it as before.
    """


CheckError.__module__ = "jaxcga"  # its public name, in tracebacks and the API reference

# ``eqx.error_if`` raises through ``jax.pure_callback``, whose host side puts its inputs on a CPU device: under
# ``JAX_PLATFORMS=cuda`` there is none, and a failing check raised "failed to find a local CPU device" instead of
# its message. A check here raises from a ``host_call`` (the backend's own callback, no CPU device) that runs
# only when the check fails. JAX hands only the callback error's text on (a GPU's with XLA's context after it), so
# the host side delimits the message in it: these markers recognise a failed check, and where its message ends.
_OPEN, _CLOSE = "<jaxcga check>", "</jaxcga check>"
_MARKED = re.compile(re.escape(_OPEN) + "(.*?)" + re.escape(_CLOSE), re.DOTALL)


@dataclasses.dataclass(frozen=True)
class _Fail:
    """The host side of failed checks: raise ``CheckError`` with the message of the first set flag, delimited
    (hashable, as ``host_call`` asks)."""

    messages: tuple[str, ...]

    def __call__(self, flags):
        message = self.messages[int(np.argmax(np.asarray(flags)))]
        raise CheckError(f"{_OPEN}{message}{_CLOSE}")


def failed_check_message(error: BaseException) -> str | None:
    """The message of the check whose failure inside compiled code raised ``error`` (a ``require`` under
    ``jax.jit`` or ``eqx.filter_jit``, raised by JAX as its runtime error); None when no check of this
    distribution failed there."""
    found = _MARKED.search(str(error))
    return None if found is None else found.group(1)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _checked(x, flags, messages):
    """``x``, or a runtime error with the message of the first set flag (``flags``: unbatched, one per message);
    the branch, and with it the host call, runs only then."""
    fail = lambda: host_call(_Fail(messages), jax.ShapeDtypeStruct(x.shape, x.dtype), flags)  # noqa: E731
    return jax.lax.cond(jnp.any(flags), fail, lambda: x)


@_checked.defjvp
def _checked_jvp(messages, primals, tangents):
    # the host call has no derivative: a check passes tangents through (as eqx.error_if does)
    x, flags = primals
    return _checked(x, flags, messages), tangents[0]


def require(x: _T, *checks: tuple[JaxArrayLike, str]) -> _T:
    """Value checks, pairs ``(bad, message)``: a ``CheckError`` on concrete input; inside jit, vmap or grad
    (traced flags) a runtime error with the message of the first failing check, raised when ``x`` is computed
    (under vmap when any batch element is bad). Returns ``x`` (to be used, so the traced checks are kept).

    The traced checks of one call are one conditional: on a GPU each conditional is a host round trip (its flag
    copied to the host, the GPU drained), so checks made together cost one."""
    flags, messages = [], []
    for bad, message in checks:
        if isinstance(bad, Tracer):
            # unvmap_any: one flag for a whole vmap batch, so the failing branch stays a branch (not a select)
            flags.append(eqx.internal.unvmap_any(jnp.any(bad)))
            messages.append(message)
        elif np.any(np.asarray(bad)):  # numpy: under a trace jnp would stage even a constant flag
            raise CheckError(message)
    if flags:
        collector = _collector()
        if collector is not None:
            collector.flags.append(jnp.stack(flags))
            collector.messages.extend(messages)
        else:
            x = _checked(jnp.asarray(x), jnp.stack(flags), tuple(messages))  # python scalars have nothing to thread on
    return x


def require_around(fn: Callable[[Array], Array], operand: Array, *checks: tuple[JaxArrayLike, str]) -> Array:
    """``fn(operand)`` with ``require``'s checks made where each platform pays least for them: on the CPU on
    ``operand`` before ``fn`` runs, elsewhere on ``fn``'s result. A GPU reads a check's flag on the host, so
    checked first it idles while the host launches the rest; on the CPU a conditional that returns a large result
    copies it (a per-call cost: 0.1-0.2 ms for 100k skinned vertices), and a small operand costs nothing.

    ``operand`` is a small array (a table of joints or key motors); the checks' flags are computed from it or
    before it. On concrete flags the ``CheckError`` comes at once, on every platform."""
    if not any(isinstance(bad, Tracer) for bad, _ in checks) or _collector() is not None:
        # concrete flags raise at once; collected flags cost no conditional, wherever they are made
        require(None, *checks)
        return fn(operand)
    # looked up at call time: the tests' --gpu-variants option replaces it to take the GPU branch on the CPU
    return jax.lax.platform_dependent(
        operand,
        cpu=lambda operand: fn(require(operand, *checks)),
        default=lambda operand: require(fn(operand), *checks),
    )


class _Collector:
    """The traced checks of one trace of a ``checked_jit`` function, returned as its outputs."""

    def __init__(self):
        self.trace = jax.extend.core.get_opaque_trace_state()
        self.flags: list[Array] = []
        self.messages: list[str] = []


# the collectors of the checked_jit functions being traced in this thread, innermost last: trace-time state only
# (each is pushed and popped around its own trace), as JAX keeps its own trace context
_tracing = threading.local()


def _collector() -> _Collector | None:
    """The innermost collecting trace, if it is the current one (a check inside a nested trace of it, a vmap, a
    loop body, a custom derivative's function, cannot leave that trace as an output: it stays a conditional)."""
    stack = getattr(_tracing, "collectors", None)
    if stack and stack[-1].trace == jax.extend.core.get_opaque_trace_state():
        return stack[-1]
    return None


def collect_checks(fn):
    """``fn`` returning ``(out, flags, messages)``: called in a trace (``jax.jit``, ``jax.export``), the value checks
    made at its top level (``require``, and the checks of the ``checked_jit`` entry points it calls there) are
    collected as ``flags``, a bool array (None: no check), with their messages, a static tuple, instead of host
    calls; the caller raises ``CheckError(messages[i])`` for the first set flag. Its program then holds no host
    callback: it can be exported and cached (the command line's ``jaxcga_cli.cache``)."""

    @functools.wraps(fn)
    def collecting(*args, **kwargs):
        collector = _Collector()
        stack = _tracing.__dict__.setdefault("collectors", [])
        stack.append(collector)
        try:
            out = fn(*args, **kwargs)
        finally:
            stack.pop()
        flags = jnp.concatenate(collector.flags) if collector.flags else None
        return out, flags, tuple(collector.messages)

    return collecting


def raise_collected(flags, messages: tuple[str, ...]) -> None:
    """``CheckError`` with the message of the first set flag of ``collect_checks``'s concrete ``flags``."""
    flags = np.asarray(flags)
    if flags.any():
        raise CheckError(messages[int(np.argmax(flags))])


def checked_jit(fn):
    """``eqx.filter_jit(fn)`` for a public entry point: called on concrete input, its value checks (``require``
    made directly in its trace or in the traces of the ``checked_jit`` functions it calls there) are outputs of the
    compiled function, not host callbacks, and a failed one raises ``CheckError`` once the result is ready; the
    executable then holds no host callback, which JAX's persistent compilation cache requires. Under the caller's
    own trace (jit, vmap, grad) it is ``eqx.filter_jit(fn)`` as it is, its checks ``require``'s. Checks made in
    nested traces of it (loop bodies, vmaps, plain jits) stay conditionals with a host call, which
    ``plain_errors`` also raises as ``CheckError``."""

    # the messages are static outputs: filter_jit returns them unchanged, from the trace of any call
    plain, collected = eqx.filter_jit(fn), eqx.filter_jit(collect_checks(fn))

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        outer = _collector()
        if outer is None and any(isinstance(leaf, Tracer) for leaf in jax.tree.leaves((args, kwargs))):
            return plain(*args, **kwargs)
        out, flags, messages = collected(*args, **kwargs)
        if flags is None:
            return out
        if outer is not None:  # called in a collecting trace: its flags join that trace's
            outer.flags.append(flags)
            outer.messages.extend(messages)
            return out
        if isinstance(flags, Tracer):
            # concrete arguments closed over in the caller's trace (jit of a lambda over a model): the flags are
            # that trace's values, so they are threaded through the result as require threads its checks
            leaves, tree = jax.tree.flatten(out)
            traced = [i for i, leaf in enumerate(leaves) if isinstance(leaf, Tracer)]
            if traced:  # nothing traced out: nothing to check, as for a require whose value goes unused
                leaves[traced[0]] = require(leaves[traced[0]], *((flags[k], m) for k, m in enumerate(messages)))
            return jax.tree.unflatten(tree, leaves)
        raise_collected(flags, messages)
        return out

    return plain_errors(wrapper)


def compiled_error_message(error: BaseException) -> str | None:
    """The message of a check that failed inside compiled code (``require`` under ``jax.jit`` or
    ``eqx.filter_jit``, ``eqx.error_if``, an exception in a host callback), without the banner, the traceback
    and XLA's context around it; None for other errors."""
    message = failed_check_message(error)
    if message is not None:
        return message
    text = str(error)
    found = re.search(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found.group(1).strip()
    if isinstance(error, jax.errors.JaxRuntimeError):
        raised = re.findall(r"^\w*(?:Error|Exception): (.+)$", text, re.MULTILINE)
        return raised[-1].strip() if raised else text.strip().splitlines()[0]
    return None


def plain_errors(fn):
    """``fn`` (a jitted public function) raising a ``CheckError`` with the check's message when a value check
    inside it (``require``, ``eqx.error_if``) fails on concrete input, on every backend (it waits for the result);
    other errors pass unchanged, and under an outer trace nothing changes (its checks fail at run time)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            out = fn(*args, **kwargs)
            if any(isinstance(leaf, Tracer) for leaf in jax.tree.leaves(out)):
                return out
            # a GPU runs compiled code asynchronously: a failed check surfaces when the result is ready
            return jax.block_until_ready(out)
        except (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError) as error:
            # JAX raises a callback's failure as a JaxRuntimeError, or a ValueError from a cached executable
            if isinstance(error, eqx.EquinoxRuntimeError):
                message = compiled_error_message(error)
            else:
                message = failed_check_message(error)
            if message is None:
                raise  # not a check inside the computation: an error of it or of its arguments
            raise CheckError(message) from None

    return wrapper


def check_index_range(name: str, indices: np.ndarray, n: int | None, what: str = "vertex") -> None:
    """A ValueError naming ``name`` when an integer array ``indices`` holds an index outside ``[0, n)`` (n None:
    only negative indices are refused); a JAX gather would clamp it silently."""
    if indices.size and (indices.min() < 0 or (n is not None and indices.max() >= n)):
        bound = "" if n is None else f", {n}"
        raise ValueError(f"{name}: {what} indices must lie in [0{bound}), got [{indices.min()}, {indices.max()}]")


def check_real(
    name: str, x: ArrayLike, shape: tuple[int | None, ...], what: str = "values", rows: str = "n"
) -> np.ndarray:
    """``x`` as a finite float64 host array of ``shape`` (None: any length, written ``rows`` in the message), or a
    ValueError naming ``name`` (``what`` says what the values are)."""
    x = np.asarray(x)
    if (
        x.ndim != len(shape)
        or any(s is not None and s != d for s, d in zip(shape, x.shape))
        or not (np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer))
    ):
        expected = ", ".join(rows if s is None else str(s) for s in shape)
        if len(shape) == 1:
            expected += ","
        raise ValueError(f"{name}: expected {what} of shape ({expected}), got {x.dtype} {x.shape}")
    x = x.astype(np.float64)
    if not np.all(np.isfinite(x)):
        raise ValueError(f"{name}: non-finite values (NaN or inf)")
    return x


def check_positive(name: str, x: ArrayLike, shapes: tuple[tuple[int, ...], ...] = ((),)) -> np.ndarray:
    """``x`` as a float64 host array of finite positive values whose shape is one of ``shapes`` (a density, a
    stiffness: per element or one for all), or a ValueError naming ``name``."""
    x = np.asarray(x)
    real = np.issubdtype(x.dtype, np.floating) or np.issubdtype(x.dtype, np.integer)
    if x.shape not in shapes or not real or not np.all(np.isfinite(x) & (x > 0)):
        expected = " or ".join(dict.fromkeys(str(shape) for shape in shapes))
        raise ValueError(f"{name}: expected finite positive values of shape {expected}, got {x.dtype} {x.shape}")
    return x.astype(np.float64)


def check_points(name: str, V: ArrayLike, *, min_count: int = 0, rows: str = "n") -> np.ndarray:
    """``V`` as a finite float64 (rows, 3) host array with at least ``min_count`` rows, or a ValueError naming
    ``name`` (``rows`` is the letter its message gives the row count)."""
    V = check_real(name, V, (None, 3), "finite positions", rows)
    if len(V) < min_count:
        raise ValueError(
            f"{name}: expected finite positions of shape ({rows}, 3), {rows} >= {min_count}, got {V.shape}"
        )
    return V


def check_faces(name: str, F: ArrayLike, n: int, *, min_count: int = 1) -> np.ndarray:
    """``F`` as an int64 (m, 3) host array of triangles with m >= ``min_count`` and vertex indices in
    ``[0, n)``, or a ValueError naming ``name``."""
    F = np.asarray(F)
    if F.ndim != 2 or F.shape[1] != 3 or len(F) < min_count or not np.issubdtype(F.dtype, np.integer):
        least = f", m >= {min_count}" if min_count else ""
        raise ValueError(f"{name}: expected integer faces of shape (m, 3){least}, got {F.dtype} {F.shape}")
    check_index_range(name, F, n)
    return F.astype(np.int64)


def check_triangle_mesh(
    V: ArrayLike,
    F: ArrayLike,
    *,
    names: tuple[str, str] = ("V", "F"),
    min_vertices: int = 0,
    min_faces: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """A triangle mesh as host arrays: (V finite float64 (n, 3), F int64 (m, 3) indexing V), or a ValueError
    naming the argument (``names``); ``min_faces=0`` accepts a mesh with no faces."""
    V = check_points(names[0], V, min_count=min_vertices)
    return V, check_faces(names[1], F, len(V), min_count=min_faces)


def check_vectors(
    name: str, x: jax.typing.ArrayLike, size: int = 3, *, rows: str | None = None
) -> Float[Array, "... size"]:
    """``x`` as a float JAX array of shape (..., size), or exactly (rows, size) when ``rows`` (the letter its
    message gives the row count) is given; a ValueError naming ``name`` otherwise. Traceable: shapes only."""
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    if rows is None and (x.ndim == 0 or x.shape[-1] != size):
        raise ValueError(f"{name}: expected an array of shape (..., {size}), got shape {x.shape}")
    if rows is not None and (x.ndim != 2 or x.shape[1] != size):
        raise ValueError(f"{name}: expected shape ({rows}, {size}), got {x.shape}")
    return x


def check_finite(name: str, x: jax.typing.ArrayLike) -> Array:
    """``x`` as a JAX array, or a ValueError when it holds NaN or infinity (inside jit a runtime error with the
    message)."""
    x = jnp.asarray(x)
    return require(x, non_finite(name, x))


def non_finite(name: str, x: jax.typing.ArrayLike) -> tuple[Array, str]:
    """``check_finite``'s check as a ``require`` pair, to be made with others in one call (one conditional)."""
    return ~jnp.all(jnp.isfinite(x)), f"{name}: non-finite values (NaN or inf)"


def check_choice(name: str, value: object, choices: Collection[object]) -> None:
    """A ValueError naming ``name`` when ``value`` is not one of ``choices`` (an option's enumeration)."""
    if value not in choices:
        raise ValueError(f"{name}: expected one of {choices}, got {value!r}")
