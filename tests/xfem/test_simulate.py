"""Trajectories across cuts (``xfem.simulate``): frame by frame the same as ``XFEMModel.cut`` and ``step``, and
differentiable through the cut's DOF copy map (gradients at the defaults with respect to Young's modulus, the
initial velocity and the forces against central differences, to 1e-6; the cut's combinatorics are fixed). The host
phase is a ``CutPlan`` the caller holds (``plan_cuts``): made once and passed twice, its Booleans run once and the
trajectories equal a plan-less call's; a plan for another model, schedule, step count or set of plane cuts is
refused; nothing else keeps a dropped plan. Plane cuts: the same as the solid cuts at the same planes,
differentiable in the plane's height and tilt (central differences); prepared once (``plane_cut_simulation``, or a
plan passed to ``simulate`` under ``jax.jit``), jit- and vmap-able over the planes: a batch of tilts in one vmapped
gradient equals separate calls, and planes that move past the pieces found raise."""

import gc
import weakref
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import xfem
import xfem._subdomains
from tests.shared import assert_same_run
from xfem import Material, State, box_tets, plan_cuts, plane_cut_solid, simulate, xfem_model

H, RHO = 0.02, 1e3
MATERIAL = Material(2e5, 0.4)
# the paper's single Newton iteration, as XFEMModel.step
PAPER: dict[str, Any] = dict(newton_iterations=1, tolerance=None)
BAR = box_tets((4, 1, 1), size=(4.0, 1.0, 1.0))
X = np.asarray(BAR.X)
FIXED = np.flatnonzero(X[:, 0] == 0)
# a slab across the bar near x = 2.5, tilted so that it meets no node, edge or face exactly: the end falls
CUT = plane_cut_solid(np.array([2.47, 0.5, 0.5]), np.array([1.0, 0.03, -0.02]), 3.0, 1e-3)
STEPS, CUT_FRAME = 4, 3


def _model():
    return xfem_model(BAR, RHO, fixed=FIXED)


@pytest.mark.slow
def test_trajectory_equals_the_model_stepped_frame_by_frame():
    model = _model()
    n_before = len(model.dof_sid)
    segments = simulate(model, [(CUT_FRAME, CUT)], MATERIAL, H, STEPS, **PAPER)
    assert [s.x.shape[0] for s in segments] == [CUT_FRAME - 1, STEPS - CUT_FRAME + 1]
    assert len(model.dof_sid) == n_before and model.pieces() == 1  # the cuts were made on a copy
    frames = [(s.x[k], s.v[k]) for s in segments for k in range(s.x.shape[0])]

    reference = _model()
    for frame in range(1, STEPS + 1):
        if frame == CUT_FRAME:
            reference.cut(CUT)
        reference.step(H, MATERIAL)
        x, v = frames[frame - 1]
        np.testing.assert_allclose(x, reference.state.x, rtol=0, atol=1e-10)
        np.testing.assert_allclose(v, reference.state.v, rtol=0, atol=1e-8)
    assert segments[0].x.shape[1] == n_before and segments[1].x.shape[1] == len(reference.dof_sid) > n_before
    assert float(jnp.min(segments[1].v[-1, :, 2])) < -0.1  # the released end falls


@pytest.mark.slow
def test_gradients_across_the_cut_match_central_differences_at_the_defaults():
    model = _model()
    rng = np.random.default_rng(5)
    v0 = jnp.asarray(rng.normal(size=X.shape))
    direction = jnp.asarray(rng.normal(size=X.shape))

    plan = plan_cuts(model, schedule := [(CUT_FRAME, CUT)], STEPS)  # the Booleans, once

    def loss(young, v0, scale):
        segments = simulate(
            model,
            schedule,
            Material(young, jnp.asarray(0.4)),
            H,
            STEPS,
            plan=plan,
            forces=lambda k, system: scale * system.force,
            state=State(jnp.asarray(X), v0),
        )
        # fixed weights per segment (the DOF counts are known once the model is cut)
        weights = [jnp.asarray(np.random.default_rng(k).normal(size=s.x.shape)) for k, s in enumerate(segments)]
        value = sum(jnp.sum(w * s.x) + 0.5 * jnp.sum(s.v**2) for w, s in zip(weights, segments, strict=True))
        return value, jnp.all(jnp.concatenate([s.stats.converged for s in segments]))

    args = (jnp.asarray(2e5), v0, jnp.asarray(1.0))
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2), has_aux=True))
    (_, converged), grad = value_and_grad(*args)
    assert plan.model.pieces() == 2 and model.pieces() == 1 and converged  # cut once, by the plan, on its copy

    def central(i, d, eps):
        plus, minus = list(args), list(args)
        plus[i], minus[i] = args[i] + eps * d, args[i] - eps * d
        return float(value_and_grad(*plus)[0][0] - value_and_grad(*minus)[0][0]) / (2 * eps)

    np.testing.assert_allclose(grad[0], central(0, 1.0, 2e5 * 1e-4), rtol=1e-6)
    np.testing.assert_allclose(jnp.sum(grad[1] * direction), central(1, direction, 1e-5), rtol=1e-6)
    np.testing.assert_allclose(grad[2], central(2, 1.0, 1e-4), rtol=1e-6)


