"""Backward Euler steps of the XFEM paper, sec. 3.3 (eq. 6-10): rest stays at rest; a free body keeps its
momentum (uniform velocity moves it rigidly) and its centre of mass falls with g exactly, on an XFEM-like
system (two disjoint copies of a mesh, one with a lumped mass); a converged step zeroes grad E (an
independent dense evaluation of eq. 10's potential); fixed nodes stay pinned or follow a moving boundary;
50 steps of a cantilever stay finite, lose energy and settle at the static equilibrium (scipy L-BFGS);
implicit gradients through three converged steps against central differences (Young's modulus, initial
velocity, moving boundary, force, integration weights); bad input."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.sparse as sp

from tests.shared import lowered_operations, needs_cuda_lowering
from xfem import (
    CapacityError,
    Material,
    State,
    SystemCapacity,
    backward_euler_step,
    body_force,
    box_tets,
    consistent_mass,
    element_energy,
    fem_from_mesh,
    fem_system,
    five_tet_cube,
    lumped_mass,
    shape_gradients,
)

# the Newton direction's host fallback and the chunked map have no public API: tested here directly
from xfem._backward_euler import _Chunks, _host_newton_direction, _in_chunks

H = 0.033
MATERIAL = Material(1e6, 0.4)
MU, LAM = MATERIAL.lame()
GRAVITY = np.array([0.0, 0.0, -9.81])
CONVERGED: dict[str, Any] = dict(newton_iterations=20, tolerance=1e-12)
PAPER: dict[str, Any] = dict(newton_iterations=1, tolerance=None)  # the paper's single Newton iteration per step

BAR = box_tets((2, 1, 1), size=(2.0, 1.0, 1.0))
X = np.asarray(BAR.X)
FIXED = np.flatnonzero(X[:, 0] == 0)
CANTILEVER = fem_from_mesh(BAR, 1e3, GRAVITY, fixed=FIXED)


def _two_cubes(gravity):
    """Two disjoint five-tet cubes in one system (as XFEM's duplicated nodes after a full cut): the first with
    the consistent mass, the second with the lumped (diagonal) one."""
    cube = five_tet_cube()
    X1, T1 = np.asarray(cube.X), np.asarray(cube.T)
    Xs = np.concatenate([X1, X1 + [2.0, 0.0, 0.0]])
    Ts = np.concatenate([T1, T1 + len(X1)])
    grads, volumes = shape_gradients(jnp.asarray(Xs), jnp.asarray(Ts))
    mass = sp.block_diag([consistent_mass(X1, T1, 1e3), sp.diags(np.asarray(lumped_mass(cube.X, cube.T, 1e3)))])
    force = body_force(jnp.asarray(Xs), jnp.asarray(Ts), 1e3 * np.asarray(gravity))
    return fem_system(Ts, grads, volumes, mass, force), mass, Xs


def _deformed(X, seed, scale=0.05):
    rng = np.random.default_rng(seed)
    return jnp.asarray(X + scale * rng.normal(size=X.shape)), jnp.asarray(rng.normal(size=X.shape))


@pytest.mark.slow
def test_rest_stays_at_rest():
    system = fem_from_mesh(BAR, 1e3, (0.0, 0.0, 0.0), fixed=FIXED)
    state = backward_euler_step(system, State(BAR.X, jnp.zeros_like(BAR.X)), H, MATERIAL)
    np.testing.assert_allclose(state.x, X, atol=1e-14)
    np.testing.assert_allclose(state.v, 0.0, atol=1e-12)


@pytest.mark.slow
def test_uniform_velocity_moves_a_free_body_rigidly():
    system, _, Xs = _two_cubes((0.0, 0.0, 0.0))
    v = jnp.broadcast_to(jnp.asarray([0.3, -1.2, 2.0]), Xs.shape)
    state = State(jnp.asarray(Xs), v)
    for _ in range(3):
        state = backward_euler_step(system, state, H, MATERIAL, **CONVERGED)
    np.testing.assert_allclose(state.x, Xs + 3 * H * v, atol=1e-12)
    np.testing.assert_allclose(state.v, v, atol=1e-10)


@pytest.mark.slow
def test_gravity_accelerates_the_centre_of_mass_by_g():
    system, mass, Xs = _two_cubes(GRAVITY)
    x, v = _deformed(Xs, 1)  # deformed, random velocities: large elastic forces, all internal
    after = backward_euler_step(system, State(x, v), H, MATERIAL, **CONVERGED)
    nodal = np.asarray(mass.sum(axis=1)).ravel()  # the nodes' shares of the mass
    for piece in (slice(0, 8), slice(8, 16)):  # each disjoint body on its own
        w = nodal[piece] / nodal[piece].sum()
        centre = w @ np.asarray(x)[piece] + H * w @ np.asarray(v)[piece]
        np.testing.assert_allclose(w @ np.asarray(after.x)[piece], centre + H**2 * GRAVITY, atol=1e-10)
        np.testing.assert_allclose(w @ np.asarray(after.v)[piece], w @ np.asarray(v)[piece] + H * GRAVITY, atol=1e-8)


def _potential_gradient(x, x_t, v_t):
    """grad E of eq. (10) from a dense mass matrix and the element energies (independent of the solver)."""
    M = np.kron(consistent_mass(X, np.asarray(BAR.T), 1e3).toarray(), np.eye(3))
    grads, volumes = shape_gradients(BAR.X, BAR.T)
    force = np.asarray(body_force(BAR.X, BAR.T, 1e3 * GRAVITY)).ravel()

    def E(y):
        d = (y - x_t - H * v_t).ravel()
        elastic = jnp.sum(element_energy(y[BAR.T], grads, volumes, MU, LAM))
        return 0.5 * d @ (M @ d) + H**2 * (elastic - force @ y.ravel())

    return np.asarray(jax.grad(E)(x)), np.abs(M @ np.asarray(x - x_t).ravel()).max()


@pytest.mark.slow
def test_converged_step_zeroes_the_gradient_and_keeps_fixed_nodes():
    x, v = _deformed(X, 2)
    x = x.at[FIXED].set(X[FIXED])
    moved = X[FIXED] + np.array([0.0, 0.02, -0.03])
    for fixed_positions, expected in ((None, X[FIXED]), (moved, moved)):
        after = backward_euler_step(CANTILEVER, State(x, v), H, MATERIAL, fixed_positions=fixed_positions, **CONVERGED)
        np.testing.assert_array_equal(after.x[FIXED], expected)
        gradient, scale = _potential_gradient(after.x, x, v)
        free = np.setdiff1d(np.arange(len(X)), FIXED)
        assert np.abs(gradient[free]).max() < 1e-11 * scale
        assert np.abs(gradient[FIXED]).max() > 1e-3 * scale  # the reaction forces of the supports


def _static_deflection():
    """The cantilever's equilibrium (min U - f . x, fixed nodes pinned) by scipy's L-BFGS: the mean tip sag."""
    grads, volumes = shape_gradients(BAR.X, BAR.T)
    free = np.setdiff1d(np.arange(len(X)), FIXED)
    force = np.asarray(CANTILEVER.force)

    @jax.jit
    def potential(y):
        x = jnp.asarray(X).at[free].set(y.reshape(-1, 3))
        return jnp.sum(element_energy(x[BAR.T], grads, volumes, MU, LAM)) - jnp.sum(force * x)

    result = scipy.optimize.minimize(
        jax.value_and_grad(potential),
        X[free].ravel(),
        jac=True,
        method="L-BFGS-B",
        options=dict(gtol=1e-9, ftol=1e-15, maxiter=5000),
    )
    x = X.copy()
    x[free] = result.x.reshape(-1, 3)
    return x[X[:, 0] == 2.0, 2].mean() - 0.5


@pytest.mark.slow
def test_cantilever_stays_finite_loses_energy_and_settles():
    M = np.kron(consistent_mass(X, np.asarray(BAR.T), 1e3).toarray(), np.eye(3))
    grads, volumes = shape_gradients(BAR.X, BAR.T)
    force = np.asarray(CANTILEVER.force).ravel()

    def total_energy(s):
        elastic = float(jnp.sum(element_energy(s.x[BAR.T], grads, volumes, MU, LAM)))
        v = np.asarray(s.v).ravel()
        return 0.5 * v @ M @ v + elastic - force @ np.asarray(s.x).ravel()

    state = State(BAR.X, jnp.zeros_like(BAR.X))
    energies, tips = [total_energy(state)], []
    for _ in range(50):
        state = backward_euler_step(CANTILEVER, state, H, MATERIAL, **PAPER)
        energies.append(total_energy(state))
        tips.append(float(state.x[X[:, 0] == 2.0, 2].mean() - 0.5))
    assert np.all(np.isfinite(np.asarray(state.x))) and np.all(np.isfinite(energies))
    assert np.all(np.diff(energies) < 0)  # backward Euler dissipates
    np.testing.assert_array_equal(state.x[FIXED], X[FIXED])
    # a suddenly applied weight overshoots (at most twice the static sag), then settles at equilibrium
    static = _static_deflection()
    assert 2 * static < min(tips) < 1.2 * static
    np.testing.assert_allclose(tips[-1], static, rtol=0.05)


@pytest.mark.slow
def test_implicit_gradients_match_central_differences_at_the_defaults():
    """Three steps at the default settings (Newton to convergence): the implicit gradient is the derivative of the
    steps computed, to 1e-6 of central differences, for every differentiable input."""
    rng = np.random.default_rng(3)
    weights = jnp.asarray(rng.normal(size=X.shape))
    v0 = jnp.asarray(rng.normal(size=X.shape))
    direction = {"v0": jnp.asarray(rng.normal(size=X.shape)), "offset": jnp.asarray(rng.normal(size=(len(FIXED), 3)))}

    def loss(young, v0, offset, gravity_scale, weight_scale):
        material = Material(young, jnp.asarray(0.4))
        system = eqx.tree_at(
            lambda s: (s.force, s.volumes),
            CANTILEVER,
            (gravity_scale * CANTILEVER.force, weight_scale * CANTILEVER.volumes),
        )

        def step(state, _):
            state = backward_euler_step(system, state, H, material, fixed_positions=X[FIXED] + offset)
            return state, state.stats.converged

        state, converged = jax.lax.scan(step, State(BAR.X, v0), length=3)
        return jnp.sum(weights * state.x) + 0.5 * jnp.sum(state.v**2), converged

    one = jnp.asarray(1.0)
    args = (jnp.asarray(2e5), v0, jnp.zeros((len(FIXED), 3)), one, one)
    value_and_grad = jax.jit(jax.value_and_grad(loss, argnums=(0, 1, 2, 3, 4), has_aux=True))  # one compilation
    (_, converged), grad = value_and_grad(*args)
    assert np.all(converged)

    def central(i, d, eps):
        plus, minus = list(args), list(args)
        plus[i], minus[i] = args[i] + eps * d, args[i] - eps * d
        return float(value_and_grad(*plus)[0][0] - value_and_grad(*minus)[0][0]) / (2 * eps)

    np.testing.assert_allclose(grad[0], central(0, 1.0, 1e-4 * float(args[0])), rtol=1e-6)
    np.testing.assert_allclose(jnp.sum(grad[1] * direction["v0"]), central(1, direction["v0"], 1e-5), rtol=1e-6)
    np.testing.assert_allclose(jnp.sum(grad[2] * direction["offset"]), central(2, direction["offset"], 1e-6), rtol=1e-6)
    np.testing.assert_allclose(grad[3], central(3, 1.0, 1e-4), rtol=1e-6)  # through system.force
    np.testing.assert_allclose(grad[4], central(4, 1.0, 1e-4), rtol=1e-6)  # through the integration weights


@pytest.mark.slow
def test_stats_say_whether_the_step_converged():
    """The default step converges (several Newton iterations, the last update below 1e-10 of the bar's size); the
    paper's single iteration does not on a moving cantilever, and says so; a state made by hand reports no step."""
    x, v = _deformed(X, 5)
    start = State(x.at[FIXED].set(X[FIXED]), v)
    assert bool(start.stats.converged) and int(start.stats.iterations) == 0
    default = backward_euler_step(CANTILEVER, start, H, MATERIAL)
    assert bool(default.stats.converged) and 1 < int(default.stats.iterations) < 20
    assert float(default.stats.residual) <= 1e-10
    paper = backward_euler_step(CANTILEVER, start, H, MATERIAL, **PAPER)
    assert not bool(paper.stats.converged) and int(paper.stats.iterations) == 1
    assert float(paper.stats.residual) > 1e-4
    # the single iteration stopped short: its distance to the converged step is about its residual's scale
    size = np.linalg.norm(X.max(axis=0) - X.min(axis=0))
    assert float(jnp.abs(paper.x - default.x).max()) > 1e-8 * size
    # a capped run that does not reach its tolerance says so too
    capped = backward_euler_step(CANTILEVER, start, H, MATERIAL, newton_iterations=2, tolerance=1e-12)
    assert not bool(capped.stats.converged) and int(capped.stats.iterations) == 2


def test_bad_input():
    state = State(BAR.X, jnp.zeros_like(BAR.X))
    with pytest.raises(ValueError, match="state.x: expected shape"):
        backward_euler_step(CANTILEVER, State(BAR.X[:-1], BAR.X[:-1]), H, MATERIAL)
    with pytest.raises(ValueError, match="h: expected a finite positive"):
        backward_euler_step(CANTILEVER, state, -H, MATERIAL)
    with pytest.raises(ValueError, match="fixed_positions: expected shape"):
        backward_euler_step(CANTILEVER, state, H, MATERIAL, fixed_positions=np.zeros((2, 3)))
    with pytest.raises(ValueError, match="newton_iterations"):
        backward_euler_step(CANTILEVER, state, H, MATERIAL, newton_iterations=0)
    with pytest.raises(ValueError, match="tolerance"):
        backward_euler_step(CANTILEVER, state, H, MATERIAL, tolerance=-1.0)
    with pytest.raises(ValueError, match="tolerance: expected 'auto'"):
        backward_euler_step(CANTILEVER, state, H, MATERIAL, tolerance="tight")  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="state.v: non-finite"):
        backward_euler_step(CANTILEVER, State(BAR.X, jnp.full_like(BAR.X, jnp.nan)), H, MATERIAL)
    with pytest.raises(ValueError, match="material: expected an xfem.Material"):
        backward_euler_step(CANTILEVER, state, H, (MU, LAM))  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="material.young: expected a scalar or one value per element"):
        backward_euler_step(CANTILEVER, state, H, Material(np.full(3, 1e6), 0.4))
    with pytest.raises(ValueError, match="young: Young's modulus must be finite and > 0"):
        Material(-1.0, 0.4)
    with pytest.raises(ValueError, match="poisson: Poisson's ratio"):
        Material(1e6, 0.5)
    grads, volumes = shape_gradients(BAR.X, BAR.T)
    mass = consistent_mass(BAR.X, BAR.T, 1.0)
    with pytest.raises(ValueError, match="mass: expected a finite symmetric"):
        fem_system(BAR.T, grads, volumes, mass + sp.coo_matrix(([1.0], ([0], [1])), shape=mass.shape), CANTILEVER.force)
    with pytest.raises(ValueError, match="force: expected"):
        fem_system(BAR.T, grads, volumes, mass, CANTILEVER.force[:-1])
    with pytest.raises(ValueError, match="gravity"):
        fem_from_mesh(BAR, 1.0, gravity=(0.0, -9.81))


