"""``jaxcga arap``: as-rigid-as-possible deformation with rotors (deformation paper sec. VII) of a mesh whose
handle vertices are moved.

The handles come from HANDLES.json, the format of ``jaxcga deform handles`` (``jaxcga_cli.models``): each group of
vertices moved by its motor, or put at its "positions". Without a handles file the mesh's two ends along its long
axis are the handles: the low end stays and the high end moves by the same motion as ``jaxcga deform``
(``--bend`` / ``--twist`` / ``--translate``).
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from jaxcga_cli import arguments
from jaxcga_cli.deform import HANDLES_HELP

HELP = (
    "deform a mesh as rigidly as possible (every small patch keeps its shape as far as it can, ARAP) so that "
    "its handle vertices reach where they are moved"
)
EXAMPLE = "jaxcga arap tests/data/Arm5.glb --bend 90 --out bent.npy"


def add_arguments(parser) -> None:
    arguments.mesh_argument(parser, "the built-in arm's rest mesh")
    parser.add_argument(
        "--handles",
        type=Path,
        default=None,
        help=f"{HANDLES_HELP}; here each group may instead give its vertices' targets, "
        '"positions": [[[x, y, z], ...], ...]; default: the low end of the long axis fixed, the '
        "high end moved by --bend/--twist/--translate",
    )
    parser.add_argument(
        "--iters", type=int, default=1000, help="at most this many local/global iterations (default 1000)"
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="stop when no vertex moves by more than this fraction of the diagonal in an iteration (the "
        "fixed-point residual; default: 50 ulps, 1.1e-14)",
    )
    parser.add_argument(
        "--fixed",
        action="store_true",
        help="run exactly --iters plain local/global iterations, libigl's algorithm (approximate positions)",
    )
    parser.add_argument(
        "--energy",
        choices=arguments.ARAP_ENERGIES,
        default="spokes_and_rims",
        help="spokes_and_rims (default, libigl's default: a rigid motion of all handles gives that "
        "rigid map) or spokes (the paper's eq. 9: with obtuse triangles it can drift from "
        "rigid maps)",
    )
    arguments.motion_arguments(parser, "default handles", "default handles")
    arguments.unhandled_argument(parser, "parts without a handle")
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="OUT.npy: float64 (n, 3) positions; OUT.glb/.obj/.ply/.stl: the mesh; OUT.png: a figure",
    )


def check_paths(args) -> None:
    from jaxcga_cli.output import DEFORM_OUTPUTS, check_files

    check_files(args, ("mesh", "handles"), {"out": args.out}, DEFORM_OUTPUTS)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_mesh

    V, F = load_mesh(args.mesh)
    summary = arap_command(
        V,
        F,
        args.out,
        handles=args.handles,
        iterations=args.iters,
        tolerance=args.tolerance,
        fixed=args.fixed,
        bend=args.bend,
        twist=args.twist,
        translate=args.translate,
        handle_fraction=args.handle_fraction,
        energy=args.energy,
        unhandled=args.unhandled,
    )
    return args.mesh or "built-in arm", summary


def handle_targets(path: Path, V):
    """(indices (k,), positions (k, 3)) of HANDLES.json for the mesh vertices ``V``: each group's vertices moved
    by its motor, or put at its positions."""
    import jax.numpy as jnp
    import numpy as np

    import jaxcga as cga
    from jaxcga_cli.models import read_handles

    groups, motors, targets = read_handles(path, V, positions=True)
    if targets is None:
        assert motors is not None  # read_handles gives motors wherever the file gives no positions
        targets = [
            np.asarray(cga.apply_to_points(cga.Multivector(motors.values[i], motors.blades), jnp.asarray(V[g])))
            for i, g in enumerate(groups)
        ]
    return np.concatenate(groups), np.concatenate(targets)


def default_handles(V, bend: float, twist: float, translate, fraction: float):
    """The low end of the long axis fixed, the high end moved by ``Motion(V, bend, twist, translate)``."""
    import numpy as np

    from jaxcga import apply_to_points
    from jaxcga_cli import cache
    from jaxcga_cli.models import Motion, end_handles

    motion = Motion(V, bend, twist, translate)
    low, high = end_handles(motion, V, fraction)
    moved = np.asarray(cache.call("apply_to_points", apply_to_points, motion.motors(np.ones(len(high))), V[high]))
    return np.concatenate([low, high]), np.concatenate([V[low], moved])


def arap_command(
    V,
    F,
    out: Path,
    *,
    handles: Path | None = None,
    iterations: int = 1000,
    tolerance: float | None = None,
    fixed: bool = False,
    bend: float = 60.0,
    twist: float = 0.0,
    translate=(0.0, 0.0, 0.0),
    handle_fraction: float = 0.05,
    energy: str = "spokes_and_rims",
    unhandled: str = "follow",
) -> dict:
    """Deform (V, F) as rigidly as possible with the handles of ``handles`` (or the default two ends),
    write ``out`` (.npy float64 (n, 3), a mesh, or a .png figure); returns a summary. ``energy`` and
    ``unhandled``: ``arap_precompute``'s ("spokes_and_rims" or "spokes"; "follow" or "error"); ``iterations``,
    ``tolerance`` (None: ``arap_solve``'s default) and ``fixed`` (exactly ``iterations`` plain local/global
    iterations): ``arap_solve``'s ``max_iterations``, ``tolerance`` and fixed mode."""
    import time

    import jax.numpy as jnp
    import numpy as np

    import deform
    from jaxcga_cli import cache
    from jaxcga_cli.output import write_result
    from jaxcga_cli.report import StepProgress, status

    if not isinstance(iterations, int) or iterations < 1:
        raise ValueError(f"iters: expected an int >= 1, got {iterations!r}")
    if handles is None:
        b, bc = default_handles(V, bend, twist, translate, handle_fraction)
    else:
        b, bc = handle_targets(handles, V)
    start = time.perf_counter()
    with status("arap", f"precomputing {len(V)} vertices, {len(b)} handles (factoring the system)"):
        data = deform.arap_precompute(V, F, b, energy=energy, unhandled=unhandled)
    precompute_ms = 1e3 * (time.perf_counter() - start)
    options: dict[str, Any]  # arap_solve's keywords: a tolerance (a number or None) and an acceleration (a name)
    if fixed:
        options = {"tolerance": None, "acceleration": "none"}
    else:
        options = {} if tolerance is None else {"tolerance": tolerance}

    first_done = []

    def report(iteration, energy, residual) -> None:
        if not first_done:
            first_done.append(time.perf_counter())
        bar.step(energy=f"{float(energy):.4g}", residual=f"{float(residual):.2g}")

    # the loop on the host: its compiled pieces hold no host callback (the CHOLMOD solves are made between them),
    # so that they are exported and read back by a later run (cache.call); the first iteration compiles them (or
    # reads them), the bar starts after it
    with StepProgress("arap", iterations, "iteration", f"arap {len(V)} vertices") as bar:
        start = time.perf_counter()
        result = deform.arap_solve(
            data,
            jnp.asarray(bc),
            max_iterations=iterations,
            progress=report,
            host_loop=True,
            runner=cache.call,
            **options,
        )
        end = time.perf_counter()
    compile_s = first_done[0] - start
    solve_ms = 1e3 * (end - first_done[0])
    U = np.asarray(result.U, np.float64)
    if not np.all(np.isfinite(U)):
        raise ValueError("the ARAP solve produced non-finite positions")
    write_result(out, U, F, V, f"ARAP, {int(result.iterations)} iterations")
    energies = np.asarray(result.energies)[: int(result.iterations) + 1]
    return {
        "vertices": len(V),
        "handles": len(b),
        "parts": data.parts,
        "following_parts": data.parts - data.handled_parts,
        "energy_type": energy,
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "residual": f"{float(result.residual):.2g}",
        "energy": f"{energies[0]:.4g} -> {energies[-1]:.4g}",
        "precompute_ms": round(precompute_ms, 1),
        "compile_s": round(compile_s, 1),  # with the first iteration
        "solve_ms": round(solve_ms, 1),  # the other iterations: compilation left out
        "out": str(out),
    }
