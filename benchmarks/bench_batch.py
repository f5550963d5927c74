"""Batch benchmark: 64 different animated characters, 100 frames each, skinned by one packed call
(``deform.pack_models`` / ``deform.skin_packed``) against a Python loop of jitted per-model calls, and the packed
batch split over 4 host devices.

The models: CesiumMan, RiggedSimple and Arm5 (tests/data; Arm5 given a random clip) and random rigs of 1k-50k
vertices (``_crowd.random_rig``: a random skeleton of 12-40 bones, a tube around each bone, 4 influences per
vertex, a clip of 3-6 keys per bone), vertex counts spread geometrically. Everything is float32, as a renderer
would use it (64 models x 100 frames of ~12k vertices on average are ~0.9 GB of positions).

Two batches of 64 models: the first (A) compiles the packed function for its capacities; the second (B: other
random rigs, each a little smaller, and the three test models) is packed with ``at_least=A.capacities`` and
reuses it. Every figure below is measured on B:

* ``packed_vs_loop`` (the issue's figure): a new batch, as a user runs it. The loop is
  ``jax.jit(jax.vmap(lambda t: deform.skin_model(model, t, method)))(times_m)`` for each model (one jit over all
  its frames, no per-frame Python), which compiles once per model; the packed call is ``pack_models`` +
  ``skin_packed`` + ``unpack`` with the function compiled for A.
* ``packed_vs_loop_first_batch``: both cold, nothing compiled (``jax.clear_caches()`` before the packed call):
  the packed function compiles once for the batch, the loop once per model.
* ``packed_vs_loop_warm``: both compiled, run time only (medians, calls interleaved; the loop blocks once after
  dispatching every model).
* ``sharded_4_vs_1``: in a subprocess with ``XLA_FLAGS=--xla_force_host_platform_device_count=4``, B packed with
  ``blocks=4`` and skinned over ``jax.make_mesh((4, 1), ("models", "time"))``, against B packed in one block on
  one device of the same process (warm medians). Host devices share the machine's cores.
* ``padding_1_block``, ``padding_4_blocks``: ``packed.padding`` (padded vertex-influence work / real work) of B
  packed at its own capacities; ``padding_new_batch``: B at A's capacities.

* the fitting figures of ``_batch_fit.fit_figures``: ``deform.fit_packed`` on 4 models against a loop of
  ``deform.fit_pose`` (cold and warm).

    python benchmarks/bench_batch.py [--models 64] [--frames 100] [--devices 4] [--figures skinning sharded fit]
                                     [--json out/bench/batch.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", False)  # float32, as a renderer: the models, times and positions
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
# _report first: it puts the checkout to measure on sys.path, and _crowd imports deform
from _report import RATIO_UNIT, add_json_argument, platform, print_device, write_json  # noqa: E402

# isort: split
import _crowd  # noqa: E402
from _batch_fit import fit_figures  # noqa: E402

import deform  # noqa: E402

FIGURES = ("skinning", "sharded", "fit")


def batches(models: int, vertices: tuple[int, int], which: str = "AB") -> dict[str, list[deform.RiggedModel]]:
    """The batches named in ``which``: A, the three test models and random rigs; B, the test models (Arm5 with
    another clip) and other random rigs, each 0.95 times the size of A's rig of the same rank (B fits A's
    capacities)."""
    out = {}
    for name, seed, shrink in (("A", 1, 1.0), ("B", 2, 0.95)):
        if name in which:
            tests = [m if m.name != "Arm5" else _crowd.animate(m, seed=seed + 10) for m in _crowd.test_models()]
            out[name] = (tests + _crowd.crowd(models - len(tests), seed, vertices, shrink))[:models]
    return out


def phase(label: str, fn):
    """``fn()`` run to completion; prints and returns (its result, the wall time)."""
    start = time.perf_counter()
    out = jax.block_until_ready(fn())
    elapsed = time.perf_counter() - start
    print(f"  {label}: {elapsed:.2f} s", flush=True)
    return out, elapsed


def loop_functions(models, method: str):
    """One jitted function of the times per model, as a user writes the loop."""
    return [jax.jit(jax.vmap(lambda t, m=m: deform.skin_model(m, t, method))) for m in models]


def run_loop(functions, times) -> list:
    return [f(t) for f, t in zip(functions, times, strict=True)]


def interleaved_medians(fns: dict, repeats: int) -> dict:
    """Median wall time of each function (already compiled), one call of each per round."""
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            out = jax.block_until_ready(fn())
            times[name].append(time.perf_counter() - start)
            del out
    return {name: statistics.median(t) for name, t in times.items()}


def max_relative_difference(models, ours: list, reference: list) -> float:
    """Largest distance between two models' frames over the model's bounding-box diagonal."""
    gaps = []
    for model, a, b in zip(models, ours, reference, strict=True):
        diagonal = float(np.linalg.norm(np.ptp(np.asarray(model.mesh.V), axis=0)))
        gaps.append(float(np.max(np.linalg.norm(np.asarray(a) - np.asarray(b), axis=-1))) / diagonal)
    return max(gaps)


def describe(name: str, models):
    counts = [m.mesh.num_vertices for m in models]
    bones = [m.skeleton.num_bones for m in models]
    print(
        f"batch {name}: {len(models)} models, {sum(counts):,} vertices ({min(counts):,} to {max(counts):,}), "
        f"{min(bones)} to {max(bones)} bones",
        flush=True,
    )


def skinning_figures(args) -> dict:
    """The packed call against the loop on batch B, after compiling the packed function on batch A."""
    frames, method = args.frames, args.method
    made, _ = phase("models generated (A and B)", lambda: batches(args.models, tuple(args.vertices)))
    first, second = made["A"], made["B"]
    describe("A", first)
    describe("B", second)

    print("packed, batch A (compiles for its capacities):", flush=True)
    packed_a, _ = phase("pack_models(A)", lambda: deform.pack_models(first))
    _, packed_a_cold = phase(
        "skin_packed(A), compile and run", lambda: deform.skin_packed(packed_a, packed_a.frame_times(frames), method)
    )
    print(f"  capacities {packed_a.capacities}", flush=True)

    print("a new batch B, as a user runs it:", flush=True)

    def packed_new_batch():
        packed = deform.pack_models(second, at_least=packed_a.capacities)
        return packed, packed.unpack(deform.skin_packed(packed, packed.frame_times(frames), method))

    (packed_b, packed_frames), packed_new = phase(
        "packed: pack_models(B, at_least=A) + skin_packed + unpack", packed_new_batch
    )
    reused = packed_b.capacities == packed_a.capacities
    print(f"  B fits A's capacities (the compiled function reused): {reused}", flush=True)
    times = packed_b.frame_times(frames)
    packed_pack = phase(
        "  of which pack_models(B, at_least=A)", lambda: deform.pack_models(second, at_least=packed_a.capacities)
    )[1]
    functions = loop_functions(second, method)
    loop_frames, loop_new = phase(
        "loop: jit(vmap(skin_model)) per model, each compiled and run", lambda: run_loop(functions, times)
    )
    difference = max_relative_difference(second, packed_frames, loop_frames)
    print(f"  max |packed - loop| / model diagonal: {difference:.1e}", flush=True)
    del packed_frames, loop_frames

    print(f"warm, both compiled (median of {args.repeats}, interleaved):", flush=True)
    warm = interleaved_medians(
        {
            "packed": lambda: deform.skin_packed(packed_b, times, method),
            "loop": lambda: run_loop(functions, times),
        },
        args.repeats,
    )
    print(f"  packed {warm['packed']:.3f} s, loop {warm['loop']:.3f} s", flush=True)

    print("first batch, both cold (caches cleared):", flush=True)
    jax.clear_caches()

    def packed_first_batch():
        packed = deform.pack_models(second)
        return packed, packed.unpack(deform.skin_packed(packed, packed.frame_times(frames), method))

    (own, _), packed_first = phase("packed: pack_models(B) + skin_packed (compile) + unpack", packed_first_batch)

    vertices = sum(m.mesh.num_vertices for m in second)
    figures = {
        "models": len(second),
        "frames": frames,
        "vertices_total": vertices,
        "loop_new_batch_s": loop_new,
        "packed_new_batch_s": packed_new,
        "packed_new_batch_pack_s": packed_pack,
        "packed_first_batch_s": packed_first,
        "packed_first_batch_a_s": packed_a_cold,
        "loop_warm_s": warm["loop"],
        "packed_warm_s": warm["packed"],
        "packed_warm_vertex_frames_per_s": vertices * frames / warm["packed"],
        "padding_1_block": own.padding,
        "padding_new_batch": packed_b.padding,
        "max_difference_vs_loop": difference,
    }
    ratios = {
        "packed_vs_loop": loop_new / packed_new,
        "packed_vs_loop_first_batch": loop_new / packed_first,
        "packed_vs_loop_warm": warm["loop"] / warm["packed"],
    }
    print(
        f"packed_vs_loop (new batch B, the packed function compiled on A; the issue's figure): "
        f"{ratios['packed_vs_loop']:.1f}\n"
        f"packed_vs_loop_first_batch (both cold): {ratios['packed_vs_loop_first_batch']:.1f}\n"
        f"packed_vs_loop_warm (both compiled, run time only): {ratios['packed_vs_loop_warm']:.2f}\n"
        f"padding: 1 block {own.padding:.3f}, B at A's capacities {packed_b.padding:.3f}",
        flush=True,
    )
    units = {name: "s" for name in figures if name.endswith("_s")}
    units |= {"models": "models", "frames": "frames", "vertices_total": "vertices"}
    units |= {"packed_warm_vertex_frames_per_s": "vertex-frames/s", "max_difference_vs_loop": "model diagonals"}
    units |= {name: "x (padded work / real work)" for name in figures if name.startswith("padding")}
    return {"figures": figures, "ratios": ratios, "units": units | {name: RATIO_UNIT for name in ratios}}


def sharded_child(args, out: Path):
    """In the process with forced host devices: B on ``args.devices`` blocks over the mesh against one block on
    one device; writes the figures to ``out``."""
    if jax.device_count() < args.devices:
        raise SystemExit(f"--devices {args.devices}: this process sees {jax.device_count()} devices")
    models = batches(args.models, tuple(args.vertices), "B")["B"]
    mesh = jax.make_mesh((args.devices, 1), ("models", "time"))
    sharded = deform.pack_models(models, blocks=args.devices)
    single = deform.pack_models(models)
    times = single.frame_times(args.frames)
    fns = {
        "sharded": lambda: deform.skin_packed(sharded, times, args.method, mesh=mesh),
        "single": lambda: deform.skin_packed(single, times, args.method),
    }
    result = {name: phase(f"{name}: compile and run", fn)[0] for name, fn in fns.items()}
    difference = max_relative_difference(models, sharded.unpack(result["sharded"]), single.unpack(result["single"]))
    del result
    warm = interleaved_medians(fns, args.repeats)
    print(
        f"  {args.devices} devices {warm['sharded']:.3f} s, 1 device {warm['single']:.3f} s (warm medians); "
        f"max |sharded - single| / model diagonal {difference:.1e}",
        flush=True,
    )
    out.write_text(
        json.dumps(
            {
                "sharded_warm_s": warm["sharded"],
                "single_warm_s": warm["single"],
                "padding_blocks": sharded.padding,
                "difference": difference,
            }
        )
    )


def sharded_figures(args) -> dict:
    """``sharded_child`` in a subprocess: the forced device count must be set before JAX initializes."""
    n = args.devices
    if platform() != "cpu":
        print(f"sharded over {n} host devices: skipped (runs on the CPU platform only)", flush=True)
        return {"figures": {}, "ratios": {}, "units": {}}
    print(f"sharded over {n} forced host devices (a subprocess; {os.cpu_count()} cores):", flush=True)
    env = dict(os.environ)
    env["XLA_FLAGS"] = f"{env.get('XLA_FLAGS', '')} --xla_force_host_platform_device_count={n}".strip()
    with tempfile.TemporaryDirectory() as folder:
        out = Path(folder) / "sharded.json"
        sizes = ["--models", str(args.models), "--frames", str(args.frames), "--vertices", *map(str, args.vertices)]
        sizes += ["--method", args.method, "--devices", str(n), "--repeats", str(args.repeats)]
        command = [sys.executable, __file__, "--sharded-child", str(out), *sizes]
        start = time.perf_counter()
        subprocess.run(command, env=env, check=True)
        print(f"  subprocess: {time.perf_counter() - start:.2f} s", flush=True)
        child = json.loads(out.read_text())
    ratio = child["single_warm_s"] / child["sharded_warm_s"]
    print(f"sharded_{n}_vs_1: {ratio:.2f}; padding with {n} blocks {child['padding_blocks']:.3f}", flush=True)
    figures = {
        f"sharded_{n}_warm_s": child["sharded_warm_s"],
        "sharded_1_warm_s": child["single_warm_s"],
        f"padding_{n}_blocks": child["padding_blocks"],
        f"max_difference_sharded_{n}_vs_1": child["difference"],
    }
    units = {
        f"sharded_{n}_warm_s": "s",
        "sharded_1_warm_s": "s",
        f"padding_{n}_blocks": "x (padded work / real work)",
        f"max_difference_sharded_{n}_vs_1": "model diagonals",
        f"sharded_{n}_vs_1": RATIO_UNIT,
    }
    return {"figures": figures, "ratios": {f"sharded_{n}_vs_1": ratio}, "units": units}


def merged(sections: list[dict]) -> dict:
    return {
        key: {k: v for section in sections for k, v in section[key].items()} for key in ("figures", "ratios", "units")
    }


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", type=int, default=64, help="models per batch (default 64)")
    parser.add_argument("--frames", type=int, default=100, help="frames per model (default 100)")
    parser.add_argument(
        "--vertices", type=int, nargs=2, default=(1_000, 50_000), help="random rigs' vertex range (default 1000 50000)"
    )
    parser.add_argument("--method", default="cga", choices=deform.METHODS, help="skinning method (default cga)")
    parser.add_argument("--devices", type=int, default=4, help="forced host devices of the sharded part (default 4)")
    parser.add_argument("--repeats", type=int, default=3, help="timed repetitions of the warm calls (default 3)")
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke test")
    parser.add_argument(
        "--figures",
        nargs="+",
        choices=FIGURES,
        default=list(FIGURES),
        help="skinning: the packed call against the loop; sharded: over forced host devices; fit: fit_packed "
        "against a loop of fit_pose (default: all)",
    )
    parser.add_argument("--sharded-child", type=Path, default=None, help=argparse.SUPPRESS)
    add_json_argument(parser)
    args = parser.parse_args(argv)
    if args.quick:
        args.models, args.frames, args.vertices, args.repeats = 4, 8, (500, 2_000), 1
    if args.sharded_child is not None:
        sharded_child(args, args.sharded_child)
        return 0
    print_device("bench_batch")
    start = time.perf_counter()
    # a few models: the vmapped solve costs minutes per call on 2 CPU cores at 8 models (benchmarks/README.md)
    parts = {
        "fit": lambda: fit_figures(
            count=2 if args.quick else 4, targets_per_model=20 if args.quick else 100, repeats=args.repeats
        ),
        "skinning": lambda: skinning_figures(args),
        "sharded": lambda: sharded_figures(args),
    }
    result = merged([part() for name, part in parts.items() if name in args.figures])
    print(f"bench_batch: {time.perf_counter() - start:.0f} s in all", flush=True)
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
