"""The ``jaxcga deform {spline,handles,ffd,cage}`` commands (called by ``jaxcga.cli``).

Each loads a triangle mesh (any trimesh format; a glTF's bind-pose mesh, welded; default: the built-in
arm's rest mesh), binds it to key motors by one of the deformation paper's methods, moves the keys by
one motion along the mesh's long axis, and writes the deformed mesh (.glb, .obj, .ply, .stl), its
positions (.npy, float64 (n, 3)) or a figure of the rest and deformed mesh (.png).

The motion: a key at fraction s in [0, 1] along the long axis (from its lowest end, the pivot) turns
about the pivot by ``s * bend`` about the axis of the mesh's smallest extent and by ``s * twist`` about
the long axis, then moves by ``s * translate``. Spline keys sit at s = j / (k - 1); harmonic handles are
the mesh's two ends (the low end fixed, the high end at s = 1) unless a handles file is given; lattice
points and cage vertices sit at their own s; ``--positional`` moves FFD control points or cage
vertices by the same motors instead (classic FFD, positional cage) for comparison.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxcga as cga
from deform._cage import cage_precompute, tube_cage
from deform._default_arm import default_arm
from deform._ffd import bounding_lattice, distortion, ffd_precompute, lattice_points
from deform._handles import handles_precompute
from deform._motor_field import blend_positions, motor_about, motor_field_solve
from deform._spline import spline_precompute
from jaxcga._meshfile import read_mesh_file
from jaxcga._output import check_output, replacing, save_figure, write_bytes

DEFORMATIONS = ("spline", "handles", "ffd", "cage")
MESH_OUTPUTS = (".glb", ".gltf", ".obj", ".ply", ".stl")
POSITION_OUTPUTS = (".npy",) + MESH_OUTPUTS
DEFORM_OUTPUTS = POSITION_OUTPUTS + (".png",)


def load_mesh(path: str | Path | None, name: str = "mesh"):
    """(V, F) float64 / int64 of a mesh file (a glTF's bind-pose skinned mesh, welded; any other format by
    ``read_mesh_file``), or of the built-in arm's rest mesh when ``path`` is None; errors start with ``name``."""
    if path is None:
        mesh = default_arm().mesh
        return np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{name}: no such file {path}")
    if path.suffix.lower() in (".glb", ".gltf"):
        from deform._gltf import load_model

        mesh = load_model(path, weld=True).mesh
        return np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    return read_mesh_file(path, name)


class Motion:
    """The keys' motion along the mesh's long axis (see the module docstring)."""

    def __init__(self, V, bend_deg: float, twist_deg: float, translate=(0.0, 0.0, 0.0)):
        extent = V.max(axis=0) - V.min(axis=0)
        if extent.max() <= 0:
            raise ValueError("mesh: has no extent (all vertices coincide)")
        self.long = int(np.argmax(extent))
        others = [i for i in range(3) if i != self.long]
        self.across = others[int(np.argmin(extent[others]))]  # a cube's axes tie: still two distinct axes
        self.low, self.length = V[:, self.long].min(), extent[self.long]
        self.pivot = 0.5 * (V.min(axis=0) + V.max(axis=0))
        self.pivot[self.long] = self.low
        self.bend, self.twist = np.radians(bend_deg), np.radians(twist_deg)
        self.translate = np.asarray(translate, np.float64)

    def fraction(self, X) -> np.ndarray:
        return np.clip((np.asarray(X)[:, self.long] - self.low) / self.length, 0.0, 1.0)

    def motors(self, s) -> cga.Multivector:
        s = jnp.asarray(s, jnp.float64)
        axes = np.eye(3)
        bend = cga.rotor(jnp.broadcast_to(jnp.asarray(axes[self.across]), s.shape + (3,)), self.bend * s)
        twist = cga.rotor(jnp.broadcast_to(jnp.asarray(axes[self.long]), s.shape + (3,)), self.twist * s)
        return motor_about(jnp.asarray(self.pivot), (bend * twist).embed(cga.KINDS["rotor"]),
                           s[..., None] * jnp.asarray(self.translate))


