"""The documentation site's sources (docs/, built by `make docs`): the API reference covers every public name of the
four library packages, the command-line reference covers every subcommand, and no page, rendered docstring or
notebook carries an internal tracker number."""

from __future__ import annotations

import doctest
import importlib
import importlib.util
import inspect
import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
PACKAGES = ("jaxcga", "deform", "cutting", "xfem")
# "issue 51", "Issues 31-32": the project's own tracker, meaningless to a reader of the site; another project's
# tracker ("fTetWild issue #72") names its project and keeps its "#"
TRACKER = re.compile(r"\bissues? \d+", re.IGNORECASE)
REFERENCE = re.compile(r"^::: ([\w.]+)\s*$", re.MULTILINE)


def reference_names(package: str) -> list[str]:
    """The names that docs/api/PACKAGE.md renders (its ``::: package.name`` lines), in order."""
    return REFERENCE.findall((DOCS / "api" / f"{package}.md").read_text())


@pytest.mark.parametrize("package", PACKAGES)
def test_api_reference_covers_every_public_name(package):
    module = importlib.import_module(package)
    documented = reference_names(package)
    assert len(documented) == len(set(documented)), "a name is documented twice"
    public = {f"{package}.{name}" for name in module.__all__}
    missing = sorted(public - set(documented))
    assert not missing, f"public names missing from docs/api/{package}.md: {missing}"
    unknown = sorted(set(documented) - public)
    assert not unknown, f"docs/api/{package}.md documents names outside {package}.__all__: {unknown}"


def test_reference_reader_sees_a_missing_name(tmp_path):
    # the coverage check above can fail: a page without one name's line is caught by the same reader
    text = (DOCS / "api" / "cutting.md").read_text()
    first = REFERENCE.search(text)
    assert first is not None
    assert first.group(1) not in REFERENCE.findall(text.replace(first.group(0), "", 1))


def public_docstrings():
    """(name, docstring) of every public name of the four packages and of their classes' public members: what the
    API reference renders."""
    for package in PACKAGES:
        module = importlib.import_module(package)
        for name in module.__all__:
            obj = getattr(module, name)
            yield f"{package}.{name}", inspect.getdoc(obj) or ""
            if inspect.isclass(obj):
                for member, value in vars(obj).items():
                    if not member.startswith("_"):
                        yield f"{package}.{name}.{member}", inspect.getdoc(value) or ""


def doc_sources():
    """(path, text) of every Markdown page of the site, the benchmark reference it includes, the README, and the
    notebooks' cells (sources and text outputs)."""
    pages = [p for p in DOCS.rglob("*.md") if "notebooks" not in p.parts]
    for path in [*pages, ROOT / "README.md", ROOT / "benchmarks" / "README.md"]:
        yield path.relative_to(ROOT), path.read_text()
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text())["cells"]
        text = []
        for cell in cells:
            text.append("".join(cell["source"]))
            for output in cell.get("outputs", []):
                text.append("".join(output.get("text", "")))
                text.append("".join(output.get("data", {}).get("text/plain", "")))
        yield path.relative_to(ROOT), "\n".join(text)


def test_no_internal_tracker_numbers():
    found = [f"{where}: {m.group(0)!r}" for where, text in doc_sources() for m in TRACKER.finditer(text)]
    for name, doc in public_docstrings():
        found += [f"docstring of {name}: {m.group(0)!r}" for m in TRACKER.finditer(doc)]
    assert not found, "internal tracker numbers in the documentation:\n" + "\n".join(found)


def test_tracker_pattern():
    assert TRACKER.search("as issue 51 places them") and TRACKER.search("Issues 31-32")
    assert not TRACKER.search("fTetWild issue #72") and not TRACKER.search("the issue of scale")


def public_functions(package: str):
    """(qualified name, function) of the package's public functions (its ``__all__``), in order."""
    module = importlib.import_module(package)
    for name in module.__all__:
        obj = getattr(module, name)
        if inspect.isfunction(obj):
            yield f"{package}.{name}", obj


