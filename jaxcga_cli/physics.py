"""``jaxcga physics CHARACTER``: a rigged character plays a clip with simulated flesh (``xfem.character_body``,
``xfem.simulate_character``): the nodes in the bones' cores follow the skinned rig, the rest lag and jiggle about it
(stable neo-Hookean, backward Euler, optional Rayleigh damping), and planes cut the body at given frames; a piece
left without the skeleton's root falls.

The cuts (``--cut FRAME PX PY PZ NX NY NZ``) are planes in the body's rest configuration: the model at its
skeleton's rest pose, in world coordinates, as ``jaxcga view CHARACTER`` shows it standing before a clip plays (the
error of a plane that misses the body gives that bounding box). Each cut is a slab ``--thickness`` thick (a
fraction of the body's bounding-box diagonal), made before the step to frame FRAME.

Writes into OUT (one run, as ``jaxcga fem``: empty unless ``force``, filled when the run ends, ``summary.json``
last):

* without ``--cut``: ``frames.npy``, (N+1, s, 3) float64, the model's surface (its welded vertices, in the order
  ``deform.load_model(CHARACTER, weld=True)`` gives them) at every frame k = 0..N (time ``times[k]`` of
  summary.json), and ``faces.npy``, (f, 3) int64, its triangles;
* with ``--cut``: ``frames.npz`` (``np.load``, no pickle), one group of arrays per segment K (segment 0 from frame
  0, then one from each cut frame on; the cuts of one frame start one segment): ``frames_K`` (n_K, s_K, 3) float64
  the surface at frames ``first[K]`` .. ``first[K] + n_K - 1``, ``faces_K`` (f_K, 3) int64 its triangles,
  ``piece_K`` (f_K,) int64 the connected piece of each triangle and ``vertex_K`` (s_K,) int64 the model's vertex
  that each row copies (a triangle across a cut gets its own copies of the corners on the other side); and
  ``first`` (segments,) int64, ``times`` (N+1,) float64;
* ``view.html``: the viewer page (``deform.view``) playing the frames at the run's frame rate; with ``--cut``, each
  connected piece in its own colour;
* ``summary.json``: the run's settings, the body (tets, nodes, DOFs, driven and anchor nodes, the
  tetrahedralization's time and quality), steps, the seconds of each stage (the rig, the cuts' pieces, each
  segment's frames, compilation included), the compilation within the frames (``compile_s``, JAX's compile events)
  and ``step_avg_s``, the time per step without it; the pieces per frame, the segments' DOFs and pieces, the Newton
  iterations and converged steps.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
from pathlib import Path
from typing import Any

from jaxcga_cli import arguments

HELP = (
    "play a rigged character's clip with simulated flesh that lags and jiggles about the skinned rig, cut it by "
    "planes mid-clip (a severed limb falls), and write its surface per frame, a viewer page and timings"
)
EXAMPLE = "jaxcga physics tests/data/CesiumMan.glb --seconds 0.6 --cut 8 0.2 1 0 1 0 0 --out out/physics_cut"
RUN_FILES = re.compile(r"frames\.npy|frames\.npz|faces\.npy|view\.html|summary\.json")
RUN_DESCRIBED = "frames.npy, frames.npz, faces.npy, view.html and summary.json"
YOUNG, POISSON, DENSITY, THICKNESS, FPS = 1e5, 0.4, 1000.0, 1e-3, 30.0
# backward Euler is stable at any step: a rate above this only multiplies the steps (and the frames kept)
MAX_FPS = 10_000.0
GRAVITY = (0.0, -9.81, 0.0)
REFINE = 1e-3  # xfem.character_body's default tolerance


def add_arguments(parser) -> None:
    parser.add_argument("character", metavar="CHARACTER", help="a rigged glTF (.glb, .gltf) with a clip")
    arguments.clip_argument(parser)
    parser.add_argument("--seconds", type=float, default=None, help="seconds to simulate (default: the clip's length)")
    parser.add_argument(
        "--fps",
        type=float,
        default=FPS,
        help=f"frames per second: the time step 1/fps (default {FPS:g}, at most {MAX_FPS:g}; every frame is kept)",
    )
    parser.add_argument(
        "--young", type=float, default=YOUNG, help=f"Young's modulus of the flesh, Pa (default {YOUNG:g})"
    )
    parser.add_argument("--poisson", type=float, default=POISSON, help=f"Poisson's ratio (default {POISSON:g})")
    parser.add_argument(
        "--damping",
        type=float,
        default=None,
        help="Rayleigh stiffness damping beta, seconds (default none: backward Euler's own damping only)",
    )
    parser.add_argument(
        "--density", type=float, default=DENSITY, help=f"mass density, kg/m^3 (default {DENSITY:g}: water)"
    )
    parser.add_argument(
        "--gravity",
        type=float,
        nargs=3,
        default=GRAVITY,
        metavar=("GX", "GY", "GZ"),
        help="gravitational acceleration in the model's units (default 0 -9.81 0: metres, glTF's up +y)",
    )
    arguments.ftetwild_arguments(parser, "the body's tets")
    parser.add_argument(
        "--refine",
        type=float,
        default=REFINE,
        metavar="T",
        help="refine the tets until the embedded surface is within T diagonals of the directly skinned one at probe "
        f"poses (xfem.character_body's tolerance; default {REFINE:g}; 0: the tets as fTetWild makes them)",
    )
    parser.add_argument(
        "--core",
        type=float,
        default=0.5,
        help="the skeleton drives the nodes within this fraction of the limb's radius about each bone (default 0.5)",
    )
    parser.add_argument("--method", choices=arguments.METHODS, default="cga", help=arguments.METHODS_HELP)
    arguments.interpolation_argument(parser)
    parser.add_argument(
        "--cut",
        type=float,
        nargs=7,
        action="append",
        default=[],
        metavar=("FRAME", "PX", "PY", "PZ", "NX", "NY", "NZ"),
        help="cut the body by the plane through point P with normal N (rest pose, world coordinates) before the "
        "step to frame FRAME (1..N); repeat for several cuts",
    )
    parser.add_argument(
        "--thickness",
        type=float,
        default=THICKNESS,
        help=f"each cut's slab thickness, a fraction of the body's bounding-box diagonal (default {THICKNESS:g})",
    )
    steps = parser.add_mutually_exclusive_group()
    steps.add_argument(
        "--tolerance",
        type=float,
        default=None,
        help="stop a step's Newton iterations once an update is below this fraction of the body's size (default: "
        "the library's, converged steps)",
    )
    steps.add_argument(
        "--paper-step",
        action="store_true",
        help="one Newton iteration per step, as the XFEM paper (faster; its gradient is approximate)",
    )
    parser.add_argument(
        "--newton",
        type=int,
        default=None,
        help="the most Newton iterations of a step (default: simulate_character's, 100); a step that stops there is "
        "counted as not converged in summary.json",
    )
    parser.add_argument(
        "--reduced",
        type=int,
        default=None,
        metavar="K",
        help="play in the reduced mode: the body's K lowest skinning eigenmodes (xfem.character_subspace, the "
        "reduction of Fast Complementary Dynamics), one K x K solve per frame; no --cut, --tolerance, --newton or "
        "--paper-step",
    )
    parser.add_argument("--force", action="store_true", help=RUN_DESCRIBED.join(("replace the run in OUT (its ", ")")))
    parser.add_argument(
        "--out", type=Path, required=True, help="folder for frames.npy or frames.npz, view.html and summary.json"
    )


def check_settings(
    *,
    seconds: float | None,
    fps: float,
    young: float,
    poisson: float,
    damping: float | None,
    density: float,
    gravity,
    edge_length: float,
    epsilon: float,
    refine: float,
    core: float,
    cuts,
    thickness: float,
    tolerance: float | None,
) -> list[tuple[int, tuple[float, ...], tuple[float, ...]]]:
    """Every setting checked before anything is loaded (``ValueError`` naming the option); returns the cuts as
    (frame, point, unit normal). Cut frames are checked against the run's frames when ``seconds`` is given
    (otherwise once the clip's length is known, ``check_cut_frames``)."""

    def positive(name: str, value: float, what: str) -> None:
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"{name}: expected {what}, got {value!r}")

    positive("fps", fps, "a positive frame rate")
    if fps > MAX_FPS:
        raise ValueError(
            f"fps: {fps:g} frames per second is above {MAX_FPS:g}; backward Euler is stable at any step, and every "
            "frame is kept in memory: give a lower --fps"
        )
    if seconds is not None:
        positive("seconds", seconds, "a positive duration in seconds")
        if round(seconds * fps) < 1:
            raise ValueError(f"seconds: {seconds} s at {fps} frames per second is no step; give more seconds")
    positive("young", young, "a positive Young's modulus (Pa)")
    if not -1 < poisson < 0.5:
        raise ValueError(f"poisson: expected a Poisson's ratio in (-1, 0.5), got {poisson!r}")
    if damping is not None and not (math.isfinite(damping) and damping >= 0):
        raise ValueError(f"damping: expected a damping >= 0 (seconds), got {damping!r}")
    positive("density", density, "a positive density")
    if len(gravity) != 3 or not all(math.isfinite(g) for g in gravity):
        raise ValueError(f"gravity: expected three finite numbers GX GY GZ, got {gravity!r}")
    if not 0 < edge_length < 1:
        raise ValueError(f"edge_length: expected a fraction of the diagonal in (0, 1), got {edge_length!r}")
    if not 0 < epsilon < 1:
        raise ValueError(f"epsilon: expected a fraction of the diagonal in (0, 1), got {epsilon!r}")
    if not 0 <= refine < 1:
        raise ValueError(f"refine: expected a fraction of the diagonal in [0, 1) (0: no refinement), got {refine!r}")
    if not 0 < core <= 1:
        raise ValueError(f"core: expected a fraction in (0, 1], got {core!r}")
    if not 0 < thickness < 1:
        raise ValueError(f"thickness: expected a fraction of the diagonal in (0, 1), got {thickness!r}")
    if tolerance is not None:
        positive("tolerance", tolerance, "a positive fraction of the body's size")
    planes = []
    for k, cut in enumerate(cuts):
        values = [float(v) for v in cut]
        if len(values) != 7 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"cut {k + 1}: expected FRAME PX PY PZ NX NY NZ, seven finite numbers, got {cut!r}")
        frame, point, normal = values[0], tuple(values[1:4]), tuple(values[4:])
        if frame != int(frame) or frame < 1:
            raise ValueError(f"cut {k + 1}: FRAME must be a whole frame number >= 1, got {cut[0]!r}")
        length = math.sqrt(sum(n * n for n in normal))
        if not length > 0:
            raise ValueError(f"cut {k + 1}: the normal NX NY NZ is zero; give the plane's normal direction")
        planes.append((int(frame), point, tuple(n / length for n in normal)))
    if seconds is not None:
        check_cut_frames(planes, round(seconds * fps))
    return planes


