"""JAX's persistent compilation cache for the command line: a second run of a command loads what the first
compiled instead of compiling it again. The command line owns its process, so it may set JAX's global
configuration; the library never does (it leaves that choice to its caller)."""

from __future__ import annotations

import os
import pickle
import sys
import warnings
from pathlib import Path
from typing import Any, NamedTuple

NO_CACHE = "JAXCGA_NO_CACHE"  # set (to anything but "", "0" or "false"): compile afresh, write nothing
CACHE_DIR = "JAXCGA_CACHE_DIR"  # another directory for the cache than the user's cache directory


def directory() -> Path:
    """Where the cache lives: ``$JAXCGA_CACHE_DIR``, else ``jax`` in the user's cache directory (platformdirs:
    ``$XDG_CACHE_HOME/jaxcga`` or ``~/.cache/jaxcga`` on Linux, ``~/Library/Caches/jaxcga`` on macOS)."""
    chosen = os.environ.get(CACHE_DIR)
    if chosen:
        return Path(chosen).expanduser()
    from platformdirs import user_cache_dir

    return Path(user_cache_dir("jaxcga")) / "jax"


def disabled_by_environment() -> bool:
    """Whether ``$JAXCGA_NO_CACHE`` turns the cache off."""
    return os.environ.get(NO_CACHE, "").strip().lower() not in ("", "0", "false", "no")


def help_text() -> str:
    """The paragraph of ``jaxcga --help`` about the cache."""
    return (
        f"compiled code is cached in {directory()} (JAX's persistent compilation cache; ${CACHE_DIR} moves it), "
        f"so that a command's second run skips most of its compilation; --no-cache or {NO_CACHE}=1 turns the "
        "cache off, and deleting the directory empties it"
    )


def enable(command: str, no_cache: bool) -> Path | None:
    """Turn JAX's persistent compilation cache on in ``directory()`` (before anything is compiled), unless
    ``no_cache``, ``$JAXCGA_NO_CACHE`` or the caller's own JAX cache configuration (``JAX_COMPILATION_CACHE_DIR``)
    decides otherwise. A directory that cannot be made or written costs one warning line, not the command.
    Returns the directory in use, or None."""
    import jax

    if no_cache or disabled_by_environment():
        return None
    configured = getattr(jax.config, "jax_compilation_cache_dir", None)
    if configured:  # the user configured JAX's cache: theirs to keep
        return Path(configured)
    path = directory()
    try:
        path.mkdir(parents=True, exist_ok=True)
        # a file written and removed: permissions, a read-only file system, a full disk all show here
        probe = path / f".probe-{os.getpid()}"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as error:
        reason = error.strerror or type(error).__name__
        print(
            f"jaxcga {command}: warning: the compilation cache {path} is not writable ({reason}); compiling "
            f"afresh (set {CACHE_DIR} elsewhere or {NO_CACHE}=1 to silence this)",
            file=sys.stderr,
        )
        return None
    jax.config.update("jax_compilation_cache_dir", str(path))
    # every executable: a command compiles many small ones (eager operations of the precomputations), which
    # together take seconds and read back in milliseconds
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    global _calls
    _calls = ExportedCalls(path / "exported")
    return path


# the packages whose sources key an exported program: a changed line compiles afresh
_SOURCES = ("jaxcga", "deform", "cutting", "xfem", "_jaxcga_shared", "jaxcga_cli")


