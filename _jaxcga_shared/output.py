"""Output files that survive failure, shared by the library's writers (``deform.save_model``) and the command line
(``jaxcga_cli``).

Every file is written to a temporary file in its own folder and renamed over the target (``os.replace``) only once
it is complete, so a failed write (a full disk, a file-size limit, an error half-way) leaves the previous file as
it was. Files written as a unit (a .gltf and its .bin, the two halves of a cut) are all written before any is
renamed. A run that writes a folder of files (``run_folder``) writes them into a private folder inside it and
moves them in when it ends, the file that marks a complete run last. The ``check_*`` functions check paths before
any work, with a ``ValueError`` naming the argument.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import secrets
import shutil
import stat
import tempfile
from collections.abc import Iterator
from pathlib import Path


def _write_protected(path: Path) -> bool:
    """No write permission for this process, or no write bit at all: a write-protected file or folder is left
    alone even by root, as ``rm`` asks before removing one."""
    return not os.access(path, os.W_OK) or not path.stat().st_mode & 0o222


def _sync(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def replacing(*paths) -> Iterator[tuple[Path, ...]]:
    """Temporary files beside ``paths`` (same folder, same suffix, so that writers infer the format), renamed over
    them together when the block ends without an error; removed, with ``paths`` untouched, when it raises.

    A missing folder is created. A symbolic link is followed: its target is replaced. Raises ``PermissionError``
    when a target is write-protected; an ``OSError`` of a write names the target, not the temporary file.
    """
    targets = tuple(Path(os.path.realpath(p)) if Path(p).is_symlink() else Path(p) for p in paths)
    temporary: list[Path] = []
    try:
        for target in targets:
            if target.is_dir():
                raise IsADirectoryError(21, "is a folder; expected a file name", str(target))
            if target.exists() and _write_protected(target):
                raise PermissionError(13, "write-protected; not replaced", str(target))
            target.parent.mkdir(parents=True, exist_ok=True)
            temp = target.with_name(f".{target.stem}.{secrets.token_hex(4)}.partial{target.suffix}")
            os.close(os.open(temp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666))
            temporary.append(temp)
            if target.is_file():  # keep the permissions of the file it replaces
                os.chmod(temp, stat.S_IMODE(target.stat().st_mode))
        try:
            yield tuple(temporary)
            for temp in temporary:
                _sync(temp)
        except OSError as error:
            if error.filename is None or str(error.filename) in map(str, temporary):
                what = ", ".join(str(t) for t in targets)
                raise type(error)(
                    error.errno, f"{error.strerror or error}; nothing written, left as before", what
                ) from error
            raise
        for temp, target in zip(temporary, targets):
            os.replace(temp, target)
    finally:
        for temp in temporary:
            temp.unlink(missing_ok=True)


def write_files(files: dict) -> None:
    """Write each ``{path: data}`` (bytes, or str as UTF-8) through one ``replacing``: none replaces an existing
    file unless all were written."""
    with replacing(*files) as temporary:
        for temp, data in zip(temporary, files.values()):
            temp.write_bytes(data.encode("utf-8") if isinstance(data, str) else data)


def write_bytes(path, data: bytes | str) -> None:
    """Write ``data`` (str as UTF-8) to ``path`` through ``replacing``."""
    write_files({path: data})


def write_json(path, data) -> None:
    """Write ``data`` as indented JSON through ``replacing``; a NaN or infinity is a ``ValueError`` (JSON has none)."""
    try:
        text = json.dumps(data, indent=1, allow_nan=False)
    except ValueError as error:
        raise ValueError(f"{path}: {error} (a non-finite number); not written") from None
    write_bytes(path, text)


def _check_writable_folder(folder: Path, what: str) -> None:
    """``folder``, or the nearest existing folder above it (missing ones are created): a folder this process may
    write in."""
    folder = folder.absolute()
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir():
        raise ValueError(f"{what}: {folder} is a file, not a folder")
    if _write_protected(folder) or not os.access(folder, os.X_OK):
        raise ValueError(f"{what}: cannot write in the folder {folder} (permission denied or write-protected)")


def check_output(path, suffixes: tuple[str, ...], what: str = "out") -> Path:
    """``path`` as a file to write: one of ``suffixes``, not a folder, not write-protected, in a folder this
    process may write in (or that can be created there). Returns it as a Path; ``ValueError`` otherwise."""
    path = Path(path)
    if path.suffix.lower() not in suffixes:
        listed = " or ".join(filter(None, (", ".join(suffixes[:-1]), suffixes[-1])))
        raise ValueError(f"{what}: expected a {listed} file, got {path}")
    if path.is_dir():
        raise ValueError(f"{what}: {path} is a folder; expected a file name")
    _check_writable_folder(path.parent, what)
    if path.exists() and _write_protected(path):
        raise ValueError(f"{what}: {path} is write-protected; not replaced")
    return path


def check_input(path, what: str) -> Path:
    """``path`` as a file to read: it exists and is a file; ``FileNotFoundError`` / ``ValueError`` otherwise."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{what}: no such file {path}")
    if not path.is_file():
        raise ValueError(f"{what}: {path} is not a file")
    return path


