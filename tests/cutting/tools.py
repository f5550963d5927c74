"""Shared by the cutting tests: the real models, measures of meshes (areas, edge counts), a posed
arm, tools placed on real models (scalpels that sweep over the surface, drills along a face's
inward normal), and tools placed on the corpus characters as a user places them (a cut across the limb
under a skin point, a tear along the skin, a drill through the limb), with their poses and checks."""

from __future__ import annotations

from pathlib import Path

import igl
import numpy as np

import deform
import jaxcga as cga

DATA = Path(__file__).resolve().parents[1] / "data"


def load_models(weld: bool):
    """Arm5 and 3Cylinder4bones. Welded: glTF splits vertices along UV seams, and a tear or a drill
    walks across faces."""
    return {name: deform.load_model(DATA / f"{name}.glb", weld=weld) for name in ("Arm5", "3Cylinder4bones")}


def rigid_mesh(V, F):
    """A ``deform.SkinnedMesh`` of V, F on one joint at the identity (every vertex weight 1): a plain surface."""
    import jax.numpy as jnp

    return deform.SkinnedMesh(
        jnp.asarray(V),
        jnp.asarray(F, jnp.int32),
        jnp.zeros((len(V), 1), jnp.int32),
        jnp.ones((len(V), 1)),
        jnp.eye(4)[None],
        (0,),
    )


def area(V, F):
    """Per-face areas."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    return 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1)


def diagonal(V) -> float:
    V = np.asarray(V)
    return float(np.linalg.norm(V.max(axis=0) - V.min(axis=0)))


def edge_counts(F):
    """(unique undirected edges, how many faces each has)."""
    F = np.asarray(F)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    return np.unique(edges, axis=0, return_counts=True)


def _frame(V, F, face):
    V, F = np.asarray(V, np.float64), np.asarray(F)
    corners = V[F[face]]
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    return corners.mean(axis=0), normal / np.linalg.norm(normal)


def mean_edge(V, F) -> float:
    V, F = np.asarray(V, np.float64), np.asarray(F)
    return float(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1).mean())


def scalpel_of(segments):
    """A ``cutting.Scalpel`` from its (samples, 2, 3) segment endpoints (handle end first)."""
    import cutting

    segments = np.asarray(segments, np.float64)
    return cutting.Scalpel(segments[:, 0], segments[:, 1])


def scalpels_over(V, F, face, direction, samples: int, step: float, depth: float | None = None):
    """A ``cutting.Scalpel`` of ``samples`` positions walking over the surface: from ``face``'s centre, each sample
    moves ``step`` along ``direction`` (projected onto the tangent plane) and back onto the surface
    (closest point); the scalpel is the segment along the surface normal there, handle outside."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    point, normal = _frame(V, F, face)
    depth = 0.5 * step if depth is None else depth
    direction = np.asarray(direction, np.float64)
    scalpels = []
    for i in range(samples):
        if i:
            tangent = direction - (direction @ normal) * normal
            if np.linalg.norm(tangent) < 1e-6 * np.linalg.norm(direction):  # along the normal: any tangent
                tangent = np.cross(normal, [1.0, 0.0, 0.0] if abs(normal[0]) < 0.9 else [0.0, 1.0, 0.0])
            tangent /= np.linalg.norm(tangent)
            found = igl.point_mesh_squared_distance((point + step * tangent)[None], V, F)
            faces, closest = np.asarray(found[1]), np.asarray(found[2])
            direction = closest[0] - point  # keep going the same way over the curved surface
            point, normal = closest[0], _frame(V, F, faces[0])[1]
        scalpels.append([point + depth * normal, point - depth * normal])
    return scalpel_of(scalpels)


def drill_into(V, F, face, depth: float):
    """(tip, base) of a drill entering the surface at ``face``'s centre along its inward normal."""
    centre, normal = _frame(V, F, face)
    return centre - depth * normal, centre + depth * normal


