"""Helpers shared by the test packages: a flat grid mesh and a finite-difference gradient check."""

from __future__ import annotations

import numpy as np


def grid(n: int = 10):
    """The unit square in z = 0 as an n x n grid of quads, two triangles each."""
    x, y = np.meshgrid(np.linspace(0, 1, n + 1), np.linspace(0, 1, n + 1), indexing="ij")
    V = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)
    index = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    return V, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])


def check_gradient(loss, params, rtol: float = 1e-5, step: float = 1e-6):
    """jax.grad of ``loss`` at ``params`` against central finite differences, component by component."""
    import jax

    grad = jax.grad(loss)(params)
    numeric = np.array([(loss(params.at[i].add(step)) - loss(params.at[i].add(-step))) / (2 * step)
                        for i in range(len(params))])
    np.testing.assert_allclose(grad, numeric, rtol=rtol, atol=1e-6 * float(np.abs(numeric).max()))
