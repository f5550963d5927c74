"""``jaxcga drill``: a hole drilled into a rigged model (Algorithm 3 of the cut/tear/drill paper)."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "drill a round hole of a given radius into a rigged model along the axis from BASE to TIP (in the bind "
    "pose) through every layer in its way, and write the drilled model as a skinned glTF"
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
        help="the drill's tip in the bind pose: it drills every sheet that meets the cylinder between base "
        "and tip (clothing, skin, inner meshes, separate parts); the command prints the model's bounding box",
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
    parser.add_argument(
        "--max-refinements",
        type=int,
        default=None,
        help="at most this many splits (default: as many as the largest face the drill meets needs)",
    )
    parser.add_argument(
        "--rim-tolerance",
        type=float,
        default=5e-4,
        help="split the faces along the hole's rim until it keeps within this fraction of the bounding-box "
        "diagonal of the cylinder (default 5e-4)",
    )
    parser.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(args, ("model",), {"out": args.out}, GLTF_OUTPUTS, gltf=True)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
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
        rim_tolerance=args.rim_tolerance,
    )


def drill_command(
    model,
    tip,
    base,
    radius: float,
    out: Path,
    min_points: int = 6,
    max_refinements: int | None = None,
    rim_tolerance: float = 5e-4,
) -> dict:
    """Drill ``model`` in its bind pose from ``base`` to ``tip`` with ``radius``; write the drilled
    model to ``out`` (.glb or .gltf). The summary counts the holes, the connected parts of the mesh they
    are in (the shells crossed: a limb drilled through has two holes in one shell, one more per layer
    inside) and the parts removed whole, and gives the rim's largest distance from the cylinder."""
    import numpy as np

    import cutting
    import deform
    from _jaxcga_shared.mesh import bounding_diagonal
    from jaxcga_cli.cut import coordinates
    from jaxcga_cli.report import say

    with coordinates("drill", model, ("drill",)):
        drilled, topology = cutting.drill(
            model.mesh,
            cutting.Drill(tip, base, radius),
            min_points=min_points,
            max_refinements=max_refinements,
            rim_tolerance=rim_tolerance,
            return_topology=True,
        )
    deform.save_model(deform.RiggedModel(drilled, model.skeleton, model.clips, f"{model.name}-drilled"), out)
    shells = _shells_crossed(np.asarray(model.mesh.F), topology)
    rim = topology.rim_distance / bounding_diagonal(np.asarray(model.mesh.V))
    say(
        "drill",
        f"{topology.holes} hole(s) in {shells} shell(s) of the mesh, {topology.removed} part(s) inside the drill "
        f"removed; the rim lies within {rim:.2g} x the bounding-box diagonal of the cylinder",
    )
    return {
        "holes": topology.holes,
        "shells": shells,
        "parts_removed": topology.removed,
        "hole_points": len(topology.points),
        "rim_distance": rim,
        "refinements": topology.refinements,
        "faces": int(drilled.F.shape[0]),
        "out": str(out),
    }


def _shells_crossed(F, topology) -> int:
    """The connected parts of the input mesh (faces F) that hold a new point of the hole."""
    import numpy as np
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    n = len(topology.vertices) - len(topology.parents)
    graph = sp.coo_matrix((np.ones(F.size), (F.ravel(), np.roll(F, 1, axis=1).ravel())), shape=(n, n))
    _, part = connected_components(graph, directed=False)
    # a split point lies in the part of its edge's first vertex (parents precede the points they split)
    origin = np.arange(len(topology.vertices))
    for k, (i, _) in enumerate(topology.parents.tolist()):
        origin[n + k] = origin[i]
    return len(np.unique(part[origin[topology.crossing[:, 0]]]))
