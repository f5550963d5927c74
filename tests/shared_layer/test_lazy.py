"""Lazy package exports (``_jaxcga_shared.lazy``): the names ``deform`` exports are exactly its ``TYPE_CHECKING``
imports, each the object its module defines; importing the package and using its skinning loads neither libigl,
optax, optimistix nor the viewer; unknown names and unreadable tables are errors."""

from __future__ import annotations

import pathlib
import subprocess
import sys

import pytest

import deform
from _jaxcga_shared.lazy import lazy_exports, type_checking_imports

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_every_exported_name_has_its_source_and_is_that_object():
    sources = type_checking_imports(deform.__file__)
    assert set(sources) == set(deform.__all__)
    assert set(deform.__all__) <= set(dir(deform))
    for name, (module, attribute) in sources.items():
        assert getattr(deform, name) is getattr(sys.modules[module], attribute), name
    assert deform.default_arap_tolerance is sys.modules["deform._arap"].default_tolerance  # an ``as`` name


def test_an_unknown_name_is_an_attribute_error():
    with pytest.raises(AttributeError, match="module 'deform' has no attribute 'skin_modle'"):
        deform.skin_modle  # noqa: B018
    assert not hasattr(deform, "skin_modle")


def test_skinning_loads_none_of_the_other_deformers_dependencies():
    script = (
        "import sys, deform\n"
        "heavy = ('igl', 'optax', 'optimistix', '_jaxcga_shared.viewer')\n"
        "loaded = lambda: sorted(m for m in heavy if m in sys.modules)\n"
        "assert loaded() == [], loaded()\n"
        "model = deform.load_model('tests/data/CesiumMan.glb')\n"
        "deform.skin_model(model, 0.5)\n"
        "print(loaded())\n"
        "deform.arap_solve, deform.view\n"
        "print(loaded())\n"
    )
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["[]", "['_jaxcga_shared.viewer', 'igl']"]


def test_a_table_it_cannot_resolve_is_refused(tmp_path):
    init = tmp_path / "__init__.py"
    init.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from ._a import f\n")
    with pytest.raises(ImportError, match="only 'from MODULE import NAME'"):
        lazy_exports("package", str(init))
    init.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from a import *\n")
    with pytest.raises(ImportError, match="cannot be made lazy"):
        type_checking_imports(init)
