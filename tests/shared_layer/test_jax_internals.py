"""The JAX internals that ``_jaxcga_shared.host.host_call`` is built on, as the pinned JAX versions have them: a JAX
that renames or reshapes them fails here, by name, rather than deep inside a compiled solve."""

from __future__ import annotations

import importlib.metadata
import inspect

import jax
import jax._src.callback
import jax._src.dispatch
import jax.extend.core
import pytest
from packaging.requirements import Requirement


def test_the_installed_jax_is_one_the_pin_admits():
    pins = [Requirement(r) for r in importlib.metadata.requires("jaxcga") or [] if Requirement(r).name == "jax"]
    assert pins, "pyproject.toml pins jax (host_call depends on its internals)"
    assert pins[0].specifier.contains(jax.__version__), f"jax {jax.__version__} is outside the pin {pins[0]}"
    upper = [spec for spec in pins[0].specifier if spec.operator in ("<", "<=", "==", "~=")]
    assert upper, f"the pin {pins[0]} needs an upper bound: host_call is tested only with the versions it admits"


def test_emit_python_callback_takes_what_host_call_passes():
    parameters = inspect.signature(jax._src.callback.emit_python_callback).parameters
    assert list(parameters)[:6] == ["ctx", "callback", "token", "operands", "operand_avals", "result_avals"]
    for keyword in ("has_side_effect", "returns_token"):
        assert parameters[keyword].kind is inspect.Parameter.KEYWORD_ONLY


def test_dispatch_hooks_exist():
    assert isinstance(jax._src.dispatch.prim_requires_devices_during_lowering, set)
    assert callable(jax._src.dispatch.apply_primitive)
    assert callable(jax.extend.core.Primitive)


@pytest.mark.parametrize("batched", [False, True])
def test_host_call_lowers_and_runs_through_them(batched):
    """End to end on this JAX: lowering (emit_python_callback's three results), eager impl and vmap."""
    from _jaxcga_shared.host import host_call

    def twice(x):
        return 2 * x

    def f(x):
        return host_call(twice, jax.ShapeDtypeStruct(x.shape, x.dtype), x)

    x = jax.numpy.arange(6.0).reshape(2, 3)
    out = jax.jit(jax.vmap(f))(x) if batched else jax.jit(f)(x)
    assert (out == 2 * x).all()
    assert (f(x) == 2 * x).all()
