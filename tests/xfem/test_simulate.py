"""Trajectories across cuts (``xfem.simulate``): frame by frame the same as ``XFEMModel.cut`` and ``step``, and
differentiable through the cut's DOF copy map (gradients with respect to Young's modulus, the initial velocity
and the forces against central differences; the cut's combinatorics are fixed). Plane cuts: the same as the
solid cuts at the same planes, and differentiable in the plane's height and tilt (central differences)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from tests.shared import assert_same_run
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


@pytest.mark.slow  # 20 s on 2 cores: in the slow job (`make test-slow`), to keep `make test` under 10 minutes
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


@pytest.mark.slow  # 25 s on 2 cores: in the slow job (`make test-slow`), to keep `make test` under 10 minutes
def test_gradients_across_the_cut_match_central_differences():
    model = _model()
    rng = np.random.default_rng(5)
    v0 = jnp.asarray(rng.normal(size=X.shape))
    direction = jnp.asarray(rng.normal(size=X.shape))

    def loss(young, v0, scale):
        segments = simulate(
            model,
            [(CUT_FRAME, CUT)],
            Material(young, jnp.asarray(0.4)),
            H,
            STEPS,
            forces=lambda k, system: scale * system.force,
            state=State(jnp.asarray(X), v0),
            **CONVERGED,
        )
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


@pytest.mark.slow  # 10-36 s on 2 cores: the fast suite's 10-minute budget
def test_a_second_call_reuses_the_cuts_and_bad_input():
    model = _model()
    first = simulate(model, schedule := [(1, CUT)], MATERIAL, H, 2)
    system = model.system()
    assert first[0].x.shape[0] == 0 and first[1].x.shape[0] == 2  # a cut at frame 1: no frame before it
    second = simulate(model, schedule, MATERIAL, H, 2)
    assert model.system() is system and model.pieces() == 2
    assert_same_run(second[1].x, first[1].x, atol=1e-12)
    with pytest.raises(ValueError, match="schedule: expected"):
        simulate(model, [(3, CUT)], MATERIAL, H, 2)
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        simulate(model, [], MATERIAL, H, 0)
    with pytest.raises(ValueError, match="model: expected an XFEMModel"):
        simulate(None, [], MATERIAL, H, 2)


# plane cuts: a bar 0.2 x 0.2 x 1 hanging from its top face, cut by a slab at a height inside the layer 0.375-0.5
# (8 layers), tilted by theta about y
HANGING = box_tets((2, 2, 8), (0.2, 0.2, 1.0))
EPS, PLANE_FRAME, PLANE_STEPS = 1e-2, 2, 3
NOTCH = plane_cut_solid(np.array([0.09, 0.1, 0.45]), np.array([1.0, 0.0, 0.0]), 0.15, 0.02)


def _hanging():
    return xfem_model(HANGING, RHO, fixed=np.flatnonzero(np.asarray(HANGING.X)[:, 2] > 1 - 1e-9))


def _plane(height, theta):
    return (
        jnp.stack([jnp.asarray(0.1), jnp.asarray(0.1), height]),
        jnp.stack([jnp.sin(theta), jnp.zeros_like(theta), jnp.cos(theta)]),
    )


@pytest.mark.slow  # 10-36 s on 2 cores: the fast suite's 10-minute budget
def test_plane_cuts_equal_the_solid_cuts():
    """A notch (a solid) at frame 1 and a tilted slab at frame 2 as ``plane_cuts``: every frame equals the schedule
    of both solids (``plane_cut_solid`` at the same plane) cut by the model; the model is left uncut."""
    point, normal = (np.asarray(a) for a in _plane(0.43, 0.2))
    model = _hanging()
    n_before = len(model.dof_sid)
    planes = simulate(model, [(1, NOTCH)], MATERIAL, H, PLANE_STEPS, plane_cuts=[(PLANE_FRAME, point, normal, EPS)])
    assert len(model.dof_sid) == n_before and model.pieces() == 1
    solids = simulate(
        _hanging(), [(1, NOTCH), (PLANE_FRAME, plane_cut_solid(point, normal, 5.0, EPS))], MATERIAL, H, PLANE_STEPS
    )
    assert [s.x.shape for s in planes] == [s.x.shape for s in solids] and len(planes) == 3
    assert planes[2].x.shape[1] > n_before
    for a, b in zip(planes, solids, strict=True):
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.v, b.v, rtol=0, atol=1e-10)


@pytest.mark.slow  # 24 s on 2 cores: in the slow job (`make test-slow`), to keep `make test` under 10 minutes
def test_gradient_with_respect_to_the_plane_matches_central_differences():
    """The hanging bar's positions after the cut (a random linear functional of the last frame), differentiated
    with respect to the slab's height and tilt through the cut and two converged steps; central differences of
    simulate at shifted planes (the combinatorics do not change within the step: the replay, which equals the
    Booleans, test above)."""
    model = _hanging()
    weights = {}

    def outcome(height, theta):
        point, normal = _plane(height, theta)
        last = simulate(
            model, [], MATERIAL, H, PLANE_STEPS, plane_cuts=[(PLANE_FRAME, point, normal, EPS)], **CONVERGED
        )[-1]
        if "w" not in weights:  # fixed once the DOF count after the cut is known
            weights["w"] = np.random.default_rng(3).normal(size=last.x.shape[1:])
        return jnp.sum(weights["w"] * last.x[-1])

    height, theta = 0.43, 0.2
    gradient = jax.grad(outcome, argnums=(0, 1))(jnp.asarray(height), jnp.asarray(theta))
    step = 1e-5
    for k, g in enumerate(gradient):
        shift = step * np.eye(2)[k]
        difference = (outcome(height + shift[0], theta + shift[1]) - outcome(height - shift[0], theta - shift[1])) / (
            2 * step
        )
        assert abs(g - difference) <= 1e-5 * abs(difference), (k, g, difference)
    assert abs(gradient[0]) > 0 and abs(gradient[1]) > 0


def test_plane_cuts_bad_input():
    model = _hanging()
    point, normal = np.array([0.1, 0.1, 0.43]), np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="plane_cuts: expected"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(3, point, normal, EPS)])
    with pytest.raises(ValueError, match="plane_cuts: expected"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, normal)])
    with pytest.raises(ValueError, match=r"normal \(plane_cuts\[0\]\): expected a unit normal"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, 2 * normal, EPS)])
    with pytest.raises(ValueError, match=r"epsilon \(plane_cuts\[0\]\)"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, normal, 0.0)])
    with pytest.raises(ValueError, match=r"point \(plane_cuts\[0\]\): simulate finds the pieces"):
        jax.jit(lambda p: simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, p, normal, EPS)])[-1].x)(point)
