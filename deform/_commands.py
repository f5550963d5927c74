"""The ``jaxcga skin``, ``jaxcga animate`` and ``jaxcga fit`` commands (called by ``jaxcga.cli``).

Each takes an optional MODEL path (glTF, or FBX / COLLADA through assimp); without one it uses the
built-in default arm.
"""

from __future__ import annotations

from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

import jaxcga as cga
from deform import _fitting, _pose, _rig
from deform._default_arm import default_arm
from deform._deform_commands import POSITION_OUTPUTS, write_positions
from deform._gltf import GLTF_OUTPUTS, buffer_file, load_model, save_model
from deform._model import RiggedModel
from jaxcga._output import check_output, save_figure, write_json
from _jaxcga_shared.mesh import bounding_diagonal


def load_or_default(path: str | Path | None, weld: bool = False) -> RiggedModel:
    """The model at ``path``, or the built-in default arm when ``path`` is None."""
    if path is None:
        return default_arm()
    return load_model(path, weld=weld)


def skin_command(model: RiggedModel, time: float, method: str, clip: int | str, out: Path,
                 interpolation: str = "gltf") -> dict:
    """Skinned positions of every skinned primitive (file order) at ``time``, in glTF world space,
    written to ``out`` (.npy: float64 (n, 3); .glb etc.: the posed mesh); keys interpolated by
    ``interpolation`` (``deform.skin_model``)."""
    out = check_output(out, POSITION_OUTPUTS)
    positions = jax.jit(lambda t: _pose.skin_model(model, t, method, clip, interpolation))(time)
    if not bool(jnp.all(jnp.isfinite(positions))):
        raise ValueError("skinning produced non-finite positions")
    write_positions(out, positions, model.mesh.F)
    return {"vertices": int(positions.shape[0]), "method": method, "interpolation": interpolation, "time": time,
            "out": str(out)}


def generated_keyframes(model: RiggedModel, duration: float = 2.0) -> _rig.Keyframes:
    """Keyframes made on the fly (sec. 2.5 / 4.1): rest, every bone bent about its local x axis with
    the deepest bone dilated by 1.25, and rest again; blended linearly by ``sample_keyframes``."""
    skeleton = model.skeleton
    rest = _rig.local_versors(skeleton)
    depth = np.zeros(skeleton.num_bones, int)
    for i, p in enumerate(skeleton.parents):
        depth[i] = 0 if p < 0 else depth[p] + 1
    dtype = rest.dtype
    bend = cga.rotor(jnp.asarray([1.0, 0.0, 0.0], dtype), jnp.asarray(0.35 * (depth > 0), dtype))
    scale = jnp.where(jnp.asarray(depth == depth.max()), 1.25, 1.0).astype(dtype)
    bent = (rest * bend * cga.dilator(scale)).embed(cga.KINDS["similitude"])
    poses = cga.Multivector(jnp.stack([rest.values, bent.values, rest.values]), rest.blades)
    return _rig.Keyframes(jnp.asarray([0.0, duration / 2, duration], dtype), poses)


def animate_command(model: RiggedModel, frames: int, out: Path, clip: int | str = 0,
                    interpolation: str = "gltf") -> dict:
    """Write an animated glTF: the model's clip re-sampled at ``frames`` times as similitudes, its keys
    interpolated by ``interpolation`` (``"gltf"``: the specification's; ``"log"``: logarithmic
    blending of key versors, sec. 4.1), or generated keyframes (linear blending) when the model has
    no clip."""
    if frames < 2:
        raise ValueError(f"frames: expected at least 2, got {frames}")
    out = check_output(out, GLTF_OUTPUTS)
    buffer_file(out, "out")
    if model.clips:
        source = model.clip(clip)
        times = jnp.linspace(source.start, source.end, frames, dtype=model.mesh.V.dtype)
        local = jax.jit(jax.vmap(lambda t: _pose.sample_pose(model, t, "cga", clip, interpolation)))(times)
        name = f"{source.name}_cga"
    else:
        keys = generated_keyframes(model)
        times = jnp.linspace(0.0, float(keys.times[-1]), frames, dtype=model.mesh.V.dtype)
        local = jax.jit(jax.vmap(lambda t: _rig.sample_keyframes(keys, t)))(times)
        name = "generated_keyframes"
    animation = _rig.clip_from_poses(times, local, name)
    save_model(RiggedModel(model.mesh, model.skeleton, (animation,), model.name), out)
    return {"frames": frames, "clip": name, "bones": model.skeleton.num_bones, "out": str(out)}


