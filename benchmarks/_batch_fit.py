"""Fitting poses to many models at once (``deform.fit_packed``), a section of ``bench_batch.py``: ``fit_figures``.

Three ways to fit every model of a batch to its own targets (random poses of each model, ``random_parameters`` +
``skin_parameters``, a subset of its vertices as targets), all with ``fit_pose``'s solver (Levenberg-Marquardt,
the same tolerances and steps):

* ``loop``: a Python loop of ``deform.fit_pose`` per model (the baseline; one compiled solver per model size);
* ``packed``: ``deform.fit_packed``, ``jax.vmap`` over the models of one optimistix solve per model (kept);
* ``one_solve``: one optimistix least-squares solve over all models' parameters at once on the packed data (its
  Jacobian is block diagonal, but the dense Levenberg-Marquardt step costs the cube of the total parameter count,
  and one damping and one stopping test serve all models).

The fits run in float64 (``jax.enable_x64``, whatever the caller's setting): in float32 the tolerances are below
the rounding noise, and ``fit_pose`` itself stops up to 1e-3 away (and twice the steps later) when its targets move
by one ulp. Warm figures are medians of calls after the first; cold ones are the first call after
``jax.clear_caches()``, compilation included. Ratios are the loop's time over the packed call's (> 1: the packed call
is faster). ``param_error`` figures are the largest parameter difference to the loop's fits; their yardstick,
``fit_pose_perturbed_param_error``, is how far ``fit_pose`` moves when the targets move by 1e-14 of themselves.
"""

from __future__ import annotations

import functools
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT  # noqa: E402

import deform  # noqa: E402
from deform._batch_fitting import fit_data  # noqa: E402
from deform._fitting import pose_residuals, run_solver  # noqa: E402
from tests.deform._rigs import random_model  # noqa: E402

REAL_MODELS = ("CesiumMan", "RiggedSimple", "Arm5")


def fit_models(count: int, seed: int = 0) -> list[deform.RiggedModel]:
    """CesiumMan, RiggedSimple and Arm5 from tests/data, then random rigs (4-24 bones in a random tree, 200-3000
    vertices, 2-4 influences) up to ``count`` models."""
    models = [deform.load_model(ROOT / "tests" / "data" / f"{name}.glb") for name in REAL_MODELS][:count]
    rng = np.random.default_rng(seed)
    for i in range(count - len(models)):
        bones = int(rng.integers(4, 25))
        parents = (-1,) + tuple(int(rng.integers(0, b)) for b in range(1, bones))
        n, k = int(rng.integers(200, 3001)), int(rng.integers(2, 5))
        models.append(random_model(seed + 100 + i, parents=parents, n=n, influences=k))
    return models


def fit_problems(models, targets_per_model: int, seed: int = 0):
    """Each model's targets at (up to) ``targets_per_model`` vertices spread over its mesh, from a random pose."""
    targets, vertices = [], []
    for m, model in enumerate(models):
        key = jax.random.PRNGKey(seed + m)
        truth = deform.random_parameters(key, model, rotation=0.3, translation=0.02, log_scale=0.1)
        n = model.mesh.num_vertices
        index = jnp.asarray(np.linspace(0, n - 1, min(n, targets_per_model)).round().astype(np.int32))
        targets.append(deform.skin_parameters(model, truth)[index])
        vertices.append(index)
    return targets, vertices


def _all_residuals(y, data):
    """The packed models' residuals as one vector: one least-squares problem over all their parameters."""
    return jax.vmap(pose_residuals)(y, data).ravel()


def _one_solve(packed, targets, vertices, options):
    """Every model's parameters (M, B, 7) from one optimistix solve over all of them, and its step count."""
    data, _ = fit_data(
        packed,
        targets,
        vertices,
        method=options["method"],
        regularization=options["regularization"],
        fit_scale=True,
    )
    y0 = jnp.zeros(data.bone_mask.shape + (deform.PARAMETERS_PER_BONE,), data.V.dtype)
    sol = run_solver(_all_residuals, "levenberg_marquardt", y0, data, options["max_steps"], 1e-10, 1e-12)
    return sol.value, sol.stats["num_steps"]


def _timed(fn, repeats: int) -> tuple[float, float, Any]:
    """(cold seconds, warm median seconds, last result) of ``fn()``."""
    jax.clear_caches()
    eqx.clear_caches()
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    cold = time.perf_counter() - start
    warm = []
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn())
        warm.append(time.perf_counter() - start)
    return cold, statistics.median(warm), out


