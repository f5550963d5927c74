"""Deformation benchmark (deformation paper sec. III-VIII) on a 100k-vertex mesh: the harmonic field
solve against ``igl.harmonic`` in the same run, and per-frame deformation time of the spline-aligned
deformation (eq. 1-2), harmonic motor handles (sec. IV), motor FFD (eq. 7-8) and the motor cage
(sec. VI), float32 and float64.

The mesh is the welded Arm5 split conformingly (``cutting.refine``) to at least 100,000 vertices.
A frame is everything from the key motors to the vertex positions, jitted: the logarithms of the key
motors, the per-vertex blend ``exp(sum_j w_ij log R_j)`` and the sandwich. Each motor deformation is
timed against its linear counterpart on the same weights in the same run: the matrix blend of the same
key motors (spline, handles; LBS-like), classic positional FFD (eq. 6), the positional cage, all at the highest
precision as the library's products are (a GPU's default would be TF32 for float32). On a GPU the XLA formulation
that the Triton program replaced is timed too (``*_xla_ms``).
Calls are interleaved round-robin (medians), so the machine's drift does not bias a ratio. Ratios are
baseline time / ours (> 1: we are faster); ``*_fps`` figures without a suffix are float64. Last, ``fit_pose`` on
notebook 02's problem on CesiumMan: Levenberg-Marquardt against gradient descent (``fit_gd_vs_lm``: LM's time over
gradient descent's).

    python benchmarks/bench_deform.py [--vertices 100000] [--repeats 15] [--skip-fit] [--json out/bench/deform.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import igl  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import cutting  # noqa: E402
import deform  # noqa: E402
import jaxcga as cga  # noqa: E402
from deform import _motor_field  # noqa: E402

HIGHEST = jax.lax.Precision.HIGHEST  # the baselines at our precision: a GPU's default is TF32 for float32

TARGET_FPS = 30.0


def refined_arm5(min_vertices: int):
    """Welded Arm5 split (``cutting.refine``, conforming) to at least ``min_vertices`` vertices: (V, F)."""
    mesh = deform.weld(deform.load_model(ROOT / "tests" / "data" / "Arm5.glb").mesh)
    while 4 * mesh.V.shape[0] <= min_vertices:
        mesh = cutting.refine(mesh)
    while mesh.V.shape[0] < min_vertices:  # split the lowest faces (each adds about 1.5 vertices)
        V, F = np.asarray(mesh.V), np.asarray(mesh.F)
        lowest = np.argsort(V[F].mean(axis=1)[:, 1])[: max(16, (min_vertices - len(V)) // 2)]
        mesh = cutting.refine(mesh, lowest)
    return np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)


def arm_handles(V):
    """The shoulder ring, the fingertips and a band around the elbow of Arm5 (y is along the arm)."""
    y = V[:, 1]
    return [np.flatnonzero(y < 2.0), np.flatnonzero(y > 70.0), np.flatnonzero(np.abs(y - 39.0) < 0.5)]


def bend_motors(k: int, V, angle: float = 1.2, twist: float = 0.8, dtype=jnp.float64):
    """k motors along the arm (y): key j turns by j/(k-1) of a bend about x and of a twist about y,
    about the shoulder."""
    s = jnp.linspace(0.0, 1.0, k, dtype=dtype)
    shoulder = jnp.asarray([V[:, 0].mean(), V[:, 1].min(), V[:, 2].mean()], dtype)
    bend = cga.rotor(jnp.broadcast_to(jnp.asarray([1.0, 0, 0], dtype), (k, 3)), angle * s)
    turn = cga.rotor(jnp.broadcast_to(jnp.asarray([0, 1.0, 0], dtype), (k, 3)), twist * s)
    return deform.motor_about(shoulder, (bend * turn).embed(cga.KINDS["rotor"]))


def matrix_blend(weights, bound):
    """The LBS-like baseline: per vertex, the weighted sum of the key motors' 3x4 matrices applied to
    the bound point."""
    ones = jnp.ones(bound.shape[:1] + (1,), bound.dtype)
    homogeneous = jnp.concatenate([bound, ones], axis=1)

    def deform_(motors):
        matrices = cga.versor_to_matrix(motors)[..., :3, :].reshape(motors.batch_shape + (12,))
        blended = jnp.matmul(weights, matrices, precision=HIGHEST).reshape(-1, 3, 4)
        return jnp.einsum("nrc,nc->nr", blended, homogeneous, precision=HIGHEST)

    return deform_


def round_robin_ms(fns: dict, repeats: int) -> dict:
    """Median milliseconds of each zero-argument function, calls interleaved over the functions."""
    for fn in fns.values():
        jax.block_until_ready(fn())  # compile and warm up
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
    return {name: 1e3 * statistics.median(t) for name, t in times.items()}


def as_dtype(tree, dtype):
    return jax.tree_util.tree_map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def harmonic_timings(V, F, repeats: int):
    """Median seconds of ``deform.harmonic_fields`` and ``igl.harmonic`` (interleaved) on the same
    handles, of a re-solve for new boundary values with the prefactored solver (``igl.harmonic`` has
    to start again), and the largest difference between the fields."""
    handles = arm_handles(V)
    b = np.concatenate(handles)
    bc = np.zeros((len(b), len(handles)))
    bc[np.arange(len(b)), np.repeat(np.arange(len(handles)), [len(h) for h in handles])] = 1.0
    ours = np.asarray(deform.harmonic_fields(V, F, handles))  # warm up (JAX dispatch)
    difference = float(np.abs(ours - igl.harmonic(V, F, b, bc, 1)).max())
    data = deform.harmonic_precompute(V, F, b)
    new_values = jnp.asarray(np.random.default_rng(0).random(bc.shape))
    jax.block_until_ready(deform.harmonic_solve(data, new_values))
    times = {"ours": [], "igl": [], "resolve": []}
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(deform.harmonic_solve(data, new_values))
        times["resolve"].append(time.perf_counter() - start)
        start = time.perf_counter()
        np.asarray(deform.harmonic_fields(V, F, handles))
        times["ours"].append(time.perf_counter() - start)
        start = time.perf_counter()
        igl.harmonic(V, F, b, bc, 1)
        times["igl"].append(time.perf_counter() - start)
    return {name: statistics.median(t) for name, t in times.items()}, difference


def run(vertices: int, repeats: int, harmonic_repeats: int):
    start = time.perf_counter()
    V, F = refined_arm5(vertices)
    n = len(V)
    print(f"mesh: welded Arm5 refined to {n} vertices, {len(F)} faces ({time.perf_counter() - start:.1f} s)")
    figures, ratios, units = {"vertices": float(n)}, {}, {"vertices": "count"}

    seconds, difference = harmonic_timings(V, F, harmonic_repeats)
    figures.update(
        harmonic_100k_s=seconds["ours"], harmonic_igl_100k_s=seconds["igl"], harmonic_resolve_100k_s=seconds["resolve"]
    )
    units.update(harmonic_100k_s="s", harmonic_igl_100k_s="s", harmonic_resolve_100k_s="s")
    ratios["harmonic_vs_igl"] = seconds["igl"] / seconds["ours"]
    ratios["harmonic_resolve_vs_igl"] = seconds["igl"] / seconds["resolve"]
    print(
        f"harmonic fields (3 handles, cotangent), from scratch: ours {seconds['ours']:.3f} s, igl.harmonic "
        f"{seconds['igl']:.3f} s -> {ratios['harmonic_vs_igl']:.2f}x; largest difference {difference:.1e}"
    )
    print(
        f"  new boundary values on the prefactored system: {1e3 * seconds['resolve']:.1f} ms -> "
        f"{ratios['harmonic_resolve_vs_igl']:.1f}x igl.harmonic"
    )

    handles = arm_handles(V)
    shoulder, fingertips = handles[0], handles[1]
    start = time.perf_counter()
    spline = deform.spline_precompute(V, F, shoulder, fingertips, basis="bspline", num_keys=6)
    handle_field = deform.handles_precompute(V, F, handles)
    lattice = deform.bounding_lattice(V, (4, 4, 4), padding=0.01)
    ffd = deform.ffd_precompute(V, lattice)
    ffd_weights = ffd.weights
    cage_V, cage_F = deform.tube_cage(V)  # 58 vertices: 7 rings of 8 along the arm, and 2 caps
    cage = deform.cage_precompute(V, cage_V, cage_F)
    print(
        f"precompute (spline, handles, FFD 4x4x4, cage of {len(cage_V)} vertices): {time.perf_counter() - start:.1f} s"
    )

    for dtype, tag in ((jnp.float64, "f64"), (jnp.float32, "f32")):
        P_twist, lattice_motors = deform.twist_lattice(as_dtype(lattice, dtype), 1.5)
        cage_motors = bend_motors(len(cage_V), V, dtype=dtype)
        cage_positions = cga.apply_to_points(
            deform.motor_about(
                jnp.asarray(cage_V.mean(axis=0), dtype),
                cga.rotor(jnp.asarray([0, 1.0, 0], dtype), jnp.asarray(0.3, dtype)),
            ),
            jnp.asarray(cage_V, dtype),
        )
        cases = {
            "spline": (as_dtype(spline, dtype), bend_motors(6, V, dtype=dtype), None),
            "handles": (as_dtype(handle_field, dtype), bend_motors(3, V, dtype=dtype), None),
            "ffd": (as_dtype(ffd, dtype), lattice_motors, ("positional FFD", jnp.asarray(ffd_weights, dtype), P_twist)),
            "cage": (
                as_dtype(cage, dtype),
                cage_motors,
                ("positional cage", as_dtype(cage.weights, dtype), cage_positions),
            ),
        }
        xla_field = jax.jit(lambda f, m: _motor_field._deform_in_xla(f.weights, f.bound, deform.motor_logs(m)))
        for name, (field, motors, positional) in cases.items():
            # the bound data are arguments, not constants folded into the compiled code
            ours = jax.jit(deform.motor_field_solve)
            if positional is None:
                label = "matrix blend"
                base = jax.jit(lambda f, m: matrix_blend(f.weights, f.bound)(m))
                base_args = (field, motors)
            else:
                label, weights, P = positional
                base, base_args = jax.jit(lambda w, P: jnp.matmul(w, P, precision=HIGHEST)), (weights, P)
            candidates = {"ours": lambda: ours(field, motors), "base": lambda: base(*base_args)}
            if jax.default_backend() != "cpu":  # the formulation the GPU's Triton program replaced, for comparison
                candidates["xla"] = lambda: xla_field(field, motors)
            ms = round_robin_ms(candidates, repeats)
            if "xla" in ms:
                figures[f"{name}_100k_{tag}_xla_ms"] = ms["xla"]
                units[f"{name}_100k_{tag}_xla_ms"] = "ms"
            fps = 1e3 / ms["ours"]
            key = f"{name}_100k_fps" + ("" if tag == "f64" else "_f32")
            figures[key] = fps
            units[key] = "frames/s"
            figures[f"{name}_100k_{tag}_ms"] = ms["ours"]
            units[f"{name}_100k_{tag}_ms"] = "ms"
            ratios[f"{name}_vs_{label.replace(' ', '_')}_{tag}"] = ms["base"] / ms["ours"]
            verdict = "meets" if fps >= TARGET_FPS else "MISSES"
            print(
                f"{name:8s} {tag}: {ms['ours']:7.2f} ms/frame = {fps:6.1f} frames/s ({verdict} {TARGET_FPS:.0f}); "
                f"{label} {ms['base']:.2f} ms -> {ms['base'] / ms['ours']:.2f}x"
            )
    return {"figures": figures, "ratios": ratios, "units": units | {k: RATIO_UNIT for k in ratios}}


def fit_figures() -> dict:
    """Notebook 02's fitting problem on CesiumMan (a random pose, every vertex a target): ``fit_pose`` by
    Levenberg-Marquardt (the default) and by gradient descent (gradients only, L-BFGS), steps, warm wall time (the
    second of two calls; the first compiles) and the error over the rest diagonal."""
    model = deform.load_model(ROOT / "tests" / "data" / "CesiumMan.glb")
    truth = deform.random_parameters(jax.random.PRNGKey(0), model, rotation=0.5, translation=0.02, log_scale=0.1)
    targets = deform.skin_parameters(model, truth)
    diagonal = float(np.linalg.norm(np.ptp(np.asarray(deform.rest_pose(model, "lbs")), axis=0)))
    figures, units = {}, {}
    runs = {}
    for key, options in (("lm", {}), ("gd", {"solver": "gradient_descent", "max_steps": 5_000})):
        for _ in range(2):
            start = time.perf_counter()
            fit = jax.block_until_ready(deform.fit_pose(model, targets, **options))
            seconds = time.perf_counter() - start
        runs[key] = seconds
        figures |= {
            f"fit_{key}_steps": float(fit.steps),
            f"fit_{key}_s": seconds,
            f"fit_{key}_error": float(fit.max_error) / diagonal,
        }
        units |= {f"fit_{key}_steps": "steps", f"fit_{key}_s": "s", f"fit_{key}_error": "diagonal"}
        print(
            f"fit_pose on CesiumMan, {key}: {int(fit.steps)} steps, converged {bool(fit.converged)}, {seconds:.2f} s, "
            f"max error {float(fit.max_error) / diagonal:.1e} of the diagonal"
        )
    ratios = {"fit_gd_vs_lm": runs["lm"] / runs["gd"]}
    print(f"gradient descent takes {runs['gd'] / runs['lm']:.1f}x Levenberg-Marquardt's time")
    return {"figures": figures, "ratios": ratios, "units": units | {k: RATIO_UNIT for k in ratios}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vertices", type=int, default=100_000, help="at least this many mesh vertices")
    parser.add_argument("--repeats", type=int, default=15, help="timed frames per method")
    parser.add_argument("--harmonic-repeats", type=int, default=9, help="timed field solves")
    parser.add_argument(
        "--skip-fit", action="store_true", help="leave out fit_pose on CesiumMan (LM and gradient descent)"
    )
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_deform")
    result = run(args.vertices, args.repeats, args.harmonic_repeats)
    if not args.skip_fit:
        fit = fit_figures()
        for key in ("figures", "ratios", "units"):
            result[key] |= fit[key]
    write_json(args.json, result)


if __name__ == "__main__":
    main()
