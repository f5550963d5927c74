"""Cut, tear and drill on the corpus of real characters (``CHARACTERS``), each tool placed as a user places it at a
random skin point (seeded; ``tools.CharacterTools``): a plane across the limb, a blade that moves 5% of the diagonal
along the skin, a drill through the limb along the inward normal. Every one must succeed and give a mesh that
re-animates exactly (the input's vertices it keeps skin where they did, in a pose of the character's clip), makes no
sliver (``tools.piece_quality``), and keeps its weights valid (``tools.consistency_problems``). A drill's rims (the
boundary it made, vertices and chords) lie on its cylinder to 1e-3 of the diagonal, and no input vertex of a part its
axis crosses stays inside it (deeper than that: a rim may pass through an input vertex). The tools run round the
characters, 100 of each kind; the failures are listed with their messages."""

from __future__ import annotations

import numpy as np
import pytest

import cutting
from tests.cutting.tools import (
    CharacterTools,
    character_pose,
    consistency_problems,
    edge_counts,
    piece_quality,
    skin_lbs_numpy,
)
from tests.shared import CHARACTERS, load_character

COUNT = 100
RIM = 1e-3  # a drill's rim lies on its cylinder to this fraction of the diagonal (issue 51, item 2)
REANIMATE = 1e-12  # of the diagonal: the kept input vertices skin where they did


def _apply(tool: str, mesh, placed, edges):
    """[(output mesh, ids)] of one tool: ids gives each output vertex's input index (>= n for a new vertex)."""
    if tool == "cut":
        halves, topology = cutting.cut(mesh, placed, edges=edges, return_topology=True)
        return list(zip(halves, (topology.positive, topology.negative)))
    if tool == "tear":
        torn = cutting.tear(mesh, placed, edges=edges)
        return [(torn, np.arange(len(torn.V)))]
    drilled, topology = cutting.drill(mesh, placed, edges=edges, return_topology=True)
    return [(drilled, topology.kept)]


def _drill_problems(placer, drilled, ids, drill) -> list[str]:
    """A drill's rims off its cylinder (the boundary edges it made, at their ends and midpoints: new points, and input
    vertices a rim passes through), and kept input vertices inside it, between its base and its tip, of the parts that
    its axis crosses there (each is drilled through; ``placer``: the ``CharacterTools``)."""
    scale = placer.diagonal
    problems = []
    base, tip, radius = (np.asarray(x, np.float64) for x in (drill.base, drill.tip, drill.radius))
    axis = (tip - base) / np.linalg.norm(tip - base)

    def from_axis(X):
        relative = X - base
        return np.linalg.norm(relative - np.outer(relative @ axis, axis), axis=1), relative @ axis

    ids = np.asarray(ids)
    out_V = np.asarray(drilled.V, np.float64)
    edges, counts = edge_counts(drilled.F)
    before_edges, before_counts = edge_counts(placer.F)
    before_boundary = before_edges[before_counts == 1]
    # a boundary edge of the output is one of the input's, a piece of one that a refinement split, or a rim: the
    # input's by their vertices, the pieces by their midpoints' distance from the input's boundary segments
    labels = np.where(ids < len(placer.V), ids, -1)[edges[counts == 1]]
    known = {tuple(e) for e in before_boundary}
    old = (labels.min(axis=1) >= 0) & np.array([tuple(sorted(e)) in known for e in labels], bool)
    boundary = edges[counts == 1][~old]
    a, b = (placer.V[before_boundary[:, k]] for k in range(2))
    m = 0.5 * (out_V[boundary[:, 0]] + out_V[boundary[:, 1]])
    if len(a):
        s = np.clip(np.einsum("mbk,bk->mb", m[:, None] - a[None], b - a) / np.einsum("bk,bk->b", b - a, b - a), 0, 1)
        gap = np.linalg.norm(m[:, None] - (a[None] + s[..., None] * (b - a)[None]), axis=2).min(axis=1)
    else:
        gap = np.full(len(m), np.inf)
    rims = boundary[gap > 1e-9 * scale]
    # the rim polyline: its vertices and the midpoints of its chords
    off, _ = from_axis(np.concatenate([out_V[rims.ravel()], 0.5 * (out_V[rims[:, 0]] + out_V[rims[:, 1]])]))
    rim = float(np.abs(off - radius).max(initial=0.0)) / scale
    placer.worst_rim = max(placer.worst_rim, rim)
    if rim > RIM:
        problems.append(f"a rim {rim:.3g} x diagonal off the cylinder")
    kept = ids < len(placer.V)
    distance, along = from_axis(out_V[kept])
    crossed = np.isin(placer.vertex_part[ids[kept]], placer.crossed_parts(base, tip))
    inside = crossed & (distance < radius - RIM * scale) & (along > 0) & (along < np.linalg.norm(tip - base))
    if inside.any():
        deepest = 1 - distance[inside].min() / radius
        problems.append(f"{int(inside.sum())} vertices left inside the drill, up to {deepest:.2g} of the radius deep")
    return problems


@pytest.mark.slow
@pytest.mark.parametrize("tool", ["cut", "tear", "drill"])
def test_tools_placed_on_real_characters(tool):
    names = list(CHARACTERS)
    rng = np.random.default_rng(51)
    placers = {name: CharacterTools(load_character(name)) for name in names}
    poses = {name: character_pose(load_character(name), seed=51) for name in names}
    edges = {name: cutting.mesh_edges(load_character(name).mesh.F) for name in names}
    failures, runs = [], 0
    for trial in range(COUNT):
        name = names[trial % len(names)]
        mesh, placer, pose = load_character(name).mesh, placers[name], poses[name]
        placed = getattr(placer, tool)(rng)
        try:
            outputs = _apply(tool, mesh, placed, edges[name])
        except ValueError as error:
            failures.append(f"{name} {tool} {trial}: refused: {error}")
            continue
        runs += 1
        V = placer.V
        before = skin_lbs_numpy(V, mesh.J, mesh.W, pose)
        problems = []
        for out, ids in outputs:
            ids = np.asarray(ids)
            found, _, _ = piece_quality(V, placer.F, out.V, out.F, ids)
            problems += found + consistency_problems(out, mesh, ids)
            kept = ids < len(V)
            after = skin_lbs_numpy(out.V, out.J, out.W, pose)
            moved = np.abs(after[kept] - before[ids[kept]]).max(initial=0.0) / placer.diagonal
            if moved > REANIMATE:
                problems.append(f"kept input vertices skin {moved:.3g} x diagonal from where they did")
            if not np.isfinite(after).all():
                problems.append("non-finite skinned positions")
            if tool == "drill":
                problems += _drill_problems(placer, out, ids, placed)
        if problems:
            failures.append(f"{name} {tool} {trial}: " + "; ".join(problems))
    print(f"{tool}: {COUNT - len(failures)} of {COUNT} pass ({runs} ran)")
    for name in names:
        tried = len(range(names.index(name), COUNT, len(names)))
        failed = sum(f.startswith(f"{name} ") for f in failures)
        rim = f", largest rim distance {placers[name].worst_rim:.2g} x diagonal" if tool == "drill" else ""
        print(f"  {name}: {tried - failed} of {tried}{rim}")
    for failure in failures:
        print("  " + failure)
    assert failures == [], f"{len(failures)} of {COUNT} {tool}s failed:\n" + "\n".join(failures[:20])
