"""The benchmark scripts run (in their small --quick mode) and write the JSON names the issues
promise. Speed itself is not asserted here: it is measured by `make bench`.

Marked slow (each run compiles the benchmark's whole set of kernels in a fresh process): `make test` leaves them
out, `make test-slow` runs them (with the notebooks), and CI (`.ci/run`) runs both."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _quick(script: str, tmp_path) -> dict:
    """Run ``benchmarks/<script> --quick`` and read back its JSON."""
    out = tmp_path / "result.json"
    done = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick", "--json", str(out)],
                          capture_output=True, text=True, timeout=600, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    return json.loads(out.read_text())


def test_bench_skinning_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_skinning.py", tmp_path)
    for name in ("cga_vs_lbs_f32", "cga_vs_lbs_f64", "cga_sum_then_project_vs_lbs_f32",
                 "cga_sum_then_project_vs_lbs_f64",
                 "cga_motor_blend_vs_dqs_f32", "cga_motor_blend_vs_dqs_f64"):
        assert result["ratios"][name] > 0
    for name in ("cga_20_poses_f32_s", "lbs_20_poses_f32_s"):  # cga_1000_poses_f32_s with the default --poses
        assert result["figures"][name] > 0 and name in result["units"]


def test_bench_cutting_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_cutting.py", tmp_path)
    for name in ("arm5_cut_ms", "arm5_cut_ga_ms", "arm5_tear_ms", "arm5_tear_ga_ms", "arm5_drill_ms",
                 "arm5_preprocess_ms", "100k_cut_ms", "100k_tear_ms", "100k_drill_ms", "100k_preprocess_ms"):
        assert result["figures"][name] > 0 and name in result["units"]
    for name in ("arm5_cut_vs_paper", "arm5_tear_vs_paper", "arm5_drill_vs_paper"):
        assert result["ratios"][name] > 0


def test_bench_arap_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_arap.py", tmp_path)
    for tag in ("10k", "40k"):
        # each energy against libigl's same energy; the names without an energy are the spokes energy's
        for key in (tag, f"spokes_{tag}", f"spokes_and_rims_{tag}"):
            assert result["ratios"][f"iteration_vs_igl_{key}"] > 0 and result["ratios"][f"precompute_vs_igl_{key}"] > 0
            # ours equals libigl's own iteration with double-precision rotations (arap_solve's are single)
            assert result["figures"][f"difference_vs_igl_float64_rotations_{key}"] < 1e-10


def test_bench_fem_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_fem.py", tmp_path)
    for name in ("step_1k_s", "step_7k_s", "step_23k_s"):
        assert result["figures"][name] > 0 and name in result["units"]
    for name in ("step_23k_vs_paper", "step_23k_vs_direct"):
        assert result["ratios"][name] > 0


def test_bench_xfem_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_xfem.py", tmp_path)
    for scene in ("sticks", "thin", "accordion"):
        for name in ("boolean_ms", "step_avg_s", "step_max_s", "integral_ms", "dpsi_ms", "cg_s", "cut_max_over_avg"):
            assert result["figures"][f"{scene}_{name}"] > 0 and f"{scene}_{name}" in result["units"]
        assert result["ratios"][f"{scene}_step_avg_vs_paper"] > 0
        # cuts only duplicate DOFs: the final count is the one reported in the Table 2 column
        dofs = result["figures"]
        assert dofs[f"{scene}_dofs_final"] > dofs[f"{scene}_dofs_initial"] > 0
        assert dofs[f"{scene}_dofs_final"] == dofs[f"{scene}_dofs"]
    assert result["figures"]["sticks_pieces"] == 36  # the small sticks end as 36 pieces too
    for name in ("thin_cut_system_grad_ms", "thin_host_cut_system_ms", "thin_cut_replay_grad_ms"):
        assert result["figures"][name] > 0 and name in result["units"]