def posed(model, t: float):
    """(local matrices, joint matrices, LBS positions) of ``model``'s clip at time t: a tool is then
    given in that pose's world space."""
    local = deform.sample_pose(model, t, "lbs")
    assert not isinstance(local, cga.Multivector)  # the matrix methods' pose
    joints = deform.joint_matrices(model.mesh, deform.forward_kinematics_matrices(model.skeleton.parents, local))
    return local, joints, np.asarray(deform.skin_pose(model, local, "lbs"))


# A tear refuses only a blade that never crosses the surface; a tool placed on the surface by construction crosses it.
TOOL_REFUSALS = ("never crosses",)


def swept_distance(scalpel, points, strips: int = 64):
    """Distances (p,) of ``points`` (p, 3) from the surface that the ``scalpel``'s blade sweeps: between samples
    i and i+1 the ruled (bilinear) surface through handle_i, tip_i, tip_{i+1}, handle_{i+1}, as ``strips``
    strips of two triangles each per step."""
    k = len(np.asarray(scalpel.handle))
    blades = blade_at(scalpel, np.linspace(0.0, k - 1, strips * (k - 1) + 1))  # (b, 2, 3)
    b = len(blades)
    rows = np.arange(b - 1)
    quads = np.concatenate([np.stack([rows, b + rows, b + rows + 1], 1), np.stack([rows, b + rows + 1, rows + 1], 1)])
    ends = np.concatenate([blades[:, 0], blades[:, 1]])
    squared, _, _ = igl.point_mesh_squared_distance(np.asarray(points, np.float64), ends, quads)
    return np.sqrt(squared)


def blade_at(scalpel, times):
    """The blade's ends (t, 2, 3) at ``times`` in [0, k], interpolated linearly between the scalpel's samples."""
    segments = np.stack([np.asarray(scalpel.handle, np.float64), np.asarray(scalpel.tip, np.float64)], axis=1)
    times = np.asarray(times, np.float64)
    i = np.minimum(np.floor(times).astype(int), len(segments) - 2)
    a = (times - i)[:, None, None]
    return (1 - a) * segments[i] + a * segments[i + 1]


