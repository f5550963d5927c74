"""The sparse solves of every package (``_jaxcga_shared.sparse``): the device path (block-Jacobi PCG in JAX, what
a GPU runs) forced on the CPU against the host path (CHOLMOD, SuperLU, the numba CG) on real systems (harmonic
fields and ARAP on Arm5, an FEM Newton step and an XFEM implicit gradient on the test box), gradients against
finite differences, vmap, and the errors of singular, indefinite and unconverged systems."""

from __future__ import annotations

import contextlib
from pathlib import Path

import equinox as eqx
import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

import deform

# xfem's sparse solves (host adjoint, to_scipy) are internal users of the shared layer tested here
import xfem._backward_euler as be
from _jaxcga_shared import ell, multigrid, sparse
from _jaxcga_shared.sparse import (
    SparseSolver,
    checked_device_pcg,
    csr_pattern,
    device_pcg,
    host_direct,
    host_pcg,
    spd_solve,
)
from tests.shared import check_gradient, gpu_branches
from tests.xfem._models import MATERIAL, RHO, H, deformed_state, plane, tall_box
from xfem import assemble_matrix, backward_euler_step, fem_from_mesh, xfem_model
from xfem._assembly import to_scipy

DATA = Path(__file__).resolve().parents[1] / "data"
ARM5 = deform.load_model(DATA / "Arm5.glb", weld=True).mesh


@contextlib.contextmanager
def _device_path():
    """Every ``jax.lax.platform_dependent`` takes its non-CPU branch (the GPU's) while inside; JAX's caches are
    cleared on the way in and out, so that no function traced for one path runs on the other. Yields the list of
    the host calls the solves traced (none, unless a device solve falls back to the host)."""
    original, original_host_call = jax.lax.platform_dependent, sparse.host_call
    traced = []

    def recorded(fn, *args):
        traced.append(fn)
        return original_host_call(fn, *args)

    jax.clear_caches()
    jax.lax.platform_dependent = gpu_branches(original, keep_cpu=False)  # no host call of the CPU's is traced
    sparse.host_call = recorded
    try:
        yield traced
    finally:
        jax.lax.platform_dependent, sparse.host_call = original, original_host_call
        jax.clear_caches()


def _arm5_dirichlet():
    """-L_ff of Arm5's cotangent Laplacian with both ends fixed, and L_fc bc for two harmonic fields."""
    V, F = np.asarray(ARM5.V, np.float64), np.asarray(ARM5.F, np.int64)
    x = V[:, 0]
    ends = [np.flatnonzero(x < np.quantile(x, 0.05)), np.flatnonzero(x > np.quantile(x, 0.95))]
    b = np.concatenate(ends)
    free = np.setdiff1d(np.arange(len(V)), b)
    L = sp.csr_matrix(igl.cotmatrix(V, F))
    bc = np.zeros((len(b), 2))
    bc[: len(ends[0]), 0] = 1.0
    bc[len(ends[0]) :, 1] = 1.0
    return -L[free][:, free], L[free][:, b] @ bc


def test_device_pcg_solves_a_cotangent_laplacian_like_cholmod():
    A, rhs = _arm5_dirichlet()
    solver = SparseSolver(A, symmetric=True)
    host = solver.host_solve(rhs)
    device = np.asarray(jax.jit(solver.device_solve)(jnp.asarray(rhs)))
    residual = np.linalg.norm(A @ device - rhs, axis=0) / np.linalg.norm(rhs, axis=0)
    assert np.all(residual <= solver.device_rtol)
    # fields in [0, 1]: the error of a 1e-10 residual on this conditioning
    np.testing.assert_allclose(device, host, rtol=0, atol=1e-7)