class ExportedCalls:
    """The command's compiled programs, exported (``jax.export``) into ``directory``: a second run reads a program
    back instead of tracing and lowering it again (JAX's compilation cache is keyed by the lowered program, so it
    saves the compilation alone; tracing the library's generated products takes longer than reading them back).

    ``calls(name, fn, *args, by_value=(), **kwargs)`` is ``fn(*args, **kwargs)`` for a function JAX can trace
    whose result is a tree of arrays; the positional arguments numbered in ``by_value`` are arrays the program
    holds as constants (``fn`` may compute with them on the host: a mesh's faces), the other arrays are its inputs.
    The key is the name, the input arrays' shapes and dtypes, the other arguments' values (the arrays given by value
    by a digest of their bytes), the JAX version and platform, and a digest of the packages' sources. The value
    checks of ``fn`` (``_jaxcga_shared.checks.collect_checks``) are outputs of the program and raise ``CheckError``
    as the library's own call would; warnings given while tracing are kept with the program and given again. A call
    the export cannot take (a host callback inside, an argument whose value has no stable text) runs as it is."""

    def __init__(self, directory: Path):
        self.directory = directory
        self._digest: str | None = None
        # a loop's step is called once per iteration (ARAP's host loop): its program is read once and called through
        # one jitted function, and its trees' text made once (Exported.call dispatches a fresh program per call)
        self._loaded: dict[Path, tuple[_Program | None, Any]] = {}
        self._tree_text: dict[Any, str] = {}

    def __call__(self, name: str, fn, *args, by_value: tuple[int, ...] = (), **kwargs):
        import jax

        try:
            key, leaves, static = self._key(name, args, kwargs, by_value)
        except _Uncacheable:
            return fn(*args, **kwargs)
        path = self.directory / f"{name}-{key[:32]}.jaxexport"
        if path in self._loaded:
            program, run = self._loaded[path]
        else:
            program, run = self._load(path, fn, leaves, static)
        if program is None:  # not exportable: plain (the plain call raises an error of the input as the library's)
            out = fn(*args, **kwargs)
            if path not in self._loaded:  # remembered for this process, and on disk for the next
                if not path.with_suffix(".plain").exists():
                    _write_bytes(path.with_suffix(".plain"), b"")
                self._loaded[path] = (None, None)
            return out
        self._loaded[path] = (program, run)
        for category, text in program.told:
            warnings.warn(text, _warning_category(category), stacklevel=2)
        out, flags = run(leaves)
        from _jaxcga_shared.checks import raise_collected

        raise_collected(jax.device_get(flags), tuple(program.messages))
        return jax.tree.unflatten(program.out_tree, out)

    @staticmethod
    def _load(path: Path, fn, leaves, static) -> tuple[_Program | None, Any]:
        """The program of ``path``, exported afresh when absent or unreadable, and its jitted call; (None, None)
        for a call found not exportable (then or before: its ``.plain`` marker)."""
        import jax

        if path.with_suffix(".plain").exists():
            return None, None
        program = _Program.read(path)
        if program is None:
            try:
                program = _Program.export(fn, leaves, static)
                data = program.to_bytes()
            except Exception:  # noqa: BLE001  not exportable (host values, a host callback, a result's tree)
                return None, None
            _write_bytes(path, data)
        return program, jax.jit(program.exported.call)

    def _key(self, name, args, kwargs, by_value):
        import hashlib

        import equinox as eqx
        import jax
        import numpy as np

        # the arrays given by value are part of the program (host work on them while tracing), keyed by their bytes
        held = {i: np.asarray(args[i]) for i in by_value}
        args = tuple(None if i in held else arg for i, arg in enumerate(args))
        dynamic, static = eqx.partition((args, kwargs), eqx.is_array)
        leaves, tree = jax.tree.flatten(dynamic)
        # the trees' own text, not the modules' pretty-printed repr (tens of milliseconds for a model)
        static_leaves, static_tree = jax.tree.flatten(static)
        values = [(i, a.shape, str(a.dtype), hashlib.sha256(a.tobytes()).hexdigest()) for i, a in held.items()]
        text = repr((self._text(tree), self._text(static_tree), static_leaves, values))
        if " at 0x" in text:  # an object without a value's text (a function, a default repr): no stable key
            raise _Uncacheable
        shapes = [(leaf.shape, str(leaf.dtype)) for leaf in leaves]
        platform = jax.default_backend()
        # x64 or not: what float64 becomes
        config = (jax.__version__, platform, str(jax.dtypes.canonicalize_dtype(np.float64)))
        if self._digest is None:
            self._digest = _sources_digest()
        key = hashlib.sha256(repr((name, text, shapes, config, self._digest)).encode()).hexdigest()
        return key, leaves, (tree, static, held)

    def _text(self, tree) -> str:
        try:
            known = self._tree_text.get(tree)
        except TypeError:  # a tree whose static values are not hashable
            return str(tree)
        if known is None:
            known = self._tree_text[tree] = str(tree)
        return known


class _Uncacheable(Exception):
    pass


