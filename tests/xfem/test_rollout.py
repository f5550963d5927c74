"""Rollouts (``xfem.rollout``): a scan of backward Euler steps, jit-, vmap- and grad-able; the reverse pass goes
through each step's implicit gradient, checked against central differences at the defaults (converged steps) and
against the implicit-function formula evaluated at the executed iterate (the paper's single Newton iteration,
which reports that it did not converge)."""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.sparse as sp

# the host Newton direction and adjoint (internal) are wrapped to count the solves a rollout runs
import xfem._backward_euler as be
from xfem import Material, State, backward_euler_step, box_tets, consistent_mass, element_energy, fem_from_mesh, rollout

H = 0.033
MATERIAL = Material(2e5, 0.4)
PAPER: dict[str, Any] = dict(newton_iterations=1, tolerance=None)  # the paper's single Newton iteration per step
BAR = box_tets((4, 1, 1), size=(4.0, 1.0, 1.0))
X = np.asarray(BAR.X)
FIXED = np.flatnonzero(X[:, 0] == 0)
SYSTEM = fem_from_mesh(BAR, 1e3, fixed=FIXED)
REST = State(jnp.asarray(X), jnp.zeros_like(jnp.asarray(X)))
RNG = np.random.default_rng(7)
V0 = jnp.asarray(RNG.normal(size=X.shape))
WEIGHTS = jnp.asarray(RNG.normal(size=(3,) + X.shape))


def _moving(steps):
    """(steps, nb, 3) targets: the clamped face pulled along x and lifted, frame by frame."""
    t = np.arange(1, steps + 1)[:, None, None]
    return jnp.asarray(X[FIXED][None] + t * np.array([0.01, 0.0, 0.005]))


def _loss(trajectory):
    return jnp.sum(WEIGHTS * trajectory.x) + 0.5 * jnp.sum(trajectory.v[-1] ** 2)


@pytest.mark.slow
def test_rollout_equals_a_loop_of_steps():
    forces = jnp.asarray(RNG.normal(size=(3,) + X.shape))
    targets = _moving(3)
    trajectory = rollout(SYSTEM, State(REST.x, V0), MATERIAL, H, 3, forces=forces, targets=targets)
    assert trajectory.x.shape == trajectory.v.shape == (3,) + X.shape
    assert trajectory.stats.converged.shape == trajectory.stats.iterations.shape == (3,)
    assert np.all(trajectory.stats.converged) and np.all(trajectory.stats.iterations > 1)
    state = State(REST.x, V0)
    for k in range(3):
        system = eqx.tree_at(lambda s: s.force, SYSTEM, forces[k])
        state = backward_euler_step(system, state, H, MATERIAL, fixed_positions=targets[k])
        np.testing.assert_allclose(trajectory.x[k], state.x, rtol=0, atol=1e-12)
        np.testing.assert_allclose(trajectory.v[k], state.v, rtol=0, atol=1e-10)
        assert int(trajectory.stats.iterations[k]) == int(state.stats.iterations)
    # constant forces, the fixed nodes kept in place
    loop = State(REST.x, V0)
    for _ in range(2):
        loop = backward_euler_step(SYSTEM, loop, H, MATERIAL, fixed_positions=X[FIXED])
    np.testing.assert_allclose(
        rollout(SYSTEM, State(REST.x, V0), MATERIAL, H, 2, forces=SYSTEM.force).x[-1], loop.x, rtol=0, atol=1e-12
    )


@pytest.mark.slow
def test_jit_and_vmap_over_young():
    youngs = jnp.asarray([1e5, 1e6])

    @jax.jit
    def final(young):
        return rollout(SYSTEM, REST, Material(young, jnp.asarray(0.4)), H, 3).x[-1]

    batched = jax.vmap(final)(youngs)
    for k in range(2):
        np.testing.assert_allclose(batched[k], final(youngs[k]), rtol=0, atol=1e-12)
    assert not np.allclose(batched[0], batched[1])  # the stiffer bar sags less


