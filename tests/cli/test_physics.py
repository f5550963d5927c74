"""The ``jaxcga physics CHARACTER`` command end to end in-process: the corpus fox (576 triangles, coarse tets, a few
frames of its walk) writes its frames, the viewer page and the summary, consistent with each other and with the rig,
and plays in the reduced mode; CesiumMan's arm cut off makes two pieces written per segment, the arm released and
falling; errors, the cheap ones before anything is loaded."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

import deform
from jaxcga_cli.main import main
from tests.shared import CHARACTERS, load_character

FOX = str(CHARACTERS["Fox"])
# The fox is modelled in centimetres (about 150 long, +y up): gravity in cm/s^2 and Young's modulus 1e4 times a
# metre model's 1e5 (the same dynamics at 100 times the lengths), coarse tets (about 1.2k), a few frames of its walk.
FOX_RUN = ["--clip", "Walk", "--gravity", "0", "-981", "0", "--young", "1e9", "--edge-length", "0.1"]
TAIL = ["0", "30", "-50", "0", "0", "-1"]  # the plane z = -50 (rest pose): the fox's tail beyond it
CESIUM = str(CHARACTERS["CesiumMan"])  # metres, +y up, a T-pose at rest: only the left arm reaches x > 0.18
ARM = ["0.2", "1", "0", "1", "0", "0"]  # the plane x = 0.2: the left arm beyond it


def _page_config(path) -> dict:
    """The viewer page's embedded configuration (``_jaxcga_shared.viewer``: a JSON script element)."""
    match = re.search(r'<script type="application/json" id="jaxcga-config">(.*?)</script>', path.read_text())
    assert match, "no configuration in the page"
    return json.loads(match.group(1))


def _summary(out) -> dict:
    return json.loads((out / "summary.json").read_text())


@pytest.mark.slow
def test_a_clip_plays_and_writes_frames_a_page_and_a_summary(tmp_path, capsys):
    out = tmp_path / "fox"
    assert main(["physics", FOX, *FOX_RUN, "--seconds", "0.2", "--out", str(out)]) == 0
    assert "jaxcga physics Fox.glb: clip Walk" in capsys.readouterr().out
    assert sorted(p.name for p in out.iterdir()) == ["faces.npy", "frames.npy", "summary.json", "view.html"]
    summary = _summary(out)
    model = load_character("Fox")
    frames, faces = np.load(out / "frames.npy"), np.load(out / "faces.npy")
    assert summary["steps"] == 6 and summary["frames"] == 7 and summary["frames_file"] == "frames.npy"
    assert frames.shape == (7, model.mesh.num_vertices, 3) and frames.dtype == np.float64
    np.testing.assert_array_equal(faces, np.asarray(model.mesh.F))
    assert summary["dofs"] == 3 * summary["nodes"] and 0 < summary["driven_nodes"] < summary["nodes"]
    assert (
        summary["tets"] > 0
        and summary["tetrahedralization"]["seconds"] > 0
        and summary["tetrahedralization"]["refine"] == 1e-3
    )
    assert summary["pieces_per_frame"] == [summary["pieces"]] * 7 and len(summary["segment_seconds"]) == 1
    assert summary["frames_s"] == pytest.approx(summary["segment_seconds"][0])
    assert 0 < summary["compile_s"] < summary["frames_s"] and summary["step_avg_s"] > 0
    assert summary["converged_steps"] == 6 and 1 <= summary["newton_iterations_mean"] <= 50
    np.testing.assert_allclose(summary["times"], model.clip("Walk").start + np.arange(7) / 30.0, rtol=0, atol=1e-12)
    # frame 0 is the rig at the clip's start: the surface carried by the skinned tet nodes, near the skinned
    # surface (the tets' envelope and the weights' transfer apart), and the body moves with the walk
    skinned = np.asarray(deform.skin_model(model, summary["times"][0], "cga", "Walk"))
    diagonal = summary["diagonal"]
    assert np.abs(frames[0] - skinned).max() < 0.05 * diagonal
    assert np.abs(frames[-1] - frames[0]).max() > 1e-3 * diagonal
    config = _page_config(out / "view.html")
    assert config["sequenceFps"] == 30.0
    (sequence,) = config["items"]
    assert sum(s["frames"] for s in sequence["segments"]) == 7


