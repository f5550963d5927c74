"""The reduced (real-time) mode of character physics (``xfem.character_subspace``,
``xfem.simulate_character(..., subspace=...)``): the modes against an independent linear-elastic stiffness, the stiff
limit against the skinned body, the damped decay of free modes against the closed-form modal recurrence, gradients
against central differences, and the full-space mode."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import deform
import xfem
from tests.shared import character_body_of
from tests.xfem._linear_elasticity import stiffness

FPS = 30.0


@functools.cache
def _arm_body(still: bool = False):
    """The built-in arm as a coarse body (its clip, or none: the rest pose held)."""
    model = deform.default_arm(rings_per_unit=60.0)
    if still:
        model = deform.RiggedModel(model.mesh, model.skeleton, (), model.name)
    return xfem.character_body(model, edge_length=0.1, threads=1)


@functools.cache
def _subspace(modes: int = 12):
    return xfem.character_subspace(_arm_body(), modes)


def _play(body, sub, frames: int, material, **options):
    """The reduced play's one segment (every frame)."""
    motion = xfem.simulate_character(body, 0, frames / FPS, FPS, material=material, subspace=sub, **options)
    assert len(motion.segments) == 1 and motion.frames == frames + 1
    return motion.segments[0]


def _free_matrices(body, subspace):
    X, T = np.asarray(body.tets.X), np.asarray(body.tets.T)
    dofs = (3 * subspace.free[:, None] + np.arange(3)).ravel()
    K = stiffness(X, T, 1.0, subspace.poisson)[dofs][:, dofs].toarray()
    M1 = xfem.consistent_mass(X, T, body.density)
    M = np.kron(M1[subspace.free][:, subspace.free].toarray(), np.eye(3))
    return K, M


@pytest.mark.slow
@pytest.mark.parametrize("name", ["arm", "Fox"])
def test_modes_are_the_lowest_mass_orthonormal_eigenvectors_of_linear_elasticity(name):
    body = _arm_body() if name == "arm" else character_body_of(name)
    sub = _subspace() if name == "arm" else xfem.character_subspace(body, 12)
    Phi, lam = sub.modes, sub.eigenvalues
    assert Phi.shape == (3 * len(sub.free), 12) and np.all(np.diff(lam) >= 0) and lam[0] > 0
    np.testing.assert_array_equal(sub.free, np.setdiff1d(np.arange(body.tets.n_nodes), body.driven))
    K, M = _free_matrices(body, sub)  # K: textbook P1 linear elasticity, E = 1
    np.testing.assert_allclose(Phi.T @ M @ Phi, np.eye(12), atol=1e-12)
    residual = np.linalg.norm(K @ Phi - M @ Phi * lam, axis=0) / np.linalg.norm(K @ Phi, axis=0)
    assert residual.max() < 1e-8
    # the lowest ones: a dense generalized eigensolve of the same pair
    np.testing.assert_allclose(lam, scipy.linalg.eigh(K, M, eigvals_only=True, subset_by_index=(0, 11)), rtol=1e-8)
    assert np.all(sub.basis[body.driven] == 0)
    np.testing.assert_array_equal(sub.basis[sub.free].reshape(-1, 12), Phi)


def _skinned_surface(body, frames: int) -> np.ndarray:
    times = np.arange(frames + 1) / FPS
    nodes = [deform.skin_model(body.node_model, t, "cga", 0) for t in times]
    return np.stack([np.asarray(body.embedding.positions(x)) for x in nodes])


def test_the_stiff_limit_is_the_skinned_body_and_the_difference_falls_with_stiffness():
    body, sub = _arm_body(), _subspace()
    frames = 30
    skinned = _skinned_surface(body, frames)
    errors = []
    for young in (1e5, 1e6, 1e7, 1e8):
        surface = _play(body, sub, frames, xfem.Material(young, 0.4)).surface
        assert surface.shape == (frames + 1, len(body.surface), 3)
        errors.append(float(np.abs(np.asarray(surface) - skinned).max()) / body.diagonal)
    np.testing.assert_allclose(np.asarray(surface)[0], skinned[0], atol=1e-12)  # frame 0 is the rig
    assert errors[0] > 3e-3 and errors[-1] < 3e-4, errors  # the flesh moves, and the stiff body is the skinned one
    # the difference falls with E, as 1/E once quasi-static (the stiffer decades; the softest may resonate)
    assert all(b / a < 0.3 for a, b in zip(errors, errors[1:])), errors
    assert all(0.05 < b / a < 0.2 for a, b in zip(errors[1:], errors[2:])), errors


