"""Skinning benchmark: matrix LBS (eq. 16), DQS, and multivector skinning (eq. 17) in both variants
on a subdivided Arm5 (>= 100k vertices, 23 joints, 4 influences), float32 and float64, one pose and
1,000 poses under vmap.

Blend after the sandwich is timed in both evaluations of sec. 4.3: ``cga`` down-projects each
sandwiched point before the sum (the paper's implementation, which it found faster, and
``skin_cga``'s default), and ``cga_sum_then_project`` sums the sandwiched conformal points and
down-projects the sum (one more gather and a division per vertex). They differ only when joints
carry unequal dilations.

Every method runs the whole pipeline from local bone transforms to vertex positions, jitted:
forward kinematics, joint transforms, per-vertex skinning. The baselines take local 4x4 matrices (LBS)
and convert joint matrices to dual quaternions (DQS); the multivector methods take local similitudes.
All get the same random rigid poses. Calls are interleaved round-robin over the methods (medians per
method), so that the machine's drift during the run does not bias a ratio, and each timed call follows
an untimed call of the same method (``round_robin_times``). The batch of poses runs as
``jax.lax.map(..., batch_size=chunk)``: vmap over chunks of 50 poses, which bounds the memory of the
per-pose temporaries (1,000 poses x 100k vertices x 3 floats is already 1.2 GB of output in float32).
Ratios are baseline time / our time (> 1: we are faster). On a GPU the motor blend's XLA formulation, which
its Triton kernel replaces there, is timed beside it (``cga_motor_blend_xla_*``).

    python benchmarks/bench_skinning.py [--vertices 100000] [--poses 1000] [--json out/bench/skinning.json]
"""

from __future__ import annotations

import argparse
import functools
import statistics
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import trimesh  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import deform  # noqa: E402
import jaxcga as cga  # noqa: E402
from deform import _skinning  # noqa: E402


def subdivided_arm5(min_vertices: int = 0, influences: int = 4, min_faces: int = 0) -> deform.RiggedModel:
    """Arm5 with midpoint subdivision; a new vertex takes the mean of its edge's weights (dense over
    the joints), the top ``influences`` kept and renormalized. With ``min_vertices`` the mesh is cut to
    its first min_vertices vertices (the original mesh, then edge midpoints) and the faces among them;
    with ``min_faces`` to its first min_faces faces (a conforming patch) and the vertices they use."""
    model = deform.load_model(ROOT / "tests" / "data" / "Arm5.glb")
    mesh = model.mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    dense = np.zeros((V.shape[0], mesh.num_joints))
    np.put_along_axis(dense, np.asarray(mesh.J), np.asarray(mesh.W), axis=1)
    while V.shape[0] < min_vertices or F.shape[0] < min_faces:
        V, F, attributes = trimesh.remesh.subdivide(V, F, vertex_attributes={"w": dense})
        dense = attributes["w"]
    if min_faces:
        F = F[:min_faces]
        used, F = np.unique(F, return_inverse=True)
        V, F, dense = V[used], F.reshape(-1, 3), dense[used]
    else:
        keep = np.all(F < min_vertices, axis=1)
        V, F, dense = V[:min_vertices], F[keep], dense[:min_vertices]
    J = np.argsort(-dense, axis=1)[:, :influences]
    W = np.take_along_axis(dense, J, axis=1)
    W[W.sum(axis=1) == 0, 0] = 1.0  # a few Arm5 vertices carry no weight: bind them to one joint
    W = W / W.sum(axis=1, keepdims=True)
    big = deform.SkinnedMesh(
        jnp.asarray(V),
        jnp.asarray(F, jnp.int32),
        jnp.asarray(J, jnp.int32),
        jnp.asarray(W),
        mesh.inverse_bind,
        mesh.joints,
    )
    return deform.RiggedModel(big, model.skeleton, (), "Arm5-subdivided")