def check_torn(mesh, scalpel, torn, path, opening: float = 0.0):
    """Assert the invariants of a tear of ``mesh`` by ``scalpel`` (``tear(..., return_topology=True)`` gave
    ``torn, path``): the area kept (a closed slit), no sliver, a consistent mesh with valid weights, tear points
    on their planes and near the swept surface (where the blade passed), tips on the blade, the input's
    vertices first and unchanged, each stretch one new boundary loop."""
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    Vt, Ft = np.asarray(torn.V, np.float64), np.asarray(torn.F)
    scale = diagonal(V)
    if opening == 0:  # the new vertices are stored in the mesh's dtype: float32 rounds them (coarse meshes show it)
        total = area(V, F).sum()
        assert abs(area(Vt, Ft).sum() - total) <= (1e-9 if np.asarray(mesh.V).dtype == np.float64 else 1e-6) * total
    ids = np.arange(len(Vt))
    problems, _, _ = piece_quality(V, F, Vt, Ft, ids)
    assert not problems + consistency_problems(torn, mesh, ids)
    n, d = path.planes[path.step, :3], path.planes[path.step, 3]
    assert np.all(np.abs(np.einsum("ij,ij->i", path.points, n) - d) <= 1e-9 * scale)
    # where the blade passed: a tear point lies within 0.4 of its edge's length of its step's quadrilateral (plus the
    # move of its plane off a vertex), and that quadrilateral within a quarter of an edge of the ruled surface the
    # blade swept, near the skin: 0.75 of the edge in all (0.53 at most over 2,100 tears measured on 13 characters)
    lengths = np.linalg.norm(V[path.crossing[:, 0]] - V[path.crossing[:, 1]], axis=1)
    assert np.all(swept_distance(scalpel, path.points) <= 0.75 * lengths + np.abs(path.shift[path.step]))
    # the tips on the blade at their times (kept 2% barycentric off their faces' edges), but for the ends of a minimal
    # slit: there by their offset, on either side of the blade's crossing
    tips = path.stretches.ravel()
    blades = blade_at(scalpel, path.sample_times[tips])
    offsets = path.sample_offsets[tips]
    for blade, point, face, offset in zip(blades, path.sample_points[tips], path.sample_faces[tips], offsets):
        direction = blade[1] - blade[0]
        off_line = np.linalg.norm(np.cross(point - blade[0], direction)) / np.linalg.norm(direction)
        corners = V[F[face]]
        longest = np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).max()
        assert off_line <= 0.06 * longest + np.linalg.norm(offset @ corners)
    # a minimal slit: both ends in one face at one time, its length at most half the face's longest edge
    minimal = np.abs(offsets).reshape(-1, 2, 3).sum(axis=(1, 2)) > 0
    for first, last in path.stretches[minimal]:
        corners = V[F[path.sample_faces[first]]]
        assert path.sample_faces[first] == path.sample_faces[last]
        assert path.sample_times[first] == path.sample_times[last]
        length = np.linalg.norm(path.sample_points[last] - path.sample_points[first])
        assert length <= 0.5 * np.linalg.norm(corners - np.roll(corners, 1, axis=0), axis=1).max() * (1 + 1e-9)
    np.testing.assert_array_equal(Vt[: len(V)], V)
    np.testing.assert_allclose(np.asarray(torn.W)[len(V) :].sum(axis=1), 1.0, atol=1e-12)
    # each stretch a slit: its tips single, its points (the Q_j, or the middle of a slit inside one face) doubled,
    # one new boundary loop of 2 (points + 1) edges
    r, q = len(path.stretches), len(path.t) + len(path.inner)
    assert len(Vt) == len(V) + 2 * r + 2 * q
    before, after = edge_counts(F)[1], edge_counts(Ft)[1]
    assert after.max() <= max(2, before.max())
    assert np.count_nonzero(after == 1) == np.count_nonzero(before == 1) + 2 * (q + r)


# --- Sliver fuzzing (issue 30, item 2) --------------------------------------------------------------
# A cut, tear or drill may not make a face smaller than AREA_RATIO x the input's smallest face, nor
# one with an angle under MIN_ANGLE unless the input face it comes from already has one.
AREA_RATIO = 1e-3
MIN_ANGLE = 1e-3
ON_TOOL = 1e-9  # new points lie on the tool's surface to this fraction of the bounding-box diagonal


def angles(V, F):
    """(m, 3) interior angles of the faces."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    result = []
    for k in range(3):
        u = V[F[:, (k + 1) % 3]] - V[F[:, k]]
        w = V[F[:, (k + 2) % 3]] - V[F[:, k]]
        result.append(np.arctan2(np.linalg.norm(np.cross(u, w), axis=1), np.einsum("ij,ij->i", u, w)))
    return np.stack(result, axis=1)


def piece_quality(V, F, V_out, F_out, ids):
    """Problems of the faces an operation made (those that are not input faces).

    ``ids``: for each output vertex its index in the input (or any value >= len(V) for a new one).
    Returns (problems: list of strings, smallest area ratio, smallest angle) over the new faces; the
    area ratio is against the input's smallest face, and an angle under MIN_ANGLE is a problem only
    where the input face holding the new face's centroid has none."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    V_out, F_out, ids = np.asarray(V_out, np.float64), np.asarray(F_out), np.asarray(ids)
    problems = []

    def keys(faces):  # one integer per face, whatever its rotation
        faces = np.sort(faces, axis=1).astype(np.int64)
        return (faces[:, 0] * (len(V) + 1) + faces[:, 1]) * (len(V) + 1) + faces[:, 2]

    labels = ids[F_out]
    is_new = (labels >= len(V)).any(axis=1) | ~np.isin(keys(np.minimum(labels, len(V))), keys(F))
    new = F_out[is_new]
    if not len(new):
        return problems, np.inf, np.inf
    ratio = area(V_out, new) / area(V, F).min()
    smallest = angles(V_out, new).min(axis=1)
    if ratio.min() < AREA_RATIO:
        problems.append(f"face of area {ratio.min():.3g} x the input's smallest")
    thin = np.flatnonzero(smallest < MIN_ANGLE)
    if len(thin):
        centroids = V_out[new[thin]].mean(axis=1)
        parents = np.asarray(igl.point_mesh_squared_distance(centroids, V, F)[1])
        inherited = angles(V, F[parents]).min(axis=1) < MIN_ANGLE
        if not inherited.all():
            problems.append(f"face with an angle of {smallest[thin][~inherited].min():.3g} rad")
    return problems, float(ratio.min()), float(smallest.min())