def check_cut_frames(planes, steps: int) -> None:
    """Each cut's frame lies in the run's 1..``steps``."""
    for k, (frame, _, _) in enumerate(planes):
        if frame > steps:
            raise ValueError(f"cut {k + 1}: frame {frame} is past the run's last frame {steps}; give 1..{steps}")


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_input, check_run_folder

    character = check_input(args.character, "CHARACTER")
    if character.suffix.lower() not in (".glb", ".gltf"):
        raise ValueError(f"CHARACTER: expected a rigged glTF (.glb, .gltf), got {character}")
    check_settings(**_settings(args))
    check_run_folder(args.out, RUN_FILES, args.force, RUN_DESCRIBED, inputs={"CHARACTER": character})


def _settings(args) -> dict:
    return {
        "seconds": args.seconds,
        "fps": args.fps,
        "young": args.young,
        "poisson": args.poisson,
        "damping": args.damping,
        "density": args.density,
        "gravity": tuple(args.gravity),
        "edge_length": args.edge_length,
        "epsilon": args.epsilon,
        "refine": args.refine,
        "core": args.core,
        "cuts": args.cut,
        "thickness": args.thickness,
        "tolerance": args.tolerance,
    }


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.fem import rounded

    summary = physics_command(
        args.character,
        args.out,
        clip=args.clip,
        method=args.method,
        interpolation=args.interpolation,
        paper_step=args.paper_step,
        newton=args.newton,
        reduced=args.reduced,
        force=args.force,
        **_settings(args),
    )
    shown = {k: summary[k] for k in ("clip", "tets", "nodes", "driven_nodes", "steps", "step_avg_s", "pieces")}
    shown |= {
        "converged": f"{summary['converged_steps']}/{summary['steps']}",
        "tet_s": summary["tetrahedralization"]["seconds"],
        "min_dihedral_deg": summary["tetrahedralization"]["min_dihedral_deg"],
    }
    return Path(args.character).name, rounded(shown) | {"out": args.out}


