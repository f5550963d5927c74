"""What ``deform.view`` reads and writes, without a browser: the page is one self-contained file, every bad input
is a ``ValueError`` naming the argument and the file, ``save`` refuses to overwrite, and the notebook form is an
iframe of the same page."""

from __future__ import annotations

import html
import json
import re
from pathlib import Path

import jax.numpy as jnp
import meshio
import numpy as np
import pytest

import deform
from tests.shared import grid

DATA = Path(__file__).resolve().parents[1] / "data"


def _config(page: deform.View) -> dict:
    text = re.search(r'<script type="application/json" id="jaxcga-config">(.*?)</script>', page.html, re.S)
    assert text is not None
    return json.loads(text.group(1))


def test_the_page_is_self_contained():
    title = "a </script> <!-- <script> title"
    page = deform.view(DATA / "RiggedSimple.glb", title=title)
    # nothing fetched at view time: no element that loads a file (src, href, a stylesheet link)
    assert not re.search(r"""<[a-z]+[^>]*\s(src|href)\s*=""", page.html)
    assert page.html.count("</script>") == page.html.count("<script")  # the title did not end a script early
    assert _config(page)["title"] == title and page.title == title
    assert page.meshes == ({"name": "RiggedSimple.glb", "kind": "skinned", "vertexCount": 160, "triangleCount": 188,
                            "source": str(DATA / "RiggedSimple.glb")},)  # fmt: skip


def test_the_vendored_three_js_and_its_licence_ship_with_the_package():
    from importlib.resources import files

    vendor = files("_jaxcga_shared.viewer") / "vendor"
    assert "MIT License" in (vendor / "LICENSE").read_text()
    assert "three.js authors" in (vendor / "LICENSE").read_text()
    assert (vendor / "three.bundle.min.js").read_text().startswith("var THREE=")


def test_frames_are_int16_in_one_box_and_decode_within_the_bound():
    """The stored frames, decoded as the page decodes them (center + q * half / quantum), are within
    diag / 131068 of the frames given."""
    V, F = grid(4)
    frames = np.stack([V + [0.0, 0.0, 0.3 * k] for k in range(3)])
    page = deform.view((jnp.asarray(frames), F))
    config = _config(page)
    (item,) = config["items"]
    (segment,) = item["segments"]
    block = re.search(rf'id="jaxcga-block-{segment["positions"]}">([^<]*)<', page.html)
    assert block is not None
    import base64

    q = np.frombuffer(base64.b64decode(block.group(1)), "<i2").reshape(frames.shape)
    decoded = np.asarray(item["center"]) + q * np.asarray(item["half"]) / item["quantum"]
    diag = np.linalg.norm(frames.reshape(-1, 3).max(0) - frames.reshape(-1, 3).min(0))
    assert np.abs(decoded - frames).max() <= diag / 131068
    assert page.meshes[0]["kind"] == "sequence" and page.meshes[0]["vertexCount"] == len(V)


def test_save_is_atomic_and_refuses_to_overwrite(tmp_path):
    page = deform.view(grid(2))
    path = page.save(tmp_path / "view.html")
    assert path.read_text() == page.html
    path.write_text("previous")
    with pytest.raises(ValueError, match="exists; pass force=True"):
        page.save(path)
    assert path.read_text() == "previous"
    page.save(path, force=True)
    assert path.read_text() == page.html
    with pytest.raises(ValueError, match=r"path: expected a \.html or \.htm file"):
        page.save(tmp_path / "view.png")


def test_the_notebook_form_is_an_iframe_of_the_same_page():
    page = deform.view(grid(2))
    frame = page._repr_html_()
    source = re.fullmatch(r'<iframe srcdoc="([^"]*)" .*sandbox="allow-scripts"></iframe>', frame, re.S)
    assert source is not None and html.unescape(source.group(1)) == page.html
    # a notebook also stores the text form: it names the contents, not the megabytes of the page
    assert repr(page).startswith("View(title=") and len(repr(page)) < 500


