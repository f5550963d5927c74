"""The ``jaxcga skin``, ``animate`` and ``fit`` commands, end to end in-process."""

from __future__ import annotations

import json
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import trimesh

import deform
from jaxcga_cli.main import main
from tests.deform._gltf_reference import Reference
from tests.deform._rigs import scaled_keys_model

DATA = Path(__file__).resolve().parents[1] / "data"


def test_skin_writes_world_space_float64_positions(tmp_path):
    out = tmp_path / "cesium.npy"
    assert main(["skin", str(DATA / "CesiumMan.glb"), "--time", "0.8", "--method", "lbs", "--out", str(out)]) == 0
    positions = np.load(out)
    assert positions.dtype == np.float64 and positions.shape == (3273, 3)
    np.testing.assert_allclose(positions, Reference(DATA / "CesiumMan.glb").skin(0, 0.8), atol=2e-6)


def test_skin_default_arm_to_a_posed_glb(tmp_path):
    out = tmp_path / "arm.glb"
    assert main(["skin", "--time", "1.0", "--out", str(out)]) == 0
    arm = deform.default_arm()
    loaded = trimesh.load_mesh(out, process=False)
    assert loaded.vertices.shape == (arm.mesh.num_vertices, 3)
    np.testing.assert_allclose(loaded.vertices, deform.skin_model(arm, 1.0, "cga"), atol=1e-5)


@pytest.mark.slow
def test_animate_resamples_the_clip_through_versors(tmp_path):
    out = tmp_path / "walk.glb"
    assert main(["animate", str(DATA / "RiggedSimple.glb"), "--frames", "9", "--out", str(out)]) == 0
    original = deform.load_model(DATA / "RiggedSimple.glb")
    animated = deform.load_model(out)
    assert len(animated.clips) == 1 and animated.clips[0].channels[0].times.shape == (9,)
    times = np.asarray(animated.clips[0].channels[0].times)
    for t in times[[0, 4, 8]]:
        expected = deform.skin_model(original, t, "cga")
        np.testing.assert_allclose(deform.skin_model(animated, t, "lbs"), expected, atol=1e-5)


@pytest.mark.slow
def test_animate_generates_keyframes_for_a_model_without_clip(tmp_path):
    out = tmp_path / "arm5.gltf"
    assert main(["animate", str(DATA / "Arm5.glb"), "--frames", "5", "--out", str(out)]) == 0
    animated = deform.load_model(out)
    assert animated.clips[0].name == "generated_keyframes"
    paths = {c.path for c in animated.clips[0].channels}
    assert paths == {"translation", "rotation", "scale"}  # the generated keys dilate the deepest bones
    middle = deform.skin_model(animated, 1.0, "cga")
    assert float(jnp.max(jnp.abs(middle - deform.rest_pose(animated, "cga")))) > 1.0


@pytest.mark.slow
def test_fit_writes_a_pose_that_reproduces_the_target(tmp_path):
    arm = deform.default_arm()
    truth = deform.random_parameters(jax.random.PRNGKey(0), arm, rotation=0.3, translation=0.01, log_scale=0.05)
    np.save(tmp_path / "target.npy", np.asarray(deform.skin_parameters(arm, truth)))
    out = tmp_path / "pose.json"
    assert main(["fit", "--target", str(tmp_path / "target.npy"), "--out", str(out)]) == 0
    pose = json.loads(out.read_text())
    assert pose["converged"] and pose["max_error"] <= 1e-6 * pose["bounding_diagonal"]
    assert [b["name"] for b in pose["bones"]] == list(arm.skeleton.names)
    params = jnp.asarray([b["parameters"] for b in pose["bones"]])
    np.testing.assert_allclose(deform.skin_parameters(arm, params), deform.skin_parameters(arm, truth), atol=1e-6)


def test_errors_are_reported_with_exit_code_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["skin", str(tmp_path / "missing.glb"), "--out", str(tmp_path / "x.npy")])
    assert exit_info.value.code == 2
    assert "missing.glb" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["skin", "--out", str(tmp_path / "x.txt")])
    assert "out" in capsys.readouterr().err
    np.save(tmp_path / "bad.npy", np.zeros((5, 3)))
    with pytest.raises(SystemExit):
        main(["fit", "--target", str(tmp_path / "bad.npy"), "--out", str(tmp_path / "p.json")])
    assert "target" in capsys.readouterr().err


