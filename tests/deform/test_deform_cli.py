"""The ``jaxcga deform {spline,handles,ffd,cage}`` commands, end to end in-process, on a closed tube
(a file written here) and on the built-in arm: outputs, the motion they apply, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from jaxcga.cli import main


@pytest.fixture(scope="module")
def tube(tmp_path_factory):
    """A closed tube along z, length 2 and radius 0.2, with rings every 0.1: (path, V, F)."""
    mesh = trimesh.creation.cylinder(radius=0.2, height=2.0, sections=16)
    for _ in range(3):
        mesh = mesh.subdivide()
    path = tmp_path_factory.mktemp("mesh") / "tube.ply"
    mesh.export(path)
    loaded = trimesh.load(path, force="mesh", process=True)
    return path, np.asarray(loaded.vertices), np.asarray(loaded.faces)


@pytest.mark.parametrize("method", ["spline", "handles", "ffd", "cage"])
def test_every_method_turns_the_far_end_by_the_bend_and_keeps_the_near_end(tube, tmp_path, method, capsys):
    path, V, F = tube
    out = tmp_path / f"{method}.npy"
    assert main(["deform", method, str(path), "--bend", "90", "--out", str(out)]) == 0
    assert f"jaxcga deform {method}" in capsys.readouterr().out
    X = np.load(out)
    assert X.dtype == np.float64 and X.shape == V.shape and np.all(np.isfinite(X))
    z = V[:, 2]
    near, far = z < -0.99, z > 0.99
    # the long axis is z, the smallest extent x (ties go to the first axis): a bend about x by 90 degrees
    # about the pivot, the centre of the low end
    pivot = np.array([0.0, 0.0, -1.0])
    turned = Rotation.from_rotvec([np.pi / 2, 0, 0]).apply(V[far] - pivot) + pivot
    if method in ("spline", "handles"):  # the end handles move rigidly
        np.testing.assert_allclose(X[near], V[near], atol=1e-10)
        np.testing.assert_allclose(X[far], turned, atol=1e-10)
    else:  # lattice points and cage vertices only near the ends: close, not exact
        assert np.abs(X[near] - V[near]).max() < 0.05
        assert np.abs(X[far] - turned).max() < 0.25
    assert np.abs(X - V).max() > 1.0


def test_figure_mesh_and_positional_outputs(tube, tmp_path):
    path, V, F = tube
    png = tmp_path / "ffd.png"
    assert main(["deform", "ffd", str(path), "--twist", "90", "--positional", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000
    glb = tmp_path / "cage.glb"
    assert main(["deform", "cage", str(path), "--bend", "45", "--out", str(glb)]) == 0
    assert trimesh.load(glb, force="mesh", process=False).vertices.shape == V.shape


def test_handles_file_with_a_translated_handle(tube, tmp_path):
    path, V, F = tube
    z = V[:, 2]
    spec = {"handles": [np.flatnonzero(z < -0.99).tolist(), np.flatnonzero(z > 0.99).tolist()],
            "motors": [{}, {"translation": [0.3, 0.0, 0.0]}]}
    handles = tmp_path / "handles.json"
    handles.write_text(json.dumps(spec))
    out = tmp_path / "moved.npy"
    assert main(["deform", "handles", str(path), "--handles", str(handles), "--weights", "mean_value",
                 "--out", str(out)]) == 0
    X = np.load(out)
    np.testing.assert_allclose(X[z > 0.99], V[z > 0.99] + [0.3, 0, 0], atol=1e-12)
    np.testing.assert_allclose(X[z < -0.99], V[z < -0.99], atol=1e-12)
    middle = np.abs(z) < 0.01  # a translation blends linearly along the harmonic field: about half way
    assert 0.1 < np.mean(X[middle, 0] - V[middle, 0]) < 0.2


def test_built_in_arm_by_default(tmp_path):
    out = tmp_path / "arm.npy"
    assert main(["deform", "spline", "--basis", "lagrange", "--bend", "30", "--out", str(out)]) == 0
    assert np.load(out).shape[1] == 3


@pytest.mark.parametrize("argv, message", [
    (["deform", "spline", "--positional", "--out", "x.npy"], "positional"),
    (["deform", "ffd", "--out", "x.txt"], "out"),
    (["deform", "spline", "missing.ply", "--out", "x.npy"], "no such file"),
    (["deform", "spline", "--basis", "lagrange", "--keys", "4", "--out", "x.npy"], "num_keys"),
])
def test_errors_name_the_problem(tmp_path, argv, message, capsys):
    argv = [a if a != "x.npy" and a != "x.txt" else str(tmp_path / a) for a in argv]
    with pytest.raises(SystemExit) as exit_info:
        main(argv)
    assert exit_info.value.code == 2
    assert message in capsys.readouterr().err
