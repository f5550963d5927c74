"""FABRIK inverse kinematics for one chain (Aristidou & Lasenby 2011), the IK solver of the CGA
mesh-deformation paper's sec. III-C (Fig. 5): its joints give the key motors Q_i of eq. (3).

``fabrik`` moves the joints of a chain so that its end reaches a target with the root fixed and every
bone keeping its length: a backward pass places the end on the target and each joint on the line to
its old position at bone length from its successor, a forward pass does the same from the root
outwards; repeat until the end is within ``tolerance`` of the target. A target farther than the chain's
length gets the chain stretched straight toward it.

``chain_motors`` turns a solved chain into one motor per joint: joint 0 gets the root's translation
(the identity for a fixed root, so the start handle of the deformed region stays put), joint i + 1 the
rigid motion of bone i from rest to pose: the minimal rotation of the rest bone direction onto the posed
one about the rest joint i, then the translation of joint i. Each maps its rest joint onto its posed
joint. Fitted by ``deform._spline_fit`` at ``lambda_i = i / m`` they drive ``deform._spline``.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga
from _jaxcga_shared.checks import require
from deform._motor_field import motor_about
from jaxcga import KINDS, Multivector


def _check_chain(name: str, P):
    P = jnp.asarray(P)
    if P.ndim != 2 or P.shape[1] != 3 or P.shape[0] < 2:
        raise ValueError(f"{name}: expected joint positions of shape (m + 1, 3) with m >= 1 bones, got {P.shape}")
    if not jnp.issubdtype(P.dtype, jnp.floating):
        P = P.astype(jnp.result_type(float))
    return P


def _unit(d, fallback):
    """``d / |d|``, or ``fallback`` where d = 0 (two joints on top of each other: no direction)."""
    n2 = jnp.sum(d * d, axis=-1, keepdims=True)
    ok = n2 > 0
    return jnp.where(ok, d / jnp.sqrt(jnp.where(ok, n2, 1.0)), fallback)


def _bones(P):
    d = P[1:] - P[:-1]
    lengths = jnp.linalg.norm(d, axis=-1)
    lengths = require(lengths, (jnp.any(lengths <= 0), "P: every bone needs a positive length"))
    return lengths, d / lengths[:, None]


def fabrik(
    P: Float[ArrayLike, "m1 3"], target: Float[ArrayLike, "3"], max_iterations: int = 100, tolerance: float = 1e-10
) -> Float[Array, "m1 3"]:
    """Solve the chain ``P`` for ``target`` (FABRIK, Aristidou & Lasenby 2011).

    Args:
        P: (m + 1, 3) joint positions, P[0] the fixed root; bone lengths are ``|P[i+1] - P[i]|`` > 0.
        target: (3,) where the end joint P[m] should go.
        max_iterations: the number of backward + forward passes at most (static).
        tolerance: stop once the end joint is this close to the target.
    Returns:
        (m + 1, 3) the solved joints. A JAX function of P and target: jit, vmap (e.g. over targets) and
        reverse-mode gradients work (converged iterations are frozen, not skipped).
    """
    P = _check_chain("P", P)
    target = jnp.asarray(target)
    if target.shape != (3,):
        raise ValueError(f"target: expected shape (3,), got {target.shape}")
    target = target.astype(P.dtype)
    target = require(target, (~jnp.all(jnp.isfinite(target)), "target: non-finite values (NaN or inf)"))
    if not isinstance(max_iterations, int) or max_iterations < 1:
        raise ValueError(f"max_iterations: expected an integer >= 1, got {max_iterations!r}")
    lengths, rest = _bones(P)
    root = P[0]

    def backward(Q):
        def step(successor, bone):
            joint, length, direction = bone
            placed = successor + length * _unit(joint - successor, -direction)
            return placed, placed

        _, placed = jax.lax.scan(step, target, (Q[:-1], lengths, rest), reverse=True)
        return jnp.concatenate([placed, target[None]])

    def forward(Q):
        def step(previous, bone):
            joint, length, direction = bone
            placed = previous + length * _unit(joint - previous, direction)
            return placed, placed

        _, placed = jax.lax.scan(step, root, (Q[1:], lengths, rest))
        return jnp.concatenate([root[None], placed])

    def iteration(_, Q):
        done = jnp.linalg.norm(Q[-1] - target) <= tolerance
        return jnp.where(done, Q, forward(backward(Q)))

    solved = jax.lax.fori_loop(0, max_iterations, iteration, P)
    # out of reach: the chain points straight at the target
    toward = _unit(target - root, rest[0])
    offsets = jnp.concatenate([jnp.zeros(1, P.dtype), jnp.cumsum(lengths)])
    straight = root[None] + offsets[:, None] * toward[None]
    unreachable = jnp.linalg.norm(target - root) >= offsets[-1]
    return jnp.where(unreachable, straight, solved)


def rotor_between(u: Float[Array, "... 3"], v: Float[Array, "... 3"]) -> Multivector:
    """The rotor of the smallest rotation that turns direction ``u`` onto direction ``v`` (normalized
    here): ``(1 + v u) / |1 + v u|``; for opposite directions, a half turn about an axis normal to u.

    Args:
        u: (..., 3) directions to turn from.
        v: (..., 3) directions to turn onto.
    Returns:
        rotors, batch shape (...,)."""
    u, v = _unit(jnp.asarray(u), 0.0), _unit(jnp.asarray(v), 0.0)
    cross = jnp.cross(u, v)
    # v u = u.v - u^v, with u^v = c3 e12 - c2 e13 + c1 e23 for the cross product c = u x v
    half = jnp.concatenate(
        [1 + jnp.sum(u * v, axis=-1, keepdims=True), -cross[..., 2:], cross[..., 1:2], -cross[..., :1]], axis=-1
    )
    # opposite: any axis normal to u; cross u with the basis axis least aligned with it
    least = jax.nn.one_hot(jnp.argmin(jnp.abs(u), axis=-1), 3, dtype=u.dtype)
    axis = _unit(jnp.cross(u, least), 0.0)
    turn = jnp.concatenate([jnp.zeros_like(axis[..., :1]), -axis[..., 2:], axis[..., 1:2], -axis[..., :1]], axis=-1)
    n2 = jnp.sum(half * half, axis=-1, keepdims=True)
    opposite = n2 < 1e-20  # |u + v| below ~1e-10: the rotation plane is undefined to working precision
    values = jnp.where(opposite, turn, half / jnp.sqrt(jnp.where(opposite, 1.0, n2)))
    return Multivector(values, KINDS["rotor"])


def chain_motors(rest: Float[ArrayLike, "m1 3"], posed: Float[ArrayLike, "m1 3"]) -> Multivector:
    """One motor per joint (batch shape (m + 1,)) from a rest chain to a posed chain with the same bone
    lengths: Q_0 the root's translation, Q_{i+1} bone i's rigid motion (minimal rotation of its direction
    about rest joint i, then rest joint i to posed joint i). Q_i maps rest joint i onto posed joint i.

    Args:
        rest: (m + 1, 3) rest joint positions, root first.
        posed: (m + 1, 3) posed joint positions, the same bone lengths.

    Returns:
        The motors, batch shape (m + 1,).
    """
    rest, posed = _check_chain("rest", rest), _check_chain("posed", posed)
    if rest.shape != posed.shape:
        raise ValueError(f"posed: expected the shape of rest {rest.shape}, got {posed.shape}")
    _, u = _bones(rest)
    _, v = _bones(posed)
    bones = motor_about(rest[:-1], rotor_between(u, v), posed[:-1] - rest[:-1])
    root = cga.translator(posed[:1] - rest[:1]).embed(KINDS["motor"])
    return Multivector(jnp.concatenate([root.values, bones.values]), KINDS["motor"])
