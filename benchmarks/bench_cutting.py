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
274 ms to drill, Python on a 2.6 GHz Core i7; the cut and the tear with GA predicates, against ours with GA
predicates, the default); ratios are baseline time / our time (> 1: we are faster).

Table 1 of the paper: the cut's four sub-routines timed one by one, with the Euclidean predicates (the baseline,
in the same run) and with the GA predicates, on Arm5 (as loaded) and on the paper's cylinder (3Cylinder4bones),
each cut by the plane across its longest extent: (1) the vertices' sides, (2) the intersection points and the
triangulation of the split faces, (3) the new vertices' weights, (4) the split into two meshes (the functions that
``cutting.cut`` calls in turn, ``cutting/_cut.py``), then the whole ``cutting.cut``; the times alternate between
the two predicate families, repetition by repetition. Printed in ms and in us per intersection point, with the
paper's figures beside them; ``{arm5,cylinder}_ga_vs_euclidean`` is the Euclidean time of the whole cut over its GA
time (the paper's: 4,476 / 4,667 ms = 0.96).

The ``real_*`` figures run on the largest character of the corpus of real characters (tests/data/characters, welded),
with tools placed as a user places them on an arm (the skin point nearest 60% of the way from the bounding box's
centre to the vertex farthest along the wider horizontal axis: a hand in a T-pose): a cut across the limb there (its
normal along the bone the point is most weighted to), a tear whose blade crosses the skin there and moves 5% of the
diagonal along the limb, a drill of radius 0.5% of the diagonal along the inward normal through the limb. Then the
per-frame deformations of ``jaxcga deform handles`` (harmonic motor handles, ``motor_field_solve``) and of ``jaxcga
arap`` (``arap_solve`` from the previous frame), the feet (lowest 3% along the long axis) fixed and the head (top
5%) turning. Baselines in the same process: trimesh's plane slice of the same mesh for the cut, LBS of one pose of
the same mesh (jit) for the others. Last, the character's tets (``xfem.tetrahedralize_surface``, fTetWild, its
defaults): time, count and quality, one run, without a baseline (TetGen refuses such a surface).

    python benchmarks/bench_cutting.py [--repeats 50] [--json out/bench/cutting.json]
