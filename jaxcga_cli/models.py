"""What several commands share: loading a rigged model or a mesh (default: the built-in arm), the model's
bounding box for commands that take coordinates, the motion of ``deform`` and ``arap`` along a mesh's long axis,
and the one ``--handles`` file format of both.

The motion: a point at fraction s in [0, 1] along the long axis (from its lowest end, the pivot) turns about the
pivot by ``s * bend`` about the axis of the mesh's smallest extent and by ``s * twist`` about the long axis, then
moves by ``s * translate``. The axes are ranked by the extent of the middle 96% of the vertices (2nd to 98th
percentile), so that a thin part of few vertices sticking out of a character (a rifle's barrel, a staff) does not
make its axis the long one; the ends are the mesh's own.

HANDLES.json (``deform handles`` and ``arap``)::

    {"handles": [[i, ...], ...],                       groups of vertex indices, one group per handle
     "motors": [{"center": [x, y, z], "axis": [x, y, z], "angle_deg": a, "translation": [x, y, z]}, ...]}

one rigid motion per handle (rotation by ``angle_deg`` about ``axis`` through ``center``, then ``translation``;
every key optional, the identity by default; no "motors": every handle stays). ``arap`` also takes, instead of
"motors", ``"positions": [[[x, y, z], ...], ...]``: where each handle vertex goes, one list per handle.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np

import deform
import jaxcga as cga


def load_model(path: str | Path | None, weld: bool = False) -> deform.RiggedModel:
    """The rigged model at ``path``, or the built-in default arm when ``path`` is None."""
    if path is None:
        return deform.default_arm()
    return deform.load_model(path, weld=weld)


def load_mesh(path: str | Path | None, name: str = "mesh"):
    """(V, F) float64 / int64 of a mesh file (a glTF's bind-pose skinned mesh, welded; any other format by
    ``read_mesh_file``), or of the built-in arm's rest mesh when ``path`` is None; errors start with ``name``."""
    from _jaxcga_shared.meshfile import read_mesh_file

    if path is None:
        mesh = deform.default_arm().mesh
        return np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{name}: no such file {path}")
    if path.suffix.lower() in deform.GLTF_OUTPUTS:
        mesh = deform.load_model(path, weld=True).mesh
        return np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    return read_mesh_file(path, name)


def bounds(V) -> str:
    """The bounding box of the bind-pose vertices ``V`` and the up axis, for commands that take coordinates."""
    V = np.asarray(V)
    lo, hi = V.min(axis=0), V.max(axis=0)
    box = ", ".join(f"{a} [{lo[i]:.4g}, {hi[i]:.4g}]" for i, a in enumerate("xyz"))
    return f"the model's bind-pose bounding box is {box}; up is +y (glTF)"


class Motion:
    """The keys' motion along the mesh's long axis (see the module docstring)."""

    def __init__(self, V, bend_deg: float, twist_deg: float, translate=(0.0, 0.0, 0.0)):
        extent = V.max(axis=0) - V.min(axis=0)
        if extent.max() <= 0:
            raise ValueError("mesh: has no extent (all vertices coincide)")
        spread = np.quantile(V, 0.98, axis=0) - np.quantile(V, 0.02, axis=0)
        if spread.max() <= 0:  # nearly every vertex at one point: the full extents rank the axes
            spread = extent
        self.long = int(np.argmax(spread))
        others = [i for i in range(3) if i != self.long]
        self.across = others[int(np.argmin(spread[others]))]  # a cube's axes tie: still two distinct axes
        self.low, self.length = V[:, self.long].min(), extent[self.long]
        self.pivot = 0.5 * (V.min(axis=0) + V.max(axis=0))
        self.pivot[self.long] = self.low
        self.bend, self.twist = np.radians(bend_deg), np.radians(twist_deg)
        self.translate = np.asarray(translate, np.float64)

    def fraction(self, X) -> np.ndarray:
        return np.clip((np.asarray(X)[:, self.long] - self.low) / self.length, 0.0, 1.0)

    def motors(self, s) -> cga.Multivector:
        """The motors at fractions ``s`` along the long axis: one compiled call (the kernel's operations dispatched
        one by one would each be compiled or looked up on their own), exported to the cache (``cache.call``)."""
        from jaxcga_cli import cache

        angles = np.array([self.bend, self.twist])
        axes = (self.across, self.long)
        return cache.call(
            "motion_motors", _motion_motors, np.asarray(s, np.float64), self.pivot, angles, self.translate, axes
        )


