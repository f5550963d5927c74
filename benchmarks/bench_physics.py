"""Character physics benchmark (issue 53, item 6): ``xfem.simulate_character`` on the built-in arm and on the largest
corpus character meshed to at least 20k tets, in the full space and in the reduced (real-time) mode.

Models. ``arm``: ``deform.default_arm()`` (its ``wave`` clip), tets at the default edge length. ``character``: the
corpus's largest animated character (``QuaterniusCyberpunkCharacter``, 3.9k vertices, 27 joints, 22 clips; the
larger ``QuaterniusWorkerDense`` has no clip and meshes to fewer tets) playing its ``Run`` clip, meshed by fTetWild
with 0.9 of the default envelope (``CHARACTER_EPSILON``: ~22k tets), as fTetWild makes them (``refine=False``: the
body's bisection near the joints would make them ~480k), its surface meshed whole (``per_part=False``: each part
meshed on its own gives ~10k tets, fewer than the issue's 20k). fTetWild takes minutes and is not
deterministic: the tets are cached in the output folder (``--cache``, default beside ``--json`` or ``out/bench``)
and reused. Material: Young 1e5 Pa, Poisson 0.4, density 1e3, Rayleigh damping 0.01 s; 30 frames/s.

Figures, for ``PREFIX`` ``arm`` and ``character`` (the issue's names are the character's):

* ``PREFIX_step_ms``: the full-space step (backward Euler converged to the default tolerance; the mean over the
  ``--frames`` steps of one compiled play, the fastest of 3 after a warm-up play that compiles it, timed from the
  end of the host work before the steps: ``PREFIX_setup_s``, the model, its pieces and its surface map), and
  ``PREFIX_step_paper_ms``: the XFEM paper's step (one Newton iteration, ``newton_iterations=1, tolerance=None``).
  ``PREFIX_newton_iterations``: the converged steps' mean Newton iterations. Target (issue 53): at most 100 ms on
  2 cores at 20k tets (ratio ``PREFIX_step_vs_target`` = 100 ms / ours).
* Where the step's time goes (``PREFIX_breakdown_*_ms``, the segment's system at the last frame's rig and state,
  medians of 5): ``hessians`` the free gradient and the Newton matrices, projected and true (element Hessians summed
  into the CSR data, as the step computes them), ``solve`` the host solve of the factored direction (CHOLMOD's factor
  of the projected matrix, CG on the true one), ``factor`` CHOLMOD's factorization alone (made afresh at every
  Newton iteration: a factor kept from the step's first iteration preconditions the later ones too weakly, as the
  state moves, to pay back), ``paper_step`` one whole paper step (the rig rest shapes, the
  starts' energies, the gradient and the projected matrix, its factored solve and the line search).
* ``PREFIX_reduced_fps``: the reduced play (``xfem.character_subspace(body, MODES)``, ``simulate_character(...,
  subspace=...)``) in frames per second: ``--reduced-frames`` frames at 60 frames/s, the whole call (the rig skinned
  for every frame, the scan, the surface), the fastest of 3 after a warm-up call of the same length. Target: at
  least 60 frames/s at 20k tets (ratio ``PREFIX_reduced_fps_vs_target`` = ours / 60). ``PREFIX_reduced_vs_full``:
  the converged full step's time over the reduced frame's. ``PREFIX_subspace_s``: the eigensolve and the
  joint pairs' mass products (``CharacterSubspace.pair_mass``).
* ``PREFIX_reduced_error``: the reduced surface against the full-space one (converged steps) over the ``--frames``
  frames at 30 frames/s: the largest over the frames of the root mean square vertex distance, as a fraction of the
  surface's bounding-box diagonal; ``PREFIX_reduced_error_max`` the largest vertex distance; beside them
  ``PREFIX_full_lag``, the full mode's own distance from the skinned surface by the same measure (the secondary
  motion the reduced mode approximates).
* ``PREFIX_grad_vs_forward``: the time of a forward play (converged) and a loss on its surface trajectory over the
  time of that loss's ``jax.grad`` with respect to Young's modulus and the damping (eager, through each step's
  implicit gradient), each the fastest of 3 after a warm-up call. Target: at least 0.25.

    python benchmarks/bench_physics.py [--quick] [--models arm character] [--frames N] [--reduced-frames N]
                                       [--cache DIR] [--json out/bench/physics.json]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import deform  # noqa: E402
import xfem  # noqa: E402

# the step's kernels timed one by one
import xfem._backward_euler as be  # noqa: E402
from _jaxcga_shared.sparse import factorize, host_csr  # noqa: E402
from xfem._character import _rig_rest_system  # noqa: E402

CHARACTER = ROOT / "tests" / "data" / "characters" / "QuaterniusCyberpunkCharacter.glb"
CHARACTER_CLIP = "CharacterArmature|Run"
# fTetWild's tets of this character hardly change with the edge length (15k from 0.05 to 0.02): the envelope
# decides; 0.9 of the default envelope gives ~22k tets (0.5 of it ~32k)
CHARACTER_EDGE, CHARACTER_EPSILON = 0.05, 9e-4
QUICK_CHARACTER = ROOT / "tests" / "data" / "characters" / "Fox.glb"  # --quick: the coarse fox and its own clip
QUICK_EDGE = 0.1
MIN_TETS = 20_000
MATERIAL = xfem.Material(1e5, 0.4, 0.01)
FPS = 30.0
REDUCED_FPS = 60.0
MODES = 24
STEP_TARGET_MS = 100.0
FPS_TARGET = 60.0
REPEATS = 3  # timed calls after the warm-up; the fastest counts


def _body(
    model: deform.RiggedModel, edge: float, cache: Path, tag: str, epsilon: float = 1e-3, **options
) -> xfem.CharacterBody:
    """The model's body, its tets read from the cache when there (fTetWild takes minutes and varies run to run)."""
    path = cache / f"physics_tets_{tag}_{edge:g}_{epsilon:g}.npz"
    if path.exists():
        with np.load(path) as saved:
            return xfem.character_body(model, tets=xfem.tet_mesh(saved["X"], saved["T"]), **options)
    body = xfem.character_body(model, edge_length=edge, epsilon=epsilon, **options)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, X=np.asarray(body.tets.X), T=np.asarray(body.tets.T))  # the rest configuration's tets
    print(f"  {tag}: fTetWild {body.seconds:.0f} s, tets cached in {path}", flush=True)
    return body


