"""``jaxcga fit``: the pose (bone motors and dilations) that best matches target vertex positions."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "find the pose of a rigged model (a motor, i.e. a rotation and translation, and a scale per bone) whose "
    "skinned vertices best match target positions, and write it as JSON"
)
EXAMPLE = "jaxcga fit tests/data/Arm5.glb --target posed.npy --max-steps 100 --out pose.json"


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--target",
        type=Path,
        required=True,
        help="TARGET.npy: (n, 3) world-space positions (for example from jaxcga skin)",
    )
    parser.add_argument("--vertices", type=Path, default=None, help="IDX.npy: (t,) vertex indices of (t, 3) targets")
    parser.add_argument("--method", choices=arguments.METHODS, default="cga", help=arguments.METHODS_HELP)
    parser.add_argument("--regularization", type=float, default=0.0, help="weight of |params|^2 toward the rest pose")
    parser.add_argument("--max-steps", type=int, default=200, help="solver step limit (default 200)")
    parser.add_argument("--no-scale", action="store_true", help="fit motors only, no dilations")
    parser.add_argument("--out", type=Path, required=True, help="POSE.json")


def check_paths(args) -> None:
    from jaxcga_cli.output import check_files

    check_files(args, ("model", "target", "vertices"), {"out": args.out}, (".json",))


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_model

    model = load_model(args.model, weld=args.weld)
    return model.name, fit_command(
        model, args.target, args.out, args.method, args.vertices, args.regularization, args.max_steps, not args.no_scale
    )


def fit_command(
    model,
    target: Path,
    out: Path,
    method: str = "cga",
    vertices: Path | None = None,
    regularization: float = 0.0,
    max_steps: int = 200,
    fit_scale: bool = True,
) -> dict:
    """Fit bone motors (and dilations) to target positions (.npy (n, 3), or (t, 3) with a vertex index
    file) and write the pose as JSON."""
    import jax.numpy as jnp
    import numpy as np

    import deform
    from _jaxcga_shared.mesh import bounding_diagonal
    from _jaxcga_shared.output import write_json
    from jaxcga_cli.report import StepProgress

    targets = _read_array("target", target)
    index = None if vertices is None else _read_array("vertices", vertices)
    if index is None and targets.shape != (model.mesh.num_vertices, 3):
        raise ValueError(
            f"target: expected shape ({model.mesh.num_vertices}, 3) (every vertex), got "
            f"{targets.shape}; give --vertices for a subset"
        )
    dtype = model.mesh.V.dtype
    desc = f"fit {model.skeleton.num_bones} bones to {len(targets)} targets"
    with StepProgress("fit", max_steps, "step", desc) as progress:
        # loss: the sum of squared residuals, distances over the rest pose's diagonal
        fit = deform.fit_pose(
            model,
            jnp.asarray(targets, dtype),
            None if index is None else jnp.asarray(index),
            method=method,
            regularization=regularization,
            max_steps=max_steps,
            fit_scale=fit_scale and method != "dqs",
            progress=lambda loss: progress.step(loss=f"{float(loss):.3g}"),
        )
        translation, rotation, scale = deform.versor_to_trs(fit.local)
    diagonal = bounding_diagonal(deform.rest_pose(model, "lbs"))
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


def _read_array(name: str, path: Path):
    """The array in the .npy file ``path`` (the option ``name`` gave it): a ValueError naming the option for a
    missing file or one that holds no plain array."""
    from _jaxcga_shared.meshfile import read_array_file

    array = read_array_file(path, name)
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{name}: {path} holds {array.dtype} values, expected numbers")
    return array
