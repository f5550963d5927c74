"""``jaxcga animate-batch``: one process against ``deform.skin_model`` of each model, two local processes on the
CPU (``jax.distributed``) against one process with as many devices, bitwise, and its bad input."""

from __future__ import annotations

import json
import os
import signal
import socket
import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

import deform
from jaxcga_cli.animate_batch import file_names
from jaxcga_cli.main import main

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / "tests" / "data"
MODELS = [str(DATA / "RiggedSimple.glb"), str(DATA / "Arm5.glb"), str(DATA / "RiggedSimple.glb")]
FILES = ["RiggedSimple.npy", "Arm5.npy", "RiggedSimple-2.npy"]


def _outputs(folder: Path) -> dict[str, np.ndarray]:
    return {p.name: np.load(p) for p in sorted(folder.glob("*.npy"))}


@pytest.mark.slow
def test_one_process_writes_each_models_frames_as_skin_model_gives_them(tmp_path):
    out = tmp_path / "batch"
    argv = ["animate-batch", *MODELS, "--frames", "3", "--method", "dqs", "--out", str(out)]
    assert main(argv) == 0
    manifest = json.loads((out / "batch.json").read_text())
    assert [m["file"] for m in manifest["models"]] == FILES
    assert sorted(p.name for p in out.iterdir()) == sorted([*FILES, "batch.json"])
    assert manifest["frames"] == 3 and manifest["processes"] == 1 and manifest["method"] == "dqs"
    assert manifest["padding"] >= 1.0 and manifest["capacities"]["blocks"] == manifest["mesh"]["models"]
    written = _outputs(out)
    for entry, path in zip(manifest["models"], MODELS, strict=True):
        model = deform.load_model(path)
        positions = written[entry["file"]]
        assert positions.dtype == np.float64 and positions.shape == (3, model.mesh.num_vertices, 3)
        assert entry["process"] == 0 and entry["shape"] == list(positions.shape)
        if model.clips:
            clip = model.clips[0]
            assert (entry["clip"], entry["start"], entry["end"]) == (clip.name, clip.start, clip.end)
        else:  # Arm5 has no clip: posed at rest
            assert (entry["clip"], entry["start"], entry["end"]) == (None, 0.0, 0.0)
        times = np.linspace(entry["start"], entry["end"], 3)
        expected = jax.vmap(lambda t, model=model: deform.skin_model(model, t, "dqs"))(times)
        np.testing.assert_allclose(positions, expected, rtol=0, atol=1e-12)

    # a second run into the same folder is refused; with --force its files replace this run's, others stay
    (out / "notes.txt").write_text("mine")
    with pytest.raises(SystemExit) as refused:
        main(argv)
    assert refused.value.code == 2
    np.save(out / FILES[0], np.zeros(1))
    assert main([*argv, "--force"]) == 0
    assert (out / "notes.txt").read_text() == "mine"
    again = _outputs(out)
    assert all(np.array_equal(again[f], written[f]) for f in FILES)


def test_file_names_are_the_stems_made_unique_in_any_case():
    assert file_names(["a/x.glb", "b/x.gltf", "X.fbx", "x-2.glb"]) == ["x.npy", "x-2.npy", "X-3.npy", "x-2-2.npy"]
    assert file_names([]) == ["default_arm.npy"]