def test_a_rigged_model_and_arrays_are_inputs():
    import deform

    model = deform.default_arm()
    page = deform.view(model, grid(3), clip="wave")
    assert [m["kind"] for m in page.meshes] == ["skinned", "static"]
    assert page.meshes[0]["vertexCount"] == model.mesh.num_vertices and page.clips[0]["name"] == "wave"
    assert deform.load_model(_glb(model)).mesh.num_vertices == model.mesh.num_vertices


def test_groups_give_each_vertex_its_first_triangles_group_and_keep_pieces_apart():
    """(V, F, groups) triples: a vertex takes the group of the first triangle that uses it; vertices that coincide
    in every frame are merged only within a group, so a piece's colour never bleeds into another's."""
    from _jaxcga_shared.viewer._inputs import read_arrays

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [1, 0, 0], [0, 1, 0]], float)
    F = np.array([[0, 1, 2], [3, 5, 4]])  # the second triangle's corners 4, 5 coincide with 1, 2
    shared = np.array([[0, 1, 2], [1, 3, 2]])
    sequence = read_arrays([(V, F, np.array([0, 1])), (V + 1.0, F, np.array([0, 1]))], "cut", "inputs[0]")
    assert [len(frames[0]) for _, frames in sequence.segments] == [6] and sequence.groups[0].tolist() == [
        0,
        0,
        0,
        1,
        1,
        1,
    ]
    one = read_arrays([(V, F, np.array([2, 2])), (V + 1.0, F, np.array([2, 2]))], "whole", "inputs[0]")
    assert len(one.segments[0][1][0]) == 4 and one.groups[0].tolist() == [2, 2, 2, 2]  # one group: merged
    first = read_arrays([(V[:4], shared, np.array([3, 1]))], "first", "inputs[0]")
    assert first.groups[0].tolist() == [3, 3, 3, 1]  # vertices 1 and 2: the first triangle's group
    changed = read_arrays([(V, F, np.array([0, 0])), (V, F, np.array([0, 1]))], "split", "inputs[0]")
    assert len(changed.segments) == 2 and len(changed.groups) == 2  # new groups: a new segment
    assert read_arrays([(V, F), (V + 1.0, F)], "plain", "inputs[0]").groups == []
    with pytest.raises(ValueError, match=r"inputs\[0\]\[1\]\[2\]: expected one integer group >= 0 per triangle"):
        read_arrays([(V, F, np.array([0, 1])), (V, F, np.array([0, -1]))], "bad", "inputs[0]")
    with pytest.raises(ValueError, match=r"inputs\[0\]\[1\]: expected a \(V, F, groups\) triple"):
        read_arrays([(V, F, np.array([0, 1])), (V, F)], "mixed", "inputs[0]")
    page = deform.view([(V, F, np.array([0, 1]))])
    assert page.meshes[0]["vertexCount"] == 6


def _glb(model) -> Path:
    import tempfile

    path = Path(tempfile.mkdtemp()) / "arm.glb"
    path.write_bytes(model.to_glb())
    return path


def _truncated(tmp_path) -> Path:
    path = tmp_path / "truncated.glb"
    path.write_bytes((DATA / "CesiumMan.glb").read_bytes()[:5000])
    return path


