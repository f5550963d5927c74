"""The public surface of the library packages: every public function and class method is annotated (arguments and
return), and what a package exports is its own (defined in the package, not a re-export of a helper from
another); the kernel leaves the viewer out, and the scene runner of the command line and the benchmarks is not
the library's."""

from __future__ import annotations

import inspect
import pathlib
import subprocess
import sys
import typing

import pytest

import cutting
import deform
import jaxcga
import xfem

PACKAGES = {"jaxcga": jaxcga, "deform": deform, "cutting": cutting, "xfem": xfem}


def _public(package):
    for name in package.__all__:
        value = getattr(package, name)
        if inspect.isfunction(value):
            yield name, value
        elif inspect.isclass(value):
            for attribute, member in vars(value).items():
                if inspect.isfunction(member) and (not attribute.startswith("_") or attribute == "__init__"):
                    yield f"{name}.{attribute}", member


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_every_public_function_is_annotated(package):
    missing = []
    for name, fn in _public(PACKAGES[package]):
        if fn.__module__.split(".")[0] != package:
            continue  # a class defined elsewhere (equinox's generated methods, a re-export)
        signature = inspect.signature(fn)
        unannotated = [
            p.name
            for p in signature.parameters.values()
            if p.annotation is inspect.Parameter.empty
            and p.name not in ("self", "cls")
            and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)
        ]
        if unannotated or (signature.return_annotation is inspect.Signature.empty and not name.endswith("__init__")):
            missing.append(f"{name}({', '.join(unannotated)}){'' if unannotated else ' -> ?'}")
    assert not missing, f"{package}: not fully annotated: " + "; ".join(missing)


@pytest.mark.parametrize("package", sorted(PACKAGES))
def test_every_public_annotation_evaluates(package):
    """jaxtyping's shapes are strings ("n 3", "*batch"): a bare 3 or ... (which ruff's UP037 once made of "3" and
    "...") fails when the annotations are evaluated, by a runtime type checker or ``typing.get_type_hints``."""
    failed = []
    for name in PACKAGES[package].__all__:
        value = getattr(PACKAGES[package], name)
        if inspect.isfunction(value) or inspect.isclass(value):
            try:
                typing.get_type_hints(value)
            except Exception as error:  # noqa: BLE001 (any failure to evaluate is the finding)
                failed.append(f"{name}: {error}")
    assert not failed, f"{package}: " + "; ".join(failed)


def test_the_kernel_leaves_the_viewer_out():
    """``jaxcga`` is the algebra: the viewer, which reads mesh and glTF files, is ``deform.view`` (and
    ``deform.View``), and importing the kernel does not load it."""
    assert not {"view", "View"} & {*jaxcga.__all__, *dir(jaxcga)}
    assert {"view", "View"} <= set(deform.__all__)
    script = "import sys, jaxcga; print(sorted(m for m in sys.modules if 'viewer' in m))"
    root = pathlib.Path(__file__).resolve().parent.parent
    out = subprocess.run([sys.executable, "-c", script], cwd=root, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"


def test_the_scene_runner_is_not_the_librarys():
    """The runner that times the XFEM scenes (tqdm, wall clocks) is the command line's (``jaxcga_cli.scene_runs``);
    the scenes themselves stay in ``xfem``."""
    assert not {"run_scene", "SceneRun", "FrameRecord"} & {*xfem.__all__, *dir(xfem)}
    assert {"scene", "Scene", "SCENES", "piece_surfaces"} <= set(xfem.__all__)
