"""The layering of DESIGN.md, read from the source: ``_jaxcga_shared`` <- ``jaxcga`` <- ``deform`` <- ``cutting``,
``_jaxcga_shared`` <- ``jaxcga`` <- ``deform`` <- ``xfem`` (characters' bodies are skinned by ``deform``; ``xfem`` and
``cutting`` never import each other), and the command line (``jaxcga_cli``) above all. No package imports one above
it, at any depth: imports inside functions and ``importlib.import_module("...")`` with a literal name count too. No
files of the project import each other in a cycle: neither through the imports that run when a module is loaded nor
through those inside functions (``if TYPE_CHECKING:`` blocks, which never run, aside; but for a package's lazy exports,
which its ``__getattr__`` imports on first use)."""

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


def _module_name(path: pathlib.Path, root: pathlib.Path = ROOT) -> str:
    """The dotted name of a file under ``root`` (a package's ``__init__.py`` is the package)."""
    parts = list(path.relative_to(root).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _is_type_checking(node: ast.stmt) -> bool:
    if not isinstance(node, ast.If):
        return False
    test = node.test
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _load_time_statements(body: list[ast.stmt]):
    """The statements that run when the module is loaded: class bodies and ``if``/``try``/``with``/... blocks do,
    function bodies do not (they run when called), nor ``if TYPE_CHECKING:`` blocks (they never run)."""
    for statement in body:
        yield statement
        if isinstance(statement, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        if _is_type_checking(statement):
            assert isinstance(statement, ast.If)
            yield from _load_time_statements(statement.orelse)
            continue
        for field in ("body", "orelse", "finalbody"):
            yield from _load_time_statements(getattr(statement, field, None) or [])
        for handler in getattr(statement, "handlers", None) or []:
            yield from _load_time_statements(handler.body)
        for case in getattr(statement, "cases", None) or []:
            yield from _load_time_statements(case.body)


def _expressions(statement: ast.stmt):
    """The expressions a statement evaluates itself (not those of the statements nested in it, nor lambdas' bodies):
    a ``def``'s decorators and defaults, a ``class``'s bases, an assignment's value, ..."""
    stack = [child for child in ast.iter_child_nodes(statement) if isinstance(child, ast.expr)]
    while stack:
        node = stack.pop()
        yield node
        stack += [child for child in ast.iter_child_nodes(node) if not isinstance(node, ast.Lambda)]


def _executed(node: ast.AST):
    """``node`` and its descendants but the bodies of ``if TYPE_CHECKING:`` blocks (which never run)."""
    yield node
    for child in ast.iter_child_nodes(node):
        if isinstance(child, ast.stmt) and _is_type_checking(child):
            assert isinstance(child, ast.If)
            for statement in child.orelse:
                yield from _executed(statement)
        else:
            yield from _executed(child)


def _imports(path: pathlib.Path, *, which: str, root: pathlib.Path = ROOT) -> set[str]:
    """Dotted names the file imports, relative imports resolved (``from a import b`` gives ``a.b``: module ``a.b``,
    or module ``a`` where ``b`` is a name it defines), and the literal names it passes to ``importlib.import_module``.
    ``which``: "load" those that run when the file is loaded, "run" those that can run at all (function bodies
    too, not ``TYPE_CHECKING`` blocks), "all" every one written."""
    tree = ast.parse(path.read_text())
    module = _module_name(path, root)
    # relative imports start from the module's package: its parent, or the package itself for an __init__
    package = module.split(".") if path.name == "__init__.py" else module.split(".")[:-1]
    if which == "load":
        statements = list(_load_time_statements(tree.body))
        nodes = [*statements, *(e for statement in statements for e in _expressions(statement))]
    elif which == "run":
        # a package __init__ with lazy exports (_jaxcga_shared.lazy) imports its TYPE_CHECKING names on first use
        nodes = list(ast.walk(tree)) if "lazy_exports(" in path.read_text() else list(_executed(tree))
    else:
        nodes = list(ast.walk(tree))
    names = set()
    for node in nodes:
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                base = ".".join([*package[: len(package) - (node.level - 1)], *([base] if base else [])])
            names |= {f"{base}.{alias.name}" for alias in node.names}
        elif isinstance(node, ast.Call) and _is_import_module(node.func) and node.args:
            first = node.args[0]
            if isinstance(first, ast.Constant) and isinstance(first.value, str):
                names.add(first.value)
    return names


def _is_import_module(func: ast.expr) -> bool:
    return (isinstance(func, ast.Attribute) and func.attr == "import_module") or (
        isinstance(func, ast.Name) and func.id in ("import_module", "__import__")
    )


def _project_files() -> dict[str, pathlib.Path]:
    return {_module_name(path): path for package in BELOW for path in sorted((ROOT / package).rglob("*.py"))}


def test_imports_inside_functions_and_import_module_are_read(tmp_path):
    """The reader of this test itself: an import in a function body, an ``importlib.import_module`` with a literal and
    a relative import from a subpackage are found; function bodies and ``TYPE_CHECKING`` blocks are not load time."""
    package = tmp_path / "pkg" / "sub"
    package.mkdir(parents=True)
    source = package / "mod.py"
    source.write_text(
        "import importlib\nfrom typing import TYPE_CHECKING\nfrom .. import top\nfrom .near import x\n"
        "if TYPE_CHECKING:\n    import hidden\nclass C:\n    import in_class\n"
        "try:\n    import in_try\nexcept ImportError:\n    pass\n"
        "CONST = importlib.import_module('at.load')\nLATER = lambda: importlib.import_module('in.lambda')\n"
        "def f():\n    import lazy\n    return importlib.import_module('dynamic.name')\n"
    )
    everything = _imports(source, which="all", root=tmp_path)
    assert {"pkg.top", "pkg.sub.near.x", "hidden", "in_class", "lazy", "dynamic.name", "in.lambda"} <= everything
    run = _imports(source, which="run", root=tmp_path)
    assert everything - run == {"hidden"}
    load_time = _imports(source, which="load", root=tmp_path)
    assert {"importlib", "pkg.top", "pkg.sub.near.x", "in_class", "in_try", "at.load"} <= load_time
    assert not {"hidden", "lazy", "dynamic.name", "in.lambda"} & load_time


@pytest.mark.parametrize("package", sorted(BELOW))
def test_no_upward_import(package):
    if not (ROOT / package).is_dir():
        pytest.skip(f"{package} is not in this checkout")
    for path in (ROOT / package).rglob("*.py"):
        for name in _imports(path, which="all"):
            top = name.split(".")[0]
            if top in BELOW and top != package:
                assert top in BELOW[package], f"{path.relative_to(ROOT)} imports {name}: {package} sits below {top}"


def _import_graph(which: str) -> dict[str, set[str]]:
    """Each file's module to the project's modules that its imports (``_imports``' ``which``) load: the most specific
    one a name reaches (``from deform._rig import Rig`` is ``deform._rig``, ``from deform import Rig`` is
    ``deform``)."""
    files = _project_files()
    graph = {}
    for module, path in files.items():
        targets = set()
        for name in _imports(path, which=which):
            parts = name.split(".")
            for cut in range(len(parts), 0, -1):
                if ".".join(parts[:cut]) in files:
                    targets.add(".".join(parts[:cut]))
                    break
        graph[module] = targets - {module}
    return graph


def _cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of the graph as a list of modules (its first one repeated at the end), or None."""
    state: dict[str, int] = {}
    trail: list[str] = []

    def visit(module: str) -> list[str] | None:
        state[module] = 1
        trail.append(module)
        for nxt in sorted(graph[module]):
            if state.get(nxt) == 1:
                return [*trail[trail.index(nxt) :], nxt]
            if nxt not in state and (found := visit(nxt)):
                return found
        trail.pop()
        state[module] = 2
        return None

    for module in sorted(graph):
        if module not in state and (found := visit(module)):
            return found
    return None


def test_cycle_finder():
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": set()}) is None
    assert _cycle({"a": {"b"}, "b": {"c"}, "c": {"b"}}) == ["b", "c", "b"]


def test_no_import_cycle_among_the_files():
    cycle = _cycle(_import_graph("load"))
    assert cycle is None, f"import cycle at load time: {' -> '.join(cycle or [])}"


def test_no_import_cycle_through_imports_inside_functions():
    """No cycle either where a function imports lazily a module that imports the function's own: such code
    belongs in the lower module (or the two in one)."""
    cycle = _cycle(_import_graph("run"))
    assert cycle is None, f"import cycle through an import inside a function: {' -> '.join(cycle or [])}"
