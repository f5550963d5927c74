"""Shared models of the XFEM tests: a tall box, a tilted plane cut across it, a deformed state, random material
points, and the material and step constants."""

import jax.numpy as jnp
import manifold3d
import numpy as np
from numpy.typing import ArrayLike

from xfem import Material, State, box_tets, plane_cut_solid

RHO, EPS, H = 1e3, 1e-3, 0.01
MATERIAL = Material(2.5e6, 0.25)  # Lamé mu = lam = 1e6
G = np.array([0.0, 0.0, -9.81])
# a plane across the tall box, tilted so that it meets no node, face or edge of the mesh exactly
POINT, NORMAL = np.array([0.5, 0.5, 0.61]), np.array([0.07, -0.04, 1.0])


def tall_box():
    return box_tets((2, 2, 3), size=(1.0, 1.0, 1.5))


def plane(point: ArrayLike = POINT, normal: ArrayLike = NORMAL, extent: float = 3.0) -> manifold3d.Manifold:
    return plane_cut_solid(np.asarray(point, np.float64), np.asarray(normal, np.float64), extent, EPS)


def deformed_state(mesh, seed=0):
    rng = np.random.default_rng(seed)
    X = np.asarray(mesh.X)
    return State(jnp.asarray(X + 0.02 * rng.normal(size=X.shape)), jnp.asarray(rng.normal(size=X.shape)))


def random_points(mesh, k, seed=1):
    """k random points inside random tets: (k, 3) points and (k,) tets, and the barycentric weights (k, 4)."""
    rng = np.random.default_rng(seed)
    elements = rng.integers(0, mesh.T.shape[0], k)
    w = rng.dirichlet(np.ones(4), k)
    return np.einsum("ka,kaj->kj", w, np.asarray(mesh.X)[np.asarray(mesh.T)[elements]]), elements, w
