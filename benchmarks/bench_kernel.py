"""Kernel benchmark: motors applied to 100k Euclidean points, in and out (issue 2, item 9).

Candidates, all under ``jax.jit`` in this process, timed round-robin (so machine noise hits all of
them alike), median of the repeats:

* jaxcga ``apply_to_points``: one motor per point, and one motor for all points, float64 and float32; per point
  also with ``fused=True`` (the layout left to XLA: on a GPU, the formulation the Triton kernel replaced);
* with ``--tune-rows``, the GPU's Triton kernel (``_jaxcga_shared.pallas_rows``) at other block sizes and warps,
  to choose its defaults (on the CPU: Pallas' interpret mode, meaningless for speed);
* baseline, the same rigid transforms as 3x4 matrices in JAX: hand-unrolled ``A[:, :, 0] x0 + ...``
  (the fastest form we know) and the idiomatic batched matmul ``A[..., :3] @ x + A[..., 3]``;
* peer, kingdon's ``M >> X`` on JAX arrays (``_kingdon_peer``);
* compile time of the first call (trace, code generation and XLA compile), measured first thing.

Ratios are baseline time / our time: larger than 1 means jaxcga is faster.
Usage: ``python benchmarks/bench_kernel.py [--points 100000] [--repeats 30] [--tune-rows] [--json PATH]`` (on a GPU
``--points 10000000``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _kingdon_peer import make_kingdon_sandwich  # noqa: E402
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import jaxcga as cga  # noqa: E402
from _jaxcga_shared import pallas_rows  # noqa: E402
from jaxcga import _versors  # noqa: E402


def _ours(motor_values, x):
    return cga.apply_to_points(cga.Multivector(motor_values, "motor"), x)


def _ours_fused(motor_values, x):
    return cga.apply_to_points(cga.Multivector(motor_values, "motor"), x, fused=True)


def _triton_rows(rows_per_program: int, warps: int):
    coordinates = _versors.row_coordinates(cga.Multivector(jnp.zeros(8), "motor").blades)

    def apply(motor_values, x):
        rows = [x, motor_values]
        return pallas_rows.rowwise(coordinates, rows, [], 3, rows_per_program=rows_per_program, warps=warps)

    return jax.jit(apply)


TUNING = [(rows, warps) for rows in (256, 512, 1024, 2048) for warps in (4, 8)]


def _matrix_unrolled(a, x):
    a = a.reshape((1,) * (x.ndim + 1 - a.ndim) + a.shape)  # one matrix for all points: its batch axes explicit
    return a[..., 0] * x[..., 0:1] + a[..., 1] * x[..., 1:2] + a[..., 2] * x[..., 2:3] + a[..., 3]


def _matrix_matmul(a, x):
    return (a[..., :3] @ x[..., None])[..., 0] + a[..., 3]


def _first_call_seconds(fn, *args) -> float:
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    return time.perf_counter() - start


def _time_round_robin(cases: dict, repeats: int) -> dict[str, float]:
    for fn, args in cases.values():
        jax.block_until_ready(fn(*args))
    samples: dict[str, list[float]] = {name: [] for name in cases}
    for _ in range(repeats):
        for name, (fn, args) in cases.items():
            start = time.perf_counter()
            jax.block_until_ready(fn(*args))
            samples[name].append(time.perf_counter() - start)
    return {name: statistics.median(ts) for name, ts in samples.items()}


def run(n: int, repeats: int, tune_rows: bool = False) -> dict:
    rng = np.random.default_rng(0)
    generators = cga.Multivector(jnp.asarray(rng.normal(size=(n, 6))), cga.MOTOR_GENERATOR)
    motors64 = cga.exp(generators).values
    x64 = jnp.asarray(rng.normal(size=(n, 3)) * 2.0)
    # Compile time first, before anything else has warmed jaxcga's generated tables.
    compile_s = _first_call_seconds(jax.jit(_ours), motors64, x64)
    kingdon64 = make_kingdon_sandwich(jnp.float64)
    kingdon_compile_s = _first_call_seconds(kingdon64, motors64, x64)

    matrices64 = cga.versor_to_matrix(cga.Multivector(motors64, "motor"))[:, :3, :]
    motors32, x32, matrices32 = (a.astype(jnp.float32) for a in (motors64, x64, matrices64))
    one64, one32 = motors64[0], motors32[0]
    ours, unrolled, matmul = jax.jit(_ours), jax.jit(_matrix_unrolled), jax.jit(_matrix_matmul)
    fused = jax.jit(_ours_fused)
    tuned = {f"rows_{r}_warps_{w}_f64": _triton_rows(r, w) for r, w in TUNING} if tune_rows else {}

    # Same transforms, same answers, before anything is timed.
    reference = np.asarray(matmul(matrices64, x64))
    for name, out in {
        "jaxcga": ours(motors64, x64),
        "jaxcga fused": fused(motors64, x64),
        **{f"jaxcga {name}": fn(motors64, x64) for name, fn in tuned.items()},
        "matrix unrolled": unrolled(matrices64, x64),
        "kingdon": kingdon64(motors64, x64),
    }.items():
        err = float(np.max(np.abs(np.asarray(out) - reference)))
        if err > 1e-10:
            raise RuntimeError(f"{name} disagrees with the matrix transform by {err:.2e}")

    cases = {
        "per_point_f64": (ours, (motors64, x64)),
        "per_point_f32": (ours, (motors32, x32)),
        "per_point_fused_f64": (fused, (motors64, x64)),
        **{name: (fn, (motors64, x64)) for name, fn in tuned.items()},
        "one_motor_f64": (ours, (one64, x64)),
        "one_motor_f32": (ours, (one32, x32)),
        "matrix_unrolled_f64": (unrolled, (matrices64, x64)),
        "matrix_unrolled_f32": (unrolled, (matrices32, x32)),
        "matrix_matmul_f64": (matmul, (matrices64, x64)),
        "matrix_one_f64": (unrolled, (matrices64[0], x64)),
        "kingdon_per_point_f64": (kingdon64, (motors64, x64)),
        "kingdon_one_motor_f64": (kingdon64, (one64, x64)),
    }
    seconds = _time_round_robin(cases, repeats)
    rate = {name: n / s for name, s in seconds.items()}

    figures = {
        "per_point_f64_points_per_s": rate["per_point_f64"],
        "per_point_f32_points_per_s": rate["per_point_f32"],
        "per_point_fused_f64_points_per_s": rate["per_point_fused_f64"],
        **{f"{name}_points_per_s": rate[name] for name in tuned},
        "one_motor_f64_points_per_s": rate["one_motor_f64"],
        "one_motor_f32_points_per_s": rate["one_motor_f32"],
        "compile_s": compile_s,
        "matrix_unrolled_f64_points_per_s": rate["matrix_unrolled_f64"],
        "matrix_matmul_f64_points_per_s": rate["matrix_matmul_f64"],
        "kingdon_per_point_f64_points_per_s": rate["kingdon_per_point_f64"],
        "kingdon_compile_s": kingdon_compile_s,
    }
    ratios = {
        "per_point_f64_vs_kingdon": seconds["kingdon_per_point_f64"] / seconds["per_point_f64"],
        "per_point_f64_vs_matrix": seconds["matrix_unrolled_f64"] / seconds["per_point_f64"],
        "per_point_f64_vs_matrix_matmul": seconds["matrix_matmul_f64"] / seconds["per_point_f64"],
        "per_point_f32_vs_matrix": seconds["matrix_unrolled_f32"] / seconds["per_point_f32"],
        "one_motor_f64_vs_matrix": seconds["matrix_one_f64"] / seconds["one_motor_f64"],
        "one_motor_f64_vs_kingdon": seconds["kingdon_one_motor_f64"] / seconds["one_motor_f64"],
        "compile_vs_kingdon": kingdon_compile_s / compile_s,
    }
    units = {name: ("s" if name.endswith("compile_s") else "points/s") for name in figures}
    units.update({name: RATIO_UNIT for name in ratios})
    return {"figures": figures, "ratios": ratios, "units": units}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--points", "--n", type=int, default=100_000, help="number of points (default 100000)")
    parser.add_argument("--repeats", type=int, default=30, help="timed calls per candidate")
    parser.add_argument(
        "--tune-rows", action="store_true", help="also time the GPU's Triton kernel at other block sizes and warps"
    )
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_kernel")
    if args.points < 1 or args.repeats < 1:
        parser.error("--points and --repeats must be positive")
    result = run(args.points, args.repeats, args.tune_rows)
    print(f"bench_kernel: {args.points} points, median of {args.repeats} round-robin calls")
    for name, value in result["figures"].items():
        unit = result["units"][name]
        print(f"  {name:38s} {value:12.4g} {unit}")
    for name, value in result["ratios"].items():
        print(f"  {name:38s} {value:12.3f} x  (baseline time / jaxcga time)")
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