def _motion_motors(s, pivot, angles, translate, axes: tuple[int, int]) -> cga.Multivector:
    """``Motion.motors``'s motors: the bend about axis ``axes[0]`` and the twist about ``axes[1]`` (``angles``,
    radians at s = 1), about ``pivot``, then ``s * translate``."""
    unit = jnp.eye(3, dtype=s.dtype)
    bend = cga.rotor(jnp.broadcast_to(unit[axes[0]], s.shape + (3,)), angles[0] * s)
    twist = cga.rotor(jnp.broadcast_to(unit[axes[1]], s.shape + (3,)), angles[1] * s)
    return deform.motor_about(
        jnp.asarray(pivot),
        (bend * twist).embed(cga.KINDS["rotor"]),
        s[..., None] * jnp.broadcast_to(translate, s.shape + (3,)),
    )


def end_handles(motion: Motion, V, fraction: float):
    """The vertices within ``fraction`` of the long axis's low and high ends (two index arrays)."""
    if fraction >= 0.5:
        raise ValueError(
            f"handle_fraction: {fraction} makes the two end handles overlap (each holds the vertices "
            "within this fraction of the long axis from its end); expected a fraction below 0.5"
        )
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


# A handle carried farther than this many mesh diagonals is a units mistake (and near float64's range the
# deformation's arithmetic overflows): refused.
MAX_REACH = 1e6


def read_handles(path: Path, V, positions: bool = False):
    """The handles of HANDLES.json (module docstring) for a mesh of vertices ``V`` ((n, 3)): (groups, motors,
    targets): the groups of vertex indices, their motors (a motor Multivector of batch shape (h,)) and, only where
    ``positions`` allows a "positions" entry and the file has one, each group's target positions (else None).
    Every handle must stay within ``MAX_REACH`` mesh diagonals of the mesh."""
    V = np.asarray(V, np.float64)
    n = len(V)
    spec = read_json(path, "handles")
    if not isinstance(spec, dict) or not isinstance(spec.get("handles"), list) or not spec["handles"]:
        raise ValueError(
            f"handles: {path} must hold a JSON object with a non-empty 'handles' list "
            '({"handles": [[i, ...], ...], "motors": [...]})'
        )
    unknown = set(spec) - {"handles", "motors", "positions"}
    if unknown:
        raise ValueError(
            f"handles: {path} has unknown keys {sorted(unknown)}; expected 'handles' and 'motors'"
            + (" or 'positions'" if positions else "")
        )
    try:
        handles = [np.asarray(h) for h in spec["handles"]]
    except (TypeError, ValueError):
        handles = []
    if len(handles) != len(spec["handles"]) or not all(np.issubdtype(h.dtype, np.integer) for h in handles):
        raise ValueError(f"handles: every handle in {path} must be a list of vertex indices")
    for i, h in enumerate(handles):
        if h.ndim != 1:
            raise ValueError(
                f"handles: handle {i} in {path} is a list of lists (groups within a group); each handle is one "
                "flat list of vertex indices [i, ...]: give each group as its own handle"
            )
    if any(len(h) == 0 or h.min() < 0 or h.max() >= n for h in handles):
        raise ValueError(f"handles: every handle needs vertex indices in [0, {n})")
    values, counts = np.unique(np.concatenate(handles), return_counts=True)
    if counts.max() > 1:
        raise ValueError(f"handles: vertex {values[np.argmax(counts)]} is in the handles {counts.max()} times")
    if "positions" in spec:
        if not positions:
            raise ValueError(
                f"handles: {path} gives 'positions'; this command moves each handle by a motor: give "
                "'motors' (jaxcga arap takes either)"
            )
        if "motors" in spec:
            raise ValueError(f"handles: {path} gives both 'motors' and 'positions'; give one")
        targets = _targets(spec["positions"], handles, path)
        _check_reach(targets, V, path, "positions")
        return handles, None, targets
    motors = _motors(spec.get("motors", [{}] * len(handles)), len(handles), path)
    moved = [
        np.asarray(cga.apply_to_points(cga.Multivector(motors.values[i], motors.blades), jnp.asarray(V[h])))
        for i, h in enumerate(handles)
    ]
    _check_reach(moved, V, path, "motor")
    return handles, motors, None