@pytest.mark.slow
def test_harmonic_fields_and_arap_on_the_device_path_equal_the_host_path():
    V, F = np.asarray(ARM5.V, np.float64), np.asarray(ARM5.F, np.int64)
    x = V[:, 0]
    fixed, hand = np.flatnonzero(x < np.quantile(x, 0.05)), np.flatnonzero(x > np.quantile(x, 0.95))
    b = np.concatenate([fixed, hand])
    bc = np.zeros((len(b), 2))
    bc[: len(fixed), 0], bc[len(fixed) :, 1] = 1.0, 1.0
    harmonic = deform.harmonic_precompute(V, F, b)
    data = deform.arap_precompute(V, F, b)
    moved = V[b] + np.where(np.isin(b, hand), 1.0, 0.0)[:, None] * np.array([0.0, 0.1, 0.05])
    host_fields = np.asarray(deform.harmonic_solve(harmonic, jnp.asarray(bc)))
    host_arap = np.asarray(deform.arap_solve(data, jnp.asarray(moved), max_iterations=3).U)
    with _device_path() as host_calls:
        fields = np.asarray(deform.harmonic_solve(harmonic, jnp.asarray(bc)))
        arap = np.asarray(deform.arap_solve(data, jnp.asarray(moved), max_iterations=3).U)
    assert host_calls == []
    np.testing.assert_allclose(fields, host_fields, rtol=0, atol=1e-7)
    np.testing.assert_allclose(arap, host_arap, rtol=0, atol=1e-7 * np.ptp(V))


def test_block_jacobi_pcg_solves_an_fem_system_like_cholmod_and_the_host_cg():
    """M + h^2 K on the test box's free DOFs (K: elementwise Laplacian stiffness (x) I3, the FEM's sparsity and
    3 x 3 node blocks), to a tight and to the Newton direction's tolerance."""
    mesh = tall_box()
    system = fem_from_mesh(mesh, RHO, fixed=np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9))
    grads, volumes = np.asarray(system.grads), np.asarray(system.volumes)
    K = np.kron(volumes[:, None, None] * grads @ grads.transpose(0, 2, 1), np.eye(3)[None]) * MATERIAL.young
    pattern = system.pattern
    data = system.mass_data + H**2 * assemble_matrix(pattern, jnp.asarray(K))
    A = to_scipy(pattern, data)
    b = np.random.default_rng(4).normal(size=A.get_shape()[0])
    exact = host_direct(np.asarray(data), b, np.asarray(pattern.indptr), np.asarray(pattern.indices))
    solve = jax.jit(lambda d, r, rtol: checked_device_pcg(pattern.csr, d, r, rtol))
    tight = np.asarray(solve(data, jnp.asarray(b), 1e-11))
    np.testing.assert_allclose(tight, exact, rtol=0, atol=1e-9 * np.abs(exact).max())
    for rtol in (1e-4, 1e-8):
        x = np.asarray(solve(data, jnp.asarray(b), rtol))
        assert np.linalg.norm(A @ x - b) <= rtol * np.linalg.norm(b)
        on_host = host_pcg(np.asarray(data), b, rtol, np.asarray(pattern.indptr), np.asarray(pattern.indices))
        assert np.linalg.norm(x - exact) <= 10 * max(np.linalg.norm(on_host - exact), rtol * np.linalg.norm(exact))


