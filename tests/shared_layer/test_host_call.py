"""``_jaxcga_shared.host.host_call``: a host function called from traced code with numpy arrays, which does not hang a
one-core machine (``jax.pure_callback`` did, in the XFEM step's Newton solve)."""

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from _jaxcga_shared.host import host_call

ROOT = Path(__file__).resolve().parents[2]


def _scaled_head(x, y):
    """A pure host function: 2 x[:len(y)] + y, and the types it was given."""
    _scaled_head.types.append((type(x), type(y)))
    return 2 * x[: len(y)] + y


_scaled_head.types = []


def test_host_call_hands_numpy_arrays_and_returns_the_function_value():
    _scaled_head.types.clear()
    x, y = np.arange(10.0), np.linspace(0, 1, 4)
    f = jax.jit(lambda x, y: host_call(_scaled_head, jax.ShapeDtypeStruct(y.shape, y.dtype), x * 3, y) + 1)
    np.testing.assert_array_equal(np.asarray(f(x, y)), 2 * 3 * x[:4] + y + 1)
    assert _scaled_head.types == [(np.ndarray, np.ndarray)]
    # eagerly too, and with the result cast to the asked dtype
    out = host_call(lambda a: a.astype(np.float32), jax.ShapeDtypeStruct((3,), jnp.float64), np.ones(3))
    assert out.dtype == jnp.float64 and np.all(np.asarray(out) == 1)


def test_host_call_under_vmap_calls_once_per_batch_element():
    _scaled_head.types.clear()
    x, ys = np.arange(6.0), np.arange(12.0).reshape(4, 3)
    f = jax.jit(jax.vmap(lambda y: host_call(_scaled_head, jax.ShapeDtypeStruct((3,), y.dtype), x, y)))
    np.testing.assert_array_equal(np.asarray(f(ys)), 2 * x[:3] + ys)
    assert len(_scaled_head.types) == 4  # sequential: one call per row, the unbatched x given to each


def test_host_call_reports_a_result_of_the_wrong_shape():
    with pytest.raises(Exception, match="Incorrect output shape"):
        jax.block_until_ready(
            jax.jit(lambda y: host_call(lambda a: a[:2], jax.ShapeDtypeStruct((3,), y.dtype), y))(np.ones(3))
        )


_ONE_CORE = textwrap.dedent("""
    import os, sys
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})  # before XLA sizes its thread pool: one thread
    import jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp
    import numpy as np
    from _jaxcga_shared.host import host_call
    call = host_call if sys.argv[1] == "host_call" else (
        lambda fn, result, *args: jax.pure_callback(fn, result, *args, vmap_method="sequential"))

    def head(d, y):
        return np.asarray(d)[: len(y)] + np.asarray(y)

    @jax.jit
    def f(x, slots):
        # a scatter-add (a parallel op, as the Newton system's assembly) just before the host call
        d = jnp.zeros(len(x)).at[slots].add(x)
        y = jnp.ones(2_000)
        return call(head, jax.ShapeDtypeStruct(y.shape, y.dtype), d, y * 1.5)

    slots = np.random.default_rng(0).integers(0, 100_000, 100_000)
    out = np.asarray(f(np.ones(100_000), slots))
    print("sum", out.sum(), np.bincount(slots, minlength=100_000)[:2_000].sum() + 1.5 * 2_000)
""")


def _run_on_one_core(call: str):
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    return subprocess.run([sys.executable, "-c", _ONE_CORE, call], capture_output=True, text=True, env=env, timeout=120)


@pytest.mark.skipif(not hasattr(os, "sched_setaffinity"), reason="needs CPU affinity (Linux)")
def test_host_call_after_a_scatter_runs_on_one_core():
    """On one core, a host call after a scatter-add hung for good with ``jax.pure_callback`` (JAX 0.10: run this
    script with ``pure_callback`` as its argument), as the XFEM step's Newton solve did."""
    try:
        done = _run_on_one_core("host_call")
    except subprocess.TimeoutExpired:
        pytest.fail("the host call hung on one core")
    assert done.returncode == 0, done.stderr[-3000:]
    got, expected = (float(v) for v in done.stdout.split()[1:3])
    assert got == expected


@pytest.mark.cpu_formulation("the CPU solves on the host; a GPU solves on the device")
def test_the_newton_solve_and_the_sparse_solver_use_host_call():
    """XFEM's Newton solve and deform's sparse solver hand their host functions numpy arrays (``host_call``)."""
    import scipy.sparse as sp

    from _jaxcga_shared.sparse import SparseSolver
    from xfem import box_tets, fem_from_mesh
    from xfem._backward_euler import _host_newton_direction, _solve  # internal host functions, recorded here

    types = []

    def recorded(*args):
        types.extend(type(a) for a in args)
        return _host_newton_direction(*args)

    system = fem_from_mesh(box_tets((2, 2, 2)), 1e3, fixed=[0])
    p = system.pattern
    rhs = np.ones(3 * p.n_free)
    x = jax.jit(lambda data: _solve(recorded, p, data, rhs, 1e-12, "accept"))(system.mass_data)
    assert types and all(t is np.ndarray for t in types)
    n = int(p.indptr[-1])
    M = sp.csr_matrix((np.asarray(system.mass_data)[:n], np.asarray(p.indices)[:n], np.asarray(p.indptr)))
    np.testing.assert_allclose(M @ np.asarray(x), rhs, rtol=1e-10)

    A = sp.csc_matrix(np.array([[4.0, 1.0], [1.0, 3.0]]))
    solver = SparseSolver(A)
    b = jnp.array([1.0, 2.0])
    np.testing.assert_allclose(np.asarray(jax.jit(solver)(b)), np.linalg.solve(A.toarray(), b), rtol=1e-12)
    grad = jax.grad(lambda b: solver(b).sum())(b)  # the adjoint solve, through host_call too
    np.testing.assert_allclose(np.asarray(grad), np.linalg.solve(A.toarray().T, np.ones(2)), rtol=1e-12)