@pytest.fixture
def booleans(monkeypatch):
    """The count of mesh Booleans run (the cut solid subtracted from a subdomain's), by a spy on their one entry."""
    calls = []
    difference = xfem._subdomains._difference

    def spy(solid, cut):
        calls.append(1)  # list.append is atomic: the Booleans run on the model's threads
        return difference(solid, cut)

    monkeypatch.setattr(xfem._subdomains, "_difference", spy)
    return calls


def test_a_plan_made_once_runs_the_booleans_once(booleans):
    model = _model()
    plan = plan_cuts(model, schedule := [(1, CUT)], 2)
    made = len(booleans)
    assert made > 0 and plan.made_for is model and plan.schedule[0][1] is CUT
    assert model.pieces() == 1 and plan.model is not model and plan.model.pieces() == 2 and plan.model.closed
    system = model.system()
    first = simulate(model, schedule, MATERIAL, H, 2, plan=plan, **PAPER)
    second = simulate(model, schedule, MATERIAL, H, 2, plan=plan, **PAPER)
    assert len(booleans) == made and model.system() is system  # no Boolean and no cut in the calls
    assert first[0].x.shape[0] == 0 and first[1].x.shape[0] == 2  # a cut at frame 1: no frame before it
    alone = simulate(_model(), schedule, MATERIAL, H, 2, **PAPER)  # a plan of its own, made and dropped
    assert len(booleans) == 2 * made
    for a, b, c in zip(first, second, alone, strict=True):
        assert_same_run(b.x, a.x, atol=1e-12)
        np.testing.assert_allclose(a.x, c.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.v, c.v, rtol=0, atol=1e-12)


