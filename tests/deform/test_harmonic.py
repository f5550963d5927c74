"""Harmonic fields (deformation paper sec. VIII): agreement with igl.harmonic, partition of unity, the
maximum principle of mean-value weights, linear precision of both Laplacians on flat meshes, the
prefactored solve as a JAX function (jit, vmap, gradients by finite differences), bad input."""

from __future__ import annotations

from pathlib import Path

import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
from tests.shared import check_gradient, grid

DATA = Path(__file__).resolve().parents[1] / "data"
ARM = deform.default_arm().mesh
ARM5 = deform.load_model(DATA / "Arm5.glb", weld=True).mesh


def _arm_handles(V):
    x = V[:, 0]
    return [np.flatnonzero(x < 0.0), np.flatnonzero(x > 0.75), np.flatnonzero(np.abs(x - 0.4) < 0.01)]


def _one_hot(handles):
    b = np.concatenate(handles)
    bc = np.zeros((len(b), len(handles)))
    bc[np.arange(len(b)), np.repeat(np.arange(len(handles)), [len(h) for h in handles])] = 1.0
    return b, bc


@pytest.mark.parametrize("name", ["arm", "Arm5"])
def test_cotangent_fields_equal_igl_harmonic(name):
    mesh = ARM if name == "arm" else ARM5
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    if name == "arm":
        handles = _arm_handles(V)
    else:  # Arm5: the shoulder ring, the fingertips, a band around the elbow
        y = V[:, 1]
        handles = [np.flatnonzero(y < 2.0), np.flatnonzero(y > 70.0), np.flatnonzero(np.abs(y - 39.0) < 0.5)]
    fields = np.asarray(deform.harmonic_fields(V, F, handles))
    b, bc = _one_hot(handles)
    np.testing.assert_allclose(fields, np.asarray(igl.harmonic(V, F, b, bc, 1)), atol=1e-8)
    np.testing.assert_allclose(fields.sum(axis=1), 1.0, atol=1e-10)
    for h, part in enumerate(handles):
        np.testing.assert_array_equal(fields[part, h], 1.0)


def test_mean_value_fields_sum_to_one_and_keep_the_maximum_principle():
    V, F = np.asarray(ARM.V, np.float64), np.asarray(ARM.F)
    fields = np.asarray(deform.harmonic_fields(V, F, _arm_handles(V), laplacian="mean_value"))
    np.testing.assert_allclose(fields.sum(axis=1), 1.0, atol=1e-10)
    assert fields.min() >= -1e-12 and fields.max() <= 1.0 + 1e-12
    # harmonic: the rows of free vertices of L annihilate every field
    L = deform.mean_value_laplacian(V, F)
    free = np.setdiff1d(np.arange(len(V)), np.concatenate(_arm_handles(V)))
    assert np.abs(L[free] @ fields).max() < 1e-10


@pytest.mark.parametrize("kind", deform.LAPLACIANS)
def test_both_laplacians_reproduce_linear_functions_on_a_flat_mesh(kind):
    """Linear precision: on a planar mesh, a linear function is harmonic at interior vertices, so its
    boundary values reproduce it exactly (an independent check of the assembled weights)."""
    V, F = grid(12)
    rng = np.random.default_rng(0)
    interior = (V[:, 0] > 0) & (V[:, 0] < 1) & (V[:, 1] > 0) & (V[:, 1] < 1)
    V[interior, :2] += rng.uniform(-0.03, 0.03, (interior.sum(), 2))  # an irregular, still planar mesh
    L = deform.laplacian(V, F, kind)
    assert np.abs(L[np.flatnonzero(interior)] @ V).max() < 1e-12
    np.testing.assert_allclose(np.asarray(L.sum(axis=1)).ravel(), 0.0, atol=1e-12)
    boundary = np.flatnonzero(~interior)
    linear = 0.3 + 2.0 * V[:, 0] - 1.5 * V[:, 1]
    data = deform.harmonic_precompute(V, F, boundary, laplacian=kind)
    np.testing.assert_allclose(deform.harmonic_solve(data, jnp.asarray(linear[boundary])), linear, atol=1e-12)


@pytest.mark.parametrize("kind", deform.LAPLACIANS)
def test_the_solve_is_a_differentiable_batched_jax_function(kind):
    V, F = np.asarray(ARM.V, np.float64), np.asarray(ARM.F)
    handles = _arm_handles(V)
    b, bc = _one_hot(handles)
    data = deform.harmonic_precompute(V, F, b, laplacian=kind)

    def solver(values):
        return deform.harmonic_solve(data, values)

    np.testing.assert_allclose(
        jax.jit(deform.harmonic_solve)(data, jnp.asarray(bc)),
        deform.harmonic_fields(V, F, handles, laplacian=kind),
        atol=1e-12,
    )
    # vmap over boundary values equals one solve per column
    batched = jax.vmap(solver, in_axes=1, out_axes=1)(jnp.asarray(bc))
    np.testing.assert_allclose(batched, solver(jnp.asarray(bc)), atol=1e-12)
    # reverse-mode gradient with respect to the boundary values (the unsymmetric mean-value system
    # needs the transposed solve)
    probe = jnp.asarray(np.random.default_rng(1).normal(size=len(V)))

    def loss(values):
        return jnp.sum(jnp.sin(solver(values)) * probe)

    params = jnp.asarray(np.random.default_rng(2).uniform(size=len(b)))
    # a step of 1e-4: a GPU's iterative solve (to 1e-12) is noise at 1e-6 (central differences: 1e-9 off here)
    check_gradient(jax.jit(loss), params, rtol=1e-6, step=1e-4)


def test_bad_input():
    V, F = np.asarray(ARM.V, np.float64), np.asarray(ARM.F)
    handles = _arm_handles(V)
    with pytest.raises(ValueError, match="laplacian"):
        deform.harmonic_fields(V, F, handles, laplacian="uniform")
    with pytest.raises(ValueError, match="kind"):
        deform.laplacian(V, F, "uniform")
    with pytest.raises(ValueError, match="disjoint"):
        deform.harmonic_fields(V, F, [handles[0], handles[0][:3]])
    with pytest.raises(ValueError, match="at least one vertex"):
        deform.harmonic_fields(V, F, [handles[0], []])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="lie in"):
        deform.harmonic_precompute(V, F, np.array([0, len(V)]))
    with pytest.raises(ValueError, match="bc: expected shape"):
        deform.harmonic_solve(deform.harmonic_precompute(V, F, handles[0]), jnp.ones(3))
    # two disjoint copies of the arm, constrained on one only: refused when asked (they follow by default,
    # tests/deform/test_multipart.py)
    two = np.concatenate([V, V + 2.0])
    with pytest.raises(ValueError, match="1 of the mesh's 2 connected part"):
        deform.harmonic_fields(two, np.concatenate([F, F + len(V)]), handles, unhandled="error")
    with pytest.raises(ValueError, match="V: non-finite"):
        deform.harmonic_fields(np.full_like(V, np.nan), F, handles)