def fit_command(model: RiggedModel, target: Path, out: Path, method: str = "cga", vertices: Path | None = None,
                regularization: float = 0.0, max_steps: int = 200, fit_scale: bool = True) -> dict:
    """Fit bone motors (and dilations) to target positions (.npy (n, 3), or (t, 3) with a vertex index
    file) and write the pose as JSON."""
    out = check_output(out, (".json",))
    targets = _read_array("target", target)
    index = None if vertices is None else _read_array("vertices", vertices)
    if index is None and targets.shape != (model.mesh.num_vertices, 3):
        raise ValueError(f"target: expected shape ({model.mesh.num_vertices}, 3) (every vertex), got "
                         f"{targets.shape}; give --vertices for a subset")
    dtype = model.mesh.V.dtype
    fit = _fitting.fit_pose(model, jnp.asarray(targets, dtype), None if index is None else jnp.asarray(index),
                            method=method, regularization=regularization, max_steps=max_steps,
                            fit_scale=fit_scale and method != "dqs")
    translation, rotation, scale = _rig.versor_to_trs(fit.local)
    diagonal = bounding_diagonal(_pose.rest_pose(model, "lbs"))
    result = {
        "model": model.name,
        "method": method,
        "max_error": float(fit.max_error),
        "rms_error": float(fit.rms_error),
        "bounding_diagonal": diagonal,
        "steps": int(fit.steps),
        "converged": bool(fit.converged),
        "parameters": "per bone: motor generator (e12, e13, e23, e1inf, e2inf, e3inf) and log-scale, applied "
                      "in the bone's frame after its rest transform",
        "bones": [
            {
                "name": name,
                "parameters": np.asarray(fit.params[i]).tolist(),
                "translation": np.asarray(translation[i]).tolist(),
                "rotation_xyzw": np.asarray(rotation[i]).tolist(),
                "scale": float(scale[i, 0]),
            }
            for i, name in enumerate(model.skeleton.names)
        ],
    }
    write_json(out, result)
    return {k: result[k] for k in ("max_error", "rms_error", "bounding_diagonal", "steps", "converged")}


def _read_array(name: str, path: Path) -> np.ndarray:
    """The array in the .npy file ``path`` (the option ``name`` gave it): a ValueError naming the option for a
    missing file or one that holds no plain array."""
    if not Path(path).is_file():
        raise FileNotFoundError(f"{name}: no such file {path}")
    try:
        return np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError) as error:
        raise ValueError(f"{name}: {path} is not a .npy file of a numeric array ({type(error).__name__})") from None


def skinning_figure(model: RiggedModel, path: Path, frames: int = 5) -> Path:
    """Save a figure of the model at ``frames`` times of its clip (or of generated keyframes),
    skinned by eq. (17), with the largest distance to matrix LBS in the title."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if model.clips:
        times = jnp.linspace(model.clips[0].start, model.clips[0].end, frames)
        cga_frames = jax.vmap(lambda t: _pose.skin_model(model, t, "cga"))(times)
        lbs_frames = jax.vmap(lambda t: _pose.skin_model(model, t, "lbs"))(times)
    else:
        keys = generated_keyframes(model)
        times = jnp.linspace(0.0, float(keys.times[-1]), frames)
        local = jax.vmap(lambda t: _rig.sample_keyframes(keys, t))(times)
        cga_frames = _pose.skin_pose(model, local, "cga")
        lbs_frames = _pose.skin_pose(model, local, "lbs")
    gap = float(jnp.max(jnp.abs(cga_frames - lbs_frames)))
    fig = plt.figure(figsize=(3.2 * frames, 3.4))
    F = np.asarray(model.mesh.F)
    lo, hi = np.asarray(jnp.min(cga_frames, axis=(0, 1))), np.asarray(jnp.max(cga_frames, axis=(0, 1)))
    for k in range(frames):
        ax = fig.add_subplot(1, frames, k + 1, projection="3d")
        X = np.asarray(cga_frames[k])
        ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=F, color="tab:orange", linewidth=0, alpha=0.9)
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_zlim(lo[2], hi[2])
        ax.set_box_aspect(hi - lo)
        ax.set_title(f"t = {float(times[k]):.2f} s", fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"{model.name}: multivector skinning, eq. (17); max |eq. 17 - LBS| = {gap:.1e}")
    return save_figure(fig, path, dpi=90, bbox_inches="tight")
