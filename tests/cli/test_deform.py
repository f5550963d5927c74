"""The ``jaxcga deform {spline,handles,ffd,cage}`` commands, end to end in-process, on a closed tube
(a file written here) and on the built-in arm: outputs, the motion they apply, errors."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from jaxcga_cli.main import main
from tests.shared import CHARACTERS, write_multipart_character


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    """A closed tube along z, length 2 and radius 0.2, with rings every 0.1: (path, V, F)."""
    mesh = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=16)
    for _ in range(3):
        mesh = mesh.subdivide()
    path = tmp_path_factory.mktemp("mesh") / "tube.ply"
    mesh.export(path)
    loaded = trimesh.load_mesh(path, process=True)
    return path, np.asarray(loaded.vertices), np.asarray(loaded.faces)


@pytest.mark.slow
@pytest.mark.parametrize("method", ["spline", "handles", "ffd", "cage"])
def test_every_method_turns_the_far_end_by_the_bend_and_keeps_the_near_end(tube, tmp_path, method, capsys):
    path, V, F = tube
    out = tmp_path / f"{method}.npy"
    assert main(["deform", method, str(path), "--bend", "90", "--out", str(out)]) == 0
    assert f"jaxcga deform {method}" in capsys.readouterr().out
    X = np.load(out)
    assert X.dtype == np.float64 and X.shape == V.shape and np.all(np.isfinite(X))
    z = V[:, 2]
    near, far = z < -0.99, z > 0.99
    # the long axis is z, the smallest extent x (ties go to the first axis): a bend about x by 90 degrees
    # about the pivot, the centre of the low end
    pivot = np.array([0.0, 0.0, -1.0])
    turned = Rotation.from_rotvec([np.pi / 2, 0, 0]).apply(V[far] - pivot) + pivot
    if method in ("spline", "handles"):  # the end handles move rigidly
        np.testing.assert_allclose(X[near], V[near], atol=1e-10)
        np.testing.assert_allclose(X[far], turned, atol=1e-10)
    else:  # lattice points and cage vertices only near the ends: close, not exact
        assert np.abs(X[near] - V[near]).max() < 0.05
        assert np.abs(X[far] - turned).max() < 0.25
    assert np.abs(X - V).max() > 1.0


@pytest.mark.slow
def test_figure_mesh_and_positional_outputs(tube, tmp_path):
    path, V, F = tube
    png = tmp_path / "ffd.png"
    assert main(["deform", "ffd", str(path), "--twist", "90", "--positional", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    glb = tmp_path / "cage.glb"
    assert main(["deform", "cage", str(path), "--bend", "45", "--out", str(glb)]) == 0
    assert trimesh.load_mesh(glb, process=False).vertices.shape == V.shape


def test_handles_file_with_a_translated_handle(tube, tmp_path):
    path, V, F = tube
    z = V[:, 2]
    spec = {
        "handles": [np.flatnonzero(z < -0.99).tolist(), np.flatnonzero(z > 0.99).tolist()],
        "motors": [{}, {"translation": [0.3, 0.0, 0.0]}],
    }
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps(spec))
    out = tmp_path / "moved.npy"
    assert (
        main(
            ["deform", "handles", str(path), "--handles", str(handles), "--laplacian", "mean_value", "--out", str(out)]
        )
        == 0
    )
    X = np.load(out)
    np.testing.assert_allclose(X[z > 0.99], V[z > 0.99] + [0.3, 0, 0], atol=1e-12)
    np.testing.assert_allclose(X[z < -0.99], V[z < -0.99], atol=1e-12)
    middle = np.abs(z) < 0.01  # a translation blends linearly along the harmonic field: about half way
    assert 0.1 < np.mean(X[middle, 0] - V[middle, 0]) < 0.2


@pytest.mark.slow
def test_built_in_arm_by_default(tmp_path):
    out = tmp_path / "arm.npy"
    assert main(["deform", "spline", "--basis", "lagrange", "--bend", "30", "--out", str(out)]) == 0
    assert np.load(out).shape[1] == 3


@pytest.mark.parametrize(
    "argv, message",
    [
        (["deform", "spline", "--positional", "--out", "x.npy"], "positional"),
        (["deform", "ffd", "--out", "x.txt"], "out"),
        (["deform", "spline", "missing.ply", "--out", "x.npy"], "no such file"),
        (["deform", "spline", "--basis", "lagrange", "--keys", "4", "--out", "x.npy"], "num_keys"),
    ],
)
def test_errors_name_the_problem(tmp_path, argv, message, capsys):
    argv = [a if a != "x.npy" and a != "x.txt" else str(tmp_path / a) for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


TETRAHEDRON = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n"


def _tetrahedron() -> trimesh.Trimesh:
    return trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]], [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False
    )


def test_a_mesh_file_is_read_as_it_is(tmp_path):
    """No vertex is moved, merged or dropped from a clean file (trimesh's processing used to drop a NaN
    vertex and go on with another mesh)."""
    import warnings

    from _jaxcga_shared.meshfile import read_mesh_file

    mesh = trimesh.Trimesh(
        [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]], [[0, 2, 1], [0, 1, 3], [1, 2, 4]], process=False
    )
    mesh.export(tmp_path / "five.ply")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        V, F = read_mesh_file(tmp_path / "five.ply")
    np.testing.assert_array_equal(V, mesh.vertices)
    np.testing.assert_array_equal(F, mesh.faces)


def test_a_weld_or_dropped_faces_are_reported(tmp_path):
    from _jaxcga_shared.meshfile import read_mesh_file

    _tetrahedron().export(tmp_path / "tet.stl")  # an STL stores every corner apart: 12 vertices
    with pytest.warns(UserWarning, match=r"tet.stl: welded 12 vertices into 4 .* dropped 0 of 4 faces"):
        V, F = read_mesh_file(tmp_path / "tet.stl")
    assert trimesh.Trimesh(V, F, process=False).is_watertight
    (tmp_path / "flat.obj").write_text(TETRAHEDRON + "f 1 1 2\n")
    with pytest.warns(UserWarning, match=r"flat.obj: welded 4 vertices into 4 .* dropped 1 of 5 faces"):
        V, F = read_mesh_file(tmp_path / "flat.obj")
    assert F.shape == (4, 3)


@pytest.mark.parametrize("command", [["deform", "handles"], ["arap"]])
@pytest.mark.parametrize("line", ["v nan 0 1", "v -inf 0 1", "v 0 1", "v 0 x 1"])
def test_a_bad_obj_vertex_names_its_line(tmp_path, capsys, command, line):
    path = tmp_path / "bad.obj"
    path.write_text(TETRAHEDRON.replace("v 0 0 1", line))
    with pytest.raises(SystemExit) as exit_info:
        main([*command, str(path), "--out", str(tmp_path / "x.npy")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1
    assert f"mesh: {path}: line 4: {line!r} is not a vertex of three finite numbers" in err


@pytest.mark.parametrize(
    "face, told",
    [
        ("f 1 3 9", "refers to vertex 9, but the file has 4 vertices"),
        ("f 0 3 2", "refers to vertex 0 (OBJ counts vertices from 1)"),
        ("f -7 3 2", "refers to vertex -7, but the file has 4 vertices before this line"),
    ],
)
def test_a_face_index_outside_the_obj_names_its_line(tmp_path, capsys, face, told):
    path = tmp_path / "bad.obj"
    path.write_text(TETRAHEDRON.replace("f 1 3 2", face))
    with pytest.raises(SystemExit) as exit_info:
        main(["arap", str(path), "--out", str(tmp_path / "x.npy")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1
    assert f"mesh: {path}: line 5: {face!r} {told}" in err


def test_an_open_or_mis_wound_cage_is_refused_before_the_mesh_loads(tmp_path, capsys, monkeypatch):
    import jaxcga_cli.models

    def refuse(path, name="mesh"):
        if name != "cage":
            raise AssertionError("loaded the mesh although the cage is refused")
        return load(path, name)

    load = jaxcga_cli.models.load_mesh
    monkeypatch.setattr(jaxcga_cli.models, "load_mesh", refuse)
    (tmp_path / "open.obj").write_text(TETRAHEDRON.replace("f 2 3 4\n", ""))
    (tmp_path / "flipped.obj").write_text(TETRAHEDRON.replace("f 2 3 4", "f 2 4 3"))
    for name, told in (
        ("open.obj", "is an open surface (3 edges lie on its border, each in one triangle only)"),
        ("flipped.obj", "is closed but its triangles are not consistently oriented"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(["deform", "cage", "--cage", str(tmp_path / name), "--out", str(tmp_path / "x.npy")])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2
        assert f"cage: {tmp_path / name} {told}" in err and err.count("\n") == 1


def test_a_non_finite_vertex_in_other_formats_names_its_index(tmp_path):
    from _jaxcga_shared.meshfile import read_mesh_file

    V = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, np.inf]])
    trimesh.Trimesh(V, [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]], process=False).export(tmp_path / "inf.ply")
    with pytest.raises(ValueError, match=r"inf.ply: a non-finite vertex, the first is vertex 3: \[0.0, 0.0, inf\]"):
        read_mesh_file(tmp_path / "inf.ply")


@pytest.mark.parametrize("command", [["deform", "spline"], ["deform", "handles"], ["arap"]])
def test_overlapping_end_handles_are_named(tmp_path, capsys, command):
    """The end handles' vertex sets overlap from a fraction of 0.5 on: said so, not "repeated handle
    vertices". The weld of the STL is reported on its own line first."""
    _tetrahedron().export(tmp_path / "tet.stl")
    with pytest.raises(SystemExit) as exit_info:
        main([*command, str(tmp_path / "tet.stl"), "--handle-fraction", "0.6", "--out", str(tmp_path / "x.npy")])
    lines = capsys.readouterr().err.splitlines()
    warning, error = lines[0], lines[-1]
    assert len(lines) == 2 and exit_info.value.code == 2
    assert warning.startswith(f"jaxcga {command[0]}: warning: mesh: ") and "welded 12 vertices into 4" in warning
    assert error.startswith(f"jaxcga {command[0]}: error: handle_fraction: 0.6 makes the two end handles overlap")


