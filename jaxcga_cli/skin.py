"""``jaxcga skin``: the skinned vertex positions of a rigged model at one time of its clip."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments

HELP = "pose a rigged model at one time of its animation and write the posed vertices or mesh"
EXAMPLE = "jaxcga skin tests/data/CesiumMan.glb --time 0.5 --out posed.glb"


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--time",
        type=float,
        default=None,
        help="clip time in seconds (default: the clip's start); outside the clip, glTF holds its nearer end (told)",
    )
    parser.add_argument("--method", choices=arguments.METHODS, default="cga", help=arguments.METHODS_HELP)
    arguments.clip_argument(parser)
    arguments.interpolation_argument(parser)
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="OUT.npy: float64 (n, 3) world-space positions; OUT.glb/.gltf/.obj/.ply/.stl: the posed mesh",
    )


def check_paths(args) -> None:
    from jaxcga_cli.output import POSITION_OUTPUTS, check_files

    check_files(args, ("model",), {"out": args.out}, POSITION_OUTPUTS)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_model

    model = load_model(args.model, weld=args.weld)
    source = arguments.check_clip(model, args.clip, args.time, args.interpolation)
    if args.time is None:
        args.time = float(source.start) if source is not None else 0.0
    return model.name, skin_command(model, args.time, args.method, args.clip, args.out, args.interpolation)


def skin_command(model, time: float, method: str, clip: int | str, out: Path, interpolation: str = "gltf") -> dict:
    """Skinned positions of every skinned primitive (file order) at ``time``, in glTF world space,
    written to ``out`` (.npy: float64 (n, 3); .glb etc.: the posed mesh); keys interpolated by
    ``interpolation`` (``deform.skin_model``)."""
    import numpy as np

    import deform
    from jaxcga_cli import cache
    from jaxcga_cli.output import write_result
    from jaxcga_cli.report import status

    with status("skin", f"skinning {model.mesh.num_vertices} vertices (compiling)"):
        # exported with its checks as values (cache.ExportedCalls): a second run reads the program back
        positions = cache.call("skin_model", deform.skin_model, model, np.float64(time), method, clip, interpolation)
        positions = np.asarray(positions)  # checked on the host: no program compiled for the check
        if not np.all(np.isfinite(positions)):
            raise ValueError("skinning produced non-finite positions")
    write_result(out, positions, model.mesh.F)
    return {
        "vertices": int(positions.shape[0]),
        "method": method,
        "interpolation": interpolation,
        "time": time,
        "out": str(out),
    }
