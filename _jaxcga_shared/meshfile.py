"""Reading triangle mesh files as they are, for the commands that take a mesh file (``deform``, ``arap``, ``fem``)
and the viewer's topology of a mesh sequence."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np


def read_mesh_file(path: str | Path, name: str = "mesh", weld: bool = True):
    """(V, F) float64 / int64 of a triangle mesh file that trimesh reads (.obj, .ply, .stl, .off, .glb, ...).

    The file is read as it is (trimesh's ``process=False``); a non-finite vertex raises, naming its line
    (OBJ) or its index. Vertices at the same position are then merged (an STL stores every corner apart,
    other formats split vertices along UV seams), faces left with two equal corners are dropped, and so
    are vertices no face uses: whatever this changes is reported by a ``UserWarning``. ``weld=False`` returns the
    file's vertices and faces as they are.

    Raises:
        FileNotFoundError: no such file. ValueError: a file trimesh cannot read, one without triangles,
        a non-finite vertex (``name`` starts the message).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{name}: no such file {path}")
    try:
        loaded = trimesh.load(path, force="mesh", process=False)
    except (ValueError, KeyError, IndexError, TypeError, AttributeError) as error:  # trimesh's parsers
        line = _bad_obj_vertex(path) or _bad_obj_face(path)
        raise ValueError(
            f"{name}: {path}: {line}" if line else f"{name}: trimesh cannot read {path} ({error})"
        ) from None
    # trimesh wraps some indices outside the file (0, or -k past the vertices read) around silently
    line = _bad_obj_face(path)
    if line:
        raise ValueError(f"{name}: {path}: {line}")
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise ValueError(f"{name}: {path} holds no triangles")
    V, F = np.asarray(loaded.vertices, np.float64), np.asarray(loaded.faces, np.int64)
    if V.ndim != 2 or V.shape[1] != 3 or not np.isfinite(V).all():
        raise ValueError(f"{name}: {path}: {_bad_vertex(path, V)}")
    if not weld:
        return V, F
    welded = trimesh.Trimesh(V, F, process=False)
    welded.merge_vertices()
    W, G = np.asarray(welded.vertices, np.float64), np.asarray(welded.faces, np.int64)
    keep = (G[:, 0] != G[:, 1]) & (G[:, 1] != G[:, 2]) & (G[:, 2] != G[:, 0])
    if keep.all() and len(W) == len(V):
        return V, F
    used = np.zeros(len(W), bool)
    used[G[keep]] = True
    renumber = np.cumsum(used) - 1
    W, G = W[used], renumber[G[keep]]
    if len(G) == 0:
        raise ValueError(f"{name}: {path} holds no triangle with three distinct corners")
    warnings.warn(
        f"{name}: {path}: welded {len(V)} vertices into {len(W)} (same positions merged, unused ones "
        f"dropped) and dropped {int((~keep).sum())} of {len(F)} faces with two equal corners",
        stacklevel=2,
    )
    return W, G


def _bad_obj_vertex(path: Path) -> str | None:
    """The first line of an OBJ file's vertices that is not three finite numbers (trimesh may renumber OBJ
    vertices, so their lines say where they are), or None."""
    if path.suffix.lower() != ".obj":
        return None
    with open(path, errors="replace") as file:
        for number, line in enumerate(file, 1):
            words = line.split()
            if words[:1] == ["v"]:
                try:
                    good = len(words) >= 4 and np.isfinite(np.asarray(words[1:4], np.float64)).all()
                except ValueError:
                    good = False
                if not good:
                    return f"line {number}: {line.strip()!r} is not a vertex of three finite numbers"
    return None


def _bad_obj_face(path: Path) -> str | None:
    """The first line of an OBJ file's faces that refers to a vertex the file does not have (OBJ counts from 1;
    a negative index counts back from the vertices read so far), or None."""
    if path.suffix.lower() != ".obj":
        return None
    with open(path, errors="replace") as file:
        lines = file.readlines()
    total = sum(line.split()[:1] == ["v"] for line in lines)
    seen = 0
    for number, line in enumerate(lines, 1):
        words = line.split()
        if words[:1] == ["v"]:
            seen += 1
        elif words[:1] == ["f"]:
            for corner in words[1:]:
                try:
                    index = int(corner.split("/")[0])
                except ValueError:
                    return f"line {number}: {line.strip()!r}: {corner!r} is not a vertex index"
                if index == 0:
                    return f"line {number}: {line.strip()!r} refers to vertex 0 (OBJ counts vertices from 1)"
                if index > total or -index > seen:
                    have = f"{total} vertices" if index > 0 else f"{seen} vertices before this line"
                    return f"line {number}: {line.strip()!r} refers to vertex {index}, but the file has {have}"
    return None


def _bad_vertex(path: Path, V) -> str:
    """Where the first vertex that is not three finite numbers is: its OBJ line, else its index."""
    line = _bad_obj_vertex(path)
    if line:
        return line
    if V.ndim != 2 or V.shape[1] != 3:
        return f"vertices of shape {V.shape}, expected (n, 3)"
    bad = ~np.isfinite(V).all(axis=1)
    count = f"{int(bad.sum())} non-finite vertices" if bad.sum() > 1 else "a non-finite vertex"
    first = int(np.argmax(bad))
    return f"{count}, the first is vertex {first}: {V[first].tolist()}"


def read_array_file(path: str | Path, name: str, mmap: bool = False) -> np.ndarray:
    """The array in the .npy file ``path``, its header checked first so that a bad file is told in its own terms:
    not a .npy file, a pickled (object) array, or truncated (fewer bytes than its header states).

    Args:
        path: the .npy file.
        name: what the caller calls it (an option's name); starts every message.
        mmap: map the file read-only instead of reading it (the viewer reads shapes of large frames so).

    Raises:
        FileNotFoundError: no such file. ValueError: any of the above, naming ``name`` and the file.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{name}: no such file {path}")
    fmt = np.lib.format
    with open(path, "rb") as file:
        try:
            version = fmt.read_magic(file)
            read_header = fmt.read_array_header_1_0 if version == (1, 0) else fmt.read_array_header_2_0
            shape, _, dtype = read_header(file)
        except (ValueError, OSError, EOFError) as error:
            raise ValueError(f"{name}: {path} is not a .npy file (np.save writes one): {error}") from None
        start = file.tell()
    if dtype.hasobject:
        raise ValueError(f"{name}: {path} holds Python objects (a pickled array), not numbers; it is not read")
    need = start + int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    have = path.stat().st_size
    if have < need:
        raise ValueError(
            f"{name}: {path} is truncated: {have} of the {need} bytes its header states for a {dtype} array of "
            f"shape {shape}"
        )
    return np.load(path, mmap_mode="r" if mmap else None, allow_pickle=False)