def _rest_box(body) -> str:
    import numpy as np

    lo, hi = np.asarray(body.surface).min(0), np.asarray(body.surface).max(0)
    return ", ".join(f"{a} [{lo[i]:.4g}, {hi[i]:.4g}]" for i, a in enumerate("xyz"))


def physics_command(
    character: str | Path,
    out: Path,
    *,
    clip: int | str = 0,
    seconds: float | None = None,
    fps: float = FPS,
    young: float = YOUNG,
    poisson: float = POISSON,
    damping: float | None = None,
    density: float = DENSITY,
    gravity=GRAVITY,
    edge_length: float = 0.05,
    epsilon: float = 1e-3,
    refine: float = REFINE,
    core: float = 0.5,
    method: str = "cga",
    interpolation: str = "gltf",
    cuts=(),
    thickness: float = THICKNESS,
    tolerance: float | None = None,
    paper_step: bool = False,
    newton: int | None = None,
    reduced: int | None = None,
    force: bool = False,
) -> dict:
    """Simulate ``character`` playing ``clip`` and write the run into ``out`` (module docstring); returns the
    summary. ``cuts``: (FRAME, PX, PY, PZ, NX, NY, NZ) rows; ``thickness``, ``edge_length``, ``epsilon``: fractions
    of the bounding-box diagonal, and ``refine`` (``xfem.character_body``'s tolerance; 0: no refinement);
    ``tolerance``: None (the library's converged steps) or a fraction of the body's size; ``paper_step``: one Newton
    iteration per step instead; ``newton``: None (the library's cap) or the most Newton iterations of a step;
    ``reduced``: None (the full space) or the modes K of the reduced mode; the rest as ``xfem.character_body`` and
    ``xfem.simulate_character``."""
    import jax
    import numpy as np

    import deform
    import xfem
    from _jaxcga_shared.output import check_input, check_run_folder, run_folder, write_json
    from jaxcga_cli.models import load_model
    from jaxcga_cli.report import status

    planes = check_settings(
        seconds=seconds,
        fps=fps,
        young=young,
        poisson=poisson,
        damping=damping,
        density=density,
        gravity=gravity,
        edge_length=edge_length,
        epsilon=epsilon,
        refine=refine,
        core=core,
        cuts=cuts,
        thickness=thickness,
        tolerance=tolerance,
    )
    if method not in deform.METHODS:
        raise ValueError(f"method: expected one of {deform.METHODS}, got {method!r}")
    if paper_step and tolerance is not None:
        raise ValueError("tolerance: the paper's step makes one Newton iteration; give --tolerance or --paper-step")
    if newton is not None and (isinstance(newton, bool) or not isinstance(newton, int) or newton < 1):
        raise ValueError(f"newton: expected an int >= 1, got {newton!r}")
    if paper_step and newton is not None:
        raise ValueError("newton: the paper's step makes one Newton iteration; give --newton or --paper-step")
    if reduced is not None:
        if isinstance(reduced, bool) or not isinstance(reduced, int) or reduced < 1:
            raise ValueError(f"reduced: expected a number of modes K >= 1, got {reduced!r}")
        if planes:
            raise ValueError("reduced: the reduced mode does not cut; give --reduced or --cut")
        if paper_step or tolerance is not None or newton is not None:
            raise ValueError("reduced: the reduced mode makes one linear solve per frame, no Newton iterations; "
                             "give --reduced or --tolerance, --newton, --paper-step")  # fmt: skip
    character = check_input(character, "CHARACTER")
    out = check_run_folder(out, RUN_FILES, force, RUN_DESCRIBED, inputs={"CHARACTER": character})

    with status("physics", f"loading {character.name}"):
        model = load_model(character, weld=True)
    if not model.clips:
        raise ValueError(f"CHARACTER: {character.name} has no animation clip to play")
    names = [c.name for c in model.clips]
    if clip not in names and not (isinstance(clip, int) and 0 <= clip < len(names)):
        raise ValueError(f"clip: {character.name} has no clip {clip!r}; its {len(names)} clips are {names}")
    played = model.clip(clip)
    length = played.end - played.start
    if seconds is None:
        if not length > 0:
            raise ValueError(f"seconds: the clip {played.name!r} lasts no time; give --seconds")
        seconds = length
    steps = round(seconds * fps)
    if steps < 1:
        raise ValueError(f"seconds: {seconds} s at {fps} frames per second is no step; give more seconds")
    check_cut_frames(planes, steps)
    try:  # a rig the method cannot pose (a non-uniform bone scale has no versor) is refused before the meshing
        deform.sample_pose(model, played.start, method, clip, interpolation)
    except ValueError:
        if method in ("lbs", "dqs"):
            raise
        deform.sample_pose(model, played.start, "lbs", clip, interpolation)  # the matrix path: the rig is fine
        raise ValueError(
            f"method: {method} cannot pose the rig of {character.name}: it has no versor form (a non-uniform or "
            "non-positive bone scale); give --method lbs or dqs"
        ) from None

    with status(
        "physics",
        f"tetrahedralizing (fTetWild), rigging{' and refining' if refine else ''} the body of "
        f"{len(model.mesh.V)} vertices",
    ):
        body = xfem.character_body(
            model,
            density=density,
            gravity=gravity,
            edge_length=edge_length,
            epsilon=epsilon,
            core=core,
            tolerance=refine or REFINE,
            refine=bool(refine),
        )
    X = np.asarray(body.tets.X)
    plane_cuts = []
    for k, (frame, point, normal) in enumerate(planes):
        side = (X - np.asarray(point)) @ np.asarray(normal)
        if side.min() >= 0 or side.max() <= 0:
            raise ValueError(
                f"cut {k + 1}: the plane through {list(point)} with normal {list(normal)} misses the body, whose "
                f"rest-pose bounding box is {_rest_box(body)} (world coordinates, up +y)"
            )
        plane_cuts.append((frame, np.asarray(point), np.asarray(normal), thickness * body.diagonal))
    material = xfem.Material(young, poisson, damping=damping)
    # simulate_character's stepping keywords: Newton's cap and tolerance, or the reduced mode's subspace
    stepping: dict[str, Any] = {"newton_iterations": 1, "tolerance": None} if paper_step else {}
    if tolerance is not None:
        stepping["tolerance"] = tolerance
    if newton is not None:
        stepping["newton_iterations"] = newton

    if reduced is not None:
        with status("physics", f"the body's {reduced} lowest skinning eigenmodes"):
            try:
                stepping = {"subspace": xfem.character_subspace(body, reduced, poisson=poisson)}
            except ValueError as error:  # it names its argument "modes"
                raise ValueError(f"reduced: {str(error).removeprefix('modes: ')}") from None

    with Timeline(steps, character.name, len(planes), reduced is not None) as timeline:
        motion = xfem.simulate_character(
            body,
            clip,
            seconds,
            fps,
            material=material,
            method=method,
            interpolation=interpolation,
            plane_cuts=plane_cuts,
            progress=timeline.progress,
            **stepping,
        )
    segments = motion.segments
    surfaces = [np.asarray(s.surface, np.float64) for s in segments]
    if any(not np.all(np.isfinite(s)) for s in surfaces):
        raise RuntimeError("physics: non-finite positions; try a stiffer --young, a higher --fps or --damping")
    pieces = np.asarray(motion.pieces_per_frame, np.int64)
    # the steps' statistics (segment 0's frame 0 is the start, no step)
    stats = [
        jax.tree.map(lambda a, k=k: np.asarray(a)[1 if k == 0 else 0 :], s.states.stats) for k, s in enumerate(segments)
    ]
    converged = int(sum(st.converged.sum() for st in stats))
    iterations = np.concatenate([st.iterations.ravel() for st in stats])
    title = f"{character.name}: {played.name}, {seconds:.3g} s at {fps:g} fps" + (
        f", {len(planes)} cut{'s' if len(planes) > 1 else ''}" if planes else ""
    )
    with status("physics", "writing the frames and the viewer page"):
        if planes:
            frames = [
                (V, np.asarray(seg.faces), np.asarray(seg.piece)) for seg, S in zip(segments, surfaces) for V in S
            ]
            page = _view(frames, fps, title)
        else:
            page = _view((surfaces[0], np.asarray(segments[0].faces)), fps, title)

    tetrahedralization = {
        **body.quality._asdict(),
        "seconds": body.seconds,
        "edge_length": edge_length,
        "refine": refine,
        "epsilon": epsilon,
        "surface_vertices": int(len(body.surface)),
        "surface_faces": int(len(body.faces)),
        "max_surface_distance": float(np.asarray(body.embedding.distance).max()) / body.diagonal,
    }
    summary = {
        "character": str(character),
        "clip": played.name,
        "seconds": seconds,
        "fps": fps,
        "frames": steps + 1,
        "steps": steps,
        "times": np.asarray(motion.times, np.float64).tolist(),
        "method": method,
        "interpolation": interpolation,
        "young": young,
        "poisson": poisson,
        "damping": damping,
        "density": density,
        "gravity": list(gravity),
        "core": core,
        "paper_step": paper_step,
        "newton": newton,
        "reduced": reduced,
        "subspace_s": stepping["subspace"].seconds if reduced is not None else None,
        "tolerance": tolerance,
        "cuts": [
            {"frame": f, "point": list(p), "normal": list(n), "thickness": thickness * body.diagonal}
            for f, p, n in planes
        ],
        "diagonal": body.diagonal,
        "tets": int(body.tets.n_elements),
        "nodes": int(body.tets.n_nodes),
        "dofs": 3 * int(body.tets.n_nodes),
        "driven_nodes": int(len(body.driven)),
        "anchor_nodes": int(len(body.anchors)),
        "free_dofs": 3 * (int(body.tets.n_nodes) - int(len(body.driven))),
        "segments": [
            {
                "first": int(seg.first),
                "frames": int(len(S)),
                "dofs": 3 * int(np.asarray(seg.driven).shape[0]),
                "driven_dofs": 3 * int(np.asarray(seg.driven).sum()),
                "pieces": int(seg.pieces),
                # the pieces with no DOF on the rig: released, they fall
                "released": [int(k) for k in range(seg.pieces) if not np.asarray(seg.driven)[seg.dof_piece == k].any()],
                "surface_vertices": int(S.shape[1]),
                "surface_faces": int(len(seg.faces)),
            }
            for seg, S in zip(segments, surfaces)
        ],
        "pieces": int(pieces[-1]),
        "pieces_per_frame": pieces.tolist(),
        **timeline.summary(),
        "converged_steps": converged,
        "newton_iterations_mean": float(iterations.mean()) if iterations.size else 0.0,
        "newton_iterations_max": int(iterations.max()) if iterations.size else 0,
        "frames_file": "frames.npz" if planes else "frames.npy",
        "tetrahedralization": tetrahedralization,
    }
    with run_folder(out, RUN_FILES, "summary.json") as staging:
        if planes:
            arrays = {"first": np.asarray([s.first for s in segments], np.int64), "times": np.asarray(motion.times)}
            for k, (seg, S) in enumerate(zip(segments, surfaces)):
                arrays |= {
                    f"frames_{k}": S,
                    f"faces_{k}": np.asarray(seg.faces, np.int64),
                    f"piece_{k}": np.asarray(seg.piece, np.int64),
                    f"vertex_{k}": np.asarray(seg.vertex, np.int64),
                }
            with open(staging / "frames.npz", "wb") as file:
                np.savez(file, **arrays)
        else:
            np.save(staging / "frames.npy", surfaces[0])
            np.save(staging / "faces.npy", np.asarray(segments[0].faces, np.int64))
        page.save(staging / "view.html")
        write_json(staging / "summary.json", summary)
    return summary