def _joint_linear(model, local) -> np.ndarray:
    globals_ = deform.forward_kinematics_matrices(model.skeleton.parents, local)
    return np.asarray(deform.joint_matrices(model.mesh, globals_))[:, :3, :3]


def test_a_moving_rig_plays_the_documented_step():
    """The step of the module docstring with the rig moving, solved densely in numpy from deform's public skinning:
    ``B_k`` formed node by node (``R_i = sum_j w_ij A_j``), ``M`` the full consistent mass. The play assembles
    ``B_k^T M B_k`` from its joint pairs' mass products instead, and must agree to rounding."""
    body, sub = _arm_body(), _subspace()
    frames, young, beta = 6, 2e5, 0.01
    h = 1 / FPS
    model = body.node_model
    x_play = np.asarray(_play(body, sub, frames, xfem.Material(young, 0.4, beta)).states.x)
    n, k = body.tets.n_nodes, len(sub.eigenvalues)
    mass = np.kron(xfem.consistent_mass(body.tets.X, body.tets.T, body.density).toarray(), np.eye(3))
    weights = np.zeros((n, len(model.mesh.joints)))
    np.add.at(weights, (np.arange(n)[:, None], np.asarray(model.mesh.J)), np.asarray(model.mesh.W))
    rest = np.linalg.inv(_joint_linear(model, deform.local_matrices(model.skeleton)))
    driven = np.zeros(n, bool)
    driven[body.driven] = True
    gravity = np.tile(body.gravity, n)

    def skinned(t):
        return np.asarray(deform.skin_model(model, t, "cga", 0)).ravel()

    def basis(t):
        A = np.einsum("jab,jbc->jac", _joint_linear(model, deform.sample_pose(model, t, "lbs", 0, "gltf")), rest)
        R = np.einsum("nj,jab->nab", weights, A)
        B = np.zeros((n, 3, k))
        B[~driven] = np.einsum("nab,nbk->nak", R[~driven], sub.basis[~driven])
        return B.reshape(3 * n, k)

    stiffness = young * sub.eigenvalues
    x, v, q = skinned(0.0), (skinned(h) - skinned(0.0)) / h, np.zeros(k)
    expected = [x]
    for step in range(1, frames + 1):
        S, B = skinned(step * h), basis(step * h)
        lhs = B.T @ mass @ B + np.diag((h**2 + beta * h) * stiffness)
        rhs = B.T @ mass @ (x + h * v - S + h**2 * gravity) + beta * h * stiffness * q
        q = np.linalg.solve(lhs, rhs)
        x, v = S + B @ q, (S + B @ q - x) / h
        expected.append(x)
    expected = np.stack(expected).reshape(frames + 1, n, 3)
    assert np.abs(expected - expected[0]).max() > 0.05 * body.diagonal  # the rig moves the arm
    lag = np.abs(expected[1:] - np.stack([skinned(i * h) for i in range(1, frames + 1)]).reshape(-1, n, 3)).max()
    assert lag > 1e-3 * body.diagonal  # and the flesh lags it
    np.testing.assert_allclose(x_play, expected, rtol=0, atol=1e-12 * body.diagonal)


def _modal_recurrence(sub, young: float, damping: float, frames: int, gravity) -> np.ndarray:
    """Each mode alone, as the step reads with the rig at rest (B = Phi, B^T M B = I, v = Phi dq / h):
    (1 + (h^2 + beta h) E lam) q_k = 2 q_{k-1} - q_{k-2} + beta h E lam q_{k-1} + h^2 Phi^T M g."""
    h = 1 / FPS
    stiff = young * sub.eigenvalues
    force = np.einsum("nak,n,a->k", sub.basis[sub.free], sub.lumped, gravity)
    q = [np.zeros(len(stiff)), np.zeros(len(stiff))]
    for _ in range(frames):
        q.append((2 * q[-1] - q[-2] + damping * h * stiff * q[-1] + h**2 * force) / (1 + (h**2 + damping * h) * stiff))
    return np.stack(q[1:])


