"""``jaxcga deform {spline,handles,ffd,cage}``: a mesh bent and twisted by motors, by one of the deformation
paper's methods.

Each loads a triangle mesh (any trimesh format; a glTF's bind-pose mesh, welded; default: the built-in arm's rest
mesh), binds it to key motors by one of the methods, moves the keys by one motion along the mesh's long axis
(``jaxcga_cli.models``), and writes the deformed mesh (.glb, .obj, .ply, .stl), its positions (.npy, float64
(n, 3)) or a figure of the rest and deformed mesh (.png). Spline keys sit at s = j / (k - 1); harmonic handles are
the mesh's two ends (the low end fixed, the high end at s = 1) unless a handles file is given; lattice points and
cage vertices sit at their own s; ``--positional`` moves FFD control points or cage vertices by the same motors
instead (classic FFD, positional cage) for comparison.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "bend and twist a mesh smoothly with motors (rigid motions: a rotation and a translation) by one of the "
    "deformation paper's methods: a spline of key motors, handles, a lattice (FFD) or a cage"
)
EXAMPLE = "jaxcga deform ffd tests/data/Arm5.glb --bend 60 --twist 30 --out bent.png"
DEFORMATIONS = ("spline", "handles", "ffd", "cage")
HANDLES_HELP = (
    'HANDLES.json {"handles": [[i, ...], ...], "motors": [{"center": [x, y, z], "axis": [x, y, z], '
    '"angle_deg": a, "translation": [x, y, z]}, ...]}: groups of vertex indices, one rigid motion per '
    "group (every motor key optional; jaxcga arap reads the same file)"
)


def add_arguments(parser) -> None:
    parser.add_argument(
        "method",
        choices=DEFORMATIONS,
        help="spline: key motors along a spline, blended along the mesh (eq. 1-2); handles: groups "
        "of vertices moved rigidly, the rest follows smoothly (harmonic weights, sec. IV); ffd: "
        "free-form deformation, the mesh moves with a lattice of control motors around it "
        "(eq. 7-8); cage: the mesh moves with a coarse closed cage around it (harmonic "
        "coordinates, sec. VI)",
    )
    arguments.mesh_argument(parser, "the built-in arm")
    parser.add_argument(
        "--basis",
        choices=arguments.BASES,
        default="bspline",
        help="spline: weights of the key motors (default bspline)",
    )
    parser.add_argument(
        "--keys",
        type=int,
        default=None,
        help="spline: number of key motors for bezier / bspline (default 4 / 5; linear has 2, lagrange 3)",
    )
    parser.add_argument(
        "--laplacian",
        choices=arguments.LAPLACIANS,
        default="cotangent",
        help="spline, handles: the Laplacian of the harmonic fields (default cotangent)",
    )
    arguments.motion_arguments(parser, "the built-in motion", "spline, handles")
    parser.add_argument("--handles", type=Path, default=None, help=f"handles: {HANDLES_HELP}, instead of the two ends")
    arguments.unhandled_argument(parser, "spline, handles: parts without a handle")
    parser.add_argument(
        "--lattice",
        type=int,
        nargs=3,
        default=(4, 4, 4),
        metavar=("L", "M", "N"),
        help="ffd: control points per axis (default 4 4 4)",
    )
    parser.add_argument(
        "--cage",
        type=Path,
        default=None,
        help="cage: a closed cage mesh around the model (default: a tube cage of 7 rings of 8 "
        "along the long axis, deform.tube_cage)",
    )
    parser.add_argument(
        "--positional",
        action="store_true",
        help="ffd, cage: move control points / cage vertices instead (classic FFD, positional cage)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="OUT.glb/.obj/.ply/.stl: the deformed mesh; OUT.npy: float64 (n, 3); OUT.png: a figure",
    )


def check_paths(args) -> None:
    from jaxcga_cli.output import DEFORM_OUTPUTS, check_files

    check_files(args, ("mesh", "handles", "cage"), {"out": args.out}, DEFORM_OUTPUTS)


def check_cage(path: Path):
    """(V, F) of the cage file ``path``, a closed, consistently oriented surface (``deform.cage_precompute``'s
    requirement, checked here in the file's terms before the model is loaded)."""
    import trimesh

    from jaxcga_cli.fem import open_edges
    from jaxcga_cli.models import load_mesh

    V, F = load_mesh(path, "cage")
    border = open_edges(F)
    if border:
        raise ValueError(
            f"cage: {path} is an open surface ({border} edges lie on its border, each in one triangle only); a cage "
            "is a closed surface around the model"
        )
    if not trimesh.Trimesh(V, F, process=False).is_winding_consistent:
        raise ValueError(
            f"cage: {path} is closed but its triangles are not consistently oriented (neighbours list a shared "
            "edge in the same direction); fix their winding, e.g. with trimesh's fix_winding"
        )
    return V, F


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_mesh

    if args.method == "cage" and args.cage is not None:
        check_cage(args.cage)
    V, F = load_mesh(args.mesh)
    return f"{args.method} {args.mesh or 'built-in arm'}", deform_command(
        args.method,
        V,
        F,
        args.out,
        bend=args.bend,
        twist=args.twist,
        translate=args.translate,
        basis=args.basis,
        keys=args.keys,
        laplacian=args.laplacian,
        handle_fraction=args.handle_fraction,
        handles=args.handles,
        lattice=args.lattice,
        cage=args.cage,
        positional=args.positional,
        unhandled=args.unhandled,
    )


def _ffd_setup(V, lattice: tuple[int, int, int]):
    """The FFD binding of V to its bounding lattice (2% padding) and the lattice's points: one exported program for
    a second run to read back (each program read back is lowered again)."""
    import deform

    grid = deform.bounding_lattice(V, lattice, padding=0.02)
    return deform.ffd_precompute(V, grid), deform.lattice_points(grid)


def deform_command(
    method: str,
    V,
    F,
    out: Path,
    *,
    bend: float = 60.0,
    twist: float = 0.0,
    translate=(0.0, 0.0, 0.0),
    basis: str = "bspline",
    keys: int | None = None,
    laplacian: str = "cotangent",
    handle_fraction: float = 0.05,
    handles: Path | None = None,
    lattice=(4, 4, 4),
    cage: Path | None = None,
    positional: bool = False,
    unhandled: str = "follow",
) -> dict:
    """Bind (V, F) by ``method`` (one of ``DEFORMATIONS``), move the keys, write ``out``; returns a
    summary (vertices, keys, precompute and per-frame milliseconds, volume and edge-length change; for spline
    and handles the mesh's connected parts and how many follow others, ``unhandled`` being
    ``deform.mesh_parts``'s "follow" or "error")."""
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    import deform
    import jaxcga as cga
    from jaxcga_cli import cache
    from jaxcga_cli.models import Motion, end_handles, read_handles
    from jaxcga_cli.output import write_result
    from jaxcga_cli.report import status

    if method not in DEFORMATIONS:
        raise ValueError(f"method: expected one of {DEFORMATIONS}, got {method!r}")
    if unhandled not in deform.UNHANDLED:
        raise ValueError(f"unhandled: expected one of {deform.UNHANDLED}, got {unhandled!r}")
    if positional and method not in ("ffd", "cage"):
        raise ValueError("positional: only the ffd and cage deformations have a positional form")
    if keys is not None and keys > len(V):
        raise ValueError(f"keys: expected at most one key motor per vertex ({len(V)}), got {keys}")
    motion = Motion(V, bend, twist, translate)
    # the handles, read and checked before the work starts
    if method == "handles" and handles is not None:
        parts, key_motors, _ = read_handles(handles, V)
    elif method in ("spline", "handles"):
        parts = list(end_handles(motion, V, handle_fraction))
        key_motors = motion.motors(np.array([0.0, 1.0]))
    start = time.perf_counter()
    with status("deform", f"binding {len(V)} vertices ({method})"):
        if method == "spline":
            if keys is None and basis == "bspline":
                keys = 5
            field = deform.spline_precompute(
                V, F, *parts, basis=basis, num_keys=keys, laplacian=laplacian, unhandled=unhandled
            )
            key_motors = motion.motors(np.linspace(0.0, 1.0, field.num_keys))
        elif method == "handles":
            field = deform.handles_precompute(V, F, parts, laplacian=laplacian, unhandled=unhandled)
        elif method == "ffd":
            field, points = cache.call("ffd_setup", _ffd_setup, V, tuple(lattice))
            key_motors = motion.motors(motion.fraction(points))
            if positional:
                control = cache.call("apply_to_points", cga.apply_to_points, key_motors, points)
        else:
            if cage is None:
                cage_V, cage_F = deform.tube_cage(V, axis=motion.long)
            else:
                cage_V, cage_F = check_cage(cage)
            field = deform.cage_precompute(V, cage_V, cage_F)
            key_motors = motion.motors(motion.fraction(cage_V))
            control = jax.jit(cga.apply_to_points)(key_motors, jnp.asarray(cage_V))
    precompute_ms = 1e3 * (time.perf_counter() - start)

    if positional:
        frame = jax.jit(lambda P: deform.blend_positions(field.weights, P))
        argument = control
    else:
        # the library's compiled entry point itself: its checks come back as values, the executable has no host
        # callback and the compilation cache keeps it
        frame = lambda motors: cache.call("motor_field_solve", deform.motor_field_solve, field, motors)  # noqa: E731
        argument = key_motors
    with status("deform", "compiling the deformation"):
        positions = jax.block_until_ready(frame(argument))
    start = time.perf_counter()
    positions = jax.block_until_ready(frame(argument))
    frame_ms = 1e3 * (time.perf_counter() - start)
    positions = np.asarray(positions, np.float64)
    if not np.all(np.isfinite(positions)):
        raise ValueError("the deformation produced non-finite positions")
    write_result(out, positions, F, V, f"{method}{' (positional)' if positional else ''}")
    measured = cache.call("distortion", deform.distortion, V, F, positions, by_value=(1,))  # edges of F on the host
    summary = {
        "method": method + (" (positional)" if positional else ""),
        "vertices": len(V),
        "keys": field.num_keys,
        "precompute_ms": round(precompute_ms, 1),
        "frame_ms": round(frame_ms, 2),
        "volume_ratio": round(float(measured["volume_ratio"]), 4),
        "mean_edge_change": round(float(measured["edge_mean"]), 4),
        "out": str(out),
    }
    if method in ("spline", "handles"):
        mesh_parts = deform.mesh_parts(V, F, np.concatenate(parts))
        summary["parts"] = mesh_parts.count
        summary["following_parts"] = int(mesh_parts.count - mesh_parts.handled.sum())
    return summary
