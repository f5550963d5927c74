"""ARAP with rotors (deform/_arap.py) against libigl's spokes and spokes-and-rims ARAP, invariants, implicit
gradients, vmap."""

from pathlib import Path

import igl
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import deform
from deform import ARAP_ENERGIES, arap_precompute, arap_solve, horn_rotors
from jaxcga import KINDS, versor_to_matrix
from tests.deform._arap_reference import libigl_arap_in_numpy as _libigl_in_numpy
from tests.shared import grid, load_character

DATA = Path(__file__).resolve().parents[1] / "data"


IGL_ENERGY = {"spokes": igl.ARAP_ENERGY_TYPE_SPOKES, "spokes_and_rims": igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS}


def _igl(V, F, b, bc, U0, iterations, energy="spokes_and_rims"):
    data = igl.ARAPData()
    data.energy = IGL_ENERGY[energy]
    data.max_iter = iterations
    igl.arap_precomputation(V, F, 3, b.astype(np.int32), data)
    return igl.arap_solve(bc, data, U0)


def _moved(V, b, lo, axis, rotvec, shift):
    """Handles of ``b`` with coordinate ``axis`` below ``lo`` stay; the others turn and shift."""
    bc = V[b].copy()
    moving = V[b, axis] > lo
    centre = V[b][moving].mean(0)
    bc[moving] = (V[b][moving] - centre) @ Rotation.from_rotvec(rotvec).as_matrix().T + centre + shift
    return bc


@pytest.fixture(scope="module")
def arm():
    mesh = deform.default_arm().mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    b = np.nonzero((V[:, 0] < 0) | (V[:, 0] > 0.75))[0]
    bc = _moved(V, b, 0.75, 0, [0, 0.6, 0.3], [-0.1, 0.05, 0.2])
    return V, F, b, bc, arap_precompute(V, F, b)


@pytest.fixture(scope="module")
def cylinder():
    mesh = trimesh.creation.cylinder(radius=0.2, height=1.0, sections=24).subdivide().subdivide()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    b = np.nonzero(np.abs(V[:, 2]) > 0.45)[0]
    bc = _moved(V, b, 0.45, 2, [0.5, 0.2, 0], [0.2, 0, -0.1])
    return V, F, b, bc, arap_precompute(V, F, b)


def test_horn_rotors_are_the_polar_rotations():
    rng = np.random.default_rng(0)
    S = rng.normal(size=(500, 3, 3))
    U, _, Vt = np.linalg.svd(S)
    sign = np.ones((500, 3))
    sign[:, 2] = np.sign(np.linalg.det(U @ Vt))
    expected = np.einsum("nji,nj,nkj->nik", Vt, sign, U)  # argmax_R tr(R S), R proper
    rotors, lam = horn_rotors(jnp.asarray(S))
    R = np.asarray(versor_to_matrix(rotors.embed(KINDS["motor"]))[:, :3, :3])
    np.testing.assert_allclose(R, expected, atol=1e-10)
    np.testing.assert_allclose(lam, np.einsum("nij,nji->n", expected, S), rtol=1e-10)


@pytest.mark.parametrize("iterations", [1, 3, 10])
def test_matches_libigl_on_a_cylinder(cylinder, iterations):
    V, F, b, bc, data = cylinder
    U = arap_solve(data, jnp.asarray(bc), V0=V, max_iterations=iterations, tolerance=None, acceleration="none").U
    diag = np.linalg.norm(np.ptp(V, axis=0))
    assert np.abs(np.asarray(U) - _igl(V, F, b, bc, V.copy(), iterations)).max() < 1e-6 * diag


@pytest.fixture(scope="module")
def arm5():
    """Welded Arm5: shoulder fixed, hand turned by 40 degrees and lifted (the benchmark's setting)."""
    mesh = deform.load_model(DATA / "Arm5.glb", weld=True).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    fixed, hand = np.flatnonzero(V[:, 1] < 2.0), np.flatnonzero(V[:, 1] > 60.0)
    moved = Rotation.from_rotvec([np.radians(40), 0, 0]).apply(V[hand] - [0, 55, 0]) + [0, 55, 5]
    b = np.concatenate([fixed, hand])
    data = {energy: arap_precompute(V, F, b, energy=energy) for energy in ARAP_ENERGIES}
    return V, F, b, np.concatenate([V[fixed], moved]), data


