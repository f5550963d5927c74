"""The command line's compilation cache: a command's executables are written to the cache and read back by its second
run, and its programs are exported there (``cache.ExportedCalls``: read back instead of traced, their checks and
warnings kept); ``--no-cache`` (before or after the command's name) and ``JAXCGA_NO_CACHE`` turn it off; an
unwritable directory costs one warning line; ``--help`` says where the cache lives and how to turn it off."""

from __future__ import annotations

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
import jaxcga
from _jaxcga_shared.checks import require
from jaxcga_cli import cache
from jaxcga_cli.main import parser
from tests.shared import DATA, run_jaxcga


def test_a_commands_executables_are_cached_and_read_back_and_the_switches_turn_the_cache_off(tmp_path):
    argv = ["skin", str(DATA / "RiggedSimple.glb"), "--time", "0.5", "--out", str(tmp_path / "posed.npy")]
    first = run_jaxcga(argv, tmp_path / "cache")
    assert first.returncode == 0, first.stderr
    written = sorted(str(path.relative_to(tmp_path)) for path in (tmp_path / "cache").rglob("*"))
    # the skinning exported, and its executable cached: JAX writes no entry for an executable with a host callback,
    # which a traced check was
    assert any(name.startswith("cache/exported/skin_model-") for name in written), written
    assert any(name.startswith("cache/jit_call-") for name in written), written  # the exported program, jitted
    second = run_jaxcga(argv, tmp_path / "cache")
    assert second.returncode == 0, second.stderr
    # every program and executable found under the same key: nothing exported or compiled, nothing new written
    assert sorted(str(path.relative_to(tmp_path)) for path in (tmp_path / "cache").rglob("*")) == written
    # the library's positions (to rounding: under --gpu-variants this process takes the GPU formulation)
    np.testing.assert_allclose(np.load(tmp_path / "posed.npy"), deform.skin_model(*_model_at(0.5)), atol=1e-12)
    for name, argv_off, env in (("flag", [*argv, "--no-cache"], {}), ("env", argv, {"JAXCGA_NO_CACHE": "1"})):
        off = run_jaxcga(argv_off, tmp_path / name, env=env)
        assert off.returncode == 0, off.stderr
        assert not (tmp_path / name).exists(), name


def test_no_cache_is_read_before_and_after_the_commands_name():
    model = str(DATA / "RiggedSimple.glb")
    assert parser().parse_args(["--no-cache", "skin", model, "--out", "x.npy"]).no_cache
    assert parser().parse_args(["skin", model, "--out", "x.npy", "--no-cache"]).no_cache
    assert not parser().parse_args(["skin", model, "--out", "x.npy"]).no_cache


def test_an_unwritable_cache_directory_is_one_warning_line_and_no_cache(tmp_path, monkeypatch, capsys):
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    monkeypatch.delenv("JAXCGA_NO_CACHE", raising=False)
    monkeypatch.setenv("JAXCGA_CACHE_DIR", str(blocker / "jax"))  # a directory inside a file cannot be made
    before = getattr(jax.config, "jax_compilation_cache_dir")
    # the tests' own cache (tests/conftest.py) would be the caller's configuration, which the command keeps
    jax.config.update("jax_compilation_cache_dir", None)
    try:
        assert cache.enable("skin", no_cache=False) is None
        assert getattr(jax.config, "jax_compilation_cache_dir") is None
    finally:
        jax.config.update("jax_compilation_cache_dir", before)
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxcga skin: warning: the compilation cache"), lines
    assert "not writable" in lines[0] and str(blocker / "jax") in lines[0]


@pytest.mark.parametrize("value, off", [("1", True), ("yes", True), ("0", False), ("", False)])
def test_the_environment_switch(monkeypatch, value, off):
    monkeypatch.setenv("JAXCGA_NO_CACHE", value)
    assert cache.disabled_by_environment() is off


