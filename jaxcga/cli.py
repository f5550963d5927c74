"""Command-line entry point ``jaxcga``.

The application layer: the only module allowed to import the other packages (lazily, per
subcommand). ``jaxcga demo`` runs the main job on the built-in default.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import math
import re
import sys
import warnings
from pathlib import Path

from jaxcga._output import check_distinct, check_folder, check_input, check_output, check_run_folder, save_figure


def _triangle_keyframes():
    """A triangle and two similitude keyframes (rotation + translation + scaling), as in Fig. 1 of
    the cut/tear/drill paper."""
    import jax.numpy as jnp

    import jaxcga as cga

    triangle = jnp.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.3, 0.8, 0.0]])
    bottom = cga.similitude(cga.rotor(jnp.array([0.0, 0.0, 1.0]), 0.0), jnp.zeros(3), 1.0)
    top = cga.similitude(cga.rotor(jnp.array([1.0, 1.0, 0.0]), 2.2), jnp.array([1.5, 0.5, 2.5]), 2.0)
    return triangle, bottom, top


def blending_figure(path: Path, steps: int = 8) -> Path:
    """Save the linear-versus-logarithmic blending figure (cf. the paper's Fig. 1) to ``path``."""
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    import jaxcga as cga

    triangle, bottom, top = _triangle_keyframes()
    alphas = jnp.linspace(0.0, 1.0, steps)[:, None]
    # Batched over alphas: one versor per frame, applied to the three vertices.
    linear = cga.apply_to_points(cga.blend_linear(bottom, top, alphas[:, 0])[:, None], triangle)
    logarithmic = cga.apply_to_points(cga.blend_log(bottom, top, alphas[:, 0])[:, None], triangle)

    fig = plt.figure(figsize=(13, 4.5))
    panels = [("(a) linear", [(linear, "tab:blue")]), ("(b) logarithmic", [(logarithmic, "tab:red")]),
              ("(c) superimposed", [(linear, "tab:blue"), (logarithmic, "tab:red")])]
    for k, (title, series) in enumerate(panels):
        ax = fig.add_subplot(1, 3, k + 1, projection="3d")
        for frames, color in series:
            for i, tri in enumerate(frames):
                closed = jnp.concatenate([tri, tri[:1]])
                ax.plot(*closed.T, color=color, alpha=0.35 + 0.65 * i / (len(frames) - 1))
        ax.set_title(title)
        ax.set_box_aspect((1, 1, 1))
    fig.suptitle("Blending similitude keyframes (rotation, translation, dilation)")
    return save_figure(fig, path, dpi=110, bbox_inches="tight")


def demo(out: Path, steps: int, figure: bool) -> int:
    """A short tour of the kernel: prints what it computes and saves a figure."""
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", True)
    import jaxcga as cga

    print("jaxcga demo: the CGA kernel G(4,1) in the null basis {e1, e2, e3, eo, einf}")
    pts = cga.up(jnp.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]]))
    a, b, c, d = (cga.Multivector(pts.values[i], pts.blades) for i in range(4))
    print(f"  distance |a - b| from -2 A.B          : {float(cga.distance(a, b)):.6f}  (sqrt 5 = {5 ** 0.5:.6f})")
    center, radius = cga.sphere_center_radius(cga.sphere_through(a, b, c, d))
    print(f"  sphere through 4 points (a^b^c^d)      : center {center.round(6).tolist()}, radius {float(radius):.6f}")
    circle = cga.meet(cga.sphere_through(a, b, c, d), cga.plane_through(a, b, d))
    cc, cr, cn = cga.circle_center_radius_normal(circle)
    print(f"  sphere meet plane (a circle)           : center {cc.round(6).tolist()}, radius {float(cr):.6f}")
    m = cga.motor(cga.rotor(jnp.array([0.0, 0.0, 1.0]), jnp.pi / 2), jnp.array([1.0, 0.0, 0.0]))
    moved = cga.apply_to_points(m, jnp.array([1.0, 0, 0])).round(6).tolist()
    print(f"  motor (90 deg about z, then +x) on a   : {moved}")
    gen = cga.log(m)
    print(f"  log of that motor (screw generator)    : {dict(zip(gen.names, gen.values.round(6).tolist()))}")
    print(f"  exp(log(M)) - M, max abs               : {float(jnp.max(jnp.abs(cga.exp(gen).values - m.values))):.2e}")
    s = cga.similitude(cga.rotor(jnp.array([1.0, 0.0, 0.0]), 0.4), jnp.array([0.0, 1.0, 0.0]), 2.0)
    _, r2 = cga.sphere_center_radius(s >> cga.sphere(jnp.zeros(3), 1.0))
    print(f"  similitude (scale 2) on a unit sphere  : radius {float(r2):.6f}")
    if figure:
        path = blending_figure(out / "blending.png", steps)
        print(f"  figure: linear vs logarithmic blending -> {path}")

    from deform import _commands, _pose

    arm = _commands.load_or_default(None)
    print(f"\nThe built-in rigged arm: {arm.mesh.num_vertices} vertices, bones {list(arm.skeleton.names)}, "
          f"clip {arm.clips[0].name!r} ({arm.clips[0].end:.1f} s)")
    frames = jax.vmap(lambda t: _pose.skin_model(arm, t, "cga"))(jnp.linspace(0.0, arm.clips[0].end, 9))
    reach = jnp.linalg.norm(frames, axis=-1).max(axis=-1)
    print(f"  eq. (17) skinning of 9 frames (vmap)    : reach {reach.min():.3f} .. {reach.max():.3f} m")
    summary = _commands.animate_command(arm, 30, out / "arm_animated.glb")
    print(f"  clip re-sampled through log blending   : {summary['frames']} frames -> {summary['out']}")
    if figure:
        path = _commands.skinning_figure(arm, out / "arm.png")
        print(f"  figure: the arm along its clip         -> {path}")

    import time

    import cutting

    normal = jnp.array([1.0, 0.15, 0.0])
    plane = cutting.Plane(normal, float(jnp.median(arm.mesh.V @ normal)))
    start = time.perf_counter()
    upper, lower = cutting.cut(arm.mesh, plane, cap=True)
    took = 1e3 * (time.perf_counter() - start)
    print(f"\nCut (Algorithm 1, capped) across the forearm: halves of {upper.F.shape[0]} and {lower.F.shape[0]} "
          f"faces in {took:.1f} ms")
    if figure:
        path = _cut_figure(arm, upper, lower, out / "arm_cut.png")
        print(f"  figure: before / after the cut, posed again -> {path}")
    from cutting import _commands as _cutting_commands

    scalpels = [[[0.2, 0.0, 0.1], [0.2, 0.0, 0.0]], [[0.3, 0.0, 0.1], [0.3, 0.0, 0.0]]]
    start = time.perf_counter()
    summary = _cutting_commands.tear_command(arm, scalpels, out / "arm_torn.glb", opening=0.005)
    print(f"Tear (Algorithm 2) along the upper arm: {summary['tear_points']} tear points, opened by 5 mm, in "
          f"{1e3 * (time.perf_counter() - start):.1f} ms with the file -> {summary['out']}")
    start = time.perf_counter()
    summary = _cutting_commands.drill_command(arm, [0.4, 0.0, 0.0], [0.4, 0.0, 0.1], 0.015, out / "arm_drilled.glb")
    print(f"Drill (Algorithm 3) of radius 15 mm into the forearm: {summary['hole_points']} points around the hole, "
          f"in {1e3 * (time.perf_counter() - start):.1f} ms with the file -> {summary['out']}")

    from deform import _deform_commands

    V, F = _deform_commands.load_mesh(None)
    print("\nMotor deformations (the deformation paper): the same 120 degree twist of a 4x4x4 lattice")
    for positional in (True, False):
        out_file = out / ("arm_ffd_classic" if positional else "arm_ffd_motor")
        summary = _deform_commands.deform_command("ffd", V, F, out_file.with_suffix(".png" if figure else ".npy"),
                                                  bend=0.0, twist=120.0, positional=positional)
        print(f"  {'classic FFD (eq. 6)' if positional else 'motor FFD (eq. 7-8)':22s}: volume ratio "
              f"{summary['volume_ratio']:.4f}, mean edge change {summary['mean_edge_change']:.4f}, "
              f"{summary['frame_ms']:.2f} ms per frame -> {summary['out']}")
    return 0


