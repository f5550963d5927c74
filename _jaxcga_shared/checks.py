"""Argument and value checks shared by every package: a ``ValueError`` naming the argument on concrete input, a
runtime error with the same message inside jit, on every backend. Private to the distribution."""

from __future__ import annotations

import dataclasses
import functools
import re
from typing import TypeVar

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
from jaxtyping import ArrayLike

from _jaxcga_shared.host import host_call

# ``eqx.error_if`` raises through ``jax.pure_callback``, whose host side puts its inputs on a CPU device: under
# ``JAX_PLATFORMS=cuda`` there is none, and a failing check raised "failed to find a local CPU device" instead of
# its message. A check here raises from a ``host_call`` (the backend's own callback, no CPU device) that runs
# only when the check fails; its message is kept here too, since a GPU's error text adds XLA's context to it.
_FAILED: dict[str, str | None] = {"message": None}

_T = TypeVar("_T")


@dataclasses.dataclass(frozen=True)
class _Fail:
    """The host side of a failed check: raise ``ValueError(message)`` (hashable, as ``host_call`` asks)."""

    message: str

    def __call__(self, flag):
        _FAILED["message"] = self.message
        raise ValueError(self.message)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2,))
def _checked(x, flag, message):
    """``x``, or a runtime error with ``message`` when ``flag`` (an unbatched scalar) is set; the branch, and
    with it the host call, runs only then."""
    fail = lambda: host_call(_Fail(message), jax.ShapeDtypeStruct(x.shape, x.dtype), flag)  # noqa: E731
    return jax.lax.cond(flag, fail, lambda: x)


@_checked.defjvp
def _checked_jvp(message, primals, tangents):
    # the host call has no derivative: a check passes tangents through (as eqx.error_if does)
    x, flag = primals
    return _checked(x, flag, message), tangents[0]


def require(x: _T, *checks: tuple[ArrayLike, str]) -> _T:
    """Value checks, pairs ``(bad, message)``: a ``ValueError`` on concrete input; inside jit, vmap or grad
    (traced flags) a runtime error with the message, raised when ``x`` is computed (under vmap when any batch
    element is bad). Returns ``x`` (to be used, so the traced check is kept)."""
    for bad, message in checks:
        if isinstance(bad, jax.core.Tracer):
            # unvmap_any: one flag for a whole vmap batch, so the failing branch stays a branch (not a select)
            flag = eqx.internal.unvmap_any(jnp.any(bad))
            x = _checked(jnp.asarray(x), flag, message)  # python scalars have nothing to thread on
        elif bool(jnp.any(bad)):
            raise ValueError(message)
    return x


def compiled_error_message(error: BaseException) -> str | None:
    """The message of a check that failed inside compiled code (``require`` under ``jax.jit`` or
    ``eqx.filter_jit``, ``eqx.error_if``, an exception in a host callback), without the banner, the traceback
    and XLA's context around it; None for other errors."""
    text = str(error)
    if _FAILED["message"] is not None and _FAILED["message"] in text:
        return _FAILED["message"]
    found = re.search(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found.group(1).strip()
    if isinstance(error, jax.errors.JaxRuntimeError):
        raised = re.findall(r"^\w*(?:Error|Exception): (.+)$", text, re.MULTILINE)
        return raised[-1].strip() if raised else text.strip().splitlines()[0]
    return None


def plain_errors(fn):
    """``fn`` (a jitted public function) raising a plain ``ValueError`` with the check's message when a value
    check inside it fails on concrete input, on every backend (it waits for the result); under an outer trace
    nothing changes (its checks fail at run time)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            out = fn(*args, **kwargs)
            if any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(out)):
                return out
            # a GPU runs compiled code asynchronously: a failed check surfaces when the result is ready
            return jax.block_until_ready(out)
        except (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError, ValueError) as error:
            # JAX raises a callback's failure as a JaxRuntimeError, or a ValueError from a cached executable
            message = compiled_error_message(error)
            if not isinstance(error, eqx.EquinoxRuntimeError) and message != _FAILED["message"]:
                raise  # not a check: an error of the computation itself, or of its arguments
            raise ValueError(message) from None

    return wrapper
