"""``jaxcga tear``: a rigged model torn by a moving scalpel (Algorithm 2 of the cut/tear/drill paper)."""

from __future__ import annotations

from pathlib import Path

from jaxcga_cli import arguments
from jaxcga_cli.cut import PREDICATES_HELP, SIDE_WEIGHT_HELP

HELP = (
    "tear a rigged model along the path of a moving scalpel (a line segment given at two or more times, in the "
    "bind pose) and write the torn model as a skinned glTF"
)
EXAMPLE = "jaxcga tear --scalpel0 0.2 0 0.1 0.2 0 0 --scalpel1 0.3 0 0.1 0.3 0 0 --opening 0.005 --out torn.glb"
SCALPEL = ("X0", "Y0", "Z0", "X1", "Y1", "Z1")


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--scalpel0",
        type=float,
        nargs=6,
        required=True,
        metavar=SCALPEL,
        help="the scalpel segment at t_0 in the bind pose, handle end (outside the skin) first; the "
        "command prints the model's bounding box",
    )
    parser.add_argument(
        "--scalpel1", type=float, nargs=6, required=True, metavar=SCALPEL, help="the scalpel segment at t_1"
    )
    parser.add_argument(
        "--scalpel-next",
        type=float,
        nargs=6,
        action="append",
        metavar=SCALPEL,
        help="further samples t_2, t_3, ... (repeat): one tear along the whole path",
    )
    parser.add_argument(
        "--opening",
        type=float,
        default=0.0,
        help="distance between the two sides of the tear (default 0: a closed slit)",
    )
    parser.add_argument("--predicates", choices=arguments.PREDICATES, default="euclidean", help=PREDICATES_HELP)
    parser.add_argument("--side-weight", type=float, default=0.0, help=SIDE_WEIGHT_HELP)
    parser.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(args, ("model",), {"out": args.out}, GLTF_OUTPUTS, gltf=True)


def run(args) -> dict:
    from jaxcga_cli.models import load_model

    # a tear walks across faces: split vertices along UV seams are always welded for it
    model = load_model(args.model, weld=True)
    scalpels = [args.scalpel0, args.scalpel1] + (args.scalpel_next or [])
    return model.name, tear_command(
        model,
        [[s[:3], s[3:]] for s in scalpels],
        args.out,
        opening=args.opening,
        predicates=args.predicates,
        side_weight=args.side_weight,
    )


def tear_command(
    model, scalpels, out: Path, opening: float = 0.0, predicates: str = "euclidean", side_weight: float = 0.0
) -> dict:
    """Tear ``model`` in its bind pose with a scalpel at the samples ``scalpels`` ((k+1, 2, 3)); write
    the torn model to ``out`` (.glb or .gltf)."""
    import numpy as np

    import cutting
    import deform
    from jaxcga_cli.cut import coordinates

    scalpels = np.asarray(scalpels, np.float64)
    with coordinates("tear", model, ("scalpel",)):
        torn, topology = cutting.tear(
            model.mesh,
            cutting.Scalpel(scalpels[:, 0], scalpels[:, 1]),
            opening=opening,
            predicates=predicates,
            side_weight=side_weight,
            return_topology=True,
        )
    deform.save_model(deform.RiggedModel(torn, model.skeleton, model.clips, f"{model.name}-torn"), out)
    return {
        "tear_points": len(topology.t),
        "faces": int(torn.F.shape[0]),
        "new_vertices": torn.num_vertices - model.mesh.num_vertices,
        "out": str(out),
    }
