"""ARAP benchmark (deformation paper sec. VII) against libigl's Python bindings in the same run: the
precompute and the time per iteration on ~10k- and ~40k-vertex meshes (welded Arm5, midpoint
subdivided), for both energies (spokes and rims, the default, and the paper's spokes), each against
libigl's same energy, the shoulder fixed and the hand moved and turned.

Per iteration: ours is ``arap_solve`` jitted with a fixed iteration count (``tolerance=None``, plain
iterations as libigl's: ``acceleration="none"``), K iterations timed and divided by K; libigl's ``arap_solve``
with ``max_iter = K`` likewise.
Medians over interleaved repeats. Ratios are baseline time / ours (> 1: we are faster). Names carry the
energy (``iteration_vs_igl_spokes_and_rims_10k``, ``iteration_vs_igl_spokes_10k``, ...); the names
without one (``iteration_vs_igl_10k``, ...) are the spokes energy's, as before both energies existed.

Sizes: ``--vertices`` (default 10000 40000; on a GPU 100000), each named by its thousands (``_100k``).

    python benchmarks/bench_arap.py [--vertices 10000 40000] [--iterations 10] [--repeats 5] [--quick]
                                    [--json out/bench/arap.json]
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
import trimesh  # noqa: E402
from scipy.spatial.transform import Rotation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import deform  # noqa: E402
from tests.deform._arap_reference import libigl_arap_in_numpy  # noqa: E402


def subdivided_arm5(min_vertices: int):
    """Welded Arm5, midpoint-subdivided until it has at least ``min_vertices`` vertices: (V, F)."""
    mesh = deform.load_model(ROOT / "tests" / "data" / "Arm5.glb", weld=True).mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    while len(V) < min_vertices:
        V, F = trimesh.remesh.subdivide(V, F)
    return V, F


def handles(V):
    """Fixed shoulder (y < 2), hand (y > 60) turned by 40 degrees about x and lifted: (b, bc)."""
    y = V[:, 1]
    fixed, hand = np.flatnonzero(y < 2.0), np.flatnonzero(y > 60.0)
    pivot = np.array([0.0, 55.0, 0.0])
    moved = Rotation.from_rotvec([np.radians(40), 0, 0]).apply(V[hand] - pivot) + pivot + [0.0, 0.0, 5.0]
    return np.concatenate([fixed, hand]), np.concatenate([V[fixed], moved])


def timed(fn, repeats: int):
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


ENERGIES = {"spokes_and_rims": igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS, "spokes": igl.ARAP_ENERGY_TYPE_SPOKES}
OLD_NAMES = "spokes"  # the energy of the names without an energy (the benchmark's only one before)


def run(sizes: dict, iterations: int, repeats: int):
    figures, ratios, units = {}, {}, {}
    for tag, size in sizes.items():
        V, F = subdivided_arm5(size)
        b, bc = handles(V)
        U0 = V.copy()
        U0[b] = bc
        diag = np.linalg.norm(np.ptp(V, axis=0))
        for energy, igl_energy in ENERGIES.items():

            def igl_precompute():
                data = igl.ARAPData()
                data.energy = igl_energy
                data.max_iter = iterations
                igl.arap_precomputation(V, F, 3, b, data)
                return data

            data_igl = igl_precompute()
            ours = deform.arap_precompute(V, F, b, energy=energy)
            solve = jax.jit(
                lambda c, x0, ours=ours: (
                    deform.arap_solve(ours, c, V0=x0, max_iterations=iterations, tolerance=None, acceleration="none").U
                )
            )
            # the handles and first guess on the device before timing: an iteration's time, not the copies (on a
            # GPU 2.4 MB each way at 100k vertices)
            bc_device, U0_device = jax.device_put(jnp.asarray(bc)), jax.device_put(jnp.asarray(U0))
            jax.block_until_ready(solve(bc_device, U0_device))
            U = np.asarray(solve(bc_device, U0_device))
            difference = np.abs(U - igl.arap_solve(bc, data_igl, U0)).max() / diag
            # libigl's algorithm with its double-precision rotation fit (arap_solve's is single precision)
            exact = np.abs(U - libigl_arap_in_numpy(V, F, b, bc, U0, iterations, False, energy)).max() / diag
            t = {"pre_ours": [], "pre_igl": [], "it_ours": [], "it_igl": []}
            for _ in range(repeats):
                t["pre_ours"].append(timed(lambda: deform.arap_precompute(V, F, b, energy=energy), 1))
                t["pre_igl"].append(timed(igl_precompute, 1))
                t["it_ours"].append(timed(lambda: jax.block_until_ready(solve(bc_device, U0_device)), 1) / iterations)
                t["it_igl"].append(timed(lambda: igl.arap_solve(bc, data_igl, U0), 1) / iterations)
            m = {k: statistics.median(v) for k, v in t.items()}
            key = f"{energy}_{tag}"
            new_figures = {
                f"precompute_{key}_s": (m["pre_ours"], "s"),
                f"precompute_igl_{key}_s": (m["pre_igl"], "s"),
                f"iteration_{key}_ms": (1e3 * m["it_ours"], "ms"),
                f"iteration_igl_{key}_ms": (1e3 * m["it_igl"], "ms"),
                f"difference_vs_igl_{key}": (difference, "diagonal"),
                f"difference_vs_igl_float64_rotations_{key}": (exact, "diagonal"),
            }
            new_ratios = {
                f"iteration_vs_igl_{key}": m["it_igl"] / m["it_ours"],
                f"precompute_vs_igl_{key}": m["pre_igl"] / m["pre_ours"],
            }
            if energy == OLD_NAMES:
                new_figures |= {name.replace(key, tag): value for name, value in new_figures.items()}
                new_ratios |= {name.replace(key, tag): value for name, value in new_ratios.items()}
            figures.update({name: value for name, (value, _) in new_figures.items()})
            units.update({name: unit for name, (_, unit) in new_figures.items()})
            ratios.update(new_ratios)
            print(
                f"{tag} ({len(V)} vertices), {energy}: precompute ours {m['pre_ours']:.3f} s, igl "
                f"{m['pre_igl']:.3f} s -> {ratios[f'precompute_vs_igl_{key}']:.2f}x; per iteration ours "
                f"{1e3 * m['it_ours']:.2f} ms, igl {1e3 * m['it_igl']:.2f} ms -> "
                f"{ratios[f'iteration_vs_igl_{key}']:.2f}x; after {iterations} iterations ours - igl.arap_solve = "
                f"{difference:.1e} of the diagonal, ours - libigl's iteration with float64 rotations = {exact:.1e}"
            )
        figures[f"vertices_{tag}"] = float(len(V))
        units[f"vertices_{tag}"] = "count"
    return {"figures": figures, "ratios": ratios, "units": units | {k: RATIO_UNIT for k in ratios}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--vertices",
        type=int,
        nargs="+",
        default=[10_000, 40_000],
        help="at least this many mesh vertices, one size each (default 10000 40000)",
    )
    parser.add_argument("--iterations", type=int, default=10, help="ARAP iterations per timed solve")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (medians)")
    parser.add_argument("--quick", action="store_true", help="3 iterations, one repeat (a smoke run for the tests)")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_arap")
    iterations, repeats = (3, 1) if args.quick else (args.iterations, args.repeats)
    if min(args.vertices) < 1:
        parser.error("--vertices: expected positive counts")
    write_json(
        args.json, run({f"{n // 1000}k" if n >= 1000 else str(n): n for n in args.vertices}, iterations, repeats)
    )


if __name__ == "__main__":
    main()
