"""The ``jaxcga xfem SCENE`` command end to end in-process on the small cheese tetrahedron (XFEM paper sec. 5,
Fig. 6): frames, surfaces and summary written, the summary's figures consistent with the files; a wild surface
(open, self-intersecting, three parts) tetrahedralized, cut and written back in pieces; errors."""

from __future__ import annotations

import json

import meshio
import numpy as np
import pytest
import trimesh

from jaxcga_cli.main import main
from tests.shared import wild_surface


@pytest.mark.slow
def test_cheese_writes_frames_surfaces_and_a_summary(tmp_path, capsys):
    out = tmp_path / "cheese"
    assert main(["xfem", "cheese", "--size", "small", "--steps", "4", "--every", "4", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    # the summary line's step times leave the first frame (compiling) out and show it apart
    assert "jaxcga xfem cheese" in printed and ", first_frame_s " in printed
    # frame 0, the cut frames 1 and 2, frame 4 (every 4 and the last)
    frames = [0, 1, 2, 4]
    assert sorted(p.name for p in out.iterdir()) == sorted(
        [f"frame_{k:04d}.{ext}" for k in frames for ext in ("png", "vtu")] + ["summary.json"]
    )
    summary = json.loads((out / "summary.json").read_text())
    for key in (
        "pieces",
        "dofs",
        "dofs_initial",
        "booleans",
        "boolean_ms",
        "integral_ms",
        "step_avg_s",
        "step_max_s",
        "total_cut_frames_s",
        "total_s",
        "epsilon",
        "cut_frames",
        "frame_pieces",
    ):
        assert key in summary
    assert summary["frames"] == summary["steps"] == 4 and summary["cuts"] == 5 and summary["size"] == "small"
    assert summary["cut_frames"] == [1, 2] and summary["frames_written"] == frames
    assert summary["epsilon"] == 1e-3 and summary["nodes"] == 4 and summary["dofs_initial"] == 12
    assert summary["pieces"] == summary["frame_pieces"][-1] >= 6 and summary["dofs"] == summary["frame_dofs"][-1] > 12
    assert summary["total_s"] == pytest.approx(sum(summary["frame_seconds"]))
    assert summary["step_max_s"] == pytest.approx(max(summary["frame_seconds"]))
    # the surfaces: one piece at the start, every piece at the end; the base stays on the ground, the rest sags
    first, last = meshio.read(out / "frame_0000.vtu"), meshio.read(out / "frame_0004.vtu")
    assert np.unique(first.cell_data["piece"][0]).tolist() == [0]
    assert np.unique(last.cell_data["piece"][0]).tolist() == list(range(summary["pieces"]))
    assert last.points[:, 2].min() == pytest.approx(0.0, abs=1e-12)
    assert 0 < summary["max_displacement"] < 0.1


@pytest.mark.slow
def test_no_figures_writes_surfaces_only(tmp_path):
    out = tmp_path / "plain"
    assert main(["xfem", "cheese", "--size", "small", "--steps", "1", "--no-figures", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["frame_0000.vtu", "frame_0001.vtu", "summary.json"]


@pytest.mark.slow
def test_without_last_cut_drops_the_scenes_last_cut(tmp_path):
    """--without-last-cut: the cheese's last cut (frame 2) is not made; the summary says so."""
    runs = {}
    for flag in ([], ["--without-last-cut"]):
        out = tmp_path / ("without" if flag else "with")
        args = ["xfem", "cheese", "--size", "small", "--steps", "2", "--no-figures", "--out", str(out)]
        assert main(args + flag) == 0
        runs[bool(flag)] = json.loads((out / "summary.json").read_text())
    assert runs[True]["last_cut"] is False and runs[False]["last_cut"] is True
    assert runs[True]["cuts"] == runs[False]["cuts"] - 1 == 4
    assert runs[True]["booleans"] < runs[False]["booleans"]


@pytest.mark.slow
def test_cut_latency_defers_cuts(tmp_path):
    """--cut-latency 2: the cuts of frames 1 and 2 are computed in the background and take effect in frames 3 and
    4; every frame is written, showing the cuts that have taken effect (frames 1 and 2: the uncut body)."""
    out = tmp_path / "latency"
    assert (
        main(
            [
                "xfem",
                "cheese",
                "--size",
                "small",
                "--steps",
                "5",
                "--every",
                "1",
                "--cut-latency",
                "2",
                "--no-figures",
                "--out",
                str(out),
            ]
        )
        == 0
    )
    summary = json.loads((out / "summary.json").read_text())
    assert summary["cut_latency"] == 2 and summary["cuts"] == 5
    assert summary["frame_pieces"][:2] == [1, 1] and summary["frame_pieces"][3] == summary["pieces"] >= 6
    assert summary["frames_written"] == [0, 1, 2, 3, 4, 5]
    for frame, pieces in ((2, 1), (5, summary["pieces"])):
        assert meshio.read(out / f"frame_{frame:04d}.vtu").cell_data["piece"][0].max() + 1 == pieces


@pytest.mark.parametrize(
    "args, message",
    [
        (["mouth"], "SCENE"),
        (["cheese", "--cut-latency", "-1"], "cut_latency"),
        (["cheese", "--steps", "0"], "steps"),
        (["cheese", "--size", "huge"], "size"),
        (["cheese", "--every", "0"], "every"),
    ],
)
def test_bad_arguments_exit_with_a_message(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["xfem", *args, "--out", str(tmp_path / "x")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def _obj_groups(path):
    """(V, F, group of each face) of an OBJ file written with ``g piece_K`` groups."""
    V, F, group, current = [], [], [], -1
    for line in path.read_text().splitlines():
        words = line.split()
        if words[:1] == ["v"]:
            V.append([float(w) for w in words[1:4]])
        elif words[:1] == ["g"]:
            current = int(words[1].removeprefix("piece_"))
        elif words[:1] == ["f"]:
            F.append([int(w) - 1 for w in words[1:4]])
            group.append(current)
    return np.array(V), np.array(F), np.array(group)


@pytest.mark.slow
def test_a_wild_surface_is_cut_and_written_in_pieces(tmp_path, capsys):
    # open, self-intersecting, three parts; the default plane z = 0 cuts the spheres and the cube in halves: the
    # spheres' top (the fixed nodes) stays, their lower half and both halves of the cube fall
    V, F, _, _ = wild_surface()
    path = tmp_path / "wild.obj"
    trimesh.Trimesh(V, F, process=False).export(path)
    out = tmp_path / "wild"
    args = ["xfem", str(path), "--steps", "3", "--every", "3", "--cut-frame", "1", "--edge-length", "0.1"]
    assert main([*args, "--no-figures", "--out", str(out)]) == 0
    assert "min_dihedral_deg" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    assert summary["pieces"] == 4 and summary["cut_frames"] == [1] and summary["frame_pieces"] == [4, 4, 4]
    assert summary["tetrahedralization"]["tets"] > 1000
    Vr, Fr, group = _obj_groups(out / "frame_0000_surface.obj")
    np.testing.assert_allclose(Vr, V, atol=1e-7)  # uncut: the user's surface as it is
    spheres = V[F].mean(axis=1)[:, 0] < 2
    assert np.array_equal(Fr, F) and len(np.unique(group)) == 2  # the cube and the spheres, apart from the start
    assert len(np.unique(group[spheres])) == 1 and len(np.unique(group[~spheres])) == 1
    Vd, Fd, group = _obj_groups(out / "frame_0003_surface.obj")
    assert len(Fd) == len(F) and len(np.unique(group)) == 4
    # every triangle is there once, its corners copies of its own vertices, in pieces by the side of the cut
    centroid = V[F].mean(axis=1)
    below = centroid[:, 2] < 0
    clear = np.abs(centroid[:, 2]) > 0.02  # off the plane by more than its perturbation and the tets' envelope
    for g in np.unique(group).tolist():
        assert len(np.unique(below[clear & (group == g)])) == 1  # a piece lies on one side
    drop = (V[F] - Vd[Fd])[..., 2].mean(axis=1)  # how far each triangle fell
    # cut before the first step, the cube and the spheres' lower half fall freely from rest, unstrained: backward
    # Euler gives x_3 = h^2 g (1 + 2 + 3); the spheres' top hangs from its fixed nodes and sags less
    free_fall = 6 * 0.033**2 * 9.81
    np.testing.assert_allclose(drop[~spheres], free_fall, rtol=1e-4)  # one Newton iteration, iterative solves
    np.testing.assert_allclose(drop[below & clear], free_fall, rtol=1e-3)
    assert drop[spheres & ~below & clear].max() < 0.6 * free_fall


def test_rxfem_method_leaves_out_intersecting_cuts(tmp_path):
    out = tmp_path / "sticks"
    argv = ["xfem", "sticks", "--size", "small", "--steps", "3", "--method", "rxfem", "--no-figures", "--out", str(out)]
    assert main(argv) == 0
    summary = json.loads((out / "summary.json").read_text())
    # the small sticks: 5 vertical cuts in frame 1, 5 horizontal ones crossing them in frame 2 (left out)
    assert summary["method"] == "rxfem" and summary["cuts"] == 5 and summary["cuts_left_out"] == [2] * 5
    assert summary["pieces"] == 6
    with pytest.raises(SystemExit):
        main(["xfem", "sticks", "--method", "rxfem", "--cut-latency", "2", "--out", str(tmp_path / "late")])