@pytest.mark.parametrize("energy", ["spokes", "spokes_and_rims"])
@pytest.mark.parametrize("iterations", [1, pytest.param(10, marks=pytest.mark.slow)])
def test_equals_libigls_algorithm_on_arm5(arm5, iterations, energy):
    """Arm5 has cells whose covariance is nearly singular with a reflection (det S < 0): there the
    single-precision 3x3 SVD that ``igl.arap_solve`` fits rotations with is off by ~1e-4 relative. With
    libigl's own double-precision rotation fit the same algorithm (transcribed from libigl's
    arap_linear_block for either energy) gives our result to round-off, and with its single-precision fit it
    gives ``igl.arap_solve``'s: the whole difference is that float32 SVD."""
    V, F, b, bc, data = arm5
    diag = np.linalg.norm(np.ptp(V, axis=0))
    U0 = V.copy()
    U = arap_solve(
        data[energy], jnp.asarray(bc), V0=U0, max_iterations=iterations, tolerance=None, acceleration="none"
    ).U
    U = np.asarray(U)
    libigl = _igl(V, F, b, bc, U0.copy(), iterations, energy)
    exact = _libigl_in_numpy(V, F, b, bc, U0, iterations, False, energy)
    assert np.abs(U - exact).max() < 1e-10 * diag  # measured 1e-14
    assert np.abs(libigl - _libigl_in_numpy(V, F, b, bc, U0, iterations, True, energy)).max() < 1e-12 * diag  # 8e-15
    assert np.abs(U - libigl).max() < 1e-3 * diag  # measured 2e-5 .. 3e-4: the float32 SVD


@pytest.mark.slow
def test_matches_libigl_on_the_arm(arm):
    V, F, b, bc, data = arm
    U0 = V + 0.01 * np.sin(7 * V[:, [1, 2, 0]])  # any initial guess, passed to both
    U = arap_solve(data, jnp.asarray(bc), V0=U0, max_iterations=5, tolerance=None, acceleration="none").U
    diag = np.linalg.norm(np.ptp(V, axis=0))
    assert np.abs(np.asarray(U) - _libigl_in_numpy(V, F, b, bc, U0, 5, False, "spokes_and_rims")).max() < 1e-10 * diag
    assert np.abs(np.asarray(U) - _igl(V, F, b, bc, U0, 5)).max() < 1e-4 * diag


@pytest.mark.slow
def test_negative_energies_do_not_stop_the_iterations(arm5):
    """Obtuse triangles give negative cotangent weights, and Arm5's spokes energy goes below zero: the
    Anderson-accelerated iterations still never increase it, and stop on the fixed-point residual. Spokes and
    rims stays positive."""
    _, _, _, bc, data = arm5
    result = arap_solve(data["spokes"], jnp.asarray(bc))
    energies = np.asarray(result.energies)[: int(result.iterations) + 1]
    assert energies[-1] < 0 < energies[0]
    assert np.all(np.diff(energies) <= 1e-12 * np.abs(energies).max())
    assert bool(result.converged) and float(result.residual) <= deform.default_arap_tolerance(jnp.float64)
    assert np.all(np.isnan(np.asarray(result.energies)[int(result.iterations) + 1 :]))
    energies = np.asarray(arap_solve(data["spokes_and_rims"], jnp.asarray(bc)).energies)
    assert np.nanmin(energies) > 0