def as_dtype(tree, dtype):
    return jax.tree_util.tree_map(lambda x: x.astype(dtype) if jnp.issubdtype(x.dtype, jnp.floating) else x, tree)


def pipelines(model: deform.RiggedModel):
    """name -> function of (local versor values, local matrices) -> positions."""
    mesh, parents = model.mesh, model.skeleton.parents
    blades = cga.KINDS["similitude"]
    # B_n in multivector form, converted once from the file's inverse bind matrices (the matrix
    # baselines use those matrices as stored)
    inverse_bind = deform.inverse_bind_versors(mesh)

    def lbs(_, local_m):
        joints = deform.joint_matrices(mesh, deform.forward_kinematics_matrices(parents, local_m))
        return deform.skin_lbs(mesh.V, mesh.J, mesh.W, joints)

    def dqs(_, local_m):
        joints = deform.joint_matrices(mesh, deform.forward_kinematics_matrices(parents, local_m))
        return deform.skin_dqs(mesh.V, mesh.J, mesh.W, deform.matrices_to_dual_quaternions(joints))

    def versors(local_v):
        return deform.joint_versors(
            mesh, deform.forward_kinematics(parents, cga.Multivector(local_v, blades)), inverse_bind
        )

    def cga_sandwich(local_v, _):
        return deform.skin_cga(mesh.V, mesh.J, mesh.W, versors(local_v))

    def cga_sum_then_project(local_v, _):
        return deform.skin_cga(mesh.V, mesh.J, mesh.W, versors(local_v), normalize_points=False)

    def cga_motor_blend(local_v, _):
        return deform.skin_cga_motor_blend(mesh.V, mesh.J, mesh.W, versors(local_v))

    methods = {
        "lbs": lbs,
        "dqs": dqs,
        "cga": cga_sandwich,
        "cga_sum_then_project": cga_sum_then_project,
        "cga_motor_blend": cga_motor_blend,
    }
    if jax.default_backend() == "gpu":
        # the XLA formulation that the motor blend's Triton kernel replaced on GPUs, timed beside it
        def cga_motor_blend_xla(local_v, _):
            blend = functools.partial(_skinning._blend_motors_in_xla, cpu=False)
            return _skinning._skin_motor_blend(mesh.V, mesh.J, mesh.W, versors(local_v), blend)

        methods["cga_motor_blend_xla"] = cga_motor_blend_xla
    return methods


def round_robin_times(fns: dict, args, repeats: int) -> dict:
    """Median wall time of each function, the calls interleaved round-robin (one timed call of each per
    round) so that drift in the machine's speed during the run affects every method alike.

    Each timed call follows an untimed call of the same function. A batch's output and temporaries
    take gigabytes, and a call that follows another method's runs in memory that allocation left
    behind: measured at 1,000 poses in float64, the motor blend took 4.18 s after DQS's call, and
    3.01 s after its own, so the order of the methods decided the ratio (0.64 against 0.88)."""
    for fn in fns.values():
        jax.block_until_ready(fn(*args))  # compile + warm up
    times = {name: [] for name in fns}
    for _ in range(repeats):
        for name, fn in fns.items():
            jax.block_until_ready(fn(*args))  # settle: this method's own allocations
            start = time.perf_counter()
            out = jax.block_until_ready(fn(*args))
            times[name].append(time.perf_counter() - start)
            del out
    return {name: statistics.median(t) for name, t in times.items()}