# deform's and cutting's examples pose, cut, tear and drill the built-in arm: the slow job
# runs them; the kernel's and xfem's take ~20 s
SLOW_EXAMPLES = ("deform", "cutting")


@pytest.mark.parametrize(
    "package", [pytest.param(p, marks=pytest.mark.slow) if p in SLOW_EXAMPLES else p for p in PACKAGES]
)
def test_docstring_examples_run(package):
    # the examples the API reference shows, run as doctests in the suite's configuration (float64, strict promotion)
    finder = doctest.DocTestFinder(recurse=False)
    runner = doctest.DocTestRunner(optionflags=doctest.NORMALIZE_WHITESPACE)
    report: list[str] = []
    examples = 0
    for name, function in public_functions(package):
        for test in finder.find(function, name, globs={}):
            examples += len(test.examples)
            runner.run(test, out=report.append)
    assert runner.failures == 0, "".join(report)
    if package == "jaxcga":
        assert examples > 0


@pytest.mark.parametrize("package", PACKAGES)
def test_public_functions_document_arguments_and_results(package):
    # every public function has the Google-style sections mkdocstrings renders; the kernel's also an example
    incomplete = []
    for name, function in public_functions(package):
        doc = inspect.getdoc(function) or ""
        needs_args = any(p.name != "self" for p in inspect.signature(function).parameters.values())
        sections = (("Args:", needs_args), ("Returns:", True), (">>>", package == "jaxcga"))
        missing = [section for section, needed in sections if needed and section not in doc]
        if missing:
            incomplete.append(f"{name}: {missing}")
    assert not incomplete, "\n".join(incomplete)


def test_cli_reference_covers_every_subcommand():
    pytest.importorskip("mkdocs", reason="the docs extra (mkdocs) is not installed")
    from jaxcga_cli.main import COMMANDS

    spec = importlib.util.spec_from_file_location("cli_reference", DOCS / "_hooks" / "cli_reference.py")
    assert spec is not None and spec.loader is not None
    hook = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(hook)
    page = hook.cli_reference()
    sections = re.findall(r"^## jaxcga (\S+)$", page, re.MULTILINE)
    assert sections == list(COMMANDS)
    for name in COMMANDS:
        # each section is the subcommand's own --help: its usage line and its example
        section = page.split(f"## jaxcga {name}\n", 1)[1].split("\n## ", 1)[0]
        assert f"usage: jaxcga {name}" in section and "example:" in section


def test_every_page_is_in_the_navigation():
    nav = (ROOT / "mkdocs.yml").read_text()
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md") if "_hooks" not in p.parts}
    pages |= {f"notebooks/{p.name}" for p in (ROOT / "notebooks").glob("*.ipynb")}
    missing = sorted(p for p in pages if f": {p}" not in nav)
    assert not missing, f"pages outside mkdocs.yml's nav: {missing}"


@pytest.mark.slow
@pytest.mark.parametrize("page", ["docs/getting-started.md", "README.md"])
def test_examples_of_the_first_pages_run(page, monkeypatch):
    # the page's Python blocks (one per package), in order, in one namespace, from the repository's root (their
    # paths are relative)
    blocks = re.findall(r"```python\n(.*?)```", (ROOT / page).read_text(), re.DOTALL)
    assert len(blocks) >= 4
    monkeypatch.chdir(ROOT)
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, page, "exec"), namespace)
    assert {"cga", "deform", "cutting", "xfem"} <= set(namespace)


def test_readme_is_a_front_door():
    # at most 150 lines, and it keeps the test command CI runs (.ci/run: make test)
    readme = (ROOT / "README.md").read_text()
    assert len(readme.splitlines()) <= 150
    assert "make test" in readme and "make test" in (ROOT / ".ci" / "run").read_text()