def _cut_figure(arm, upper, lower, path: Path) -> Path:
    """The arm at t = 0 before the cut, and both halves posed again at t = 1.2 s after it."""
    import jax.numpy as jnp
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deform import _pose
    from deform._model import RiggedModel

    fig = plt.figure(figsize=(10, 4.5))
    halves = [(RiggedModel(upper, arm.skeleton, arm.clips), 1.2, "tab:blue"),
              (RiggedModel(lower, arm.skeleton, arm.clips), 1.2, "tab:red")]
    panels = [("before the cut (t = 0 s)", [(arm, 0.0, "tab:gray")]), ("after: both halves posed at t = 1.2 s", halves)]
    for k, (title, parts) in enumerate(panels):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        everything = []
        for model, t, color in parts:
            V = _pose.skin_model(model, t, "cga")
            everything.append(V)
            ax.plot_trisurf(V[:, 0], V[:, 1], V[:, 2], triangles=model.mesh.F, color=color, alpha=0.6, linewidth=0)
        V = jnp.concatenate(everything)
        center, half = (V.max(axis=0) + V.min(axis=0)) / 2, float((V.max(axis=0) - V.min(axis=0)).max()) / 2
        ax.set(xlim=(center[0] - half, center[0] + half), ylim=(center[1] - half, center[1] + half),
               zlim=(center[2] - half, center[2] + half), title=title)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=20, azim=-60)
    return save_figure(fig, path, dpi=100, bbox_inches="tight")


