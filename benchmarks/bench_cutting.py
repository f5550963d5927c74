"""Cutting benchmark: the planar cut (Algorithm 1), the tear (Algorithm 2) and the drill (Algorithm 3)
of Arm5 (5,037 faces) and of a 100k-face refined Arm5, with the reusable preprocessing (adjacency:
``cutting.mesh_edges``) timed separately and both predicate families of Table 1 (Euclidean and GA)
for the cut and the tear.

The large mesh is Arm5, welded (glTF splits vertices along UV seams; a tear or a drill walks across
faces), with every face split in four twice, then the lowest faces once more up to 100k faces
(``cutting.refine``: conforming, weights blended as for every new vertex). On Arm5 the tear and the drill
run on the welded mesh, the cut on the file as loaded. The same tools act on both meshes: a scalpel
moved 6 units (about 7 Arm5 edges) over the skin, opening 0.2; a drill of radius 1.5 entering the skin
3 units deep.
The baseline is the paper's published timing on Arm5 (sec. 4.3: 4,666 ms to cut, 2,437 ms to tear,
274 ms to drill, Python on a 2.6 GHz Core i7); ratios are baseline time / our time (> 1: we are faster).

    python benchmarks/bench_cutting.py [--repeats 50] [--json out/bench/cutting.json]
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
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import cutting  # noqa: E402
import deform  # noqa: E402

PAPER_MS = {"cut": 4666.0, "tear": 2437.0, "drill": 274.0}


def median_ms(fn, repeats: int) -> float:
    fn()  # warm up (and compile the GA predicates)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def plane_through_middle(V) -> cutting.Plane:
    """A plane across the mesh's longest extent, through its middle, slightly tilted."""
    V = np.asarray(V)
    axis = np.argmax(V.max(axis=0) - V.min(axis=0))
    n = np.full(3, 0.1)
    n[axis] = 1.0
    n /= np.linalg.norm(n)
    return cutting.Plane(n, float(np.median(V @ n)))


def surface_point(V, F, near):
    """The point of the surface (V, F) closest to ``near`` and the unit normal of its face."""
    _, face, closest = igl.point_mesh_squared_distance(np.asarray(near, np.float64)[None], V, F)
    a, b, c = V[F[face[0]]]
    normal = np.cross(b - a, c - a)
    return closest[0], normal / np.linalg.norm(normal)


def tools(V, F) -> tuple[cutting.Scalpel, cutting.Drill]:
    """A scalpel (2 samples) crossing the skin near the middle of the mesh, moved 6 units along the arm,
    and a drill of radius 1.5 entering the skin there."""
    middle = 0.5 * (V.min(axis=0) + V.max(axis=0))
    start, normal = surface_point(V, F, middle + np.array([0.0, 0.0, 20.0]))
    end, normal_end = surface_point(V, F, start + np.array([0.0, 6.0, 0.0]))
    scalpel = cutting.Scalpel(
        np.array([start + 2.0 * normal, end + 2.0 * normal_end]),
        np.array([start - 2.0 * normal, end - 2.0 * normal_end]),
    )
    return scalpel, cutting.Drill(start - 3.0 * normal, start + 3.0 * normal, 1.5)