def test_simulate_without_a_plan_leaves_the_model_as_it_was():
    """Plan-less calls cut a copy each: two calls on one model (with a cut of its own before) give the same
    trajectory, and the model's cuts, pieces, DOFs and state are those it had."""
    model, cut_model = _model(), _model()  # cut_model: cut by both solids, for the DOF counts
    for m in (model, cut_model):
        m.cut(plane_cut_solid(np.array([1.53, 0.5, 0.5]), np.array([1.0, -0.02, 0.03]), 3.0, 1e-3))
    cut_model.cut(CUT)
    model.state = State(model.state.x + 0.01 * np.random.default_rng(2).normal(size=model.state.x.shape), model.state.v)
    before = (len(model.cuts), model.pieces(), model.dof_sid.copy(), np.array(model.state.x), np.array(model.state.v))
    first = simulate(model, [(2, CUT)], MATERIAL, H, 2, **PAPER)
    second = simulate(model, [(2, CUT)], MATERIAL, H, 2, **PAPER)
    assert [s.x.shape[:2] for s in first] == [(1, len(before[2])), (1, len(cut_model.dof_sid))]
    for a, b in zip(first, second, strict=True):
        np.testing.assert_allclose(b.x, a.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(b.v, a.v, rtol=0, atol=1e-12)
    assert (len(model.cuts), model.pieces()) == before[:2] == (1, 2)
    np.testing.assert_array_equal(model.dof_sid, before[2])
    np.testing.assert_array_equal(model.state.x, before[3])
    np.testing.assert_array_equal(model.state.v, before[4])


def test_a_plan_for_another_model_schedule_or_step_count_is_refused():
    model = _model()
    plan = plan_cuts(model, schedule := [(1, CUT)], 2)
    other = _model()
    with pytest.raises(ValueError, match="plan: made for another model"):
        simulate(other, schedule, MATERIAL, H, 2, plan=plan)
    with pytest.raises(ValueError, match="plan: made for steps=2, got steps=3"):
        simulate(model, schedule, MATERIAL, H, 3, plan=plan)
    with pytest.raises(ValueError, match="plan: made for another schedule"):
        simulate(model, [(2, CUT)], MATERIAL, H, 2, plan=plan)
    # an equal solid made anew is another object: the plan compares the solids it keeps by identity
    again = plane_cut_solid(np.array([2.47, 0.5, 0.5]), np.array([1.0, 0.03, -0.02]), 3.0, 1e-3)
    with pytest.raises(ValueError, match="plan: made for another schedule"):
        simulate(model, [(1, again)], MATERIAL, H, 2, plan=plan)
    with pytest.raises(ValueError, match="plan: made for plane cuts at frames"):
        simulate(model, schedule, MATERIAL, H, 2, plan=plan, plane_cuts=[(1, np.full(3, 0.5), np.eye(3)[0], 0.1)])
    with pytest.raises(ValueError, match="plan: expected None or a CutPlan"):
        simulate(model, schedule, MATERIAL, H, 2, plan=object())  # pyright: ignore[reportArgumentType]
    model.cut(plane_cut_solid(np.array([1.53, 0.5, 0.5]), np.array([1.0, -0.02, 0.03]), 3.0, 1e-3))
    with pytest.raises(ValueError, match="model: cut since the plan was made"):
        simulate(model, schedule, MATERIAL, H, 2, plan=plan)
    with pytest.raises(ValueError, match="schedule: expected"):
        plan_cuts(model, [(3, CUT)], 2)
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        plan_cuts(model, [], 0)
    with pytest.raises(ValueError, match="model: expected an XFEMModel"):
        plan_cuts(None, [], 2)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="schedule: expected"):
        simulate(model, [(3, CUT)], MATERIAL, H, 2)
    with pytest.raises(ValueError, match="steps: expected an int >= 1"):
        simulate(model, [], MATERIAL, H, 0)
    with pytest.raises(ValueError, match="model: expected an XFEMModel"):
        simulate(None, [], MATERIAL, H, 2)  # pyright: ignore[reportArgumentType]


def test_nothing_keeps_a_dropped_plan():
    model = _model()
    plan = plan_cuts(model, schedule := [(1, CUT)], 1)
    simulate(model, schedule, MATERIAL, H, 1, plan=plan, **PAPER)
    # the system after the cut and the cut copy: only the plan has them (the model keeps its own system)
    dropped = weakref.ref(plan), weakref.ref(plan.segments[-1].system), weakref.ref(plan.model)
    del plan
    gc.collect()
    assert all(ref() is None for ref in dropped)  # no module, cache, thread or compiled step keeps them
    assert model.pieces() == 1  # the plan never cut the model


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


@pytest.mark.slow
def test_plane_cuts_equal_the_solid_cuts():
    """A notch (a solid) at frame 1 and a tilted slab at frame 2 as ``plane_cuts``: every frame equals the schedule
    of both solids (``plane_cut_solid`` at the same plane) cut by the model; the model is left uncut."""
    point, normal = (np.asarray(a) for a in _plane(0.43, 0.2))
    model = _hanging()
    n_before = len(model.dof_sid)
    planes = simulate(
        model, [(1, NOTCH)], MATERIAL, H, PLANE_STEPS, plane_cuts=[(PLANE_FRAME, point, normal, EPS)], **PAPER
    )
    assert len(model.dof_sid) == n_before and model.pieces() == 1
    solids = simulate(
        _hanging(),
        [(1, NOTCH), (PLANE_FRAME, plane_cut_solid(point, normal, 5.0, EPS))],
        MATERIAL,
        H,
        PLANE_STEPS,
        **PAPER,
    )
    assert [s.x.shape for s in planes] == [s.x.shape for s in solids] and len(planes) == 3
    assert planes[2].x.shape[1] > n_before
    for a, b in zip(planes, solids, strict=True):
        np.testing.assert_allclose(a.x, b.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.v, b.v, rtol=0, atol=1e-10)