def _error(argv, capsys) -> str:
    """The one error line ``main(argv)`` prints when it fails with exit code 2 (after status lines, if any)."""
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    *status, error = err.splitlines()
    assert error.startswith(f"jaxcga {argv[0]}: error: "), err
    assert all(line.startswith(f"jaxcga {argv[0]}: ") and ": error: " not in line for line in status), err
    return error + "\n"


@pytest.mark.parametrize("value", ["nan", "inf", "-inf", "NaN", "1e999"])
def test_non_finite_numbers_are_refused_by_the_parser(tmp_path, capsys, value):
    err = _error(["skin", "--time", value, "--out", str(tmp_path / "x.npy")], capsys)
    assert f"argument --time: expected a finite number, got '{value}'" in err


def test_parser_errors_are_one_line(tmp_path, capsys):
    assert "the following arguments are required: --out" in _error(["skin"], capsys)
    assert "invalid choice: 'nope'" in _error(["skin", "--method", "nope", "--out", "x.npy"], capsys)


def test_an_error_inside_compiled_code_prints_its_message_only(tmp_path, capsys, monkeypatch):
    """A runtime check (the library's ``require``, as every in-jit check) under jax.jit and under eqx.filter_jit:
    one line with the check's message, and no log of the failed callback. The result is waited for, as a command
    reads its results: a GPU raises a failed check only then."""
    import equinox as eqx

    from _jaxcga_shared.checks import require
    from jaxcga_cli import skin

    check = lambda x: require(x, (x > 0, "x: must not be positive"))  # noqa: E731
    for jit in (jax.jit, eqx.filter_jit):
        monkeypatch.setattr(skin, "run", lambda args, jit=jit: jax.block_until_ready(jit(check)(jnp.ones(()))))
        err = _error(["skin", "--out", str(tmp_path / "x.npy")], capsys)
        assert err == "jaxcga skin: error: x: must not be positive\n"


def test_fit_names_unreadable_target_and_vertex_files(tmp_path, capsys):
    out = str(tmp_path / "p.json")
    assert "target: no such file" in _error(["fit", "--target", str(tmp_path / "none.npy"), "--out", out], capsys)
    (tmp_path / "text.npy").write_text("not an array")
    assert "text.npy is not a .npy file" in _error(
        ["fit", "--target", str(tmp_path / "text.npy"), "--out", out], capsys
    )
    np.save(tmp_path / "whole.npy", np.zeros((10, 3)))
    (tmp_path / "cut.npy").write_bytes((tmp_path / "whole.npy").read_bytes()[:150])
    assert (
        "cut.npy is truncated: 150 of the 368 bytes its header states for a float64 array of shape (10, 3)"
        in _error(["fit", "--target", str(tmp_path / "cut.npy"), "--out", out], capsys)
    )
    np.save(tmp_path / "t.npy", np.zeros((2, 3)))
    np.save(tmp_path / "i.npy", np.array([0, 1]))
    argv = ["fit", "--target", str(tmp_path / "t.npy"), "--out", out]
    assert "vertices: no such file" in _error(argv + ["--vertices", str(tmp_path / "none.npy")], capsys)
    assert "max_steps: expected an int >= 1, got 0" in _error(
        argv + ["--vertices", str(tmp_path / "i.npy"), "--max-steps", "0"], capsys
    )


def test_a_corrupt_buffer_is_blamed_on_its_accessor(tmp_path, capsys):
    raw = bytearray((DATA / "RiggedSimple.glb").read_bytes())
    length = int.from_bytes(raw[12:16], "little")
    doc = json.loads(raw[20 : 20 + length])
    accessor = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    start = 20 + length + 8 + doc["bufferViews"][accessor["bufferView"]].get("byteOffset", 0)
    start += accessor.get("byteOffset", 0)
    raw[start : start + 12] = b"\xff" * 12  # NaN bit patterns: the first vertex
    (tmp_path / "corrupt.glb").write_bytes(bytes(raw))
    err = _error(["skin", str(tmp_path / "corrupt.glb"), "--out", str(tmp_path / "x.npy")], capsys)
    assert "POSITION (accessor" in err and "non-finite" in err


