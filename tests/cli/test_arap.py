"""The ``jaxcga arap`` command end to end in-process: handles from JSON, the default end handles, outputs,
errors."""

from __future__ import annotations

import json
import re
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

import deform
from deform import arap_precompute, arap_solve
from jaxcga_cli.main import main
from tests.shared import CHARACTERS, write_multipart_character

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    """A closed tube along z (length 2, radius 0.2) written as .ply: (path, V, F)."""
    mesh = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=12).subdivide().subdivide()
    path = tmp_path_factory.mktemp("mesh") / "tube.ply"
    mesh.export(path)
    loaded = trimesh.load_mesh(path, process=True)
    return path, np.asarray(loaded.vertices), np.asarray(loaded.faces, np.int64)


@pytest.mark.slow
@pytest.mark.parametrize("energy", [None, "spokes"])
def test_handles_file_gives_arap_solves_result(tube, tmp_path, capsys, energy):
    """The default energy is spokes and rims; --energy spokes gives the paper's."""
    path, V, F = tube
    low, high = np.flatnonzero(V[:, 2] < -0.95), np.flatnonzero(V[:, 2] > 0.95)
    indices = np.concatenate([low, high])
    moved = Rotation.from_rotvec([0.8, 0.0, 0.3]).apply(V[high] - [0, 0, -1.0]) + [0.1, 0.2, -1.0]
    positions = np.concatenate([V[low], moved])
    handles = tmp_path / "handles.json"
    handles.write_text(
        json.dumps({"handles": [low.tolist(), high.tolist()], "positions": [V[low].tolist(), moved.tolist()]})
    )
    out = tmp_path / "arap.npy"
    option = [] if energy is None else ["--energy", energy]
    assert main(["arap", str(path), "--handles", str(handles), "--iters", "7", "--out", str(out), *option]) == 0
    assert f"energy_type {energy or 'spokes_and_rims'}" in capsys.readouterr().out
    X = np.load(out)
    assert X.dtype == np.float64 and X.shape == V.shape
    np.testing.assert_allclose(X[indices], positions, atol=1e-12)
    data = arap_precompute(V, F, indices, energy=energy or "spokes_and_rims")
    expected = arap_solve(data, jnp.asarray(positions), max_iterations=7).U
    np.testing.assert_allclose(X, expected, atol=1e-10)


@pytest.mark.slow
def test_the_handles_file_of_deform_moves_arap_handles_by_their_motors(tube, tmp_path):
    """One --handles format for deform and arap: each group of vertices moved by its motor (a rotation about an
    axis through a centre, then a translation), here against scipy's rotation of the same vertices."""
    path, V, _ = tube
    low, high = np.flatnonzero(V[:, 2] < -0.95), np.flatnonzero(V[:, 2] > 0.95)
    axis, angle, center, shift = np.array([0.8, 0.0, 0.3]), 40.0, np.array([0.0, 0.0, -1.0]), [0.1, 0.2, 0.0]
    moved = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).apply(V[high] - center) + center
    handles = tmp_path / "handles.json"
    handles.write_text(
        json.dumps(
            {
                "handles": [low.tolist(), high.tolist()],
                "motors": [
                    {},
                    {"center": center.tolist(), "axis": axis.tolist(), "angle_deg": angle, "translation": shift},
                ],
            }
        )
    )
    out = tmp_path / "arap.npy"
    assert main(["arap", str(path), "--handles", str(handles), "--iters", "2", "--out", str(out)]) == 0
    X = np.load(out)
    np.testing.assert_allclose(X[low], V[low], atol=1e-12)
    np.testing.assert_allclose(X[high], moved + shift, atol=1e-12)
    assert main(["deform", "handles", str(path), "--handles", str(handles), "--out", str(tmp_path / "d.npy")]) == 0
    np.testing.assert_allclose(np.load(tmp_path / "d.npy")[high], moved + shift, atol=1e-9)


@pytest.mark.slow
def test_default_handles_mesh_and_figure_outputs(tube, tmp_path):
    path, V, F = tube
    glb = tmp_path / "arap.glb"
    assert main(["arap", str(path), "--bend", "90", "--iters", "5", "--out", str(glb)]) == 0
    X = trimesh.load_mesh(glb, process=False).vertices
    assert X.shape == V.shape
    far = V[:, 2] > 0.95  # the far end is turned by 90 degrees about x about the centre of the low end
    np.testing.assert_allclose(
        X[far], Rotation.from_rotvec([np.pi / 2, 0, 0]).apply(V[far] - [0, 0, -1]) + [0, 0, -1], atol=1e-5
    )  # float32 in the glb
    png = tmp_path / "arap.png"
    assert main(["arap", "--iters", "2", "--out", str(png)]) == 0  # the built-in arm
    assert png.stat().st_size > 10_000


