"""Command-line entry point ``jaxcga``.

The application layer: the only module allowed to import the other packages (lazily, per
subcommand). ``jaxcga demo`` runs the main job on the built-in default.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


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
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path


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
    print(f"  motor (90 deg about z, then +x) on a   : {cga.apply_to_points(m, jnp.array([1.0, 0, 0])).round(6).tolist()}")
    gen = cga.log(m)
    print(f"  log of that motor (screw generator)    : {dict(zip(gen.names, gen.values.round(6).tolist()))}")
    print(f"  exp(log(M)) - M, max abs               : {float(jnp.max(jnp.abs(cga.exp(gen).values - m.values))):.2e}")
    s = cga.similitude(cga.rotor(jnp.array([1.0, 0.0, 0.0]), 0.4), jnp.array([0.0, 1.0, 0.0]), 2.0)
    _, r2 = cga.sphere_center_radius(s >> cga.sphere(jnp.zeros(3), 1.0))
    print(f"  similitude (scale 2) on a unit sphere  : radius {float(r2):.6f}")
    if figure:
        path = blending_figure(out / "blending.png", steps)
        print(f"  figure: linear vs logarithmic blending -> {path}")
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="jaxcga", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p_demo = sub.add_parser("demo", help="run the main job on the built-in default")
    p_demo.add_argument("--out", type=Path, default=Path("out"), help="folder for figures (default: out/)")
    p_demo.add_argument("--steps", type=int, default=8, help="frames in the blending figure (>= 2)")
    p_demo.add_argument("--no-figure", action="store_true", help="print the tour only")
    args = parser.parse_args(argv)
    if args.command == "demo":
        if args.steps < 2:
            parser.error("--steps: expected at least 2 frames")
        return demo(args.out, args.steps, not args.no_figure)
    return 2  # unreachable: argparse requires a command


if __name__ == "__main__":
    sys.exit(main())
