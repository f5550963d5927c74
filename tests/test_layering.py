"""The layering of DESIGN.md, read from the source: ``_jaxcga_shared`` <- ``jaxcga`` <- ``deform`` <- ``cutting``,
``_jaxcga_shared`` <- ``jaxcga`` <- ``deform`` <- ``xfem`` (characters' bodies are skinned by ``deform``; ``xfem`` and
``cutting`` never import each other), and the command line (``jaxcga_cli``) above all; no package imports one
above it (at any depth, lazy imports included) and no package's modules import each other in a cycle."""

from __future__ import annotations

import ast
import pathlib

import pytest

ROOT = pathlib.Path(__file__).resolve().parent.parent
BELOW = {
    "_jaxcga_shared": set(),
    "jaxcga": {"_jaxcga_shared"},
    "deform": {"_jaxcga_shared", "jaxcga"},
    "cutting": {"_jaxcga_shared", "jaxcga", "deform"},
    "xfem": {"_jaxcga_shared", "jaxcga", "deform"},
    "jaxcga_cli": {"_jaxcga_shared", "jaxcga", "deform", "cutting", "xfem"},
}


def _imports(path: pathlib.Path, package: str, *, top_level_only: bool) -> set[str]:
    """Dotted module names imported by the file (relative imports resolved inside ``package``)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else list(ast.walk(tree))
    names = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([package, *([base] if base else [])])
            names |= {f"{base}.{alias.name}" for alias in node.names} | {base}
    return names


@pytest.mark.parametrize("package", sorted(BELOW))
def test_no_upward_import(package):
    if not (ROOT / package).is_dir():
        pytest.skip(f"{package} is not in this checkout")
    for path in (ROOT / package).rglob("*.py"):
        for name in _imports(path, package, top_level_only=False):
            top = name.split(".")[0]
            if top in BELOW and top != package:
                assert top in BELOW[package], f"{path.relative_to(ROOT)} imports {name}: {package} sits below {top}"


@pytest.mark.parametrize("package", sorted(BELOW))
def test_no_import_cycle(package):
    if not (ROOT / package).is_dir():
        pytest.skip(f"{package} is not in this checkout")
    modules = {f"{package}.{p.stem}" if p.stem != "__init__" else package: p for p in (ROOT / package).glob("*.py")}
    graph = {
        m: {
            n
            for name in _imports(p, package, top_level_only=True)
            for n in modules
            if n != package and (name == n or name.startswith(n + "."))
        }
        - {m}
        for m, p in modules.items()
    }
    state: dict[str, int] = {}

    def visit(module, trail):
        state[module] = 1
        for nxt in graph[module]:
            assert state.get(nxt) != 1, f"import cycle: {' -> '.join([*trail, module, nxt])}"
            if nxt not in state:
                visit(nxt, [*trail, module])
        state[module] = 2

    for module in modules:
        if module not in state:
            visit(module, [])