@pytest.mark.slow
def test_gradients_at_the_defaults_match_central_differences():
    """Young's modulus, the initial velocity, per-frame forces and moving targets, through 10 steps at the default
    settings (each step converged): within 1e-6 of central differences."""
    steps = 10
    forces0 = jnp.broadcast_to(SYSTEM.force, (steps,) + X.shape)
    targets0 = _moving(steps)
    weights = jnp.asarray(RNG.normal(size=(steps,) + X.shape))

    def loss(young, v0, forces, targets):
        trajectory = rollout(
            SYSTEM, State(REST.x, v0), Material(young, jnp.asarray(0.4)), H, steps, forces=forces, targets=targets
        )
        return jnp.sum(weights * trajectory.x) + 0.5 * jnp.sum(trajectory.v[-1] ** 2), trajectory.stats.converged

    args = (jnp.asarray(2e5), V0, forces0, targets0)
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3), has_aux=True))
    (_, converged), grad = value_and_grad(*args)
    assert np.all(converged)
    directions = [jnp.asarray(1.0)] + [jnp.asarray(RNG.normal(size=a.shape)) for a in args[1:]]
    sizes = (2e5 * 1e-4, 1e-5, 1e-2, 1e-6)  # the finite differences' steps (not ``steps``, which loss reads)
    for i, (d, eps) in enumerate(zip(directions, sizes, strict=True)):
        plus, minus = list(args), list(args)
        plus[i], minus[i] = args[i] + eps * d, args[i] - eps * d
        central = float(value_and_grad(*plus)[0][0] - value_and_grad(*minus)[0][0]) / (2 * eps)
        np.testing.assert_allclose(float(jnp.sum(grad[i] * d)), central, rtol=1e-6, err_msg=f"argument {i}")


def _incremental_potential_gradient(x_free, x_t, v_t, young):
    """grad E on the free DOFs (eq. 10), written here from the mass matrix and element energies."""
    mu, lam = Material(young, jnp.asarray(0.4)).lame()
    M = jnp.asarray(sp.csr_matrix(consistent_mass(BAR.X, BAR.T, 1e3)).toarray())
    free = np.setdiff1d(np.arange(len(X)), FIXED)

    def energy(y):
        x = x_t.at[free].set(y)
        d = x - x_t - H * v_t
        elastic = jnp.sum(element_energy(x[BAR.T], SYSTEM.grads, SYSTEM.volumes, mu, lam))
        return 0.5 * jnp.sum(d * (M @ d)) + H**2 * (elastic - jnp.sum(SYSTEM.force * x))

    return jax.grad(energy)(x_free)


