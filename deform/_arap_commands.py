"""The ``jaxcga arap`` command (called by ``jaxcga.cli``): ARAP with rotors (deformation paper sec. VII,
``deform/_arap.py``) on a mesh file with handles from JSON.

HANDLES.json is ``{"indices": [i, ...], "positions": [[x, y, z], ...]}``: the handle vertices and where they
go. Without a handles file the mesh's two ends along its long axis are the handles: the low end stays and
the high end moves by the same motion as ``jaxcga deform`` (``--bend`` / ``--twist`` / ``--translate``).
"""

from __future__ import annotations

import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from deform._arap import arap_precompute, arap_solve
from deform._deform_commands import DEFORM_OUTPUTS, Motion, _end_handles, _write, read_json
from jaxcga import apply_to_points
from jaxcga._output import check_output


def read_handles(path: Path, n: int):
    """(indices (k,), positions (k, 3)) from HANDLES.json, checked against a mesh of ``n`` vertices."""
    spec = read_json(path, "handles")
    if not isinstance(spec, dict) or "indices" not in spec or "positions" not in spec:
        raise ValueError(f'handles: {path} must hold {{"indices": [...], "positions": [[x, y, z], ...]}}')
    indices = np.asarray(spec["indices"])
    positions = np.asarray(spec["positions"], dtype=np.float64)
    if indices.ndim != 1 or len(indices) == 0 or not np.issubdtype(indices.dtype, np.integer):
        raise ValueError(f"handles: 'indices' must be a non-empty list of vertex indices, got {spec['indices']!r:.80}")
    if indices.min() < 0 or indices.max() >= n:
        raise ValueError(f"handles: 'indices' must lie in [0, {n}) for this mesh")
    values, counts = np.unique(indices, return_counts=True)
    if counts.max() > 1:
        raise ValueError(f"handles: 'indices' has vertex {values[np.argmax(counts)]} repeated ({counts.max()} times)")
    if positions.shape != (len(indices), 3) or not np.all(np.isfinite(positions)):
        raise ValueError(f"handles: 'positions' must be {len(indices)} finite [x, y, z] triples (one per index), "
                         f"got shape {positions.shape}")
    return indices.astype(np.int64), positions


def default_handles(V, bend: float, twist: float, translate, fraction: float):
    """The low end of the long axis fixed, the high end moved by ``Motion(V, bend, twist, translate)``."""
    motion = Motion(V, bend, twist, translate)
    low, high = _end_handles(motion, V, fraction)
    moved = np.asarray(apply_to_points(motion.motors(jnp.ones(len(high))), jnp.asarray(V[high])))
    return np.concatenate([low, high]), np.concatenate([V[low], moved])


def arap_command(V, F, out: Path, *, handles: Path | None = None, iterations: int = 10, tolerance: float = 1e-8,
                 bend: float = 60.0, twist: float = 0.0, translate=(0.0, 0.0, 0.0),
                 handle_fraction: float = 0.05, energy: str = "spokes_and_rims") -> dict:
    """Deform (V, F) as rigidly as possible with the handles of ``handles`` (or the default two ends),
    write ``out`` (.npy float64 (n, 3), a mesh, or a .png figure); returns a summary. ``energy``:
    ``arap_precompute``'s ("spokes_and_rims" or "spokes")."""
    out = check_output(out, DEFORM_OUTPUTS)
    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iters: expected an int >= 1, got {iterations!r}")
    if handles is None:
        b, bc = default_handles(V, bend, twist, translate, handle_fraction)
    else:
        b, bc = read_handles(handles, len(V))
    start = time.perf_counter()
    data = arap_precompute(V, F, b, energy=energy)
    precompute_ms = 1e3 * (time.perf_counter() - start)
    start = time.perf_counter()
    result = jax.block_until_ready(arap_solve(data, jnp.asarray(bc), max_iterations=iterations, tolerance=tolerance))
    solve_ms = 1e3 * (time.perf_counter() - start)
    U = np.asarray(result.U, np.float64)
    _write(out, V, U, F, f"ARAP, {int(result.iterations)} iterations")
    energies = np.asarray(result.energies)[: int(result.iterations) + 1]
    return {
        "vertices": len(V),
        "handles": len(b),
        "energy_type": energy,
        "iterations": int(result.iterations),
        "energy": f"{energies[0]:.4g} -> {energies[-1]:.4g}",
        "precompute_ms": round(precompute_ms, 1),
        "solve_ms": round(solve_ms, 1),  # includes compilation
        "out": str(out),
    }
