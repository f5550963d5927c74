"""Arguments several commands share."""

from __future__ import annotations

FORCE_HELP = (
    "replace the run in a non-empty OUT: its frame_XXXX.png/.vtu and summary.json are replaced when this "
    "run ends; other files stay"
)
METHODS_HELP = (
    "skinning method: lbs (linear blend skinning, matrices), dqs (dual quaternions), cga (the paper's "
    "multivector skinning, eq. 17; default) or cga_motor_blend (eq. 17 blending motors only)"
)


def model_argument(parser) -> None:
    parser.add_argument(
        "model",
        nargs="?",
        default=None,
        help="glTF (.gltf/.glb), or FBX/COLLADA through assimp; default: the built-in arm",
    )
    weld_argument(parser)


def weld_argument(parser) -> None:
    parser.add_argument("--weld", action="store_true", help="weld split vertices of the loaded model")


def unhandled_argument(parser, scope: str) -> None:
    """--unhandled: what a connected part of the mesh without a handle does (``deform.mesh_parts``)."""
    parser.add_argument(
        "--unhandled",
        choices=UNHANDLED,
        default="follow",
        help=f"{scope}: a connected part of the mesh that holds no handle (eyes, teeth, clothing, an inner mesh) "
        "follows the part it touches or is nearest to (follow, default), or is refused (error)",
    )


def ftetwild_arguments(parser, scope: str) -> None:
    """--edge-length and --epsilon of fTetWild (``xfem.tetrahedralize_surface``'s defaults) for fem and xfem."""
    parser.add_argument(
        "--edge-length",
        type=float,
        default=0.05,
        help=f"{scope}: the target tet edge length over the bounding box diagonal (default 0.05)",
    )
    parser.add_argument(
        "--epsilon",
        type=float,
        default=1e-3,
        help=f"{scope}: how far the tets' boundary may stray from the surface, over the bounding box "
        "diagonal (default 1e-3)",
    )


def mesh_argument(parser, default: str) -> None:
    parser.add_argument(
        "mesh",
        nargs="?",
        default=None,
        help=f"a mesh file (glTF: its bind-pose mesh; .obj, .ply, .stl, ...); default: {default}",
    )


def interpolation_argument(parser) -> None:
    parser.add_argument(
        "--interpolation",
        choices=("gltf", "log"),
        default="gltf",
        help="key interpolation: gltf, the file's (the glTF specification's lerp / slerp / "
        "step / cubic spline; default), or log, the paper's logarithmic blending of "
        "key versors (sec. 4.1)",
    )


def motion_arguments(parser, scope: str, fraction_scope: str) -> None:
    """--bend, --twist, --translate of the built-in motion of the long axis's far end, and --handle-fraction (the
    vertices near the ends that hold it), for ``deform`` and ``arap``; the scopes say where they apply."""
    parser.add_argument("--bend", type=float, default=60.0, help=f"{scope}: degrees of bend (default 60)")
    parser.add_argument(
        "--twist", type=float, default=0.0, help=f"{scope}: degrees of twist about the long axis (default 0)"
    )
    parser.add_argument(
        "--translate",
        type=float,
        nargs=3,
        default=(0.0, 0.0, 0.0),
        metavar=("X", "Y", "Z"),
        help=f"{scope}: translation of the far end (default none)",
    )
    parser.add_argument(
        "--handle-fraction",
        type=float,
        default=0.05,
        help=f"{fraction_scope}: the end handles hold the vertices within this fraction of the long axis's ends "
        "(default 0.05)",
    )


def clip(value: str) -> int | str:
    """A clip index (an integer) or name."""
    return int(value) if value.lstrip("-").isdigit() else value


def clip_argument(parser) -> None:
    parser.add_argument("--clip", type=clip, default=0, help="clip name or index (default 0)")


# The packages' enumerations, listed here so that --help runs without importing JAX (tests/cli checks that they
# equal the packages' own).
BASES = ("linear", "lagrange", "bezier", "bspline")  # deform.BASES
LAPLACIANS = ("cotangent", "mean_value")  # deform.LAPLACIANS
ARAP_ENERGIES = ("spokes_and_rims", "spokes")  # deform.ARAP_ENERGIES
UNHANDLED = ("follow", "error")  # deform.UNHANDLED
PREDICATES = ("euclidean", "ga")  # cutting.PREDICATES
XFEM_SCENES = ("sticks", "thin", "cheese", "accordion", "octopus")  # xfem.SCENES
XFEM_SIZES = ("paper", "small")  # xfem.SIZES
METHODS = ("lbs", "dqs", "cga", "cga_motor_blend")  # deform.METHODS


def check_clip(model, clip: int | str = 0, time: float | None = None, interpolation: str = "gltf"):
    """The clip ``clip`` of ``model`` (None for a model without clips), checked after loading and before anything
    compiles: an unknown clip is a ``ValueError`` naming --clip; options that do nothing are told (a warning, one
    line): --clip, --time and --interpolation on a model without clips, and a ``time`` outside the clip, which
    glTF holds at the clip's nearer end."""
    import warnings

    if not model.clips:
        ignored = [f"--clip {clip}"] if clip not in (0, -1) else []
        ignored += [f"--time {time:g}"] if time not in (None, 0.0) else []
        ignored += [f"--interpolation {interpolation}"] if interpolation != "gltf" else []
        if ignored:
            warnings.warn(f"{model.name} has no clip: {', '.join(ignored)} ignored", stacklevel=2)
        return None
    source = model.clip(clip)
    start, end = float(source.start), float(source.end)
    if time is not None and not start <= time <= end:
        held = start if time < start else end
        warnings.warn(
            f"--time {time:g} is outside clip {source.name!r} ({start:g} to {end:g} s); glTF holds a clip at its "
            f"ends: posed at {held:g} s",
            stacklevel=2,
        )
    return source