def test_newton_direction_is_exact_on_small_systems_and_cg_on_large_ones(monkeypatch):
    """Up to _DIRECT_DOFS unknowns the Newton system is factorized (exact), above it CG stops at its relative
    residual; a small matrix CHOLMOD refuses (indefinite) goes to CG too."""
    import xfem._backward_euler as be  # the direct/CG switch is internal: patched and called directly

    rng = np.random.default_rng(3)
    n = 64  # a mass-like diagonal plus a 4 x 4 x 4 grid Laplacian, like M + h^2 K
    # scipy is unannotated: pyright takes the type of offsets from its default, 0
    D = sp.diags([-1.0, 2.0, -1.0], [-1, 0, 1], shape=(4, 4))  # pyright: ignore[reportArgumentType]
    eye = sp.identity(4)
    A = sp.csr_matrix(
        sp.kron(sp.kron(D, eye), eye)
        + sp.kron(sp.kron(eye, D), eye)
        + sp.kron(sp.kron(eye, eye), D)
        + 0.5 * sp.identity(n)
    )
    b = rng.normal(size=n)
    exact = np.linalg.solve(A.toarray(), b)
    direct = _host_newton_direction(A.data, b, 1e-2, A.indptr, A.indices)
    np.testing.assert_allclose(direct, exact, rtol=1e-10, atol=1e-12)
    monkeypatch.setattr(be, "_DIRECT_DOFS", n - 1)  # the same system is now "large": CG to 1e-2
    inexact = _host_newton_direction(A.data, b, 1e-2, A.indptr, A.indices)
    residual = np.linalg.norm(A @ inexact - b) / np.linalg.norm(b)
    assert 1e-12 < residual <= 1e-2
    monkeypatch.setattr(be, "_DIRECT_DOFS", 1000)
    indefinite = sp.csr_matrix(np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]]))
    x = _host_newton_direction(indefinite.data, b[:3], 1e-12, indefinite.indptr, indefinite.indices)
    assert np.all(np.isfinite(x))


