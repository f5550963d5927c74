"""The marks and options of tests/conftest.py: a test that needs the host is skipped with its reason on a GPU and
runs on the CPU; one that checks the CPU formulations is skipped where the GPU formulations run; a mark without a
reason is an error; ``--gpu-variants`` takes the GPU formulations on the CPU; every test ``tests/extended.txt``
names exists and carries the extended mark."""

import ast
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.shared import cpu_formulation_skip_reason, extended_tests, gpu_branches, host_skip_reason


def test_a_host_test_is_skipped_with_its_reason_off_the_cpu():
    mark = pytest.mark.host("reads a CPU-only file format").mark
    assert host_skip_reason(mark, "cpu") is None
    assert host_skip_reason(mark, "gpu") == "needs the host (gpu backend): reads a CPU-only file format"
    assert host_skip_reason(None, "gpu") is None


@pytest.mark.parametrize("args", [(), ("",), (3,), ("a", "b")])
def test_a_host_mark_needs_one_reason(args):
    with pytest.raises(ValueError, match="expected one reason"):
        host_skip_reason(pytest.mark.host(*args).mark, "gpu")


def test_a_cpu_formulation_test_is_skipped_with_its_reason_where_the_gpu_formulations_run():
    mark = pytest.mark.cpu_formulation("a lowering for the CPU holds barriers").mark
    assert cpu_formulation_skip_reason(mark, False) is None
    assert cpu_formulation_skip_reason(mark, True) == (
        "checks the CPU formulation, not run here: a lowering for the CPU holds barriers"
    )
    assert cpu_formulation_skip_reason(None, True) is None
    with pytest.raises(ValueError, match="cpu_formulation: expected one reason"):
        cpu_formulation_skip_reason(pytest.mark.cpu_formulation().mark, True)


def test_gpu_variants_take_the_other_branch_on_the_cpu_and_keep_both_in_the_trace(monkeypatch):
    """``--gpu-variants`` (conftest.py): eagerly and jitted the non-CPU branch runs; the jaxpr still holds both."""
    monkeypatch.setattr(jax.lax, "platform_dependent", gpu_branches(jax.lax.platform_dependent))

    def f(x):
        return jax.lax.platform_dependent(x, cpu=lambda x: x + 1.0, default=lambda x: x + 2.0)

    x = jnp.zeros(())
    assert float(f(x)) == float(jax.jit(f)(x)) == 2.0
    assert str(jax.make_jaxpr(f)(x)).count("add") == 2
    dropping = gpu_branches(jax.lax.platform_dependent, keep_cpu=False)
    assert float(jax.jit(lambda x: dropping(x, cpu=lambda x: x + 1.0, default=lambda x: x + 2.0))(x)) == 2.0
    assert (
        str(jax.make_jaxpr(lambda x: dropping(x, cpu=lambda x: x + 1.0, default=lambda x: x + 2.0))(x)).count("add")
        == 1
    )
    with pytest.raises(ValueError, match="per_platform: a TPU branch"):
        jax.lax.platform_dependent(x, cpu=lambda x: x, tpu=lambda x: x, default=lambda x: x)


def test_implicit_rank_promotion_raises_and_explicit_broadcasting_is_the_same():
    """The suite runs with ``jax_numpy_rank_promotion="raise"`` (conftest.py): an implicit broadcast of a (3,) row
    against (2, 3) is an error, the explicit one the library writes gives numpy's result."""
    row, table = jnp.arange(3.0), jnp.ones((2, 3))
    with pytest.raises(ValueError, match="rank_promotion"):
        _ = row + table
    np.testing.assert_array_equal(row[None] + table, np.arange(3.0) + np.ones((2, 3)))


def test_every_extended_test_exists_once():
    """A name in ``tests/extended.txt`` that is no longer a test (renamed, moved) would silently run in CI again: each
    names a test function of its file, once."""
    root = Path(__file__).resolve().parents[1]
    ids = extended_tests()
    assert ids and len(ids) == len(set(ids))
    for node in ids:
        path, name = node.split("::")
        tree = ast.parse((root / path).read_text())
        functions = [d.name for d in ast.walk(tree) if isinstance(d, ast.FunctionDef)]
        assert name.split("[")[0] in functions, node


def test_the_extended_mark_is_given_to_the_named_tests_alone(request):
    from tests import conftest

    class Item:  # what the collection hook reads of a test item
        def __init__(self, nodeid):
            self.nodeid, self.marks = nodeid, []

        def get_closest_marker(self, name):
            return next((m for m in self.marks if m.name == name), None)

        def add_marker(self, mark):
            self.marks.append(mark.mark)

    named, other = Item(extended_tests()[0]), Item("tests/test_conftest.py::test_a_test_not_named")
    conftest.pytest_collection_modifyitems(request.config, [named, other])
    assert [m.name for m in named.marks] == ["extended"] and other.marks == []
