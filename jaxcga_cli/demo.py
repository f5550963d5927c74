"""``jaxcga demo``: the main job on the built-in default: a tour of the kernel, then the rigged arm skinned,
animated, cut, torn, drilled and deformed, with figures and a page to open in a browser (``out/demo.html``)."""

from __future__ import annotations

import argparse
from pathlib import Path

HELP = "a short tour: the geometric-algebra kernel, then the built-in rigged arm skinned, cut, torn and deformed"
EXAMPLE = "jaxcga demo --out out"


def add_arguments(parser) -> None:
    parser.add_argument("--out", type=Path, default=Path("out"), help="folder for figures (default: out/)")
    parser.add_argument("--steps", type=int, default=8, help="frames in the blending figure (>= 2)")
    parser.add_argument("--no-figure", action="store_true", help="print the tour only")


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_folder

    if args.steps < 2:
        raise ValueError("steps: expected at least 2 frames")
    check_folder(args.out)


def run(args: argparse.Namespace) -> None:
    demo(args.out, args.steps, not args.no_figure)


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

    import jaxcga as cga
    from jaxcga_cli import figures

    triangle, bottom, top = _triangle_keyframes()
    alphas = jnp.linspace(0.0, 1.0, steps)[:, None]
    # Batched over alphas: one versor per frame, applied to the three vertices.
    linear = cga.apply_to_points(cga.blend_linear(bottom, top, alphas[:, 0])[:, None], triangle)
    logarithmic = cga.apply_to_points(cga.blend_log(bottom, top, alphas[:, 0])[:, None], triangle)

    fig = figures.figure(13, 4.5)
    panels = [
        ("(a) linear", [(linear, "tab:blue")]),
        ("(b) logarithmic", [(logarithmic, "tab:red")]),
        ("(c) superimposed", [(linear, "tab:blue"), (logarithmic, "tab:red")]),
    ]
    for k, (title, series) in enumerate(panels):
        ax = figures.axes_3d(fig, 1, 3, k + 1)
        for frames, color in series:
            for i, tri in enumerate(frames):
                closed = jnp.concatenate([tri, tri[:1]])
                ax.plot(*closed.T, color=color, alpha=0.35 + 0.65 * i / (len(frames) - 1))
        ax.set_title(title)
        ax.set_box_aspect((1, 1, 1))
        figures.readable_ticks(ax)
    fig.suptitle("Blending similitude keyframes (rotation, translation, dilation)")
    return figures.save_figure(fig, path, dpi=110, bbox_inches="tight")