def _x64():
    import jax

    jax.config.update("jax_enable_x64", True)


def _model_argument(p):
    p.add_argument("model", nargs="?", default=None,
                   help="glTF (.gltf/.glb), or FBX/COLLADA through assimp; default: the built-in arm")
    p.add_argument("--weld", action="store_true", help="weld split vertices of the loaded model")


def _run_deformation(args) -> int:
    from deform import _deform_commands

    V, F = _deform_commands.load_mesh(args.mesh)
    summary = _deform_commands.deform_command(
        args.method, V, F, args.out, bend=args.bend, twist=args.twist, translate=args.translate, basis=args.basis,
        keys=args.keys, weights=args.weights, handle_fraction=args.handle_fraction, handles=args.handles,
        lattice=args.lattice, cage=args.cage, positional=args.positional)
    print(f"jaxcga deform {args.method} {args.mesh or 'built-in arm'}: "
          + ", ".join(f"{k} {v}" for k, v in summary.items()))
    return 0


def _run_arap(args) -> int:
    from deform import _arap_commands, _deform_commands

    V, F = _deform_commands.load_mesh(args.mesh)
    summary = _arap_commands.arap_command(
        V, F, args.out, handles=args.handles, iterations=args.iters, tolerance=args.tolerance, bend=args.bend,
        twist=args.twist, translate=args.translate, handle_fraction=args.handle_fraction, energy=args.energy)
    print(f"jaxcga arap {args.mesh or 'built-in arm'}: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    return 0


def _run_fem(args) -> int:
    from xfem import _fem_commands

    summary = _fem_commands.fem_command(
        args.scene, args.steps, args.out, h=args.dt, young=args.young, poisson=args.poisson, density=args.density,
        gravity=tuple(args.gravity), newton_iterations=args.newton, every=args.every, fix_fraction=args.fix_fraction,
        figures=not args.no_figures, force=args.force)
    shown = {k: summary[k] for k in ("nodes", "dofs", "elements", "steps", "step_avg_s", "step_max_s",
                                     "max_displacement")}
    print(f"jaxcga fem {args.scene}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                   for k, v in shown.items()) + f", out {args.out}")
    return 0


def _run_xfem(args) -> int:
    from xfem import _xfem_commands

    summary = _xfem_commands.xfem_command(args.scene, args.out, args.steps, size=args.size, every=args.every,
                                          figures=not args.no_figures, cut_latency=args.cut_latency, force=args.force)
    shown = {k: summary[k] for k in ("size", "nodes", "dofs", "pieces", "frames", "cuts", "booleans", "boolean_ms",
                                     "integral_ms", "step_avg_s", "step_max_s", "total_s")}
    print(f"jaxcga xfem {args.scene}: " + ", ".join(f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}"
                                                    for k, v in shown.items()) + f", out {args.out}")
    return 0


def _run_deform(args) -> int:
    _x64()
    if args.command == "fem":
        return _run_fem(args)
    if args.command == "xfem":
        return _run_xfem(args)
    if args.command == "deform":
        return _run_deformation(args)
    if args.command == "arap":
        return _run_arap(args)
    from deform import _commands

    # tear and drill walk across faces: split vertices along UV seams are always welded for them
    model = _commands.load_or_default(args.model, weld=args.weld or args.command in ("tear", "drill"))
    if args.command == "tear":
        from cutting import _commands as _cutting_commands

        scalpels = [args.scalpel0, args.scalpel1] + (args.scalpel_next or [])
        summary = _cutting_commands.tear_command(model, [[s[:3], s[3:]] for s in scalpels], args.out,
                                                 opening=args.opening, predicates=args.predicates,
                                                 side_weight=args.side_weight)
    elif args.command == "drill":
        from cutting import _commands as _cutting_commands

        summary = _cutting_commands.drill_command(model, args.tip, args.base, args.radius, args.out,
                                                  min_points=args.min_points, max_refinements=args.max_refinements)
    elif args.command == "cut":
        from cutting import _commands as _cutting_commands

        summary = _cutting_commands.cut_command(model, args.plane, *args.out, cap=args.cap,
                                                predicates=args.predicates, side_weight=args.side_weight)
    elif args.command == "skin":
        summary = _commands.skin_command(model, args.time, args.method, args.clip, args.out, args.interpolation)
    elif args.command == "animate":
        summary = _commands.animate_command(model, args.frames, args.out, args.clip, args.interpolation)
    else:
        summary = _commands.fit_command(model, args.target, args.out, args.method, args.vertices,
                                        args.regularization, args.max_steps, not args.no_scale)
    print(f"jaxcga {args.command} {model.name}: " + ", ".join(f"{k} {v}" for k, v in summary.items()))
    return 0


FORCE_HELP = ("replace the run in a non-empty OUT: its frame_XXXX.png/.vtu and summary.json are replaced when this "
              "run ends; other files stay")


def _check_paths(args) -> None:
    """Every input and output path of the command, before anything is loaded or computed: inputs are files;
    outputs have a known suffix, are no folder and lie in a folder this process may write in; fem and xfem
    folders are empty (or --force); no output is an input or another output; a .gltf written with its .bin
    does not replace an unrelated .bin."""
    command = args.command
    if command == "demo":
        check_folder(args.out)
        return
    named = {"fit": ("model", "target", "vertices"), "deform": ("mesh", "handles", "cage"), "arap": ("mesh", "handles"),
             "fem": (), "xfem": ()}.get(command, ("model",))
    inputs = {name: check_input(getattr(args, name), name) for name in named if getattr(args, name) is not None}
    if command in ("fem", "xfem"):
        from xfem._fem_commands import RUN_DESCRIBED, RUN_FILES, SCENES

        if command == "fem" and args.scene not in SCENES:
            inputs["SCENE"] = check_input(args.scene, f"SCENE (one of {', '.join(SCENES)} or a mesh file)")
        check_run_folder(args.out, RUN_FILES, args.force, RUN_DESCRIBED, inputs=inputs)
        return
    from deform._deform_commands import DEFORM_OUTPUTS, POSITION_OUTPUTS
    from deform._gltf import GLTF_OUTPUTS, buffer_file

    suffixes = {"skin": POSITION_OUTPUTS, "fit": (".json",), "deform": DEFORM_OUTPUTS, "arap": DEFORM_OUTPUTS}
    if command == "cut":
        outputs = {"out (positive half)": args.out[0], "out (negative half)": args.out[1]}
    else:
        outputs = {"out": args.out}
    for name, path in outputs.items():
        check_output(path, suffixes.get(command, GLTF_OUTPUTS), name)
        if command in ("animate", "cut", "tear", "drill"):  # save_model writes a .gltf with its .bin
            buffer_file(path, name)
    check_distinct(outputs, inputs)


def _error_message(error: BaseException) -> str:
    """The one line ``jaxcga CMD: error: ...`` reports: an OSError as ``FILE: reason``, else ``error_line``."""
    if isinstance(error, OSError) and error.strerror:
        files = [str(f) for f in (error.filename, error.filename2) if f is not None]
        return f"{' -> '.join(files)}: {error.strerror}" if files else error.strerror
    return error_line(error)


def _finite_float(value: str) -> float:
    number = float(value)
    if not math.isfinite(number):
        raise argparse.ArgumentTypeError(f"expected a finite number, got {value!r}")
    return number


class _Parser(argparse.ArgumentParser):
    """argparse with every ``type=float`` option finite, negative numbers in any notation read as values
    (argparse's own test, ``-1`` or ``-.5``, takes ``-1e0`` for an option) and errors on one line."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.register("type", float, _finite_float)
        self._negative_number_matcher = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?$|^-(inf|infinity|nan)$",
                                                   re.IGNORECASE)

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message}\n")


def error_line(error: BaseException) -> str:
    """The message of ``error`` on one line; for an error raised inside compiled code the check's own message,
    without the banner and the traceback around it."""
    from _jaxcga_shared.checks import compiled_error_message

    text = str(error).strip()
    return compiled_error_message(error) or (text.splitlines()[0] if text else type(error).__name__)


@contextlib.contextmanager
def _one_line_reports(command: str):
    """Warnings (a mesh welded on load, ...) as one line each, and JAX's log of a failed host callback (the
    traceback of an ``eqx.error_if`` under ``jax.jit``) muted: that error reaches ``main`` and is printed on
    one line."""
    logger = logging.getLogger("jax._src.callback")
    disabled, logger.disabled = logger.disabled, True
    try:
        with warnings.catch_warnings():
            warnings.showwarning = lambda message, *_, **__: print(f"jaxcga {command}: warning: {message}",
                                                                   file=sys.stderr)
            yield
    finally:
        logger.disabled = disabled


def _interpolation_argument(parser):
    parser.add_argument("--interpolation", choices=("gltf", "log"), default="gltf",
                        help="key interpolation: gltf, the file's (the glTF specification's lerp / slerp / "
                             "step / cubic spline; default), or log, the paper's logarithmic blending of "
                             "key versors (sec. 4.1)")


def _clip(value: str):
    return int(value) if value.lstrip("-").isdigit() else value


def main(argv: list[str] | None = None) -> int:
    parser = _Parser(prog="jaxcga", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser("demo", help="run the main job on the built-in default")
    p_demo.add_argument("--out", type=Path, default=Path("out"), help="folder for figures (default: out/)")
    p_demo.add_argument("--steps", type=int, default=8, help="frames in the blending figure (>= 2)")
    p_demo.add_argument("--no-figure", action="store_true", help="print the tour only")

    methods = ("lbs", "dqs", "cga", "cga_motor_blend")
    p_skin = sub.add_parser("skin", help="skinned vertex positions of a model at a clip time")
    _model_argument(p_skin)
    p_skin.add_argument("--time", type=float, default=0.0, help="clip time in seconds (default 0)")
    p_skin.add_argument("--method", choices=methods, default="cga", help="skinning method (default cga, eq. 17)")
    p_skin.add_argument("--clip", type=_clip, default=0, help="clip name or index (default 0)")
    _interpolation_argument(p_skin)
    p_skin.add_argument("--out", type=Path, required=True,
                        help="OUT.npy: float64 (n, 3) world-space positions; OUT.glb: the posed mesh")

    p_anim = sub.add_parser("animate", help="write an animated glTF re-sampled through the multivector path")
    _model_argument(p_anim)
    p_anim.add_argument("--frames", type=int, default=60, help="frames to sample (default 60)")
    p_anim.add_argument("--clip", type=_clip, default=0, help="clip name or index (default 0)")
    _interpolation_argument(p_anim)
    p_anim.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")

    p_fit = sub.add_parser("fit", help="fit bone motors (and dilations) to target vertex positions")
    _model_argument(p_fit)
    p_fit.add_argument("--target", type=Path, required=True, help="TARGET.npy: (n, 3) world-space positions")
    p_fit.add_argument("--vertices", type=Path, default=None, help="IDX.npy: (t,) vertex indices of (t, 3) targets")
    p_fit.add_argument("--method", choices=methods, default="cga", help="skinning method (default cga)")
    p_fit.add_argument("--regularization", type=float, default=0.0, help="weight of |params|^2 toward the rest pose")
    p_fit.add_argument("--max-steps", type=int, default=200, help="solver step limit (default 200)")
    p_fit.add_argument("--no-scale", action="store_true", help="fit motors only, no dilations")
    p_fit.add_argument("--out", type=Path, required=True, help="POSE.json")

    p_cut = sub.add_parser("cut", help="cut a model by a plane (Algorithm 1) into two skinned glTF halves")
    _model_argument(p_cut)
    p_cut.add_argument("--plane", type=float, nargs=4, required=True, metavar=("NX", "NY", "NZ", "D"),
                       help="the plane n . x = d in the bind pose (n is normalized)")
    p_cut.add_argument("--cap", action="store_true", help="close both halves (the model must be closed)")
    p_cut.add_argument("--predicates", choices=("euclidean", "ga"), default="euclidean",
                       help="Euclidean or GA predicates (Table 1; default euclidean)")
    p_cut.add_argument("--side-weight", type=float, default=0.0,
                       help="0: barycentric weights for new vertices (sec. 4.3); up to 1: favour each half's side")
    p_cut.add_argument("--out", type=Path, nargs=2, required=True, metavar=("POS.glb", "NEG.glb"),
                       help="the positive (n . x > d) and negative halves")

    scalpel = ("X0", "Y0", "Z0", "X1", "Y1", "Z1")
    p_tear = sub.add_parser("tear", help="tear a model with a moving scalpel (Algorithm 2) into a skinned glTF")
    _model_argument(p_tear)
    p_tear.add_argument("--scalpel0", type=float, nargs=6, required=True, metavar=scalpel,
                        help="the scalpel segment at t_0 in the bind pose, handle end (outside the skin) first")
    p_tear.add_argument("--scalpel1", type=float, nargs=6, required=True, metavar=scalpel,
                        help="the scalpel segment at t_1")
    p_tear.add_argument("--scalpel-next", type=float, nargs=6, action="append", metavar=scalpel,
                        help="further samples t_2, t_3, ... (repeat): one tear along the whole path")
    p_tear.add_argument("--opening", type=float, default=0.0,
                        help="distance between the two sides of the tear (default 0: a closed slit)")
    p_tear.add_argument("--predicates", choices=("euclidean", "ga"), default="euclidean",
                        help="Euclidean or GA predicates (Table 1; default euclidean)")
    p_tear.add_argument("--side-weight", type=float, default=0.0,
                        help="0: barycentric weights for new vertices (sec. 4.3); up to 1: favour each side")
    p_tear.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")

    p_drill = sub.add_parser("drill", help="drill a hole into a model (Algorithm 3) and write a skinned glTF")
    _model_argument(p_drill)
    p_drill.add_argument("--tip", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"),
                         help="the drill's tip in the bind pose: it drills the sheets its axis reaches")
    p_drill.add_argument("--base", type=float, nargs=3, required=True, metavar=("X", "Y", "Z"),
                         help="the drill's base (the other end of its axis)")
    p_drill.add_argument("--radius", type=float, required=True, help="the drill's radius")
    p_drill.add_argument("--min-points", type=int, default=6,
                         help="fewest points around a hole before faces are split and drilled again (default 6)")
    p_drill.add_argument("--max-refinements", type=int, default=4, help="at most this many splits (default 4)")
    p_drill.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")

    p_deform = sub.add_parser("deform", help="deform a mesh by motors: spline, harmonic handles, FFD or cage "
                                             "(the deformation paper, sec. III-VI)")
    p_deform.add_argument("method", choices=("spline", "handles", "ffd", "cage"),
                          help="spline-aligned (eq. 1-2), harmonic motor handles (sec. IV), motor FFD (eq. 7-8), "
                               "harmonic-coordinate cage (sec. VI)")
    p_deform.add_argument("mesh", nargs="?", default=None,
                          help="a mesh file (glTF: its bind-pose mesh; .obj, .ply, .stl, ...); "
                               "default: the built-in arm")
    p_deform.add_argument("--bend", type=float, default=60.0,
                          help="degrees of bend across the long axis at its far end (default 60)")
    p_deform.add_argument("--twist", type=float, default=0.0, help="degrees of twist about the long axis (default 0)")
    p_deform.add_argument("--translate", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                          help="translation at the far end (default none)")
    p_deform.add_argument("--basis", choices=("linear", "lagrange", "bezier", "bspline"), default="bspline",
                          help="spline: weights of the key motors (default bspline)")
    p_deform.add_argument("--keys", type=int, default=None,
                          help="spline: number of key motors for bezier / bspline (default 4 / 5; linear has 2, "
                               "lagrange 3)")
    p_deform.add_argument("--weights", choices=("cotangent", "mean_value"), default="cotangent",
                          help="spline, handles: Laplacian weights of the harmonic fields (default cotangent)")
    p_deform.add_argument("--handle-fraction", type=float, default=0.05,
                          help="spline, handles: the end handles hold the vertices within this fraction of the "
                               "long axis's ends (default 0.05)")
    p_deform.add_argument("--handles", type=Path, default=None,
                          help='handles: HANDLES.json {"handles": [[i, ...], ...], "motors": [{"center", "axis", '
                               '"angle_deg", "translation"}, ...]} instead of the two ends')
    p_deform.add_argument("--lattice", type=int, nargs=3, default=(4, 4, 4), metavar=("L", "M", "N"),
                          help="ffd: control points per axis (default 4 4 4)")
    p_deform.add_argument("--cage", type=Path, default=None,
                          help="cage: a closed cage mesh around the model (default: a tube cage of 7 rings of 8 "
                               "along the long axis, deform.tube_cage)")
    p_deform.add_argument("--positional", action="store_true",
                          help="ffd, cage: move control points / cage vertices instead (classic FFD, positional cage)")
    p_deform.add_argument("--out", type=Path, required=True,
                          help="OUT.glb/.obj/.ply/.stl: the deformed mesh; OUT.npy: float64 (n, 3); OUT.png: a figure")

    p_arap = sub.add_parser("arap", help="as-rigid-as-possible deformation with rotors (the deformation paper, "
                                         "sec. VII) by handle vertices")
    p_arap.add_argument("mesh", nargs="?", default=None,
                        help="a mesh file (glTF: its bind-pose mesh; .obj, .ply, .stl, ...); "
                             "default: the built-in arm's rest mesh")
    p_arap.add_argument("--handles", type=Path, default=None,
                        help='HANDLES.json {"indices": [i, ...], "positions": [[x, y, z], ...]}; default: the low end '
                             "of the long axis fixed, the high end moved by --bend/--twist/--translate")
    p_arap.add_argument("--iters", type=int, default=10, help="at most this many local/global iterations (default 10)")
    p_arap.add_argument("--tolerance", type=float, default=1e-8,
                        help="stop when the energy decreases by less than this fraction in one iteration "
                             "(default 1e-8; negative: run every iteration)")
    p_arap.add_argument("--energy", choices=("spokes_and_rims", "spokes"), default="spokes_and_rims",
                        help="spokes_and_rims (default, libigl's default: a rigid motion of all handles gives that "
                             "rigid map) or spokes (the paper's eq. 9: with obtuse triangles it can drift from "
                             "rigid maps)")
    p_arap.add_argument("--bend", type=float, default=60.0, help="default handles: degrees of bend (default 60)")
    p_arap.add_argument("--twist", type=float, default=0.0, help="default handles: degrees of twist (default 0)")
    p_arap.add_argument("--translate", type=float, nargs=3, default=(0.0, 0.0, 0.0), metavar=("X", "Y", "Z"),
                        help="default handles: translation of the high end (default none)")
    p_arap.add_argument("--handle-fraction", type=float, default=0.05,
                        help="default handles: vertices within this fraction of the long axis's ends (default 0.05)")
    p_arap.add_argument("--out", type=Path, required=True,
                        help="OUT.npy: float64 (n, 3) positions; OUT.glb/.obj/.ply/.stl: the mesh; OUT.png: a figure")

    p_fem = sub.add_parser("fem", help="simulate a stable neo-Hookean body under gravity by backward Euler "
                                       "(the XFEM paper, sec. 3)")
    p_fem.add_argument("scene", help="bar (a cantilever), cube (hanging from its top face), a tet mesh file "
                                     "(meshio: .msh, .vtu, ...) or a closed surface (.obj, .ply, .stl, .off, glTF) "
                                     "to tetrahedralize")
    p_fem.add_argument("--steps", type=int, default=100, help="time steps (default 100)")
    p_fem.add_argument("--dt", type=float, default=0.033, help="time step h in seconds (default 0.033, the paper's)")
    p_fem.add_argument("--young", type=float, default=1e6, help="Young's modulus in Pa (default 1e6)")
    p_fem.add_argument("--poisson", type=float, default=0.4, help="Poisson's ratio (default 0.4)")
    p_fem.add_argument("--density", type=float, default=1e3, help="mass density in kg/m^3 (default 1e3)")
    p_fem.add_argument("--gravity", type=float, nargs=3, default=(0.0, 0.0, -9.81), metavar=("GX", "GY", "GZ"),
                       help="gravitational acceleration (default 0 0 -9.81)")
    p_fem.add_argument("--newton", type=int, default=1, help="Newton iterations per step (default 1, the paper's)")
    p_fem.add_argument("--every", type=int, default=10, help="write a frame every this many steps (default 10)")
    p_fem.add_argument("--fix-fraction", type=float, default=0.02,
                       help="mesh files: clamp the nodes within this fraction of the height below the top "
                            "(default 0.02)")
    p_fem.add_argument("--no-figures", action="store_true", help="write the .vtu meshes and summary.json only")
    p_fem.add_argument("--force", action="store_true", help=FORCE_HELP)
    p_fem.add_argument("--out", type=Path, required=True,
                       help="folder for frame_XXXX.png, frame_XXXX.vtu and summary.json")

    p_xfem = sub.add_parser("xfem", help="run a cutting scene of the XFEM paper (sec. 5: sticks, thin, cheese, "
                                         "accordion, mouth) with Table 2's timings")
    p_xfem.add_argument("scene", help="sticks (Fig. 5), thin (Fig. 1), cheese (Fig. 6), accordion (Fig. 7) or mouth "
                                      "(Fig. 8)")
    p_xfem.add_argument("--steps", type=int, default=None, help="frames (default: the scene's, past its last cut)")
    p_xfem.add_argument("--size", default="paper", help="paper (Table 1's meshes, the default) or small (coarse)")
    p_xfem.add_argument("--every", type=int, default=10,
                        help="write a frame every this many frames, besides cut frames and the last (default 10)")
    p_xfem.add_argument("--cut-latency", type=int, default=0,
                        help="compute each cut in the background while the body steps; it takes effect this many "
                             "frames after its scheduled frame (default 0: in its frame, as Algorithm 1)")
    p_xfem.add_argument("--no-figures", action="store_true", help="write the .vtu surfaces and summary.json only")
    p_xfem.add_argument("--force", action="store_true", help=FORCE_HELP)
    p_xfem.add_argument("--out", type=Path, required=True,
                        help="folder for frame_XXXX.png, frame_XXXX.vtu and summary.json")

    args = parser.parse_args(argv)
    if args.command == "demo" and args.steps < 2:
        parser.error("--steps: expected at least 2 frames")
    try:
        with _one_line_reports(args.command):
            _check_paths(args)
            if args.command == "demo":
                return demo(args.out, args.steps, not args.no_figure)
            return _run_deform(args)
    except (ValueError, OSError, RuntimeError) as error:
        parser.exit(2, f"jaxcga {args.command}: error: {_error_message(error)}\n")


if __name__ == "__main__":
    sys.exit(main())
