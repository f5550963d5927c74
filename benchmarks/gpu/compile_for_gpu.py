"""The GPU programs of issue 32's benchmarks, compiled for an H100 or H200 on a machine without a GPU.

XLA compiles for a GPU it does not have when given the GPU's description (deviceless ahead-of-time compilation
through the CUDA plugin's compile-only topology): the whole pipeline runs, Triton kernels included, down to PTX and
machine code. Nothing runs, so nothing is timed; what the compiled program shows is what sets the time of the
small, latency-bound programs here (100k vertices, a few thousand CG unknowns):

* kernel launches (fusions, library calls, copies), in the program and per iteration of each loop;
* host round trips: every ``conditional`` (a runtime check, a ``lax.cond``) and every loop whose trip count is
  not known at compile time copies its predicate to the host and waits for the GPU to finish;
* host calls left on the GPU path, and the runtime checks' failure branches (both stood in by zeros here, counted);
* the registers and spills of every Triton kernel (``ptxas -v`` on its PTX, when ``ptxas`` is on the PATH).

A program that fails to compile, or a Triton kernel that spills, makes the exit status 1.

Setup (``make gpu-programs`` does it): the CUDA plugin of the installed jaxlib's version, without its CUDA
libraries (compiling needs none), in ``.cuda-plugin/``; run with ``PYTHONPATH=.cuda-plugin``.
Usage: ``python benchmarks/gpu/compile_for_gpu.py [--target h100|h200] [--quick] [--only NAME ...] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import functools
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.experimental import topologies

ROOT = Path(__file__).resolve().parents[2]
sys.path[:0] = [str(ROOT), str(ROOT / "benchmarks")]

from _jaxcga_shared import checks as _checks  # noqa: E402
from _jaxcga_shared import host  # noqa: E402

# GpuTargetConfigProto text of each target (the device description XLA's autotuner and emitters read; the
# numbers are the GPUs' published figures, as in XLA's own gpu_specs).
_DEVICE_INFO = """gpu_device_info {{
  threads_per_block_limit: 1024 threads_per_warp: 32 shared_memory_per_block: 49152
  shared_memory_per_core: 233472 threads_per_core_limit: 2048 core_count: 132 fpus_per_core: 128
  block_dim_limit_x: 2147483647 block_dim_limit_y: 65535 block_dim_limit_z: 65535
  memory_bandwidth: {bandwidth} l2_cache_size: 52428800 clock_rate_ghz: 1.98
  device_memory_size: {memory} shared_memory_per_block_optin: 232448
  cuda_compute_capability {{ major: 9 }} registers_per_core_limit: 65536 registers_per_block_limit: 65536
}}
platform_name: "CUDA"
dnn_version_info {{ major: 9 minor: 8 }}
device_description_str: "{name}"
"""
TARGETS = {
    "h100": _DEVICE_INFO.format(bandwidth=3352320000000, memory=84978434048, name="NVIDIA H100 80GB HBM3"),
    "h200": _DEVICE_INFO.format(bandwidth=4800000000000, memory=150754820096, name="NVIDIA H200"),
}

# ops that launch nothing (views, tuples, control flow, whose bodies are counted on their own)
_NO_LAUNCH = {
    "parameter",
    "constant",
    "tuple",
    "get-tuple-element",
    "bitcast",
    "while",
    "conditional",
    "call",
    "after-all",
    "opt-barrier",
    "add-dependency",
    "partition-id",
    "replica-id",
}
_INSTRUCTION = re.compile(r"^\s*(?:ROOT )?%([\w.\-]+) = .+? ([a-z][\w\-]*)\((.*)$")


@dataclasses.dataclass
class Loop:
    trip_count: int | None  # None: data-dependent, a host round trip per iteration
    launches: int  # per iteration, condition included
    conditionals: int  # per iteration
    loops: list[Loop]


@dataclasses.dataclass
class Program:
    name: str
    compile_s: float
    launches: int  # outside loops, the branches of conditionals left out
    conditionals: int  # outside loops
    waiting: int  # of those, the ones with launches or loops after them: the GPU idles while the host decides
    loops: list[Loop]
    host_calls: int  # on the GPU path
    checks: int  # runtime checks' failure branches (a host call each, run only when the check fails)
    graphs: Graphs | None  # how XLA's runtime launches the kernels (its thunk sequence); None where not dumped
    triton: dict[str, tuple[int, int] | None]  # kernel -> (registers, spill bytes) from ptxas; None without it

    def summary(self) -> str:
        loops = "; ".join(_loop_text(loop) for loop in self.loops) or "none"
        triton = ", ".join(_triton_text(k, stats) for k, stats in self.triton.items()) or "none"
        return (
            f"{self.name}: {self.launches} launches, {self.conditionals} conditionals (host round trips; "
            f"{self.waiting} before more work), "
            f"{self.host_calls} host calls, {self.checks} checks; loops: {loops}; Triton: {triton}; "
            f"{self.graphs.summary() if self.graphs else 'no thunk sequence'} "
            f"(compiled in {self.compile_s:.1f} s)"
        )


def _triton_text(kernel: str, stats: tuple[int, int] | None) -> str:
    return f"{kernel} (no ptxas)" if stats is None else f"{kernel} {stats[0]} registers, {stats[1]} B spilled"


def _loop_text(loop: Loop) -> str:
    trips = f"{loop.trip_count} trips" if loop.trip_count is not None else "data-dependent (a round trip each)"
    inner = f" [{'; '.join(_loop_text(inner) for inner in loop.loops)}]" if loop.loops else ""
    return f"{trips}, {loop.launches} launches and {loop.conditionals} conditionals an iteration{inner}"


def computations(text: str) -> dict[str, list[str]]:
    """The instruction lines of each computation of an HLO module's text, by name (the entry's as ``ENTRY``)."""
    out, name = {}, None
    for line in text.splitlines():
        head = re.match(r"^(ENTRY )?%([\w.\-]+) .*\{$", line)
        if head:
            name = "ENTRY" if head.group(1) else head.group(2)
            out[name] = []
        elif line == "}":
            name = None
        elif name is not None:
            out[name].append(line)
    return out


class Structure(NamedTuple):
    launches: int
    conditionals: int
    waiting: int  # conditionals of the entry computation followed by launches or loops (in schedule order)
    loops: list[Loop]


def structure(text: str) -> Structure:
    """The launches, conditionals and loops of the entry computation of a compiled HLO module (its text lists the
    instructions in their schedule), and how many of its conditionals more work waits for."""
    comps = computations(text)

    def visit(name: str) -> tuple[int, int, list[Loop]]:
        launches = conditionals = 0
        loops = []
        for line in comps[name]:
            match = _INSTRUCTION.match(line)
            if not match:
                continue
            op, rest = match.group(2), match.group(3)
            if op == "while":
                body = re.search(r"body=%([\w.\-]+)", rest).group(1)
                condition = re.search(r"condition=%([\w.\-]+)", rest).group(1)
                trips = re.search(r'"known_trip_count":\{"n":"(\d+)"', rest)
                b_launch, b_cond, inner = visit(body)
                c_launch, c_cond, _ = visit(condition)
                loops.append(Loop(int(trips.group(1)) if trips else None, b_launch + c_launch, b_cond + c_cond, inner))
            elif op == "conditional":
                conditionals += 1
            elif op == "call":
                called = re.search(r"to_apply=%([\w.\-]+)", rest)
                if called and called.group(1) in comps:
                    more = visit(called.group(1))
                    launches, conditionals = launches + more[0], conditionals + more[1]
                    loops += more[2]
            elif op not in _NO_LAUNCH:
                launches += 1
        return launches, conditionals, loops

    launches, conditionals, loops = visit("ENTRY")
    waiting = pending = 0
    for line in comps["ENTRY"]:
        match = _INSTRUCTION.match(line)
        if not match:
            continue
        if match.group(2) == "conditional":
            pending += 1
        elif match.group(2) in ("while", "call") or match.group(2) not in _NO_LAUNCH:
            waiting, pending = waiting + pending, 0
    return Structure(launches, conditionals, waiting, loops)


@dataclasses.dataclass
class Graphs:
    """The launches (kernels, copies) of a program's thunk sequence (what XLA's GPU runtime executes), each counted
    once (a loop's body too, a conditional's branches not): those inside command buffers, which run as CUDA graphs
    (one launch for all of a graph's kernels), and those launched one by one. Conditionals and data-dependent loops
    stay outside graphs."""

    graphs: int
    in_graphs: int
    alone: int

    def summary(self) -> str:
        return f"thunks: {self.in_graphs} launches in {self.graphs} CUDA graphs, {self.alone} alone"


# thunks that launch nothing themselves (their nested thunks are counted)
_STRUCTURAL_THUNKS = {"kCommandBuffer", "kConditional", "kWhile", "kSequential", "kWaitForStreams"}
_THUNK = re.compile(r"^(\s*)\d+: (k\w+)")


def graphs(thunks: str) -> Graphs:
    """``Graphs`` of a thunk sequence as XLA dumps it (``*.thunk_sequence_after_thunk_passes.txt``): one thunk a
    line, ``NNN: kKind ...``, nested thunks indented below their command buffer, loop or conditional."""
    count = in_graphs = alone = 0
    around: list[tuple[int, str]] = []  # the command buffers and conditionals the current line may lie in
    for line in thunks.splitlines():
        match = _THUNK.match(line)
        if not match:
            continue
        depth, kind = len(match.group(1)), match.group(2)
        while around and depth <= around[-1][0]:
            around.pop()
        if any(k == "kConditional" for _, k in around):
            continue  # a branch: the failure branch of a check runs only when it fails
        if kind in ("kCommandBuffer", "kConditional"):
            count += kind == "kCommandBuffer"
            around.append((depth, kind))
        elif kind not in _STRUCTURAL_THUNKS:
            if around:
                in_graphs += 1
            else:
                alone += 1
    return Graphs(count, in_graphs, alone)


def _read_graphs(dump: Path) -> Graphs | None:
    for pattern in ("*.thunk_sequence_after_thunk_passes.txt", "*.thunk_sequence.txt"):
        found = sorted(dump.glob(pattern))
        if found:
            return graphs(found[0].read_text())
    return None


def ptxas_statistics(ptx_files: list[Path], kernels: set[str]) -> dict[str, tuple[int, int]]:
    """(registers, spill store bytes) of the named kernels, from ``ptxas -v`` for sm_90a; {} without ptxas."""
    ptxas = shutil.which("ptxas")
    if ptxas is None:
        return {}
    stats = {}
    for path in ptx_files:
        report = subprocess.run(
            [ptxas, "-arch=sm_90a", "-v", str(path), "-o", os.devnull], capture_output=True, text=True
        )
        for block in report.stderr.split("Compiling entry function '")[1:]:
            name = block.split("'", 1)[0]
            if name in kernels:
                registers = re.search(r"Used (\d+) registers", block)
                spills = re.search(r"(\d+) bytes spill stores", block)
                stats[name] = (int(registers.group(1)) if registers else -1, int(spills.group(1)) if spills else 0)
    return stats


class Compiler:
    """Compiles functions of pytrees for one GPU target: array leaves become abstract inputs on the target's
    device, everything else is closed over (static)."""

    def __init__(self, target: str):
        topology = topologies.get_topology_desc("1x1x1", "cuda", target_config=TARGETS[target], topology="1x1x1")
        self.sharding = jax.sharding.SingleDeviceSharding(topology.devices[0])
        self.host_calls = collections.Counter()
        # a host callback needs a live backend to be lowered: on this target, zeros stand in for it (counted)
        jax.interpreters.mlir.register_lowering(host._host_call_p, self._stand_in, platform="cuda", cacheable=False)

    def _stand_in(self, ctx, *operands, fn, result):
        self.host_calls[getattr(fn, "__name__", type(fn).__name__)] += 1
        zeros = jax.interpreters.mlir.lower_fun(lambda *_: jnp.zeros(result.shape, result.dtype), False)
        return zeros(ctx, *operands)

    def abstract(self, a) -> jax.ShapeDtypeStruct:
        return jax.ShapeDtypeStruct(a.shape, a.dtype, sharding=self.sharding)

    def compile(self, name: str, fn: Callable, *args) -> Program:
        arrays, static = eqx.partition(args, lambda x: isinstance(x, (jax.Array, jax.ShapeDtypeStruct)))
        specs = jax.tree.map(self.abstract, arrays)
        self.host_calls.clear()
        with tempfile.TemporaryDirectory(prefix="compile_for_gpu_") as dump:
            start = time.perf_counter()
            lowered = jax.jit(lambda a: fn(*eqx.combine(a, static))).trace(specs).lower()
            compiled = lowered.compile(compiler_options={"xla_dump_to": dump})
            seconds = time.perf_counter() - start
            text = compiled.as_text()
            triton = set(re.findall(r'custom_call_target="__gpu\$xla\.gpu\.triton".*?name = "(\w+)"', text))
            stats = dict.fromkeys(triton) | ptxas_statistics(sorted(Path(dump).glob("*.ptx")), triton)
            thunks = _read_graphs(Path(dump))
        launches, conditionals, waiting, loops = structure(text)
        checks = self.host_calls.pop(_checks._Fail.__name__, 0)
        host_calls = sum(self.host_calls.values())
        return Program(name, seconds, launches, conditionals, waiting, loops, host_calls, checks, thunks, stats)


def _kernel_programs(quick: bool):
    n = 100_000 if quick else 10_000_000
    for dtype in (jnp.float64, jnp.float32):
        x = jax.ShapeDtypeStruct((n, 3), dtype)
        tag = jnp.dtype(dtype).name
        yield f"apply_to_points, a motor per point, {tag}", _apply, jax.ShapeDtypeStruct((n, 8), dtype), x
        yield f"apply_to_points, one motor, {tag}", _apply, jax.ShapeDtypeStruct((8,), dtype), x


def _apply(m, x):
    import jaxcga as cga

    return cga.apply_to_points(cga.Multivector(m, "motor"), x)


def _skinning_programs(quick: bool):
    import bench_skinning

    import deform
    import jaxcga as cga

    base = bench_skinning.subdivided_arm5(5_000 if quick else 100_000)
    keys = jax.random.split(jax.random.PRNGKey(0), 2)
    params = jax.vmap(lambda k: deform.random_parameters(k, base, rotation=0.5, translation=0.01))(keys)
    local = deform.pose_from_parameters(base, params)
    local_m = cga.versor_to_matrix(local)
    for dtype in (jnp.float32, jnp.float64):
        tag = jnp.dtype(dtype).name
        for method, fn in bench_skinning.pipelines(bench_skinning.as_dtype(base, dtype)).items():
            yield f"skinning {method}, one pose, {tag}", fn, local.values[0].astype(dtype), local_m[0].astype(dtype)


def _deform_programs(quick: bool):
    import bench_deform

    import deform

    V, F = bench_deform.refined_arm5(5_000 if quick else 100_000)
    handles = bench_deform.arm_handles(V)
    lattice = deform.bounding_lattice(V, (4, 4, 4), padding=0.01)
    cage_V, cage_F = deform.tube_cage(V)
    fields = {
        "spline": (deform.spline_precompute(V, F, handles[0], handles[1], basis="bspline", num_keys=6), 6),
        "handles": (deform.handles_precompute(V, F, handles), 3),
        "ffd": (deform.ffd_precompute(V, lattice), None),
        "cage": (deform.cage_precompute(V, cage_V, cage_F), len(cage_V)),
    }
    for dtype in (jnp.float64, jnp.float32):
        tag = jnp.dtype(dtype).name
        for name, (field, keys) in fields.items():
            field = bench_deform.as_dtype(field, dtype)
            if keys is None:
                motors = deform.twist_lattice(bench_deform.as_dtype(lattice, dtype), 1.5)[1]
            else:
                motors = bench_deform.bend_motors(keys, V, dtype=dtype)
            yield f"motor field {name}, {tag}", deform.motor_field_solve, field, motors
            blend = functools.partial(_matrix_blend, bench_deform.matrix_blend)
            yield f"matrix blend of the {name} field, {tag}", blend, field, motors


def _matrix_blend(matrix_blend, field, motors):
    return matrix_blend(field.weights, field.bound)(motors)


def _arap_programs(quick: bool):
    import bench_arap

    import deform

    V, F = bench_arap.subdivided_arm5(5_000 if quick else 100_000)
    b, bc = bench_arap.handles(V)
    U0 = V.copy()
    U0[b] = bc
    data = deform.arap_precompute(V, F, b, energy="spokes_and_rims")

    def solve(bc, U0):
        return deform.arap_solve(data, bc, V0=U0, max_iterations=10, tolerance=-1.0).U

    yield "ARAP, 10 iterations", solve, jnp.asarray(bc), jnp.asarray(U0)


def _fem_programs(quick: bool):
    import bench_fem

    import xfem

    system, state = bench_fem.hanging_block(bench_fem.QUICK_CELLS if quick else bench_fem.CELLS["23k"])
    material = xfem.Material(jnp.asarray(bench_fem.YOUNG), jnp.asarray(bench_fem.POISSON))

    def step(system, state, h, material):
        return xfem.backward_euler_step(system, state, h, material, **bench_fem.PAPER_STEP)

    yield "FEM step", step, system, state, jnp.asarray(bench_fem.H), material


def _xfem_programs(quick: bool):
    import bench_xfem

    import xfem

    scene, system, state = bench_xfem._after_cuts("small" if quick else "paper")
    material = xfem.Material(jnp.asarray(scene.young), jnp.asarray(scene.poisson))

    def step(system, state, h, material):
        # the paper's fixed iterations (Table 2), not the converging default
        return xfem.backward_euler_step(
            system, state, h, material, newton_iterations=scene.newton_iterations, tolerance=None
        )

    yield "XFEM step, the accordion after its cuts", step, system, state, jnp.asarray(scene.h), material


GROUPS = {
    "kernel": _kernel_programs,
    "skinning": _skinning_programs,
    "deform": _deform_programs,
    "arap": _arap_programs,
    "fem": _fem_programs,
    "xfem": _xfem_programs,
}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--target", choices=sorted(TARGETS), default="h100")
    parser.add_argument("--quick", action="store_true", help="small sizes: the same programs, faster to set up")
    parser.add_argument("--only", nargs="+", choices=sorted(GROUPS), default=sorted(GROUPS), metavar="GROUP")
    parser.add_argument("--json", type=Path, help="write every program's figures here")
    args = parser.parse_args(argv)

    # this process compiles for a GPU it does not have: its own backend is the CPU (JAX_PLATFORMS may say so)
    if not jax.config.jax_platforms:
        jax.config.update("jax_platforms", "cpu")
    jax.config.update("jax_enable_x64", True)
    compiler = Compiler(args.target)
    programs, failures = [], []
    print(f"compiling for {args.target} (no GPU here); ptxas: {shutil.which('ptxas') or 'not found, no registers'}")
    for group in args.only:
        for name, fn, *inputs in GROUPS[group](args.quick):
            try:
                program = compiler.compile(name, fn, *inputs)
            except Exception as error:  # every program is tried; a failure is reported and fails the run
                failures.append(f"{name}: {type(error).__name__}: {str(error)[:2000]}")
                print(f"FAILED {failures[-1]}", flush=True)
                continue
            programs.append(program)
            print(program.summary(), flush=True)
    spilled = [f"{p.name}: {k}" for p in programs for k, stats in p.triton.items() if stats and stats[1] > 0]
    for line in spilled:
        print(f"SPILLS {line}")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        record = {
            "target": args.target,
            "jax": jax.__version__,
            "programs": [dataclasses.asdict(p) for p in programs],
            "failures": failures,
            "spills": spilled,
        }
        args.json.write_text(json.dumps(record, indent=1))
    return 1 if failures or spilled else 0


if __name__ == "__main__":
    sys.exit(main())
