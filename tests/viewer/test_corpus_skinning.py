"""The corpus of real characters (``CHARACTERS``) skinned by deform against three.js (headless Chromium, ``browser``
in conftest.py): three.js's loader and mixer are an implementation of glTF independent of deform's, so the skinned
vertices it draws at a few times of the first clip (the rest pose without a clip) are the specification's. Both LBS and
eq. (17) must match them to ``TOLERANCE`` of the bounding-box diagonal; the error is printed per model (``-s``)."""

from __future__ import annotations

import jax
import numpy as np
import pytest

import deform
from _jaxcga_shared.mesh import bounding_diagonal
from tests.shared import CHARACTERS, character_params, gltf_json, load_character, moving_mesh_nodes

TOLERANCE = 5e-6  # of the posed diagonal: three.js skins in float32; eq. (17) takes nearest similitudes (1.8e-6)


def skinned_order(document: dict) -> np.ndarray:
    """Indices into three.js's drawn vertices (``vertexPositions``) of the model's vertices in deform's order.

    three.js draws one mesh per primitive of every mesh node found by a depth-first walk of the scene, sorted by (mesh,
    primitive, walk order) (page.js), skinned or not, each at its matrixWorld; deform takes the primitives of the
    skinned and rigidly attached mesh nodes in node order."""
    nodes, meshes, accessors = document["nodes"], document["meshes"], document["accessors"]
    drawn = []  # (mesh, primitive, walk order, node, vertex count)

    def walk(i):
        node = nodes[i]
        if "mesh" in node:
            for p, primitive in enumerate(meshes[node["mesh"]]["primitives"]):
                drawn.append((node["mesh"], p, len(drawn), i, accessors[primitive["attributes"]["POSITION"]]["count"]))
        for child in node.get("children", []):
            walk(child)

    for root in document["scenes"][document.get("scene", 0)]["nodes"]:
        walk(root)
    drawn.sort(key=lambda d: d[:3])
    starts = np.cumsum([0] + [d[4] for d in drawn])
    slices = {(d[3], d[1]): np.arange(starts[k], starts[k + 1]) for k, d in enumerate(drawn)}
    moving = set(moving_mesh_nodes(document))
    return np.concatenate([slices[key] for key in sorted(slices) if key[0] in moving])


@pytest.mark.parametrize("name", character_params())
def test_every_character_skins_as_three_js_does(browser, tmp_path, name):
    path = CHARACTERS[name]
    model = load_character(name, weld=False)
    state = browser.open(deform.view(path).save(tmp_path / "view.html"))
    assert state["errors"] == [] and state["ready"], state["errors"]
    order = skinned_order(gltf_json(path))
    assert len(order) == model.mesh.num_vertices
    duration = float(model.clip(0).end) if model.clips else 0.0
    times = (0.0, 0.31 * duration, 0.77 * duration) if duration else (0.0,)
    errors = {}
    for method in ("lbs", "cga"):
        skin = jax.jit(lambda t, method=method: deform.skin_model(model, t, method))
        worst = 0.0
        for t in times:
            shown = browser.positions(0, t)[order]
            ours = np.asarray(skin(t)) if duration else np.asarray(deform.rest_pose(model, method))
            # the posed diagonal: mesh space can be in other units (the Quaternius files' meshes are 100x smaller)
            worst = max(worst, float(np.abs(shown - ours).max()) / bounding_diagonal(shown))
        errors[method] = worst
    print(f"{name}: deform vs three.js, max |error| / diagonal: lbs {errors['lbs']:.2g}, cga {errors['cga']:.2g}")
    assert max(errors.values()) <= TOLERANCE, errors