@pytest.mark.slow
def test_energy_decreases_and_tolerance_stops(arm):
    V, _, _, bc, data = arm
    diag = np.linalg.norm(np.ptp(V, axis=0))
    plain = arap_solve(
        data, jnp.asarray(bc), V0=V, max_iterations=30, tolerance=None, acceleration="none"
    )  # from the rest pose
    energies = np.asarray(plain.energies)
    assert int(plain.iterations) == 30 and not np.any(np.isnan(energies))
    assert np.all(np.diff(energies) <= 1e-12 * energies[0])
    assert energies[-1] < 0.01 * energies[0]
    # the residual is the last iteration's step, max |G(x) - x| / diagonal, with U = G(x)
    before = arap_solve(data, jnp.asarray(bc), V0=V, max_iterations=29, tolerance=None, acceleration="none").U
    assert float(plain.residual) == pytest.approx(np.abs(np.asarray(plain.U - before)).max() / diag, rel=1e-6)
    assert not bool(plain.converged)  # 30 plain iterations are far from the default tolerance
    # plain iterations need thousands of iterations for 1e-8 on the arm from its rest pose
    for tolerance, acceleration in ((1e-4, "none"), (1e-4, "anderson"), (1e-8, "anderson")):
        result = arap_solve(data, jnp.asarray(bc), V0=V, tolerance=tolerance, acceleration=acceleration)
        k = int(result.iterations)
        energies = np.asarray(result.energies)
        assert bool(result.converged) and float(result.residual) <= tolerance and k < 1000
        assert np.all(np.diff(energies[: k + 1]) <= 1e-12 * energies[0]) and np.all(np.isnan(energies[k + 1 :]))
        # it stopped at the first iteration that met the tolerance: one fewer does not meet it
        shorter = arap_solve(
            data, jnp.asarray(bc), V0=V, max_iterations=k - 1, tolerance=tolerance, acceleration=acceleration
        )
        assert float(shorter.residual) > tolerance and not bool(shorter.converged)


def test_rigid_motion_of_all_handles_is_exact(arm):
    V, _, b, _, data = arm
    R = Rotation.from_rotvec([0.3, -1.2, 0.7]).as_matrix()
    t = np.array([0.4, -0.2, 1.0])
    rigid = V @ R.T + t
    # the rigid map is a fixed point: started there, the iterations stay there
    result = arap_solve(data, jnp.asarray(rigid[b]), V0=rigid)
    np.testing.assert_allclose(result.U, rigid, atol=1e-9)
    assert bool(result.converged) and int(result.iterations) <= 10  # rounding-level steps only


def _welded(name):
    """A welded test model with its two ends along the long axis (5% each) as handles: (V, F, b, diagonal)."""
    mesh = deform.load_model(DATA / f"{name}.glb", weld=True).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    axis = np.argmax(np.ptp(V, axis=0))
    s = (V[:, axis] - V[:, axis].min()) / np.ptp(V[:, axis])
    return V, F, np.flatnonzero((s < 0.05) | (s > 0.95)), np.linalg.norm(np.ptp(V, axis=0))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Arm5", "CesiumMan"])
def test_rigid_motion_stays_rigid_on_real_meshes(name):
    """Every handle moved by one rigid motion: with spokes and rims (the default) the rigid map is the
    energy's minimum (zero), the default start (the handles' best rigid alignment) is on it and the iterations
    stay there; with the spokes energy, whose obtuse triangles make
    it negative, they fall away from it (the caveat of ``energy="spokes"``)."""
    V, F, b, diag = _welded(name)
    rigid = V @ Rotation.from_rotvec([0.1, -0.2, 0.2]).as_matrix().T + np.array([0.1, 0.0, -0.05]) * diag
    c = jnp.asarray(rigid[b])
    data = arap_precompute(V, F, b)
    result = arap_solve(data, c)  # the defaults, as `jaxcga arap`
    assert np.abs(np.asarray(result.U) - rigid).max() < 1e-6 * diag  # measured 2e-14 (Arm5), 2e-13 (CesiumMan)
    assert abs(float(result.energies[int(result.iterations)])) < 1e-10 * float(data.rest_energy)  # the minimum, zero
    spokes = arap_solve(arap_precompute(V, F, b, energy="spokes"), c, V0=rigid, max_iterations=50, tolerance=None)
    assert np.abs(np.asarray(spokes.U) - rigid).max() > 1e-3 * diag  # measured 1.8e-2 (Arm5), 4.4e-2 (CesiumMan)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["Arm5", "CesiumMan"])