def test_more_keys_than_vertices_are_refused(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["deform", "spline", "--keys", "100000", "--out", str(tmp_path / "x.npy")])
    assert "keys: expected at most one key motor per vertex (3266), got 100000" in capsys.readouterr().err


@pytest.mark.parametrize(
    "content, message",
    [
        ("", "is not valid JSON"),
        ('{"handles": 5}', "must hold a JSON object with a non-empty 'handles' list"),
        ('{"handles": [["a"]]}', "must be a list of vertex indices"),
        ('{"handles": [[0], [1]], "motors": [{"angle": 5}, {}]}', "motor 0 in .* must be an object with keys among"),
        ('{"handles": [[0], [1]], "motors": [{"axis": [1, 0]}, {}]}', r"motor 0 in .* needs \[x, y, z\] lists"),
        (
            '{"handles": [[0], [1]], "motors": [{"axis": [0, 0, 0]}, {}]}',
            "motor 0 .* needs finite numbers and a non-zero",
        ),
        ('{"handles": [[0], [1]], "motors": [{"center": [NaN, 0, 0]}, {}]}', "motor 0 in .* needs finite numbers"),
        ('{"handles": [[[0, 1]], [[2]]]}', "handle 0 in .* is a list of lists"),
        ('{"handles": [[0], [1]], "motors": [{}, {"translation": [1e308, 1e308, 0]}]}', "motor 1 .* beyond float64"),
        ('{"handles": [[0], [1]], "motors": [{}, {"translation": [0, 1e7, 0]}]}', r"motor 1 .* 1.1\d+e\+07 mesh diag"),
    ],
)
def test_bad_handle_files_are_named(tmp_path, capsys, content, message):
    (tmp_path / "h.json").write_text(content)
    with pytest.raises(SystemExit) as exit_info:
        main(["deform", "handles", "--handles", str(tmp_path / "h.json"), "--out", str(tmp_path / "x.npy")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and err.count("\n") == 1
    assert re.search(f"jaxcga deform: error: handles: .*{message}", err), err


@pytest.mark.parametrize("method", ["handles", "spline"])
def test_a_character_of_many_parts_moves_as_one(tmp_path, capsys, method):
    """On the multi-part CesiumMan of tests.shared: the default end handles bend it with every part finite and
    the parts counted; for handles, one rigid motion on both handle groups moves every part, the five without a
    handle included, by it (scipy); --unhandled error refuses the mesh, naming the parts."""
    path = tmp_path / "character.ply"
    V, _, parts = write_multipart_character(path)
    out = tmp_path / "bent.npy"
    assert main(["deform", method, str(path), "--bend", "45", "--out", str(out)]) == 0
    assert np.all(np.isfinite(np.load(out)))
    assert re.search(r"parts 6, following_parts \d", capsys.readouterr().out)
    if method == "handles":
        axis, angle, center, shift = np.array([0.3, 1.0, -0.4]), 50.0, np.array([0.1, 1.0, 0.0]), [0.2, -0.1, 0.3]
        spec = {"center": center.tolist(), "axis": axis.tolist(), "angle_deg": angle, "translation": shift}
        handles = tmp_path / "handles.json"
        handles.write_text(
            json.dumps({"handles": [parts["feet"].tolist(), parts["crown"].tolist()], "motors": [spec] * 2})
        )
        assert main(["deform", "handles", str(path), "--handles", str(handles), "--out", str(out)]) == 0
        assert "parts 6, following_parts 5" in capsys.readouterr().out
        turned = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).apply(V - center)
        np.testing.assert_allclose(np.load(out), turned + center + shift, atol=1e-9)
    with pytest.raises(SystemExit) as exit_info:
        main(["deform", method, str(path), "--unhandled", "error", "--out", str(out)])
    assert exit_info.value.code == 2
    assert "of the mesh's 6 connected part(s) hold no constrained vertex (part" in capsys.readouterr().err


def test_a_corpus_character_of_many_parts(tmp_path, capsys):
    """jaxcga deform handles on a real character of 15 connected parts (tests/data/characters): every position
    finite, the parts and the followers counted."""
    out = tmp_path / "worker.npy"
    path = CHARACTERS["QuaterniusWorker"]
    assert main(["deform", "handles", str(path), "--bend", "45", "--out", str(out)]) == 0
    assert np.all(np.isfinite(np.load(out)))
    assert re.search(r"parts 15, following_parts [1-9]", capsys.readouterr().out)
