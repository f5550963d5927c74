"""Cutting benchmark: the planar cut (Algorithm 1) of Arm5 (5,037 faces) and of a 100k-face
subdivided Arm5, with the reusable preprocessing (adjacency: ``cutting.mesh_edges``) timed separately
and both predicate families of Table 1 (Euclidean and GA).

The large mesh is the first 100k faces of Arm5 after three midpoint subdivisions (a conforming patch).
The baseline is the paper's published timing on Arm5 (sec. 4.3: 4,666 ms to cut, on a 2.6 GHz Core i7);
ratios are baseline time / our time (> 1: we are faster). Tear and drill are not implemented yet.

    python benchmarks/bench_cutting.py [--repeats 50] [--json out/bench/cutting.json]
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
import cutting  # noqa: E402
import deform  # noqa: E402
from bench_skinning import subdivided_arm5  # noqa: E402

PAPER_MS = {"cut": 4666.0}


def median_ms(fn, repeats: int) -> float:
    fn()  # warm up (and compile the GA predicates)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def plane_through_middle(V) -> np.ndarray:
    """A plane across the mesh's longest extent, through its middle, slightly tilted."""
    V = np.asarray(V)
    axis = np.argmax(V.max(axis=0) - V.min(axis=0))
    n = np.full(3, 0.1)
    n[axis] = 1.0
    n /= np.linalg.norm(n)
    return np.append(n, float(np.median(V @ n)))


def run(repeats: int, faces_100k: int):
    arm = deform.load_model(ROOT / "tests" / "data" / "Arm5.glb").mesh
    big = subdivided_arm5(min_faces=faces_100k).mesh
    cases = {"arm5": arm, "100k": big}
    figures, ratios, units = {}, {}, {}
    for tag, mesh in cases.items():
        plane = plane_through_middle(mesh.V)
        edges = cutting.mesh_edges(mesh.F)
        figures[f"{tag}_preprocess_ms"] = median_ms(lambda: cutting.mesh_edges(mesh.F), repeats)
        for predicates in cutting.PREDICATES:
            suffix = "" if predicates == "euclidean" else "_ga"
            figures[f"{tag}_cut{suffix}_ms"] = median_ms(
                lambda: cutting.cut(mesh, plane, edges=edges, predicates=predicates), repeats)
        positive, negative = cutting.cut(mesh, plane, edges=edges)
        print(f"{tag}: {mesh.F.shape[0]} faces, {mesh.num_vertices} vertices; halves of {positive.F.shape[0]} "
              f"and {negative.F.shape[0]} faces")
        print(f"  preprocess (mesh_edges)  {figures[f'{tag}_preprocess_ms']:8.2f} ms")
        print(f"  cut, Euclidean predicates {figures[f'{tag}_cut_ms']:8.2f} ms")
        print(f"  cut, GA predicates        {figures[f'{tag}_cut_ga_ms']:8.2f} ms")
    for op, paper in PAPER_MS.items():
        ratios[f"arm5_{op}_vs_paper"] = paper / figures[f"arm5_{op}_ms"]
        print(f"ratio arm5_{op}_vs_paper: {ratios[f'arm5_{op}_vs_paper']:.0f}x (paper {paper:.0f} ms)")
    for name in figures:
        units[name] = "ms"
    for name in ratios:
        units[name] = "x (baseline time / ours)"
    return {"figures": figures, "ratios": ratios, "units": units}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50, help="timed repetitions per figure")
    parser.add_argument("--faces", type=int, default=100_000, help="faces of the large mesh (about)")
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke test")
    parser.add_argument("--json", type=Path, default=None, help="write figures, ratios and units here")
    args = parser.parse_args(argv)
    if args.quick:
        args.repeats, args.faces = 2, 20_000
    result = run(args.repeats, args.faces)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