def _in_float64(fn):
    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.enable_x64(True):
            return fn(*args, **kwargs)

    return wrapped


@_in_float64
def fit_figures(
    count: int = 8,
    targets_per_model: int = 200,
    *,
    method: str = "cga",
    regularization: float = 1e-6,
    max_steps: int = 200,
    repeats: int = 3,
    one_solve: bool = False,
) -> dict:
    """Time ``fit_packed`` against a loop of ``fit_pose`` on ``count`` models (``fit_models``), and with
    ``one_solve`` one solve over all their parameters (its dense step grows with the cube of the parameter count:
    minutes per call at 8 models), print the figures and return ``{"figures", "ratios", "units"}`` (``_report``'s
    layout)."""
    models = fit_models(count)
    targets, vertices = fit_problems(models, targets_per_model)
    packed = deform.pack_models(models)
    options: dict[str, Any] = dict(method=method, regularization=regularization, max_steps=max_steps)
    caps = packed.capacities
    print(
        f"fit: {count} models ({', '.join(m.name for m in models)}), {caps.bones} bones and "
        f"{deform.capacity(targets_per_model)} targets per model slot, {method}, {max_steps} steps at most",
        flush=True,
    )

    def loop():
        return [deform.fit_pose(m, t, v, **options) for m, t, v in zip(models, targets, vertices, strict=True)]

    loop_cold, loop_warm, alone = _timed(loop, repeats)
    print(f"  loop of fit_pose: {loop_warm:.4g} s warm, {loop_cold:.4g} s cold", flush=True)
    packed_cold, packed_warm, fits = _timed(lambda: deform.fit_packed(packed, targets, vertices, **options), repeats)
    print(f"  fit_packed: {packed_warm:.4g} s warm, {packed_cold:.4g} s cold", flush=True)
    reference = [np.asarray(f.params) for f in alone]
    perturbed = [
        deform.fit_pose(m, t * (1 + 1e-14), v, **options) for m, t, v in zip(models, targets, vertices, strict=True)
    ]
    figures = {
        "fit_loop_s": loop_warm,
        "fit_loop_cold_s": loop_cold,
        "fit_packed_s": packed_warm,
        "fit_packed_cold_s": packed_cold,
        "fit_packed_param_error": max(
            float(np.abs(np.asarray(f.params) - r).max()) for f, r in zip(fits, reference, strict=True)
        ),
        "fit_pose_perturbed_param_error": max(
            float(np.abs(np.asarray(f.params) - r).max()) for f, r in zip(perturbed, reference, strict=True)
        ),
        "fit_loop_steps_max": max(int(f.steps) for f in alone),
        "fit_packed_steps_max": max(int(f.steps) for f in fits),
    }
    units = {name: "s" for name in figures if name.endswith("_s")}
    units |= {"fit_packed_param_error": "rad / log-scale / model units", "fit_loop_steps_max": "steps"}
    units["fit_pose_perturbed_param_error"] = units["fit_packed_param_error"]
    units["fit_packed_steps_max"] = "steps"
    ratios = {"fit_packed_vs_loop": loop_warm / packed_warm, "fit_packed_vs_loop_cold": loop_cold / packed_cold}
    if one_solve:
        one_cold, one_warm, (value, steps) = _timed(lambda: _one_solve(packed, targets, vertices, options), repeats)
        value = np.asarray(value)
        figures |= {
            "fit_one_solve_s": one_warm,
            "fit_one_solve_cold_s": one_cold,
            "fit_one_solve_param_error": max(
                float(np.abs(value[m, : len(r)] - r).max()) for m, r in enumerate(reference)
            ),
            "fit_one_solve_steps": int(steps),
        }
        units |= {"fit_one_solve_s": "s", "fit_one_solve_cold_s": "s", "fit_one_solve_steps": "steps"}
        units["fit_one_solve_param_error"] = units["fit_packed_param_error"]
        ratios |= {"fit_packed_vs_one_solve": one_warm / packed_warm, "fit_one_solve_vs_loop": loop_warm / one_warm}
    units |= {name: RATIO_UNIT for name in ratios}
    for name, value in figures.items():
        print(f"  {name}: {value:.4g} {units[name]}")
    for name, value in ratios.items():
        print(f"  {name}: {value:.3g} {RATIO_UNIT}")
    return {"figures": figures, "ratios": ratios, "units": units}
