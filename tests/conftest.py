"""Tests run in float64 with strict dtype promotion (DESIGN.md "Style"). A test marked
``@pytest.mark.host("why")`` needs the host by nature and is skipped, with that reason, where JAX's default
backend is not the CPU (README.md, "On a GPU")."""

import os

# several test workers share one GPU: each takes memory as it needs it, not 75% of it up front (read when JAX
# starts its backend, after this)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")

import jax  # noqa: E402
import pytest  # noqa: E402

from tests.shared import host_skip_reason  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


def pytest_collection_modifyitems(config, items):
    backend = jax.default_backend()
    for item in items:
        reason = host_skip_reason(item.get_closest_marker("host"), backend)
        if reason is not None:
            item.add_marker(pytest.mark.skip(reason=reason))
