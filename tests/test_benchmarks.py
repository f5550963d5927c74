"""The benchmark scripts run (in their small --quick mode) and write the JSON names the issues
promise, suffixed ``_gpu`` on a GPU. Speed itself is not asserted here: it is measured by `make bench`.

The smoke runs are marked slow (each compiles the benchmark's whole set of kernels in a fresh process): `make test`
leaves them out, `make test-slow` runs them (with the notebooks), and CI (`.ci/run`) runs both."""

from __future__ import annotations

import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import jax
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(ROOT / "benchmarks"), str(ROOT / "benchmarks" / "gpu")]
import _report  # noqa: E402


def _quick(script: str, tmp_path, *args: str) -> dict:
    """Run ``benchmarks/<script> --quick ARGS`` and read back its JSON."""
    out = tmp_path / "result.json"
    done = subprocess.run(
        [sys.executable, str(ROOT / "benchmarks" / script), "--quick", *args, "--json", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result = json.loads(out.read_text())
    assert result["platform"] == jax.default_backend() and result["device"] == jax.devices()[0].device_kind
    return _unsuffixed(result)


def _unsuffixed(result: dict) -> dict:
    """``result``'s names without this platform's suffix (none on the CPU), every name checked to carry it."""
    end = _report.suffix()
    for key in ("figures", "ratios", "units"):
        assert all(name.endswith(end) for name in result[key])
    return {
        key: {name[: len(name) - len(end)]: v for name, v in result[key].items()}
        for key in ("figures", "ratios", "units")
    }


def test_names_carry_the_gpu_suffix_on_a_gpu_only():
    result = {
        "figures": {"step_23k_s": 0.5},
        "ratios": {"step_23k_vs_paper": 11.6},
        "units": {"step_23k_s": "s", "step_23k_vs_paper": _report.RATIO_UNIT},
    }
    on_cpu, on_gpu = _report.with_suffix(result, "cpu"), _report.with_suffix(result, "gpu")
    assert {key: on_cpu[key] for key in result} == result and on_cpu["platform"] == "cpu"
    assert on_gpu["figures"] == {"step_23k_s_gpu": 0.5} and on_gpu["ratios"] == {"step_23k_vs_paper_gpu": 11.6}
    assert on_gpu["units"] == {"step_23k_s_gpu": "s", "step_23k_vs_paper_gpu": _report.RATIO_UNIT}
    assert on_gpu["platform"] == "gpu" and on_gpu["device"] == jax.devices()[0].device_kind
    assert _report.suffix("cpu") == "" and _report.suffix("gpu") == "_gpu"


def test_bench_kernel_takes_points_and_writes_this_platforms_names(tmp_path, capsys):
    """A tiny size in this process (one compile of each candidate, no fresh interpreter): the platform and the
    device are printed and recorded, the names suffixed for this platform (the CPU's: none, as before)."""
    import bench_kernel

    assert bench_kernel.main(["--points", "64", "--repeats", "1", "--json", str(tmp_path / "kernel.json")]) == 0
    printed = capsys.readouterr().out
    assert f"bench_kernel: {jax.default_backend()}, {jax.devices()[0].device_kind}" in printed
    assert "64 points" in printed
    written = json.loads((tmp_path / "kernel.json").read_text())
    result = _unsuffixed(written)
    assert result["ratios"]["per_point_f64_vs_matrix"] > 0 and result["figures"]["per_point_f64_points_per_s"] > 0
    if jax.default_backend() == "cpu":
        assert "per_point_f64_vs_kingdon" in written["ratios"]  # the CPU's JSON names are unchanged


@pytest.mark.slow
def test_bench_skinning_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_skinning.py", tmp_path)
    for name in (
        "cga_vs_lbs_f32",
        "cga_vs_lbs_f64",
        "cga_sum_then_project_vs_lbs_f32",
        "cga_sum_then_project_vs_lbs_f64",
        "cga_motor_blend_vs_dqs_f32",
        "cga_motor_blend_vs_dqs_f64",
    ):
        assert result["ratios"][name] > 0
    for name in ("cga_20_poses_f32_s", "lbs_20_poses_f32_s"):  # cga_1000_poses_f32_s with the default --poses
        assert result["figures"][name] > 0 and name in result["units"]


@pytest.mark.slow
def test_bench_cutting_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_cutting.py", tmp_path)
    for name in (
        "arm5_cut_ms",
        "arm5_cut_ga_ms",
        "arm5_tear_ms",
        "arm5_tear_ga_ms",
        "arm5_drill_ms",
        "arm5_preprocess_ms",
        "100k_cut_ms",
        "100k_tear_ms",
        "100k_drill_ms",
        "100k_preprocess_ms",
        "real_cut_ms",
        "real_tear_ms",
        "real_drill_ms",
        "real_skin_ms",
        "real_trimesh_slice_ms",
        "real_tetrahedralize_ms",
        "real_tets",
        "real_tets_min_dihedral_deg",
        "real_tets_min_volume_ratio",
    ):
        assert result["figures"][name] > 0 and name in result["units"]
    for name in (
        "arm5_cut_vs_paper",
        "arm5_tear_vs_paper",
        "arm5_drill_vs_paper",
        "real_cut_vs_trimesh_slice",
        "real_tear_vs_skinning",
        "real_drill_vs_skinning",
        "arm5_ga_vs_euclidean",
        "cylinder_ga_vs_euclidean",
    ):
        assert result["ratios"][name] > 0
    assert result["figures"]["cylinder_table1_intersections_ga_ms"] > 0


def test_bench_cutting_table1_times_each_subroutine_with_both_predicates(capsys):
    """Table 1 in this process, one repetition: the cut's sub-routines compose to ``cutting.cut`` with either
    predicate family and make the same cut (``table1`` checks both), each timed on both models."""
    import bench_cutting

    result = bench_cutting.table1(repeats=1)
    printed = capsys.readouterr().out
    for tag in ("arm5", "cylinder"):
        assert f"Table 1, {tag}" in printed and f"ratio {tag}_ga_vs_euclidean" in printed
        for name in ("sides", "intersections", "weights", "split", "cut"):
            for family in ("", "_ga"):
                assert result["figures"][f"{tag}_table1_{name}{family}_ms"] > 0
        assert result["figures"][f"{tag}_intersection_points"] > 10
        assert result["units"][f"{tag}_intersection_points"] == "points"
        assert result["ratios"][f"{tag}_ga_vs_euclidean"] > 0


@pytest.mark.slow
def test_bench_arap_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_arap.py", tmp_path, "--vertices", "3000", "10000")
    for tag in ("3k", "10k"):
        # each energy against libigl's same energy; the names without an energy are the spokes energy's
        for key in (tag, f"spokes_{tag}", f"spokes_and_rims_{tag}"):
            assert result["ratios"][f"iteration_vs_igl_{key}"] > 0 and result["ratios"][f"precompute_vs_igl_{key}"] > 0
            # ours equals libigl's own iteration with double-precision rotations (arap_solve's are single)
            assert result["figures"][f"difference_vs_igl_float64_rotations_{key}"] < 1e-10


@pytest.mark.slow
def test_bench_fem_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_fem.py", tmp_path)
    for name in ("step_1k_s", "step_7k_s", "step_23k_s"):
        assert result["figures"][name] > 0 and name in result["units"]
    only = _quick("bench_fem.py", tmp_path, "--sizes", "23k")  # the GPU set's one size
    assert {name for name in only["figures"] if name.startswith("step_")} >= {"step_23k_s"}
    assert not any(name.endswith(("_1k_s", "_7k_s")) for name in only["figures"])
    for name in ("step_23k_vs_paper", "step_23k_vs_direct"):
        assert result["ratios"][name] > 0


@pytest.mark.slow
def test_bench_xfem_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_xfem.py", tmp_path)
    for scene in ("sticks", "thin", "accordion", "octopus"):
        for name in (
            "boolean_ms",
            "step_avg_s",
            "step_max_s",
            "integral_ms",
            "dpsi_ms",
            "cg_s",
            "cut_max_over_avg",
            "cut_work_s",
            "async_cut_max_over_avg",
        ):
            assert result["figures"][f"{scene}_{name}"] > 0 and f"{scene}_{name}" in result["units"]
        assert result["ratios"][f"{scene}_step_avg_vs_paper"] > 0
        # cuts only duplicate DOFs: the final count is the one reported in the Table 2 column
        dofs = result["figures"]
        assert dofs[f"{scene}_dofs_final"] > dofs[f"{scene}_dofs_initial"] > 0
        assert dofs[f"{scene}_dofs_final"] == dofs[f"{scene}_dofs"]
    assert result["figures"]["sticks_pieces"] == 36  # the small sticks end as 36 pieces too
    # Table 2's RXFEM column beside ours, on the 5 cuts that cross no earlier one (RXFEM makes no intersecting cut)
    figures = result["figures"]
    for name in ("dofs", "dpsi_ms", "step_avg", "step_max", "total"):
        assert figures[f"sticks_rxfem_{name}"] > 0 and figures[f"sticks_ours_{name}"] > 0
    assert figures["sticks_rxfem_dofs"] == figures["sticks_ours_dofs"]
    assert (figures["sticks_rxfem_cuts"], figures["sticks_rxfem_cuts_left_out"]) == (5, 5)
    assert figures["sticks_rxfem_element_rows"] > figures["sticks_ours_element_rows"]
    assert result["ratios"]["sticks_ours_vs_rxfem"] > 0 and "sticks_ours_vs_rxfem" in result["units"]
    table_only = _quick("bench_xfem.py", tmp_path, "--scenes", "sticks", "--figures", "table", "--no-background")
    assert table_only["figures"]["sticks_step_avg_s"] > 0 and "sticks_async_step_avg_s" not in table_only["figures"]
    for name in ("thin_cut_system_grad_ms", "thin_host_cut_system_ms", "thin_cut_replay_grad_ms"):
        assert result["figures"][name] > 0 and name in result["units"]
    # the differentiable rollouts: 100 and 1,000 steps in the full run, 10 and 20 here
    for name in ("accordion_rollout_10_s", "accordion_grad_10_s", "accordion_grad_20_peak_rss_gib"):
        assert result["figures"][name] > 0 and name in result["units"]
    assert result["ratios"]["accordion_grad_vs_forward_10"] > 0


@pytest.mark.slow
def test_bench_physics_quick_writes_the_published_names(tmp_path):
    """Issue 53's names, for the arm and the character (the fox, coarse, in the quick run); the tets cached."""
    result = _quick("bench_physics.py", tmp_path)
    for prefix in ("arm", "character"):
        for name in ("step_ms", "step_paper_ms", "reduced_fps", "reduced_error", "full_lag", "breakdown_solve_ms"):
            assert result["figures"][f"{prefix}_{name}"] > 0 and f"{prefix}_{name}" in result["units"]
        for name in ("grad_vs_forward", "step_vs_target", "reduced_fps_vs_target", "reduced_vs_full"):
            assert result["ratios"][f"{prefix}_{name}"] > 0
        # the reduced mode follows the full one more closely than the rig does
        assert result["figures"][f"{prefix}_reduced_error"] < result["figures"][f"{prefix}_full_lag"]
    assert sorted(path.name for path in tmp_path.glob("physics_tets_*.npz")) == [
        "physics_tets_arm_0.1_0.001.npz",
        "physics_tets_fox_0.1_0.001.npz",
    ]


@pytest.mark.slow
def test_bench_batch_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_batch.py", tmp_path)
    for name in ("packed_vs_loop", "packed_vs_loop_first_batch", "packed_vs_loop_warm"):
        assert result["ratios"][name] > 0 and name in result["units"]
    for name in ("loop_new_batch_s", "packed_new_batch_s", "packed_first_batch_s", "loop_warm_s", "packed_warm_s"):
        assert result["figures"][name] > 0 and name in result["units"]
    # padded work is never less than the real work; the packed frames are each model's own (float32)
    assert result["figures"]["padding_1_block"] >= 1.0 and result["figures"]["padding_new_batch"] >= 1.0
    assert result["figures"]["max_difference_vs_loop"] < 1e-5
    if jax.default_backend() == "cpu":  # the sharded part runs on forced host devices only
        assert result["ratios"]["sharded_4_vs_1"] > 0 and result["figures"]["sharded_4_warm_s"] > 0
        assert result["figures"]["padding_4_blocks"] >= 1.0
        assert result["figures"]["max_difference_sharded_4_vs_1"] < 1e-5


@pytest.mark.slow
def test_bench_viewer_quick_writes_the_published_names(tmp_path):
    from _jaxcga_shared.viewer.browser import chromium_missing

    missing = chromium_missing()
    if missing:
        pytest.skip(f"browser benchmark skipped: {missing}")
    result = _quick("bench_viewer.py", tmp_path)
    for name in ("viewer_fps_10k_20", "viewer_fps_paused_10k_20", "page_megabytes", "load_seconds", "json_fps_10k_10"):
        assert result["figures"][name] > 0 and name in result["units"]
    for name in ("load_vs_json", "megabytes_vs_json"):
        assert result["ratios"][name] > 0 and name in result["units"]
    assert result["ratios"]["megabytes_vs_json"] > 1  # int16 in base64 against numbers in text: smaller by design


def test_bench_fem_times_the_cpu_chunks_and_restores_them():
    """The GPU run's comparison step (the CPU's chunk sizes, ``bench_fem.cpu_chunked_steps``) times one step per
    state and leaves the step's chunk sizes as they were."""
    import bench_fem

    import xfem._backward_euler as be

    system, state = bench_fem.hanging_block((2, 2, 2))
    material = bench_fem.xfem.Material(bench_fem.YOUNG, bench_fem.POISSON)
    chunks = be._ELEMENT_CHUNK, be._MASS_CHUNK
    times = bench_fem.cpu_chunked_steps(system, [state, state], bench_fem.H, material)
    assert len(times) == 2 and min(times) > 0
    assert (be._ELEMENT_CHUNK, be._MASS_CHUNK) == chunks


def test_compile_for_gpu_reads_loops_and_conditionals_of_compiled_code():
    """``benchmarks/gpu/compile_for_gpu.py`` reads the host round trips from a compiled module: a conditional (and
    whether work waits for it), a loop of known trip count and one whose every iteration asks the host (here a CPU
    module, the same HLO text)."""
    import compile_for_gpu
    import jax.numpy as jnp

    def program(x):
        x = jax.lax.fori_loop(0, 3, lambda i, y: jnp.sin(y) * 2, x)
        x = jax.lax.while_loop(lambda y: y.sum() < 100, lambda y: y * 2 + jnp.cos(y), x)
        return jax.lax.cond(x.sum() > 0, lambda y: y + 1, lambda y: y - 1, x)

    def checked_first(x):
        return jnp.sin(jax.lax.cond(x.sum() > 0, lambda y: y + 1, lambda y: y - 1, x)) * x

    def compiled_text(f) -> str:
        text = jax.jit(f).lower(jnp.ones(5)).compile().as_text()
        assert text is not None, "the CPU backend gives the compiled module's text"
        return text

    launches, conditionals, waiting, loops = compile_for_gpu.structure(compiled_text(program))
    assert conditionals == 1 and waiting == 0 and launches >= 1  # the conditional is last: nothing waits for it
    assert [loop.trip_count for loop in loops] == [3, None]
    assert all(loop.launches >= 1 and loop.conditionals == 0 and not loop.loops for loop in loops)
    first = compile_for_gpu.structure(compiled_text(checked_first))
    assert first.conditionals == 1 and first.waiting == 1


# a thunk sequence as XLA dumps it for a GPU (shortened from an ARAP solve compiled for an H100)
_THUNKS = """001: kCopy          [source       | next=021 (6)] kCopy
003: kCustomKernel  [source       | next=004 (1)] input_reduce_fusion_5 grid: [14, 1, 1] threads: [256, 1, 1]
007: kConditional   [prev=004 (1) | next=000 (1)]
  false_branch:
    005: kCustomKernel [source | sink] loop_broadcast_fusion grid: [149, 1, 1] threads: [128, 1, 1]
  true_branch:
    006: kCopy [source | sink] kCopy
000: kCommandBuffer [prev=007 (1) | next=021 (1)]
    008: kCustomKernel [source       | next=009 (1)] input_scatter_fusion_2 grid: [149, 1, 1] threads: [128, 1, 1]
    009: kCustomKernel [prev=008 (1) | next=010 (1)] loop_subtract_fusion_3 grid: [2133, 1, 1] threads: [128, 1, 1]
021: kWhile         [prev=000 (1) | sink        ]
condition:
    022: kCustomKernel [source | sink] loop_compare_fusion grid: [1, 1, 1] threads: [1, 1, 1]
  body:
    000: kCommandBuffer [source       | next=042 (1)]
        023: kCopy         [source       | sink        ] kCopy
        025: kCustomKernel [source       | sink        ] loop_add_fusion_10 grid: [1, 1, 1] threads: [1, 1, 1]
    063: kCustomKernel  [prev=042 (1) | next=066 (1)] loop_not_fusion grid: [1, 1, 1] threads: [1, 1, 1]
"""


def test_compile_for_gpu_reads_cuda_graphs_from_the_thunk_sequence():
    """Launches inside command buffers (CUDA graphs) and those made one by one; a conditional's branches (a
    check's failure branch) are not counted."""
    import compile_for_gpu

    found = compile_for_gpu.graphs(_THUNKS)
    assert (found.graphs, found.in_graphs, found.alone) == (2, 4, 4)


# a kernel that keeps 40 doubles in registers: ptxas reports its registers and no spills
_PTX = """.version 8.0
.target sm_90a
.address_size 64
.visible .entry keep(.param .u64 out)
{
  .reg .b64 %rd<3>;
  .reg .f64 %fd<41>;
  ld.param.u64 %rd1, [out];
  cvta.to.global.u64 %rd2, %rd1;
"""
_PTX += "".join(f"  ld.global.f64 %fd{i}, [%rd2+{8 * i}];\n" for i in range(1, 41))
_PTX += "".join(f"  add.f64 %fd{i}, %fd{i}, %fd{i - 1};\n" for i in range(2, 41))
_PTX += "".join(f"  st.global.f64 [%rd2+{8 * i}], %fd{i};\n" for i in range(1, 41))
_PTX += "  ret;\n}\n"


@pytest.mark.skipif(shutil.which("ptxas") is None, reason="ptxas (the CUDA toolkit) is not on the PATH")
def test_compile_for_gpu_reads_registers_and_spills_from_ptxas(tmp_path):
    import compile_for_gpu

    path = tmp_path / "keep.ptx"
    path.write_text(_PTX)
    stats = compile_for_gpu.ptxas_statistics([path], {"keep"})
    assert set(stats) == {"keep"}
    registers, spills = stats["keep"]
    assert registers >= 10 and spills == 0
    assert compile_for_gpu.ptxas_statistics([path], {"other"}) == {}


_CUDA_PLUGIN = ROOT / ".cuda-plugin"


@pytest.mark.slow
@pytest.mark.skipif(
    not (_CUDA_PLUGIN / "jax_plugins").is_dir(), reason="no CUDA plugin in .cuda-plugin/ (make gpu-programs)"
)
def test_compile_for_gpu_compiles_the_triton_programs_for_an_h100(tmp_path):
    """With the plugin that ``make gpu-programs`` installs: the point map and the motor fields compile for an H100
    on this machine, each a Triton kernel that does not spill."""
    out = tmp_path / "programs.json"
    done = subprocess.run(
        [
            sys.executable,
            "benchmarks/gpu/compile_for_gpu.py",
            "--quick",
            "--only",
            "kernel",
            "deform",
            "--json",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=900,
        cwd=ROOT,
        env={**os.environ, "PYTHONPATH": str(_CUDA_PLUGIN), "JAX_PLATFORMS": "cpu"},
    )
    assert done.returncode == 0, done.stdout[-3000:] + done.stderr[-3000:]
    record = json.loads(out.read_text())
    assert record["failures"] == [] and record["spills"] == []
    programs = {p["name"]: p for p in record["programs"]}
    for name in ("apply_to_points, a motor per point, float64", "motor field ffd, float64"):
        assert programs[name]["launches"] >= 1 and programs[name]["triton"], name


def _write(path: Path, figures: dict, ratios: dict, units: dict) -> Path:
    path.write_text(json.dumps({"figures": figures, "ratios": ratios, "units": units}))
    return path


# before and after: name -> (section, old, new, unit); the comments say how each moved
_MOVES = {
    "cut_ms": ("figures", 10.0, 13.0, "ms"),  # 30% slower: worse
    "blend_vs_dqs": ("ratios", 1.0, 0.5, _report.RATIO_UNIT),  # half as fast against its baseline: worse, the worst
    "points_per_s": ("figures", 100.0, 125.0, "points/s"),  # 25% more: better
    "step_s": ("figures", 2.0, 1.7, "s (slowest frame)"),  # 15% faster: better; the unit's first word is a time
    "peak_gib": ("figures", 4.0, 4.6, "GiB (peak RSS)"),  # 15% more memory: worse
    "fps_f32": ("figures", 300.0, 200.0, "frames/s"),  # a third fewer frames: worse
    "padded_ratio": ("figures", 1.5, 3.0, _report.RATIO_UNIT),  # a ratio among the figures: doubled, better
    "dofs": ("figures", 100.0, 150.0, "count"),  # moved, no direction
    "noise_ms": ("figures", 10.0, 10.5, "ms"),  # 5%: below the default threshold
}


def _compare_files(tmp_path) -> tuple[Path, Path]:
    sides = []
    for index, side in ((1, "old"), (2, "new")):
        sections = {"figures": {}, "ratios": {}}
        for name, move in _MOVES.items():
            sections[move[0]][name] = move[index]
        sections["figures"][f"only_{side}_ms"] = 1.0
        units = {name: move[3] for name, move in _MOVES.items()} | {f"only_{side}_ms": "ms"}
        sides.append(_write(tmp_path / f"{side}.json", sections["figures"], sections["ratios"], units))
    return sides[0], sides[1]


def _listed(printed: str) -> dict[str, list[str]]:
    """The names under each heading of compare.py's output."""
    groups, heading = {}, None
    for line in printed.splitlines()[1:]:
        if line.startswith(("  ", "* ")):
            groups[heading].append(line[2:].split()[0] + line[0].strip())  # a name, marked * where its runs lie apart
        elif not line.startswith("marked *"):
            heading = line.split(" (")[0].split(":")[0]
            groups[heading] = []
    return groups


def test_compare_lists_the_worse_first_by_unit_then_the_better_then_the_rest(tmp_path, capsys):
    import compare

    old, new = _compare_files(tmp_path)
    assert compare.main([str(old), str(new)]) == 0
    printed = capsys.readouterr().out
    assert "9 figures and ratios on both sides, 8 moved by more than 10%" in printed.splitlines()[0]
    assert _listed(printed) == {
        "worse": ["blend_vs_dqs", "fps_f32", "cut_ms", "peak_gib"],  # the largest move first
        "better": ["padded_ratio", "points_per_s", "step_s"],
        "moved, the unit does not say which way is better": ["dofs"],
        f"only in {old}": ["only_old_ms"],
        f"only in {new}": ["only_new_ms"],
    }
    assert "-50.0%" in next(line for line in printed.splitlines() if "blend_vs_dqs" in line)


def test_compare_threshold(tmp_path, capsys):
    import compare

    old, new = _compare_files(tmp_path)
    compare.main([str(old), str(new), "--threshold", "0.04"])
    assert _listed(capsys.readouterr().out)["worse"] == ["blend_vs_dqs", "fps_f32", "cut_ms", "peak_gib", "noise_ms"]
    compare.main([str(old), str(new), "--threshold", "0.4"])
    listed = _listed(capsys.readouterr().out)
    assert listed["worse"] == ["blend_vs_dqs"] and listed["better"] == ["padded_ratio"]
    assert listed["moved, the unit does not say which way is better"] == ["dofs"]


def test_compare_direction_comes_from_the_unit_and_the_section():
    import compare

    for section, unit, sign in (
        ("ratios", "x (JSON page size / ours)", 1),
        ("figures", _report.RATIO_UNIT, 1),
        ("figures", "vertex-frames/s", 1),
        ("figures", "ms", -1),
        ("figures", "s (slowest frame while a background cut is under way)", -1),
        ("figures", "GiB (peak RSS of the process)", -1),
        ("figures", "count (after the cuts)", 0),
        ("figures", "x (padded work / real work)", 0),
        ("figures", None, 0),
    ):
        assert compare.direction(section, unit) == sign, (section, unit)


def test_best_of_runs_takes_each_names_better_value():
    """Times the smaller, rates the larger, ratios and no direction the median, NaN never; a name missing from a run
    kept; the spread of each name over the runs."""
    import compare

    units = {"t_ms": "ms", "rate": "points/s", "n": "count", "r": _report.RATIO_UNIT}
    runs = [
        {"figures": {"t_ms": 3.0, "rate": 10.0, "n": 1.0}, "ratios": {"r": 0.9}, "units": units, "device": "first"},
        {"figures": {"t_ms": 2.0, "rate": 30.0, "n": 5.0}, "ratios": {"r": 1.2}, "units": units, "device": "second"},
        {"figures": {"t_ms": 4.0, "rate": 20.0, "n": 2.0, "late_ms": 7.0}, "ratios": {"r": 1.0}, "units": units},
        {"figures": {"t_ms": math.nan, "rate": math.nan}, "ratios": {"r": math.nan}, "units": units},  # a failed figure
    ]
    best = compare.best_of(runs)
    assert best["figures"] == {"t_ms": 2.0, "rate": 30.0, "n": 2.0, "late_ms": 7.0}
    assert best["ratios"] == {"r": 1.0} and best["device"] == "first" and best["units"] == units
    assert best["spread"] == {"t_ms": [2.0, 4.0], "rate": [10.0, 30.0], "n": [1.0, 5.0], "late_ms": [7.0, 7.0],
                              "r": [0.9, 1.2]}  # fmt: skip


def test_benchmarks_measure_the_packages_named_by_the_environment(tmp_path):
    """``JAXCGA_BENCH_LIBRARY`` (make bench-compare's BASE) puts another checkout's packages first, for a script
    that imports ``_report`` before them; one that imports a package first is stopped by ``check_library``."""
    for name in _report.PACKAGES:
        (tmp_path / name).symlink_to(ROOT / name)
    probe = (
        "import sys; sys.path.insert(0, 'benchmarks'); import _report, deform; print(deform.__file__); "
        "_report.print_device('probe')"
    )
    env = {**os.environ, _report.LIBRARY_VARIABLE: str(tmp_path), "JAX_PLATFORMS": "cpu"}
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]
    assert done.stdout.splitlines()[0] == str(tmp_path / "deform" / "__init__.py")
    assert f"probe: cpu, cpu; library {tmp_path}" in done.stdout
    early = "import sys, deform; sys.path.insert(0, 'benchmarks'); import _report; _report.print_device('probe')"
    done = subprocess.run([sys.executable, "-c", early], capture_output=True, text=True, env=env, cwd=ROOT)
    assert done.returncode != 0 and "must import benchmarks/_report.py before the project's packages" in done.stderr
    # this checkout reached through a link (as pytest may find it) is this checkout
    (tmp_path / "link").symlink_to(ROOT)
    linked = early.replace(
        "import sys, deform;", f"import sys; sys.path.insert(0, {str(tmp_path / 'link')!r}); import deform;"
    )
    env.pop(_report.LIBRARY_VARIABLE)
    done = subprocess.run([sys.executable, "-c", linked], capture_output=True, text=True, env=env, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-3000:]


@pytest.mark.skipif(shutil.which("git") is None or not (ROOT / ".git").exists(), reason="not a git checkout")
def test_compare_commit_exports_only_the_packages_of_a_commit(tmp_path):
    """BASE's side of make bench-compare: its packages, nothing else (the tests and benchmarks stay this tree's)."""
    import compare_commit

    names = compare_commit.export_library("HEAD", tmp_path)
    assert set(names) == set(_report.PACKAGES) == {path.name for path in tmp_path.iterdir()}
    committed = subprocess.run(
        ["git", "show", "HEAD:deform/__init__.py"], capture_output=True, text=True, cwd=ROOT, check=True
    ).stdout
    assert (tmp_path / "deform" / "__init__.py").read_text() == committed


def test_compare_marks_and_lists_first_the_moves_whose_runs_lie_apart(tmp_path, capsys):
    """With the runs' spread on both sides (make bench-compare's merged files): a move that every run makes comes
    before a larger one that the runs' noise covers."""
    import compare

    old, new = _compare_files(tmp_path)
    spread = {"old": {"cut_ms": [9.0, 10.0], "blend_vs_dqs": [0.4, 1.2]}, "new": {"cut_ms": [13.0, 14.0],
              "blend_vs_dqs": [0.5, 0.6]}}  # fmt: skip
    for path, side in ((old, "old"), (new, "new")):
        path.write_text(json.dumps(json.loads(path.read_text()) | {"spread": spread[side]}))
    compare.main([str(old), str(new)])
    printed = capsys.readouterr().out
    assert _listed(printed)["worse"] == ["cut_ms*", "blend_vs_dqs", "fps_f32", "peak_gib"]
    assert "marked *" in printed.splitlines()[1]


@pytest.mark.slow
def test_bench_cli_quick_writes_the_published_names(tmp_path):
    result = _quick("bench_cli.py", tmp_path)
    assert set(result["ratios"]) == {"cli_first_vs_second_run_skin"}
    assert {"cli_help_s", "cli_skin_first_s", "cli_skin_second_s"} <= set(result["figures"])
    assert all(math.isfinite(v) and v > 0 for v in result["figures"].values())