@pytest.mark.slow
def test_gradient_with_respect_to_the_plane_matches_central_differences():
    """The hanging bar's positions after the cut (a random linear functional of the last frame), differentiated
    with respect to the slab's height and tilt through the cut and two steps at the defaults (converged); central
    differences of simulate at shifted planes, to 1e-6 (the combinatorics do not change within the step: the
    replay, which equals the Booleans, test above)."""
    model = _hanging()
    weights = {}
    height, theta = 0.43, 0.2
    point, normal = (np.asarray(a) for a in _plane(height, theta))
    plan = plan_cuts(model, [], PLANE_STEPS, plane_cuts=[(PLANE_FRAME, point, normal, EPS)])  # the pieces, once

    def outcome(height, theta):
        point, normal = _plane(height, theta)
        planes = [(PLANE_FRAME, point, normal, EPS)]
        last = simulate(model, [], MATERIAL, H, PLANE_STEPS, plane_cuts=planes, plan=plan)[-1]
        assert np.all(last.stats.converged)
        if "w" not in weights:  # fixed once the DOF count after the cut is known
            weights["w"] = np.random.default_rng(3).normal(size=last.x.shape[1:])
        return jnp.sum(weights["w"] * last.x[-1])

    gradient = jax.grad(outcome, argnums=(0, 1))(jnp.asarray(height), jnp.asarray(theta))
    step = 1e-5
    for k, g in enumerate(gradient):
        shift = step * np.eye(2)[k]
        difference = (outcome(height + shift[0], theta + shift[1]) - outcome(height - shift[0], theta - shift[1])) / (
            2 * step
        )
        assert abs(g - difference) <= 1e-6 * abs(difference), (k, g, difference)
    assert abs(gradient[0]) > 0 and abs(gradient[1]) > 0


def test_plane_cuts_bad_input():
    model = _hanging()
    point, normal = np.array([0.1, 0.1, 0.43]), np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="plane_cuts: expected"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(3, point, normal, EPS)])
    with pytest.raises(ValueError, match="plane_cuts: expected"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, normal)])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match=r"normal \(plane_cuts\[0\]\): expected a unit normal"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, 2 * normal, EPS)])
    with pytest.raises(ValueError, match=r"epsilon \(plane_cuts\[0\]\)"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, normal, 0.0)])
    with pytest.raises(ValueError, match=r"point \(plane_cuts\[0\]\): simulate finds the pieces .*xfem.plan_cuts"):
        jax.jit(lambda p: simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, p, normal, EPS)])[-1].x)(point)
    plan = plan_cuts(model, [], 2, plane_cuts=[(1, point, normal, EPS)])
    assert len(model.dof_sid) == HANGING.n_nodes and model.pieces() == 1  # the model is left uncut
    assert plan.cuts is not None and plan.model is plan.cuts.model and plan.made_for is model
    assert plan.model.pieces() == 2
    assert bool(plan.holds(point[None] + 1e-4, normal[None])) and not plan.holds(point[None] + 0.1, normal[None])
    with pytest.raises(ValueError, match="plan: its pieces were found at other planes and do not hold at these"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point + 0.1, normal, EPS)], plan=plan)
    with pytest.raises(ValueError, match="plan: made for plane cuts at frames \\[1\\] with thicknesses"):
        simulate(model, [], MATERIAL, H, 2, plane_cuts=[(1, point, normal, 2 * EPS)], plan=plan)
    with pytest.raises(ValueError, match="plan: made for plane cuts at frames"):
        simulate(model, [], MATERIAL, H, 2, plan=plan)
    with pytest.raises(ValueError, match=r"points, normals: expected shape \(1, 3\)"):
        plan.holds(point, normal)
    with pytest.raises(ValueError, match="plan_cuts finds the pieces at concrete planes"):
        jax.jit(lambda p: plan_cuts(model, [], 2, plane_cuts=[(1, p, normal, EPS)]).points)(point)


