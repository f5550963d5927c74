"""The inputs on which each per-platform kernel's CPU and GPU variants must agree (``_jaxcga_shared.platform``),
keyed by the kernel's registered name: ``test_platform_kernels.py`` runs both variants on them, and a registered
kernel without an entry here fails that test."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp

import jaxcga as cga
from _jaxcga_shared.sparse import csr_pattern
from deform._rig import _MATRIX_PRODUCT, _doubling_rounds, _versor_product
from jaxcga import KINDS, Multivector


class Example(NamedTuple):
    """Positional array arguments (pytrees: the branches of the platform conditional) and static keyword
    arguments of one call of a kernel."""

    args: tuple
    static: dict[str, Any]


def example(*args, **static) -> Example:
    return Example(args, static)


def _apply_to_points() -> list[Example]:
    rng = np.random.default_rng(7)
    motors = cga.exp_motor(Multivector(rng.normal(size=(64, 6)), cga.MOTOR_GENERATOR))
    similitude = cga.exp_similitude(Multivector(rng.normal(size=7) * [1, 1, 1, 1, 1, 1, 0.3], cga.SIMILITUDE_GENERATOR))
    rotors = cga.rotor(rng.normal(size=(2, 5, 3)), rng.normal(size=(2, 5)))
    dilators = cga.dilator(rng.uniform(0.1, 10.0, size=64))
    return [
        example(motors, rng.normal(size=(64, 3))),  # one versor per point
        example(similitude, rng.normal(size=(64, 3))),  # one for all points
        example(rotors, rng.normal(size=(5, 3))),  # batches broadcast
        example(dilators, rng.normal(size=(64, 3))),
    ]


def _table_product() -> list[Example]:
    rng = np.random.default_rng(3)
    similitudes = (
        Multivector(rng.normal(size=(23, 16)), KINDS["similitude"]),
        Multivector(rng.normal(size=(23, 16)), KINDS["similitude"]),
    )
    motors = (
        Multivector(rng.normal(size=(4, 1, 8)), KINDS["motor"]),
        Multivector(rng.normal(size=(3, 8)), KINDS["motor"]),
    )
    return [example(*similitudes, kind="geometric"), example(*motors, kind="geometric"), example(*motors, kind="outer")]


def _motor_field() -> list[Example]:
    rng = np.random.default_rng(11)
    weights = rng.dirichlet(np.ones(5), size=70)
    bound = rng.normal(size=(70, 3))
    logs = rng.normal(size=(5, 6)) * [0.8, 0.8, 0.8, 0.3, 0.3, 0.3]
    # 27 keys: the Triton program's loop over groups of keys and the keys left after it
    many = rng.dirichlet(np.ones(27), size=40)
    many_logs = rng.normal(size=(27, 6)) * [0.8, 0.8, 0.8, 0.3, 0.3, 0.3]
    return [
        example(weights, bound, logs),
        example(weights, bound, np.stack([logs, 0.5 * logs])),
        example(many, bound[:40], many_logs),
    ]


def _forward_kinematics() -> list[Example]:
    """Two trees (depths 5 and 1: three rounds of doubling), two poses, bones first; as similitudes and as
    matrices."""
    parents = (-1, 0, 1, 2, 3, 4, 1, 6, -1, 8)
    rounds = _doubling_rounds(parents, len(parents))
    generators = np.random.default_rng(5).normal(size=(len(parents), 2, 7)) * 0.5
    local = cga.exp_similitude(Multivector(generators, cga.SIMILITUDE_GENERATOR))
    indices = jnp.asarray(parents, jnp.int32)
    return [
        example(local.values, indices, compose=_versor_product(local.blades), rounds=rounds),
        example(cga.versor_to_matrix(local), indices, compose=_MATRIX_PRODUCT, rounds=rounds),
    ]


def _largest_quartic_root() -> list[Example]:
    rng = np.random.default_rng(3)
    S = rng.normal(size=(40, 3, 3))
    norm2 = np.sum(S * S, axis=(1, 2))
    c1, c0 = -8.0 * np.linalg.det(S), rng.normal(size=40) * norm2
    return [example(-2.0 * norm2, c1, c0, np.sqrt(3.0 * norm2), newton_steps=24)]


def _rig() -> tuple:
    """A small rig: 40 vertices, 3 influences each, 6 joints; motors and log-dilations for a batch of 3 poses."""
    rng = np.random.default_rng(11)
    n, k, joints = 40, 3, 6
    V = rng.normal(size=(n, 3))
    J = jnp.asarray(rng.integers(0, joints, size=(n, k)), jnp.int32)
    W = rng.uniform(0.1, 1.0, size=(n, k))
    W = W / W.sum(axis=1, keepdims=True)
    motors = cga.exp_motor(Multivector(rng.normal(size=(3, joints, 6)), cga.MOTOR_GENERATOR)).values
    log_scale = rng.normal(size=(3, joints)) * 0.3
    return V, J, W, motors, log_scale


def _skin_dqs() -> list[Example]:
    """One pose and a batch of three."""
    V, J, W, motors, _ = _rig()
    dq = cga.motor_to_dual_quaternion(Multivector(motors, KINDS["motor"]))
    return [example(V, J, W, dq[0]), example(V, J, W, dq)]


def _skin_cga_motor_blend() -> list[Example]:
    V, J, W, motors, log_scale = _rig()
    table = jnp.concatenate([motors, log_scale[..., None]], axis=-1)  # motor and log-dilation per joint
    return [example(V, J, W, table[0]), example(V, J, W, table)]


def _blend_dilations() -> list[Example]:
    _, J, W, _, log_scale = _rig()
    dilations = jnp.exp(log_scale)
    return [example(J, W, dilations[0]), example(J, W, dilations)]


def _spd_solve() -> list[Example]:
    """A 1-D Laplacian plus a mass term, 3 DOFs per node with coupled blocks (the FEM's block structure)."""
    m = 12
    # scipy is not annotated: pyright takes the type of ``offsets`` from its default, 0
    L = sp.diags([-1.0, 2.1, -1.0], [-1, 0, 1], shape=(m, m))  # pyright: ignore[reportArgumentType]
    block = np.array([[2.0, 0.5, 0.1], [0.5, 1.5, 0.2], [0.1, 0.2, 1.0]])
    A = sp.csr_matrix(sp.kron(L, block) + sp.identity(3 * m))
    b = np.random.default_rng(0).normal(size=3 * m)
    pattern = csr_pattern(A.indptr, A.indices, block=3)
    # CG to 1e-14 (well conditioned: 32 iterations) agrees with CHOLMOD to a few units of rounding
    return [example(pattern, jnp.asarray(A.data), jnp.asarray(b), jnp.asarray(1e-14))]


EXAMPLES: dict[str, Callable[[], list[Example]]] = {
    "apply_to_points": _apply_to_points,
    "table_product": _table_product,
    "deform.motor_field": _motor_field,
    "deform.forward_kinematics": _forward_kinematics,
    "deform.largest_quartic_root": _largest_quartic_root,
    "deform.skin_dqs": _skin_dqs,
    "deform.skin_cga_motor_blend": _skin_cga_motor_blend,
    "deform.blend_dilations": _blend_dilations,
    "sparse_spd_solve": _spd_solve,
    "sparse_spd_solve_dense": _spd_solve,
}
