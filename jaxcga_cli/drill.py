"""``jaxcga drill``: a hole drilled into a rigged model (Algorithm 3 of the cut/tear/drill paper)."""

from __future__ import annotations

from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "drill a round hole of a given radius into a rigged model along the axis from BASE to TIP (in the bind "
    "pose) and write the drilled model as a skinned glTF"
)
EXAMPLE = "jaxcga drill --tip 0.4 0 0 --base 0.4 0 0.1 --radius 0.015 --out drilled.glb"


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--tip",
        type=float,
        nargs=3,
        required=True,
        metavar=("X", "Y", "Z"),
        help="the drill's tip in the bind pose: it drills the sheets its axis reaches; the command "
        "prints the model's bounding box",
    )
    parser.add_argument(
        "--base",
        type=float,
        nargs=3,
        required=True,
        metavar=("X", "Y", "Z"),
        help="the drill's base (the other end of its axis)",
    )
    parser.add_argument("--radius", type=float, required=True, help="the drill's radius")
    parser.add_argument(
        "--min-points",
        type=int,
        default=6,
        help="fewest points around a hole before faces are split and drilled again (default 6)",
    )
    parser.add_argument("--max-refinements", type=int, default=4, help="at most this many splits (default 4)")
    parser.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(args, ("model",), {"out": args.out}, GLTF_OUTPUTS, gltf=True)


def run(args) -> dict:
    from jaxcga_cli.models import load_model

    # a drill walks across faces: split vertices along UV seams are always welded for it
    model = load_model(args.model, weld=True)
    return model.name, drill_command(
        model,
        args.tip,
        args.base,
        args.radius,
        args.out,
        min_points=args.min_points,
        max_refinements=args.max_refinements,
    )


def drill_command(model, tip, base, radius: float, out: Path, min_points: int = 6, max_refinements: int = 4) -> dict:
    """Drill ``model`` in its bind pose from ``base`` to ``tip`` with ``radius``; write the drilled
    model to ``out`` (.glb or .gltf)."""
    import cutting
    import deform
    from jaxcga_cli.cut import coordinates

    with coordinates("drill", model, ("drill",)):
        drilled, topology = cutting.drill(
            model.mesh,
            cutting.Drill(tip, base, radius),
            min_points=min_points,
            max_refinements=max_refinements,
            return_topology=True,
        )
    deform.save_model(deform.RiggedModel(drilled, model.skeleton, model.clips, f"{model.name}-drilled"), out)
    return {
        "holes": topology.holes,
        "hole_points": len(topology.points),
        "refinements": topology.refinements,
        "faces": int(drilled.F.shape[0]),
        "out": str(out),
    }