@pytest.mark.slow
def test_a_vmapped_gradient_over_plane_tilts_equals_separate_calls():
    """``plane_cut_simulation`` prepares the pieces once; ``jax.jit(jax.vmap(jax.grad(loss)))`` over 8 tilts of the
    slab equals ``jax.grad`` of ``simulate`` at each tilt (to 1e-10), and so does ``simulate`` under ``jax.jit`` with
    its plan. A batch with a tilt past the pieces found raises; a concrete call there cuts again."""
    model = _hanging()
    weights = np.random.default_rng(4).normal(size=(len(model.dof_sid) + 20, 3))

    def functional(last):
        return jnp.sum(jnp.asarray(weights[: last.x.shape[1]]) * last.x[-1])

    point0, normal0 = (np.asarray(a) for a in _plane(0.43, 0.2))
    prepared = xfem.plane_cut_simulation(model, [], [(PLANE_FRAME, point0, normal0, EPS)], PLANE_STEPS)
    assert len(model.dof_sid) == len(weights) - 20 and model.pieces() == 1  # the model is left uncut

    def loss(theta):
        point, normal = _plane(jnp.asarray(0.43), theta)
        return functional(prepared(point[None], normal[None], MATERIAL, H)[-1])

    def separate(theta):
        point, normal = _plane(jnp.asarray(0.43), theta)
        last = simulate(model, [], MATERIAL, H, PLANE_STEPS, plane_cuts=[(PLANE_FRAME, point, normal, EPS)])[-1]
        return functional(last)

    thetas = np.linspace(0.15, 0.25, 8)
    batched = jax.jit(jax.vmap(jax.grad(loss)))
    gradients = np.asarray(batched(jnp.asarray(thetas)))
    expected = np.array([float(jax.grad(separate)(jnp.asarray(t))) for t in thetas])
    np.testing.assert_allclose(gradients, expected, rtol=1e-10, atol=0)
    assert np.all(np.abs(np.diff(gradients)) > 0)  # the tilts differ

    def through_simulate(theta):  # simulate traced by jit: the plan passed, no host work
        point, normal = _plane(jnp.asarray(0.43), theta)
        planes = [(PLANE_FRAME, point, normal, EPS)]
        return functional(simulate(model, [], MATERIAL, H, PLANE_STEPS, plane_cuts=planes, plan=prepared.plan)[-1])

    np.testing.assert_allclose(jax.jit(jax.grad(through_simulate))(jnp.asarray(thetas[3])), gradients[3], rtol=1e-10)

    # a tilt that moves the slab's face past a piece's vertex: the prepared pieces do not hold there
    far = np.append(thetas[:7], 0.6)
    holds = jax.vmap(lambda t: prepared.holds(*(a[None] for a in _plane(jnp.asarray(0.43), t))))(jnp.asarray(far))
    assert np.all(holds[:7]) and not holds[7]
    with pytest.raises(Exception, match="planes: they moved past a node or a piece's vertex"):
        batched(jnp.asarray(far))
    point, normal = (np.asarray(a)[None] for a in _plane(jnp.asarray(0.43), jnp.asarray(0.6)))
    plan = prepared.plan
    prepared(point, normal, MATERIAL, H, **PAPER)  # concrete planes: found again there, in a new plan
    assert bool(prepared.holds(point, normal)) and np.allclose(prepared.normals, normal) and prepared.plan is not plan


def test_plane_cut_simulation_bad_input():
    model = _hanging()
    point, normal = np.array([0.1, 0.1, 0.43]), np.array([0.0, 0.0, 1.0])
    prepared = xfem.plane_cut_simulation(model, [], [(1, point, normal, EPS)], 2)
    with pytest.raises(ValueError, match=r"points, normals: expected shape \(1, 3\)"):
        prepared(point, normal, MATERIAL, H)
    with pytest.raises(ValueError, match=r"normal \(plane_cuts\[0\]\): expected a unit normal"):
        prepared(point[None], 2 * normal[None], MATERIAL, H)
    with pytest.raises(ValueError, match="plane_cuts: expected at least one"):
        xfem.plane_cut_simulation(model, [], [], 2)
    with pytest.raises(ValueError, match="plan_cuts finds the pieces at concrete planes"):
        jax.jit(lambda p: xfem.plane_cut_simulation(model, [], [(1, p, normal, EPS)], 2).points)(point)
    with pytest.raises(ValueError, match="model: expected an XFEMModel"):
        xfem.plane_cut_simulation(None, [], [(1, point, normal, EPS)], 2)  # pyright: ignore[reportArgumentType]
