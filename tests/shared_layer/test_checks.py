"""``_jaxcga_shared.checks``: a value check raises its message eagerly (``ValueError``) and inside jit, vmap and
grad (a runtime error), the same on every backend this machine has (on a CPU machine only the CPU), and without a
CPU device (``JAX_PLATFORMS=cuda``), where ``eqx.error_if``'s ``jax.pure_callback`` finds none."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga
from _jaxcga_shared.checks import (
    checked_jit,
    compiled_error_message,
    failed_check_message,
    plain_errors,
    require,
    require_around,
)
from _jaxcga_shared.host import host_call

MESSAGE = "x: expected non-negative values"


def _backends():
    found = []
    for name in ("cpu", "gpu"):
        try:
            found.append(jax.devices(name)[0])
        except RuntimeError:  # no such backend here
            pass
    return found


BACKENDS = pytest.mark.parametrize("device", _backends(), ids=lambda d: d.platform)


def _doubled(x):
    return 2 * require(x, (x < 0, MESSAGE))


def _raises_the_message(fn, x):
    with pytest.raises(RuntimeError) as raised:
        jax.block_until_ready(fn(x))
    assert compiled_error_message(raised.value) == MESSAGE


@BACKENDS
def test_a_check_raises_its_message_eagerly_and_inside_jit_vmap_and_grad(device):
    good, bad = (jax.device_put(np.array(v), device) for v in ([0.0, 1.5], [1.0, -1.0]))
    with jax.default_device(device):
        with pytest.raises(jaxcga.CheckError, match=MESSAGE):
            _doubled(bad)
        for fn in (
            jax.jit(_doubled),
            eqx.filter_jit(_doubled),
            jax.jit(jax.vmap(_doubled)),
            jax.jit(jax.grad(lambda x: jnp.sum(jnp.sin(_doubled(x))))),
        ):
            _raises_the_message(fn, bad)
        # passing checks change nothing: values, a vmap batch, derivatives through the check
        np.testing.assert_array_equal(jax.jit(_doubled)(good), [0.0, 3.0])
        np.testing.assert_array_equal(jax.jit(jax.vmap(_doubled))(jnp.stack([good, good + 1])), [[0, 3], [2, 5]])
        np.testing.assert_allclose(
            jax.jit(jax.grad(lambda x: jnp.sum(jnp.sin(_doubled(x)))))(good), 2 * np.cos(2 * np.array([0.0, 1.5]))
        )


@BACKENDS
def test_under_vmap_one_bad_element_fails_the_batch(device):
    batch = jax.device_put(np.array([[1.0, 2.0], [3.0, -4.0], [5.0, 6.0]]), device)
    with jax.default_device(device):
        _raises_the_message(jax.jit(jax.vmap(_doubled)), batch)


@BACKENDS
def test_plain_errors_turns_a_failed_check_into_a_value_error_and_leaves_other_errors(device):
    good, bad = (jax.device_put(np.array([v]), device) for v in (1.0, -1.0))
    with jax.default_device(device):
        for jit in (eqx.filter_jit, jax.jit):
            doubled = plain_errors(jit(_doubled))
            np.testing.assert_array_equal(doubled(good), [2.0])
            for _ in range(2):  # JAX raises a JaxRuntimeError, and a ValueError from the cached executable
                with pytest.raises(jaxcga.CheckError, match=f"^{MESSAGE}$"):
                    doubled(bad)
    with pytest.raises(TypeError):  # not a check: as it was
        plain_errors(jax.jit(_doubled))("not an array")


def _same_text_raised(x):
    raise ValueError(MESSAGE)


@pytest.mark.parametrize("jit", [jax.jit, eqx.filter_jit], ids=["jit", "filter_jit"])
def test_a_failed_check_is_recognised_by_its_type_not_its_text(jit):
    """A failed check is a ``CheckError`` (a ``ValueError``); an error raised inside compiled code with a check's
    very text, after that check failed, is not one: ``plain_errors`` passes it on as it came."""
    assert issubclass(jaxcga.CheckError, ValueError)
    bad = np.array([-1.0])
    with pytest.raises(jaxcga.CheckError, match=f"^{MESSAGE}$"):
        plain_errors(jit(_doubled))(bad)

    def not_a_check(x):
        return host_call(_same_text_raised, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    with pytest.raises((RuntimeError, ValueError)) as raised:
        plain_errors(jit(not_a_check))(bad)
    assert not isinstance(raised.value, jaxcga.CheckError)
    assert failed_check_message(raised.value) is None
    assert MESSAGE in str(raised.value) and str(raised.value) != MESSAGE  # JAX's error, with the traceback


def test_the_message_of_a_failed_check_is_read_up_to_its_end():
    """A GPU's error text goes on after the callback's error (XLA's context on the same line); a message may span
    lines."""
    with pytest.raises(RuntimeError) as raised:
        jax.block_until_ready(jax.jit(_doubled)(np.array([-1.0])))
    text = str(raised.value)
    assert failed_check_message(RuntimeError(text + "; current tracing scope: custom-call.3")) == MESSAGE
    two_lines = "x: bad\nsee the docs"

    def checked(x):
        return require(x, (x < 0, two_lines))

    with pytest.raises(RuntimeError) as raised:
        jax.block_until_ready(jax.jit(checked)(np.array([-1.0])))
    assert failed_check_message(RuntimeError(f"{raised.value}; more context")) == two_lines
    assert failed_check_message(RuntimeError("INTERNAL: ValueError: x: bad")) is None


def test_a_check_needs_no_cpu_device(monkeypatch):
    """As under ``JAX_PLATFORMS=cuda``: asked for a CPU device, JAX finds none. ``eqx.error_if`` (through
    ``jax.pure_callback``) then loses its message; ``require`` does not."""
    import jax._src.xla_bridge as xla_bridge

    local_devices = xla_bridge.local_devices

    def no_cpu(*args, backend=None, **kwargs):
        if backend == "cpu":
            raise RuntimeError("Unknown backend cpu")
        return local_devices(*args, backend=backend, **kwargs)

    monkeypatch.setattr(xla_bridge, "local_devices", no_cpu)
    bad = np.array([1.0, -1.0])
    _raises_the_message(jax.jit(_doubled), bad)
    with pytest.raises(RuntimeError, match="failed to find a local CPU device"):
        jax.block_until_ready(jax.jit(lambda x: eqx.error_if(x, x < 0, MESSAGE))(bad))


def test_plain_errors_keeps_an_argument_error_raised_before_any_check_failed():
    """An argument check that raises a plain ValueError before tracing keeps its message, also when no value check
    has failed yet in the process (a fresh interpreter: the first error of its run)."""
    import subprocess
    import sys

    script = (
        "import jax\n"
        "from _jaxcga_shared.checks import plain_errors\n"
        "def f(x, kind):\n"
        "    if kind != 'a':\n"
        "        raise ValueError('kind: expected one of (\\'a\\',)')\n"
        "    return x\n"
        "try:\n"
        "    plain_errors(jax.jit(f, static_argnums=1))(1.0, 'b')\n"
        "except ValueError as error:\n"
        "    print(error)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.strip() == "kind: expected one of ('a',)"


def test_the_checks_of_one_call_are_one_conditional_raising_the_first_failing_message():
    """A GPU makes a host round trip per conditional: ``require``'s traced checks together are one, and a
    failure names the first failing check."""

    def checked(x):
        return require(x, (jnp.isnan(x), "x: NaN"), (x < 0, "x: negative"), (x > 10, "x: over 10"))

    text = jax.jit(checked).lower(jnp.ones(3)).as_text()
    assert text.count("stablehlo.case") == 1
    np.testing.assert_array_equal(jax.jit(checked)(jnp.array([1.0, 2.0])), [1.0, 2.0])
    for x, message in (([1.0, -1.0, 11.0], "x: negative"), ([11.0], "x: over 10"), ([np.nan, -1.0], "x: NaN")):
        # a cached executable's callback failure comes as a ValueError, a first call's as a JaxRuntimeError
        with pytest.raises((RuntimeError, ValueError)) as raised:
            jax.block_until_ready(jax.jit(checked)(jnp.array(x)))
        assert compiled_error_message(raised.value) == message
    with pytest.raises(ValueError, match="x: over 10"):
        checked(jnp.array([11.0]))


@pytest.mark.parametrize("variant", ["cpu", "gpu"])
def test_require_around_checks_in_either_placement_and_passes_values_and_derivatives(variant, monkeypatch):
    """``require_around`` on the CPU checks its operand first and elsewhere the result: each placement, taken on the
    CPU, raises the message eagerly and inside jit, vmap and grad, and passing checks change nothing."""
    platform_dependent = jax.lax.platform_dependent

    def one_placement(*operands, cpu, default):
        chosen = cpu if variant == "cpu" else default
        return platform_dependent(*operands, cpu=chosen, default=chosen)

    monkeypatch.setattr(jax.lax, "platform_dependent", one_placement)
    weights = jnp.linspace(0.0, 1.0, 1_000)

    def spread(table):  # a small operand to a large result, as a joints' table to skinned vertices
        return require_around(lambda t: weights[:, None] * t[None], table, (table < 0, MESSAGE))

    good, bad = np.array([0.0, 1.5]), np.array([1.0, -1.0])
    with pytest.raises(ValueError, match=MESSAGE):
        spread(bad)
    for fn, x in (
        (jax.jit(spread), bad),
        (jax.jit(jax.vmap(spread)), np.stack([good, bad])),
        (jax.jit(jax.grad(lambda t: jnp.sum(jnp.sin(spread(t))))), bad),
    ):
        with pytest.raises((RuntimeError, ValueError)) as raised:  # a cached executable's failure: a ValueError
            jax.block_until_ready(fn(x))
        assert compiled_error_message(raised.value) == MESSAGE
    np.testing.assert_array_equal(jax.jit(spread)(good), weights[:, None] * good[None])
    np.testing.assert_array_equal(
        jax.jit(jax.vmap(spread))(np.stack([good, 2 * good])), [spread(good), spread(2 * good)]
    )
    np.testing.assert_allclose(
        jax.jit(jax.grad(lambda t: jnp.sum(spread(t) ** 2)))(good), 2 * jnp.sum(weights**2) * good, rtol=1e-12
    )


@checked_jit
def _non_negative(x):
    return require(x, (x < 0, "x: negative values"))


@checked_jit
def _entry_point(x):
    # a nested entry point's checks join this one's; a check in a loop body stays a host call
    y = jax.lax.map(lambda v: require(v, (v > 100, "v: above 100")), _non_negative(x))
    return 2.0 * require_around(lambda y: y, y, (jnp.isnan(y).any(), "y: NaN"))


def test_checked_jit_returns_its_checks_as_values_on_concrete_input():
    x = jnp.array([1.0, 2.0])
    np.testing.assert_array_equal(_entry_point(x), [2.0, 4.0])
    # the nested entry point's and the around check come back as values, raised on the host (no runtime error
    # behind them); the loop body's check is a host call, whose error (JAX's) is raised as CheckError
    for bad, message, called_back in (
        (-1.0, "x: negative values", False),
        (jnp.nan, "y: NaN", False),
        (101.0, "v: above 100", True),
    ):
        with pytest.raises(jaxcga.CheckError, match=message) as raised:
            _entry_point(x.at[1].set(bad))
        assert (raised.value.__context__ is not None) is called_back, message  # JAX's error of the callback


def test_checked_jit_under_the_callers_jit_vmap_and_grad_checks_as_require():
    x = jnp.array([1.0, -2.0])
    with pytest.raises((jax.errors.JaxRuntimeError, ValueError), match="x: negative values"):
        jax.block_until_ready(jax.jit(_entry_point)(x))
    with pytest.raises((jax.errors.JaxRuntimeError, ValueError), match="x: negative values"):
        jax.block_until_ready(jax.vmap(lambda v: _non_negative(v[None]))(x))
    assert float(jax.grad(lambda v: _entry_point(v[None]).sum())(3.0)) == 2.0
    # concrete arguments closed over by the caller's jit: its checks are that trace's (no host read of a tracer)
    good, bad = np.array([1.0, 2.0]), np.array([1.0, -2.0])
    np.testing.assert_array_equal(jax.jit(lambda: _entry_point(good))(), [2.0, 4.0])
    np.testing.assert_array_equal(jax.jit(jax.vmap(lambda s: s * _entry_point(good)))(good), [[2.0, 4.0], [4.0, 8.0]])
    with pytest.raises((jax.errors.JaxRuntimeError, ValueError), match="x: negative values"):
        jax.block_until_ready(jax.jit(lambda: _entry_point(bad))())
