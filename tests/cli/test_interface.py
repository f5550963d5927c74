"""What the ``jaxcga`` command tells its user: ``--version``, each subcommand's ``--help`` (a one-line description
and an example that parses), enumerations as choices equal to the packages' own, status lines and a progress bar
that leaves compilation out, the model's bounding box around coordinates, animate's memory guard; and the layering
(the library never imports the command line, the kernel nothing above it)."""

from __future__ import annotations

import importlib.metadata
import inspect
import shlex
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

import cutting
import deform
import xfem
from jaxcga_cli import animate, arguments
from jaxcga_cli.main import COMMANDS, command_module, main, parser
from jaxcga_cli.report import StepProgress

ROOT = Path(__file__).resolve().parents[2]


def _exit(argv: list[str]) -> int | str | None:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    return stop.value.code


def test_version_is_the_distributions(capsys):
    assert _exit(["--version"]) == 0
    assert capsys.readouterr().out.strip() == f"jaxcga {importlib.metadata.version('jaxcga')}"
    done = subprocess.run(
        [sys.executable, "-m", "jaxcga_cli", "--version"],
        capture_output=True,
        text=True,
        cwd=ROOT,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0 and done.stdout.startswith("jaxcga "), done.stderr


@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_help_has_a_description_line_and_an_example_that_parses(command, capsys):
    assert _exit([command, "--help"]) == 0
    text = capsys.readouterr().out
    module = command_module(command)
    description = text.split("\n\n")[1]  # after the usage paragraph
    assert " ".join(description.split()) == module.HELP[0].upper() + module.HELP[1:] + "."
    assert len(module.HELP) < 240 and "\n" not in module.HELP  # one line, plain
    example = text.split("example:\n", 1)[1].strip()
    assert example == module.EXAMPLE and example.startswith(f"jaxcga {command}")
    args = parser().parse_args(shlex.split(example)[1:])
    assert args.command == command


def test_the_command_lines_enumerations_are_the_packages():
    import jax  # noqa: F401  (deform's METHODS etc. need nothing else)

    assert arguments.METHODS == deform.METHODS
    assert arguments.BASES == deform.BASES
    assert arguments.LAPLACIANS == deform.LAPLACIANS
    assert arguments.ARAP_ENERGIES == deform.ARAP_ENERGIES
    assert arguments.UNHANDLED == deform.UNHANDLED
    assert arguments.PREDICATES == cutting.PREDICATES
    assert arguments.XFEM_SCENES == xfem.SCENES
    assert arguments.XFEM_SIZES == xfem.SIZES


@pytest.mark.parametrize("command", ["fem", "xfem"])
def test_the_ftetwild_options_default_to_the_librarys_defaults(command):
    defaults = inspect.signature(xfem.tetrahedralize_surface).parameters
    args = parser().parse_args([command, "surface.obj", "--out", "out"])
    assert args.edge_length == defaults["edge_length"].default
    assert args.epsilon == defaults["epsilon"].default


def test_a_scene_that_is_neither_built_in_nor_a_file_is_named_with_the_choices(capsys):
    assert _exit(["xfem", "cake", "--out", "out"]) == 2
    err = capsys.readouterr().err
    assert "SCENE (one of sticks, thin, cheese, accordion, octopus or a surface file): no such file cake" in err, err


@pytest.mark.parametrize(
    "argv, option",
    [
        (["skin", "--method", "quaternions", "--out", "x.npy"], "--method"),
        (["cut", "--plane", "1", "0", "0", "0", "--predicates", "exact", "--out", "a.glb", "b.glb"], "--predicates"),
        (["deform", "spline", "--basis", "nurbs", "--out", "x.npy"], "--basis"),
        (["deform", "handles", "--laplacian", "uniform", "--out", "x.npy"], "--laplacian"),
        (["arap", "--energy", "rims", "--out", "x.npy"], "--energy"),
        (["xfem", "cheese", "--size", "huge", "--out", "out"], "--size"),
        (["animate", "--interpolation", "cubic", "--out", "x.glb"], "--interpolation"),
    ],
)
def test_enumerations_are_choices(argv, option, capsys):
    assert _exit(argv) == 2
    err = capsys.readouterr().err
    assert f"argument {option}: invalid choice" in err and "choose from" in err, err


def test_a_step_progress_starts_its_bar_after_the_compiling_step(capsys):
    with StepProgress("fem", 4, "step", "fem test") as progress:
        time.sleep(0.3)  # the first step: compilation
        compiled = time.time()
        progress.step()
        assert progress.bar is not None and progress.bar.start_t >= compiled  # the bar's clock starts after it
        for _ in range(3):
            progress.step()
        assert progress.bar.n == 4 and progress.bar.format_dict["initial"] == 1
    err = capsys.readouterr().err
    lines = err.splitlines()
    assert lines[0] == "jaxcga fem: compiling (the first step includes compilation) ..."
    assert lines[1].startswith("jaxcga fem: first step done in 0.")
    assert "fem test: 100%" in err and "4/4" in err


def test_a_step_progress_of_a_loop_compiled_ahead_starts_at_once_and_shows_its_values(capsys):
    with StepProgress("arap", 10, "iteration", "arap test", compiled=True) as progress:
        assert progress.bar is not None and progress.bar.n == 0
        for k in range(3):
            progress.step(residual=f"{10.0**-k:.2g}")
    err = capsys.readouterr().err
    assert "compiling" not in err and "first" not in err
    assert "3/10" in err and "residual=0.01" in err


def test_quiet_leaves_out_status_lines_and_bars_but_not_warnings(capsys):
    import warnings

    from jaxcga_cli.report import one_line_reports, quiet, say, status

    with one_line_reports("demo"), quiet():
        with status("animate", "sampling"):
            say("tear", "the model's bounding box")
        with StepProgress("fem", 2, "step", "fem test") as progress:
            progress.step()
            progress.step()
        warnings.warn("a mesh was welded", stacklevel=1)
    assert capsys.readouterr().err == "jaxcga demo: warning: a mesh was welded\n"
    with status("animate", "sampling"):  # outside: as before
        pass
    assert capsys.readouterr().err.startswith("jaxcga animate: sampling ...\n")


def test_skin_reports_its_compiling_step_on_stderr(tmp_path, capsys):
    assert main(["skin", "--time", "0.2", "--out", str(tmp_path / "x.npy")]) == 0
    out, err = capsys.readouterr()
    assert out.startswith("jaxcga skin default_arm: vertices 3266") and out.count("\n") == 1
    assert err.splitlines()[0] == "jaxcga skin: skinning 3266 vertices (compiling) ..."
    assert err.splitlines()[1].startswith("jaxcga skin: skinning 3266 vertices (compiling): done in ")


def _box(V) -> str:
    V = np.asarray(V)
    return ", ".join(f"{a} [{V[:, i].min():.4g}, {V[:, i].max():.4g}]" for i, a in enumerate("xyz"))


def test_a_cut_that_misses_the_mesh_gives_the_bounding_box_and_up_axis(tmp_path, capsys):
    box = _box(deform.default_arm().mesh.V)
    assert box.startswith("x [-0.05, 0.7913]")  # the built-in arm lies along x
    assert _exit(["cut", "--plane", "1", "0", "0", "5", "--out", str(tmp_path / "a.glb"), str(tmp_path / "b.glb")]) == 2
    status, error = capsys.readouterr().err.splitlines()
    assert status == f"jaxcga cut: the model's bind-pose bounding box is {box}; up is +y (glTF)"
    assert error.startswith("jaxcga cut: error: plane: misses the mesh") and f"bounding box is {box}" in error
    assert not any(tmp_path.iterdir())


def test_a_drill_that_misses_the_mesh_gives_the_bounding_box(tmp_path, capsys):
    box = _box(deform.default_arm().mesh.V)
    assert (
        _exit(
            [
                "drill",
                "--tip",
                "3",
                "3",
                "3",
                "--base",
                "3",
                "3",
                "4",
                "--radius",
                "0.01",
                "--out",
                str(tmp_path / "d.glb"),
            ]
        )
        == 2
    )
    error = capsys.readouterr().err.splitlines()[-1]
    assert "misses the mesh" in error and f"bounding box is {box}; up is +y" in error


def test_animate_refuses_frames_that_would_not_fit_in_memory_before_allocating(tmp_path, capsys, monkeypatch):
    def refuse(*args, **kwargs):
        raise AssertionError("sampled frames although they would not fit")

    monkeypatch.setattr(deform, "sample_pose", refuse)
    monkeypatch.setattr(deform, "sample_keyframes", refuse)
    monkeypatch.setattr(animate, "available_memory", lambda: 2**30)
    bones = deform.default_arm().skeleton.num_bones
    fit = 2**30 // (bones * animate.BYTES_PER_BONE_FRAME)
    assert _exit(["animate", "--frames", "10000000", "--out", str(tmp_path / "a.glb")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"jaxcga animate: error: frames: 10000000 frames of {bones} bones need about ")
    assert "than the 1.0 GiB of memory available now" in err and f"at most --frames {fit}" in err
    assert not any(tmp_path.iterdir())
    animate.check_memory(fit, bones)  # the largest request that fits passes
    with pytest.raises(ValueError, match="frames: "):
        animate.check_memory(fit + 1, bones)


def test_animate_refuses_a_request_larger_than_this_machines_memory(tmp_path, capsys):
    assert animate.available_memory() > 0
    assert _exit(["animate", "--frames", str(10**13), "--out", str(tmp_path / "a.glb")]) == 2
    assert "of memory available now" in capsys.readouterr().err


def test_ctrl_c_is_one_line_and_exit_130(monkeypatch, capsys, tmp_path):
    module = command_module("skin")

    def interrupted(args):
        raise KeyboardInterrupt

    monkeypatch.setattr(module, "run", interrupted)
    with pytest.raises(SystemExit) as exit_:
        main(
            [
                "skin",
                str(Path(__file__).resolve().parents[1] / "data" / "CesiumMan.glb"),
                "--out",
                str(tmp_path / "a.obj"),
            ]
        )
    assert exit_.value.code == 130
    err = capsys.readouterr().err
    assert err == "jaxcga skin: interrupted; its outputs were left as they were\n"
    assert not (tmp_path / "a.obj").exists()