class Timeline:
    """What ``simulate_character`` reports as it works (its ``progress`` stages: the rig skinned, the cuts' pieces
    found, each segment's frames; in the reduced mode the rig and the frames are one compiled play, reported as the
    rig), as status lines and a bar over the frames, with the seconds of each stage and the compilation within
    them: JAX's compile events, listened to during the run only (``jax.monitoring``)."""

    _COMPILE = "/jax/core/compile/"

    def __init__(self, steps: int, name: str, cuts: int, reduced: bool):
        self.steps, self.name, self.cuts, self.reduced = steps, name, cuts, reduced
        self.compile_s, self.marks, self.bar = 0.0, {}, None
        self.segments: list[tuple[float, float]] = []  # (seconds, compilation) of each segment's frames

    def _listen(self, event: str, duration_secs: float, **_: str | int) -> None:
        if event.startswith(self._COMPILE):
            self.compile_s += duration_secs

    def __enter__(self) -> "Timeline":
        import time

        import jax.monitoring

        from jaxcga_cli.report import say

        jax.monitoring.register_event_duration_secs_listener(self._listen)
        say("physics", self._first())
        self.start = self.last = time.perf_counter()
        self.compiled = 0.0
        return self

    def _first(self) -> str:
        if self.reduced:
            return "playing the frames in the reduced mode (the rig, then one compiled scan) ..."
        return "skinning the rig at every frame ..."

    def __exit__(self, *exc) -> None:
        import jax.monitoring

        jax.monitoring.unregister_event_duration_listener(self._listen)
        if self.bar is not None:
            self.bar.close()

    def _bar(self):
        from tqdm import tqdm

        if self.bar is None:
            self.bar = tqdm(total=self.steps, desc=f"physics {self.name}", unit="frame", file=sys.stderr)
        return self.bar

    def progress(self, stage: str, done: int, total: int) -> None:
        import time

        from jaxcga_cli.report import say

        now = time.perf_counter()
        seconds, compiled = now - self.last, self.compile_s - self.compiled
        self.last, self.compiled = now, self.compile_s
        if self.reduced and stage == "rig":  # the whole play
            self.segments.append((seconds, compiled))
            say("physics", f"{self._first().removesuffix(' ...')}: done in {seconds:.1f} s")
        elif stage == "frames":
            if not self.reduced:
                self.segments.append((seconds, compiled))
            self._bar().update(done - self._bar().n)
        elif stage == "rig":
            self.marks[stage] = seconds
            say("physics", f"{self._first().removesuffix(' ...')}: done in {seconds:.1f} s")
            say("physics", "finding the pieces of the cuts ..." if self.cuts else "building the body's system ...")
        elif stage == "cuts":
            self.marks[stage] = seconds
            say("physics", f"{'the pieces of the cuts' if self.cuts else 'the system'}: done in {seconds:.1f} s")
            say("physics", "stepping (each segment's first call compiles its step) ...")
            self._bar()

    def summary(self) -> dict:
        """The seconds of the stages; the steps' average with the compilation in the segments left out."""
        frames_s = sum(s for s, _ in self.segments)
        compile_s = sum(c for _, c in self.segments)
        return {
            "rig_s": None if self.reduced else self.marks.get("rig", 0.0),  # reduced: in the frames' seconds
            "cuts_s": None if self.reduced else self.marks.get("cuts", 0.0),
            "frames_s": frames_s,  # compilation included
            "compile_s": compile_s,  # of the frames' steps (JAX's compile events)
            "step_avg_s": max(frames_s - compile_s, 0.0) / self.steps,
            "segment_seconds": [s for s, _ in self.segments],
            "total_s": self.last - self.start,
        }


def _view(item, fps: float, title: str):
    import deform

    return deform.view(item, fps=fps, title=title)