def _end_handles(motion: Motion, V, fraction: float):
    if fraction >= 0.5:
        raise ValueError(f"handle_fraction: {fraction} makes the two end handles overlap (each holds the vertices "
                         "within this fraction of the long axis from its end); expected a fraction below 0.5")
    if not fraction >= 0:
        raise ValueError(f"handle_fraction: expected a fraction in [0, 0.5), got {fraction}")
    s = motion.fraction(V)
    start, end = np.flatnonzero(s <= fraction), np.flatnonzero(s >= 1.0 - fraction)
    if len(start) == 0 or len(end) == 0:
        raise ValueError(f"handle_fraction: no vertex within {fraction} of an end of the long axis")
    return start, end


def read_json(path: Path, what: str):
    """The JSON document in ``path``; a ``ValueError`` naming ``what`` and the file when it is not JSON."""
    try:
        return json.loads(Path(path).read_bytes())
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise ValueError(f"{what}: {path} is not valid JSON ({error})") from None


_MOTOR_KEYS = {"center": [0.0, 0.0, 0.0], "axis": [0.0, 0.0, 1.0], "angle_deg": 0.0, "translation": [0.0, 0.0, 0.0]}


def _handles_file(path: Path, n: int):
    """Handles and their motors from JSON: ``{"handles": [[i, ...], ...], "motors": [{"center": [x, y, z],
    "axis": [x, y, z], "angle_deg": a, "translation": [x, y, z]}, ...]}`` (one motor per handle; every
    key optional: the identity by default)."""
    spec = read_json(path, "handles")
    if not isinstance(spec, dict) or not isinstance(spec.get("handles"), list) or not spec["handles"]:
        raise ValueError(f"handles: {path} must hold a JSON object with a non-empty 'handles' list")
    try:
        handles = [np.asarray(h, np.int64).reshape(-1) for h in spec["handles"]]
    except (TypeError, ValueError):
        raise ValueError(f"handles: every handle in {path} must be a list of vertex indices") from None
    if any(len(h) == 0 or h.min() < 0 or h.max() >= n for h in handles):
        raise ValueError(f"handles: every handle needs vertex indices in [0, {n})")
    motors = spec.get("motors", [{}] * len(handles))
    if not isinstance(motors, list) or len(motors) != len(handles):
        raise ValueError(f"handles: 'motors' in {path} must be a list of one motor per handle ({len(handles)})")
    values = []
    for i, m in enumerate(motors):
        if not isinstance(m, dict) or set(m) - set(_MOTOR_KEYS):
            raise ValueError(f"handles: motor {i} in {path} must be an object with keys among {tuple(_MOTOR_KEYS)}, "
                             f"got {m!r}")
        try:
            axis, center, translation = (np.asarray(m.get(k, _MOTOR_KEYS[k]), np.float64).reshape(3)
                                         for k in ("axis", "center", "translation"))
            angle = float(m.get("angle_deg", 0.0))
        except (TypeError, ValueError):
            raise ValueError(f"handles: motor {i} in {path} needs [x, y, z] lists and a number angle_deg") from None
        if not (np.isfinite([*axis, *center, *translation, angle]).all() and np.any(axis)):
            raise ValueError(f"handles: motor {i} in {path} needs finite numbers and a non-zero axis, got {m!r}")
        rotor = cga.rotor(jnp.asarray(axis), jnp.radians(jnp.asarray(angle, jnp.float64)))
        values.append(motor_about(jnp.asarray(center), rotor, jnp.asarray(translation)).values)
    return handles, cga.Multivector(jnp.stack(values), cga.KINDS["motor"])