@pytest.mark.slow
def test_fem_newton_step_and_xfem_gradient_on_the_device_path_equal_the_host_path():
    """A converged FEM step (Newton systems by block-Jacobi PCG on the device, CHOLMOD on the host) and the
    implicit gradient of a cut XFEM system's step (its adjoint solve)."""
    mesh = tall_box()
    top = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    model = xfem_model(mesh, RHO, fixed=top, state=deformed_state(mesh))
    model.cut(plane())
    system, state = model.system(), model.state

    def step(young):
        return backward_euler_step(
            system, state, H, type(MATERIAL)(young, MATERIAL.poisson), newton_iterations=20, tolerance=1e-11
        )

    def loss(young):
        return jnp.sum(jnp.sin(step(young).x))

    young = jnp.asarray(MATERIAL.young)
    host_x, host_grad = np.asarray(step(young).x), float(jax.grad(loss)(young))
    with _device_path() as host_calls:
        x, grad = np.asarray(step(young).x), float(jax.grad(loss)(young))
    assert all(fn is be._host_adjoint for fn in host_calls)  # only the adjoint's fallback, traced, not necessarily run
    np.testing.assert_allclose(x, host_x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(grad, host_grad, rtol=1e-6)


@pytest.mark.slow
def test_gradient_and_vmap_through_the_device_path():
    # scipy is unannotated: pyright takes the type of offsets from its default, 0
    A = sp.csr_matrix(sp.diags([-1.0, 2.2, -1.0], [-1, 0, 1], shape=(30, 30)))  # pyright: ignore[reportArgumentType]
    solver = SparseSolver(A, symmetric=True)
    probe = jnp.asarray(np.random.default_rng(0).normal(size=30))
    b = jnp.asarray(np.random.default_rng(1).uniform(size=30))
    with _device_path() as host_calls:
        check_gradient(jax.jit(lambda b: jnp.sum(jnp.sin(solver(b)) * probe)), b, rtol=1e-6)
        batch = jnp.stack([b, 2 * b + 1, -b])
        solved = np.asarray(jax.jit(jax.vmap(solver))(batch))
    assert host_calls == []
    np.testing.assert_allclose(solved, np.linalg.solve(A.toarray(), np.asarray(batch).T).T, rtol=1e-8)


@pytest.mark.slow
def test_singular_indefinite_and_unconverged_systems_are_reported():
    singular = sp.csr_matrix(np.array([[1.0, 1.0], [1.0, 1.0]]))
    with pytest.raises(ValueError, match="A: the matrix is singular or not positive definite"):
        SparseSolver(singular, symmetric=True)
    with pytest.raises(ValueError, match="A: the matrix is singular"):
        SparseSolver(singular)
    with pytest.raises(ValueError, match="A: expected a square"):
        SparseSolver(sp.csr_matrix(np.ones((2, 3))))
    with pytest.raises(ValueError, match="A: symmetric=True but"):
        SparseSolver(sp.csr_matrix(np.array([[2.0, 1.0], [0.0, 1.0]])), symmetric=True)
    unsymmetric = SparseSolver(sp.csc_matrix(np.array([[2.0, 1.0], [0.0, 1.0]])))
    np.testing.assert_allclose(unsymmetric(jnp.array([3.0, 1.0])), [1.0, 1.0])
    with pytest.raises(ValueError, match="b: expected shape"):
        unsymmetric(jnp.ones(3))

    # host_direct: SuperLU for an indefinite matrix, NaN for a singular one
    indefinite = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))
    b = np.array([1.0, -2.0, 3.0])
    exact = np.linalg.solve(indefinite.toarray(), b)
    np.testing.assert_allclose(host_direct(indefinite.data, b, indefinite.indptr, indefinite.indices), exact)
    assert np.all(np.isnan(host_direct(singular.data, b[:2], singular.indptr, singular.indices)))

    # the device CG inside jit: an error naming the system, or the host's solve where asked
    pattern = csr_pattern(indefinite.indptr, indefinite.indices)
    data, rhs = jnp.asarray(indefinite.data), jnp.asarray(b)
    with _device_path():
        with pytest.raises(
            (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError),
            match="A: the conjugate gradient did not reach its tolerance",
        ):
            eqx.filter_jit(lambda d, r: spd_solve(pattern, d, r, 1e-10))(data, rhs).block_until_ready()
        fallback = jax.jit(lambda d, r: spd_solve(pattern, d, r, 1e-10, on_failure="host"))(data, rhs)
    np.testing.assert_allclose(np.asarray(fallback), exact, rtol=1e-12)
    _, info = jax.jit(lambda d, r: device_pcg(pattern, d, r, 1e-10))(data, rhs)
    assert bool(info.breakdown) and not bool(info.converged)

    # an SPD system stopped after 2 iterations: reported, not silent
    # scipy is unannotated: pyright takes the type of offsets from its default, 0
    A = sp.csr_matrix(sp.diags([-1.0, 2.01, -1.0], [-1, 0, 1], shape=(50, 50)))  # pyright: ignore[reportArgumentType]
    pattern = csr_pattern(A.indptr, A.indices)
    with _device_path():
        with pytest.raises(
            (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError),
            match="the Newton system: the conjugate gradient did not reach",
        ):
            eqx.filter_jit(lambda d, r: spd_solve(pattern, d, r, 1e-10, max_iterations=2, what="the Newton system"))(
                jnp.asarray(A.data), jnp.ones(50)
            ).block_until_ready()
    _, info = device_pcg(pattern, jnp.asarray(A.data), jnp.ones(50), 1e-10, 2)
    assert int(info.iterations) == 2 and not bool(info.converged) and not bool(info.breakdown)
    with pytest.raises(ValueError, match="block: expected a positive divisor"):
        csr_pattern(A.indptr, A.indices, block=3)