# --- several processes ----------------------------------------------------------------------------------------


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _environment(devices: int) -> dict[str, str]:
    # proxies can make jax.distributed's connection hang; the JAX_ variables of the caller would leak in
    env = {k: v for k, v in os.environ.items() if not k.lower().endswith("_proxy") and not k.startswith("JAX_")}
    env.update(PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    env.pop("XLA_FLAGS", None)
    if devices > 1:
        env["XLA_FLAGS"] = f"--xla_force_host_platform_device_count={devices}"
    return env


def _run_processes(commands: list[tuple], timeout: float = 400, check: bool = True) -> tuple[list[int], list[str]]:
    """Run the commands ``(argv, env[, python arguments before argv])`` concurrently (each in its own process
    group, killed on timeout); their exit codes and outputs."""
    processes = [
        subprocess.Popen(
            [sys.executable, *(start[0] if start else ["-m", "jaxcga_cli"]), *argv],
            env=env,
            cwd=ROOT,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            start_new_session=True,
        )
        for argv, env, *start in commands
    ]
    logs = []
    try:
        for process in processes:
            logs.append(process.communicate(timeout=timeout)[0])
    except subprocess.TimeoutExpired:
        for process in processes:
            if process.poll() is None:
                os.killpg(process.pid, signal.SIGKILL)
        pytest.fail("animate-batch processes timed out:\n" + "\n".join(p.communicate()[0] for p in processes))
    for process, log in zip(processes, logs, strict=True):
        assert process.returncode == 0 or not check, log
    return [p.returncode for p in processes], logs


def _two_processes_against_one(
    tmp_path: Path, models: list[str], devices: int, options: list[str], shared_folder: bool = True
) -> None:
    """One process with 2 * ``devices`` devices and two with ``devices`` each (process 0 told by options,
    process 1 by the environment variables) write the same files, bitwise; without ``shared_folder`` each
    process writes into its own folder (machines without a shared file system)."""
    one, two = tmp_path / "one", tmp_path / "two"
    second = two if shared_folder else tmp_path / "two_second"
    coordinator = f"127.0.0.1:{_free_port()}"
    argv = ["animate-batch", *models, "--frames", "2", *options, "--out"]
    by_options = [*argv, str(two), "--coordinator", coordinator, "--num-processes", "2", "--process-id", "0"]
    by_environment = _environment(devices) | {
        "JAX_COORDINATOR_ADDRESS": coordinator,
        "JAX_NUM_PROCESSES": "2",
        "JAX_PROCESS_ID": "1",
    }
    _, logs = _run_processes(
        [
            ([*argv, str(one)], _environment(2 * devices)),
            (by_options, _environment(devices)),
            ([*argv, str(second)], by_environment),
        ]
    )
    reference, shared = _outputs(one), _outputs(two) | _outputs(second)
    assert sorted(shared) == sorted(file_names(models))
    assert not (second / "batch.json").exists() or shared_folder
    assert sorted(reference) == sorted(shared)
    for name in reference:
        np.testing.assert_array_equal(reference[name].view(np.uint64), shared[name].view(np.uint64), err_msg=name)
    manifest, alone = (json.loads((d / "batch.json").read_text()) for d in (two, one))
    assert manifest["processes"] == 2 and alone["processes"] == 1
    assert manifest["mesh"] == alone["mesh"] and manifest["capacities"] == alone["capacities"]
    writers = {m["file"]: m["process"] for m in manifest["models"]}
    assert set(writers.values()) == {0, 1}  # each process wrote its share ...
    for process in (0, 1):  # ... and says so
        mine = sorted(f for f, p in writers.items() if p == process)
        assert f"process {process} of 2" in logs[1 + process] and f"wrote {len(mine)} files" in logs[1 + process]
        assert sorted(p.name for p in (two if process == 0 else second).glob("*.npy")) == (
            mine if not shared_folder else sorted(writers)
        )


@pytest.mark.slow
def test_two_processes_write_exactly_what_one_process_with_their_devices_writes(tmp_path):
    _two_processes_against_one(tmp_path, MODELS, 1, [])


@pytest.mark.slow
def test_two_processes_of_two_devices_split_models_and_frames_into_their_own_folders(tmp_path):
    models = [str(DATA / "CesiumMan.glb"), *MODELS]
    _two_processes_against_one(tmp_path, models, 2, ["--time-shards", "2"], shared_folder=False)


# the command with a file-size limit of 1000 bytes (Python ignores SIGXFSZ: a larger write raises)
FILE_SIZE_LIMITED = [
    "-c",
    "import resource, runpy; resource.setrlimit(resource.RLIMIT_FSIZE, (1000, 1000)); "
    "runpy.run_module('jaxcga_cli', run_name='__main__')",
]


@pytest.mark.slow
def test_a_process_that_fails_to_write_stops_every_process_and_nothing_is_written(tmp_path):
    out = tmp_path / "out"
    coordinator = ["--coordinator", f"127.0.0.1:{_free_port()}", "--num-processes", "2"]
    argv = ["animate-batch", *MODELS, "--frames", "2", "--out", str(out), *coordinator, "--process-id"]
    codes, logs = _run_processes(
        [([*argv, "0"], _environment(1)), ([*argv, "1"], _environment(1), FILE_SIZE_LIMITED)], check=False
    )
    assert codes == [2, 2], logs
    assert "error: process 1 failed to write its files; this process wrote nothing" in logs[0], logs[0]
    assert "the run's files were not written, the folder is as before" in logs[1], logs[1]
    assert not out.exists() or not any(out.iterdir())  # (removed by the process that made it, if last)


# --- bad input ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "options, message",
    [
        (["--frames", "0"], "frames: expected --frames >= 1"),
        (["--time-shards", "0"], "time_shards: expected --time-shards >= 1"),
        (["--frames", "5", "--time-shards", "2"], "time_shards: --frames 5 do not split"),
        (
            ["--frames", "3", "--time-shards", "3"],
            "time_shards: --time-shards 3 does not divide every process's device",
        ),
        (["--num-processes", "2", "--process-id", "2"], "process_id: --process-id 2 is out of range"),
        (["--num-processes", "0"], "num_processes: expected --num-processes >= 1, got --num-processes 0"),
        (["--num-processes", "2"], "coordinator: --num-processes 2 needs --coordinator"),
        (["--process-id", "1"], "coordinator: --process-id 1 needs --coordinator"),
    ],
)
def test_bad_options_are_refused_naming_the_option(tmp_path, capsys, monkeypatch, options, message):
    for variable in ("JAX_COORDINATOR_ADDRESS", "JAX_NUM_PROCESSES", "JAX_PROCESS_ID"):
        monkeypatch.delenv(variable, raising=False)
    with pytest.raises(SystemExit) as refused:
        main(["animate-batch", MODELS[0], *options, "--out", str(tmp_path / "out")])
    assert refused.value.code == 2
    assert f"jaxcga animate-batch: error: {message}" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_environment_variables_are_read_and_checked(tmp_path, capsys, monkeypatch):
    monkeypatch.delenv("JAX_COORDINATOR_ADDRESS", raising=False)
    monkeypatch.setenv("JAX_NUM_PROCESSES", "two")
    with pytest.raises(SystemExit):
        main(["animate-batch", MODELS[0], "--out", str(tmp_path / "out")])
    assert "num_processes: $JAX_NUM_PROCESSES = 'two' is not an integer" in capsys.readouterr().err
    monkeypatch.setenv("JAX_NUM_PROCESSES", "3")
    monkeypatch.setenv("JAX_PROCESS_ID", "3")
    with pytest.raises(SystemExit):
        main(["animate-batch", MODELS[0], "--out", str(tmp_path / "out")])
    assert (
        "process_id: $JAX_PROCESS_ID = 3 is out of range (expected 0 to 2 for $JAX_NUM_PROCESSES = 3)"
        in capsys.readouterr().err
    )