def _timed(fn, repeats: int = REPEATS):
    """(seconds, result): the fastest of ``repeats`` calls after a warm-up call (which compiles); the machine is
    shared, the fastest call is the one least slowed by others."""
    result = jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        result = jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return min(times), result


def _steps(play, frames: int, repeats: int = REPEATS):
    """(seconds per step, the surface, seconds of host setup) of a full-space play, the fastest of ``repeats`` after
    a warm-up play: the steps are timed from the end of the host work before them (``simulate_character``'s
    ``progress`` stage ``"cuts"``, the last before the frames) to the surface's arrival."""
    jax.block_until_ready(_surface(play()))
    runs = []
    for _ in range(repeats):
        marks = {}

        def progress(stage, done, total):
            marks.setdefault(stage, time.perf_counter())

        start = time.perf_counter()
        surface = jax.block_until_ready(_surface(play(progress=progress)))
        end = time.perf_counter()
        runs.append(((end - marks["cuts"]) / frames, marks["cuts"] - start))
    step, setup = min(runs)
    return step, surface, setup


def _median(fn, repeats: int = 5) -> float:
    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        jax.block_until_ready(fn())
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _surface(motion: xfem.CharacterMotion):
    (segment,) = motion.segments
    return segment.surface


def _rms(a, b) -> np.ndarray:
    """(frames,) the root mean square distance of two surfaces per frame."""
    return np.sqrt(np.mean(np.sum((np.asarray(a) - np.asarray(b)) ** 2, axis=-1), axis=-1))


@eqx.filter_jit
def _newton_system(system, x, v, rest, target, h, mu, lam, beta):
    """The free gradient and the CSR data of the Newton matrix where a step from (x, v) starts (its rig rest
    shapes, its targets on the driven nodes, damped)."""
    moved = _rig_rest_system(system, rest)
    start = (x + h * v).at[system.fixed].set(target)
    elastic_t = be._elastic_forces(moved, x, moved.grads, moved.volumes, mu, lam)
    theta = be._Theta(
        x, v, mu, lam, target, system.force, moved.grads, moved.volumes, system.mass_values, beta, elastic_t
    )
    return be._gradient_and_matrices(moved, start, theta, h, be._element_gradient_hessians, 2)


@eqx.filter_jit
def _paper_step(system, x, v, rest, target, h, mu, lam, beta):
    moved = _rig_rest_system(system, rest)
    return be._advance(moved, be.State(x, v), h, mu, lam, target, system.force, 1, None, True, beta, factored=True)


