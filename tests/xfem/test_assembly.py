"""Sparse assembly of the backward Euler system (XFEM paper sec. 3.3): element Hessians, vectors and a scalar
mass matrix against dense numpy scatter-adds, the reduced (Dirichlet) system against the full one with rows
and columns deleted, XFEM-like element lists (repeated elements, nodes in no element), jit and gradients,
bad input."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

from _jaxcga_shared.sparse import _full_blocks
from tests.shared import assert_same_run
from tests.xfem._models import RHO, plane, tall_box
from xfem import box_tets, consistent_mass, xfem_model
from xfem._assembly import (
    assemble_matrix,
    assemble_scalar,
    assemble_vector,
    assembly_pattern,
    matvec,
    restrict,
    scalar_slots,
    sorted_unique,
    to_scipy,
)

MESH = box_tets((2, 2, 1))
T = np.asarray(MESH.T)
N = len(MESH.X)
RNG = np.random.default_rng(0)


def _dofs(T):
    return (3 * T[:, :, None] + np.arange(3)).reshape(len(T), 12)


def _dense_matrix(T, H, n):
    A = np.zeros((3 * n, 3 * n))
    for e, dof in enumerate(_dofs(T)):
        A[np.ix_(dof, dof)] += H[e]
    return A


def _free_dofs(n, fixed):
    free = np.setdiff1d(np.arange(n), fixed)
    return (3 * free[:, None] + np.arange(3)).ravel()


@pytest.mark.parametrize("fixed", [(), (0, 4, 17)])
def test_matrix_equals_dense_scatter_add(fixed):
    H = RNG.normal(size=(len(T), 12, 12))
    pattern = assembly_pattern(T, N, np.array(fixed, int))
    A = to_scipy(pattern, assemble_matrix(pattern, jnp.asarray(H)))
    dense = _dense_matrix(T, H, N)[np.ix_(_free_dofs(N, fixed), _free_dofs(N, fixed))]
    np.testing.assert_allclose(A.toarray(), dense, atol=1e-13)
    # canonical CSR: sorted columns, no duplicates, exactly the structural nonzeros
    assert A.has_sorted_indices and A.nnz == pattern.nnz == np.count_nonzero(dense)
    assert pattern.n_free == N - len(fixed)


def test_reduced_matrix_is_the_full_one_without_fixed_rows_and_columns():
    H = RNG.normal(size=(len(T), 12, 12))
    fixed = np.array([1, 2, 9, 10])
    full = assembly_pattern(T, N)
    reduced = assembly_pattern(T, N, fixed)
    A_full = to_scipy(full, assemble_matrix(full, jnp.asarray(H))).toarray()
    A_reduced = to_scipy(reduced, assemble_matrix(reduced, jnp.asarray(H))).toarray()
    keep = _free_dofs(N, fixed)
    assert_same_run(A_reduced, A_full[np.ix_(keep, keep)], atol=1e-13)
    np.testing.assert_array_equal(np.asarray(reduced.free_index)[fixed], -1)
    np.testing.assert_array_equal(
        np.asarray(reduced.free)[np.asarray(reduced.free_index)[reduced.free]], np.asarray(reduced.free)
    )


def test_scalar_matrix_expands_by_the_identity():
    M = consistent_mass(MESH.X, MESH.T, 2.0)
    # XFEM-like extra couplings between nodes that share no element
    extra = sp.coo_matrix((np.full(2, 0.25), ([0, N - 1], [N - 1, 0])), shape=(N, N))
    M = (M + extra).tocoo()
    fixed = np.array([3, 7])
    pattern = assembly_pattern(T, N, fixed, coupling=M)
    slots = scalar_slots(pattern, M.row, M.col)
    A = to_scipy(pattern, assemble_scalar(pattern, jnp.asarray(slots), jnp.asarray(M.data))).toarray()
    keep = _free_dofs(N, fixed)
    np.testing.assert_allclose(A, np.kron(M.toarray(), np.eye(3))[np.ix_(keep, keep)], atol=1e-15)
    np.testing.assert_array_equal(slots[np.isin(M.row, fixed) | np.isin(M.col, fixed)], pattern.nnz)


def test_repeated_elements_and_unused_nodes():
    # XFEM sub-elements: the same DOF nodes in several elements, and DOF nodes coupled only by the mass
    T2 = np.concatenate([T, T[:3], [[0, 1, 2, 3]]]) + 2
    n = N + 4
    H = RNG.normal(size=(len(T2), 12, 12))
    coupling = sp.identity(n, format="csr")
    pattern = assembly_pattern(T2, n, coupling=coupling)
    A = to_scipy(pattern, assemble_matrix(pattern, jnp.asarray(H))).toarray()
    np.testing.assert_allclose(A, _dense_matrix(T2, H, n), atol=1e-13)
    # the unused nodes 0, 1, n-2, n-1 carry just their diagonal blocks (zero here)
    unused = _free_dofs(n, np.arange(2, n - 2))
    assert pattern.nnz == np.count_nonzero(A) + 9 * 4
    np.testing.assert_array_equal(A[unused], 0.0)


def test_cut_system_pattern_is_scipy_assembly():
    # an XFEM system after two crossing cuts: enriched copies in many pieces, mass couplings beyond the elements
    model = xfem_model(tall_box(), RHO)
    model.cut(plane())
    model.cut(plane((0.43, 0.5, 0.75), (1.0, 0.06, -0.03)))
    system = model.system()
    T2, n, fixed = np.asarray(system.T), system.n, np.asarray(system.fixed)
    M = sp.coo_matrix((np.asarray(system.mass_values), (np.asarray(system.mass_rows), np.asarray(system.mass_cols))))
    exact = assembly_pattern(T2, n, fixed, coupling=M)
    pattern = assembly_pattern(T2, n, fixed, coupling=M, nnz_capacity=exact.nnz + 50)
    keep = _free_dofs(n, fixed)
    # the structure: the element blocks and the mass blocks, each stored once, columns ascending
    rows, cols = np.repeat(_dofs(T2), 12, axis=1).ravel(), np.tile(_dofs(T2), 12).ravel()
    structure = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(3 * n, 3 * n))
    structure = (structure + sp.kron(abs(M), np.ones((3, 3)))).tocsr()[keep][:, keep]
    structure.sum_duplicates()
    used = int(pattern.indptr[-1])
    np.testing.assert_array_equal(np.asarray(pattern.indptr), structure.indptr)
    np.testing.assert_array_equal(np.asarray(pattern.indices)[:used], structure.indices)
    assert used == exact.nnz and pattern.nnz == exact.nnz + 50
    # the values: scipy's duplicate-summing assembly of the element blocks and the mass (x) I3
    H = RNG.normal(size=(len(T2), 12, 12))
    data = assemble_matrix(pattern, jnp.asarray(H)) + assemble_scalar(
        pattern, jnp.asarray(scalar_slots(pattern, M.row, M.col)), jnp.asarray(M.data)
    )
    expected = sp.csr_matrix((H.ravel(), (rows, cols)), shape=(3 * n, 3 * n)) + sp.kron(M, np.eye(3))
    np.testing.assert_allclose(to_scipy(pattern, data).toarray(), expected.tocsr()[keep][:, keep].toarray(), atol=1e-12)
    np.testing.assert_array_equal(np.asarray(data)[used:], 0.0)
    # made of full 3 x 3 blocks, as its pattern promises the device CG, padding blocks and all
    assert pattern.csr.full_blocks and _full_blocks(np.asarray(pattern.indptr), np.asarray(pattern.indices)[:used], 3)
    x = RNG.normal(size=3 * pattern.n_free)
    np.testing.assert_allclose(matvec(pattern, data, jnp.asarray(x)), to_scipy(pattern, data) @ x, atol=1e-12)
    # the system's mass data (its pattern's host pairs) as the public scalar slots place it
    mass_data = assemble_scalar(exact, jnp.asarray(scalar_slots(exact, M.row, M.col)), jnp.asarray(M.data))
    np.testing.assert_array_equal(np.asarray(system.mass_data), mass_data)


def test_vector_restrict_and_matvec():
    g = RNG.normal(size=(len(T), 12))
    expected = np.zeros(3 * N)
    np.add.at(expected, _dofs(T), g)
    v = assemble_vector(jnp.asarray(T), jnp.asarray(g), N)
    np.testing.assert_allclose(np.asarray(v).ravel(), expected, atol=1e-13)
    fixed = np.array([5, 6])
    pattern = assembly_pattern(T, N, fixed)
    assert_same_run(restrict(pattern, v), expected[_free_dofs(N, fixed)], atol=1e-13)
    data = assemble_matrix(pattern, jnp.asarray(RNG.normal(size=(len(T), 12, 12))))
    x = RNG.normal(size=3 * pattern.n_free)
    np.testing.assert_allclose(matvec(pattern, data, jnp.asarray(x)), to_scipy(pattern, data) @ x, atol=1e-12)


def test_assembly_under_jit_and_grad():
    pattern = assembly_pattern(T, N, np.array([0]))
    weights = jnp.asarray(RNG.normal(size=pattern.nnz))
    H = jnp.asarray(RNG.normal(size=(len(T), 12, 12)))
    loss = jax.jit(lambda H: jnp.sum(weights * assemble_matrix(pattern, H)))
    # the derivative of an entry is the weight of its slot, 0 for entries on the fixed node
    slots = np.asarray(pattern.hessian_slots)
    expected = np.where(slots < pattern.nnz, np.asarray(weights)[np.minimum(slots, pattern.nnz - 1)], 0.0)
    np.testing.assert_allclose(jax.grad(loss)(H).ravel(), expected)
    np.testing.assert_allclose(loss(H), np.sum(expected * np.asarray(H).ravel()), rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.int32, np.int64])
@pytest.mark.parametrize("shape", [(0,), (1,), (1000,), (300, 4)])
def test_sorted_unique_is_np_unique(dtype, shape):
    values = RNG.integers(-50, 200, size=shape).astype(dtype)
    unique = sorted_unique(values)
    assert unique.dtype == values.dtype
    np.testing.assert_array_equal(unique, np.unique(values))


def test_bad_input():
    with pytest.raises(ValueError, match="T: expected integer elements"):
        assembly_pattern(T[:, :3], N)
    with pytest.raises(ValueError, match="T: node indices"):
        assembly_pattern(T, N - 1)
    with pytest.raises(ValueError, match="fixed: node indices"):
        assembly_pattern(T, N, np.array([N]))
    with pytest.raises(ValueError, match="fixed: repeated"):
        assembly_pattern(T, N, np.array([1, 1]))
    with pytest.raises(ValueError, match="coupling: expected shape"):
        assembly_pattern(T, N, coupling=sp.identity(N + 1))
    pattern = assembly_pattern(T, N)
    with pytest.raises(ValueError, match="not in the pattern"):
        scalar_slots(pattern, np.array([0]), np.array([N - 1]))
    with pytest.raises(ValueError, match="H: expected shape"):
        assemble_matrix(pattern, jnp.zeros((len(T), 12, 11)))
    with pytest.raises(ValueError, match="T, g: expected shapes"):
        assemble_vector(jnp.asarray(T), jnp.zeros((len(T), 9)), N)