class _Program(NamedTuple):
    """An exported program: its function of the arguments' arrays returns its result's arrays and the check flags."""

    exported: Any  # jax.export.Exported
    out_tree: Any  # the result's PyTreeDef (pickled: it may hold the library's own node types)
    messages: list[str]  # the checks' messages, one per flag
    told: list[tuple[str, str]]  # the warnings given while tracing: (category, text)

    @classmethod
    def export(cls, fn, leaves, static) -> _Program:
        import equinox as eqx
        import jax
        import jax.numpy as jnp

        from _jaxcga_shared.checks import collect_checks

        tree, rest, held = static
        collecting = collect_checks(fn)
        traced: dict = {}

        def program(leaves):
            args, kwargs = eqx.combine(jax.tree.unflatten(tree, leaves), rest)
            args = tuple(held.get(i, arg) for i, arg in enumerate(args))
            out, flags, messages = collecting(*args, **kwargs)
            outs, traced["tree"] = jax.tree.flatten(out)
            traced["messages"] = list(messages)
            return outs, jnp.zeros((0,), bool) if flags is None else flags

        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            exported = jax.export.export(jax.jit(program))(leaves)
        told = [(w.category.__name__, str(w.message)) for w in caught]
        return cls(exported, traced["tree"], traced["messages"], told)

    def to_bytes(self) -> bytes:
        """A header (messages, warnings), the result's tree and the serialized program, each after its length."""
        import io
        import json

        buffer = io.BytesIO()
        _TreePickler(buffer).dump(self.out_tree)
        tree = buffer.getvalue()
        if pickle.loads(tree) != self.out_tree:  # a node type that does not come back equal: not cached
            raise ValueError("the result's tree does not survive pickling")
        header = json.dumps({"messages": self.messages, "warnings": self.told}).encode()
        parts = (header, tree, bytes(self.exported.serialize()))
        return b"".join(len(part).to_bytes(8, "little") + part for part in parts)

    @classmethod
    def read(cls, path: Path) -> _Program | None:
        """The program in ``path``, or None when absent or unreadable (a file of another JAX or a corrupt one is
        exported afresh and overwritten)."""
        import json

        import jax

        try:
            data = path.read_bytes()
        except OSError:
            return None
        try:
            parts, at = [], 0
            for _ in range(3):
                size = int.from_bytes(data[at : at + 8], "little")
                parts.append(data[at + 8 : at + 8 + size])
                at += 8 + size
            header, tree, serialized = parts
            told = [(str(category), str(text)) for category, text in json.loads(header)["warnings"]]
            messages = list(json.loads(header)["messages"])
            return cls(jax.export.deserialize(bytearray(serialized)), pickle.loads(tree), messages, told)
        except Exception:  # noqa: BLE001  corrupt or foreign
            return None


def _equinox_missing():
    """Equinox's marker of a module's field left out of its tree (``eqx.partition``, and the trees of modules
    whose fields are static), compared by identity; None where this equinox keeps it elsewhere (results holding
    it are then not cached: ``tests/cli/test_cache.py`` fails loudly)."""
    try:
        from equinox._module._flatten import MISSING
    except ImportError:
        return None
    return MISSING


class _TreePickler(pickle.Pickler):
    """Pickles a result's tree with equinox's marker as a reference to the marker itself, so that the tree read
    back is equal to the tree written (a copy of the marker would not be the marker)."""

    def reducer_override(self, obj):
        if obj is not None and obj is _equinox_missing():
            return _equinox_missing, ()
        return NotImplemented


def _write_bytes(path: Path, data: bytes) -> None:
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f"{path.name}.{os.getpid()}.part")
        partial.write_bytes(data)
        os.replace(partial, path)
    except OSError:
        pass


def _warning_category(name: str) -> type[Warning]:
    import builtins

    category = getattr(builtins, name, UserWarning)
    return category if isinstance(category, type) and issubclass(category, Warning) else UserWarning


def _sources_digest() -> str:
    """A digest of the packages' Python sources (``_SOURCES``), found without importing them."""
    import hashlib
    import importlib.util

    digest = hashlib.sha256()
    for package in _SOURCES:
        spec = importlib.util.find_spec(package)
        if spec is None or not spec.submodule_search_locations:
            continue
        for root in spec.submodule_search_locations:
            for source in sorted(Path(root).rglob("*.py")):
                digest.update(str(source.relative_to(root)).encode())
                digest.update(source.read_bytes())
    return digest.hexdigest()


# the process's exported calls: set by ``enable`` (the command line owns its process); None: off
_calls: ExportedCalls | None = None


def call(name: str, fn, *args, by_value: tuple[int, ...] = (), **kwargs):
    """``fn(*args, **kwargs)`` through the exported programs of the cache when it is on (``ExportedCalls``)."""
    if _calls is None:
        return fn(*args, **kwargs)
    return _calls(name, fn, *args, by_value=by_value, **kwargs)