"""

from __future__ import annotations

import argparse
import inspect
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

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

import cutting  # noqa: E402
import deform  # noqa: E402
import jaxcga as cga  # noqa: E402
import xfem  # noqa: E402

PAPER_MS = {"cut": 4666.0, "tear": 2437.0, "drill": 274.0}
# Table 1's rows: name, label, the paper's Arm5 ms with Euclidean and with GA predicates (sub-routines 3 and 4 do
# not use them), and its cylinder's ms (sec. 4.3: 898 ms in all, 92 intersection points; predicates not stated)
TABLE1 = (
    ("sides", "1 vertices' sides", 36.4, 72.4, 42.0),
    ("intersections", "2 intersections, triangulation", 2051.0, 2205.7, 757.0),
    ("weights", "3 weights of new vertices", 61.5, 61.5, 12.0),
    ("split", "4 split into two meshes", 2326.9, 2326.9, 87.0),
    ("cut", "whole cut (cutting.cut)", 4475.9, 4666.6, 898.0),
)
PAPER_CYLINDER_POINTS = 92
TABLE1_MODELS = {"arm5": "Arm5.glb", "cylinder": "3Cylinder4bones.glb"}


def median_ms(fn, repeats: int) -> float:
    fn()  # warm up (and compile the GA predicates)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def interleaved_seconds(fns: dict, repeats: int) -> dict:
    """Times (s) of ``repeats`` calls of each of ``fns`` (name: function), the functions called in turn at every
    repetition (so that a change of the machine's load falls on all of them), in the reverse order every other
    time (so that none is always first or last), after one warm-up call each."""
    for fn in fns.values():
        fn()
    times = {name: [] for name in fns}
    names = list(fns)
    for repeat in range(repeats):
        for name in names if repeat % 2 == 0 else names[::-1]:
            start = time.perf_counter()
            fns[name]()
            times[name].append(time.perf_counter() - start)
    return times


def both_predicates(name: str, operation, repeats: int) -> dict:
    """``{name}_ms`` and ``{name}_ga_ms``: the median ms of ``operation(predicates)`` with the Euclidean and the GA
    predicates, timed in turn (``interleaved_seconds``)."""
    seconds = interleaved_seconds({p: lambda p=p: operation(p) for p in cutting.PREDICATES}, repeats)
    return {f"{name}{'' if p == 'euclidean' else '_ga'}_ms": 1e3 * statistics.median(seconds[p]) for p in seconds}


def table1(repeats: int) -> dict:
    """Table 1 of the paper on Arm5 and on the cylinder (module docstring): figures, ratios and units."""
    try:  # the sub-routines as cutting.cut calls them (a commit measured by bench-compare may lack them)
        from cutting._cut import intersections, new_vertex_data, separate, split_mesh, vertex_sides
        from cutting._tools import check_plane
    except ImportError as error:
        print(f"Table 1 skipped: the measured cutting has no sub-routine functions ({error})")
        return {"figures": {}, "ratios": {}, "units": {}}
    tolerance = inspect.signature(cutting.cut).parameters["tolerance"].default
    figures, ratios, units = {}, {}, {}
    for tag, file in TABLE1_MODELS.items():
        mesh = deform.load_model(ROOT / "tests" / "data" / file).mesh
        mesh = deform.SkinnedMesh(
            np.asarray(mesh.V),
            np.asarray(mesh.F),
            np.asarray(mesh.J),
            np.asarray(mesh.W),
            mesh.inverse_bind,
            mesh.joints,
        )
        V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
        J, W = np.asarray(mesh.J), np.asarray(mesh.W)
        plane = plane_through_middle(V)
        edges = cutting.mesh_edges(F)
        n, d = check_plane(plane)
        fns, topologies = {}, {}
        for predicates in cutting.PREDICATES:
            # each sub-routine's input, computed once outside the timing
            s = vertex_sides(V, F, n, d, predicates, tolerance)
            crossings = intersections(V, F, edges, s, n, d, predicates)
            topology = separate(V, F, edges, n, crossings, False)
            rest, weights = new_vertex_data(V, J, W, topology, 0.0, None)
            halves = split_mesh(mesh, V, J, W, topology, rest, weights)
            # the steps compose to cutting.cut: the same halves
            for ours, theirs in zip(halves, cutting.cut(mesh, plane, edges=edges, predicates=predicates)):
                for a, b in ((ours.V, theirs.V), (ours.F, theirs.F), (ours.J, theirs.J), (ours.W, theirs.W)):
                    np.testing.assert_array_equal(a, b)
            topologies[predicates] = topology

            def split(topology=topology, rest=rest, weights=weights, crossings=crossings):
                separate(V, F, edges, n, crossings, False)
                split_mesh(mesh, V, J, W, topology, rest, weights)

            fns |= {
                (predicates, "sides"): lambda p=predicates: vertex_sides(V, F, n, d, p, tolerance),
                (predicates, "intersections"): lambda p=predicates, s=s: intersections(V, F, edges, s, n, d, p),
                (predicates, "weights"): lambda t=topology: new_vertex_data(V, J, W, t, 0.0, None),
                (predicates, "split"): split,
                (predicates, "cut"): lambda p=predicates: cutting.cut(mesh, plane, edges=edges, predicates=p),
            }
        euclidean, ga = topologies["euclidean"], topologies["ga"]
        same = all(
            np.array_equal(getattr(euclidean, field), getattr(ga, field))
            for field in ("crossing", "positive", "positive_faces", "negative", "negative_faces")
        )
        if not same:
            raise RuntimeError(f"{tag}: the Euclidean and the GA predicates give different cuts")
        points = len(euclidean.t)
        seconds = interleaved_seconds(fns, repeats)
        ms = {key: 1e3 * statistics.median(times) for key, times in seconds.items()}
        print(
            f"Table 1, {tag}: {len(F)} faces, {len(V)} vertices, {points} intersection points (the same cut with "
            f"both predicates); ms (us per intersection point)"
        )
        paper = "paper Euclidean / GA ms" if tag == "arm5" else f"paper ms ({PAPER_CYLINDER_POINTS} points)"
        print(f"  {'sub-routine':32s} {'Euclidean':>15s} {'GA':>15s} {'GA/Eucl.':>9s}   {paper}")
        for name, label, paper_euclidean, paper_ga, paper_cylinder in TABLE1:
            e, g = ms[("euclidean", name)], ms[("ga", name)]
            figures[f"{tag}_table1_{name}_ms"], figures[f"{tag}_table1_{name}_ga_ms"] = e, g
            quoted = f"{paper_euclidean:.1f} / {paper_ga:.1f}" if tag == "arm5" else f"{paper_cylinder:.0f}"
            print(
                f"  {label:32s} {e:7.3f} ({1e3 * e / points:5.2f}) {g:7.3f} ({1e3 * g / points:5.2f}) "
                f"{g / e:8.2f}x   {quoted}"
            )
        parts = [ms[(p, name)] for p in cutting.PREDICATES for name, *_ in TABLE1[:4]]
        print(f"  {'sum of 1-4':32s} {sum(parts[:4]):7.3f} {'':7s} {sum(parts[4:]):7.3f}")
        figures[f"{tag}_intersection_points"] = points
        units[f"{tag}_intersection_points"] = "points"
        ratios[f"{tag}_ga_vs_euclidean"] = ms[("euclidean", "cut")] / ms[("ga", "cut")]
        print(
            f"ratio {tag}_ga_vs_euclidean: {ratios[f'{tag}_ga_vs_euclidean']:.2f} (Euclidean / GA time of the whole "
            f"cut; target >= 0.91, the paper's {TABLE1[-1][2] / TABLE1[-1][3]:.2f})"
        )
    return {"figures": figures, "ratios": ratios, "units": units}


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
        figures |= both_predicates(
            f"{tag}_cut", lambda predicates: cutting.cut(mesh, plane, edges=edges, predicates=predicates), repeats
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
        figures |= both_predicates(
            f"{tag}_tear",
            lambda predicates: cutting.tear(welded, scalpel, opening=0.2, edges=welded_edges, predicates=predicates),
            repeats,
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
        # the paper's cut and tear use GA predicates (Table 1), as ours do by default; the drill has none
        ours = f"arm5_{op}_ga_ms" if f"arm5_{op}_ga_ms" in figures else f"arm5_{op}_ms"
        ratios[f"arm5_{op}_vs_paper"] = paper / figures[ours]
        print(f"ratio arm5_{op}_vs_paper: {ratios[f'arm5_{op}_vs_paper']:.0f}x (paper {paper:.0f} ms, ours {ours})")
    table = table1(4 * repeats)  # sub-routines of tens of microseconds, compared with each other: more repetitions
    figures.update(table["figures"])
    ratios.update(table["ratios"])
    real = real_figures(repeats, frames=min(20, max(3, repeats)))
    figures.update(real["figures"])
    ratios.update(real["ratios"])
    for name in figures:
        units[name] = REAL_UNITS.get(name, "ms")
    units.update(table["units"])
    for name in ratios:
        units[name] = RATIO_UNIT
    return {"figures": figures, "ratios": ratios, "units": units}


REAL_UNITS = {"real_tets": "tets", "real_tets_min_dihedral_deg": "deg", "real_tets_min_volume_ratio": "1"}


def largest_character() -> deform.RiggedModel:
    """The character of tests/data/characters with the most vertices, welded."""
    paths = sorted((ROOT / "tests" / "data" / "characters").glob("*.glb"))
    return max((deform.load_model(p, weld=True) for p in paths), key=lambda m: m.mesh.num_vertices)


def limb_direction(model, face: int, barycentric) -> np.ndarray:
    """Unit direction of the bone the point is most weighted to, in the bind pose: from its joint to its child joints'
    mean (or from its parent joint)."""
    mesh = model.mesh
    F, J, W = np.asarray(mesh.F), np.asarray(mesh.J), np.asarray(mesh.W)
    weight = np.zeros(mesh.num_joints)
    np.add.at(weight, J[F[face]].ravel(), (np.asarray(barycentric)[:, None] * W[F[face]]).ravel())
    joint = int(np.argmax(weight))
    heads = np.linalg.inv(np.asarray(mesh.inverse_bind, np.float64))[:, :3, 3]
    bones, parents = np.asarray(mesh.joints), np.asarray(model.skeleton.parents)
    children = np.flatnonzero(parents[bones] == bones[joint])
    if len(children):
        axis = heads[children].mean(axis=0) - heads[joint]
    else:
        axis = heads[joint] - heads[np.flatnonzero(bones == parents[bones[joint]])[0]]
    return axis / np.linalg.norm(axis)


def arm_tools(model) -> tuple[cutting.Plane, cutting.Scalpel, cutting.Drill]:
    """The module docstring's cut, tear and drill on ``model``'s arm (bind pose)."""
    V, F = np.asarray(model.mesh.V, np.float64), np.asarray(model.mesh.F)
    extent = V.max(axis=0) - V.min(axis=0)
    diagonal = float(np.linalg.norm(extent))
    long = int(np.argmax(extent))
    side = max((a for a in range(3) if a != long), key=lambda a: extent[a])
    centre = 0.5 * (V.min(axis=0) + V.max(axis=0))
    target = centre + 0.6 * (V[np.argmax(V[:, side])] - centre)
    _, faces, closest = igl.point_mesh_squared_distance(target[None], V, F)
    face, point = int(faces[0]), closest[0]
    a, b, c = V[F[face]]
    barycentric = np.linalg.lstsq(np.stack([a, b, c], axis=1), point, rcond=None)[0]
    normal = np.cross(b - a, c - a)
    normal /= np.linalg.norm(normal)
    along = limb_direction(model, face, barycentric)
    plane = cutting.Plane(along, float(along @ point))
    end, _ = surface_point(V, F, point + 0.05 * diagonal * along)
    _, end_face, _ = igl.point_mesh_squared_distance(end[None], V, F)
    a2, b2, c2 = V[F[end_face[0]]]
    normal_end = np.cross(b2 - a2, c2 - a2)
    normal_end /= np.linalg.norm(normal_end)
    blade = 0.02 * diagonal
    scalpel = cutting.Scalpel(
        np.array([point + blade * normal, end + blade * normal_end]),
        np.array([point - blade * normal, end - blade * normal_end]),
    )
    radius = 0.005 * diagonal
    depth = through(V, F, point, -normal) + 2 * radius
    return plane, scalpel, cutting.Drill(point - depth * normal, point + 2 * radius * normal, radius)


def through(V, F, origin, direction) -> float:
    """Distance along the unit ``direction`` from ``origin`` (on the surface) to the farthest crossing of the surface
    within a tenth of the diagonal: where the ray leaves the limb (Moller and Trumbore's test on every face)."""
    a, b, c = (V[F[:, k]] for k in range(3))
    e1, e2 = b - a, c - a
    p = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, p)
    inv = np.divide(1.0, det, out=np.zeros_like(det), where=np.abs(det) > 1e-300)
    s = origin - a
    u, q = np.einsum("ij,ij->i", s, p) * inv, np.cross(s, e1)
    v, t = (q @ direction) * inv, np.einsum("ij,ij->i", e2, q) * inv
    diagonal = float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))
    hit = (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 1e-6 * diagonal) & (t < 0.1 * diagonal)
    return float(t[hit].max()) if hit.any() else 0.03 * diagonal


