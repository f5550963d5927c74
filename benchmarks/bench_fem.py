"""FEM benchmark (XFEM paper sec. 3.3 and 5.2): the time of one backward Euler step (``xfem.backward_euler_step``,
eq. 10, one projected Newton iteration with a CG solve) at about 1k, 7.2k and 22.8k DOFs, with the paper's
parameters (stable neo-Hookean, Young 1e6, Poisson 0.4, density 1e3, h = 0.033 s, one Newton iteration).

Scene: like the paper's accordion (Fig. 7), a block hanging under gravity from its clamped top face (z max),
``box_tets`` cells of 0.13 m (average tet edge 0.165 m; the accordion's is 0.17 m, Table 1). The cells are chosen
so that the FREE DOFs (3 x the nodes not on the top face) are 1,029, 7,200 and 22,800; the fixed nodes are not
counted (the totals are printed too). The block starts at rest and falls into its sag, so the state evolves.

Timing: after a first step (jit compilation included; reported as a figure), the median and the max of
``--steps`` steps of the running simulation, wall-clock, float64. Same run baselines:

* the paper's averages per step (Table 2, "Ours", cut and uncut frames): 5.785 s for the 22.8k-DOF accordion
  and 0.627 s for the 7.2k-DOF "Thin" model, on an i9-13900K (ratios ``step_23k_vs_paper``, ``step_7k_vs_paper``);
* the same step with the Newton system solved exactly by CHOLMOD (``_jaxcga_shared.sparse.host_direct``) instead of the
  inexact Jacobi-preconditioned CG, from the same states (``step_<size>_vs_direct``);
* a breakdown from the same states: projected element gradients and Hessians
  (``element_gradient_hessian``), their assembly (``assemble_matrix``), the CG and the CHOLMOD solves of the
  Newton system (host, as the step's callback runs them), the block-Jacobi CG in JAX that a GPU runs instead
  (``device_pcg``, jitted, here on the CPU: ``device_cg_solve``; with its matrix-vector product over the CSR
  entries instead of the 3 x 3 blocks: ``device_cg_entries_solve``) and the line search;
* off the CPU, the step with the CPU's chunks of elements and mass entries (``xfem._backward_euler._Chunks``:
  1,024 elements a chunk there, every element at once on a GPU), from the same states
  (``step_cpu_chunks_<size>_s``).

Ratios are baseline time / ours (> 1: we are faster).

Sizes: ``--sizes`` picks some of 1k, 7k and 23k (default all; on a GPU ``--sizes 23k``).

    python benchmarks/bench_fem.py [--sizes 1k 7k 23k] [--steps 10] [--quick] [--json out/bench/fem.json]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, platform, print_device, write_json  # noqa: E402

import xfem  # noqa: E402

# times the step's internal kernels (gradient and matrix, solve, line search) one by one
import xfem._backward_euler as be  # noqa: E402
from _jaxcga_shared.host import host_call  # noqa: E402
from _jaxcga_shared.sparse import device_pcg, host_direct, host_pcg  # noqa: E402

YOUNG, POISSON, DENSITY, H = 1e6, 0.4, 1e3, 0.033
CELL = 0.13  # m
# free DOFs 3 * nx * ny * (nz - 1) for nx x ny x nz nodes with the top layer fixed: 1029, 7200, 22800
CELLS = {"1k": (6, 6, 7), "7k": (11, 9, 20), "23k": (19, 19, 19)}
QUICK_CELLS = (3, 3, 3)  # --quick: every size tag on this one small block (one compilation)
PAPER_S = {"7k": 0.627, "23k": 5.785}  # Table 2, average step time, "Thin (Ours)" and "Accordion (Ours)"
CG_RTOL = be._CG_RTOL  # the step's relative residual for the Newton direction
# the paper's single Newton iteration per step (its Table 2 timings), not the converging default
PAPER_STEP = dict(newton_iterations=1, tolerance=None)


def hanging_block(cells):
    """A box of ``cells`` cells of size CELL, clamped on its top face, under gravity: (system, rest state)."""
    mesh = xfem.box_tets(cells, tuple(CELL * c for c in cells))
    X = np.asarray(mesh.X)
    top = np.flatnonzero(np.isclose(X[:, 2], X[:, 2].max()))
    system = xfem.fem_from_mesh(mesh, DENSITY, (0.0, 0.0, -9.81), top)
    return system, xfem.State(mesh.X, jnp.zeros_like(mesh.X))


def seconds(fn):
    """(result, wall-clock seconds) of ``fn()``, JAX results waited for."""
    start = time.perf_counter()
    result = jax.block_until_ready(fn())
    return result, time.perf_counter() - start


def _theta(system, state, h, mu, lam):
    return be._Theta(
        state.x, state.v, mu, lam, state.x[system.fixed], system.force, system.grads, system.volumes, system.mass_values
    )


@eqx.filter_jit
def newton_start(system, state, h, mu, lam):
    """The point one Newton iteration starts from, its free gradient of E and the CSR data of ``M + h^2 K_+``."""
    x = (state.x + h * state.v).at[system.fixed].set(state.x[system.fixed])
    gradient, data = be._gradient_and_matrix(system, x, _theta(system, state, h, mu, lam), h, project=True)
    return x, gradient, data


@eqx.filter_jit
def direct_step(system, state, h, mu, lam):
    """``backward_euler_step`` with one Newton iteration whose system is solved by CHOLMOD (``host_direct``) on
    the host, on every platform, instead of CG: the body of ``_newton`` with the same gradient, matrix and line
    search (keep in step)."""
    theta = _theta(system, state, h, mu, lam)
    x, gradient, data = newton_start(system, state, h, mu, lam)
    csr = system.pattern.csr
    # the host's direct solve also on a GPU (spd_solve would run the device CG there, to a tolerance of 0)
    step = -host_call(
        _direct, jax.ShapeDtypeStruct(gradient.shape, gradient.dtype), data, gradient, csr.indptr, csr.indices
    )
    start = be._energy(system, x, theta, h)
    alpha, _ = be._line_search(system, x, step.reshape(-1, 3), jnp.dot(gradient, step), theta, h, start)
    x = x.at[system.pattern.free].add(alpha * step.reshape(-1, 3))
    return xfem.State(x, (x - state.x) / h)


def _direct(data, rhs, indptr, indices):
    return host_direct(data, rhs, indptr, indices)


@eqx.filter_jit
def device_solve(system, data, gradient):
    return device_pcg(system.pattern.csr, data, gradient, CG_RTOL)[0]


@eqx.filter_jit
def device_entries_solve(system, data, gradient):
    """``device_solve`` with the matrix-vector product over the CSR entries instead of the 3 x 3 blocks."""
    entries = dataclasses.replace(system.pattern.csr, full_blocks=False)
    return device_pcg(entries, data, gradient, CG_RTOL)[0]


@eqx.filter_jit
def element_hessians(system, x, mu, lam):
    return xfem.element_gradient_hessian(x[system.T], system.grads, system.volumes, mu, lam)


@eqx.filter_jit
def assembly(system, Hs):
    return xfem.assemble_matrix(system.pattern, Hs)


@eqx.filter_jit
def line_search(system, state, x, gradient, step, h, mu, lam):
    theta = _theta(system, state, h, mu, lam)
    start = be._energy(system, x, theta, h)  # the Newton loop carries it from the last line search
    return be._line_search(system, x, step.reshape(-1, 3), jnp.dot(gradient, step), theta, h, start)[0]


def breakdown(system, states, h, mu, lam):
    """Median seconds of the parts of a step from each of ``states`` (the first call of each compiles)."""
    indptr, indices = np.asarray(system.pattern.indptr), np.asarray(system.pattern.indices)
    times = {
        "hessians": [],
        "assembly": [],
        "cg_solve": [],
        "direct_solve": [],
        "device_cg_solve": [],
        "device_cg_entries_solve": [],
        "line_search": [],
    }
    for i, state in enumerate(states):
        x, gradient, data = newton_start(system, state, h, mu, lam)
        (_, Hs), t_hessians = seconds(lambda: element_hessians(system, x, mu, lam))
        _, t_assembly = seconds(lambda: assembly(system, Hs))
        rhs, A = np.asarray(gradient), np.asarray(data)
        step, t_cg = seconds(lambda: -host_pcg(A, rhs, CG_RTOL, indptr, indices))
        _, t_direct = seconds(lambda: host_direct(A, rhs, indptr, indices))
        _, t_device = seconds(lambda: device_solve(system, data, gradient))
        _, t_entries = seconds(lambda: device_entries_solve(system, data, gradient))
        step = jnp.asarray(step)
        _, t_line = seconds(lambda: line_search(system, state, x, gradient, step, h, mu, lam))
        if i > 0:  # the first state compiles
            for key, t in zip(times, (t_hessians, t_assembly, t_cg, t_direct, t_device, t_entries, t_line)):
                times[key].append(t)
    return {key: statistics.median(t) for key, t in times.items()}


def cpu_chunked_steps(system, states, h, material) -> list[float]:
    """Seconds of the step from each of ``states`` with the CPU's chunk sizes (``_in_chunks``) on this platform:
    the formulation a GPU would run without the per-platform choice (the first call compiles)."""
    chunks = be._ELEMENT_CHUNK, be._MASS_CHUNK
    be._ELEMENT_CHUNK, be._MASS_CHUNK = (be._Chunks(c.cpu, c.cpu) for c in chunks)
    jax.clear_caches()  # the step's trace reads the chunk sizes
    try:
        times = [
            seconds(lambda: xfem.backward_euler_step(system, s, h, material, **PAPER_STEP))[1]
            for s in [states[0], *states]
        ]
    finally:
        be._ELEMENT_CHUNK, be._MASS_CHUNK = chunks
        jax.clear_caches()
    return times[1:]


def run(cells: dict, steps: int):
    material = xfem.Material(jnp.asarray(YOUNG, jnp.float64), jnp.asarray(POISSON, jnp.float64))
    mu, lam = material.lame()  # for the step's parts, timed one by one
    h = jnp.asarray(H, jnp.float64)
    figures, ratios, units = {}, {}, {}
    for tag, c in cells.items():
        system, state = hanging_block(c)
        rest = state.x
        n_free = system.pattern.n_free
        # the first step compiles; the timed steps continue the same simulation
        state, first = seconds(lambda: xfem.backward_euler_step(system, state, h, material, **PAPER_STEP))
        states, t_ours = [], []
        for _ in range(steps):
            states.append(state)
            state, t = seconds(lambda: xfem.backward_euler_step(system, states[-1], h, material, **PAPER_STEP))
            t_ours.append(t)
        # CHOLMOD from the same states (the first call compiles)
        seconds(lambda: direct_step(system, states[0], h, mu, lam))
        t_direct, difference = [], 0.0
        for i, s in enumerate(states):
            exact, t = seconds(lambda: direct_step(system, s, h, mu, lam))
            t_direct.append(t)
            ours = states[i + 1].x if i + 1 < len(states) else state.x
            difference = max(difference, float(jnp.max(jnp.abs(ours - exact.x))))
        sag = float(jnp.max(jnp.abs(state.x - rest)))
        parts = breakdown(system, [states[0]] + states, h, mu, lam)  # a first pass to compile

        t_cpu_chunks = cpu_chunked_steps(system, states, h, material) if platform() != "cpu" else []

        step, direct = statistics.median(t_ours), statistics.median(t_direct)
        other = step - sum(parts[key] for key in ("hessians", "assembly", "cg_solve", "line_search"))
        f = {
            f"step_{tag}_s": step,
            f"step_max_{tag}_s": max(t_ours),
            f"step_first_{tag}_s": first,
            f"step_direct_{tag}_s": direct,
        }
        if t_cpu_chunks:
            f[f"step_cpu_chunks_{tag}_s"] = statistics.median(t_cpu_chunks)
        units.update({k: "s" for k in f})
        f |= {f"{key}_{tag}_ms": 1e3 * t for key, t in parts.items()}
        units.update({f"{key}_{tag}_ms": "ms" for key in parts})
        f[f"dofs_{tag}"], f[f"tets_{tag}"] = 3.0 * n_free, float(len(system.T))
        units[f"dofs_{tag}"] = units[f"tets_{tag}"] = "count"
        f[f"direct_difference_{tag}"] = difference / sag
        units[f"direct_difference_{tag}"] = "largest displacement"
        figures |= f
        ratios[f"step_{tag}_vs_direct"] = direct / step
        print(
            f"{tag}: cells {c}, {3 * n_free} free DOFs ({3 * system.n} with the {system.n - n_free} fixed nodes), "
            f"{len(system.T)} tets; largest displacement after {steps + 1} steps {sag:.3g} m"
        )
        print(
            f"  step (CG, ours): median {step:.4f} s, max {max(t_ours):.4f} s over {steps} steps; "
            f"first step (with compilation) {first:.2f} s"
        )
        if t_cpu_chunks:
            print(
                f"  step with the CPU's chunks of {be._ELEMENT_CHUNK.cpu} elements: median "
                f"{statistics.median(t_cpu_chunks):.4f} s (this platform's: {be._ELEMENT_CHUNK.device})"
            )
        print(
            f"  step with CHOLMOD: median {direct:.4f} s -> step_{tag}_vs_direct "
            f"{ratios[f'step_{tag}_vs_direct']:.2f}x; positions differ by at most "
            f"{f[f'direct_difference_{tag}']:.1e} of the largest displacement"
        )
        print(
            "  breakdown (medians): "
            + ", ".join(f"{key} {1e3 * t:.1f} ms" for key, t in parts.items())
            + f"; the rest of the CG step {1e3 * other:.1f} ms "
            "(gather, gradient and mass products, callback)"
        )
        if tag in PAPER_S:
            ratios[f"step_{tag}_vs_paper"] = PAPER_S[tag] / step
            print(f"  step_{tag}_vs_paper {ratios[f'step_{tag}_vs_paper']:.1f}x (paper {PAPER_S[tag]} s a step)")
    return {"figures": figures, "ratios": ratios, "units": units | {k: RATIO_UNIT for k in ratios}}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--sizes",
        nargs="+",
        choices=CELLS,
        default=list(CELLS),
        help="the free DOFs of the blocks to run, of 1k, 7k, 23k (default: all)",
    )
    parser.add_argument("--steps", type=int, default=10, help="timed steps per size (medians and max)")
    parser.add_argument(
        "--quick",
        action="store_true",
        help=f"every size on one {QUICK_CELLS} block (compiled once), 2 steps: a smoke run",
    )
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_fem")
    cells = {tag: QUICK_CELLS if args.quick else CELLS[tag] for tag in CELLS if tag in args.sizes}
    steps = 2 if args.quick else args.steps
    write_json(args.json, run(cells, steps))
    return 0


if __name__ == "__main__":
    sys.exit(main())