def consistency_problems(mesh, input_mesh, ids):
    """Problems of an output SkinnedMesh: repeated corners, duplicate faces, an edge on more than
    two faces or twice in one direction (inconsistent winding), unused vertices, weights of new
    vertices negative or not summing to one, input vertices' weights changed. ``ids``: as for
    ``piece_quality``."""
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    J, W = np.asarray(mesh.J), np.asarray(mesh.W)
    problems = []
    if np.any((F[:, 0] == F[:, 1]) | (F[:, 1] == F[:, 2]) | (F[:, 2] == F[:, 0])):
        problems.append("a face repeats a corner")
    if len(np.unique(np.sort(F, axis=1), axis=0)) != len(F):
        problems.append("duplicate faces")
    if edge_counts(F)[1].max() > 2:
        problems.append("an edge on more than two faces")
    directed = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    if len(np.unique(directed, axis=0)) != len(directed):
        problems.append("inconsistent winding (a directed edge twice)")
    if len(np.unique(F)) != len(V):
        problems.append("unused vertices")
    ids = np.asarray(ids)
    old = ids < len(input_mesh.V)
    # the input's own weights are kept as they are (glTF's float32 sums are off by up to 2e-3)
    if not np.array_equal(W[old], np.asarray(input_mesh.W)[ids[old]]):
        problems.append("an input vertex's weights changed")
    new = W[~old]
    if not (np.all(new >= 0) and np.allclose(new.sum(axis=1), 1.0, rtol=0, atol=8 * np.finfo(W.dtype).eps)):
        problems.append("weights of a new vertex negative or not summing to one")
    if not (np.all(J >= 0) and np.all(J < input_mesh.num_joints)):
        problems.append("joint index out of range")
    return problems


def random_plane(V, rng):
    """A ``cutting.Plane`` with a random unit normal through the mesh (between 1% and 99% of its extent
    along it)."""
    import cutting

    n = rng.normal(size=3)
    n /= np.linalg.norm(n)
    heights = np.asarray(V) @ n
    return cutting.Plane(n, heights.min() + rng.uniform(0.01, 0.99) * (heights.max() - heights.min()))