def test_a_missing_model_is_refused_before_any_work(tmp_path, capsys):
    with pytest.raises(SystemExit) as refused:
        main(["animate-batch", MODELS[0], str(tmp_path / "missing.glb"), "--out", str(tmp_path / "out")])
    assert refused.value.code == 2
    assert f"error: model: no such file {tmp_path / 'missing.glb'}" in capsys.readouterr().err


def test_missing_distributed_values_name_their_options(tmp_path):
    env = {k: v for k, v in _environment(1).items() if not k.startswith(("SLURM_", "OMPI_", "KUBERNETES_"))}
    for options, message in (
        (["--distributed"], "coordinator: not given and no cluster detected by jax.distributed; give --coordinator"),
        (["--coordinator", "127.0.0.1:1"], "num_processes: not given and no cluster detected by jax.distributed"),
    ):
        done = subprocess.run(
            [sys.executable, "-m", "jaxcga_cli", "animate-batch", MODELS[0], *options, "--out", str(tmp_path / "o")],
            env=env,
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
        )
        assert done.returncode == 2 and f"jaxcga animate-batch: error: {message}" in done.stderr, done.stderr


@pytest.mark.parametrize("process", [0, 1])
def test_a_missing_peer_is_a_status_line_then_one_error_line_at_the_timeout(tmp_path, process):
    # 2 processes, only one started: jax.distributed alone would wait 300 s, then abort natively (a C++ stack)
    address = f"127.0.0.1:{_free_port()}"
    argv = ["animate-batch", MODELS[0], "--coordinator", address, "--num-processes", "2", "--process-id"]
    codes, logs = _run_processes(
        [([*argv, str(process), "--timeout", "2", "--out", str(tmp_path / "out")], _environment(1))],
        timeout=120,
        check=False,
    )
    lines = logs[0].splitlines()
    assert codes == [2], logs[0]
    assert lines == [
        f"jaxcga animate-batch: process {process} of 2: waiting for 1 more process at {address} (at most 2 s, "
        "--timeout)",
        f"jaxcga animate-batch: error: coordinator: process {process} of 2: still waiting for 1 more process at "
        f"{address} after 2 s (--timeout); start every process with the same --coordinator and --num-processes "
        "and its own --process-id",
    ], logs[0]
    assert not (tmp_path / "out").exists()


def test_a_request_that_would_not_fit_in_memory_is_refused_before_skinning(tmp_path, capsys, monkeypatch):
    from jaxcga_cli import animate, animate_batch

    def refuse(*args, **kwargs):
        raise AssertionError("skinned although the frames would not fit")

    monkeypatch.setattr(deform, "skin_packed", refuse)
    monkeypatch.setattr(animate, "available_memory", lambda: 2**30)
    packed = deform.pack_models([deform.load_model(p) for p in MODELS], blocks=1)
    slots = packed.capacities.vertices
    fit = 2**30 // (slots * animate_batch.BYTES_PER_SLOT_FRAME)
    with pytest.raises(SystemExit) as refused:
        main(["animate-batch", *MODELS, "--frames", str(fit + 1), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert refused.value.code == 2
    assert f"error: frames: {fit + 1} frames of 1 block of {slots} vertex slots need about " in err
    assert f"than the 1.0 GiB of memory available now; give at most --frames {fit}" in err
    assert not (tmp_path / "out").exists()
    animate_batch.check_memory(fit, 1, slots)  # the largest request that fits passes


def test_timeout_must_be_positive(tmp_path, capsys):
    with pytest.raises(SystemExit) as refused:
        main(["animate-batch", MODELS[0], "--timeout", "0", "--out", str(tmp_path / "out")])
    assert (
        refused.value.code == 2 and "timeout: expected --timeout in (0, 1e6) seconds, got 0" in capsys.readouterr().err
    )
