"""The ``jaxcga fem SCENE`` command end to end in-process: the bar scene's frames, meshes and summary, a
closed surface tetrahedralized, a written frame read back as a tet mesh scene, an open, self-intersecting,
multi-part surface written back as itself and carried by the tets, a corpus character, TetGen named as an extra,
errors."""

from __future__ import annotations

import json
import sys

import meshio
import numpy as np
import pytest
import trimesh

import xfem
from jaxcga_cli.main import main
from tests.shared import CHARACTERS, load_character, wild_surface


@pytest.fixture(scope="module")
def bar_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("fem") / "bar"
    assert main(["fem", "bar", "--steps", "3", "--every", "2", "--out", str(out)]) == 0
    return out


def test_bar_writes_frames_meshes_and_a_summary(bar_run, capsys):
    names = sorted(p.name for p in bar_run.iterdir())
    assert names == [
        "frame_0000.png",
        "frame_0000.vtu",
        "frame_0002.png",
        "frame_0002.vtu",
        "frame_0003.png",
        "frame_0003.vtu",
        "summary.json",
    ]
    summary = json.loads((bar_run / "summary.json").read_text())
    assert summary["steps"] == 3 and summary["nodes"] == 17 * 5 * 5 and summary["elements"] == 6 * 16 * 4 * 4
    assert summary["dofs"] == 3 * (summary["nodes"] - summary["fixed_nodes"]) and summary["fixed_nodes"] == 25
    assert len(summary["kinetic_energy"]) == 3 and all(np.isfinite(summary["potential_energy"]))
    # the paper's single Newton iteration by default: the falling bar's steps stop short of convergence, and say so
    assert summary["newton_iterations_mean"] == 1 and summary["converged_steps"] == 0 and summary["tolerance"] is None
    last = meshio.read(bar_run / "frame_0003.vtu")
    u = last.point_data["displacement"]
    clamped = last.points[:, 0] - u[:, 0] <= 1e-12
    assert np.abs(u[clamped]).max() == 0.0  # the clamped face stays
    assert u[:, 2].min() < -1e-3 and np.abs(u).max() == pytest.approx(summary["max_displacement"])  # it falls
    assert last.cells_dict["tetra"].shape == (summary["elements"], 4)


