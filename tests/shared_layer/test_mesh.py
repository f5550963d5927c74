"""``_jaxcga_shared.mesh``: the bounding-box diagonal and the signed volume against closed forms and trimesh."""

import jax
import jax.numpy as jnp
import numpy as np
import trimesh

from _jaxcga_shared.mesh import bounding_diagonal, signed_volume


def test_bounding_diagonal_of_a_box_and_of_no_points():
    V = np.random.default_rng(0).uniform(-1.0, 1.0, (200, 3)) * [1.0, 2.0, 3.0]
    V[:2] = [[-1.0, -2.0, -3.0], [1.0, 2.0, 3.0]]  # the corners of the box
    assert abs(bounding_diagonal(V) - 2 * np.sqrt(14.0)) < 1e-12
    assert bounding_diagonal(jnp.asarray(V)) == bounding_diagonal(V)
    assert bounding_diagonal(np.zeros((0, 3))) == 0.0


def test_signed_volume_of_a_box_a_reversed_one_and_a_batch():
    box = trimesh.creation.box(extents=(4.0, 1.0, 1.0)).subdivide()
    V, F = np.asarray(box.vertices), np.asarray(box.faces)
    np.testing.assert_allclose(signed_volume(jnp.asarray(V), F), 4.0, rtol=1e-12)
    np.testing.assert_allclose(signed_volume(jnp.asarray(V), F[:, ::-1]), -4.0, rtol=1e-12)
    sphere = trimesh.creation.icosphere(subdivisions=2)
    Vs = np.asarray(sphere.vertices)
    np.testing.assert_allclose(signed_volume(jnp.asarray(Vs), np.asarray(sphere.faces)), sphere.volume, rtol=1e-12)
    scales = jnp.asarray([1.0, 2.0, 0.5])
    batch = scales[:, None, None] * jnp.asarray(V)[None]
    np.testing.assert_allclose(jax.jit(signed_volume)(batch, F), 4.0 * scales**3, rtol=1e-12)
    # d volume / d V is the area-weighted vertex normal / 3: a uniform scale s changes it by 3 s^2 V0
    grad = jax.grad(lambda s: signed_volume(s * jnp.asarray(V), F))(1.0)
    np.testing.assert_allclose(grad, 12.0, rtol=1e-12)