def random_surface_point(V, F, rng):
    """(face, point, unit normal): a uniformly random point of the surface."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    areas = area(V, F)
    face = int(rng.choice(len(F), p=areas / areas.sum()))
    b = rng.dirichlet(np.ones(3))
    _, normal = _frame(V, F, face)
    return face, b @ V[F[face]], normal


def random_drill(V, F, rng):
    """A ``cutting.Drill``: a drill along the normal at a random surface point, radius 0.3 to 2 mean
    edges, its axis piercing the surface there."""
    _, point, normal = random_surface_point(V, F, rng)
    edge = mean_edge(V, F)
    radius = rng.uniform(0.3, 2.0) * edge
    depth = rng.uniform(0.5, 2.0) * edge
    import cutting

    return cutting.Drill(point - depth * normal, point + depth * normal, radius)


def random_scalpels(V, F, rng):
    """(samples, 2, 3) scalpels crossing the surface: 2 to 4 samples, 1.5 to 4 mean edges apart,
    from a random face in a random direction (``scalpels_over``), each reaching a step's length to
    both sides of the surface."""
    face, _, _ = random_surface_point(V, F, rng)
    step = rng.uniform(1.5, 4.0) * mean_edge(V, F)
    return scalpels_over(V, F, face, rng.normal(size=3), int(rng.integers(2, 5)), step, depth=step)


def fuzz(mesh, tool: str, count: int, seed: int):
    """Apply ``count`` random tools (``"plane"``, ``"drill"`` or ``"tear"``) to ``mesh`` (bind pose); a
    tool that the algorithm declines (a ValueError) is recorded and replaced by another, up to 3 *
    ``count`` tries.

    Returns a dict: runs (tools applied), refused (the ValueError messages), failures (descriptions),
    smallest area ratio and smallest angle of the new faces, the largest distance of a new point from
    the tool's surface (off_tool) and the largest distance from it of an input vertex that the cut's
    boundary passes through instead of a new point next to it (snapped; for a tear: the largest move
    of its plane), both relative to the diagonal."""
    import cutting

    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F)
    edges = cutting.mesh_edges(F)
    scale = diagonal(V)
    rng = np.random.default_rng(seed)
    stats = {
        "runs": 0,
        "refused": [],
        "failures": [],
        "area_ratio": np.inf,
        "angle": np.inf,
        "off_tool": 0.0,
        "snapped": 0.0,
    }
    for trial in range(3 * count):
        if stats["runs"] == count:
            break
        try:
            if tool == "plane":
                plane = random_plane(V, rng)
                halves, topology = cutting.cut(mesh, plane, edges=edges, return_topology=True)
                outputs = [(h, keep) for h, keep in zip(halves, (topology.positive, topology.negative))]
                off = np.abs(topology.points @ plane.normal - plane.distance)
                snapped = np.abs(V @ plane.normal - plane.distance)[topology.distances == 0]
            elif tool == "drill":
                drill = random_drill(V, F, rng)
                tip, base, radius = drill.tip, drill.base, drill.radius
                drilled, topology = cutting.drill(mesh, drill, edges=edges, return_topology=True)
                outputs = [(drilled, topology.kept)]
                axis = (tip - base) / np.linalg.norm(tip - base)
                relative = topology.points - base
                off = np.abs(np.linalg.norm(relative - np.outer(relative @ axis, axis), axis=1) - radius)
                # input vertices on the hole's boundary (on a boundary edge that the input did not have)
                rim_edges, rim_counts = edge_counts(topology.kept[np.asarray(drilled.F)])
                before_edges, before_counts = edge_counts(F)
                rim = np.unique(rim_edges[rim_counts == 1])
                rim = np.setdiff1d(rim[rim < len(V)], before_edges[before_counts == 1])
                relative = V[rim] - base
                snapped = np.abs(np.linalg.norm(relative - np.outer(relative @ axis, axis), axis=1) - radius)
            else:
                scalpels = random_scalpels(V, F, rng)
                torn, path = cutting.tear(mesh, scalpels, edges=edges, return_topology=True)
                outputs = [(torn, np.arange(len(torn.V)))]
                normals, offsets = path.planes[path.step, :3], path.planes[path.step, 3]
                off = np.abs(np.einsum("ij,ij->i", path.points, normals) - offsets)
                snapped = np.abs(path.shift)
        except ValueError as error:
            stats["refused"].append(f"{tool} {trial}: {error}")
            continue
        stats["runs"] += 1
        problems = []
        for out, ids in outputs:
            found, ratio, angle = piece_quality(V, F, out.V, out.F, ids)
            problems += found + consistency_problems(out, mesh, ids)
            stats["area_ratio"] = min(stats["area_ratio"], ratio)
            stats["angle"] = min(stats["angle"], angle)
        worst = float(off.max(initial=0.0)) / scale
        stats["off_tool"] = max(stats["off_tool"], worst)
        stats["snapped"] = max(stats["snapped"], float(snapped.max(initial=0.0)) / scale)
        if worst > ON_TOOL:
            problems.append(f"a new point {worst:.3g} x diagonal off the tool")
        if problems:
            stats["failures"].append(f"{tool} {trial}: " + "; ".join(problems))
    return stats


# --- Drills through layered characters (issue 51, item 2) ---------------------------------------------


def drill_through_limb(V, F, rng, *, radius=(0.05, 0.3), tries: int = 100):
    """A ``cutting.Drill`` placed as a user places one: at a random point of the outer skin (just outside it,
    the generalized winding number of the whole mesh is below 1/2), along the inward normal, through the limb
    (its tip just past the first point where the inward ray leaves every layer, winding number below 1/2
    again), its radius a random fraction ``radius`` of the limb's thickness there. It crosses every layer
    in between (clothing, the skin, inner meshes). Returns (drill, thickness)."""
    import cutting
    from cutting._geometry import segment_hits  # the ray's crossings, as the drill finds its seeds

    V, F = np.asarray(V, np.float64), np.asarray(F)
    scale = diagonal(V)
    for _ in range(tries):
        face, point, normal = random_surface_point(V, F, rng)
        outer = point + 1e-4 * scale * normal
        _, _, s = segment_hits(V, F, point - 1e-6 * scale * normal, point - scale * normal)
        if not len(s):
            continue
        s = np.concatenate([s, [1.0]]) * scale
        between = point - 0.5 * (np.concatenate([[0.0], s[:-1]]) + s)[:, None] * normal
        winding = np.asarray(igl.fast_winding_number(V, F, np.vstack([outer, between])))
        if winding[0] > 0.5:  # not on the outer skin
            continue
        out = np.flatnonzero(winding[2:] < 0.5)  # the first gap outside every layer after a crossing
        if not len(out) or out[0] + 1 >= len(s):
            continue
        thickness = float(s[out[0]])
        r = rng.uniform(*radius) * thickness
        tip = point - (thickness + 0.5 * r) * normal
        base = point + 0.5 * r * normal
        return cutting.Drill(tip, base, r), thickness
    raise ValueError("no skin point with a limb behind it found")


def inside_drill(X, drill, margin: float):
    """Which points X (n, 3) lie strictly inside the drilled volume: distance to the axis under
    drill.radius - margin, height along the axis strictly between base and tip."""
    tip, base, r = (np.asarray(x, np.float64) for x in (drill.tip, drill.base, drill.radius))
    length = float(np.linalg.norm(tip - base))
    axis = (tip - base) / length
    relative = np.asarray(X, np.float64) - base
    h = relative @ axis
    rho = np.linalg.norm(relative - np.outer(h, axis), axis=1)
    return (rho < r - margin) & (h > 0) & (h < length)


def drill_outcome(V, F, drill, topology, tolerance: float = 1e-6):
    """What a drill left, in the space it was drilled in (``topology.vertices``), relative to the bounding-box
    diagonal of V: (input vertices left strictly inside the drilled volume (count; ``inside_drill`` with
    margin tolerance x diagonal), the largest distance of a rim vertex from the cylinder, the largest distance
    of a rim edge's midpoint). The rim: the boundary edges of the drilled mesh that do not lie along the
    input's own boundary."""
    V, F = np.asarray(V, np.float64), np.asarray(F)
    tip, base, r = (np.asarray(x, np.float64) for x in (drill.tip, drill.base, drill.radius))
    scale = diagonal(V)
    axis = (tip - base) / np.linalg.norm(tip - base)

    def radial(X):
        relative = X - base
        return np.linalg.norm(relative - np.outer(relative @ axis, axis), axis=1)

    original = topology.kept[topology.kept < len(V)]
    inside = int(inside_drill(topology.vertices[original], drill, tolerance * scale).sum())
    X = np.concatenate([topology.vertices, topology.points])[topology.kept]
    edges, counts = edge_counts(topology.faces)
    rim = edges[counts == 1]
    input_edges, input_counts = edge_counts(F)
    border = input_edges[input_counts == 1]
    if len(rim) and len(border):
        # a boundary edge along an input boundary edge: its midpoint lies on that edge
        a, b = V[border[:, 0]], V[border[:, 1]]
        mid = 0.5 * (X[rim[:, 0]] + X[rim[:, 1]])
        d = b - a
        t = np.clip(np.einsum("mbj,bj->mb", mid[:, None] - a[None], d) / np.einsum("bj,bj->b", d, d), 0.0, 1.0)
        gap = np.linalg.norm(mid[:, None] - (a[None] + t[..., None] * d[None]), axis=2).min(axis=1)
        rim = rim[gap > 1e-9 * scale]
    if not len(rim):
        return inside, 0.0, 0.0
    vertex = np.abs(radial(X[np.unique(rim)]) - r).max()
    middle = np.abs(radial(0.5 * (X[rim[:, 0]] + X[rim[:, 1]])) - r).max()
    return inside, float(vertex) / scale, float(middle) / scale


# --- Tools placed on real characters (issue 51, item 5) ---------------------------------------------------------------
# A user picks a point of the skin and places the tool there: a plane across the limb (its normal along the bone the
# point is most weighted to), a blade through the skin that moves along it, a drill along the inward normal that goes
# through the limb.
TEAR_TRAVEL = 0.05  # a tear's blade moves this fraction of the diagonal along the surface


def character_pose(model, seed: int = 0) -> np.ndarray:
    """(j, 4, 4) joint matrices of a pose of ``model``: 40% into its first clip, or, without a clip, the rest pose
    with every bone turned by a random rotation of up to 25 degrees (seeded)."""
    from scipy.spatial.transform import Rotation

    if model.clips:
        times = np.concatenate([np.asarray(c.times) for c in model.clips[0].channels])
        local = np.asarray(deform.sample_pose(model, times.min() + 0.4 * np.ptp(times), "lbs"))
    else:
        local = np.array(deform.local_matrices(model.skeleton))
        # the legacy keyword keeps the seeded stream (scipy's signature names only rng)
        turn = Rotation.random(len(local), random_state=seed).as_rotvec()  # pyright: ignore[reportCallIssue]
        turn *= np.radians(25.0) / np.pi  # rotation vectors of length <= pi scaled to <= 25 degrees
        local[:, :3, :3] = local[:, :3, :3] @ Rotation.from_rotvec(turn).as_matrix()
    return np.asarray(
        deform.joint_matrices(model.mesh, deform.forward_kinematics_matrices(model.skeleton.parents, local))
    )


def skin_lbs_numpy(V, J, W, joints) -> np.ndarray:
    """LBS (eq. 16) in plain numpy: ``sum_k W_k joints[J_k] [V; 1]`` (no compilation per mesh size)."""
    V, J, W, joints = np.asarray(V, np.float64), np.asarray(J), np.asarray(W, np.float64), np.asarray(joints)
    homogeneous = np.concatenate([V, np.ones((len(V), 1))], axis=1)
    return np.einsum("nk,nkij,nj->ni", W, joints[J], homogeneous)[:, :3]


class CharacterTools:
    """Tools placed on ``model`` (bind pose) as a user places them, each at a random skin point (a point of an
    area-weighted random face; ``rng``): ``cut`` a plane through it across the limb, its normal along the bone the
    point is most weighted to; ``tear`` a blade along the normal there that moves TEAR_TRAVEL x the diagonal along the
    surface in a random direction, in 2 to 5 samples (``scalpels_over``); ``drill`` along the inward normal there, from
    just outside through to where the ray leaves the part it entered (through the limb, and any layer inside it)."""

    def __init__(self, model):
        from tests.shared import connected_parts

        self.model = model
        self.worst_rim = 0.0  # the largest distance of a drill's new point from its cylinder, over the diagonal
        self.V, self.F = np.asarray(model.mesh.V, np.float64), np.asarray(model.mesh.F)
        self.diagonal = diagonal(self.V)
        self.areas = area(self.V, self.F)
        labels = np.full(len(self.V), -1)
        for k, part in enumerate(connected_parts(self.F, len(self.V))):
            labels[part] = k
        self.vertex_part, self.face_part = labels, labels[self.F[:, 0]]
        mesh = model.mesh
        self.heads = np.linalg.inv(np.asarray(mesh.inverse_bind, np.float64))[:, :3, 3]  # joints' bind positions
        self.bones = np.asarray(mesh.joints)
        self.parents = np.asarray(model.skeleton.parents)

    def hits(self, origin, direction):
        """(distances, faces) of every crossing of the ray from ``origin`` along the unit ``direction`` (Moller and
        Trumbore's ray-triangle test on every face at once)."""
        a, b, c = (self.V[self.F[:, k]] for k in range(3))
        e1, e2 = b - a, c - a
        p = np.cross(direction, e2)
        det = np.einsum("ij,ij->i", e1, p)
        ok = np.abs(det) > 1e-300
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        s = origin - a
        u = np.einsum("ij,ij->i", s, p) * inv
        q = np.cross(s, e1)
        v = (q @ direction) * inv
        t = np.einsum("ij,ij->i", e2, q) * inv
        faces = np.flatnonzero(ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0))
        return t[faces], faces

    def crossed_parts(self, start, end) -> np.ndarray:
        """The parts (indices into ``connected_parts``) that the segment from ``start`` to ``end`` crosses."""
        length = np.linalg.norm(end - start)
        t, faces = self.hits(start, (end - start) / length)
        return np.unique(self.face_part[faces[t < length]])

    def skin_point(self, rng):
        """(face, barycentric (3,), point, outward unit normal) of a uniformly random point of the surface."""
        face = int(rng.choice(len(self.F), p=self.areas / self.areas.sum()))
        b = rng.dirichlet(np.ones(3))
        return face, b, b @ self.V[self.F[face]], _frame(self.V, self.F, face)[1]

    def limb_direction(self, face: int, barycentric) -> np.ndarray:
        """Unit direction of the bone the point is most weighted to: from its joint to the mean of its child joints,
        or from the nearest ancestor joint to it when it has none."""
        J, W = np.asarray(self.model.mesh.J), np.asarray(self.model.mesh.W)
        corners = self.F[face]
        weight = np.zeros(len(self.bones))
        np.add.at(weight, J[corners].ravel(), (np.asarray(barycentric)[:, None] * W[corners]).ravel())
        joint = int(np.argmax(weight))
        children = np.flatnonzero(self.parents[self.bones] == self.bones[joint])
        axis = np.zeros(3)
        if len(children):
            axis = self.heads[children].mean(axis=0) - self.heads[joint]
        else:
            bone = self.parents[self.bones[joint]]
            while bone >= 0 and bone not in self.bones:
                bone = self.parents[bone]
            if bone >= 0:
                axis = self.heads[joint] - self.heads[np.flatnonzero(self.bones == bone)[0]]
        if np.linalg.norm(axis) < 1e-9 * self.diagonal:
            axis = np.array([0.0, 1.0, 0.0])  # a joint on top of its neighbours: up
        return axis / np.linalg.norm(axis)

    def cut(self, rng):
        import cutting

        face, b, point, _ = self.skin_point(rng)
        normal = self.limb_direction(face, b)
        return cutting.Plane(normal, float(normal @ point))

    def tear(self, rng):
        face, _, _, _ = self.skin_point(rng)
        samples = int(rng.integers(2, 6))
        step = TEAR_TRAVEL * self.diagonal / (samples - 1)
        return scalpels_over(self.V, self.F, face, rng.normal(size=3), samples, step)

    def drill(self, rng):
        import cutting

        face, _, point, normal = self.skin_point(rng)
        radius = rng.uniform(0.004, 0.012) * self.diagonal
        hits, faces = self.hits(point, -normal)
        mine = (self.face_part[faces] == self.face_part[face]) & (hits > 1e-6 * self.diagonal)
        depth = hits[mine].min() + 2 * radius if mine.any() else 0.05 * self.diagonal  # an open sheet: 5% deep
        return cutting.Drill(point - depth * normal, point + 2 * radius * normal, radius)