def test_rigid_motion_is_reached_from_the_rest_pose(name):
    """From the rest pose with the handles moved by one rigid motion, plain local/global iterations approach the
    rigid map linearly and slowly (a rotation must spread along a long body); the default, Anderson-accelerated,
    reaches it to its tolerance, where 1000 plain iterations do not."""
    V, F, b, diag = _welded(name)
    rigid = V @ Rotation.from_rotvec([0.05, 0.0, -0.05]).as_matrix().T + np.array([0.1, 0.2, -0.1]) * diag
    c, x = jnp.asarray(rigid[b]), jnp.asarray(V)
    data = arap_precompute(V, F, b)
    result = arap_solve(data, c, V0=x)
    assert bool(result.converged) and int(result.iterations) < 1000
    assert np.abs(np.asarray(result.U) - rigid).max() < 1e-11 * diag
    plain = arap_solve(data, c, V0=x, acceleration="none")
    assert not bool(plain.converged) and int(plain.iterations) == 1000
    assert np.abs(np.asarray(plain.U) - rigid).max() > 1e3 * np.abs(np.asarray(result.U) - rigid).max()


def test_bad_input(arm):
    V, F, b, bc, data = arm
    with pytest.raises(ValueError, match="V"):
        arap_precompute(V[:, :2], F, b)
    with pytest.raises(ValueError, match="F"):
        arap_precompute(V, F[:, :2], b)
    with pytest.raises(ValueError, match=r"b: handle indices"):
        arap_precompute(V, F, np.array([0, len(V)]))
    with pytest.raises(ValueError, match="repeated"):
        arap_precompute(V, F, np.array([3, 3]))
    with pytest.raises(ValueError, match="non-empty"):
        arap_precompute(V, F, np.array([], int))
    with pytest.raises(ValueError, match="energy: expected one of"):
        arap_precompute(V, F, b, energy="rims")
    with pytest.raises(ValueError, match="bc"):
        arap_solve(data, jnp.asarray(bc[:-1]))
    with pytest.raises(ValueError, match="V0"):
        arap_solve(data, jnp.asarray(bc), V0=V[:-1])
    with pytest.raises(ValueError, match="max_iterations"):
        arap_solve(data, jnp.asarray(bc), max_iterations=0)
    for tolerance in (0.0, -1.0, "tight", True):
        with pytest.raises(ValueError, match="tolerance"):
            arap_solve(data, jnp.asarray(bc), tolerance=tolerance)
    with pytest.raises(ValueError, match="acceleration: expected one of"):
        arap_solve(data, jnp.asarray(bc), acceleration="nesterov")
    with pytest.raises(Exception, match="non-finite"):
        arap_solve(data, jnp.asarray(bc).at[0, 0].set(jnp.nan))


def _strip():
    """A bent 8 x 8 grid; the column x = 0 is fixed, the column x = 1 is the moving handle."""
    V, F = grid(8)
    V[:, 2] = 0.2 * np.sin(np.pi * V[:, 0]) * (1 + 0.3 * V[:, 1])
    left, right = np.nonzero(V[:, 0] == 0)[0], np.nonzero(V[:, 0] == 1)[0]
    return V, F, np.concatenate([left, right]), len(left)


@pytest.mark.slow
@pytest.mark.parametrize("energy", ARAP_ENERGIES)
def test_gradient_at_the_defaults_matches_central_differences(cylinder, energy):
    """At the default settings (converged to the default tolerance) the implicit gradient of a scalar of U with
    respect to the handle positions matches central differences of the same forward computation to 1e-6
    relative (a step of 1e-6 of the diagonal: the forward error is far below the step)."""
    V, F, b, bc, _ = cylinder
    data = arap_precompute(V, F, b, energy=energy)
    rng = np.random.default_rng(1)
    weights, direction = jnp.asarray(rng.normal(size=V.shape)), jnp.asarray(rng.normal(size=bc.shape))
    loss = jax.jit(lambda c: jnp.sum(weights * arap_solve(data, c).U))
    gradient = jax.jit(jax.grad(lambda c: jnp.sum(weights * arap_solve(data, c).U)))(jnp.asarray(bc))
    step = 1e-6 * np.linalg.norm(np.ptp(V, axis=0))
    numeric = (loss(bc + step * direction) - loss(bc - step * direction)) / (2 * step)
    assert bool(arap_solve(data, jnp.asarray(bc)).converged)
    assert float(jnp.sum(gradient * direction)) == pytest.approx(float(numeric), rel=1e-6)


