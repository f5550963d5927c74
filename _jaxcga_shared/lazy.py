"""Lazy public names for a package ``__init__``: each name is imported from its module on first use, so a program
that uses a few of a package's names (a command of the command line) does not pay for the imports of the rest
(libigl, optax, optimistix, the viewer). The PEP 562 module ``__getattr__`` of scientific Python's SPEC 1
(lazy_loader), with the names' sources written once, as ordinary imports under ``if TYPE_CHECKING:``, where type
checkers and the documentation read them.

    if TYPE_CHECKING:
        from deform._arap import arap_solve
        from _jaxcga_shared.viewer import view
    __getattr__, __dir__ = lazy_exports(__name__, __file__)
"""

from __future__ import annotations

import ast
import importlib
import sys
from collections.abc import Callable
from pathlib import Path


def type_checking_imports(path: str | Path) -> dict[str, tuple[str, str]]:
    """The ``from MODULE import NAME [as ALIAS]`` statements under ``if TYPE_CHECKING:`` at the top level of the
    module at ``path``: exported name -> (module, name in it)."""
    tree = ast.parse(Path(path).read_text(encoding="utf-8"))
    sources: dict[str, tuple[str, str]] = {}
    for node in tree.body:
        if isinstance(node, ast.If) and isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING":
            for statement in node.body:
                # relative or star imports would need the package's own resolution: refused, not guessed
                if not isinstance(statement, ast.ImportFrom) or statement.level or statement.module is None:
                    raise ImportError(f"{path}: only 'from MODULE import NAME' belongs under TYPE_CHECKING")
                for alias in statement.names:
                    if alias.name == "*":
                        raise ImportError(f"{path}: 'from {statement.module} import *' cannot be made lazy")
                    sources[alias.asname or alias.name] = (statement.module, alias.name)
    return sources


def lazy_exports(package: str, path: str) -> tuple[Callable[[str], object], Callable[[], list[str]]]:
    """``(__getattr__, __dir__)`` for the package ``package`` whose ``__init__`` is at ``path``: a name of its
    ``if TYPE_CHECKING:`` imports is imported on first access and kept in the package's namespace (later accesses
    are plain lookups); any other name is an ``AttributeError``, as for a module without ``__getattr__``."""
    sources = type_checking_imports(path)

    def __getattr__(name: str) -> object:
        try:
            module, attribute = sources[name]
        except KeyError:
            raise AttributeError(f"module {package!r} has no attribute {name!r}") from None
        value = getattr(importlib.import_module(module), attribute)
        setattr(sys.modules[package], name, value)
        return value

    def __dir__() -> list[str]:
        return sorted(set(vars(sys.modules[package])) | set(sources))

    return __getattr__, __dir__
