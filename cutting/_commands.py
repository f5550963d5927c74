"""The ``jaxcga cut``, ``tear`` and ``drill`` commands (called by ``jaxcga.cli``): operate on a rigged
model in its bind pose and write skinned glTF files with the input's skeleton and clips, so that the
results animate again."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cutting._cut import cut
from cutting._drill import drill
from cutting._tear import tear
from cutting._tools import Drill, Plane, Scalpel
from deform._gltf import GLTF_OUTPUTS, buffer_file, model_files, save_model
from deform._model import RiggedModel
from jaxcga._output import check_distinct, check_output, write_files


def cut_command(model: RiggedModel, plane, out_positive: Path, out_negative: Path, cap: bool = False,
                predicates: str = "euclidean", side_weight: float = 0.0) -> dict:
    """Cut ``model`` by ``plane`` (nx, ny, nz, d) in its bind pose; write the positive half to
    ``out_positive`` and the negative half to ``out_negative`` (.glb or .gltf, two different files), both
    before either replaces an existing file."""
    check_distinct({"out (positive half)": _check_out(out_positive), "out (negative half)": _check_out(out_negative)})
    plane = np.asarray(plane, np.float64)
    positive, negative = cut(model.mesh, Plane(plane[:3], plane[3]), cap=cap, predicates=predicates,
                             side_weight=side_weight)
    files = {}
    for half, out, side in ((positive, out_positive, "positive"), (negative, out_negative, "negative")):
        files.update(model_files(RiggedModel(half, model.skeleton, model.clips, f"{model.name}-{side}"), out))
    write_files(files)
    return {"positive_faces": int(positive.F.shape[0]), "negative_faces": int(negative.F.shape[0]),
            "new_vertices": positive.num_vertices + negative.num_vertices - model.mesh.num_vertices,
            "out": f"{out_positive} {out_negative}"}


def tear_command(model: RiggedModel, scalpels, out: Path, opening: float = 0.0, predicates: str = "euclidean",
                 side_weight: float = 0.0) -> dict:
    """Tear ``model`` in its bind pose with a scalpel at the samples ``scalpels`` ((k+1, 2, 3)); write
    the torn model to ``out`` (.glb or .gltf)."""
    _check_out(out)
    scalpels = np.asarray(scalpels, np.float64)
    torn, topology = tear(model.mesh, Scalpel(scalpels[:, 0], scalpels[:, 1]), opening=opening, predicates=predicates,
                          side_weight=side_weight, return_topology=True)
    save_model(RiggedModel(torn, model.skeleton, model.clips, f"{model.name}-torn"), out)
    return {"tear_points": len(topology.t), "faces": int(torn.F.shape[0]),
            "new_vertices": torn.num_vertices - model.mesh.num_vertices, "out": str(out)}


def drill_command(model: RiggedModel, tip, base, radius: float, out: Path, min_points: int = 6,
                  max_refinements: int = 4) -> dict:
    """Drill ``model`` in its bind pose from ``base`` to ``tip`` with ``radius``; write the drilled
    model to ``out`` (.glb or .gltf)."""
    _check_out(out)
    drilled, topology = drill(model.mesh, Drill(tip, base, radius), min_points=min_points,
                              max_refinements=max_refinements, return_topology=True)
    save_model(RiggedModel(drilled, model.skeleton, model.clips, f"{model.name}-drilled"), out)
    return {"holes": topology.holes, "hole_points": len(topology.points), "refinements": topology.refinements,
            "faces": int(drilled.F.shape[0]), "out": str(out)}


def _check_out(out) -> Path:
    out = check_output(out, GLTF_OUTPUTS)
    buffer_file(out, "out")
    return out