@pytest.mark.parametrize(
    "content, message",
    [
        ("{", "not valid JSON"),
        ('{"indices": [0, 1], "positions": [[0, 0, 0], [1, 1, 1]]}', "must hold"),
        ('{"handles": [[0, 100000]], "positions": [[[0, 0, 0], [1, 1, 1]]]}', "indices in [0, "),
        ('{"handles": [[0, 1]], "positions": [[[0, 0, 0]]]}', "one per vertex of handle 0"),
        ('{"handles": [[0.5]], "positions": [[[0, 0, 0]]]}', "list of vertex indices"),
        ('{"handles": [[0], [0]], "positions": [[[0, 0, 0]], [[0, 0, 0]]]}', "vertex 0 is in the handles 2 times"),
        ('{"handles": [[0]], "motors": [{}], "positions": [[[0, 0, 0]]]}', "give one"),
    ],
)
def test_bad_handles_exit_with_a_message(tube, tmp_path, capsys, content, message):
    path, _, _ = tube
    handles = tmp_path / "bad.json"
    handles.write_text(content)
    with pytest.raises(SystemExit) as exit_info:
        main(["arap", str(path), "--handles", str(handles), "--out", str(tmp_path / "x.npy")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_bad_output_and_iterations(tube, tmp_path, capsys):
    path, _, _ = tube
    for args, message in (
        (["--out", str(tmp_path / "x.txt")], "out: expected"),
        (["--iters", "0", "--out", str(tmp_path / "x.npy")], "iters"),
        (["--energy", "rims", "--out", str(tmp_path / "x.npy")], "--energy"),
    ):
        with pytest.raises(SystemExit):
            main(["arap", str(path), *args])
        assert message in capsys.readouterr().err


@pytest.mark.slow
def test_one_rigid_motion_of_every_handle_gives_that_motion_on_arm5(tmp_path):
    """Issue 30's probe: `jaxcga arap` on Arm5 (welded on load) with both ends moved by one rigid motion returns
    that rigid map (the default energy, start and convergence test)."""
    V = np.array(deform.load_model(DATA / "Arm5.glb", weld=True).mesh.V, np.float64)  # writable, for scipy
    axis = int(np.argmax(np.ptp(V, axis=0)))
    s = (V[:, axis] - V[:, axis].min()) / np.ptp(V[:, axis])
    indices = np.flatnonzero((s < 0.05) | (s > 0.95))
    diag = np.linalg.norm(np.ptp(V, axis=0))
    rigid = Rotation.from_rotvec([0.3, -0.5, 0.2]).apply(V) + np.array([0.1, -0.05, 0.2]) * diag
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps({"handles": [indices.tolist()], "positions": [rigid[indices].tolist()]}))
    out = tmp_path / "arap.npy"
    assert (
        main(
            [
                "arap",
                str(DATA / "Arm5.glb"),
                "--handles",
                str(handles),
                "--out",
                str(out),
            ]
        )
        == 0
    )
    assert np.abs(np.load(out) - rigid).max() < 1e-6 * diag


@pytest.fixture(scope="module")
def character(tmp_path_factory):
    """The multi-part CesiumMan of tests.shared written as .ply: (path, V, F, parts)."""
    path = tmp_path_factory.mktemp("character") / "character.ply"
    return (path, *write_multipart_character(path))


@pytest.mark.slow
def test_a_character_of_many_parts_moves_as_one(character, tmp_path, capsys):
    """The feet and the crown turned by one rigid motion: every part, the five without a handle included, is
    moved by it (scipy's rotation of every vertex); the default end handles run too, every position finite; and
    --unhandled error refuses the mesh, naming the parts."""
    path, V, _, parts = character
    axis, angle, center, shift = np.array([0.3, 1.0, -0.4]), 50.0, np.array([0.1, 1.0, 0.0]), [0.2, -0.1, 0.3]
    spec = {"center": center.tolist(), "axis": axis.tolist(), "angle_deg": angle, "translation": shift}
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps({"handles": [parts["feet"].tolist(), parts["crown"].tolist()], "motors": [spec] * 2}))
    out = tmp_path / "arap.npy"
    assert main(["arap", str(path), "--handles", str(handles), "--iters", "3", "--out", str(out)]) == 0
    assert "parts 6, following_parts 5" in capsys.readouterr().out
    expected = Rotation.from_rotvec(np.radians(angle) * axis / np.linalg.norm(axis)).apply(V - center) + center + shift
    np.testing.assert_allclose(np.load(out), expected, atol=1e-9)
    assert main(["arap", str(path), "--iters", "3", "--out", str(out)]) == 0
    assert np.all(np.isfinite(np.load(out)))
    with pytest.raises(SystemExit) as exit_info:
        main(["arap", str(path), "--unhandled", "error", "--out", str(out)])
    assert exit_info.value.code == 2
    assert "of the mesh's 6 connected part(s) hold no constrained vertex (part" in capsys.readouterr().err


@pytest.mark.slow
def test_a_corpus_character_of_many_parts(tmp_path, capsys):
    """jaxcga arap on a real character of 15 connected parts (tests/data/characters): every position finite, the
    parts and the followers counted."""
    out = tmp_path / "worker.npy"
    assert main(["arap", str(CHARACTERS["QuaterniusWorker"]), "--bend", "45", "--iters", "5", "--out", str(out)]) == 0
    assert np.all(np.isfinite(np.load(out)))
    assert re.search(r"parts 15, following_parts [1-9]", capsys.readouterr().out)


def test_each_iteration_is_shown_and_the_solve_time_leaves_compilation_out(tmp_path, capsys):
    assert main(["arap", "--bend", "30", "--fixed", "--iters", "40", "--out", str(tmp_path / "a.npy")]) == 0
    captured = capsys.readouterr()
    # the first iteration compiles the loop's pieces: the bar starts after it
    assert "jaxcga arap: first iteration done in " in captured.err
    bar = captured.err.replace("\r", "\n").splitlines()
    assert any(" 40/40 [" in line and "residual=" in line and "energy=" in line for line in bar), captured.err
    summary = dict(item.split(" ", 1) for item in captured.out.split(": ", 1)[1].strip().split(", "))
    assert summary["iterations"] == "40" and float(summary["compile_s"]) > 0 and float(summary["solve_ms"]) > 0