@pytest.mark.slow
def test_implicit_gradient_fits_a_handle():
    """One compiled loss and gradient (the adjoint compiles slowly), at the defaults: gradient descent on it
    brings a marker vertex to a target."""
    V, F, b, k = _strip()
    data = arap_precompute(V, F, b)
    marker = 40

    @jax.jit
    @jax.value_and_grad
    def loss(shift, target):
        U = arap_solve(data, jnp.asarray(V[b]).at[k:].add(shift)).U
        return jnp.sum((U[marker] - target) ** 2)

    target = jnp.asarray(V[marker] + np.array([0.0, 0.1, 0.15]))
    shift = jnp.zeros(3)
    start = loss(shift, target)[0]
    for _ in range(12):
        shift = shift - 2.0 * loss(shift, target)[1]
    assert loss(shift, target)[0] < 1e-3 * start


@pytest.mark.slow
def test_vmap_and_jit_equal_one_by_one(cylinder):
    _, _, _, bc, data = cylinder
    batch = jnp.stack([jnp.asarray(bc) * s for s in (1.0, 0.9, 1.1)])
    solve = jax.jit(lambda c: arap_solve(data, c))  # each element iterates until its own convergence
    together = jax.vmap(solve)(batch)
    for c, U in zip(batch, together.U):
        # the same fixed point; the batched products round differently, and Anderson's extrapolation (its
        # least squares cut near-dependent differences) can take another path there: the iteration counts differ
        np.testing.assert_allclose(U, arap_solve(data, c).U, atol=1e-12)
    assert np.all(np.asarray(together.converged))


@pytest.mark.slow
def test_gradient_on_a_multi_part_character_matches_central_differences():
    """RobotExpressive (63 connected parts joined by weak bridges: the local/global map contracts slowly, and
    GMRES(40) on the adjoint stagnated): the implicit gradient at the defaults (1000 iterations, a residual
    short of the tolerance) matches central differences of tightly converged forward solves to 1e-6 relative."""
    mesh = load_character("RobotExpressive").mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    axis = np.argmax(np.ptp(V, axis=0))
    s = (V[:, axis] - V[:, axis].min()) / np.ptp(V[:, axis])
    b = np.flatnonzero((s < 0.05) | (s > 0.95))
    diag = np.linalg.norm(np.ptp(V, axis=0))
    bc = _moved(V, b, V[:, axis].min() + 0.5 * np.ptp(V[:, axis]), axis, [0.3, 0.2, 0.1], [0.05 * diag, 0, 0])
    data = arap_precompute(V, F, b)
    rng = np.random.default_rng(1)
    weights, direction = jnp.asarray(rng.normal(size=V.shape)), jnp.asarray(rng.normal(size=bc.shape))
    gradient = jax.jit(jax.grad(lambda c: jnp.sum(weights * arap_solve(data, c).U)))(jnp.asarray(bc))
    # references converged to 50 ulps; the slow contraction amplifies their residual into the positions, so a
    # wide step with a fourth-order stencil (its truncation error ~1e-8 relative here) rather than a narrow one
    loss = jax.jit(lambda c: jnp.sum(weights * arap_solve(data, c, tolerance=1.1e-14, max_iterations=5000).U))
    step = 1e-4 * diag

    def at(k):
        return loss(bc + k * step * direction)

    numeric = (8 * (at(1) - at(-1)) - (at(2) - at(-2))) / (12 * step)
    assert np.all(np.isfinite(np.asarray(gradient)))
    assert float(jnp.sum(gradient * direction)) == pytest.approx(float(numeric), rel=1e-6)


