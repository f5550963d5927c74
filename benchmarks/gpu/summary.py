"""The GPU figures of issue 32 (item 5) from one ``bench_gpu.sh`` run, each beside its target: the lines for the
closing note. Usage: ``python benchmarks/gpu/summary.py FOLDER`` (the folder of the run's JSON files)."""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path

# (JSON file, a pattern for the names, the target: at least or at most the bound)
TARGETS = [
    ("kernel", r"per_point_f64_vs_matrix_gpu", ">=", 1.0),
    ("kernel", r"per_point_f64_vs_kingdon_gpu", ">=", 1.5),
    ("kernel", r"per_point_f64_points_per_s_gpu", ">=", 2e10),
    ("skinning", r"cga_vs_lbs_(\d+_poses_)?f(32|64)_gpu", ">=", 0.9),
    ("skinning", r"cga_motor_blend_vs_dqs_(\d+_poses_)?f(32|64)_gpu", ">=", 0.9),
    ("deform", r"(spline|handles|ffd|cage)_vs_\w+_f(32|64)_gpu", ">=", 0.9),
    ("arap", r"iteration_(spokes_and_rims_)?100k_ms_gpu", "<=", 5.0),
    ("fem", r"step_23k_s_gpu", "<=", 0.05),
    ("xfem", r"accordion_step_avg_s_gpu", "<=", 0.05),
]
# untargeted figures printed beside them: what the accordion's average frame is made of (the GPU's steps, the
# host's cuts), and the FEM step's formulations not chosen on a GPU (the CPU's chunks of elements, the CG's
# product over entries instead of blocks) beside the chosen ones
PARTS = [
    ("xfem", r"accordion_(uncut_step_avg|cut_work|total)_s_gpu"),
    ("fem", r"step_cpu_chunks_23k_s_gpu|(hessians|device_cg(_entries)?_solve)_23k_ms_gpu"),
]


def lines(folder: Path) -> list[str]:
    """One line per targeted figure found (name, value, target, whether it holds), and one per missing file or
    name."""
    out = []
    loaded = {}
    for file, pattern, op, bound in TARGETS:
        if file not in loaded:
            path = folder / f"{file}.json"
            loaded[file] = json.loads(path.read_text()) if path.exists() else None
            if loaded[file] is not None:
                out.append(f"{file}.json: {loaded[file].get('platform')}, {loaded[file].get('device')}")
        result = loaded[file]
        if result is None:
            out.append(f"  {file}.json missing: no {pattern}")
            continue
        found = {
            name: value
            for key in ("figures", "ratios")
            for name, value in result[key].items()
            if re.fullmatch(pattern, name)
        }
        if not found:
            out.append(f"  {file}.json has no {pattern}")
        for name, value in found.items():
            holds = value >= bound if op == ">=" else value <= bound
            out.append(f"  {name:44s} {value:12.4g}  target {op} {bound:g}  {'holds' if holds else 'MISSES'}")
    for file, pattern in PARTS:
        result = loaded.get(file)
        if result is not None:
            out.extend(
                f"  {name:44s} {value:12.4g}  (no target)"
                for key in ("figures", "ratios")
                for name, value in result[key].items()
                if re.fullmatch(pattern, name)
            )
    return out


if __name__ == "__main__":
    print("\n".join(lines(Path(sys.argv[1] if len(sys.argv) > 1 else "out/bench-gpu"))))