def feet_and_head(V) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(feet, head, neck point, the axis the head turns about): the lowest 3% and the top 5% of the vertices along the
    long axis, the head's lowest point at its centre, the wider horizontal axis."""
    extent = V.max(axis=0) - V.min(axis=0)
    long = int(np.argmax(extent))
    side = max((a for a in range(3) if a != long), key=lambda a: extent[a])
    height = V[:, long]
    feet = np.flatnonzero(height <= np.quantile(height, 0.03))
    head = np.flatnonzero(height >= np.quantile(height, 0.95))
    neck = V[head].mean(axis=0)
    neck[long] = height[head].min()
    return feet, head, neck, side


def real_figures(repeats: int, frames: int = 20) -> dict:
    """The ``real_*`` figures (module docstring)."""
    model = largest_character()
    mesh = model.mesh
    mesh = deform.SkinnedMesh(
        np.asarray(mesh.V), np.asarray(mesh.F), np.asarray(mesh.J), np.asarray(mesh.W), mesh.inverse_bind, mesh.joints
    )
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    plane, scalpel, drill = arm_tools(model)
    edges = cutting.mesh_edges(mesh.F)
    print(f"real: {model.name}, {len(V)} vertices, {len(F)} faces, {mesh.num_joints} joints (welded)")
    local = deform.local_matrices(model.skeleton)
    skin = jax.jit(lambda local: deform.skin_pose(deform.RiggedModel(mesh, model.skeleton), local, "lbs"))
    skin_ms = median_ms(lambda: jax.block_until_ready(skin(local)), repeats)
    slice_ms = median_ms(
        lambda: trimesh.intersections.slice_faces_plane(V, F, plane.normal, plane.normal * plane.distance), repeats
    )
    figures = {"real_skin_ms": skin_ms, "real_trimesh_slice_ms": slice_ms}
    ratios = {}
    timed = {
        "cut": lambda: cutting.cut(mesh, plane, edges=edges),
        "tear": lambda: cutting.tear(mesh, scalpel, edges=edges),
        "drill": lambda: cutting.drill(mesh, drill, edges=edges),
    }
    for name, fn in timed.items():
        try:
            figures[f"real_{name}_ms"] = median_ms(fn, repeats)
        except ValueError as error:  # reported, the other figures still measured
            print(f"  {name:6s} refused: {error}")
            continue
        baseline, label = (slice_ms, "trimesh_slice") if name == "cut" else (skin_ms, "skinning")
        ratios[f"real_{name}_vs_{label}"] = baseline / figures[f"real_{name}_ms"]
        print(
            f"  {name:6s} {figures[f'real_{name}_ms']:8.2f} ms  ({label.replace('_', ' ')} {baseline:.2f} ms: "
            f"{ratios[f'real_{name}_vs_{label}']:.2f}x)"
        )
    feet, head, neck, side = feet_and_head(V)
    axis = np.zeros(3)
    axis[side] = 1.0
    angles = np.linspace(0.0, 0.6, frames)

    def turned(angle):
        """Motors (2,): the feet's (the identity) and the head's, turned by ``angle`` about the neck."""
        rotor = cga.rotor(jnp.asarray([axis, axis]), jnp.asarray([0.0, angle]))
        return deform.motor_about(jnp.asarray([neck, neck]), rotor)

    deformers = {}
    try:
        field = deform.handles_precompute(V, F, [feet, head])
        solve = jax.jit(deform.motor_field_solve)
        motors = [turned(a) for a in angles]
        deformers["handles"] = lambda k: solve(field, motors[k])
    except ValueError as error:
        print(f"  deform handles refused: {error}")
    try:
        data = deform.arap_precompute(V, F, np.concatenate([feet, head]))
        arap = jax.jit(lambda bc, V0: deform.arap_solve(data, bc, V0=V0).U)
        targets = [
            np.concatenate([V[feet], np.asarray(cga.apply_to_points(turned(a)[1], jnp.asarray(V[head])))])
            for a in angles
        ]
        previous = {"U": jnp.asarray(V)}

        def arap_frame(k):
            previous["U"] = arap(jnp.asarray(targets[k]), previous["U"])
            return previous["U"]

        deformers["arap"] = arap_frame
    except ValueError as error:
        print(f"  arap refused: {error}")
    for name, frame in deformers.items():
        jax.block_until_ready(frame(0))  # compile
        times = []
        for k in range(frames):
            start = time.perf_counter()
            jax.block_until_ready(frame(k))
            times.append(time.perf_counter() - start)
        figures[f"real_{name}_ms"] = 1e3 * statistics.median(times)
        ratios[f"real_{name}_vs_skinning"] = skin_ms / figures[f"real_{name}_ms"]
        print(
            f"  {name:6s} {figures[f'real_{name}_ms']:8.2f} ms per frame  (skinning {skin_ms:.2f} ms: "
            f"{ratios[f'real_{name}_vs_skinning']:.2f}x)"
        )
    # one run (fTetWild takes tens of seconds); no baseline in the same process: TetGen refuses such a surface
    start = time.perf_counter()
    tets = xfem.tetrahedralize_surface(V, F)
    figures["real_tetrahedralize_ms"] = 1e3 * (time.perf_counter() - start)
    figures["real_tets"] = tets.quality.tets
    figures["real_tets_min_dihedral_deg"] = tets.quality.min_dihedral_deg
    figures["real_tets_min_volume_ratio"] = tets.quality.min_volume_ratio
    q = tets.quality
    print(
        f"  tetrahedralize_surface {figures['real_tetrahedralize_ms'] / 1e3:.1f} s: {q.tets} tets, smallest "
        f"dihedral angle {q.min_dihedral_deg:.1f} deg, worst volume ratio {q.min_volume_ratio:.3f}"
    )
    return {"figures": figures, "ratios": ratios}


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
