"""The command line's compilation cache: a command's executables are written to the cache (the skinning's own,
whose checks come back as values, among them) and read back by its second run; ``--no-cache`` (before or after the
command's name) and ``JAXCGA_NO_CACHE`` turn it off; an unwritable directory costs one warning line; ``--help``
says where the cache lives and how to turn it off."""

from __future__ import annotations

import jax
import pytest

from jaxcga_cli import cache
from jaxcga_cli.main import parser
from tests.shared import DATA, run_jaxcga


def test_a_commands_executables_are_cached_and_read_back_and_the_switches_turn_the_cache_off(tmp_path):
    argv = ["skin", str(DATA / "RiggedSimple.glb"), "--time", "0.5", "--out", str(tmp_path / "posed.npy")]
    first = run_jaxcga(argv, tmp_path / "cache")
    assert first.returncode == 0, first.stderr
    written = sorted(path.name for path in (tmp_path / "cache").iterdir())
    # the skinning itself: JAX writes no entry for an executable with a host callback, which a traced check was
    assert any(name.startswith("jit__skin_model-") for name in written), written
    second = run_jaxcga(argv, tmp_path / "cache")
    assert second.returncode == 0, second.stderr
    # every executable found under the same key: nothing compiled, nothing new written
    assert sorted(path.name for path in (tmp_path / "cache").iterdir()) == written
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
    assert cache.enable("skin", no_cache=False) is None
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("jaxcga skin: warning: the compilation cache"), lines
    assert "not writable" in lines[0] and str(blocker / "jax") in lines[0]
    assert getattr(jax.config, "jax_compilation_cache_dir") == before


@pytest.mark.parametrize("value, off", [("1", True), ("yes", True), ("0", False), ("", False)])
def test_the_environment_switch(monkeypatch, value, off):
    monkeypatch.setenv("JAXCGA_NO_CACHE", value)
    assert cache.disabled_by_environment() is off


def test_help_says_where_the_cache_lives_and_how_to_turn_it_off(tmp_path, monkeypatch):
    monkeypatch.setenv("JAXCGA_CACHE_DIR", str(tmp_path / "here"))
    text = " ".join(parser().format_help().split())
    assert f"cached in {tmp_path / 'here'}" in text
    assert "--no-cache" in text and "JAXCGA_NO_CACHE=1" in text