def test_help_says_where_the_cache_lives_and_how_to_turn_it_off(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXCGA_CACHE_DIR", str(tmp_path / "here"))
    text = " ".join(parser().format_help().split())
    assert f"cached in {tmp_path / 'here'}" in text
    assert "--no-cache" in text and "JAXCGA_NO_CACHE=1" in text


def _model_at(t: float):
    return deform.load_model(DATA / "RiggedSimple.glb"), t


def test_an_exported_call_is_read_back_and_gives_the_librarys_result(tmp_path):
    calls = cache.ExportedCalls(tmp_path)
    model, t = _model_at(0.25)
    expected = np.asarray(deform.skin_model(model, t, "lbs"))
    first = calls("skin_model", deform.skin_model, model, np.float64(t), "lbs")
    (written,) = tmp_path.iterdir()
    assert written.name.startswith("skin_model-") and written.suffix == ".jaxexport"
    stamp = written.stat().st_mtime_ns
    # a fresh object, as a second run has: the program is read back, not exported again
    second = cache.ExportedCalls(tmp_path)("skin_model", deform.skin_model, model, np.float64(t), "lbs")
    assert written.stat().st_mtime_ns == stamp and len(list(tmp_path.iterdir())) == 1
    np.testing.assert_array_equal(np.asarray(first), expected)
    np.testing.assert_array_equal(np.asarray(second), expected)
    # another time is an argument of the same program; another method is another program
    other = calls("skin_model", deform.skin_model, model, np.float64(0.75), "lbs")
    np.testing.assert_array_equal(np.asarray(other), np.asarray(deform.skin_model(model, 0.75, "lbs")))
    assert len(list(tmp_path.iterdir())) == 1
    calls("skin_model", deform.skin_model, model, np.float64(t), "cga")
    assert len(list(tmp_path.iterdir())) == 2


def _checked_half(x):
    require(None, (jnp.any(x < 0), "x: expected non-negative values"))
    with warnings.catch_warnings():
        warnings.simplefilter("always")
        warnings.warn("halved", UserWarning, stacklevel=1)  # given while tracing, as the library's notices are
    return {"half": x / 2}


def test_an_exported_calls_checks_raise_and_its_warnings_are_given_again(tmp_path):
    for calls in (cache.ExportedCalls(tmp_path), cache.ExportedCalls(tmp_path)):  # exported, then read back
        with pytest.warns(UserWarning, match="halved"):
            out = calls("half", _checked_half, np.array([1.0, 4.0]))
        np.testing.assert_array_equal(np.asarray(out["half"]), [0.5, 2.0])
        with pytest.warns(UserWarning, match="halved"), pytest.raises(jaxcga.CheckError, match="x: expected non"):
            calls("half", _checked_half, np.array([1.0, -4.0]))


def test_a_call_that_cannot_be_exported_runs_plain_and_is_remembered(tmp_path):
    def on_the_host(x):
        return np.asarray(x) * 2  # needs the values: no program to export

    calls = cache.ExportedCalls(tmp_path)
    np.testing.assert_array_equal(calls("host", on_the_host, np.array([1.0, 2.0])), [2.0, 4.0])
    assert [path.suffix for path in tmp_path.iterdir()] == [".plain"]
    np.testing.assert_array_equal(calls("host", on_the_host, np.array([2.0, 3.0])), [4.0, 6.0])
    # an error of the input is the library's own, and nothing is remembered for it
    with pytest.raises(ValueError, match="method"):
        calls("skin_model", deform.skin_model, *_model_at(0.5), "nope")
    assert [path.suffix for path in tmp_path.iterdir()] == [".plain"]


def test_a_corrupt_program_is_exported_again(tmp_path):
    calls = cache.ExportedCalls(tmp_path)
    with pytest.warns(UserWarning, match="halved"):
        calls("half", _checked_half, np.array([1.0]))
    (written,) = tmp_path.iterdir()
    written.write_bytes(b"not a program")
    with pytest.warns(UserWarning, match="halved"):
        out = cache.ExportedCalls(tmp_path)("half", _checked_half, np.array([1.0]))
    assert float(out["half"][0]) == 0.5 and written.stat().st_size > 100


def test_a_module_result_is_exported_and_read_back(tmp_path):
    """A result holding the library's modules (a Multivector, whose tree marks its static fields with equinox's
    marker) is exported, not run plain: this fails loudly if equinox moves the marker ``cache`` pickles by name."""
    axis, angle = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), np.array([0.3, -1.2])
    expected = jaxcga.rotor(jnp.asarray(axis), jnp.asarray(angle))
    for calls in (cache.ExportedCalls(tmp_path), cache.ExportedCalls(tmp_path)):  # exported, then read back
        rotors = calls("rotor", jaxcga.rotor, axis, angle)
        assert isinstance(rotors, jaxcga.Multivector) and rotors.blades == expected.blades
        np.testing.assert_array_equal(np.asarray(rotors.values), np.asarray(expected.values))
    assert [path.suffix for path in tmp_path.iterdir()] == [".jaxexport"]


def test_arap_host_loops_steps_are_exported_and_read_back(tmp_path):
    """ARAP's host loop through the exported programs (the ``arap`` command's): its four steps are exported once,
    each iteration calls the same program, and a second process's loop reads them back to the same positions."""
    mesh = deform.default_arm().mesh
    V, F = np.asarray(mesh.V, np.float64), np.asarray(mesh.F, np.int64)
    b = np.flatnonzero((V[:, 0] < 0) | (V[:, 0] > 0.75))
    bc = V[b] + np.where(V[b, :1] > 0.75, [0.0, 0.2, 0.1], 0.0)
    data = deform.arap_precompute(V, F, b)
    expected = np.asarray(deform.arap_solve(data, jnp.asarray(bc), host_loop=True, max_iterations=20).U)
    for calls in (cache.ExportedCalls(tmp_path), cache.ExportedCalls(tmp_path)):  # exported, then read back
        result = deform.arap_solve(data, jnp.asarray(bc), host_loop=True, max_iterations=20, runner=calls)
        np.testing.assert_allclose(np.asarray(result.U), expected, rtol=0, atol=1e-12)
        names = sorted(path.name.split("-")[0] for path in tmp_path.iterdir())
        assert names == ["arap_aligned_rest", "arap_between_solves", "arap_result", "arap_start"], names
