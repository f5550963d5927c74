"""``jaxcga cut`` end to end: skinned glTF halves with the input's skeleton, joints and weights, that
animate again."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

import deform
from jaxcga_cli.main import main


@pytest.mark.slow
def test_cut_writes_two_skinned_halves_that_animate(tmp_path):
    pos, neg = tmp_path / "pos.glb", tmp_path / "neg.glb"
    assert main(["cut", "--plane", "1", "0.1", "0", "0.3", "--cap", "--out", str(pos), str(neg)]) == 0
    arm = deform.default_arm()
    volumes = []
    for path, sign in ((pos, 1), (neg, -1)):
        half = deform.load_model(path)
        assert half.skeleton.names == arm.skeleton.names and len(half.clips) == len(arm.clips)
        V, W = np.asarray(half.mesh.V), np.asarray(half.mesh.W)
        n = np.array([1.0, 0.1, 0.0]) / np.linalg.norm([1.0, 0.1, 0.0])
        assert np.all(sign * (V @ n - 0.3 / np.linalg.norm([1.0, 0.1, 0.0])) >= -1e-6)
        np.testing.assert_allclose(W.sum(axis=1), 1.0, atol=1e-6)
        assert np.all(np.isfinite(np.asarray(deform.skin_model(half, 1.2, "cga"))))
        mesh = trimesh.Trimesh(V, np.asarray(half.mesh.F))
        assert mesh.is_watertight
        volumes.append(mesh.volume)
    whole = trimesh.Trimesh(np.asarray(arm.mesh.V), np.asarray(arm.mesh.F)).volume
    assert abs(sum(volumes) - whole) <= 1e-5 * whole  # float32 in the files


def test_cut_errors_exit_with_code_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["cut", "--plane", "1", "0", "0", "100", "--out", str(tmp_path / "a.glb"), str(tmp_path / "b.glb")])
    assert stop.value.code == 2 and "misses the mesh" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["cut", "--plane", "1", "0", "0", "0.3", "--out", str(tmp_path / "a.npy"), str(tmp_path / "b.glb")])


def test_tear_writes_a_skinned_model_with_an_open_slit(tmp_path):
    out = tmp_path / "torn.glb"
    samples = ["0.2 0 0.1 0.2 0 0", "0.3 0 0.1 0.3 0 0", "0.35 0.01 0.1 0.35 0.01 0"]
    argv = ["tear", *[a for s in samples for a in ("--scalpel", *s.split())], "--opening", "0.005"]
    assert main([*argv, "--out", str(out)]) == 0
    arm = deform.default_arm()
    torn = deform.load_model(out)
    assert torn.skeleton.names == arm.skeleton.names and len(torn.clips) == len(arm.clips)
    V, F = np.asarray(torn.mesh.V), np.asarray(torn.mesh.F)
    np.testing.assert_allclose(np.asarray(torn.mesh.W).sum(axis=1), 1.0, atol=1e-6)
    mesh = trimesh.Trimesh(V, F, process=False)
    assert not mesh.is_watertight and mesh.is_winding_consistent  # the closed arm now has a slit
    assert len(V) > arm.mesh.num_vertices
    assert np.all(np.isfinite(np.asarray(deform.skin_model(torn, 1.2, "cga"))))
    # the same samples from a path file, in both of its forms, give the same model
    for form in ("objects", "pairs"):
        ends = [[float(x) for x in s.split()] for s in samples]
        entries = [{"handle": e[:3], "tip": e[3:]} if form == "objects" else [e[:3], e[3:]] for e in ends]
        path = tmp_path / f"{form}.json"
        path.write_text(json.dumps(entries))
        again = tmp_path / f"{form}.glb"
        assert main(["tear", "--scalpel-path", str(path), "--opening", "0.005", "--out", str(again)]) == 0
        np.testing.assert_array_equal(np.asarray(deform.load_model(again).mesh.F), F)
    # a file's samples come first, then any --scalpel
    path.write_text(json.dumps(entries[:2]))
    assert main(["tear", "--scalpel-path", str(path), "--scalpel", *samples[2].split(), "--out", str(again)]) == 0


def test_tear_path_errors_exit_with_code_2(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    for text, needle in [
        ('{"handle": [0, 0, 0]}', "expected a list of samples"),
        ('[{"handle": [0.2, 0, 0.1], "tip": [0.2, 0]}]', "entry 0 of"),
        ("[[[0.2, 0, 0.1], [0.2, 0, 0]], [[1, 2, 3], [4, 5, null]]]", "entry 1 of"),
        ("[[", "cannot read"),
    ]:
        bad.write_text(text)
        with pytest.raises(SystemExit) as stop:
            main(["tear", "--scalpel-path", str(bad), "--out", str(tmp_path / "t.glb")])
        assert stop.value.code == 2 and needle in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["tear", "--scalpel", *"0.2 0 0.1 0.2 0 0".split(), "--out", str(tmp_path / "t.glb")])
    assert stop.value.code == 2 and "expected two or more samples" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(["tear", "--scalpel-path", str(tmp_path / "missing.json"), "--out", str(tmp_path / "t.glb")])
    assert stop.value.code == 2 and "missing.json" in capsys.readouterr().err


def test_a_side_weight_outside_0_1_is_refused_before_loading(tmp_path, capsys, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("loaded the model although --side-weight is refused")

    monkeypatch.setattr(deform, "load_model", refuse)
    monkeypatch.setattr(deform, "default_arm", refuse)
    scalpel = [a for s in ("0.2 0 0.1 0.2 0 0", "0.3 0 0.1 0.3 0 0") for a in ("--scalpel", *s.split())]
    for argv in (
        ["cut", "--plane", "1", "0", "0", "0.3", "--out", str(tmp_path / "a.glb"), str(tmp_path / "b.glb")],
        ["tear", *scalpel, "--out", str(tmp_path / "t.glb")],
    ):
        with pytest.raises(SystemExit) as stop:
            main([*argv, "--side-weight", "5"])
        err = capsys.readouterr().err
        assert (
            stop.value.code == 2
            and err == f"jaxcga {argv[0]}: error: side_weight: expected a number in [0, 1], got 5.0\n"
        )


def test_a_tear_opening_wider_than_the_model_is_refused(tmp_path, capsys):
    from _jaxcga_shared.mesh import bounding_diagonal

    diagonal = bounding_diagonal(deform.default_arm().mesh.V)
    scalpel = [a for s in ("0.2 0 0.1 0.2 0 0", "0.3 0 0.1 0.3 0 0") for a in ("--scalpel", *s.split())]
    with pytest.raises(SystemExit) as stop:
        main(["tear", *scalpel, "--opening", "10", "--out", str(tmp_path / "t.glb")])
    err = capsys.readouterr().err
    assert (
        stop.value.code == 2
        and f"opening: 10 is wider than the model itself (its bounding box diagonal is {diagonal:.4g}" in err
    )
    assert not (tmp_path / "t.glb").exists()
    assert main(["tear", *scalpel, "--opening", f"{0.01 * diagonal}", "--out", str(tmp_path / "t.glb")]) == 0


def test_drill_writes_a_skinned_model_with_a_hole(tmp_path):
    out = tmp_path / "drilled.glb"
    assert (
        main(["drill", "--tip", "0.4", "0", "0", "--base", "0.4", "0", "0.1", "--radius", "0.015", "--out", str(out)])
        == 0
    )
    drilled = deform.load_model(out)
    V, F = np.asarray(drilled.mesh.V), np.asarray(drilled.mesh.F)
    mesh = trimesh.Trimesh(V, F, process=False)
    assert not mesh.is_watertight and mesh.is_winding_consistent
    assert np.all(np.isfinite(np.asarray(deform.skin_model(drilled, 1.2, "lbs"))))


def test_tear_and_drill_errors_exit_with_code_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "tear",
                "--scalpel",
                "5",
                "5",
                "5",
                "5",
                "5",
                "6",
                "--scalpel",
                "6",
                "5",
                "5",
                "6",
                "5",
                "6",
                "--out",
                str(tmp_path / "t.glb"),
            ]
        )
    assert stop.value.code == 2 and "never crosses the surface" in capsys.readouterr().err
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "drill",
                "--tip",
                "5",
                "5",
                "5",
                "--base",
                "5",
                "5",
                "6",
                "--radius",
                "0.01",
                "--out",
                str(tmp_path / "d.glb"),
            ]
        )
    assert stop.value.code == 2 and "misses" in capsys.readouterr().err


@pytest.mark.parametrize(
    "value, parsed",
    [
        ("-1e0", "-1.0"),
        ("-1E+0", "-1.0"),
        ("-.5e1", "-5.0"),
        ("-2.", "-2.0"),
        ("-1e12", "-1000000000000.0"),
        ("-0.3", "-0.3"),
    ],
)
def test_negative_numbers_parse_in_any_notation(tmp_path, capsys, value, parsed):
    """argparse's own test takes ``-1e0`` for an option: every notation reaches the command as a number."""
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "cut",
                "--plane",
                "1",
                "0",
                "0",
                "0.3",
                "--side-weight",
                value,
                "--out",
                str(tmp_path / "a.glb"),
                str(tmp_path / "b.glb"),
            ]
        )
    err = capsys.readouterr().err
    assert stop.value.code == 2
    assert err.splitlines()[-1] == f"jaxcga cut: error: side_weight: expected a number in [0, 1], got {parsed}"


