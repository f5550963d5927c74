"""Output that survives failure (``_jaxcga_shared.output`` and every command's writer): a failed write (a full
disk, made with a file-size limit) leaves the previous files as they were; every path problem is found before any
loading or computing and reported on one line with exit code 2; outputs never overwrite an input, each other, or
an unrelated .bin; fem / xfem folders hold one run."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import deform
from _jaxcga_shared.output import replacing, write_json
from jaxcga_cli.main import main
from tests.shared import TESTS_JAX_CACHE_VARIABLES

DATA = Path(__file__).resolve().parents[1] / "data"
ROOT = Path(__file__).resolve().parents[2]

# Every command with the smallest arguments that reach its output; "OUT" is replaced by the output path.
COMMANDS = {
    "skin": ["skin", "--out", "OUT.npy"],
    "animate": ["animate", "--out", "OUT.glb"],
    "animate-batch": ["animate-batch", "--frames", "2", "--out", "OUT"],
    "fit": ["fit", "--target", str(DATA / "RiggedSimple.glb"), "--out", "OUT.json"],
    "cut": ["cut", "--plane", "1", "0", "0", "0.3", "--out", "OUT.glb", "OUT_other.glb"],
    "tear": [
        "tear",
        "--scalpel",
        *"0.2 0 0.1 0.2 0 0".split(),
        "--scalpel",
        *"0.3 0 0.1 0.3 0 0".split(),
        "--out",
        "OUT.glb",
    ],
    "drill": ["drill", "--tip", "0.4", "0", "0", "--base", "0.4", "0", "0.1", "--radius", "0.015", "--out", "OUT.glb"],
    "deform": ["deform", "ffd", "--out", "OUT.png"],
    "arap": ["arap", "--out", "OUT.npy"],
    "fem": ["fem", "bar", "--steps", "1", "--out", "OUT"],
    "xfem": ["xfem", "cheese", "--size", "small", "--steps", "1", "--out", "OUT"],
    "demo": ["demo", "--out", "OUT"],
    "view": ["view", str(DATA / "RiggedSimple.glb"), "--out", "OUT.html"],
}


def _argv(command: str, out: Path) -> list[str]:
    return [a.replace("OUT", str(out)) if a.startswith("OUT") else a for a in COMMANDS[command]]


def _fails_on_one_line(capsys, argv: list[str], *needles: str) -> str:
    with pytest.raises(SystemExit) as stop:
        main(argv)
    err = capsys.readouterr().err
    assert stop.value.code == 2, err
    assert _one_line_error(err, argv[0]), err
    for needle in needles:
        assert needle in err, err
    return err


def _one_line_error(err: str, command: str) -> bool:
    """``err`` (stderr) ends with one error line, after status lines only: no traceback."""
    lines = err.splitlines()
    return (
        err.endswith("\n")
        and lines[-1].startswith(f"jaxcga {command}: error: ")
        and all(line.startswith(f"jaxcga {command}: ") and ": error: " not in line for line in lines[:-1])
    )


def _snapshot(folder: Path) -> dict[str, bytes]:
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.fixture
def no_work(monkeypatch):
    """Loading and computing raise: a test with it checks that paths are refused before any of that."""

    def refuse(*args, **kwargs):
        raise AssertionError("loaded or computed before the paths were checked")

    import xfem
    from jaxcga_cli import fem, models

    for module, name in (
        (models, "load_model"),
        (deform, "fit_pose"),
        (models, "load_mesh"),
        (fem, "scene_mesh"),
        (xfem, "scene"),
    ):
        monkeypatch.setattr(module, name, refuse)


# ------------------------------------------------------------------------------ the atomic writer itself


def test_replacing_keeps_the_old_file_when_the_writer_fails(tmp_path):
    target = tmp_path / "out.npy"
    target.write_bytes(b"previous")
    os.chmod(target, 0o640)
    with pytest.raises(RuntimeError, match="half-way"), replacing(target) as (temp,):
        assert temp.parent == tmp_path and temp.suffix == ".npy" and temp != target
        temp.write_bytes(b"partial")
        raise RuntimeError("the writer stopped half-way")
    assert target.read_bytes() == b"previous" and sorted(tmp_path.iterdir()) == [target]
    with replacing(target) as (temp,):
        np.save(temp, np.arange(3.0))
    np.testing.assert_array_equal(np.load(target), np.arange(3.0))
    assert stat.S_IMODE(target.stat().st_mode) == 0o640 and sorted(tmp_path.iterdir()) == [target]


def test_write_json_refuses_non_finite_numbers(tmp_path):
    with pytest.raises(ValueError, match="non-finite"):
        write_json(tmp_path / "x.json", {"error": float("nan")})
    assert not any(tmp_path.iterdir())


# ------------------------------------------------------------------------------ a full disk


_LIMITED = """
import contextlib, io, json, resource, signal, sys
from jaxcga_cli.main import main
import deform

signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG, as on a full disk
hard = resource.getrlimit(resource.RLIMIT_FSIZE)[1]
results = []
for limit, argv in json.loads(sys.argv[1]):
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        try:
            if argv[0] == "save_model":
                deform.save_model(deform.load_model(argv[1]), argv[2])
                code = 0
            else:
                code = main(argv)
        except SystemExit as stop:
            code = stop.code
        except OSError as error:
            code, err = "OSError", io.StringIO(str(error))
    resource.setrlimit(resource.RLIMIT_FSIZE, (hard, hard))
    results.append([code, err.getvalue()])
print(json.dumps(results))
"""


@pytest.fixture(scope="module")
def disk_full(tmp_path_factory):
    """Three writes that hit a file-size limit over previous outputs, in one subprocess: a cut whose first half
    fits and second does not; a .gltf whose JSON fits and .bin does not (the library's save_model); a fem run
    whose first frame does not fit, into the folder of an earlier run with --force."""
    import cutting

    folder = tmp_path_factory.mktemp("disk_full")
    sizing = tmp_path_factory.mktemp("sizes")
    arm = deform.default_arm()
    plane = [1.0, 0.0, 0.0, 0.45]
    halves = cutting.cut(arm.mesh, cutting.Plane(plane[:3], plane[3]))
    sizes = []
    for k, half in enumerate(halves):
        deform.save_model(deform.RiggedModel(half, arm.skeleton, arm.clips), sizing / f"{k}.glb")
        sizes.append((sizing / f"{k}.glb").stat().st_size)
    assert sizes[0] < 0.9 * sizes[1]  # the positive half fits under the limit, the negative one does not
    cut_limit = (sizes[0] + sizes[1]) // 2
    for name in ("pos.glb", "neg.glb"):  # the previous outputs: valid models
        (folder / name).write_bytes((DATA / "RiggedSimple.glb").read_bytes())
    deform.save_model(deform.load_model(DATA / "RiggedSimple.glb"), sizing / "model.gltf")
    gltf_sizes = [(sizing / name).stat().st_size for name in ("model.gltf", "model.bin")]
    assert gltf_sizes[0] < 0.9 * gltf_sizes[1]  # the JSON (written first) fits under the limit, the buffer does not
    gltf_limit = sum(gltf_sizes) // 2
    deform.save_model(deform.load_model(DATA / "PlaneWith3Bones.glb"), folder / "model.gltf")  # the previous one
    run = folder / "run"
    run.mkdir()
    for name in ("frame_0000.vtu", "frame_0010.vtu", "summary.json", "notes.txt"):
        (run / name).write_text(f"the earlier run's {name}")
    before = _snapshot(folder)
    probes = [
        [cut_limit, ["cut", "--plane", *map(str, plane), "--out", str(folder / "pos.glb"), str(folder / "neg.glb")]],
        [gltf_limit, ["save_model", str(DATA / "RiggedSimple.glb"), str(folder / "model.gltf")]],
        [4096, ["fem", "bar", "--steps", "2", "--no-figures", "--force", "--out", str(run)]],
    ]
    # without the tests' compilation cache: under the size limit JAX would leave truncated entries in it
    env = {k: v for k, v in os.environ.items() if k not in TESTS_JAX_CACHE_VARIABLES}
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")])
    done = subprocess.run(
        [sys.executable, "-c", _LIMITED, json.dumps(probes)],
        capture_output=True,
        text=True,
        cwd=folder,
        env=env,
        timeout=600,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    return folder, before, json.loads(done.stdout.splitlines()[-1])


@pytest.mark.slow
def test_disk_full_leaves_both_halves_of_a_cut_as_they_were(disk_full):
    folder, before, (cut_result, _, _) = disk_full
    code, err = cut_result
    assert code == 2 and _one_line_error(err, "cut") and "File too large" in err and "left as before" in err
    for name in ("pos.glb", "neg.glb"):  # the positive half was written, but not renamed: the negative one failed
        assert (folder / name).read_bytes() == before[name]
        deform.load_model(folder / name)


def test_disk_full_leaves_a_gltf_and_its_bin_as_they_were(disk_full):
    folder, before, (_, gltf_result, _) = disk_full
    assert gltf_result[0] == "OSError" and "File too large" in gltf_result[1]
    assert (folder / "model.gltf").read_bytes() == before["model.gltf"]
    assert (folder / "model.bin").read_bytes() == before["model.bin"]
    assert deform.load_model(folder / "model.gltf").mesh.num_vertices > 0


def test_disk_full_leaves_the_previous_fem_run_as_it_was(disk_full):
    folder, before, (_, _, fem_result) = disk_full
    code, err = fem_result
    assert code == 2 and _one_line_error(err, "fem") and "File too large" in err
    after = _snapshot(folder)
    assert after == before  # every file, including the earlier run's frames; no temporary file is left
    assert sorted(p.name for p in folder.iterdir()) == ["model.bin", "model.gltf", "neg.glb", "pos.glb", "run"]
    assert sorted(p.name for p in (folder / "run").iterdir()) == sorted(
        ["frame_0000.vtu", "frame_0010.vtu", "summary.json", "notes.txt"]
    )


# ------------------------------------------------------------------------------ paths checked before any work


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_folder_in_the_way_is_one_line(tmp_path, capsys, no_work, command):
    (tmp_path / "out.npy").mkdir()  # a folder with the name of the output file
    argv = _argv(command, tmp_path / "out")
    if command in ("fem", "xfem", "demo", "animate-batch"):
        (tmp_path / "out").write_text("a file")  # these write a folder: a file is in the way
        _fails_on_one_line(capsys, argv, "is a file; expected a folder")
        return
    for suffix in (".glb", ".png", ".json", ".html"):
        (tmp_path / f"out{suffix}").mkdir()
    _fails_on_one_line(capsys, argv, "is a folder")


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_file_where_a_folder_is_expected_is_one_line(tmp_path, capsys, no_work, command):
    (tmp_path / "plain").write_text("a file, not a folder")
    _fails_on_one_line(capsys, _argv(command, tmp_path / "plain" / "sub" / "out"), "is a file, not a folder")


@pytest.mark.parametrize("command", ["skin", "cut", "fem", "demo"])
def test_a_write_protected_folder_or_file_is_one_line(tmp_path, capsys, no_work, command):
    """A folder or file without write permission bits is refused for every user, root included (root could
    write there, as it could remove a write-protected file; neither happens without asking)."""
    locked = tmp_path / "locked"
    locked.mkdir()
    os.chmod(locked, 0o555)
    try:
        _fails_on_one_line(capsys, _argv(command, locked / "out"), "cannot write in the folder", str(locked))
    finally:
        os.chmod(locked, 0o755)
    if command in ("fem", "demo"):
        return
    previous = tmp_path / ("out.npy" if command == "skin" else "out.glb")
    previous.write_bytes(b"keep me")
    os.chmod(previous, 0o444)
    _fails_on_one_line(capsys, _argv(command, tmp_path / "out"), "write-protected")
    assert previous.read_bytes() == b"keep me"


def test_fit_checks_its_output_before_loading_and_optimizing(tmp_path, capsys, no_work):
    (tmp_path / "pose.json").mkdir()
    target = tmp_path / "target.npy"
    np.save(target, np.zeros((3, 3)))
    _fails_on_one_line(capsys, ["fit", "--target", str(target), "--out", str(tmp_path / "pose.json")], "is a folder")
    _fails_on_one_line(
        capsys,
        ["fit", "--target", str(tmp_path / "missing.npy"), "--out", str(tmp_path / "p.json")],
        "target: no such file",
    )
    _fails_on_one_line(
        capsys, ["fit", "--target", str(target), "--out", str(tmp_path / "pose.txt")], "expected a .json file"
    )


# ------------------------------------------------------------------------------ outputs that clobber each other


def test_identical_outputs_and_an_output_that_is_the_input_are_refused(tmp_path, capsys, no_work):
    same = tmp_path / "same.glb"
    _fails_on_one_line(
        capsys,
        ["cut", "--plane", "1", "0", "0", "0.3", "--out", str(same), str(same)],
        "same file as the output out (positive half)",
    )
    _fails_on_one_line(
        capsys,
        ["cut", "--plane", "1", "0", "0", "0.3", "--out", str(same), str(tmp_path / "." / "same.glb")],
        "same file",
    )
    model = tmp_path / "model.glb"
    model.write_bytes((DATA / "RiggedSimple.glb").read_bytes())
    for argv in (
        ["tear", str(model), *COMMANDS["tear"][1:-1], str(model)],
        ["animate", str(model), "--out", str(model)],
        ["deform", "ffd", str(model), "--out", str(model)],
    ):
        _fails_on_one_line(capsys, argv, "same file as the input")
    assert model.read_bytes() == (DATA / "RiggedSimple.glb").read_bytes()
    # fem --force would remove its own input, a frame of the earlier run in that folder
    run = tmp_path / "run"
    run.mkdir()
    (run / "frame_0000.vtu").write_text("an earlier frame")
    _fails_on_one_line(
        capsys, ["fem", str(run / "frame_0000.vtu"), "--force", "--out", str(run)], "that --force would remove"
    )


def test_an_unrelated_bin_beside_a_gltf_is_not_replaced(tmp_path, capsys, no_work):
    unrelated = tmp_path / "model.bin"
    unrelated.write_bytes(b"someone else's buffer")
    for command in ("animate", "tear", "drill", "cut"):
        argv = [str(tmp_path / "model.gltf") if a == "OUT.glb" else a for a in COMMANDS[command]]
        argv = [str(tmp_path / "other.glb") if a == "OUT_other.glb" else a for a in argv]
        _fails_on_one_line(capsys, argv, "model.bin exists and is not the buffer of")
    assert unrelated.read_bytes() == b"someone else's buffer"


def test_save_model_replaces_its_own_bin_only(tmp_path):
    model = deform.load_model(DATA / "RiggedSimple.glb")
    (tmp_path / "a.bin").write_bytes(b"someone else's buffer")
    with pytest.raises(ValueError, match="a.bin exists and is not the buffer of"):
        deform.save_model(model, tmp_path / "a.gltf")
    assert (tmp_path / "a.bin").read_bytes() == b"someone else's buffer" and not (tmp_path / "a.gltf").exists()
    deform.save_model(model, tmp_path / "b.gltf")
    deform.save_model(model, tmp_path / "b.gltf")  # b.bin is b.gltf's own buffer: both are replaced
    assert deform.load_model(tmp_path / "b.gltf").mesh.num_vertices == model.mesh.num_vertices
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.bin", "b.bin", "b.gltf"]


def test_a_trimesh_gltf_holds_its_buffers(tmp_path):
    """skin / deform / arap write a posed mesh as .gltf through trimesh: one file, no sibling buffer to clobber."""
    import trimesh

    from jaxcga_cli.output import write_result

    for name in ("mesh.bin", "gltf_buffer_0.bin", "gltf_buffer.bin"):
        (tmp_path / name).write_bytes(b"someone else's buffer")
    V = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    F = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    write_result(tmp_path / "mesh.gltf", V, F)
    assert sorted(p.name for p in tmp_path.iterdir()) == [
        "gltf_buffer.bin",
        "gltf_buffer_0.bin",
        "mesh.bin",
        "mesh.gltf",
    ]
    assert all((tmp_path / n).read_bytes() == b"someone else's buffer" for n in ("mesh.bin", "gltf_buffer_0.bin"))
    np.testing.assert_allclose(trimesh.load_mesh(tmp_path / "mesh.gltf", process=False).vertices, V)


# ------------------------------------------------------------------------------ fem / xfem folders hold one run


@pytest.mark.parametrize("command", ["fem", "xfem", "animate-batch"])
def test_a_non_empty_run_folder_needs_force(tmp_path, capsys, no_work, command):
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "frame_0040.png").write_text("another scene's frame")
    _fails_on_one_line(capsys, _argv(command, tmp_path / "out"), "is not empty", "--force")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["frame_0040.png"]


def test_json_errors_are_one_line(tmp_path, capsys):
    handles = tmp_path / "handles.json"
    handles.write_text('{"handles": [[0]], "motors": [')
    _fails_on_one_line(
        capsys,
        ["deform", "handles", "--handles", str(handles), "--out", str(tmp_path / "x.npy")],
        "handles:",
        "not valid JSON",
    )
    handles.write_text('{"handles": [[0]], "motors": [3]}')
    _fails_on_one_line(
        capsys,
        ["deform", "handles", "--handles", str(handles), "--out", str(tmp_path / "x.npy")],
        "motor 0",
        "must be an object",
    )