@pytest.mark.slow
def test_one_newton_iteration_gives_the_converged_formula_at_the_executed_iterate():
    """With one Newton iteration the rollout's gradient is the implicit-function formula dx/dtheta = -H^-1 dG/dtheta
    evaluated at each step's executed iterate x_k (not the minimizer), chained through the steps: checked to 1e-8
    against that formula built here with dense autodiff. Its distance from the executed iteration's derivative
    (central differences of the 1-iteration rollout) is bounded, and well above the converged case's 1e-5."""
    free = np.setdiff1d(np.arange(len(X)), FIXED)
    steps = 3

    def loss(young, v0):
        return _loss(rollout(SYSTEM, State(REST.x, v0), Material(young, jnp.asarray(0.4)), H, steps, **PAPER))

    young = jnp.asarray(2e5)
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    grad = value_and_grad(young, V0)[1]
    trajectory = rollout(SYSTEM, State(REST.x, V0), MATERIAL, H, steps, **PAPER)
    # the moving bar is not at a minimizer after one iteration, and the stats say so
    assert not np.any(trajectory.stats.converged) and np.all(trajectory.stats.iterations == 1)

    # forward-mode chain of the formula: dx_{k+1} = -H^-1 (dG/dx_t dx_k + dG/dv_t dv_k + dG/dE), at x_{k+1} executed
    x_t, v_t = REST.x, V0
    dx, dv = jnp.zeros_like(x_t), jnp.zeros_like(v_t)
    dloss = 0.0
    G = _incremental_potential_gradient
    jacobian = jax.jit(jax.jacfwd(G))
    tangent = jax.jit(
        lambda y, xt, vt, E, dx, dv: jax.jvp(
            lambda xt, vt, E: G(y, xt, vt, E), (xt, vt, E), (dx, dv, jnp.ones_like(E))
        )[1]
    )
    for k in range(steps):
        x_next = trajectory.x[k]
        hessian = jacobian(x_next[free], x_t, v_t, young).reshape(3 * len(free), 3 * len(free))
        rhs = tangent(x_next[free], x_t, v_t, young, dx, dv)
        dx_next = jnp.zeros_like(x_t).at[free].set(-jnp.linalg.solve(hessian, rhs.reshape(-1)).reshape(-1, 3))
        dv = (dx_next - dx) / H
        dx, x_t, v_t = dx_next, x_next, trajectory.v[k]
        dloss = dloss + jnp.sum(WEIGHTS[k] * dx)
    dloss = dloss + jnp.sum(trajectory.v[-1] * dv)
    np.testing.assert_allclose(float(grad), float(dloss), rtol=1e-8)

    eps = 2e5 * 1e-4
    central = float(value_and_grad(young + eps, V0)[0] - value_and_grad(young - eps, V0)[0]) / (2 * eps)
    difference = abs(float(grad) - central) / abs(central)
    print(f"one Newton iteration: implicit gradient vs the executed iteration's central difference: {difference:.3g}")
    assert 1e-4 < difference < 1e-2, difference


@pytest.mark.cpu_formulation("counts the host's Newton and adjoint solves; a GPU solves on the device")
@pytest.mark.slow
def test_reverse_pass_reruns_no_newton_iteration(monkeypatch):
    """Checkpointing keeps each step's Newton result: the gradient of a 4-step rollout runs the forward pass's
    Newton solves (as many as its steps' iterations, ``stats.iterations``) and 4 adjoint solves, none again."""
    calls = {"newton": 0, "adjoint": 0}
    newton, adjoint = be._host_newton_direction, be._host_adjoint

    def counted_newton(*args):
        calls["newton"] += 1
        return newton(*args)

    def counted_adjoint(*args):
        calls["adjoint"] += 1
        return adjoint(*args)

    monkeypatch.setattr(be, "_host_newton_direction", counted_newton)
    monkeypatch.setattr(be, "_host_adjoint", counted_adjoint)
    mesh = box_tets((3, 1, 1), size=(3.0, 1.0, 1.0))  # a shape of its own: traced anew with the counters
    system = fem_from_mesh(mesh, 1e3, fixed=np.flatnonzero(np.asarray(mesh.X)[:, 0] == 0))
    start = State(jnp.asarray(mesh.X), jnp.zeros_like(jnp.asarray(mesh.X)))
    jax.grad(lambda young: jnp.sum(rollout(system, start, Material(young, 0.4), H, 4).x ** 2))(jnp.asarray(1e6))
    solves = dict(calls)
    iterations = int(jnp.sum(rollout(system, start, Material(1e6, 0.4), H, 4).stats.iterations))
    assert solves == {"newton": iterations, "adjoint": 4} and iterations > 4


def test_bad_input():
    with pytest.raises(ValueError, match="steps: expected an int >= 0"):
        rollout(SYSTEM, REST, MATERIAL, H, -1)
    with pytest.raises(ValueError, match="forces: expected float forces of shape"):
        rollout(SYSTEM, REST, MATERIAL, H, 2, forces=jnp.zeros((3, len(X), 3)))
    with pytest.raises(ValueError, match="targets: expected float positions of shape"):
        rollout(SYSTEM, REST, MATERIAL, H, 2, targets=jnp.zeros((2, len(X), 3)))
    with pytest.raises(ValueError, match="material: expected an xfem.Material"):
        rollout(SYSTEM, REST, (1e6, 1e6), H, 2)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="h: expected a finite positive"):
        rollout(SYSTEM, REST, MATERIAL, -H, 2)