def test_a_drill_wider_than_the_model_says_so(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "drill",
                "--tip",
                "0.4",
                "0",
                "0",
                "--base",
                "0.4",
                "0",
                "0.1",
                "--radius",
                "10",
                "--out",
                str(tmp_path / "d.glb"),
            ]
        )
    err = capsys.readouterr().err
    assert stop.value.code == 2 and len(err.splitlines()) == 2  # the bounding box, the error
    assert "radius: 10 exceeds the model's size: every vertex lies within 0.45 of the drill's axis" in err


def test_drill_through_a_character_reports_the_holes_and_shells(tmp_path, capsys):
    """A drill through a limb of CesiumMan (welded by the command): the summary counts the holes, the shells
    they are in and the parts removed, and gives the rim's distance from the cylinder; the written model
    skins, and its vertices outside the drill are the input's."""
    from tests.cutting.tools import DATA, drill_outcome, drill_through_limb

    model = deform.load_model(DATA / "CesiumMan.glb", weld=True)
    V, F = np.asarray(model.mesh.V, np.float64), np.asarray(model.mesh.F)
    drill, _ = drill_through_limb(V, F, np.random.default_rng(3))
    out = tmp_path / "drilled.glb"
    numbers = lambda x: [repr(float(v)) for v in np.atleast_1d(x)]  # noqa: E731
    arguments = ["--tip", *numbers(drill.tip), "--base", *numbers(drill.base), "--radius", *numbers(drill.radius)]
    assert main(["drill", str(DATA / "CesiumMan.glb"), *arguments, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    import cutting

    _, topology = cutting.drill(model.mesh, drill, return_topology=True)
    inside, rim, middle = drill_outcome(V, F, drill, topology)
    assert inside == 0 and max(rim, middle) <= 1e-3
    summary = captured.out
    assert f"holes {topology.holes}, shells 1, parts_removed 0" in summary  # CesiumMan is one closed shell
    assert "hole(s) in 1 shell(s)" in captured.err and "the rim lies within" in captured.err
    assert float(summary.split("rim_distance ")[1].split(",")[0]) == pytest.approx(max(rim, middle), rel=1e-6)
    drilled = deform.load_model(out)
    assert np.all(np.isfinite(np.asarray(deform.skin_model(drilled, 0.5, "lbs"))))
    assert drilled.mesh.num_vertices == len(topology.kept)