def _breakdown(body, motion, clip, h: float) -> dict[str, float]:
    """Where a step's time goes, at the last frame of the played ``clip`` (module docstring)."""
    (segment,) = motion.segments
    system = segment.system
    x, v = segment.states.x[-2], segment.states.v[-2]
    times = motion.times
    rest = jnp.asarray(deform.skin_model(body.node_model, times[-1], "cga", clip))
    target = rest[jnp.asarray(segment.dof_node)[system.fixed]]
    rest = rest[jnp.asarray(segment.dof_node)]
    mu, lam = MATERIAL.lame()
    args = (system, x, v, rest, target, jnp.asarray(h), jnp.asarray(mu), jnp.asarray(lam), jnp.asarray(0.01))
    hessians = _median(lambda: _newton_system(*args))
    gradient, (data, true_data) = _newton_system(*args)
    rhs, A, H = np.asarray(gradient), np.asarray(data), np.asarray(true_data)
    indptr, indices = np.asarray(system.pattern.indptr), np.asarray(system.pattern.indices)
    solve = _median(lambda: be._host_factored_direction(A, H, rhs, be._CG_RTOL, indptr, indices))
    factor = _median(lambda: factorize(host_csr(A, indptr, indices), symmetric=True))
    step = _median(lambda: _paper_step(*args))
    return {"hessians": hessians, "solve": solve, "factor": factor, "paper_step": step, "unknowns": float(len(rhs))}


def run_model(prefix: str, body: xfem.CharacterBody, clip, frames: int, reduced_frames: int) -> tuple[dict, dict, dict]:
    figures, ratios, units = {}, {}, {}

    def figure(name, value, unit):
        figures[f"{prefix}_{name}"] = float(value)
        units[f"{prefix}_{name}"] = unit

    def ratio(name, value):
        ratios[f"{prefix}_{name}"] = float(value)
        units[f"{prefix}_{name}"] = RATIO_UNIT

    free = body.tets.n_nodes - len(body.driven)
    print(
        f"{prefix}: {body.model.name}, {body.tets.n_elements} tets, {body.tets.n_nodes} nodes ({free} free), "
        f"{len(body.surface)} surface vertices, clip {clip!r}",
        flush=True,
    )
    figure("tets", body.tets.n_elements, "count")
    figure("free_dofs", 3 * free, "count")
    seconds = frames / FPS

    def play(**options):
        return xfem.simulate_character(body, clip, seconds, FPS, material=MATERIAL, **options)

    full_s, full, setup_s = _steps(play, frames)
    motion = play()
    iterations = np.asarray(motion.segments[0].states.stats.iterations)[1:]
    paper_s, _, _ = _steps(lambda **options: play(newton_iterations=1, tolerance=None, **options), frames)
    step_ms, paper_ms = 1e3 * full_s, 1e3 * paper_s
    figure("step_ms", step_ms, "ms")
    figure("step_paper_ms", paper_ms, "ms")
    figure("setup_s", setup_s, "s")
    figure("newton_iterations", iterations.mean(), "count (mean per converged step)")
    ratio("step_vs_target", STEP_TARGET_MS / step_ms)
    print(
        f"  full step {step_ms:.1f} ms converged ({iterations.mean():.1f} Newton iterations, at most "
        f"{iterations.max()}), {paper_ms:.1f} ms one iteration (target {STEP_TARGET_MS:.0f} ms)",
        flush=True,
    )
    parts = _breakdown(body, motion, clip, 1 / FPS)
    for name in ("hessians", "solve", "factor", "paper_step"):
        figure(f"breakdown_{name}_ms", 1e3 * parts[name], "ms")
    print(
        f"  where a step goes ({parts['unknowns']:.0f} unknowns): gradient and Newton matrix "
        f"{1e3 * parts['hessians']:.1f} ms, the host solve {1e3 * parts['solve']:.1f} ms (its factorization "
        f"{1e3 * parts['factor']:.1f} ms), one paper step "
        f"{1e3 * parts['paper_step']:.1f} ms",
        flush=True,
    )

    start = time.perf_counter()
    subspace = xfem.character_subspace(body, MODES)
    figure("subspace_s", time.perf_counter() - start, "s")
    reduced_s, _ = _timed(
        lambda: _surface(
            xfem.simulate_character(
                body, clip, reduced_frames / REDUCED_FPS, REDUCED_FPS, material=MATERIAL, subspace=subspace
            )
        )
    )
    fps = reduced_frames / reduced_s
    figure("reduced_fps", fps, "frames/s")
    ratio("reduced_fps_vs_target", fps / FPS_TARGET)
    ratio("reduced_vs_full", step_ms / (1e3 / fps))
    reduced = _surface(play(subspace=subspace))
    skinned = _skinned(body, motion.times, clip)
    error, lag = _rms(reduced, full) / body.diagonal, _rms(full, skinned) / body.diagonal
    worst = np.linalg.norm(np.asarray(reduced) - np.asarray(full), axis=-1).max() / body.diagonal
    figure("reduced_error", error.max(), "fraction of the diagonal (largest RMS over the frames)")
    figure("reduced_error_max", worst, "fraction of the diagonal (largest vertex distance)")
    figure("full_lag", lag.max(), "fraction of the diagonal (largest RMS over the frames)")
    print(
        f"  reduced ({MODES} modes, subspace {figures[f'{prefix}_subspace_s']:.1f} s): {fps:.0f} frames/s "
        f"(target {FPS_TARGET:.0f}); error against the full space {error.max():.2e} of the diagonal (RMS; largest "
        f"vertex {worst:.2e}), the full mode's lag behind the rig {lag.max():.2e}",
        flush=True,
    )

    young, beta = jnp.asarray(1e5), jnp.asarray(0.01)

    def loss(young, beta):
        motion = xfem.simulate_character(body, clip, seconds, FPS, material=xfem.Material(young, 0.4, beta))
        surface = _surface(motion)
        return jnp.mean(surface[:, :, 1]) + jnp.mean(jnp.sum((surface[-1] - surface[0]) ** 2, axis=-1))

    forward_s, _ = _timed(lambda: loss(young, beta))
    gradient_s, _ = _timed(lambda: jax.grad(loss, argnums=(0, 1))(young, beta))
    figure("forward_s", forward_s, "s")
    figure("grad_s", gradient_s, "s")
    ratio("grad_vs_forward", forward_s / gradient_s)
    print(
        f"  forward {forward_s:.2f} s, gradient (E, beta) {gradient_s:.2f} s: forward / gradient "
        f"{forward_s / gradient_s:.2f} (target >= 0.25)",
        flush=True,
    )
    return figures, ratios, units