@pytest.mark.slow
def test_a_surface_and_a_written_frame_are_scenes(bar_run, tmp_path, capsys):
    sphere = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1, radius=0.3).export(sphere)
    out = tmp_path / "ball"
    assert main(["fem", str(sphere), "--steps", "2", "--no-figures", "--fix-fraction", "0.2", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["fixed_nodes"] >= 3 and summary["elements"] > 0
    assert not any(p.suffix == ".png" for p in out.iterdir())
    # a frame written by the bar run is a meshio tet mesh: simulate it again, hanging from its top
    out = tmp_path / "again"
    assert main(["fem", str(bar_run / "frame_0000.vtu"), "--steps", "1", "--no-figures", "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["nodes"] == 17 * 5 * 5
    assert "jaxcga fem" in capsys.readouterr().out


def test_force_replaces_the_previous_run_and_nothing_else(tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    for name in ("frame_0000.png", "frame_0000.vtu", "frame_0040.vtu", "summary.json"):  # another scene's run
        (out / name).write_text("an earlier run")
    (out / "notes.txt").write_text("not the run's")
    (out / "frame_0001.vtu.bak").write_text("not the run's either")
    (out / "keep").mkdir()
    assert main(["fem", "bar", "--steps", "1", "--no-figures", "--force", "--out", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == [
        "frame_0000.vtu",
        "frame_0001.vtu",
        "frame_0001.vtu.bak",
        "keep",
        "notes.txt",
        "summary.json",
    ]
    assert (out / "notes.txt").read_text() == "not the run's"
    summary = json.loads((out / "summary.json").read_text())
    assert summary["steps"] == 1 and meshio.read(out / "frame_0001.vtu").points.shape == (summary["nodes"], 3)
    # summary.json is renamed into the folder last: it marks a complete run
    assert (out / "summary.json").stat().st_ctime_ns >= max(
        (out / f"frame_000{k}.vtu").stat().st_ctime_ns for k in (0, 1)
    )


@pytest.mark.parametrize(
    "args, message",
    [
        (["nowhere.msh"], "SCENE"),
        (["bar", "--steps", "0"], "steps"),
        (["bar", "--poisson", "0.5"], "poisson"),
        (["bar", "--dt", "-1"], "dt"),
        (["bar", "--tolerance", "0"], "tolerance"),
    ],
)
def test_bad_arguments_exit_with_a_message(tmp_path, capsys, args, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["fem", *args, "--out", str(tmp_path / "x")])
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err


def test_corrupt_scenes_and_overflowing_gravity_are_named(tmp_path, capsys):
    (tmp_path / "nan.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 nan\nf 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n")
    (tmp_path / "junk.msh").write_text("not a mesh")
    for args, message in (
        (
            ["bar", "--gravity", "0", "0", "-1e308"],
            "gravity: expected three numbers whose product with the density is finite",
        ),
        (
            [str(tmp_path / "nan.obj")],
            f"SCENE: {tmp_path / 'nan.obj'}: line 4: 'v 0 0 nan' is not a vertex of three finite numbers",
        ),
        ([str(tmp_path / "junk.msh")], "SCENE: meshio cannot read"),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(["fem", *args, "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and err.count("\n") == 1 and message in err


@pytest.mark.slow
def test_a_wild_surface_is_simulated_and_written_as_itself(tmp_path, capsys):
    # open, self-intersecting, three parts: fTetWild meshes it, and the user's own surface is what is written
    V, F, _, _ = wild_surface()
    path = tmp_path / "wild.obj"
    trimesh.Trimesh(V, F, process=False).export(path)
    out = tmp_path / "wild"
    args = ["fem", str(path), "--steps", "2", "--every", "1", "--no-figures", "--edge-length", "0.1", "--out", str(out)]
    assert main(args) == 0
    assert "min_dihedral_deg" in capsys.readouterr().out
    summary = json.loads((out / "summary.json").read_text())
    report = summary["tetrahedralization"]
    assert report["mesher"] == "ftetwild" and report["tets"] == summary["elements"] and report["seconds"] > 0
    assert report["surface_vertices"] == len(V) and report["surface_faces"] == len(F)
    assert 0 < report["min_dihedral_deg"] <= report["max_dihedral_deg"] < 180 and 0 < report["min_volume_ratio"] <= 1
    assert report["max_surface_distance"] < 3 * report["epsilon"]
    rest = trimesh.load(out / "frame_0000_surface.obj", process=False)
    assert isinstance(rest, trimesh.Trimesh)
    np.testing.assert_allclose(rest.vertices, V, atol=1e-7)
    assert np.array_equal(rest.faces, F)
    # the written surface is the tets' motion at the embedded vertices
    frame = meshio.read(out / "frame_0002.vtu")
    rest_tets = xfem.tet_mesh(frame.points - frame.point_data["displacement"], frame.cells_dict["tetra"])
    moved = trimesh.load(out / "frame_0002_surface.obj", process=False)
    assert isinstance(moved, trimesh.Trimesh)
    embedding = xfem.embed_points(rest_tets, V)
    expected = np.asarray(embedding.positions(frame.points))
    inside = embedding.distance == 0
    np.testing.assert_allclose(moved.vertices[inside], expected[inside], atol=1e-6)
    # a vertex just outside the tets (fTetWild's envelope) extrapolates its nearest tet; the .vtu's rounded rest
    # positions may pick a neighbouring one, whose extrapolation differs by the distance x the jump in the gradient
    off = np.linalg.norm(moved.vertices - expected, axis=1)[~inside]
    assert np.all(off <= 1e-6 + embedding.distance[~inside])
    assert np.abs(moved.vertices - V).max() > 1e-4  # it fell


@pytest.mark.slow
def test_a_character_runs_and_writes_its_own_skin(tmp_path):
    # jaxcga fem CHARACTER.glb: the bind-pose skin of every part, hanging along -y (glTF's up)
    out = tmp_path / "fox"
    assert main(["fem", str(CHARACTERS["Fox"]), "--steps", "2", "--every", "2", "--no-figures", "--out", str(out)]) == 0
    mesh = load_character("Fox").mesh
    V, F = np.asarray(mesh.V), np.asarray(mesh.F)
    rest = trimesh.load(out / "frame_0000_surface.obj", process=False)
    assert isinstance(rest, trimesh.Trimesh)
    np.testing.assert_allclose(rest.vertices, V, atol=1e-6 * float(np.linalg.norm(np.ptp(V, axis=0))))
    assert np.array_equal(rest.faces, F)
    moved = trimesh.load(out / "frame_0002_surface.obj", process=False)
    assert isinstance(moved, trimesh.Trimesh)
    moved = moved.vertices - V
    assert moved[:, 1].mean() < 0 and np.abs(moved[:, [0, 2]]).mean() < np.abs(moved[:, 1]).mean()  # down y
    report = json.loads((out / "summary.json").read_text())["tetrahedralization"]
    assert report["surface_faces"] == len(F) and report["tets"] > 200


def test_tetgen_is_an_extra_the_command_names(tmp_path, capsys, monkeypatch):
    monkeypatch.setitem(sys.modules, "tetgen", None)
    path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=1).export(path)
    with pytest.raises(SystemExit) as exit_info:
        main(["fem", str(path), "--mesher", "tetgen", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "mesher: tetrahedralize needs TetGen" in err and "jaxcga[tetgen]" in err


def test_newton_0_is_refused_before_the_scene_is_built(tmp_path, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["fem", "bar", "--newton", "0", "--out", str(tmp_path / "x")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2
    assert err == "jaxcga fem: error: newton: expected --newton >= 1 Newton iterations per step, got 0\n"


def test_surfaces_tetgen_cannot_fill_and_surfaces_in_tet_formats_are_told(tmp_path, capsys):
    box = trimesh.creation.box()
    trimesh.Trimesh(box.vertices, box.faces[:-1], process=False).export(tmp_path / "open.obj")
    meshio.write(tmp_path / "surface.vtu", meshio.Mesh(box.vertices, [("triangle", box.faces)]))
    for args, told in (
        (
            [str(tmp_path / "open.obj"), "--mesher", "tetgen"],
            f"SCENE: {tmp_path / 'open.obj'} is an open surface (3 edges lie on its border, each in one triangle "
            "only); TetGen fills closed surfaces only: give --mesher ftetwild (the default), which takes open ones",
        ),
        (
            [str(tmp_path / "surface.vtu")],
            f"SCENE: {tmp_path / 'surface.vtu'} holds a surface (triangle cells), no tetrahedra; fem fills a surface",
        ),
    ):
        with pytest.raises(SystemExit) as exit_info:
            main(["fem", *args, "--out", str(tmp_path / "x")])
        err = capsys.readouterr().err
        assert exit_info.value.code == 2 and err.count("\n") == 1 and told in err
