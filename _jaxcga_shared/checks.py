"""Argument and value checks shared by every package: a ``ValueError`` naming the argument on concrete input,
``eqx.error_if`` inside jit. Private to the distribution."""

from __future__ import annotations

import functools
import re

import equinox as eqx
import jax
import jax.numpy as jnp


def require(x, *checks):
    """Value checks, pairs ``(bad, message)``: a ``ValueError`` on concrete input; inside jit or grad
    (traced flags) ``eqx.error_if`` on ``x``. Returns ``x`` (to be used, so the traced check is kept)."""
    for bad, message in checks:
        if isinstance(bad, jax.core.Tracer):
            x = eqx.error_if(jnp.asarray(x), jnp.any(bad), message)  # python scalars have nothing to thread on
        elif bool(jnp.any(bad)):
            raise ValueError(message)
    return x


def compiled_error_message(error: BaseException) -> str | None:
    """The message of a check that failed inside compiled code (``eqx.error_if`` under ``eqx.filter_jit`` or
    ``jax.jit``, an exception in a host callback), without the banner and traceback around it; None for
    other errors."""
    text = str(error)
    found = re.search(r"EquinoxRuntimeError: (.+)", text)
    if found:
        return found.group(1).strip()
    if isinstance(error, jax.errors.JaxRuntimeError):
        raised = re.findall(r"^\w*(?:Error|Exception): (.+)$", text, re.MULTILINE)
        return raised[-1].strip() if raised else text.strip().splitlines()[0]
    return None


def plain_errors(fn):
    """``fn`` (a jitted public function) raising a plain ``ValueError`` with the check's message when a value
    check inside it fails on concrete input; under an outer trace nothing changes (its checks fail at run time)."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        try:
            return fn(*args, **kwargs)
        except eqx.EquinoxRuntimeError as error:
            raise ValueError(compiled_error_message(error)) from None

    return wrapper