@pytest.mark.slow
def test_skin_and_animate_interpolation(tmp_path):
    """``--interpolation gltf`` (default) follows the file's animation for every method; ``log`` is the
    paper's sampling, which departs from it between scale keys."""
    model = scaled_keys_model(tmp_path / "scaled.glb")
    reference = Reference(tmp_path / "scaled.glb")
    expected = reference.skin(0, 0.75)
    diagonal = float(np.linalg.norm(np.ptp(expected, axis=0)))
    for interpolation in ("gltf", "log"):
        out = tmp_path / f"{interpolation}.npy"
        assert (
            main(
                [
                    "skin",
                    str(tmp_path / "scaled.glb"),
                    "--time",
                    "0.75",
                    "--method",
                    "cga",
                    "--interpolation",
                    interpolation,
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        gap = np.abs(np.load(out) - expected).max() / diagonal
        assert gap < 1e-6 if interpolation == "gltf" else gap > 1e-2, (interpolation, gap)
    np.testing.assert_allclose(
        np.load(tmp_path / "log.npy"), deform.skin_model(model, 0.75, "cga", interpolation="log"), atol=1e-12
    )
    # animate re-samples at 0, 0.5, 1.0, 1.5 s: its keys hold the chosen sampling there
    for interpolation in ("gltf", "log"):
        out = tmp_path / f"{interpolation}.glb"
        assert (
            main(
                [
                    "animate",
                    str(tmp_path / "scaled.glb"),
                    "--frames",
                    "4",
                    "--interpolation",
                    interpolation,
                    "--out",
                    str(out),
                ]
            )
            == 0
        )
        animated = deform.load_model(out)
        wanted = deform.skin_model(model, 0.5, "lbs", interpolation=interpolation)
        np.testing.assert_allclose(deform.skin_model(animated, 0.5, "lbs"), wanted, atol=1e-5 * diagonal)


def test_clip_options_that_do_nothing_are_told(tmp_path, capsys):
    model = deform.load_model(DATA / "RiggedSimple.glb")
    start, end = float(model.clips[0].start), float(model.clips[0].end)
    out = tmp_path / "x.npy"
    # a time past the clip: glTF holds the clip's last pose, and the user is told so
    assert main(["skin", str(DATA / "RiggedSimple.glb"), "--time", "100", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    told = f"--time 100 is outside clip 'clip0' ({start:g} to {end:g} s); glTF holds a clip at its ends"
    assert f"jaxcga skin: warning: {told}: posed at {end:g} s" in err
    np.testing.assert_allclose(np.load(out), np.asarray(deform.skin_model(model, end, "cga")), rtol=0, atol=1e-12)
    # no --time: the clip's start (RiggedSimple's is not 0), without a word
    assert main(["skin", str(DATA / "RiggedSimple.glb"), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    assert "warning" not in captured.err and f"time {start}," in captured.out
    # a model without clips: --time and --interpolation change nothing
    assert main(["skin", str(DATA / "Arm5.glb"), "--time", "1", "--interpolation", "log", "--out", str(out)]) == 0
    assert "jaxcga skin: warning: Arm5 has no clip: --time 1, --interpolation log ignored" in capsys.readouterr().err


def test_an_unknown_clip_is_named_as_the_option_before_anything_compiles(tmp_path, capsys, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("compiled although the clip does not exist")

    monkeypatch.setattr(deform, "skin_model", refuse)
    monkeypatch.setattr(deform, "sample_pose", refuse)
    for command in ("skin", "animate"):
        for clip, message in (
            ("Walk", "clip: no clip called 'Walk'; clips are ['clip0']"),
            ("3", "clip: model has 1 clips, no clip 3"),
        ):
            argv = [command, str(DATA / "RiggedSimple.glb"), "--clip", clip, "--out", str(tmp_path / "x.glb")]
            assert _error(argv, capsys) == f"jaxcga {command}: error: {message}\n"


def test_fit_shows_each_solver_step_after_the_compiling_one(tmp_path, capsys):
    model = deform.load_model(DATA / "RiggedSimple.glb")
    np.save(tmp_path / "target.npy", np.asarray(deform.skin_model(model, 1.0, "cga")))
    argv = ["fit", str(DATA / "RiggedSimple.glb"), "--target", str(tmp_path / "target.npy")]
    assert main([*argv, "--max-steps", "50", "--out", str(tmp_path / "pose.json")]) == 0
    captured = capsys.readouterr()
    steps = json.loads((tmp_path / "pose.json").read_text())["steps"]
    assert "jaxcga fit: compiling (the first step includes compilation) ..." in captured.err
    assert "jaxcga fit: first step done in " in captured.err
    # the bar counts every step the solver made, each with its loss
    bar = captured.err.replace("\r", "\n").splitlines()
    assert any(f" {steps}/50 [" in line and "loss=" in line for line in bar), captured.err
    assert not any(f" {steps + 1}/50 [" in line for line in bar)