def deform_command(method: str, V, F, out: Path, *, bend: float = 60.0, twist: float = 0.0,
                   translate=(0.0, 0.0, 0.0), basis: str = "bspline", keys: int | None = None,
                   weights: str = "cotangent", handle_fraction: float = 0.05, handles: Path | None = None,
                   lattice=(4, 4, 4), cage: Path | None = None, positional: bool = False) -> dict:
    """Bind (V, F) by ``method`` (one of ``DEFORMATIONS``), move the keys, write ``out``; returns a
    summary (vertices, keys, precompute and per-frame milliseconds, volume and edge-length change)."""
    if method not in DEFORMATIONS:
        raise ValueError(f"method: expected one of {DEFORMATIONS}, got {method!r}")
    out = check_output(out, DEFORM_OUTPUTS)
    if positional and method not in ("ffd", "cage"):
        raise ValueError("positional: only the ffd and cage deformations have a positional form")
    if keys is not None and keys > len(V):
        raise ValueError(f"keys: expected at most one key motor per vertex ({len(V)}), got {keys}")
    motion = Motion(V, bend, twist, translate)
    start = time.perf_counter()
    if method == "spline":
        first, last = _end_handles(motion, V, handle_fraction)
        if keys is None and basis == "bspline":
            keys = 5
        field = spline_precompute(V, F, first, last, basis=basis, num_keys=keys, laplacian=weights)
        key_motors = motion.motors(np.linspace(0.0, 1.0, field.num_keys))
    elif method == "handles":
        if handles is None:
            parts = list(_end_handles(motion, V, handle_fraction))
            key_motors = motion.motors(np.array([0.0, 1.0]))
        else:
            parts, key_motors = _handles_file(handles, len(V))
        field = handles_precompute(V, F, parts, laplacian=weights)
    elif method == "ffd":
        grid = bounding_lattice(V, tuple(lattice), padding=0.02)
        field = ffd_precompute(V, grid)
        points = lattice_points(grid)
        key_motors = motion.motors(motion.fraction(points))
        control = cga.apply_to_points(key_motors, points)
    else:
        if cage is None:
            cage_V, cage_F = tube_cage(V, axis=motion.long)
        else:
            cage_V, cage_F = load_mesh(cage, "cage")
        field = cage_precompute(V, cage_V, cage_F)
        key_motors = motion.motors(motion.fraction(cage_V))
        control = cga.apply_to_points(key_motors, jnp.asarray(cage_V))
    precompute_ms = 1e3 * (time.perf_counter() - start)

    if positional:
        frame = jax.jit(lambda P: blend_positions(field.weights, P))
        argument = control
    else:
        frame = jax.jit(lambda motors: motor_field_solve(field, motors))
        argument = key_motors
    positions = jax.block_until_ready(frame(argument))
    start = time.perf_counter()
    positions = jax.block_until_ready(frame(argument))
    frame_ms = 1e3 * (time.perf_counter() - start)
    positions = np.asarray(positions, np.float64)
    if not np.all(np.isfinite(positions)):
        raise ValueError("the deformation produced non-finite positions")
    _write(out, V, positions, F, f"{method}{' (positional)' if positional else ''}")
    measured = distortion(V, F, positions)
    return {
        "method": method + (" (positional)" if positional else ""),
        "vertices": len(V),
        "keys": field.num_keys,
        "precompute_ms": round(precompute_ms, 1),
        "frame_ms": round(frame_ms, 2),
        "volume_ratio": round(float(measured["volume_ratio"]), 4),
        "mean_edge_change": round(float(measured["edge_mean"]), 4),
        "out": str(out),
    }


def write_positions(out: Path, positions, F) -> None:
    """Write ``positions`` to ``out``: .npy float64 (n, 3), or the mesh (positions, F) in a trimesh format (a
    .gltf holds its buffers), through ``jaxcga._output`` (an existing file survives a failed write)."""
    if out.suffix.lower() == ".npy":
        with replacing(out) as (temp,), open(temp, "wb") as file:  # np.save on a name would append .npy
            np.save(file, np.asarray(positions, np.float64))
        return
    import trimesh

    file_type = out.suffix.lower()[1:]
    data = trimesh.Trimesh(np.asarray(positions), np.asarray(F), process=False).export(
        file_type=file_type, **({"embed_buffers": True} if file_type == "gltf" else {}))
    write_bytes(out, data["model.gltf"] if isinstance(data, dict) else data)


def _write(out: Path, V, positions, F, title: str):
    if out.suffix.lower() == ".png":
        deformation_figure(V, positions, F, out, title)
    else:
        write_positions(out, positions, F)


def deformation_figure(V, positions, F, path: Path, title: str) -> Path:
    """Rest and deformed mesh side by side, on the same axes' scale."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    both = np.concatenate([V, positions])
    lo, hi = both.min(axis=0), both.max(axis=0)
    fig = plt.figure(figsize=(10, 4.5))
    for k, (X, label, color) in enumerate(((V, "rest", "tab:gray"), (positions, title, "tab:orange"))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=F, color=color, linewidth=0, alpha=0.9)
        ax.set(xlim=(lo[0], hi[0]), ylim=(lo[1], hi[1]), zlim=(lo[2], hi[2]), title=label)
        ax.set_box_aspect(np.maximum(hi - lo, 1e-9 * (hi - lo).max()))
        ax.set_axis_off()
    return save_figure(fig, path, dpi=90, bbox_inches="tight")
