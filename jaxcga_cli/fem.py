"""``jaxcga fem SCENE``: backward Euler (XFEM paper eq. 10) of a stable neo-Hookean body under gravity, with the
paper's parameters by default (Young 1e6, Poisson 0.4, density 1e3, h = 0.033 s, one Newton iteration).

Scenes:

* ``bar``: a 2 x 0.5 x 0.5 bar (16 x 4 x 4 cells, 6 tets each), clamped at x = 0: a cantilever.
* ``cube``: a unit cube (8^3 cells) hanging from its top face.
* a file: a tet mesh read by meshio (``.msh``, ``.vtu``, ``.vtk``, ...), or a triangle surface (``.obj``,
  ``.ply``, ``.stl``, ``.off``, glTF: a rigged model's bind-pose skin, every part) tetrahedralized by fTetWild
  (``xfem.tetrahedralize_surface``: open, self-intersecting, several parts are fine) or, with ``mesher="tetgen"``,
  by TetGen (closed, clean surfaces; an optional extra). The surface is embedded in the tets and carried along.
  The nodes within ``fix_fraction`` of the top (along -gravity) are clamped; gravity points down z, or down y
  for glTF (its up axis).

Writes into OUT: ``frame_XXXX.png`` (the boundary surface, or the user's surface for a surface scene, fixed
axes), ``frame_XXXX.vtu`` (the tet mesh with its displacement and velocity, for ParaView or meshio) and, for a
surface scene, ``frame_XXXX_surface.obj`` (the user's own surface, its vertices and faces as read, deformed)
every ``every`` steps and for the last one, and ``summary.json`` (nodes, DOFs, elements, steps, step times,
energies; for a surface scene ``tetrahedralization``: the mesher, tets, nodes, quality (``xfem.tet_quality``),
seconds, the surface's size and its largest distance to the tets). OUT holds one run: it must be empty
unless ``force``, and the files appear when the run ends (written beside, in a private folder), replacing the
previous run's files (only those), ``summary.json`` last; a failed run leaves OUT as it was.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "simulate an elastic body (a soft solid of tetrahedra, stable neo-Hookean material) sagging under gravity "
    "and write its frames as images and ParaView files"
)
EXAMPLE = "jaxcga fem bar --steps 50 --out out/bar"
SCENES = ("bar", "cube")
RUN_FILES = re.compile(r"frame_\d{4,}(\.png|\.vtu|_surface\.obj)|summary\.json")  # one run's files in its OUT folder
RUN_DESCRIBED = "frame_XXXX.png, frame_XXXX.vtu, frame_XXXX_surface.obj and summary.json"
MESHERS = ("ftetwild", "tetgen")
GRAVITY = 9.81
SURFACE_FORMATS = (".obj", ".ply", ".stl", ".off", ".glb", ".gltf")


def add_arguments(parser) -> None:
    parser.add_argument(
        "scene",
        help="bar (a cantilever), cube (hanging from its top face), a tet mesh file "
        "(meshio: .msh, .vtu, ...) or a surface (.obj, .ply, .stl, .off, glTF; open, self-intersecting, "
        "several parts are fine) to tetrahedralize",
    )
    parser.add_argument("--steps", type=int, default=100, help="time steps (default 100)")
    parser.add_argument("--dt", type=float, default=0.033, help="time step h in seconds (default 0.033, the paper's)")
    parser.add_argument("--young", type=float, default=1e6, help="Young's modulus (stiffness) in Pa (default 1e6)")
    parser.add_argument(
        "--poisson",
        type=float,
        default=0.4,
        help="Poisson's ratio (how much the body keeps its volume; below 0.5; default 0.4)",
    )
    parser.add_argument("--density", type=float, default=1e3, help="mass density in kg/m^3 (default 1e3)")
    parser.add_argument(
        "--gravity",
        type=float,
        nargs=3,
        default=None,
        metavar=("GX", "GY", "GZ"),
        help="gravitational acceleration (default 0 0 -9.81; glTF, whose up is +y: 0 -9.81 0)",
    )
    parser.add_argument(
        "--newton",
        type=int,
        default=1,
        help="Newton iterations per step (default 1, the paper's); the most with --tolerance",
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="stop a step's Newton iterations once an update is below this fraction of the body's size (e.g. 1e-10 "
        "with --newton 50: converged steps, as the library's default); default: run exactly --newton iterations",
    )
    parser.add_argument("--every", type=int, default=10, help="write a frame every this many steps (default 10)")
    parser.add_argument(
        "--fix-fraction",
        type=float,
        default=0.02,
        help="mesh files: clamp the nodes within this fraction of the height below the top (default 0.02)",
    )
    parser.add_argument(
        "--mesher",
        choices=MESHERS,
        default="ftetwild",
        help="surfaces: ftetwild (any surface, the default) or tetgen (closed, self-intersection-free surfaces; "
        "the optional extra jaxcga[tetgen])",
    )
    arguments.ftetwild_arguments(parser, "surfaces, ftetwild")
    parser.add_argument("--no-figures", action="store_true", help="write the .vtu meshes and summary.json only")
    parser.add_argument("--force", action="store_true", help=arguments.FORCE_HELP)
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help="folder for frame_XXXX.png, frame_XXXX.vtu, frame_XXXX_surface.obj (surfaces) and summary.json",
    )


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_input, check_run_folder

    inputs = {}
    if args.scene not in SCENES:
        inputs["SCENE"] = check_input(args.scene, f"SCENE (one of {', '.join(SCENES)} or a mesh file)")
    check_run_folder(args.out, RUN_FILES, args.force, RUN_DESCRIBED, inputs=inputs)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    summary = fem_command(
        args.scene,
        args.steps,
        args.out,
        h=args.dt,
        young=args.young,
        poisson=args.poisson,
        density=args.density,
        gravity=None if args.gravity is None else tuple(args.gravity),
        newton_iterations=args.newton,
        tolerance=args.tolerance,
        every=args.every,
        fix_fraction=args.fix_fraction,
        mesher=args.mesher,
        edge_length=args.edge_length,
        epsilon=args.epsilon,
        figures=not args.no_figures,
        force=args.force,
    )
    shown = {
        k: summary[k] for k in ("nodes", "dofs", "elements", "steps", "step_avg_s", "step_max_s", "max_displacement")
    }
    if "tetrahedralization" in summary:
        report = summary["tetrahedralization"]
        shown |= {
            "mesher": report["mesher"],
            "tet_s": report["seconds"],
            "min_dihedral_deg": report["min_dihedral_deg"],
            "min_volume_ratio": report["min_volume_ratio"],
        }
    return args.scene, rounded(shown) | {"out": args.out}


def rounded(summary: dict) -> dict:
    """``summary`` with its floats to 4 significant digits, for the summary line."""
    return {k: f"{v:.4g}" if isinstance(v, float) else v for k, v in summary.items()}


def is_gltf(scene: str) -> bool:
    return Path(scene).suffix.lower() in (".glb", ".gltf")


def scene_mesh(
    scene: str,
    fix_fraction: float = 0.02,
    up=(0.0, 0.0, 1.0),
    mesher: str = "ftetwild",
    edge_length: float = 0.05,
    epsilon: float = 1e-3,
):
    """(TetMesh, fixed node indices, surface) of a named scene or a mesh file (module docstring): the nodes within
    ``fix_fraction`` of the extent along ``up`` from the top are fixed; surface: None, or (V, F, the
    ``SurfaceEmbedding`` of V, the tetrahedralization's report) for a surface file."""
    import contextlib
    import io

    import numpy as np

    import xfem
    from jaxcga_cli.models import load_mesh

    if scene == "bar":
        mesh = xfem.box_tets((16, 4, 4), size=(2.0, 0.5, 0.5))
        return mesh, np.flatnonzero(np.asarray(mesh.X)[:, 0] <= 1e-12), None
    if scene == "cube":
        mesh = xfem.box_tets((8, 8, 8))
        return mesh, np.flatnonzero(np.asarray(mesh.X)[:, 2] >= 1.0 - 1e-12), None
    path = Path(scene)
    if not path.exists():
        raise FileNotFoundError(f"SCENE: expected one of {SCENES} or a mesh file, got {scene!r} (no such file)")
    if mesher not in MESHERS:
        raise ValueError(f"mesher: expected one of {MESHERS}, got {mesher!r}")
    if not 0 < fix_fraction < 1:
        raise ValueError(f"fix_fraction: expected a fraction in (0, 1), got {fix_fraction}")
    surface = None
    if path.suffix.lower() in SURFACE_FORMATS:
        V, F = load_mesh(path, "SCENE")  # glTF: the bind-pose skin of every part
        if mesher == "tetgen":
            import time

            border = open_edges(F)
            if border:
                raise ValueError(
                    f"SCENE: {path} is an open surface ({border} edges lie on its border, each in one triangle "
                    "only); TetGen fills closed surfaces only: give --mesher ftetwild (the default), which takes "
                    "open ones"
                )
            start = time.perf_counter()
            try:
                mesh = xfem.tetrahedralize(V, F)
            except ModuleNotFoundError as error:  # TetGen is an optional extra
                raise ValueError(f"mesher: {error}") from None
            embedding = xfem.embed_points(mesh, V)
            seconds = time.perf_counter() - start
            quality = xfem.tet_quality(mesh)
        else:
            mesh, embedding, quality, seconds = xfem.tetrahedralize_surface(
                V, F, edge_length=edge_length, epsilon=epsilon
            )
        diagonal = float(np.linalg.norm(V.max(0) - V.min(0)))
        report = {"mesher": mesher, **quality._asdict(), "seconds": seconds}
        if mesher == "ftetwild":
            report |= {"edge_length": edge_length, "epsilon": epsilon}
        report |= {
            "surface_vertices": len(V),
            "surface_faces": len(F),
            "max_surface_distance": float(embedding.distance.max()) / diagonal,  # over the diagonal
        }
        surface = (V, F, embedding, report)
    else:
        try:
            # meshio prints its readers' complaints before giving up: the error below says it on one line
            with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
                mesh = xfem.read_tet_mesh(path)
        except ValueError as error:  # it names its argument "path"
            surface = _surface_cells(path)
            if surface:
                raise ValueError(
                    f"SCENE: {path} holds a surface ({surface} cells), no tetrahedra; fem fills a surface with "
                    f"tetrahedra when it comes as {', '.join(SURFACE_FORMATS)}: convert it to one of those"
                ) from None
            raise ValueError(f"SCENE: {str(error).removeprefix('path: ')}") from None
    height = np.asarray(mesh.X) @ np.asarray(up, np.float64)
    fixed = np.flatnonzero(height >= height.max() - fix_fraction * (height.max() - height.min()))
    return mesh, fixed, surface


def open_edges(F) -> int:
    """The number of edges of the triangles ``F`` ((m, 3)) that only one triangle has (0 for a closed surface)."""
    import numpy as np

    edges = np.sort(np.asarray(F)[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return int((counts == 1).sum())


def _surface_cells(path: Path) -> str:
    """The surface cell types (triangle, quad, ...) of a mesh file meshio reads that holds no tetrahedra, joined
    (empty when meshio cannot read it or it has none)."""
    import contextlib
    import io

    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            cells = {block.type for block in meshio.read(path).cells}
    # meshio's readers fail in many ways, some by sys.exit: the caller's error stands then
    except (Exception, SystemExit):  # noqa: BLE001
        return ""
    return ", ".join(sorted(cells & {"triangle", "quad", "polygon"}))


def surface_frame(V, F, limits, path: Path, title: str, colours=None) -> None:
    """A figure of the triangles ``F`` of ``V`` inside the fixed box ``limits`` (lo, hi): one colour, or one per
    triangle (``colours``)."""
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from jaxcga_cli import figures

    fig = figures.figure(5, 5)
    ax = figures.axes_3d(fig)
    if colours is None:
        ax.plot_trisurf(
            V[:, 0], V[:, 1], V[:, 2], triangles=F, color="tab:orange", linewidth=0.1, edgecolor="k", alpha=0.95
        )
    else:
        ax.add_collection3d(Poly3DCollection(V[F], facecolors=colours, edgecolors="k", linewidths=0.05, alpha=0.95))
    lo, hi = limits
    figures.set_box(ax, lo, hi, title, floor=1e-3)
    figures.save_figure(fig, path, dpi=80, bbox_inches="tight")


def write_obj(path: Path, V, F, groups=None) -> None:
    """A triangle mesh as Wavefront OBJ (vertices, then 1-based faces in F's order), written whole or not at all;
    ``groups``: None, or (f,) int a group per face, written as OBJ groups ``piece_K`` (a ``g`` line where the group
    changes from one face to the next, so the faces keep their order)."""
    import io

    import numpy as np

    from _jaxcga_shared.output import write_bytes

    F = np.asarray(F)
    text = io.StringIO()
    text.write(f"# {len(V)} vertices, {len(F)} faces\n")
    np.savetxt(text, V, fmt="v %.9g %.9g %.9g")
    if groups is None:
        np.savetxt(text, F + 1, fmt="f %d %d %d")
    else:
        groups = np.asarray(groups)
        starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
        for start, end in zip(starts.tolist(), np.r_[starts[1:], len(F)].tolist()):
            text.write(f"g piece_{int(groups[start])}\n")
            np.savetxt(text, F[start:end] + 1, fmt="f %d %d %d")
    write_bytes(path, text.getvalue())


def fem_command(
    scene: str,
    steps: int,
    out: Path,
    *,
    h: float = 0.033,
    young: float = 1e6,
    poisson: float = 0.4,
    density: float = 1e3,
    gravity=None,
    newton_iterations: int = 1,
    tolerance: float | None = None,
    every: int = 10,
    fix_fraction: float = 0.02,
    mesher: str = "ftetwild",
    edge_length: float = 0.05,
    epsilon: float = 1e-3,
    figures: bool = True,
    force: bool = False,
) -> dict:
    """Simulate ``scene`` for ``steps`` backward Euler steps and write frames into ``out``; returns the summary.
    ``gravity``: None for the scene's down (module docstring). ``newton_iterations``, ``tolerance``: as
    ``xfem.backward_euler_step``'s, the paper's single iteration by default. ``mesher``, ``edge_length``,
    ``epsilon``: how a surface is tetrahedralized (``xfem.tetrahedralize_surface``'s arguments). ``out`` must be
    empty unless ``force``; the run's files replace the previous run's when it ends
    (``_jaxcga_shared.output.run_folder``)."""
    import time

    import jax
    import jax.numpy as jnp
    import meshio
    import numpy as np

    import xfem
    from _jaxcga_shared.output import check_run_folder, run_folder, write_json
    from jaxcga_cli.report import StepProgress

    if not isinstance(steps, int) or steps < 1:
        raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
    if not isinstance(every, int) or every < 1:
        raise ValueError(f"every: expected an int >= 1, got {every!r}")
    if not h > 0:
        raise ValueError(f"dt: expected a positive time step, got {h}")
    if not density > 0:
        raise ValueError(f"density: expected a positive density, got {density}")
    if tolerance is not None and not tolerance > 0:
        raise ValueError(f"tolerance: expected a positive fraction of the body's size, got {tolerance}")
    if not isinstance(newton_iterations, int) or newton_iterations < 1:
        raise ValueError(f"newton: expected --newton >= 1 Newton iterations per step, got {newton_iterations!r}")
    if gravity is None:
        gravity = (0.0, -GRAVITY, 0.0) if is_gltf(scene) else (0.0, 0.0, -GRAVITY)
    if len(gravity) != 3 or not np.isfinite(max(abs(float(g)) for g in gravity) * float(density)):
        raise ValueError(f"gravity: expected three numbers whose product with the density is finite, got {gravity}")
    out = check_run_folder(
        out, RUN_FILES, force, RUN_DESCRIBED, inputs=None if scene in SCENES else {"SCENE": Path(scene)}
    )
    material = xfem.Material(young, poisson)
    g = np.asarray(gravity, np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0 else np.array([0.0, 0.0, 1.0])
    mesh, fixed, surface = scene_mesh(scene, fix_fraction, up, mesher, edge_length, epsilon)
    system = xfem.fem_from_mesh(mesh, density, gravity, fixed)
    faces = mesh.boundary_faces() if surface is None else surface[1]
    X = np.asarray(mesh.X)
    carry = None if surface is None else jax.jit(lambda x: surface[2].positions(x))
    extent = X.max(0) - X.min(0)
    limits = (X.min(0) - 0.6 * extent.max(), X.max(0) + 0.6 * extent.max())
    energies = jax.jit(lambda state: xfem.mechanical_energy(system, state, material))

    with run_folder(out, RUN_FILES, "summary.json") as staging:

        def write(k: int, state):
            x = np.asarray(state.x)
            meshio.write(
                staging / f"frame_{k:04d}.vtu",
                meshio.Mesh(
                    x,
                    [("tetra", np.asarray(mesh.T))],
                    point_data={"displacement": x - X, "velocity": np.asarray(state.v)},
                ),
            )
            shown = x
            if surface is not None:  # the user's own surface, carried by the tets
                assert carry is not None
                shown = np.asarray(carry(state.x))
                write_obj(staging / f"frame_{k:04d}_surface.obj", shown, surface[1])
            if figures:
                surface_frame(
                    shown, faces, limits, staging / f"frame_{k:04d}.png", f"{scene}: step {k}, t = {k * h:.3f} s"
                )

        state = xfem.State(mesh.X, jnp.zeros_like(mesh.X))
        write(0, state)
        times, kinetic, potential, iterations, converged = [], [], [], [], 0
        with StepProgress("fem", steps, "step", f"fem {Path(scene).name}") as progress:
            for k in range(1, steps + 1):
                start = time.perf_counter()
                state = jax.block_until_ready(
                    # by default the paper's fixed Newton iterations (--newton, 1), timed as its Table 2
                    xfem.backward_euler_step(
                        system, state, h, material, newton_iterations=newton_iterations, tolerance=tolerance
                    )
                )
                times.append(time.perf_counter() - start)
                iterations.append(int(state.stats.iterations))
                converged += bool(state.stats.converged)
                if not bool(jnp.all(jnp.isfinite(state.x))):
                    raise RuntimeError(f"fem: non-finite positions at step {k}; try a smaller --dt or more --newton")
                e_kin, e_elastic, e_external = energies(state)
                kinetic.append(float(e_kin))
                potential.append(float(e_elastic + e_external))
                if k % every == 0 or k == steps:
                    write(k, state)
                progress.step()
        summary = {
            "scene": scene,
            "nodes": int(mesh.n_nodes),
            "dofs": 3 * (int(mesh.n_nodes) - len(fixed)),
            "elements": int(mesh.n_elements),
            "fixed_nodes": len(fixed),
            "steps": steps,
            "dt": h,
            "young": young,
            "poisson": poisson,
            "density": density,
            "newton_iterations": newton_iterations,
            "tolerance": tolerance,
            "newton_iterations_mean": float(np.mean(iterations)),
            "converged_steps": converged,  # steps whose last Newton update was below the tolerance (or 1e-10)
            "first_step_s": times[0],
            "step_avg_s": float(np.mean(times[1:])) if steps > 1 else times[0],
            "step_max_s": float(np.max(times[1:])) if steps > 1 else times[0],
            "kinetic_energy": kinetic,
            "potential_energy": potential,
            "max_displacement": float(np.abs(np.asarray(state.x) - X).max()),
        }
        if surface is not None:
            summary["tetrahedralization"] = surface[3]
        write_json(staging / "summary.json", summary)
    return summary