def skinning_figure(model, path: Path, frames: int = 5) -> Path:
    """Save a figure of the model at ``frames`` times of its clip (or of generated keyframes),
    skinned by eq. (17), with the largest distance to matrix LBS in the title."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    import deform
    from jaxcga_cli import figures
    from jaxcga_cli.animate import generated_keyframes

    if model.clips:
        times = jnp.linspace(model.clips[0].start, model.clips[0].end, frames)
        cga_frames = jax.vmap(lambda t: deform.skin_model(model, t, "cga"))(times)
        lbs_frames = jax.vmap(lambda t: deform.skin_model(model, t, "lbs"))(times)
    else:
        keys = generated_keyframes(model)
        times = jnp.linspace(0.0, float(keys.times[-1]), frames)
        local = jax.vmap(lambda t: deform.sample_keyframes(keys, t))(times)
        cga_frames = deform.skin_pose(model, local, "cga")
        lbs_frames = deform.skin_pose(model, local, "lbs")
    gap = float(jnp.max(jnp.abs(cga_frames - lbs_frames)))
    fig = figures.figure(3.2 * frames, 3.4)
    F = np.asarray(model.mesh.F)
    lo, hi = np.asarray(jnp.min(cga_frames, axis=(0, 1))), np.asarray(jnp.max(cga_frames, axis=(0, 1)))
    for k in range(frames):
        ax = figures.axes_3d(fig, 1, frames, k + 1)
        X = np.asarray(cga_frames[k])
        ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=F, color="tab:orange", linewidth=0, alpha=0.9)
        figures.set_box(ax, lo, hi)
        ax.set_title(f"t = {float(times[k]):.2f} s", fontsize=9)
        ax.set_axis_off()
    fig.suptitle(f"{model.name}: multivector skinning, eq. (17); max |eq. 17 - LBS| = {gap:.1e}")
    return figures.save_figure(fig, path, dpi=90, bbox_inches="tight")


def cut_figure(arm, upper, lower, path: Path) -> Path:
    """The arm at t = 0 before the cut, and both halves posed again at t = 1.2 s after it."""
    import jax.numpy as jnp

    import deform
    from jaxcga_cli import figures

    fig = figures.figure(10, 4.5)
    halves = [
        (deform.RiggedModel(upper, arm.skeleton, arm.clips), 1.2, "tab:blue"),
        (deform.RiggedModel(lower, arm.skeleton, arm.clips), 1.2, "tab:red"),
    ]
    panels = [("before the cut (t = 0 s)", [(arm, 0.0, "tab:gray")]), ("after: both halves posed at t = 1.2 s", halves)]
    for k, (title, parts) in enumerate(panels):
        ax = figures.axes_3d(fig, 1, 2, k + 1)
        everything = []
        for model, t, color in parts:
            V = deform.skin_model(model, t, "cga")
            everything.append(V)
            ax.plot_trisurf(V[:, 0], V[:, 1], V[:, 2], triangles=model.mesh.F, color=color, alpha=0.6, linewidth=0)
        V = jnp.concatenate(everything)
        center, half = (V.max(axis=0) + V.min(axis=0)) / 2, float((V.max(axis=0) - V.min(axis=0)).max()) / 2
        figures.set_box(ax, center - half, center + half, title)
        ax.view_init(elev=20, azim=-60)
    return figures.save_figure(fig, path, dpi=100, bbox_inches="tight")


def ffd_figure(V, F, classic, motor, ratios: tuple[float, float], path: Path) -> Path:
    """Classic (positional) and motor FFD of the same twist side by side, on one box, and their cross-sections at
    mid-length over the rest one's: where classic FFD loses volume, its section shrinks. ``ratios``: the volume
    ratios (deformed over rest) of classic and motor FFD, in the titles and the figure's title."""
    import numpy as np

    from jaxcga_cli import figures

    V, classic, motor = (np.asarray(X, np.float64) for X in (V, classic, motor))
    both = np.concatenate([classic, motor])
    lo, hi = both.min(axis=0), both.max(axis=0)
    long = int(np.argmax(V.max(axis=0) - V.min(axis=0)))
    across = [i for i in range(3) if i != long]
    fig = figures.figure(13, 4.6)
    names = ("classic FFD (eq. 6)", "motor FFD (eq. 7-8)")
    for k, (X, name, ratio, color) in enumerate(zip((classic, motor), names, ratios, ("tab:blue", "tab:orange"))):
        ax = figures.axes_3d(fig, 1, 3, k + 1)
        ax.plot_trisurf(X[:, 0], X[:, 1], X[:, 2], triangles=F, color=color, linewidth=0, alpha=0.9)
        figures.set_box(ax, lo, hi, f"{name}\nvolume x {ratio:.3f}")
        figures.readable_ticks(ax, count=3)
    # the vertices of a thin slab at mid-length (their rest positions pick them: a twist keeps them in the slab)
    middle = 0.5 * (V[:, long].min() + V[:, long].max())
    slab = np.abs(V[:, long] - middle) <= 0.02 * (V[:, long].max() - V[:, long].min())
    ax = fig.add_subplot(1, 3, 3)
    for X, label, color in ((V, "rest", "0.6"), (classic, names[0], "tab:blue"), (motor, names[1], "tab:orange")):
        section = X[slab][:, across]
        section = section - section.mean(axis=0)  # each on its own centre: the twist also moves the section
        ax.scatter(section[:, 0], section[:, 1], s=4, color=color, label=label)
    ax.set_aspect("equal")
    ax.set_title("cross-sections at mid-length (centred)")
    ax.set_xlabel("xyz"[across[0]], fontsize=8)
    ax.set_ylabel("xyz"[across[1]], fontsize=8, labelpad=0)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.18), ncol=3, markerscale=2, frameon=False)
    figures.readable_ticks(ax)
    fig.suptitle(
        f"The same 120 degree twist of a 4x4x4 lattice: classic FFD keeps {ratios[0]:.1%} of the volume, motor FFD "
        f"{ratios[1]:.1%} (motor / classic = {ratios[1] / ratios[0]:.2f})"
    )
    return figures.save_figure(fig, path, dpi=100, bbox_inches="tight")


def viewer_page(out: Path, arm, halves) -> Path:
    """Write ``out/demo.html``: the viewer (``deform.view``) of the arm, the two halves of its cut (RiggedModels), and
    the torn and drilled arms (``out/arm_torn.glb``, ``out/arm_drilled.glb``), side by side, all playing the arm's
    clip (by its name: ``out/arm_animated.glb`` names its re-sampled clip apart)."""
    import deform

    inputs = [arm, *halves, out / "arm_torn.glb", out / "arm_drilled.glb"]
    title = "jaxcga demo: the arm animated, cut, torn and drilled"
    return deform.view(*inputs, title=title).save(out / "demo.html", force=True)