def test_small_systems_are_factorized_densely_off_the_cpu():
    """``dense_up_to``: a system that small is solved exactly on the device (padding entries past its last row
    included), without a host call; one that is not positive definite goes to CG as before (an error, or the host's
    solve where asked)."""
    A = _node_block_matrix(12)
    padding = 9
    indices = np.concatenate([A.indices, np.zeros(padding, A.indices.dtype)])
    data = jnp.asarray(np.concatenate([A.data, np.full(padding, 5.0)]))
    pattern = csr_pattern(A.indptr, indices, block=3)
    b = np.random.default_rng(12).normal(size=A.get_shape()[0])
    exact = np.linalg.solve(A.toarray(), b)
    with _device_path() as host_calls:
        dense = np.asarray(jax.jit(lambda d, r: spd_solve(pattern, d, r, 1e-4, dense_up_to=A.get_shape()[0]))(data, b))
        iterative = np.asarray(
            jax.jit(lambda d, r: spd_solve(pattern, d, r, 1e-4, dense_up_to=A.get_shape()[0] - 1))(data, b)
        )
    assert host_calls == []
    np.testing.assert_allclose(dense, exact, rtol=0, atol=1e-12 * np.abs(exact).max())
    assert np.abs(iterative - exact).max() > 1e-8 * np.abs(exact).max()  # CG to 1e-4: the other path ran

    indefinite = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))
    pattern = csr_pattern(indefinite.indptr, indefinite.indices)
    data, rhs = jnp.asarray(indefinite.data), jnp.asarray([1.0, -2.0, 3.0])
    with _device_path():
        with pytest.raises(
            (eqx.EquinoxRuntimeError, jax.errors.JaxRuntimeError),
            match="A: the conjugate gradient did not reach its tolerance",
        ):
            eqx.filter_jit(lambda d, r: spd_solve(pattern, d, r, 1e-10, dense_up_to=3))(data, rhs).block_until_ready()
        fallback = jax.jit(lambda d, r: spd_solve(pattern, d, r, 1e-10, on_failure="host", dense_up_to=3))(data, rhs)
    np.testing.assert_allclose(np.asarray(fallback), np.linalg.solve(indefinite.toarray(), rhs), rtol=1e-12)
    for bad in (-1, 2.5):
        with pytest.raises(ValueError, match="dense_up_to: expected an int >= 0"):
            spd_solve(pattern, data, rhs, 1e-10, dense_up_to=bad)  # pyright: ignore[reportArgumentType]


def _node_block_matrix(seed: int, nodes: int = 9, block: int = 3) -> sp.csr_matrix:
    """A symmetric positive definite matrix of full ``block`` x ``block`` blocks on a random node graph, with
    rows of different lengths (an FEM system's structure)."""
    rng = np.random.default_rng(seed)
    graph = sp.random(nodes, nodes, density=0.3, rng=rng)
    graph = ((graph + graph.T + sp.identity(nodes)) != 0).astype(float)
    values = sp.kron(graph, np.ones((block, block))).tocsr()
    values.data = rng.normal(size=values.nnz)
    return sp.csr_matrix(values @ values.T + sp.identity(nodes * block))


def test_block_matvec_multiplies_like_scipy_and_the_device_cg_like_the_entry_one():
    """A matrix of full 3 x 3 blocks, with padding entries past its last row: found to be made of blocks, its
    product over blocks (vectors and columns) equals scipy's, and the block-Jacobi CG over blocks reaches what
    the CG over entries reaches."""
    A = _node_block_matrix(8)
    A.sort_indices()
    padding = 18  # two blocks' entries past indptr[-1], as a capacity leaves
    indices = np.concatenate([A.indices, np.zeros(padding, A.indices.dtype)])
    data = jnp.asarray(np.concatenate([A.data, np.full(padding, 7.0)]))
    blocks, entries = (
        csr_pattern(A.indptr, indices, block=3),
        csr_pattern(A.indptr, indices, block=3, full_blocks=False),
    )
    assert blocks.full_blocks and not entries.full_blocks and entries.blocks is None
    # the layout found once: scipy's block rows and columns, then the padding's two blocks (dropped rows)
    bsr = A.tobsr(blocksize=(3, 3))
    nodes = A.get_shape()[0] // 3
    layout = jax.tree.map(np.asarray, blocks.blocks)
    np.testing.assert_array_equal(layout.rows, np.r_[np.repeat(np.arange(nodes), np.diff(bsr.indptr)), nodes, nodes])
    np.testing.assert_array_equal(layout.columns[: len(bsr.indices)], bsr.indices)
    for k in range(len(bsr.indices)):
        entries_of_block = layout.starts[k] + layout.strides[k] * np.arange(3)[:, None] + np.arange(3)
        np.testing.assert_array_equal(np.asarray(data)[entries_of_block], bsr.data[k])
    x = np.random.default_rng(9).normal(size=(A.get_shape()[0], 2))
    for v in (x, x[:, 0]):
        np.testing.assert_allclose(jax.jit(sparse.matvec(blocks, data))(jnp.asarray(v)), A @ v, rtol=1e-13, atol=1e-13)
    b = jnp.asarray(x[:, 0])
    (on_blocks, info), (on_entries, _) = (device_pcg(p, data, b, 1e-12, 500) for p in (blocks, entries))
    assert bool(info.converged)
    np.testing.assert_allclose(on_blocks, on_entries, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(on_entries))))