def _check_reach(moved, V, path, what: str) -> None:
    """Each handle's moved vertices lie within ``MAX_REACH`` mesh diagonals of the mesh's centre."""
    center = 0.5 * (V.min(axis=0) + V.max(axis=0))
    diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0))) or 1.0
    for i, P in enumerate(moved):
        with np.errstate(over="ignore", invalid="ignore"):
            reach = float(np.max(np.linalg.norm(P - center, axis=1))) / diagonal
        if not reach <= MAX_REACH:
            far = f"{reach:.3g} mesh diagonals ({diagonal:.4g})" if np.isfinite(reach) else "beyond float64's range"
            raise ValueError(
                f"handles: {what} {i} in {path} moves handle {i} {far} from the mesh, more than {MAX_REACH:g} "
                "diagonals: give the translation in the mesh's units"
            )


def _targets(given, handles, path):
    if not isinstance(given, list) or len(given) != len(handles):
        raise ValueError(
            f"handles: 'positions' in {path} must be a list of one list of positions per handle ({len(handles)})"
        )
    targets = []
    for i, (p, h) in enumerate(zip(given, handles)):
        try:
            p = np.asarray(p, np.float64)
        except (TypeError, ValueError):
            p = np.zeros(0)
        if p.shape != (len(h), 3) or not np.all(np.isfinite(p)):
            raise ValueError(
                f"handles: positions {i} in {path} must be {len(h)} finite [x, y, z] triples (one per "
                f"vertex of handle {i}), got shape {p.shape}"
            )
        targets.append(p)
    return targets


def _motors(motors, count: int, path):
    if not isinstance(motors, list) or len(motors) != count:
        raise ValueError(f"handles: 'motors' in {path} must be a list of one motor per handle ({count})")
    values = []
    for i, m in enumerate(motors):
        if not isinstance(m, dict) or set(m) - set(_MOTOR_KEYS):
            raise ValueError(
                f"handles: motor {i} in {path} must be an object with keys among {tuple(_MOTOR_KEYS)}, got {m!r}"
            )
        try:
            axis, center, translation = (
                np.asarray(m.get(k, _MOTOR_KEYS[k]), np.float64).reshape(3) for k in ("axis", "center", "translation")
            )
            angle = float(m.get("angle_deg", 0.0))
        except (TypeError, ValueError):
            raise ValueError(f"handles: motor {i} in {path} needs [x, y, z] lists and a number angle_deg") from None
        if not (np.isfinite([*axis, *center, *translation, angle]).all() and np.any(axis)):
            raise ValueError(f"handles: motor {i} in {path} needs finite numbers and a non-zero axis, got {m!r}")
        rotor = cga.rotor(jnp.asarray(axis), jnp.radians(jnp.asarray(angle, jnp.float64)))
        values.append(deform.motor_about(jnp.asarray(center), rotor, jnp.asarray(translation)).values)
    return cga.Multivector(jnp.stack(values), cga.KINDS["motor"])