def check_distinct(outputs: dict[str, Path], inputs: dict[str, Path] | None = None) -> None:
    """No two ``outputs`` are the same file and none is one of ``inputs`` (argument name -> path; None skipped):
    one would overwrite the other. ``ValueError`` naming both arguments."""
    seen: dict[str, str] = {}
    for name, path in list((inputs or {}).items()) + list(outputs.items()):
        if path is None:
            continue
        key = os.path.realpath(path)
        if key in seen:
            kind = "input" if inputs and seen[key] in inputs else "output"
            raise ValueError(f"{name}: {path} is the same file as the {kind} {seen[key]}; give another file name")
        seen[key] = name


def check_folder(folder, what: str = "out") -> Path:
    """``folder`` as a folder to write files in: not a file, and this process may write in it (or in the
    nearest existing folder above it, where it is created). Returns it as a Path; ``ValueError`` otherwise."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{what}: {folder} is a file; expected a folder")
    _check_writable_folder(folder, what)
    return folder


def _run_files(folder: Path, own: re.Pattern) -> list[Path]:
    return sorted(p for p in folder.iterdir() if own.fullmatch(p.name) and p.is_file())


def check_run_folder(
    folder, own: re.Pattern, force: bool, described: str, what: str = "out", inputs: dict[str, Path] | None = None
) -> Path:
    """``folder`` as the folder of one run: not a file, in a folder this process may write in, and empty unless
    ``force`` (then its files matching ``own``, ``described`` in messages, are replaced at the end of the run;
    no other file is touched). An input among those files is refused. Returns it as a Path; ``ValueError``
    otherwise."""
    folder = check_folder(folder, what)
    if folder.is_dir() and any(folder.iterdir()):
        if not force:
            names = sorted(p.name for p in folder.iterdir())
            raise ValueError(
                f"{what}: the folder {folder} is not empty ({len(names)} "
                f"{'entry' if len(names) == 1 else 'entries'}: "
                f"{', '.join(names[:3])}{', ...' if len(names) > 3 else ''}); give --force to replace "
                f"the run in it (its {described}; nothing else is removed) or another folder"
            )
        old = {os.path.realpath(p) for p in _run_files(folder, own)}
        for name, path in (inputs or {}).items():
            if path is not None and os.path.realpath(path) in old:
                raise ValueError(f"{name}: {path} is a file of the run in {folder} that --force would remove")
    return folder


@contextlib.contextmanager
def run_folder(folder, own: re.Pattern, last: str) -> Iterator[Path]:
    """A private folder inside ``folder`` (created if missing) for the files of one run. When the block ends
    without an error, the previous run's files (those matching ``own``) are removed, ``last`` first, and the new
    files moved in, ``last`` last: a folder with ``last`` holds one complete run. When it raises, the private
    folder is removed and ``folder`` is as before (or removed again if the run created it)."""
    folder = Path(folder)
    created = not folder.exists()
    folder.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".partial-", dir=folder))
    try:
        try:
            yield staging
        except OSError as error:
            if error.filename is None or str(staging) in str(error.filename):
                raise type(error)(
                    error.errno,
                    f"{error.strerror or error}; the run's files were not written, the folder is as before",
                    str(folder),
                ) from error
            raise
        new = sorted(staging.iterdir(), key=lambda p: (p.name == last, p.name))
        for path in new:
            _sync(path)
        for path in sorted(_run_files(folder, own), key=lambda p: p.name != last):
            path.unlink()
        for path in new:
            os.replace(path, folder / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        if created:
            # the processes of one run (animate-batch) share the folder: another may have removed it already, or
            # staged in it since; either way it is theirs to leave, and this run's own error is the one to tell
            try:
                if not any(folder.iterdir()):
                    folder.rmdir()
            except FileNotFoundError:
                pass
            except OSError as error:
                if error.errno != errno.ENOTEMPTY:
                    raise