@pytest.mark.slow
def test_a_cut_makes_two_pieces_written_per_segment(tmp_path):
    """CesiumMan's left arm cut off (the plane x = 0.2 m, rest pose) before frame 2 at 10 frames per second, on
    coarse unrefined tets with wide cores (as notebook 08): frames 0-1 in one piece, 2-5 in two, the arm released
    and falling for 0.4 s, the rest walking on."""
    out = tmp_path / "arm"
    args = ["--fps", "10", "--seconds", "0.5", "--edge-length", "0.1", "--refine", "0", "--core", "0.8"]
    assert main(["physics", CESIUM, *args, "--cut", "2", *ARM, "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["frames.npz", "summary.json", "view.html"]
    summary = _summary(out)
    assert summary["frames_file"] == "frames.npz" and summary["steps"] == 5
    assert summary["tetrahedralization"]["refine"] == 0 and summary["cuts"][0]["frame"] == 2
    assert summary["cuts"][0]["normal"] == [1.0, 0.0, 0.0] and summary["pieces_per_frame"] == [1] * 2 + [2] * 4
    before, after = summary["segments"]
    assert (before["first"], before["frames"], after["first"], after["frames"]) == (0, 2, 2, 4)
    assert (before["pieces"], after["pieces"]) == (1, 2) and after["dofs"] > before["dofs"] == summary["dofs"]
    assert before["released"] == [] and len(after["released"]) == 1
    with np.load(out / "frames.npz") as data:  # no pickle
        arrays = dict(data)
    assert sorted(arrays) == sorted(
        ["first", "times"] + [f"{name}_{k}" for k in (0, 1) for name in ("frames", "faces", "piece", "vertex")]
    )
    assert arrays["first"].tolist() == [0, 2] and arrays["times"].shape == (6,)
    s0, s1, vertex = arrays["frames_0"], arrays["frames_1"], arrays["vertex_1"]
    model = load_character("CesiumMan")
    assert s0.shape == (2, model.mesh.num_vertices, 3) and s1.shape == (4, len(vertex), 3)
    assert arrays["faces_1"].max() < len(vertex) and np.array_equal(arrays["faces_0"], np.asarray(model.mesh.F))
    assert np.unique(arrays["piece_1"]).tolist() == [0, 1] and np.unique(arrays["piece_0"]).size == 1
    # the released piece is the arm beyond the plane at rest; from where the cut left it (frame 1) it falls by
    # at least half of free fall's 0.4 s, while the body's piece stays within a tenth of that
    rest = np.asarray(deform.rest_pose(model, "lbs"))
    faces, piece = arrays["faces_1"], arrays["piece_1"]
    (arm,) = after["released"]
    rows = {k: np.unique(faces[piece == k]) for k in (0, 1)}
    assert np.all(rest[vertex[rows[arm]], 0] > 0.1) and np.any(rest[vertex[rows[1 - arm]], 0] < 0)
    drop = {k: (s1[-1, r, 1] - s0[-1, vertex[r], 1]).mean() for k, r in rows.items()}
    assert drop[arm] < -0.5 * 0.5 * 9.81 * 0.4**2 and abs(drop[1 - arm]) < 0.1 * abs(drop[arm])
    config = _page_config(out / "view.html")
    assert sum(s["frames"] for s in config["items"][0]["segments"]) == 6
    assert all("groups" in s for s in config["items"][0]["segments"])  # pieces coloured


@pytest.mark.slow
def test_the_reduced_mode_plays_in_skinning_eigenmodes(tmp_path):
    """--reduced K: the body's K lowest skinning eigenmodes carry the flesh (xfem.character_subspace); the same
    files, one segment, no Newton iterations; frame 0 is the rig, as in the full space."""
    out = tmp_path / "reduced"
    assert main(["physics", FOX, *FOX_RUN, "--seconds", "0.2", "--reduced", "12", "--out", str(out)]) == 0
    summary = _summary(out)
    assert summary["reduced"] == 12 and summary["subspace_s"] > 0 and summary["newton_iterations_max"] == 0
    assert summary["rig_s"] is None and len(summary["segment_seconds"]) == 1 and summary["steps"] == 6
    frames = np.load(out / "frames.npy")
    model = load_character("Fox")
    assert frames.shape == (7, model.mesh.num_vertices, 3) and np.all(np.isfinite(frames))
    skinned = np.asarray(deform.skin_model(model, summary["times"][0], "cga", "Walk"))
    assert np.abs(frames[0] - skinned).max() < 0.05 * summary["diagonal"]
    assert np.abs(frames[-1] - frames[0]).max() > 1e-3 * summary["diagonal"]  # it walks


@pytest.mark.parametrize(
    "args, message",
    [
        (["--fps", "0"], "fps: expected a positive frame rate"),
        (["--seconds", "-1"], "seconds: expected a positive duration"),
        (["--seconds", "0.01"], "is no step"),
        (["--young", "0"], "young: expected a positive Young's modulus"),
        (["--poisson", "0.5"], "poisson"),
        (["--damping", "-1"], "damping"),
        (["--edge-length", "2"], "edge_length"),
        (["--cut", "0", *TAIL], "cut 1: FRAME must be a whole frame number >= 1"),
        (["--cut", "2.5", *TAIL], "cut 1: FRAME must be a whole frame number"),
        (["--seconds", "1", "--cut", "31", *TAIL], "cut 1: frame 31 is past the run's last frame 30"),
        (["--cut", "3", "0", "0", "0", "0", "0", "0"], "cut 1: the normal NX NY NZ is zero"),
        (["--thickness", "0"], "thickness"),
        (["--newton", "0"], "newton: expected an int >= 1"),
        (["--refine", "1"], "refine: expected a fraction of the diagonal in [0, 1)"),
        (["--reduced", "0"], "reduced: expected a number of modes K >= 1"),
        (["--reduced", "8", "--cut", "3", *TAIL], "reduced: the reduced mode does not cut"),
        (["--reduced", "8", "--newton", "5"], "reduced: the reduced mode makes one linear solve per frame"),
        (["--paper-step", "--newton", "5"], "newton: the paper's step makes one Newton iteration"),
    ],
)
def test_bad_options_are_refused_before_loading(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["physics", FOX, *args, "--out", str(tmp_path / "x")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1 and "loading" not in err
    assert not (tmp_path / "x").exists()


def test_bad_inputs_and_folders_are_refused(tmp_path, capsys):
    def refused(args, message, loads=False):
        with pytest.raises(SystemExit) as exit_info:
            main(["physics", *args])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err
        assert message in err, err
        assert ("loading" in err) == loads and "tetrahedralizing" not in err

    out = tmp_path / "x"
    refused([str(tmp_path / "missing.glb"), "--out", str(out)], "CHARACTER: no such file")
    (tmp_path / "mesh.obj").write_text("v 0 0 0\n")
    refused([str(tmp_path / "mesh.obj"), "--out", str(out)], "CHARACTER: expected a rigged glTF")
    out.mkdir()
    (out / "notes.txt").write_text("not the run's")
    refused([FOX, "--out", str(out)], "is not empty")
    refused([FOX, "--clip", "Dance", "--out", str(tmp_path / "y")], "clip: Fox.glb has no clip 'Dance'", True)
    refused([str(CHARACTERS["MaleBaseMesh"]), "--out", str(tmp_path / "y")], "has no animation clip", True)
    # without --seconds the run is the clip's length (the walk: 0.71 s, 21 frames), known once it is loaded
    refused([FOX, "--clip", "Walk", "--cut", "30", *TAIL, "--out", str(tmp_path / "y")], "past the run's last", True)
    with pytest.raises(SystemExit):
        main(["physics", FOX, "--tolerance", "1e-8", "--paper-step", "--out", str(tmp_path / "y")])
    assert "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "y").exists()


@pytest.mark.slow
def test_a_plane_that_misses_the_body_names_its_bounding_box(tmp_path, capsys):
    with pytest.raises(SystemExit):
        main(["physics", FOX, *FOX_RUN, "--seconds", "0.1", "--cut", "1", "0", "1000", "0", "0", "1", "0",
              "--out", str(tmp_path / "x")])  # fmt: skip
    err = capsys.readouterr().err
    assert "cut 1: the plane through [0.0, 1000.0, 0.0]" in err and "misses the body" in err and "y [" in err
    assert not (tmp_path / "x").exists()


def test_a_frame_rate_above_the_limit_is_refused_before_loading(tmp_path, capsys):
    from jaxcga_cli.physics import MAX_FPS

    with pytest.raises(SystemExit) as exit_info:
        main(["physics", FOX, "--fps", "1e9", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "loading" not in err
    assert err.startswith(f"jaxcga physics: error: fps: 1e+09 frames per second is above {MAX_FPS:g};")
