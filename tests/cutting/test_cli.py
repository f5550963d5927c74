"""``jaxcga cut`` end to end: skinned glTF halves with the input's skeleton, joints and weights, that
animate again."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import deform
from jaxcga.cli import main


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
