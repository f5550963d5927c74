"""Rollouts: ``steps`` backward Euler steps (``xfem._backward_euler``, eq. 10) as one ``jax.lax.scan``, every
frame's state returned, differentiable in reverse mode with respect to the initial state, the ``Material``, the
body forces and the fixed nodes' targets of every frame.

Gradient. Each step's reverse pass is the step's implicit gradient (``_minimize``'s custom VJP): the step's
result x is treated as the converged minimizer of E (eq. 10), so ``dx/dtheta = -H(x)^-1 d(grad E)/dtheta`` with
H the true Hessian at x. At the defaults every step converges (``stats.converged`` per frame says so), and this
is the derivative of the rollout computed. With the paper's single Newton iteration (``newton_iterations=1,
tolerance=None``) the step stops short of the minimizer, and the gradient is the converged step's formula
evaluated at the executed iterate: an approximation of the derivative of the executed iteration (which would
differentiate the Newton update, the line search and the start's choice, and is not computed).
tests/xfem/test_rollout.py checks both statements and measures the difference.

Memory. The scan body is checkpointed (``jax.checkpoint``) with a policy that keeps only each step's Newton
result (``checkpoint_name``): the reverse pass stores the states and re-runs none of the Newton iterations, and
no per-step temporaries (element Hessians, line-search trials) live across steps.
"""

from __future__ import annotations

import functools
from typing import Literal

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from xfem._backward_euler import _NEWTON_ITERATIONS, _NEWTON_RESULT, FEMSystem, State, _advance, _step_arguments
from xfem._material import Material


def rollout(
    system: FEMSystem,
    state: State,
    material: Material,
    h: float | Float[Array, ""],
    steps: int,
    *,
    newton_iterations: int = _NEWTON_ITERATIONS,
    tolerance: float | Literal["auto"] | None = "auto",
    line_search: bool = True,
    forces: Float[Array | np.ndarray, "n 3"] | Float[Array | np.ndarray, "steps n 3"] | None = None,
    targets: Float[Array, "steps nb 3"] | None = None,
) -> State:
    """``steps`` backward Euler steps from ``state`` (``backward_euler_step`` in a ``jax.lax.scan``); jit-,
    vmap- and grad-able (reverse mode through each step's implicit gradient, module docstring).

    Args:
        system: the ``FEMSystem``.
        state: the ``State`` at time 0, x and v (n, 3) in the system's dtype.
        material: the ``Material``.
        h: the positive time step.
        steps: python int >= 0, the number of steps.
        newton_iterations: as ``backward_euler_step`` (by default each step converges;
            ``newton_iterations=1, tolerance=None`` is the paper's single iteration, approximate for gradients).
        tolerance: see ``newton_iterations``.
        line_search: see ``newton_iterations``.
        forces: None (the system's ``force`` every frame), (n, 3) forces for every frame, or (steps, n, 3) the
            forces of each frame, replacing ``system.force``.
        targets: None (the fixed nodes stay where they are in ``state``), or (steps, nb, 3) the fixed nodes'
            positions at each frame (``fixed_positions`` of the steps: a moving boundary).
    Returns:
        The ``State`` of every frame: x and v of shape (steps, n, 3), frame k after k + 1 steps, and each step's
        ``SolveStats`` (``stats.converged``, ``iterations``, ``residual`` of shape (steps,)).
    """
    system, state, h, material, _, iterations, tolerance, line_search = _step_arguments(
        system, state, h, material, None, newton_iterations, tolerance, line_search
    )
    if not isinstance(steps, int) or isinstance(steps, bool) or steps < 0:
        raise ValueError(f"steps: expected an int >= 0, got {steps!r}")
    dtype, n, nb = system.grads.dtype, system.n, system.fixed.shape[0]
    if forces is not None:
        forces = jnp.asarray(forces)
        if forces.shape not in ((n, 3), (steps, n, 3)) or not jnp.issubdtype(forces.dtype, jnp.floating):
            raise ValueError(
                f"forces: expected float forces of shape ({n}, 3) or ({steps}, {n}, 3), got "
                f"{forces.dtype} {forces.shape}"
            )
        forces = forces.astype(dtype)
    if targets is not None:
        targets = jnp.asarray(targets)
        if targets.shape != (steps, nb, 3) or not jnp.issubdtype(targets.dtype, jnp.floating):
            raise ValueError(
                f"targets: expected float positions of shape ({steps}, {nb}, 3), got {targets.dtype} {targets.shape}"
            )
        targets = targets.astype(dtype)
    return _rollout(system, state, h, material, forces, targets, steps, iterations, tolerance, line_search)


@eqx.filter_jit
def _rollout(system, state, h, material, forces, targets, steps, iterations, tolerance, line_search):
    mu, lam = material.lame()
    per_frame = forces is not None and forces.ndim == 3
    constant = system.force if forces is None else forces
    fixed_start = state.x[system.fixed]

    # only the Newton result is kept for the reverse pass: it re-runs the cheap parts of a step, not its Newton
    @functools.partial(
        jax.checkpoint,
        prevent_cse=False,  # no CSE across scan iterations to prevent
        policy=jax.checkpoint_policies.save_only_these_names(_NEWTON_RESULT),
    )
    def body(s, frame):
        force, target = frame
        s = _advance(
            system,
            s,
            h,
            mu,
            lam,
            fixed_start if target is None else target,
            force if per_frame else constant,
            iterations,
            tolerance,
            line_search,
            material.damping,
        )
        return s, s

    return jax.lax.scan(body, state, (forces if per_frame else None, targets), length=steps)[1]