@pytest.mark.parametrize(
    "case", ["converges", "stopped at the limit", "indefinite", "indefinite later", "two columns", "from a guess"]
)
def test_cg_checking_every_few_iterations_takes_the_same_iterates(case):
    """The iterations a loop step runs after convergence, a breakdown or the limit are no-ops: x and the
    ``PCGInfo`` are bitwise those of a check after every iteration."""
    A = _node_block_matrix(11)
    rtol, limit, x0 = 1e-12, 500, None
    b = np.random.default_rng(12).normal(size=(A.get_shape()[0], 2))
    if case == "stopped at the limit":
        limit = 6
    if case == "indefinite":
        A = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))
        b = np.array([[1.0, -2.0, 3.0], [0.5, 1.0, 1.0]]).T
    if case == "indefinite later":  # positive diagonal, negative curvature found after a few iterations
        A = sp.csr_matrix(sp.diags([1.0] * 8 + [-0.5], 0) + sp.diags([0.3, 0.3], [-1, 1], shape=(9, 9)))  # pyright: ignore[reportArgumentType]
        b = np.ones((9, 2))
    b = b if case in ("two columns", "from a guess") else b[:, 0]
    if case == "from a guess":
        x0 = jnp.asarray(0.1 * b)
    A.sort_indices()
    pattern = csr_pattern(A.indptr, A.indices)
    precondition, _ = sparse._preconditioner(pattern, jnp.asarray(A.data))
    solves = [
        sparse.preconditioned_cg(
            sparse.matvec(pattern, jnp.asarray(A.data)), precondition, jnp.asarray(b), rtol, limit, x0=x0, check_every=c
        )
        for c in (1, 3, 4)
    ]
    for x, info in solves[1:]:
        np.testing.assert_array_equal(x, solves[0][0])
        for got, expected in zip(jax.tree.leaves(info), jax.tree.leaves(solves[0][1])):
            np.testing.assert_array_equal(got, expected)
    info = solves[0][1]
    assert bool(info.breakdown) == case.startswith("indefinite")
    assert bool(info.converged) == (case in ("converges", "two columns", "from a guess"))
    assert case != "stopped at the limit" or int(info.iterations) == limit
    with pytest.raises(ValueError, match="check_every"):
        sparse.preconditioned_cg(
            sparse.matvec(pattern, jnp.asarray(A.data)), precondition, jnp.asarray(b), rtol, 5, check_every=0
        )


def test_full_blocks_are_found_only_where_every_block_is_full():
    A = _node_block_matrix(10)
    A.sort_indices()
    assert sparse._full_blocks(A.indptr, A.indices, 3)
    broken = A.tolil()
    i, j = 4, int(A.indices[A.indptr[4]])  # an entry of a block, removed: the block is no longer full
    broken[i, j] = 0
    broken = sp.csr_matrix(broken)
    broken.eliminate_zeros()
    assert not sparse._full_blocks(broken.indptr, broken.indices, 3)
    assert not csr_pattern(broken.indptr, broken.indices, block=3).full_blocks
    shifted = sp.csr_matrix(sp.block_diag([sp.identity(1), A, sp.identity(2)]))  # blocks off the multiples of 3
    assert not sparse._full_blocks(shifted.indptr, shifted.indices, 3)
    assert not csr_pattern(A.indptr, A.indices).full_blocks  # Jacobi: no blocks


# ---------------------------------------------------------------------------------------------------------
# the multigrid preconditioner of a fixed system's device solve