def run(vertices: int, poses: int, repeats: int, batch_repeats: int, chunk: int):
    base = subdivided_arm5(vertices)
    params = jax.vmap(lambda k: deform.random_parameters(k, base, rotation=0.5, translation=0.01))(
        jax.random.split(jax.random.PRNGKey(0), poses)
    )
    local = deform.pose_from_parameters(base, params)  # (poses, b) rigid similitudes
    local_m = cga.versor_to_matrix(local)
    figures, ratios, units = {}, {}, {}
    print(
        f"model: {base.name}, {base.mesh.num_vertices} vertices, {base.mesh.num_joints} joints, "
        f"{base.mesh.J.shape[1]} influences; {poses} poses; {jax.device_count()} device(s), "
        f"{jax.devices()[0].platform}"
    )
    for dtype, tag in ((jnp.float32, "f32"), (jnp.float64, "f64")):
        model = as_dtype(base, dtype)
        fns = pipelines(model)
        lv, lm = local.values.astype(dtype), local_m.astype(dtype)
        # Single poses first, all methods, then the batches: the large batch outputs would otherwise
        # sit in memory while the small calls are timed.
        t_one = round_robin_times({name: jax.jit(fn) for name, fn in fns.items()}, (lv[0], lm[0]), repeats)
        many = {
            name: jax.jit(lambda lv, lm, fn=fn: jax.lax.map(lambda a: fn(*a), (lv, lm), batch_size=chunk))
            for name, fn in fns.items()
        }
        reference = many["lbs"](lv, lm)
        gaps = {}
        for name, fn in many.items():
            gaps[name] = float(jnp.max(jnp.abs(fn(lv, lm) - reference)))
        del reference
        t_many = round_robin_times(many, (lv, lm), batch_repeats)
        results = {}
        for name in fns:
            results[name] = (t_one[name], t_many[name])
            figures[f"{name}_1_pose_{tag}_ms"] = 1e3 * t_one[name]
            figures[f"{name}_{poses}_poses_{tag}_s"] = t_many[name]
            units[f"{name}_1_pose_{tag}_ms"] = "ms"
            units[f"{name}_{poses}_poses_{tag}_s"] = "s"
            rate = poses * model.mesh.num_vertices / t_many[name]
            print(
                f"  {tag} {name:16s} one pose {1e3 * t_one[name]:8.2f} ms   {poses} poses {t_many[name]:7.3f} s "
                f"({rate:.3g} vertex-poses/s)   max |x - lbs| {gaps[name]:.1e}",
                flush=True,
            )
        for ours, baseline in (("cga", "lbs"), ("cga_sum_then_project", "lbs"), ("cga_motor_blend", "dqs")):
            key = f"{ours}_vs_{baseline}_{tag}"
            ratios[key] = results[baseline][0] / results[ours][0]
            ratios[f"{ours}_vs_{baseline}_{poses}_poses_{tag}"] = results[baseline][1] / results[ours][1]
            print(
                f"  {tag} ratio {key}: {ratios[key]:.2f} (one pose), "
                f"{ratios[f'{ours}_vs_{baseline}_{poses}_poses_{tag}']:.2f} ({poses} poses)"
            )
    for name in ratios:
        units[name] = RATIO_UNIT
    return {"figures": figures, "ratios": ratios, "units": units}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--vertices", type=int, default=100_000, help="minimum vertex count (default 100000)")
    parser.add_argument("--poses", type=int, default=1000, help="poses in the vmap batch (default 1000)")
    parser.add_argument("--repeats", type=int, default=100, help="timed repetitions for one pose")
    parser.add_argument("--batch-repeats", type=int, default=5, help="timed repetitions for the batch")
    parser.add_argument(
        "--chunk",
        type=int,
        default=50,
        help="poses per vmapped chunk of the batch (jax.lax.map batch_size; bounds memory)",
    )
    parser.add_argument("--quick", action="store_true", help="small sizes for a smoke test")
    add_json_argument(parser)
    args = parser.parse_args(argv)
    print_device("bench_skinning")
    if args.quick:
        args.vertices, args.poses, args.repeats, args.batch_repeats = 5_000, 20, 3, 1
    result = run(args.vertices, args.poses, args.repeats, args.batch_repeats, args.chunk)
    write_json(args.json, result)
    return 0


if __name__ == "__main__":
    sys.exit(main())