def test_factored_direction_is_the_true_newton_direction_or_descends():
    """The factored direction (a character's Newton steps): CG on the true Hessian preconditioned by the factored
    projected one. Where the true Hessian is positive definite it is the true Newton direction; where it is
    indefinite along the first direction, the projected Newton direction; either way it descends."""
    from xfem._backward_euler import _host_factored_direction  # internal: the host solve of one Newton direction

    rng = np.random.default_rng(5)
    n = 40
    Q = np.linalg.qr(rng.normal(size=(n, n)))[0]
    projected = Q @ np.diag(rng.uniform(1.0, 3.0, n)) @ Q.T  # P, positive definite
    csr = sp.csr_matrix(np.ones((n, n)))  # one dense pattern for both matrices
    b = rng.normal(size=n)

    def direction(true, rtol=1e-12):
        return _host_factored_direction(projected[csr.nonzero()], true[csr.nonzero()], b, rtol, csr.indptr, csr.indices)

    # true = P plus a low-rank positive definite change: CG converges to the true Newton direction
    low_rank = rng.normal(size=(n, 3))
    true = projected - 0.4 * (low_rank @ low_rank.T) / np.linalg.norm(low_rank, 2) ** 2
    assert np.linalg.eigvalsh(true).min() > 0
    np.testing.assert_allclose(direction(true), np.linalg.solve(true, b), rtol=1e-9, atol=1e-12)
    # indefinite along P^-1 b itself: the projected Newton direction
    first = np.linalg.solve(projected, b)
    unit = first / np.linalg.norm(first)
    indefinite = projected - 10 * (unit @ projected @ unit) * np.outer(unit, unit)
    assert unit @ indefinite @ unit < 0
    np.testing.assert_allclose(direction(indefinite), first, rtol=1e-12)
    # indefinite elsewhere: CG stops where it meets the negative curvature, with a descent direction
    other = np.linalg.qr(np.stack([first, rng.normal(size=n)], axis=1))[0][:, 1]
    mixed = projected - 5 * np.outer(other, other)
    x = direction(mixed)
    assert b @ x > 0 and np.all(np.isfinite(x))  # b = -grad E: a descent direction


