"""The two tetrahedral mesh generators the packages use, behind one place that knows which is installed.

fTetWild (Hu et al. 2020, "Fast Tetrahedral Meshing in the Wild"; MPL-2.0, through the ``wildmeshing`` wheel) is
the required one: it meshes any triangle soup (open, self-intersecting, several parts) inside an envelope of
width ``epsilon`` around it and keeps the tets whose generalized winding number with respect to the input is
above 1/2. TetGen (AGPL-3.0, wrapper ``tetgen``) is an optional extra (``pip install jaxcga[tetgen]``): it keeps a
closed, clean surface exactly: cages and the ``octopus`` scene use it where it is installed, ``jaxcga fem`` on
request (``--mesher tetgen``). Private to the distribution.
"""

from __future__ import annotations

import importlib
from types import ModuleType

import numpy as np

from _jaxcga_shared.mesh import tet_face_matching

TETGEN_EXTRA = "TetGen is an optional extra (AGPL-3.0): pip install 'jaxcga[tetgen]'"


def optional_tetgen() -> ModuleType | None:
    """The ``tetgen`` module, or None where it is not installed (or an import of it is blocked)."""
    try:
        return importlib.import_module("tetgen")
    except ImportError:
        return None


def ftetwild(
    V: np.ndarray,
    F: np.ndarray,
    edge_length: float,
    epsilon: float,
    stop_quality: float = 10.0,
    max_iterations: int = 80,
    threads: int | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """fTetWild's tets of the inside of a triangle soup (host, numpy).

    fTetWild runs in a child process in a private temporary folder: it writes a debugging file
    (``__tracked_surface.stl``) into its working folder and prints its log on fd 1, neither of which a library
    may do to its user's process, and a crash of it (an abort on odd input) becomes an error here.

    Args:
        V: (n, 3) float64 vertices; F: (f, 3) int triangles.
        edge_length: the target edge length relative to the bounding box diagonal (fTetWild's ``-l``).
        epsilon: the envelope's width relative to the bounding box diagonal (fTetWild's ``-e``).
        stop_quality: the AMIPS energy below which the optimization stops (fTetWild's ``--stop-energy``).
        max_iterations: the optimization's passes at most (``--max-its``).
        threads: the worker threads; None: fTetWild's default (every core).
    Returns:
        TV (N, 3) float64 nodes, TT (t, 4) int64 tets (the inside, by the winding number).
    Raises:
        RuntimeError: fTetWild failed (its last output lines in the message).
    """
    import subprocess
    import sys
    import tempfile
    from pathlib import Path

    options = [float(edge_length), float(epsilon), float(stop_quality), int(max_iterations), int(threads or 0)]
    with tempfile.TemporaryDirectory(prefix="jaxcga-ftetwild-") as folder:
        np.savez(Path(folder) / "input.npz", V=np.asarray(V, np.float64), F=np.asarray(F, np.int32), options=options)
        done = subprocess.run(
            # -P: not this folder on sys.path, where platform.py would shadow the standard library's
            [sys.executable, "-P", str(Path(__file__).with_name("_ftetwild_worker.py"))],
            cwd=folder,
            capture_output=True,
            text=True,
            check=False,
        )
        result = Path(folder) / "output.npz"
        if done.returncode != 0 or not result.exists():
            tail = "\n".join((done.stdout + done.stderr).strip().splitlines()[-5:])
            raise RuntimeError(f"fTetWild failed (exit status {done.returncode}): {tail}")
        with np.load(result) as arrays:
            return np.asarray(arrays["TV"], np.float64), np.asarray(arrays["TT"], np.int64)


def embed(X: np.ndarray, T: np.ndarray, P: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points P (s, 3) in the tets T (m, 4) of nodes X (n, 3) (checked by the caller): the tet containing each
    point (libigl ``in_element`` on an AABB tree), else the tet of the nearest boundary face (libigl
    ``point_mesh_squared_distance``); returns element (s,) int64, barycentric coordinates (s, 4) float64
    (extrapolated outside the tet, so they still sum to 1 and reproduce affine maps) and the distance to the
    tets (s,) (0 inside)."""
    import igl

    tree = igl.AABB()
    tree.init(X, T)
    element = np.asarray(igl.in_element(X, T, P, tree), np.int64)
    distance = np.zeros(len(P))
    outside = np.flatnonzero(element < 0)
    if len(outside):
        faces, inverse, counts = tet_face_matching(T)
        boundary = counts[inverse] == 1
        d2, face, _ = igl.point_mesh_squared_distance(P[outside], X, faces.reshape(-1, 3)[boundary])
        element[outside] = np.flatnonzero(boundary)[np.asarray(face)] // 4
        distance[outside] = np.sqrt(np.asarray(d2))
    x = X[T[element]]
    edges = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)  # as columns
    lam = np.linalg.solve(edges, (P - x[:, 0])[..., None])[..., 0]
    return element, np.concatenate([1 - lam.sum(axis=1, keepdims=True), lam], axis=1), distance
