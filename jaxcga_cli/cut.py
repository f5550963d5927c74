"""``jaxcga cut``: a rigged model cut in two by a plane (Algorithm 1 of the cut/tear/drill paper); both halves
keep the input's skeleton and clips, so that they animate again."""

from __future__ import annotations

import argparse
import contextlib
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "cut a rigged model in two along a plane n . x = d (in its rest, or bind, pose) and write both halves as "
    "skinned glTF files that still animate"
)
EXAMPLE = "jaxcga cut --plane 1 0 0 0.3 --cap --out upper.glb lower.glb"
PREDICATES_HELP = (
    "the geometric tests that decide which side a point is on: ga (the paper's geometric-algebra form, Table 1; "
    "default) or euclidean (plain vector algebra)"
)
SIDE_WEIGHT_HELP = (
    "bone weights of the new vertices: 0 (default) interpolates the edge's end points (sec. 4.3); up "
    "to 1 favours the vertices on the new vertex's own side"
)


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--plane",
        type=float,
        nargs=4,
        required=True,
        metavar=("NX", "NY", "NZ", "D"),
        help="the plane n . x = d in the bind pose (n is normalized); the command prints the model's bounding box",
    )
    parser.add_argument("--cap", action="store_true", help="close both halves (the model must be closed)")
    parser.add_argument("--predicates", choices=arguments.PREDICATES, default="ga", help=PREDICATES_HELP)
    parser.add_argument("--side-weight", type=float, default=0.0, help=SIDE_WEIGHT_HELP)
    parser.add_argument(
        "--out",
        type=Path,
        nargs=2,
        required=True,
        metavar=("POS.glb", "NEG.glb"),
        help="the positive (n . x > d) and negative halves (.glb or .gltf)",
    )


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(
        args,
        ("model",),
        {"out (positive half)": args.out[0], "out (negative half)": args.out[1]},
        GLTF_OUTPUTS,
        gltf=True,
    )


def check_side_weight(side_weight: float) -> None:
    """--side-weight in [0, 1] (``cutting.cut``'s own check, made before the model is loaded)."""
    if not 0.0 <= side_weight <= 1.0:
        raise ValueError(f"side_weight: expected a number in [0, 1], got {side_weight}")


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_model

    check_side_weight(args.side_weight)
    model = load_model(args.model, weld=args.weld)
    return model.name, cut_command(
        model, args.plane, *args.out, cap=args.cap, predicates=args.predicates, side_weight=args.side_weight
    )


@contextlib.contextmanager
def coordinates(command: str, model, names: tuple[str, ...]):
    """Print the model's bounding box and up axis (the command takes coordinates), and add them to an error about
    the coordinates, the arguments ``names`` (a plane or a tool that misses the mesh, ...)."""
    from jaxcga_cli.models import bounds
    from jaxcga_cli.report import error_line, say

    where = bounds(model.mesh.V)
    say(command, where)
    try:
        yield
    except ValueError as error:
        line = error_line(error)
        if line.split(":")[0].startswith(names):
            raise ValueError(f"{line} ({where})") from None
        raise


def cut_command(
    model,
    plane,
    out_positive: Path,
    out_negative: Path,
    cap: bool = False,
    predicates: str = "ga",
    side_weight: float = 0.0,
) -> dict:
    """Cut ``model`` by ``plane`` (nx, ny, nz, d) in its bind pose; write the positive half to
    ``out_positive`` and the negative half to ``out_negative`` (.glb or .gltf, two different files), both
    before either replaces an existing file."""
    import numpy as np

    import cutting
    import deform

    with coordinates("cut", model, ("plane",)):
        plane = np.asarray(plane, np.float64)
        positive, negative = cutting.cut(
            model.mesh, cutting.Plane(plane[:3], plane[3]), cap=cap, predicates=predicates, side_weight=side_weight
        )
    deform.save_models(
        {
            out_positive: deform.RiggedModel(positive, model.skeleton, model.clips, f"{model.name}-positive"),
            out_negative: deform.RiggedModel(negative, model.skeleton, model.clips, f"{model.name}-negative"),
        }
    )
    return {
        "positive_faces": int(positive.F.shape[0]),
        "negative_faces": int(negative.F.shape[0]),
        "new_vertices": positive.num_vertices + negative.num_vertices - model.mesh.num_vertices,
        "out": f"{out_positive} {out_negative}",
    }