def test_free_modes_decay_with_damping_as_the_modal_recurrence():
    body = _arm_body(still=True)
    sub = xfem.character_subspace(body, 8)
    # the lowest mode at h omega = 0.3, where backward Euler's own damping leaves it swinging, and damped
    # by beta = 1 / omega (damping ratio beta omega / 2 = 1/2 there, more above)
    omega = 0.3 * FPS
    frames, young, beta = 60, omega**2 / sub.eigenvalues[0], 1 / omega
    mass = xfem.consistent_mass(body.tets.X, body.tets.T, body.density)
    amplitudes = {}
    for damping in (0.0, beta):
        material = xfem.Material(young, 0.4, damping) if damping else xfem.Material(young, 0.4)
        x = np.asarray(_play(body, sub, frames, material).states.x)
        # the modal coordinates of the displacement from the rest pose (B = Phi there: Phi^T M Phi = I)
        q = np.einsum("fnd,ndk->fk", np.stack([mass @ d for d in x - np.asarray(body.tets.X)]), sub.basis)
        expected = _modal_recurrence(sub, young, damping, frames, body.gravity)
        np.testing.assert_allclose(q, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
        rest = _static(sub, body) / (young * sub.eigenvalues)  # the static sag the modes swing about
        swing = np.abs(q - rest).max(axis=1)
        amplitudes[damping] = (swing[:10].max(), swing[-10:].max())
    (_, undamped_late), (damped_early, damped_late) = amplitudes[0.0], amplitudes[beta]
    assert damped_late < 0.1 * damped_early and damped_late < 0.5 * undamped_late


def _static(sub, body) -> np.ndarray:
    """Phi^T M g: the modal gravity force (the static sag is its quotient by E Lambda)."""
    return np.einsum("nak,n,a->k", sub.basis[sub.free], sub.lumped, body.gravity)


def test_reduced_play_gradients_match_central_differences():
    body, sub = _arm_body(), _subspace()
    frames = 10

    def loss(params):
        material = xfem.Material(params[0], 0.4, params[1])
        surface = _play(body, sub, frames, material).surface
        return jnp.mean(surface[-1, :, 1]) + jnp.mean(surface[frames // 2] ** 2)

    params = jnp.array([3e5, 0.02])
    grad = jax.grad(loss)(params)
    # small steps: the loss swings with E (the modes' phases after 10 frames), and fTetWild's body varies run to run
    for i, step in enumerate((1e1, 1e-6)):
        plus, minus = (loss(params.at[i].add(s)) for s in (step, -step))
        np.testing.assert_allclose(grad[i], (plus - minus) / (2 * step), rtol=1e-5)


def test_bad_input_is_a_value_error_naming_the_argument():
    body, sub = _arm_body(), _subspace()
    free = 3 * len(sub.free)
    for modes in (0, free, 2.5, True):
        with pytest.raises(ValueError, match="modes"):
            xfem.character_subspace(body, modes)  # pyright: ignore[reportArgumentType]
    for poisson in (0.5, -1.0, "0.3"):
        with pytest.raises(ValueError, match="poisson"):
            xfem.character_subspace(body, 4, poisson=poisson)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="body"):
        xfem.character_subspace(body.tets, 4)  # pyright: ignore[reportArgumentType]
    material = xfem.Material(1e5, 0.4)
    with pytest.raises(ValueError, match="material: Poisson's ratio 0.3"):
        _play(body, sub, 3, xfem.Material(1e5, 0.3))
    with pytest.raises(ValueError, match="subspace: it was computed for another body"):
        _play(_arm_body(still=True), sub, 3, material)
    with pytest.raises(ValueError, match="subspace: expected a CharacterSubspace"):
        _play(body, sub.modes, 3, material)
    with pytest.raises(ValueError, match="subspace: the reduced mode does not cut"):
        _play(body, sub, 3, material, plane_cuts=[(2, np.zeros(3), np.array([1.0, 0, 0]), 1e-3)])
    with pytest.raises(ValueError, match="fps"):
        xfem.simulate_character(body, 0, 1.0, -1.0, material=material, subspace=sub)
    with pytest.raises(ValueError, match="method"):
        _play(body, sub, 3, material, method="linear")
    with pytest.raises(ValueError, match="clip"):
        xfem.simulate_character(body, "no such clip", 1.0, FPS, material=material, subspace=sub)


@pytest.mark.slow
def test_the_reduced_play_follows_the_full_space_one():
    """The arm waving, soft and damped: the reduced surface lies close to the full mode's (converged steps), much
    closer than either lies to the skinned surface, and it moves as much as the full one does."""
    body = _arm_body()
    frames, material = 15, xfem.Material(1e5, 0.4, 0.01)
    full = np.asarray(xfem.simulate_character(body, 0, frames / FPS, FPS, material=material).segments[0].surface)
    reduced = np.asarray(_play(body, xfem.character_subspace(body, 24), frames, material).surface)
    skinned = _skinned_surface(body, frames)

    def rms(a, b):
        return float(np.sqrt(np.mean(np.sum((a - b) ** 2, axis=-1)))) / body.diagonal

    lag_full, lag_reduced, error = rms(full, skinned), rms(reduced, skinned), rms(reduced, full)
    assert lag_full > 1e-3  # the flesh does lag
    assert error < 0.25 * lag_full and abs(lag_reduced - lag_full) < 0.2 * lag_full, (error, lag_full, lag_reduced)