def test_progress_reports_every_iteration_with_its_energy_and_residual(arm):
    V, F, b, bc, data = arm
    seen = []
    solve = jax.jit(lambda bc: arap_solve(data, bc, progress=lambda *values: seen.append([float(v) for v in values])))
    result = solve(jnp.asarray(bc))
    plain = jax.jit(lambda bc: arap_solve(data, bc))(jnp.asarray(bc))  # jitted too: the same rounding
    iterations = int(result.iterations)
    assert iterations == int(plain.iterations) and [s[0] for s in seen] == list(range(1, iterations + 1))
    # each iteration's energy is that of the positions it started from: the result's energies before U's
    np.testing.assert_allclose([s[1] for s in seen], np.asarray(result.energies)[:iterations], rtol=1e-12)
    assert seen[-1][2] == pytest.approx(float(result.residual), rel=1e-12)
    np.testing.assert_allclose(np.asarray(result.U), np.asarray(plain.U), rtol=0, atol=1e-10)
    with pytest.raises(ValueError, match="progress: expected None or a function, got int"):
        arap_solve(data, jnp.asarray(bc), progress=3)  # pyright: ignore[reportArgumentType]


@pytest.mark.parametrize("options", [{}, {"tolerance": None, "acceleration": "none", "max_iterations": 15}])
def test_the_host_loop_gives_the_compiled_loops_iterations(arm, options):
    V, _, _, bc, data = arm
    diag = float(np.linalg.norm(np.ptp(V, axis=0)))
    seen = []
    host = arap_solve(
        data, bc, host_loop=True, progress=lambda *values: seen.append([float(v) for v in values]), **options
    )
    compiled = arap_solve(data, bc, **options)
    k = int(host.iterations)
    # the same iterations: Anderson's least squares may round apart near convergence, so the count may differ by
    # a few where the tolerance stops the loop, never the result
    assert abs(k - int(compiled.iterations)) <= (0 if options else 0.1 * k) and bool(host.converged) == bool(
        compiled.converged
    )
    # both stop at the fixed-point residual max |G(x) - x| (1.1e-14 of the diagonal); their distance from the fixed
    # point is that over (1 - the contraction), which ARAP's slow contraction makes thousands of times larger (the GPU
    # formulations' rounding, --gpu-variants, parts them by 1.1e-10 of the diagonal)
    np.testing.assert_allclose(np.asarray(host.U), np.asarray(compiled.U), rtol=0, atol=1e-9 * diag)
    # plain iterations follow one path; Anderson's paths part by rounding (the same start and minimum)
    energies, expected = np.asarray(host.energies), np.asarray(compiled.energies)
    if options:
        np.testing.assert_allclose(energies, expected, rtol=1e-9)
    else:
        assert energies[0] == pytest.approx(expected[0], rel=1e-12)
        assert energies[k] == pytest.approx(expected[int(compiled.iterations)], rel=1e-9)
    assert [s[0] for s in seen] == list(range(1, k + 1)) and seen[-1][2] == pytest.approx(float(host.residual))
    np.testing.assert_allclose([s[1] for s in seen], np.asarray(host.energies)[:k], rtol=1e-12)


def test_the_host_loops_runner_runs_each_compiled_step(arm):
    """A runner (the command line's exported programs) gets every compiled step of the host loop, by a stable name,
    on data without the factor, and the loop gives the host loop's own result."""
    V, _, _, bc, data = arm
    names = []

    def runner(name, step, *args):
        names.append(name)
        assert all(getattr(arg, "solver", None) is None for arg in args)  # no step holds the factor
        return step(*args)

    options = {"tolerance": None, "acceleration": "none", "max_iterations": 4}
    ran = arap_solve(data, bc, host_loop=True, runner=runner, **options)
    assert names == ["arap_aligned_rest", "arap_start", *["arap_between_solves"] * 4, "arap_result"]
    np.testing.assert_array_equal(np.asarray(ran.U), np.asarray(arap_solve(data, bc, host_loop=True, **options).U))
    with pytest.raises(ValueError, match="runner: expected a function, with host_loop=True"):
        arap_solve(data, bc, runner=runner)
    with pytest.raises(ValueError, match="runner: expected a function"):
        arap_solve(data, bc, host_loop=True, runner=3)  # pyright: ignore[reportArgumentType]


def test_the_host_loop_refuses_a_trace(arm):
    _, _, _, bc, data = arm
    with pytest.raises(ValueError, match="host_loop: runs on concrete input only"):
        jax.jit(lambda bc: arap_solve(data, bc, host_loop=True).U)(jnp.asarray(bc))
