"""``jaxcga view``: the page of its inputs (the same as ``deform.view``'s), its summary line, --force, and bad input
on one line naming the file."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest

import deform
from jaxcga_cli.main import main
from tests.shared import given, read_gltf, tube

DATA = Path(__file__).resolve().parents[1] / "data"


def test_view_writes_the_page_of_its_inputs(tmp_path, capsys):
    V, F, _, _ = tube(0.3)
    frames = np.stack([V * (1 + 0.1 * k) for k in range(3)])
    np.save(tmp_path / "frames.npy", frames)
    np.save(tmp_path / "mesh_V.npy", V)
    import trimesh

    trimesh.Trimesh(V, F, process=False).export(tmp_path / "tube.obj")
    out = tmp_path / "view.html"
    argv = ["view", str(DATA / "RiggedSimple.glb"), str(tmp_path / "frames.npy"), "--mesh", str(tmp_path / "tube.obj")]
    assert main([*argv, "--fps", "12", "--title", "two", "--joint", "1", "--out", str(out)]) == 0
    summary = capsys.readouterr().out
    assert summary.startswith("jaxcga view two: meshes 2, vertices ") and f"out {out}" in summary
    page = deform.view(DATA / "RiggedSimple.glb", tmp_path / "frames.npy", mesh=tmp_path / "tube.obj", fps=12,
                       title="two", joint=1)  # fmt: skip
    assert out.read_text() == page.html

    out.write_text("previous")
    with pytest.raises(SystemExit) as stop:
        main([*argv, "--out", str(out)])
    assert stop.value.code == 2 and "give --force to replace it" in capsys.readouterr().err
    assert out.read_text() == "previous"
    assert main([*argv, "--force", "--out", str(out)]) == 0
    assert out.read_text() != "previous"


def test_a_file_the_viewer_cannot_show_is_one_line_naming_it(tmp_path, capsys):
    truncated = tmp_path / "cut.glb"
    truncated.write_bytes((DATA / "CesiumMan.glb").read_bytes()[:3000])
    with pytest.raises(SystemExit) as stop:
        main(["view", str(truncated), "--out", str(tmp_path / "view.html")])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.splitlines()[-1].startswith("jaxcga view: error: ")
    assert f"{truncated}: truncated" in err and not (tmp_path / "view.html").exists()


def _nan_position_glb(path: Path) -> Path:
    """RiggedSimple.glb with its first vertex's x a NaN (the binary chunk edited in place)."""
    gltf = read_gltf(DATA / "RiggedSimple.glb")
    blob = bytearray(given(gltf.binary_blob()))
    accessor = gltf.accessors[given(gltf.meshes[0].primitives[0].attributes.POSITION)]
    start = (gltf.bufferViews[given(accessor.bufferView)].byteOffset or 0) + (accessor.byteOffset or 0)
    blob[start : start + 4] = np.float32(np.nan).tobytes()
    gltf.set_binary_blob(bytes(blob))
    gltf.save(str(path))
    return path


def _gltf_without_its_bin(path: Path) -> Path:
    """RiggedSimple as a .gltf whose buffer is a file beside it that does not exist (returned)."""
    import json

    import pygltflib

    gltf = read_gltf(DATA / "RiggedSimple.glb")
    gltf.convert_buffers(pygltflib.BufferFormat.DATAURI)  # in memory: BINFILE would write beside the .glb
    document = json.loads(gltf.gltf_to_json())
    document["buffers"][0]["uri"] = f"{path.stem}.bin"
    path.write_text(json.dumps(document))
    return path.with_suffix(".bin")


def test_a_gltf_the_page_would_show_empty_is_refused_before_embedding(tmp_path, capsys):
    # NaN positions and a missing buffer file: three.js would draw nothing; deform.load_model refuses both
    import deform

    nan = _nan_position_glb(tmp_path / "nan.glb")
    missing = _gltf_without_its_bin(tmp_path / "nobin.gltf")
    for path, message in (
        (nan, f"{nan}: accessor 3 (mesh 0 primitive 0 POSITION) holds 1 non-finite values (NaN or infinity)"),
        (tmp_path / "nobin.gltf", f"{tmp_path / 'nobin.gltf'}: buffer 0 refers to {missing.name!r}, no such file"),
    ):
        with pytest.raises((ValueError, FileNotFoundError)):
            deform.load_model(path)
        with pytest.raises(SystemExit) as stop:
            main(["view", str(path), "--out", str(tmp_path / "view.html")])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.splitlines()[-1].startswith("jaxcga view: error: INPUT 1: ")
        assert message in err
        assert not (tmp_path / "view.html").exists()


def test_the_frame_rate_and_the_page_size_are_bounded(tmp_path, capsys):
    from jaxcga_cli.view import MAX_FPS

    out = tmp_path / "view.html"
    with pytest.raises(SystemExit) as stop:
        main(["view", str(DATA / "RiggedSimple.glb"), "--fps", "1e9", "--out", str(out)])
    assert stop.value.code == 2 and f"fps: expected a frame rate in (0, {MAX_FPS:g}]" in capsys.readouterr().err
    # CesiumMan's page is about 1.2 MB: above a limit of 0.5 it is refused, below the default it is written
    with pytest.raises(SystemExit) as stop:
        main(["view", str(DATA / "CesiumMan.glb"), "--max-megabytes", "0.5", "--out", str(out)])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and re.search(
        r"max_megabytes: the page would be [\d.]+ MB, more than --max-megabytes 0.5", err
    )
    assert not out.exists()
    assert main(["view", str(DATA / "CesiumMan.glb"), "--out", str(out)]) == 0
    shown = float(capsys.readouterr().out.split("megabytes ")[1].split(",")[0])
    assert 0.5 < shown == pytest.approx(out.stat().st_size / 2**20, abs=0.01)


def test_a_truncated_npy_is_told_as_truncated(tmp_path, capsys):
    V, F, _, _ = tube(0.3)
    import trimesh

    trimesh.Trimesh(V, F, process=False).export(tmp_path / "tube.obj")
    np.save(tmp_path / "frames.npy", np.stack([V, V]))
    whole = (tmp_path / "frames.npy").read_bytes()
    (tmp_path / "frames.npy").write_bytes(whole[:200])
    with pytest.raises(SystemExit) as stop:
        main(
            [
                "view",
                str(tmp_path / "frames.npy"),
                "--mesh",
                str(tmp_path / "tube.obj"),
                "--out",
                str(tmp_path / "v.html"),
            ]
        )
    err = capsys.readouterr().err
    assert stop.value.code == 2
    told = (
        f"is truncated: 200 of the {len(whole)} bytes its header states for a float64 array of shape (2, {len(V)}, 3)"
    )
    assert f"frames.npy {told}" in err
