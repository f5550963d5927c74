"""``jaxcga tear``: a rigged model torn by a moving scalpel (Algorithm 2 of the cut/tear/drill paper)."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments
from jaxcga_cli.cut import PREDICATES_HELP, SIDE_WEIGHT_HELP, check_side_weight

HELP = (
    "tear a rigged model along the path of a moving scalpel (a line segment given at two or more times, in the "
    "bind pose) and write the torn model as a skinned glTF"
)
EXAMPLE = (
    "jaxcga tear --scalpel 0.2 0 0.1 0.2 0 0 --scalpel 0.3 0 0.1 0.3 0 0 --scalpel 0.35 0.01 0.1 0.35 0.01 0 "
    "--opening 0.005 --out torn.glb"
)
SCALPEL = ("HX", "HY", "HZ", "TX", "TY", "TZ")
PATH_HELP = (
    'a JSON file of the scalpel\'s samples in order: a list of {"handle": [x, y, z], "tip": [x, y, z]} or of '
    "[[hx, hy, hz], [tx, ty, tz]] entries (two or more in all, with any --scalpel samples after them)"
)


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument(
        "--scalpel",
        type=float,
        nargs=6,
        action="append",
        metavar=SCALPEL,
        help="the scalpel segment at one time, in the bind pose: its handle end (outside the skin) and its tip; "
        "repeat it for each time t_0, t_1, ... (two or more samples in all); the tear follows the surface the "
        "blade sweeps between them. The command prints the model's bounding box",
    )
    parser.add_argument("--scalpel-path", type=Path, metavar="FILE.json", help=PATH_HELP)
    parser.add_argument(
        "--opening",
        type=float,
        default=0.0,
        help="distance between the two sides of the tear (default 0: a closed slit; at most the model's bounding "
        "box diagonal)",
    )
    parser.add_argument("--predicates", choices=arguments.PREDICATES, default="ga", help=PREDICATES_HELP)
    parser.add_argument("--side-weight", type=float, default=0.0, help=SIDE_WEIGHT_HELP)
    parser.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(args, ("model", "scalpel_path"), {"out": args.out}, GLTF_OUTPUTS, gltf=True)


def read_scalpel_path(path: Path) -> list:
    """The samples [[handle, tip], ...] of a --scalpel-path file, with errors that name the file and the entry."""
    import json

    import numpy as np

    try:
        entries = json.loads(Path(path).read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise ValueError(f"--scalpel-path: cannot read {path} as JSON ({error})") from None
    if not isinstance(entries, list):
        raise ValueError(f"--scalpel-path: expected a list of samples in {path}, got a {type(entries).__name__}")
    samples = []
    for k, entry in enumerate(entries):
        ends = [entry.get("handle"), entry.get("tip")] if isinstance(entry, dict) else entry
        try:
            ends = np.asarray(ends, np.float64)
        except (TypeError, ValueError):
            ends = None
        if ends is None or ends.shape != (2, 3) or not np.all(np.isfinite(ends)):
            raise ValueError(
                f"--scalpel-path: entry {k} of {path} is not a sample: expected "
                '{"handle": [x, y, z], "tip": [x, y, z]} or [[hx, hy, hz], [tx, ty, tz]] with finite numbers, '
                f"got {json.dumps(entry)[:80]}"
            )
        samples.append(ends.tolist())
    return samples


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_model

    samples = read_scalpel_path(args.scalpel_path) if args.scalpel_path is not None else []
    samples += [[s[:3], s[3:]] for s in args.scalpel or []]
    if len(samples) < 2:
        raise ValueError(
            f"scalpel: expected two or more samples (--scalpel repeated, or --scalpel-path), got {len(samples)}"
        )
    check_side_weight(args.side_weight)
    if not args.opening >= 0:
        raise ValueError(f"opening: expected a distance >= 0, got {args.opening:g}")
    # a tear walks across faces: split vertices along UV seams are always welded for it
    model = load_model(args.model, weld=True)
    return model.name, tear_command(
        model,
        samples,
        args.out,
        opening=args.opening,
        predicates=args.predicates,
        side_weight=args.side_weight,
    )


def tear_command(
    model, scalpels, out: Path, opening: float = 0.0, predicates: str = "ga", side_weight: float = 0.0
) -> dict:
    """Tear ``model`` in its bind pose with a scalpel at the samples ``scalpels`` ((k+1, 2, 3)); write
    the torn model to ``out`` (.glb or .gltf)."""
    import numpy as np

    import cutting
    import deform
    from _jaxcga_shared.mesh import bounding_diagonal
    from jaxcga_cli.cut import coordinates

    scalpels = np.asarray(scalpels, np.float64)
    diagonal = bounding_diagonal(model.mesh.V)
    if opening > diagonal:
        raise ValueError(
            f"opening: {opening:g} is wider than the model itself (its bounding box diagonal is {diagonal:.4g}, "
            "in the file's units); give the distance between the tear's two sides in those units"
        )
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
        "tear_points": len(topology.t) + len(topology.inner),
        "stretches": len(topology.stretches),
        "faces": int(torn.F.shape[0]),
        "new_vertices": torn.num_vertices - model.mesh.num_vertices,
        "out": str(out),
    }