def _skinned(body: xfem.CharacterBody, times, clip) -> np.ndarray:
    """(frames, s, 3) the surface carried by the skinned tet nodes (every node on the rig)."""
    nodes = jax.vmap(lambda t: deform.skin_model(body.node_model, t, "cga", clip))(jnp.asarray(times))
    return np.stack([np.asarray(body.embedding.positions(x)) for x in nodes])


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", choices=("arm", "character"), default=["arm", "character"])
    parser.add_argument("--frames", type=int, default=10, help="full-space frames timed at 30 frames/s")
    parser.add_argument("--reduced-frames", type=int, default=240, help="reduced frames timed at 60 frames/s")
    parser.add_argument(
        "--cache", type=Path, default=None, help="where the tets are cached (default: the JSON's folder)"
    )
    parser.add_argument(
        "--quick", action="store_true", help="coarse tets, the fox as the character, 3 frames: a smoke run"
    )
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_physics")
    cache = args.cache or (args.json.parent if args.json else ROOT / "out" / "bench")
    frames = 3 if args.quick else args.frames
    reduced_frames = 20 if args.quick else args.reduced_frames
    result = {"figures": {}, "ratios": {}, "units": {}}
    warnings.simplefilter("ignore", UserWarning)  # fTetWild's far surface vertices, clip ends: not what is measured
    for prefix in args.models:
        if prefix == "arm":
            model = deform.default_arm(rings_per_unit=60.0) if args.quick else deform.default_arm()
            body, clip = _body(model, QUICK_EDGE if args.quick else 0.05, cache, "arm"), "wave"
        elif args.quick:
            body, clip = _body(deform.load_model(QUICK_CHARACTER, weld=True), QUICK_EDGE, cache, "fox"), 0
        else:
            model = deform.load_model(CHARACTER, weld=True)
            body = _body(model, CHARACTER_EDGE, cache, "cyberpunk", CHARACTER_EPSILON, refine=False, per_part=False)
            clip = CHARACTER_CLIP
            if body.tets.n_elements < MIN_TETS:
                print(f"  warning: {body.tets.n_elements} tets, fewer than {MIN_TETS}", flush=True)
        for key, values in zip(("figures", "ratios", "units"), run_model(prefix, body, clip, frames, reduced_frames)):
            result[key].update(values)
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
