"""Trajectories across cuts (``xfem.simulate``): frame by frame the same as ``XFEMModel.cut`` and ``step``, and
differentiable through the cut's DOF copy map (gradients with respect to Young's modulus, the initial velocity
and the forces against central differences; the cut's combinatorics are fixed)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from xfem import Material, State, box_tets, plane_cut_solid, simulate, xfem_model

H, RHO = 0.02, 1e3
MATERIAL = Material(2e5, 0.4)
CONVERGED = dict(newton_iterations=20, tolerance=1e-12)
BAR = box_tets((4, 1, 1), size=(4.0, 1.0, 1.0))
X = np.asarray(BAR.X)
FIXED = np.flatnonzero(X[:, 0] == 0)
# a slab across the bar near x = 2.5, tilted so that it meets no node, edge or face exactly: the end falls
CUT = plane_cut_solid(np.array([2.47, 0.5, 0.5]), np.array([1.0, 0.03, -0.02]), 3.0, 1e-3)
STEPS, CUT_FRAME = 4, 3


def _model():
    return xfem_model(BAR, RHO, fixed=FIXED)


def test_trajectory_equals_the_model_stepped_frame_by_frame():
    model = _model()
    n_before = len(model.dof_sid)
    segments = simulate(model, [(CUT_FRAME, CUT)], MATERIAL, H, STEPS)
    assert [s.x.shape[0] for s in segments] == [CUT_FRAME - 1, STEPS - CUT_FRAME + 1]
    assert segments[0].x.shape[1] == n_before and segments[1].x.shape[1] == len(model.dof_sid) > n_before
    assert model.pieces() == 2
    frames = [(s.x[k], s.v[k]) for s in segments for k in range(s.x.shape[0])]

    reference = _model()
    for frame in range(1, STEPS + 1):
        if frame == CUT_FRAME:
            reference.cut(CUT)
        reference.step(H, MATERIAL)
        x, v = frames[frame - 1]
        np.testing.assert_allclose(x, reference.state.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(v, reference.state.v, rtol=0, atol=1e-8)
    assert float(jnp.min(segments[1].v[-1, :, 2])) < -0.1  # the released end falls


def test_gradients_across_the_cut_match_central_differences():
    model = _model()
    rng = np.random.default_rng(5)
    v0 = jnp.asarray(rng.normal(size=X.shape))
    direction = jnp.asarray(rng.normal(size=X.shape))

    def loss(young, v0, scale):
        segments = simulate(model, [(CUT_FRAME, CUT)], Material(young, jnp.asarray(0.4)), H, STEPS,
                            forces=lambda k, system: scale * system.force, state=State(jnp.asarray(X), v0),
                            **CONVERGED)
        # fixed weights per segment (the DOF counts are known once the model is cut)
        weights = [jnp.asarray(np.random.default_rng(k).normal(size=s.x.shape)) for k, s in enumerate(segments)]
        return sum(jnp.sum(w * s.x) + 0.5 * jnp.sum(s.v**2) for w, s in zip(weights, segments, strict=True))

    args = (jnp.asarray(2e5), v0, jnp.asarray(1.0))
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2)))
    grad = value_and_grad(*args)[1]
    assert model.pieces() == 2  # cut once, on the first trace

    def central(i, d, eps):
        plus, minus = list(args), list(args)
        plus[i], minus[i] = args[i] + eps * d, args[i] - eps * d
        return float(value_and_grad(*plus)[0] - value_and_grad(*minus)[0]) / (2 * eps)

    np.testing.assert_allclose(grad[0], central(0, 1.0, 2e5 * 1e-4), rtol=1e-5)
    np.testing.assert_allclose(jnp.sum(grad[1] * direction), central(1, direction, 1e-5), rtol=1e-5)
    np.testing.assert_allclose(grad[2], central(2, 1.0, 1e-4), rtol=1e-5)


def test_a_second_call_reuses_the_cuts_and_bad_input():
    model = _model()
    first = simulate(model, schedule := [(1, CUT)], MATERIAL, H, 2)
    system = model.system()
    assert first[0].x.shape[0] == 0 and first[1].x.shape[0] == 2  # a cut at frame 1: no frame before it
    second = simulate(model, schedule, MATERIAL, H, 2)
    assert model.system() is system and model.pieces() == 2
    np.testing.assert_array_equal(second[1].x, first[1].x)
    with pytest.raises(ValueError, match="schedule: expected"):
        simulate(model, [(3, CUT)], MATERIAL, H, 2)
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        simulate(model, [], MATERIAL, H, 0)
    with pytest.raises(ValueError, match="model: expected an XFEMModel"):
        simulate(None, [], MATERIAL, H, 2)