def refined_arm5(min_faces: int) -> deform.SkinnedMesh:
    """Welded Arm5 split (``cutting.refine``) to at least ``min_faces`` faces, as host arrays."""
    mesh = deform.weld(deform.load_model(ROOT / "tests" / "data" / "Arm5.glb").mesh)
    while 4 * mesh.F.shape[0] <= min_faces:
        mesh = cutting.refine(mesh)
    if mesh.F.shape[0] < min_faces:  # split the lowest faces once more (each adds at least 3)
        V, F = np.asarray(mesh.V), np.asarray(mesh.F)
        lowest = np.argsort(V[F].mean(axis=1)[:, 1])[: -(-(min_faces - len(F)) // 3)]
        mesh = cutting.refine(mesh, lowest)
    return mesh


def run(repeats: int, faces_100k: int):
    arm = deform.load_model(ROOT / "tests" / "data" / "Arm5.glb").mesh
    big = refined_arm5(faces_100k)
    cases = {"arm5": arm, "100k": big}
    figures, ratios, units = {}, {}, {}
    for tag, mesh in cases.items():
        plane = plane_through_middle(mesh.V)
        edges = cutting.mesh_edges(mesh.F)
        figures[f"{tag}_preprocess_ms"] = median_ms(lambda: cutting.mesh_edges(mesh.F), repeats)
        for predicates in cutting.PREDICATES:
            suffix = "" if predicates == "euclidean" else "_ga"
            figures[f"{tag}_cut{suffix}_ms"] = median_ms(
                lambda: cutting.cut(mesh, plane, edges=edges, predicates=predicates), repeats
            )
        positive, negative = cutting.cut(mesh, plane, edges=edges)
        print(
            f"{tag}: {mesh.F.shape[0]} faces, {mesh.num_vertices} vertices; halves of {positive.F.shape[0]} "
            f"and {negative.F.shape[0]} faces"
        )
        print(f"  preprocess (mesh_edges)  {figures[f'{tag}_preprocess_ms']:8.2f} ms")
        print(f"  cut, Euclidean predicates {figures[f'{tag}_cut_ms']:8.2f} ms")
        print(f"  cut, GA predicates        {figures[f'{tag}_cut_ga_ms']:8.2f} ms")
        welded = deform.weld(mesh) if tag == "arm5" else mesh
        welded = deform.SkinnedMesh(
            np.asarray(welded.V),
            np.asarray(welded.F),
            np.asarray(welded.J),
            np.asarray(welded.W),
            welded.inverse_bind,
            welded.joints,
        )
        welded_edges = cutting.mesh_edges(welded.F)
        scalpel, drill = tools(np.asarray(welded.V, np.float64), np.asarray(welded.F))
        for predicates in cutting.PREDICATES:
            suffix = "" if predicates == "euclidean" else "_ga"
            figures[f"{tag}_tear{suffix}_ms"] = median_ms(
                lambda: cutting.tear(welded, scalpel, opening=0.2, edges=welded_edges, predicates=predicates), repeats
            )
        figures[f"{tag}_drill_ms"] = median_ms(lambda: cutting.drill(welded, drill, edges=welded_edges), repeats)
        _, path = cutting.tear(welded, scalpel, opening=0.2, edges=welded_edges, return_topology=True)
        _, hole = cutting.drill(welded, drill, edges=welded_edges, return_topology=True)
        print(f"  tear, Euclidean predicates {figures[f'{tag}_tear_ms']:7.2f} ms  ({len(path.t)} tear points)")
        print(f"  tear, GA predicates       {figures[f'{tag}_tear_ga_ms']:8.2f} ms")
        print(
            f"  drill                     {figures[f'{tag}_drill_ms']:8.2f} ms  ({len(hole.points)} hole points, "
            f"{hole.refinements} refinements)"
        )
    for op, paper in PAPER_MS.items():
        ratios[f"arm5_{op}_vs_paper"] = paper / figures[f"arm5_{op}_ms"]
        print(f"ratio arm5_{op}_vs_paper: {ratios[f'arm5_{op}_vs_paper']:.0f}x (paper {paper:.0f} ms)")
    for name in figures:
        units[name] = "ms"
    for name in ratios:
        units[name] = RATIO_UNIT
    return {"figures": figures, "ratios": ratios, "units": units}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50, help="timed repetitions per figure")
    parser.add_argument("--faces", type=int, default=100_000, help="faces of the large mesh (about)")
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke test")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_cutting")
    if args.quick:
        args.repeats, args.faces = 2, 20_000
    result = run(args.repeats, args.faces)
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
