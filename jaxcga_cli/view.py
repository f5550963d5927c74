"""``jaxcga view``: one self-contained HTML page (three.js inside, no network at view time) that shows skinned glTF
models with their clips, mesh sequences (the .npy frames of ``skin``/``deform``/``arap``, the .vtu frames of
``fem``/``xfem``) and meshes side by side, to open in a browser (``deform.view``)."""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "write an interactive HTML viewer of glTF models with their clips, mesh sequences (.npy, .vtu frames) and "
    "meshes, side by side, to open in a browser"
)
EXAMPLE = "jaxcga view tests/data/CesiumMan.glb tests/data/RiggedSimple.glb --out view.html"
# A page embeds every frame (int16, base64): a browser tab holds a few times its size while decoding, and pages
# of a few hundred MB fail to open in some browsers.
MAX_MEGABYTES = 100.0
MAX_FPS = 1000.0


def add_arguments(parser) -> None:
    parser.add_argument(
        "inputs",
        nargs="+",
        metavar="INPUT",
        help="glTF (.glb/.gltf), .npy frames (t, n, 3) or one (n, 3) file per frame (with --mesh), a .vtu file or "
        "a folder of frame_XXXX.vtu (jaxcga fem/xfem runs); several are shown side by side",
    )
    parser.add_argument(
        "--mesh",
        help="the mesh of .npy frames (.obj, .ply, .stl, .off, glTF): its triangles, for the vertices the frames move",
    )
    parser.add_argument("--joint", help="colour the skin weights of this joint (name or index)")
    parser.add_argument("--clip", type=arguments.clip, default=None, help="clip to play first (name or index)")
    parser.add_argument(
        "--fps",
        type=float,
        default=30.0,
        help=f"frame rate of mesh sequences (default 30, at most {MAX_FPS:g}: a browser draws at most a few hundred "
        "frames per second)",
    )
    parser.add_argument("--title", help="the page's title (default: the inputs' names)")
    parser.add_argument("--out", type=Path, required=True, help="VIEW.html: the page to write")
    parser.add_argument("--force", action="store_true", help="replace an existing VIEW.html")
    parser.add_argument(
        "--max-megabytes",
        type=float,
        default=MAX_MEGABYTES,
        help=f"refuse to write a page larger than this (default {MAX_MEGABYTES:g} MB: larger pages load slowly or "
        "not at all in a browser; give fewer frames, or raise this)",
    )


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_distinct, check_input, check_output

    check_output(args.out, (".html", ".htm"), "out")
    if args.out.exists() and not args.force:
        raise ValueError(f"out: {args.out} exists; give --force to replace it")
    mesh = {"mesh": check_input(args.mesh, "mesh")} if args.mesh is not None else {}
    inputs = {f"INPUT {k + 1}": Path(p) for k, p in enumerate(args.inputs) if Path(p).is_file()}
    check_distinct({"out": args.out}, {**inputs, **mesh})


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from _jaxcga_shared.viewer import view
    from jaxcga_cli.report import status

    if not 0 < args.fps <= MAX_FPS:
        raise ValueError(
            f"fps: expected a frame rate in (0, {MAX_FPS:g}] (a browser draws at most a few hundred frames per "
            f"second), got {args.fps:g}"
        )
    if not args.max_megabytes > 0:
        raise ValueError(f"max_megabytes: expected a positive size, got {args.max_megabytes:g}")
    with status("view", f"reading {len(args.inputs)} input{'s' if len(args.inputs) > 1 else ''}"):
        try:
            page = view(*args.inputs, mesh=args.mesh, joint=args.joint, clip=args.clip, fps=args.fps, title=args.title)
        except ValueError as error:  # the library names its k-th argument inputs[k]; here it is INPUT k+1
            text = str(error)
            named = re.match(r"inputs\[(\d+)\]: ", text)
            if named is None:
                raise
            raise ValueError(f"INPUT {int(named[1]) + 1}: {text[named.end() :]}") from None
    megabytes = len(page.html.encode("utf-8")) / 2**20
    if megabytes > args.max_megabytes:
        raise ValueError(
            f"max_megabytes: the page would be {megabytes:.3g} MB, more than --max-megabytes {args.max_megabytes:g} "
            "(a browser loads such a page slowly or not at all); give fewer frames or inputs, or a larger "
            "--max-megabytes to write it anyway"
        )
    page.save(args.out, force=args.force)
    return page.title, {
        "meshes": len(page.meshes),
        "vertices": sum(m["vertexCount"] for m in page.meshes),
        "clips": len(page.clips),
        "megabytes": round(megabytes, 2),
        "out": str(args.out),
    }