@pytest.mark.slow
def test_padded_system_steps_like_the_real_one():
    """A system padded to a capacity (extra free and fixed nodes, zero-weight elements, zero mass entries and CSR
    slots) takes the same step on its real nodes and leaves the padded ones where they are."""
    mesh = box_tets((2, 2, 3))
    n, m = mesh.X.shape[0], mesh.T.shape[0]
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] < 1e-9)
    real = fem_from_mesh(mesh, 1e3, fixed=fixed)
    grads, volumes = shape_gradients(mesh.X, mesh.T)
    mass = consistent_mass(mesh.X, mesh.T, 1e3)
    force = body_force(mesh.X, mesh.T, 1e3 * np.array([0.0, 0.0, -9.81]))
    capacity = SystemCapacity(
        nodes=n + 20,
        elements=m + 7,
        mass_entries=real.mass_values.shape[0] + 40,
        fixed=len(fixed) + 5,
        nonzeros=real.pattern.nnz + 9 * 15 + 99,
    )  # 15 free padded nodes
    padded = fem_system(mesh.T, grads, volumes, mass, force, fixed, capacity=capacity)
    assert (padded.n, padded.T.shape[0], padded.fixed.shape[0], padded.pattern.nnz) == tuple(
        capacity[k] for k in (0, 1, 3, 4)
    )
    X = np.asarray(mesh.X)
    state = State(jnp.asarray(X), jnp.asarray(np.random.default_rng(0).normal(size=X.shape)))
    wide = State(jnp.asarray(np.vstack([X, np.zeros((20, 3))])), jnp.asarray(np.vstack([state.v, np.zeros((20, 3))])))
    for _ in range(2):
        state = backward_euler_step(real, state, 0.033, MATERIAL, **PAPER)
        wide = backward_euler_step(padded, wide, 0.033, MATERIAL, **PAPER)
    np.testing.assert_allclose(np.asarray(wide.x)[:n], state.x, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(np.asarray(wide.x)[n:], 0.0)
    with pytest.raises(CapacityError, match="capacity"):
        fem_system(mesh.T, grads, volumes, mass, force, fixed, capacity=capacity._replace(nonzeros=9))
    with pytest.raises(CapacityError, match="capacity"):
        fem_system(mesh.T, grads, volumes, mass, force, fixed, capacity=capacity._replace(elements=m - 1))


def _step_inputs(system, X, x, v):
    """The differentiable inputs of a step (``_Theta``) at positions x, velocities v, rest positions X."""
    import xfem._backward_euler as be  # internal: the chunk tests call the step's kernels directly

    return be._Theta(
        jnp.asarray(X),
        v,
        jnp.asarray(MU),
        jnp.asarray(LAM),
        x[system.fixed],
        system.force,
        system.grads,
        system.volumes,
        system.mass_values,
    )


@pytest.mark.slow
def test_in_chunks_visits_every_row_once():
    """The last chunk is moved back to end at the last row; the rows it shares with the chunk before are masked."""
    rows = jnp.arange(1.0, 34.0)

    def add_chunk(start, size, own, total):
        return total + jnp.sum(jnp.where(own, jax.lax.dynamic_slice_in_dim(rows, start, size), 0))

    for count in (1, 5, 8, 9, 16, 17, 33):
        for chunk in (1, 3, 8, 40):
            assert float(_in_chunks(count, _Chunks(chunk, chunk), add_chunk, jnp.zeros(()))) == count * (count + 1) / 2


@pytest.mark.cpu_formulation("a lowering for the CPU loops over chunks")
@needs_cuda_lowering
def test_element_chunks_are_the_cpus_only(monkeypatch):
    """The step's sums over elements and mass entries loop over chunks when lowered for the CPU and take every
    row at once when lowered for CUDA (the sizes per platform, ``_Chunks``); that both sum alike is
    ``test_steps_in_chunks_equal_one_pass``'s check."""
    import xfem._backward_euler as be  # the chunk sizes are internal: patched directly

    monkeypatch.setattr(be, "_ELEMENT_CHUNK", be._Chunks(cpu=3, device=1 << 17))
    monkeypatch.setattr(be, "_MASS_CHUNK", be._Chunks(cpu=7, device=1 << 20))
    x, v = _deformed(X, 4)
    theta = _step_inputs(CANTILEVER, X, x, v)
    arrays, static = eqx.partition(CANTILEVER, eqx.is_array)
    # abstract inputs: arrays committed to the CPU cannot enter a program lowered for CUDA
    args = jax.tree.map(lambda a: jax.ShapeDtypeStruct(a.shape, a.dtype), (x, theta, arrays))

    def energy_gradient_and_matrix(x, theta, arrays):
        system = eqx.combine(arrays, static)
        return be._energy(system, x, theta, H)[0], be._gradient_and_matrix(system, x, theta, H, True)

    loops = {p: lowered_operations(energy_gradient_and_matrix, args, p)["while"] for p in ("cpu", "cuda")}
    assert loops["cpu"] - loops["cuda"] == 4  # an element loop and a mass loop each (the rest: the eigensolver's)


def test_the_energy_and_newton_system_make_no_runtime_checks():
    """E and the Newton system, which a step evaluates several times, take Lamé parameters that ``Material.lame``
    checked once: no conditional (a runtime check under jit is one, a host round trip on a GPU)."""
    import xfem._backward_euler as be  # the step's kernels are internal

    x, v = _deformed(X, 4)
    theta = _step_inputs(CANTILEVER, X, x, v)

    def energy_gradient_and_matrix(x, theta):
        return be._energy(CANTILEVER, x, theta, H)[0], be._gradient_and_matrix(CANTILEVER, x, theta, H, True)

    assert "stablehlo.case" not in jax.jit(energy_gradient_and_matrix).lower(x, theta).as_text()
    with pytest.raises(ValueError, match="Poisson's ratio"):
        backward_euler_step(CANTILEVER, State(jnp.asarray(X), v), H, Material(1e5, 0.5))


@pytest.mark.slow
def test_steps_in_chunks_equal_one_pass(monkeypatch):
    """The energy, its gradient and Newton matrix, M d, a step and its implicit gradient, summed over chunks of
    elements and mass entries that overlap at the end (3 of 30 elements, 7 of 174 mass entries), equal one pass
    over all of them."""
    import xfem._backward_euler as be  # the chunk sizes and per-chunk kernels are internal: patched directly

    mesh = box_tets((5, 1, 1), size=(5.0, 1.0, 1.0))
    X = np.asarray(mesh.X)
    system = fem_from_mesh(mesh, 1e3, GRAVITY, fixed=np.flatnonzero(X[:, 0] == 0))
    x, v = _deformed(X, 4)
    theta = _step_inputs(system, X, x, v)

    def everything():
        jax.clear_caches()  # the step's trace reads the chunk sizes
        energy = be._energy(system, x, theta, H)[0]
        dE_dx = jax.grad(lambda z: be._energy(system, z, theta, H)[0])(x)
        dE_dvolumes = jax.grad(lambda t: be._energy(system, x, t, H)[0])(theta).volumes
        projected, true = (be._gradient_and_matrix(system, x, theta, H, project) for project in (True, False))

        def loss(young):
            state = backward_euler_step(
                system, State(jnp.asarray(X), v), H, Material(young, jnp.asarray(0.4)), **CONVERGED
            )
            return jnp.sum(state.x**2)

        return (
            energy,
            dE_dx,
            dE_dvolumes,
            *projected,
            *true,
            be._mass_times(system, system.mass_values, v),
            *jax.value_and_grad(loss)(jnp.asarray(1e6)),
        )

    assert (system.T.shape[0], system.mass_values.shape[0]) == (30, 174)
    one_pass = everything()
    monkeypatch.setattr(be, "_ELEMENT_CHUNK", be._Chunks(3, 3))
    monkeypatch.setattr(be, "_MASS_CHUNK", be._Chunks(7, 7))
    chunked = everything()
    monkeypatch.undo()
    jax.clear_caches()
    for a, b in zip(chunked, one_pass):
        np.testing.assert_allclose(a, b, rtol=1e-11, atol=1e-11 * float(jnp.max(jnp.abs(b))))
