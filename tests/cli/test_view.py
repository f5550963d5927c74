"""``jaxcga view``: the page of its inputs (the same as ``deform.view``'s), its summary line, --force, and bad input
on one line naming the file."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import deform
from jaxcga_cli.main import main
from tests.shared import tube

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