def demo(out: Path, steps: int, figure: bool) -> None:
    """A short tour of the kernel: prints what it computes and saves figures into ``out``."""
    import time

    import jax
    import jax.numpy as jnp
    import numpy as np

    import cutting
    import deform
    import jaxcga as cga
    from jaxcga_cli.animate import animate_command
    from jaxcga_cli.deform import deform_command
    from jaxcga_cli.drill import drill_command
    from jaxcga_cli.models import load_mesh
    from jaxcga_cli.report import quiet
    from jaxcga_cli.tear import tear_command

    print("jaxcga demo: the CGA kernel G(4,1) in the null basis {e1, e2, e3, eo, einf}")
    pts = cga.up(jnp.array([[1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0], [0.0, 0.0, 0.0]]))
    a, b, c, d = (cga.Multivector(pts.values[i], pts.blades) for i in range(4))
    print(f"  distance |a - b| from -2 A.B          : {float(cga.distance(a, b)):.6f}  (sqrt 5 = {5**0.5:.6f})")
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

    arm = deform.default_arm()
    print(
        f"\nThe built-in rigged arm: {arm.mesh.num_vertices} vertices, bones {list(arm.skeleton.names)}, "
        f"clip {arm.clips[0].name!r} ({arm.clips[0].end:.1f} s)"
    )
    frames = jax.vmap(lambda t: deform.skin_model(arm, t, "cga"))(jnp.linspace(0.0, arm.clips[0].end, 9))
    reach = jnp.linalg.norm(frames, axis=-1).max(axis=-1)
    print(f"  eq. (17) skinning of 9 frames (vmap)    : reach {reach.min():.3f} .. {reach.max():.3f} m")
    with quiet():
        summary = animate_command(arm, 30, out / "arm_animated.glb")
    print(f"  clip re-sampled through log blending   : {summary['frames']} frames -> {summary['out']}")
    if figure:
        path = skinning_figure(arm, out / "arm.png")
        print(f"  figure: the arm along its clip         -> {path}")

    normal = jnp.array([1.0, 0.15, 0.0])
    plane = cutting.Plane(normal, float(jnp.median(arm.mesh.V @ normal)))
    start = time.perf_counter()
    upper, lower = cutting.cut(arm.mesh, plane, cap=True)
    took = 1e3 * (time.perf_counter() - start)
    print(
        f"\nCut (Algorithm 1, capped) across the forearm: halves of {upper.F.shape[0]} and {lower.F.shape[0]} "
        f"faces in {took:.1f} ms"
    )
    if figure:
        path = cut_figure(arm, upper, lower, out / "arm_cut.png")
        print(f"  figure: before / after the cut, posed again -> {path}")

    scalpels = [[[0.2, 0.0, 0.1], [0.2, 0.0, 0.0]], [[0.3, 0.0, 0.1], [0.3, 0.0, 0.0]]]
    start = time.perf_counter()
    with quiet():
        summary = tear_command(arm, scalpels, out / "arm_torn.glb", opening=0.005)
    print(
        f"Tear (Algorithm 2) along the upper arm: {summary['tear_points']} tear points, opened by 5 mm, in "
        f"{1e3 * (time.perf_counter() - start):.1f} ms with the file -> {summary['out']}"
    )
    start = time.perf_counter()
    with quiet():
        summary = drill_command(arm, [0.4, 0.0, 0.0], [0.4, 0.0, 0.1], 0.015, out / "arm_drilled.glb")
    print(
        f"Drill (Algorithm 3) of radius 15 mm into the forearm: {summary['hole_points']} points around the hole, "
        f"in {1e3 * (time.perf_counter() - start):.1f} ms with the file -> {summary['out']}"
    )

    halves = [
        deform.RiggedModel(half, arm.skeleton, arm.clips, name=f"arm_cut_{side}")
        for half, side in ((upper, "upper"), (lower, "lower"))
    ]
    page = viewer_page(out, arm, halves)
    print(f"Viewer: the animated arm, both halves of the cut, the torn and the drilled arm, playing -> {page}")

    V, F = load_mesh(None)
    print("\nMotor deformations (the deformation paper): the same 120 degree twist of a 4x4x4 lattice")
    results, ratios = [], []
    for positional in (True, False):
        out_file = out / ("arm_ffd_classic.npy" if positional else "arm_ffd_motor.npy")
        with quiet():
            summary = deform_command("ffd", V, F, out_file, bend=0.0, twist=120.0, positional=positional)
        results.append(np.load(out_file))
        ratios.append(summary["volume_ratio"])
        print(
            f"  {'classic FFD (eq. 6)' if positional else 'motor FFD (eq. 7-8)':22s}: volume ratio "
            f"{summary['volume_ratio']:.4f}, mean edge change {summary['mean_edge_change']:.4f}, "
            f"{summary['frame_ms']:.2f} ms per frame -> {summary['out']}"
        )
    if figure:
        path = ffd_figure(V, F, results[0], results[1], (ratios[0], ratios[1]), out / "arm_ffd.png")
        print(f"  figure: classic and motor FFD, their volumes and cross-sections -> {path}")
