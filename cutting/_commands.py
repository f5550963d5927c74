"""The ``jaxcga cut`` command (called by ``jaxcga.cli``): cut a rigged model by a plane and write both
halves as skinned glTF files with the input's skeleton and clips, so that they animate again."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from cutting._cut import cut
from deform._gltf import save_model
from deform._model import RiggedModel


def cut_command(model: RiggedModel, plane, out_positive: Path, out_negative: Path, cap: bool = False,
                predicates: str = "euclidean", side_weight: float = 0.0) -> dict:
    """Cut ``model`` by ``plane`` (nx, ny, nz, d) in its bind pose; write the positive half to
    ``out_positive`` and the negative half to ``out_negative`` (.glb or .gltf)."""
    for out in (out_positive, out_negative):
        if Path(out).suffix not in (".glb", ".gltf"):
            raise ValueError(f"out: expected .glb or .gltf paths, got {out}")
    positive, negative = cut(model.mesh, np.asarray(plane, np.float64), cap=cap, predicates=predicates,
                             side_weight=side_weight)
    for half, out, side in ((positive, out_positive, "positive"), (negative, out_negative, "negative")):
        Path(out).parent.mkdir(parents=True, exist_ok=True)
        save_model(RiggedModel(half, model.skeleton, model.clips, f"{model.name}-{side}"), out)
    return {"positive_faces": int(positive.F.shape[0]), "negative_faces": int(negative.F.shape[0]),
            "new_vertices": positive.num_vertices + negative.num_vertices - model.mesh.num_vertices,
            "out": f"{out_positive} {out_negative}"}