def _bad_inputs(tmp_path):
    V, F = grid(3)
    (tmp_path / "mesh.txt").write_text("not a mesh")
    (tmp_path / "junk.glb").write_bytes(b"glTF junk that is no glTF binary")
    (tmp_path / "text.gltf").write_text("{ not json")
    np.save(tmp_path / "flat.npy", np.zeros((4, 2)))
    np.save(tmp_path / "frames.npy", np.stack([V, V]))
    nan = np.stack([V, V])
    nan[1, 5, 2] = np.nan
    np.save(tmp_path / "nan.npy", nan)
    np.save(tmp_path / "other.npy", np.zeros((7, 3)))
    meshio.write(tmp_path / "points.vtu", meshio.Mesh(V, [("vertex", np.arange(len(V))[:, None])]))
    (tmp_path / "empty").mkdir()
    fan = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [1, 1, 1]], float)
    meshio.write(tmp_path / "fan.vtu", meshio.Mesh(fan, [("tetra", [[0, 1, 2, 3], [0, 1, 2, 4], [0, 1, 2, 5]])]))
    lines = tmp_path / "lines.gltf"
    lines.write_text(json.dumps({"asset": {"version": "2.0"}, "meshes": [{"primitives": [{"attributes": {}}]}]}))
    draco = tmp_path / "draco.gltf"
    draco.write_text(json.dumps({"asset": {"version": "2.0"}, "extensionsRequired": ["KHR_draco_mesh_compression"]}))
    return [
        ((_truncated(tmp_path),), {}, "truncated.glb: truncated: 5000 of the"),
        ((draco,), {}, "draco.gltf: needs KHR_draco_mesh_compression, which the viewer does not decode"),
        ((tmp_path / "junk.glb",), {}, "junk.glb: a glTF binary of version"),
        ((tmp_path / "text.gltf",), {}, "text.gltf: not a readable glTF"),
        ((lines,), {}, "lines.gltf: holds no triangle mesh"),
        ((tmp_path / "mesh.txt",), {}, r"inputs\[0\]: .*mesh.txt: cannot show a .txt file"),
        ((tmp_path / "missing.glb",), {}, r"inputs\[0\]: no such file or folder .*missing.glb"),
        ((tmp_path / "flat.npy",), {"mesh": (V, F)}, r"flat.npy: expected positions of shape \(n, 3\), got \(4, 2\)"),
        ((tmp_path / "frames.npy",), {}, "frames.npy.*give the mesh they belong to"),
        ((tmp_path / "nan.npy",), {"mesh": (V, F)}, r"nan.npy: non-finite position at index \(1, 5\)"),
        ((tmp_path / "other.npy",), {"mesh": (V, F)}, r"mesh: 16 vertices, but the frames .*other.npy have 7"),
        ((tmp_path / "frames.npy",), {"mesh": DATA / "RiggedSimple.glb"}, "RiggedSimple.glb has 160 vertices"),
        ((tmp_path / "points.vtu",), {}, "points.vtu holds no triangles or tetrahedra"),
        ((tmp_path / "empty",), {}, "holds no frame_XXXX.vtu"),
        ((tmp_path / "fan.vtu",), {}, r"fan.vtu: T: face .* is shared by 3 tetrahedra"),
        (((V, F[:, :2]),), {}, r"inputs\[0\]\[1\]: expected integer triangles of shape \(m, 3\)"),
        (((V, F + 100),), {}, r"inputs\[0\]\[1\]: a triangle index outside \[0, 16\)"),
        (((V[:, :2], F),), {}, r"inputs\[0\]\[0\]: expected positions of shape \(n, 3\)"),
        ((object(),), {}, r"inputs\[0\]: cannot show a object"),
        (([(V, F), V],), {}, r"inputs\[0\]\[1\]: expected a \(V, F\) pair, like the frames before it"),
        (([(V, F), (V, F + 100)],), {}, r"inputs\[0\]\[1\]\[1\]: a triangle index outside \[0, 16\)"),
        ((DATA / "RiggedSimple.glb",), {"joint": "nobody"}, "joint: no joint called 'nobody'"),
        ((DATA / "RiggedSimple.glb",), {"joint": 7}, "joint: index 7 outside"),
        (((V, F),), {"joint": 0}, "joint: no input has a skin"),
        ((DATA / "RiggedSimple.glb",), {"clip": "run"}, "clip: no clip called 'run'"),
        ((DATA / "RiggedSimple.glb",), {"fps": 0.0}, "fps: expected a positive frame rate"),
        ((), {}, "inputs: nothing to show"),
    ]


def test_bad_inputs_name_the_argument_and_the_file(tmp_path):
    for inputs, options, message in _bad_inputs(tmp_path):
        with pytest.raises(ValueError, match=message):
            deform.view(*inputs, **options)
