"""``jaxcga xfem SCENE``: one of the XFEM paper's cutting scenes of sec. 5 (``xfem.scene``: sticks, thin, cheese,
accordion, octopus; parameters of sec. 5 and Table 1), simulated with the timings of Table 2; or a surface file
(.obj, .ply, .stl, .off, glTF: a rigged model's bind-pose skin), tetrahedralized by fTetWild
(``xfem.tetrahedralize_surface``), hanging from its top (the nodes within 2% of its height; up is +z, +y for glTF)
and cut by a plane (``--plane``, default: through the middle of its bounding box, across the up axis) before frame
``--cut-frame``, with ``jaxcga fem``'s default material and time step.

Writes into OUT, every ``every`` frames, on every frame with a cut, and for the last frame (with a cut latency,
a frame shows the cuts that have taken effect):

* ``frame_XXXX.png``: the deformed surfaces of the pieces (mesh boundary and cut faces, ``xfem.piece_surfaces``),
  coloured by connected piece, fixed axes;
* ``frame_XXXX.vtu``: the same triangles (each with its own three vertices) with the cell data ``piece``, for
  ParaView or meshio;

* ``frame_XXXX_surface.obj`` (surface files): the user's own surface, deformed and in pieces
  (``xfem.cut_surface``: each triangle follows the side of the cut its centroid is on), its faces in the
  file's order, each under the OBJ group ``piece_K`` of its connected piece;

and ``summary.json``: ``SceneRun.summary()`` (``jaxcga_cli.scene_runs``: pieces, DOFs, Booleans, timings) plus
the run's settings, the cut frames and the per-frame pieces, DOFs and times (surface files: also
``tetrahedralization``, as ``jaxcga fem`` writes it). OUT holds one run, as for ``jaxcga fem``
(``jaxcga_cli.fem``): empty unless ``force``, filled when the run ends, ``summary.json`` last.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxcga_cli import arguments
from jaxcga_cli.fem import RUN_DESCRIBED, RUN_FILES, SURFACE_FORMATS, rounded

HELP = (
    "run one of the XFEM paper's cutting scenes (soft bodies cut while they move; the extended finite element "
    "method keeps the cuts exact without remeshing), or cut any surface (a character) by a plane, and write its "
    "frames and timings"
)
EXAMPLE = "jaxcga xfem cheese --size small --steps 20 --out out/cheese"


def add_arguments(parser) -> None:
    parser.add_argument(
        "scene",
        metavar="SCENE",
        help="sticks (Fig. 5), thin (Fig. 1), cheese (Fig. 6), accordion (Fig. 7), octopus (Fig. 8), or a surface "
        "file (.obj, .ply, .stl, .off, glTF; open, self-intersecting, several parts are fine) to tetrahedralize "
        "and cut by --plane",
    )
    parser.add_argument(
        "--steps", type=int, default=None, help="frames (default: the scene's, past its last cut; 30 for a surface)"
    )
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
    parser.add_argument(
        "--plane",
        type=float,
        nargs=6,
        default=None,
        metavar=("PX", "PY", "PZ", "NX", "NY", "NZ"),
        help="surface files: the cut plane's point and normal (default: the bounding box's centre, normal up)",
    )
    parser.add_argument(
        "--cut-frame", type=int, default=5, help="surface files: the frame the plane cuts before (default 5)"
    )
    arguments.ftetwild_arguments(parser, "surface files")
    parser.add_argument(
        "--method",
        choices=("xfem", "rxfem"),
        default="xfem",
        help="xfem (the paper's generalized XFEM, the default) or rxfem (the baseline of Koschier et al. 2017 that "
        "Table 2 compares against: the scene's cuts that intersect an earlier one are left out)",
    )
    parser.add_argument(
        "--without-last-cut",
        action="store_true",
        help="paper scenes: drop the scene's last cut (the thin sheets' cross cut, the accordion's release, the "
        "octopus's jaw), to compare with the full run",
    )
    parser.add_argument("--no-figures", action="store_true", help="write the .vtu surfaces and summary.json only")
    parser.add_argument("--force", action="store_true", help=arguments.FORCE_HELP)
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for frame_XXXX.png, frame_XXXX.vtu and summary.json"
    )


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_input, check_run_folder

    inputs = {}
    if args.scene not in arguments.XFEM_SCENES:
        inputs["SCENE"] = check_input(
            args.scene, f"SCENE (one of {', '.join(arguments.XFEM_SCENES)} or a surface file)"
        )
    check_run_folder(args.out, RUN_FILES, args.force, RUN_DESCRIBED, inputs=inputs)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    summary = xfem_command(
        args.scene,
        args.out,
        args.steps,
        size=args.size,
        every=args.every,
        figures=not args.no_figures,
        cut_latency=args.cut_latency,
        method=args.method,
        last_cut=not args.without_last_cut,
        plane=args.plane,
        cut_frame=args.cut_frame,
        edge_length=args.edge_length,
        epsilon=args.epsilon,
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
    # the first frame compiles the step: shown apart, and the step times over the frames after it
    seconds = summary["frame_seconds"]
    if len(seconds) > 1:
        later = seconds[1:]
        shown |= {"step_avg_s": sum(later) / len(later), "step_max_s": max(later), "first_frame_s": seconds[0]}
    if "tetrahedralization" in summary:
        report = summary["tetrahedralization"]
        shown |= {k: report[k] for k in ("tets", "seconds", "min_dihedral_deg", "min_volume_ratio")}
    return args.scene, rounded(shown) | {"out": args.out}


def surface_scene(
    path: str, steps: int, plane=None, cut_frame: int = 5, edge_length: float = 0.05, epsilon: float = 1e-3
):
    """(``xfem.Scene``, (V, F, embedding, tetrahedralization report)) of a surface file (module docstring)."""
    import numpy as np

    import xfem
    from jaxcga_cli.fem import GRAVITY, is_gltf, scene_mesh

    if not isinstance(cut_frame, int) or not 1 <= cut_frame <= steps:
        raise ValueError(f"cut_frame: expected an int in [1, {steps}] (the frames run), got {cut_frame!r}")
    gravity = (0.0, -GRAVITY, 0.0) if is_gltf(path) else (0.0, 0.0, -GRAVITY)
    up = -np.asarray(gravity) / GRAVITY
    mesh, fixed, surface = scene_mesh(path, 0.02, up, "ftetwild", edge_length, epsilon)
    X = np.asarray(mesh.X)
    diagonal = float(np.linalg.norm(X.max(0) - X.min(0)))
    if plane is None:
        point, normal = (X.min(0) + X.max(0)) / 2, up
    else:
        point, normal = np.asarray(plane[:3], np.float64), np.asarray(plane[3:], np.float64)
    T = np.asarray(mesh.T)
    pairs = np.sort(T[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2), axis=1)
    edges = np.unique(pairs, axis=0)
    average = float(np.linalg.norm(X[edges[:, 0]] - X[edges[:, 1]], axis=1).mean())
    # the paper's scenes: a cut 1e-4 thick on a body of unit size, moved by 1% of an edge (sec. 6.1)
    solid = xfem.plane_cut_solid(point, normal, 2 * diagonal, 1e-4 * diagonal)
    cut = xfem.ScheduledCut(cut_frame, solid, 1e-2 * average, f"the plane through {point.tolist()}")
    scene = xfem.Scene(
        Path(path).name, "paper", mesh, fixed, 1e6, 0.4, 1e3, 0.033, 1e-4 * diagonal, steps, (cut,), 1, gravity
    )
    return scene, surface


def xfem_command(
    name: str,
    out: Path,
    steps: int | None = None,
    *,
    size: str = "paper",
    every: int = 10,
    figures: bool = True,
    cut_latency: int = 0,
    method: str = "xfem",
    last_cut: bool = True,
    plane=None,
    cut_frame: int = 5,
    edge_length: float = 0.05,
    epsilon: float = 1e-3,
    force: bool = False,
) -> dict:
    """Run scene ``name`` (a paper scene or a surface file) for ``steps`` frames (None: the scene's default, 30 for a
    surface file) and write frames into ``out``; returns the summary (module docstring). ``cut_latency``: as
    ``jaxcga_cli.scene_runs.run_scene``; ``method``: "xfem" or "rxfem" (``xfem.rxfem_schedule``: the RXFEM baseline
    on the cuts that intersect no earlier one; no cut latency); ``last_cut``: as ``xfem.scene`` (paper scenes);
    ``plane`` (6 numbers: point, normal), ``cut_frame``, ``edge_length``, ``epsilon``: the surface file's cut and
    tetrahedralization; ``force``: as ``fem_command``'s."""
    import meshio
    import numpy as np

    import xfem
    from _jaxcga_shared.output import check_run_folder, run_folder, write_json
    from jaxcga_cli.fem import surface_frame, write_obj
    from jaxcga_cli.figures import colormap
    from jaxcga_cli.report import StepProgress
    from jaxcga_cli.scene_runs import run_scene

    is_file = name not in xfem.SCENES
    if is_file and Path(name).suffix.lower() not in SURFACE_FORMATS:
        raise ValueError(
            f"SCENE: expected one of {xfem.SCENES} or a surface file ({', '.join(SURFACE_FORMATS)}), got {name!r}"
        )
    if plane is not None and (len(plane) != 6 or not np.all(np.isfinite(np.asarray(plane, np.float64)))):
        raise ValueError(f"plane: expected six finite numbers (a point and a normal), got {plane!r}")
    if size not in xfem.SIZES:
        raise ValueError(f"size: expected one of {xfem.SIZES}, got {size!r}")
    if steps is not None and (not isinstance(steps, int) or steps < 1):
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if not isinstance(cut_latency, int) or cut_latency < 0:
        raise ValueError(f"cut_latency: expected an int >= 0, got {cut_latency!r}")
    if method not in ("xfem", "rxfem"):
        raise ValueError(f"method: expected 'xfem' or 'rxfem', got {method!r}")
    if method == "rxfem" and cut_latency:
        raise ValueError("cut_latency: cuts in the background are for method 'xfem' only")
    out = check_run_folder(out, RUN_FILES, force, RUN_DESCRIBED, inputs={"SCENE": Path(name)} if is_file else None)

    surface = None
    if is_file:
        steps = 30 if steps is None else steps
        sc, surface = surface_scene(name, steps, plane, cut_frame, edge_length, epsilon)
    else:
        sc = xfem.scene(name, size, last_cut=last_cut)
    left_out = ()
    if method == "rxfem":
        _, sc, left_out = xfem.rxfem_schedule(sc)
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
            if surface is not None:  # the user's own surface, in the pieces' motion
                V, F, piece, _ = xfem.cut_surface(model, surface[2], surface[0], surface[1])
                write_obj(staging / f"frame_{frame:04d}_surface.obj", V, F, piece)
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

            with sc.model() as first:  # frame 0's model, closed once written
                write(0, first)
            run = run_scene(sc, steps, on_frame=on_frame, cut_latency=cut_latency)
            run.model.close()  # its threads: the cuts' Booleans, the next level's compilation
        summary: dict[str, object] = dict(run.summary())
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
                "last_cut": last_cut,
                "method": method,
                "cuts_left_out": [c.frame for c in left_out],
                "cut_frames": sorted({c.frame for c in sc.cuts if c.frame <= steps}),
                "frames_written": written,
                "frame_pieces": [r.pieces for r in run.records],
                "frame_dofs": [r.dofs for r in run.records],
                "frame_seconds": [r.seconds for r in run.records],
                "max_displacement": float(np.abs(np.asarray(run.model.state.x) - X[run.model.dof_node]).max()),
            }
        )
        if surface is not None:
            summary["tetrahedralization"] = surface[3]
        write_json(staging / "summary.json", summary)
    return summary