@pytest.mark.parametrize("smoother", multigrid.SMOOTHERS)
def test_the_v_cycle_is_symmetric_positive_definite_and_cuts_cg_iterations(smoother):
    """On Arm5's Dirichlet Laplacian (cotangent weights, some negative): u.Mv = v.Mu and u.Mu > 0 for the V-cycle
    M over three levels, and the CG it preconditions reaches CHOLMOD's solution in a fraction of block-Jacobi CG's
    iterations."""
    A, rhs = _arm5_dirichlet()
    mg = multigrid.multigrid_precompute(A, max_coarse=100, smoother=smoother)
    assert len(mg.levels) >= 2
    u, v = np.random.default_rng(5).normal(size=(2, A.shape[0], 8))
    Mu, Mv = (np.asarray(multigrid.v_cycle(mg, jnp.asarray(w))) for w in (u, v))
    np.testing.assert_allclose(np.sum(u * Mv, 0), np.sum(v * Mu, 0), rtol=1e-10)
    assert np.all(np.sum(u * Mu, 0) > 0)
    A_ell = ell.ell_matrix(A)
    x, info = sparse.preconditioned_cg(
        lambda w: ell.ell_matvec(A_ell, w), lambda r: multigrid.v_cycle(mg, r), jnp.asarray(rhs), 1e-12, 1000
    )
    A = sp.csr_matrix(A)
    _, jacobi = device_pcg(csr_pattern(A.indptr, A.indices), jnp.asarray(A.data), jnp.asarray(rhs), 1e-12)
    assert bool(info.converged) and 4 * int(info.iterations) < int(jacobi.iterations)
    np.testing.assert_allclose(x, sp.linalg.spsolve(A.tocsc(), rhs), rtol=0, atol=1e-9)


def test_ell_matrices_multiply_like_scipy():
    """Rectangular, with empty rows and rows of different lengths; vectors and blocks of columns."""
    M = sp.random(30, 17, density=0.15, rng=np.random.default_rng(6), format="lil")
    M[3] = 0
    M = M.tocsr()
    M_ell = ell.ell_matrix(M)
    x = np.random.default_rng(7).normal(size=(17, 2))
    np.testing.assert_allclose(ell.ell_matvec(M_ell, jnp.asarray(x)), M @ x, rtol=1e-13, atol=1e-15)
    np.testing.assert_allclose(ell.ell_matvec(M_ell, jnp.asarray(x[:, 0])), M @ x[:, 0], rtol=1e-13, atol=1e-15)


def test_multigrid_names_bad_options_and_matrices():
    A, _ = _arm5_dirichlet()
    with pytest.raises(ValueError, match="smoother"):
        multigrid.multigrid_precompute(A, smoother="gauss-seidel")
    with pytest.raises(ValueError, match="degree"):
        multigrid.multigrid_precompute(A, degree=0)
    with pytest.raises(ValueError, match="A: a diagonal entry is not positive"):
        multigrid.multigrid_precompute(-A)


@pytest.mark.slow
def test_a_first_guess_changes_neither_the_solve_nor_its_gradient():
    """``SparseSolver(b, x0)`` on the device path: the solution of b (to the tolerance) whatever x0, the same
    gradient with respect to b, none with respect to x0; a guess of the wrong shape is named."""
    A, rhs = _arm5_dirichlet()
    solver = SparseSolver(A, symmetric=True)
    exact = solver.host_solve(rhs)
    probe = jnp.asarray(np.random.default_rng(8).normal(size=rhs.shape))
    b = jnp.asarray(rhs)
    with _device_path():
        for guess in (None, jnp.zeros_like(b), jnp.asarray(exact) + 0.01):
            np.testing.assert_allclose(jax.jit(solver)(b, guess), exact, rtol=0, atol=1e-9)

        def loss(b, guess):
            return jnp.sum(jnp.sin(solver(b, guess)) * probe)

        g_b, g_guess = jax.jit(jax.grad(loss, argnums=(0, 1)))(b, jnp.asarray(exact) + 0.01)
        np.testing.assert_allclose(g_b, jax.grad(loss)(b, None), rtol=0, atol=1e-9 * float(jnp.abs(g_b).max()))
        assert not np.any(np.asarray(g_guess))
    with pytest.raises(ValueError, match="x0: expected b's shape"):
        solver(b, b[:, 0])
