"""The ``host`` mark (tests/conftest.py): a test that needs the host is skipped with its reason on a GPU, runs on
the CPU, and a mark without a reason is an error."""

import pytest

from tests.shared import host_skip_reason


def test_a_host_test_is_skipped_with_its_reason_off_the_cpu():
    mark = pytest.mark.host("reads a CPU-only file format").mark
    assert host_skip_reason(mark, "cpu") is None
    assert host_skip_reason(mark, "gpu") == "needs the host (gpu backend): reads a CPU-only file format"
    assert host_skip_reason(None, "gpu") is None


@pytest.mark.parametrize("args", [(), ("",), (3,), ("a", "b")])
def test_a_host_mark_needs_one_reason(args):
    with pytest.raises(ValueError, match="expected one reason"):
        host_skip_reason(pytest.mark.host(*args).mark, "gpu")
