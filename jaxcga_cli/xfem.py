"""``jaxcga xfem SCENE``: one of the XFEM paper's cutting scenes of sec. 5 (``xfem.scene``: sticks, thin, cheese,
accordion, mouth; parameters of sec. 5 and Table 1), simulated with the timings of Table 2.

Writes into OUT, every ``every`` frames, on every frame with a cut, and for the last frame (with a cut latency,
a frame shows the cuts that have taken effect):

* ``frame_XXXX.png``: the deformed surfaces of the pieces (mesh boundary and cut faces, ``xfem.piece_surfaces``),
  coloured by connected piece, fixed axes;
* ``frame_XXXX.vtu``: the same triangles (each with its own three vertices) with the cell data ``piece``, for
  ParaView or meshio;

and ``summary.json``: ``SceneRun.summary()`` (pieces, DOFs, Booleans, timings) plus the run's settings, the
cut frames and the per-frame pieces, DOFs and times. OUT holds one run, as for ``jaxcga fem``
(``jaxcga_cli.fem``): empty unless ``force``, filled when the run ends, ``summary.json`` last.
"""

from __future__ import annotations

from pathlib import Path

from jaxcga_cli import arguments
from jaxcga_cli.fem import RUN_DESCRIBED, RUN_FILES, rounded

HELP = (
    "run one of the XFEM paper's cutting scenes (soft bodies cut while they move; the extended finite element "
    "method keeps the cuts exact without remeshing) and write its frames and timings"
)
EXAMPLE = "jaxcga xfem cheese --size small --steps 20 --out out/cheese"


def add_arguments(parser) -> None:
    parser.add_argument(
        "scene",
        choices=arguments.XFEM_SCENES,
        metavar="SCENE",
        help="sticks (Fig. 5), thin (Fig. 1), cheese (Fig. 6), accordion (Fig. 7) or mouth (Fig. 8)",
    )
    parser.add_argument("--steps", type=int, default=None, help="frames (default: the scene's, past its last cut)")
    parser.add_argument(
        "--size",
        choices=arguments.XFEM_SIZES,
        default="paper",
        help="paper (Table 1's meshes, the default) or small (coarse)",
    )
    parser.add_argument(
        "--every",
        type=int,
        default=10,
        help="write a frame every this many frames, besides cut frames and the last (default 10)",
    )
    parser.add_argument(
        "--cut-latency",
        type=int,
        default=0,
        help="compute each cut in the background while the body steps; it takes effect this many "
        "frames after its scheduled frame (default 0: in its frame, as Algorithm 1)",
    )
    parser.add_argument("--no-figures", action="store_true", help="write the .vtu surfaces and summary.json only")
    parser.add_argument("--force", action="store_true", help=arguments.FORCE_HELP)
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for frame_XXXX.png, frame_XXXX.vtu and summary.json"
    )


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_run_folder

    check_run_folder(args.out, RUN_FILES, args.force, RUN_DESCRIBED)


def run(args) -> dict:
    summary = xfem_command(
        args.scene,
        args.out,
        args.steps,
        size=args.size,
        every=args.every,
        figures=not args.no_figures,
        cut_latency=args.cut_latency,
        force=args.force,
    )
    shown = {
        k: summary[k]
        for k in (
            "size",
            "nodes",
            "dofs",
            "pieces",
            "frames",
            "cuts",
            "booleans",
            "boolean_ms",
            "integral_ms",
            "step_avg_s",
            "step_max_s",
            "total_s",
        )
    }
    return args.scene, rounded(shown) | {"out": args.out}


def xfem_command(
    name: str,
    out: Path,
    steps: int | None = None,
    *,
    size: str = "paper",
    every: int = 10,
    figures: bool = True,
    cut_latency: int = 0,
    force: bool = False,
) -> dict:
    """Run scene ``name`` for ``steps`` frames (None: the scene's default) and write frames into ``out``; returns
    the summary (module docstring). ``cut_latency``: as ``xfem.run_scene``; ``force``: as ``fem_command``'s."""
    import meshio
    import numpy as np

    import xfem
    from _jaxcga_shared.output import check_run_folder, run_folder, write_json
    from jaxcga_cli.fem import surface_frame
    from jaxcga_cli.figures import colormap
    from jaxcga_cli.report import StepProgress

    if name not in xfem.SCENES:
        raise ValueError(f"SCENE: expected one of {xfem.SCENES}, got {name!r}")
    if size not in xfem.SIZES:
        raise ValueError(f"size: expected one of {xfem.SIZES}, got {size!r}")
    if steps is not None and (not isinstance(steps, int) or steps < 1):
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if not isinstance(cut_latency, int) or cut_latency < 0:
        raise ValueError(f"cut_latency: expected an int >= 0, got {cut_latency!r}")
    out = check_run_folder(out, RUN_FILES, force, RUN_DESCRIBED)

    sc = xfem.scene(name, size)
    steps = sc.steps if steps is None else steps
    X = np.asarray(sc.mesh.X)
    extent = X.max(0) - X.min(0)
    # room to fall: the body's size below it, half of it around
    limits = (X.min(0) - np.array([0.5, 0.5, 1.0]) * extent.max(), X.max(0) + 0.5 * extent.max())
    written = []

    with run_folder(out, RUN_FILES, "summary.json") as staging:

        def write(frame: int, model):
            V, F, piece = xfem.piece_surfaces(model)
            meshio.write(
                staging / f"frame_{frame:04d}.vtu", meshio.Mesh(V, [("triangle", F)], cell_data={"piece": [piece]})
            )
            if figures:
                surface_frame(
                    V,
                    F,
                    limits,
                    staging / f"frame_{frame:04d}.png",
                    f"{name}: frame {frame}, t = {frame * sc.h:.3f} s, {int(piece.max()) + 1} pieces",
                    colormap("tab20")(piece % 20),
                )
            written.append(frame)

        with StepProgress("xfem", steps, "frame", f"xfem {name}") as progress:

            def on_frame(record, model):
                if record.cuts or record.frame % every == 0 or record.frame == steps:
                    write(record.frame, model)
                progress.step()

            write(0, sc.model())
            run = xfem.run_scene(sc, steps, on_frame=on_frame, cut_latency=cut_latency)
        summary = run.summary()
        summary.update(
            {
                "steps": steps,
                "dt": sc.h,
                "young": sc.young,
                "poisson": sc.poisson,
                "density": sc.density,
                "epsilon": sc.epsilon,
                "newton_iterations": sc.newton_iterations,
                "fixed_nodes": int(len(sc.fixed)),
                "cut_latency": cut_latency,
                "cut_frames": sorted({c.frame for c in sc.cuts if c.frame <= steps}),
                "frames_written": written,
                "frame_pieces": [r.pieces for r in run.records],
                "frame_dofs": [r.dofs for r in run.records],
                "frame_seconds": [r.seconds for r in run.records],
                "max_displacement": float(np.abs(np.asarray(run.model.state.x) - X[run.model.dof_node]).max()),
            }
        )
        write_json(staging / "summary.json", summary)
    return summary
