"""Fitting poses to every model of a packed batch at once (``fit_packed``): ``fit_pose`` of each model, under one
jit, as ``jax.vmap`` over the models of one optimistix solve.

Each model keeps its own solve: ``fit_pose``'s residual (``_fitting.pose_residuals``) over its own parameters,
with its own damping and stopping test; under vmap the batched solver loop runs until every model's solve has
stopped, a stopped model's state held. A model's data are padded to the batch's capacities:

* targets to ``capacity`` of the largest target count, the padded rows masked out of the residual;
* bones to the packed bone capacity: a padded bone binds no joint and is not regularized, so its Jacobian
  columns (and gradient) are zero and every solver's step leaves its parameters at zero;
* influences to the packed influence count, with zero weights.

One least-squares solve over all models' parameters (a block-diagonal Jacobian) is the alternative:
``benchmarks/_batch_fit.py`` measures both against a loop of ``fit_pose``. A dense Levenberg-Marquardt over the
joint parameters costs the cube of their total count per step and shares one damping and one stopping test among
all models, so each model's fit no longer equals its own.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.mesh import bounding_diagonal
from deform import _pose
from deform._batch import PackedModels, PackedRigs, capacity, skin_joint_tables
from deform._fitting import (
    PARAMETERS_PER_BONE,
    FitData,
    PoseFit,
    check_options,
    check_targets,
    full_parameters,
    pose_fit,
    pose_residuals,
    run_solver,
    similitudes_from_parameters,
)
from jaxcga._multivector import Multivector


def _per_model(name: str, items, count: int) -> list:
    if isinstance(items, (np.ndarray, jax.Array)) or not isinstance(items, (list, tuple)):
        raise ValueError(f"{name}: expected a list with one array per model ({count}), got {type(items).__name__}")
    if len(items) != count:
        raise ValueError(f"{name}: expected one array per model ({count}), got {len(items)}")
    return list(items)


def _rest(rigs: PackedRigs):
    return rigs.translation, rigs.rotation, rigs.scale


@eqx.filter_jit
def posed_blocks(rigs: PackedRigs, params: Float[Array, "D M B 7"], method: str) -> Float[Array, "D N 3"]:
    """Skinned positions of every block with each model posed by its parameters (``pose_from_parameters``)."""

    def block(r: PackedRigs, p):
        local = _pose.local_for_method(similitudes_from_parameters(_rest(r), p), method)
        joints = jax.vmap(_pose.joint_transforms)(r.parents, r.joint_bones, r.inverse_bind, local)
        return skin_joint_tables(r, jax.tree.map(lambda x: x[:, None], joints), method)[0]

    return jax.vmap(block)(rigs, params)


def fit_data(
    packed: PackedModels,
    targets: Sequence,
    vertices: Sequence | None,
    *,
    method: str,
    regularization: float,
    fit_scale: bool,
) -> tuple[FitData, list[tuple[Array, np.ndarray]]]:
    """The batched ``FitData`` (leading axis: the models, in the order packed) of a packed fit, and each model's
    checked targets and vertex indices."""
    M = packed.num_models
    dtype = packed.rigs.V.dtype
    targets = _per_model("targets", targets, M)
    vertices = [None] * M if vertices is None else _per_model("vertices", vertices, M)
    checked = [
        check_targets(t, v, n, dtype, f"[{m}]")
        for m, (t, v, n) in enumerate(zip(targets, vertices, packed.vertex_count, strict=True))
    ]
    caps = packed.capacities
    T = capacity(max(len(index) for _, index in checked))
    rows = np.zeros((M, T), np.int32)
    padded = np.zeros((M, T, 3), dtype)
    target_mask = np.zeros((M, T), dtype)
    for m, (t, index) in enumerate(checked):
        # padded rows repeat the model's first vertex: finite, and masked out of the residual
        rows[m] = packed.vertex_offset[m]
        rows[m, : len(index)] += index
        padded[m, : len(index)] = np.asarray(t)
        target_mask[m, : len(index)] = 1.0
    bone_mask = (np.arange(caps.bones) < np.asarray(packed.bone_count)[:, None]).astype(dtype)
    block, slot = np.asarray(packed.block), np.asarray(packed.slot)
    rigs = packed.rigs
    rest = posed_blocks(rigs, jnp.zeros((caps.blocks, caps.models, caps.bones, PARAMETERS_PER_BONE), dtype), method)
    rest = np.asarray(rest)
    diagonal = [
        bounding_diagonal(rest[b, o : o + n])
        for b, o, n in zip(block, packed.vertex_offset, packed.vertex_count, strict=True)
    ]

    def take(x):
        return x[block, slot]

    def vertex(x):
        return x[block[:, None], rows]

    data = FitData(
        rest=(take(rigs.translation), take(rigs.rotation), take(rigs.scale)),
        parents=take(rigs.parents),
        joint_bones=take(rigs.joint_bones),
        inverse_bind=take(rigs.inverse_bind),
        V=vertex(rigs.V),
        # the block's joint table holds slot s's joints from s * joints on: back to the model's own indices
        J=vertex(rigs.J) - jnp.asarray(slot * caps.joints, jnp.int32)[:, None, None],
        W=vertex(rigs.W),
        targets=jnp.asarray(padded),
        target_mask=jnp.asarray(target_mask),
        bone_mask=jnp.asarray(bone_mask),
        diagonal=jnp.asarray(diagonal, dtype),
        root_regularization=jnp.full(M, np.sqrt(regularization), dtype),
        fit_scale=fit_scale,
        method=method,
    )
    return data, checked


@eqx.filter_jit
def _solve(data: FitData, solver: str, max_steps: int, rtol: float, atol: float):
    width = PARAMETERS_PER_BONE if data.fit_scale else PARAMETERS_PER_BONE - 1
    y0 = jnp.zeros(data.bone_mask.shape + (width,), data.V.dtype)

    def one(d, y):
        sol = run_solver(pose_residuals, solver, y, d, max_steps, rtol, atol)
        return sol.value, sol.stats["num_steps"], sol.result == optx.RESULTS.successful

    return jax.vmap(one)(data, y0)


def fit_packed(
    packed: PackedModels,
    targets: Sequence[Float[ArrayLike, "t 3"]],
    vertices: Sequence[Int[ArrayLike, " t"] | None] | None = None,
    *,
    method: str = "cga",
    regularization: float = 0.0,
    fit_scale: bool = True,
    solver: str = "levenberg_marquardt",
    max_steps: int = 200,
    rtol: float = 1e-10,
    atol: float = 1e-12,
) -> list[PoseFit]:
    """``fit_pose`` for every model of a packed batch at once, each to its own targets: one jit, ``jax.vmap`` over
    the models of one optimistix solve. In float64 each fit equals ``fit_pose`` of its model alone to the solver's
    tolerance; in float32 the default tolerances lie below the rounding noise, and both stop within it (as
    ``fit_pose`` does, up to 1e-3 away, when a target moves by one ulp).

    Args:
        packed: the PackedModels (``pack_models``; one process).
        targets: one (t_m, 3) array per model, in the order packed: target positions of the vertices
            ``vertices[m]`` (all of the model's vertices when ``vertices`` is None: t_m = n_m).
        vertices: one (t_m,) int array of vertex indices per model (None for all of a model's vertices), or
            None (all vertices of every model).
        method: as ``fit_pose``, for every model.
        regularization: see ``method``.
        fit_scale: see ``method``.
        solver: see ``method``.
        max_steps: see ``method``.
        rtol: see ``method``.
        atol: see ``method``.
    Returns:
        one PoseFit per model, in the order packed."""
    if not isinstance(packed, PackedModels):
        raise ValueError(f"packed: expected the PackedModels of pack_models, got {type(packed).__name__}")
    check_options(method, regularization, fit_scale, solver, max_steps)
    data, checked = fit_data(
        packed, targets, vertices, method=method, regularization=regularization, fit_scale=fit_scale
    )
    value, steps, converged = _solve(data, solver, int(max_steps), rtol, atol)
    params = full_parameters(value, fit_scale)
    local = similitudes_from_parameters(data.rest, params)
    caps = packed.capacities
    block, slot = np.asarray(packed.block), np.asarray(packed.slot)
    by_block = jnp.zeros((caps.blocks, caps.models) + params.shape[1:], params.dtype).at[block, slot].set(params)
    positions = posed_blocks(packed.rigs, by_block, method)
    fits = []
    for m, (t, index) in enumerate(checked):
        b, o, n, nb = block[m], packed.vertex_offset[m], packed.vertex_count[m], packed.bone_count[m]
        local_m = Multivector(local.values[m, :nb], local.blades)
        fits.append(pose_fit(params[m, :nb], local_m, positions[b, o : o + n], t, index, steps[m], converged[m]))
    return fits
