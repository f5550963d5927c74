"""Tests run in float64 with strict dtype promotion (DESIGN.md "Style") and with implicit rank promotion raising, as
diffrax's do: the library broadcasts explicitly (``x[None]``, ``[..., None]``, ``jnp.broadcast_to``), so that a shape
mistake fails where it is made instead of broadcasting silently. The library never sets either itself. A test marked
``@pytest.mark.host("why")`` needs the host by nature and is skipped, with that reason, where JAX's default
backend is not the CPU (docs/gpu.md).

``pytest --gpu-variants`` takes every per-platform kernel's GPU formulation on the CPU (the non-CPU branch of each
``jax.lax.platform_dependent``): the suite then checks the arithmetic of the code a GPU runs, without a GPU. Tests
marked ``@pytest.mark.cpu_formulation("why")`` check the CPU formulations themselves and are skipped with that
reason wherever the GPU formulations run; the ``running_variant`` fixture names the one that runs."""

import ctypes
import ctypes.util
import gc
import os
from pathlib import Path

# several test workers share one GPU: each takes memory as it needs it, not 75% of it up front (read when JAX
# starts its backend, after this)
os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
# the tests run the command line's main() in this process: it must neither write the user's compilation cache nor
# turn JAX's cache on for the rest of the session (the cache's own tests run the command in subprocesses)
os.environ.setdefault("JAXCGA_NO_CACHE", "1")
# JAX's persistent compilation cache in the checkout (.cache/, ignored by git), set in the environment so that the
# processes the tests start (the command line, the benchmarks, the batch's peers) share it: a run's two workers and
# the runs after it (the GPU variants, the slow job) load an executable compiled once instead of compiling it again.
# No size bound: a bound makes JAX scan the whole directory at every write (a third of a cold run's time). Two
# processes writing one entry at once is harmless (JAX warns of an entry it cannot read and compiles afresh). An
# empty JAX_COMPILATION_CACHE_DIR runs the tests cold. The library never turns this on; the command line's own cache
# is tested with these variables removed (tests.shared.run_jaxcga).
os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", str(Path(__file__).resolve().parents[1] / ".cache" / "jax-tests"))
os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0")

import jax  # noqa: E402
import pytest  # noqa: E402

from tests.shared import cpu_formulation_skip_reason, extended_tests, gpu_branches, host_skip_reason  # noqa: E402

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")
jax.config.update("jax_numpy_rank_promotion", "raise")
# and in this process, were JAX imported before this file (a plugin) and its environment read then
jax.config.update("jax_compilation_cache_dir", os.environ["JAX_COMPILATION_CACHE_DIR"] or None)
jax.config.update(
    "jax_persistent_cache_min_compile_time_secs", float(os.environ["JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"])
)


def pytest_addoption(parser):
    parser.addoption(
        "--gpu-variants",
        action="store_true",
        help="take the GPU formulation of every per-platform kernel on the CPU (make test-gpu-variants)",
    )


def pytest_configure(config):
    if config.getoption("--gpu-variants"):
        jax.lax.platform_dependent = gpu_branches(jax.lax.platform_dependent)


def _gpu_formulations(config) -> bool:
    return jax.default_backend() != "cpu" or config.getoption("--gpu-variants")


# before pytest's own hook deselects by mark (-m): the extended mark is given here
@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    backend = jax.default_backend()
    extended = set(extended_tests())
    for item in items:
        if item.nodeid in extended:
            item.add_marker(pytest.mark.extended)
        for reason in (
            host_skip_reason(item.get_closest_marker("host"), backend),
            cpu_formulation_skip_reason(item.get_closest_marker("cpu_formulation"), _gpu_formulations(config)),
        ):
            if reason is not None:
                item.add_marker(pytest.mark.skip(reason=reason))


# glibc's malloc keeps what a module's tests freed (XLA's buffers and executables, meshes, sparse factors) in its
# arenas instead of returning it to the system, so a worker of a long run grows by gigabytes (5.8 GB a worker a
# quarter into the slow job, 0.4-0.8 GB after a trim), and two of them near the job's end, in its largest tests,
# can exhaust a 24 GB machine; the tests return it between modules (the library leaves a caller's allocator alone)
_LIBC = ctypes.CDLL(ctypes.util.find_library("c")) if ctypes.util.find_library("c") else None
_TRIM = getattr(_LIBC, "malloc_trim", None)


@pytest.fixture(autouse=True, scope="module")
def _return_freed_memory_after_each_module():
    yield
    if _TRIM is not None:  # glibc only
        gc.collect()
        _TRIM(0)


@pytest.fixture
def running_variant(request) -> str:
    """The per-platform kernels' variant that runs here: "gpu" on a GPU or under ``--gpu-variants``, else "cpu"."""
    return "gpu" if _gpu_formulations(request.config) else "cpu"
