"""Tetrahedral meshes: the meshed domain Omega with nodes V and elements E of sec. 3.2 of the XFEM paper
(Ton-That, Kry, Andrews, "Generalized eXtended Finite Element Method for Deformable Cutting via Boolean
Operations"), on which the linear shape functions of eq. 5 (``xfem._linear_tet``) and the integrals of
eqs. 7-9 live.

``TetMesh`` bundles the rest positions X (n, 3) and the tets T (m, 4), positively oriented: the signed
volume ``(X1 - X0) . ((X2 - X0) x (X3 - X0)) / 6`` of every tet is > 0. ``tet_mesh`` validates and orients
raw arrays; ``box_tets``, ``five_tet_cube`` and ``one_tet`` generate meshes; ``tetrahedralize`` meshes
the inside of a closed triangle surface with TetGen (any surface: ``xfem.tetrahedralize_surface``, fTetWild);
``read_tet_mesh`` reads any format meshio reads.
The topology helpers (``boundary_faces``, ``node_rings``, ``element_adjacency``) run on the host in
vectorized numpy; ``tet_volumes`` is JAX and differentiable in X.

TetGen is AGPL-3.0 (its Python wrapper ``tetgen`` is MIT): an optional extra (``pip install jaxcga[tetgen]``),
used as a separate library where it is installed.
"""

from __future__ import annotations

import os
from pathlib import Path

import equinox as eqx
import igl.copyleft.cgal
import jax
import jax.numpy as jnp
import meshio
import numpy as np
import numpy.typing as npt
import trimesh
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_index_range, check_points, check_triangle_mesh, require
from _jaxcga_shared.host import quiet_stdout
from _jaxcga_shared.mesh import tet_boundary_faces, tet_face_matching
from _jaxcga_shared.tetmeshing import TETGEN_EXTRA, optional_tetgen

# a tet is degenerate when |6 V| <= this times the cube of its longest edge (a regular tet has 0.707)
_DEGENERATE = 1e-12


class TetMesh(eqx.Module):
    """A tetrahedral mesh (build it with ``tet_mesh`` or a generator, which validate and orient it).

    Attributes:
        X: (n, 3) float rest positions of the nodes.
        T: (m, 4) int tets, indices into X, positively oriented (signed volume > 0). Every node is in
            at least one tet.
    """

    X: Float[Array | np.ndarray, "n 3"]
    T: Int[Array | np.ndarray, "m 4"]

    @property
    def n_nodes(self) -> int:
        return self.X.shape[0]

    @property
    def n_elements(self) -> int:
        return self.T.shape[0]

    def volumes(self) -> Float[Array, " m"]:
        """(m,) the tets' volumes (``tet_volumes``)."""
        return tet_volumes(self.X, self.T)

    def boundary_faces(self) -> Int[np.ndarray, "k 3"]:
        """(k, 3) the outward oriented boundary triangles (``boundary_faces``; host, numpy)."""
        return boundary_faces(np.asarray(self.T))


def _host_tets(T, n: int | None = None, name: str = "T") -> np.ndarray:
    """T as an int64 (m, 4) numpy array with indices in [0, n) (n None: only >= 0), or ValueError."""
    T = np.asarray(T)
    if T.ndim != 2 or T.shape[1] != 4 or not np.issubdtype(T.dtype, np.integer):
        raise ValueError(f"{name}: expected integer tets of shape (m, 4), got {T.dtype} {T.shape}")
    check_index_range(name, T, n, "node")
    return T.astype(np.int64)


def _jax_mesh_arrays(X, T):
    """Trace-time shape and dtype checks of X (n, 3) float and T (m, 4) int for the JAX functions."""
    X, T = jnp.asarray(X), jnp.asarray(T)
    if X.ndim != 2 or X.shape[1] != 3 or not jnp.issubdtype(X.dtype, jnp.floating):
        raise ValueError(f"X: expected float positions of shape (n, 3), got {X.dtype} {X.shape}")
    if T.ndim != 2 or T.shape[1] != 4 or not jnp.issubdtype(T.dtype, jnp.integer):
        raise ValueError(f"T: expected integer tets of shape (m, 4), got {T.dtype} {T.shape}")
    return X, T


def _bad_index(T, n: int):
    """Node indices out of range, which a JAX gather would clamp silently (message: ``_index_message``)."""
    return jnp.any((T < 0) | (T >= n))


def _index_message(n: int) -> str:
    return f"T: node indices must lie in [0, {n})"


def _host_volumes(X: np.ndarray, T: np.ndarray) -> np.ndarray:
    """(m,) signed volumes in float64 numpy (the host twin of ``tet_volumes``)."""
    x = X[T]
    return np.einsum("ij,ij->i", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6


def tet_volumes(X: Float[ArrayLike, "n 3"], T: Int[ArrayLike, "m 4"]) -> Float[Array, " m"]:
    """Signed volumes ``(X1 - X0) . ((X2 - X0) x (X3 - X0)) / 6`` of the tets (JAX, differentiable in X).

    Args:
        X: (n, 3) float node positions.
        T: (m, 4) int tets.
    Returns:
        (m,) signed volumes, > 0 for positively oriented tets.

    Examples:
        >>> import xfem
        >>> tet = xfem.one_tet()
        >>> [round(v, 6) for v in xfem.tet_volumes(tet.X, tet.T).tolist()]
        [0.166667]
    """
    X, T = _jax_mesh_arrays(X, T)
    volumes, bad = _tet_volumes(X, T)
    return require(volumes, (bad, _index_message(X.shape[0])))


@jax.jit
def _tet_volumes(X, T):
    x = X[T]
    a, b, c = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    return jnp.sum(a * jnp.cross(b, c), axis=-1) / 6, _bad_index(T, X.shape[0])


def tet_mesh(X: Float[npt.ArrayLike, "n 3"], T: Int[npt.ArrayLike, "m 4"]) -> TetMesh:
    """Validate raw arrays and orient every tet positively.

    Args:
        X: (n, 3) real, finite node positions (stored as float64, float32 when JAX runs without x64).
        T: (m, 4) integer tets, indices into X; any orientation (a negatively oriented tet gets its last
            two vertices swapped).
    Returns:
        The ``TetMesh``.
    Raises:
        ValueError: bad shapes or dtypes, non-finite X, indices out of range, a degenerate (flat or
            repeated-vertex) tet, or nodes in no tet (they would make the mass matrix singular; drop
            them first).
    """
    X = check_points("X", X)
    T = _host_tets(T, len(X))
    if len(T) == 0:
        raise ValueError("T: expected at least one tetrahedron")
    volume = _host_volumes(X, T)
    x = X[T]
    edges = x[:, [1, 2, 3, 2, 3, 3]] - x[:, [0, 0, 0, 1, 1, 2]]
    longest = np.linalg.norm(edges, axis=2).max(axis=1)
    flat = np.flatnonzero(np.abs(6 * volume) <= _DEGENERATE * longest**3)
    if len(flat):
        e = int(flat[0])
        raise ValueError(f"T: {len(flat)} degenerate (zero-volume) tetrahedra, the first is tet {e} = {T[e].tolist()}")
    unused = np.setdiff1d(np.arange(len(X)), T)
    if len(unused):
        raise ValueError(
            f"X: nodes {unused[:10].tolist()}{' ...' if len(unused) > 10 else ''} "
            f"({len(unused)} in all) are in no tetrahedron"
        )
    T = np.where((volume < 0)[:, None], T[:, [0, 1, 3, 2]], T)
    return TetMesh(jnp.asarray(X), jnp.asarray(T))


def _triple(value, name: str, kind: type) -> tuple:
    try:
        values = tuple(kind(v) for v in value)
    except (TypeError, ValueError):
        values = ()
    if len(values) != 3:
        raise ValueError(f"{name}: expected three {kind.__name__}s, got {value!r}")
    return values


def box_tets(
    cells: tuple[int, int, int] | Int[npt.ArrayLike, " 3"] = (1, 1, 1),
    size: tuple[float, float, float] | Float[npt.ArrayLike, " 3"] = (1.0, 1.0, 1.0),
    origin: tuple[float, float, float] | Float[npt.ArrayLike, " 3"] = (0.0, 0.0, 0.0),
) -> TetMesh:
    """The box ``origin + [0, size]`` as a grid of cells, each split into 6 tets (Kuhn / Freudenthal split).

    Every tet of a cell runs from its lowest corner to its highest corner along the cell's edges, one tet per
    order of the axes, so every face of a cell is cut along the same diagonal as its neighbour's face: the
    mesh is conforming. Node (i, j, k) (i along x) has index ``(i * (cells[1] + 1) + j) * (cells[2] + 1) + k``.

    Args:
        cells: (3,) positive ints, the cells along x, y, z.
        size: (3,) positive box extents.
        origin: (3,) the lowest corner.
    Returns:
        The ``TetMesh`` with ``prod(cells + 1)`` nodes and ``6 prod(cells)`` tets, each of volume
        ``prod(size / cells) / 6``.

    Examples:
        >>> import xfem
        >>> mesh = xfem.box_tets((2, 1, 1), size=(2.0, 1.0, 1.0))  # two unit cells
        >>> mesh.X.shape, mesh.T.shape
        ((12, 3), (12, 4))
    """
    cells = _triple(cells, "cells", int)
    if min(cells) < 1:
        raise ValueError(f"cells: expected three ints >= 1, got {cells}")
    size = np.array(_triple(size, "size", float))
    if not np.all(np.isfinite(size)) or size.min() <= 0:
        raise ValueError(f"size: expected three positive extents, got {size.tolist()}")
    origin = np.array(_triple(origin, "origin", float))
    if not np.all(np.isfinite(origin)):
        raise ValueError(f"origin: expected a finite point, got {origin.tolist()}")
    axes = [np.linspace(0.0, s, c + 1) for s, c in zip(size, cells)]
    X = origin + np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    index = np.arange(len(X)).reshape(*(c + 1 for c in cells))
    low = index[:-1, :-1, :-1].ravel()
    step = np.array([(cells[1] + 1) * (cells[2] + 1), cells[2] + 1, 1])  # index offsets along x, y, z
    tets = []
    for order, even in (
        ((0, 1, 2), True),
        ((1, 2, 0), True),
        ((2, 0, 1), True),
        ((0, 2, 1), False),
        ((2, 1, 0), False),
        ((1, 0, 2), False),
    ):
        path = np.cumsum(step[list(order)])  # the corners after one, two and three steps
        corners = [low, low + path[0], low + path[1], low + path[2]]
        if not even:  # an odd order of the axes flips the orientation
            corners[2], corners[3] = corners[3], corners[2]
        tets.append(np.stack(corners, axis=1))
    T = np.stack(tets, axis=1).reshape(-1, 4)  # the six tets of a cell are consecutive
    return TetMesh(jnp.asarray(X), jnp.asarray(T))


def five_tet_cube(
    size: float = 1.0, origin: tuple[float, float, float] | Float[npt.ArrayLike, " 3"] = (0.0, 0.0, 0.0)
) -> TetMesh:
    """The cube ``origin + [0, size]^3`` as 5 tets: a central regular tet on the four corners of even
    parity (volume 1/3 of the cube) and one tet at each odd corner (volume 1/6 each).

    Node c is the corner ``origin + size * ((c >> 2) & 1, (c >> 1) & 1, c & 1)``; tet 0 is the central one.

    Args:
        size: the positive edge length.
        origin: (3,) the lowest corner.
    Returns:
        The ``TetMesh`` with 8 nodes and 5 tets.

    Examples:
        >>> import xfem
        >>> cube = xfem.five_tet_cube()
        >>> cube.T.shape, round(float(xfem.tet_volumes(cube.X, cube.T).sum()), 6)
        ((5, 4), 1.0)
    """
    size = float(size)
    if not np.isfinite(size) or size <= 0:
        raise ValueError(f"size: expected a positive edge length, got {size}")
    origin = np.array(_triple(origin, "origin", float))
    if not np.all(np.isfinite(origin)):
        raise ValueError(f"origin: expected a finite point, got {origin.tolist()}")
    corners = (np.arange(8)[:, None] >> np.array([2, 1, 0])) & 1
    T = np.array([[0, 3, 6, 5], [1, 0, 3, 5], [2, 0, 6, 3], [4, 0, 5, 6], [7, 3, 5, 6]])
    return tet_mesh(origin + size * corners, T)


def one_tet() -> TetMesh:
    """The unit corner tetrahedron: nodes (0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), volume 1/6.

    Returns:
        The ``TetMesh`` of one element.
    Examples:
        >>> import xfem
        >>> mesh = xfem.one_tet()
        >>> mesh.X.shape, mesh.T.shape
        ((4, 3), (1, 4))
    """
    return tet_mesh(np.vstack([np.zeros(3), np.eye(3)]), np.array([[0, 1, 2, 3]]))


def tetrahedralize(
    V: Float[npt.ArrayLike, "v 3"], F: Int[npt.ArrayLike, "f 3"], max_volume: float | None = None, quality: bool = True
) -> TetMesh:
    """Tetrahedralize the inside of a closed triangle surface with TetGen (an optional extra: ``pip install
    jaxcga[tetgen]``; ``tetrahedralize_surface`` is the fTetWild alternative for any surface).

    TetGen keeps the surface: the input vertices are the first ``len(V)`` nodes, unchanged, and the
    boundary faces cover the input triangles exactly (it may split a triangle with Steiner points on it,
    never move it).

    Args:
        V: (v, 3) finite surface vertices, each on some face.
        F: (f, 3) int triangles of a closed (watertight) surface without self-intersections.
        max_volume: None, or the largest tet volume wanted (absolute units; TetGen's switch ``a``, which it
            honours only approximately: measured up to ~1.2x on a box).
        quality: refine to a radius-edge ratio <= 1.414 (TetGen's ``q1.414``); False: the coarsest
            constrained Delaunay tetrahedralization (switch ``p`` alone).
    Returns:
        The ``TetMesh``.
    Raises:
        ValueError: bad shapes, an open or self-intersecting surface, unused or duplicate vertices, a bad
            max_volume, a surface TetGen fails on.
        ModuleNotFoundError: TetGen is not installed.
    """
    tetgen = optional_tetgen()
    if tetgen is None:
        raise ModuleNotFoundError(f"tetrahedralize needs TetGen: {TETGEN_EXTRA}; or use xfem.tetrahedralize_surface")
    V, F = check_triangle_mesh(V, F, min_faces=4)
    unused = np.setdiff1d(np.arange(len(V)), F)
    if len(unused):
        raise ValueError(f"V: vertices {unused[:10].tolist()} ({len(unused)} in all) are on no face of F")
    if len(np.unique(V, axis=0)) < len(V):  # TetGen would merge them and leave nodes in no tet
        raise ValueError("V: duplicate vertex positions; weld the surface first (trimesh merge_vertices)")
    if not trimesh.Trimesh(V, F, process=False).is_watertight:
        raise ValueError("F: the surface is not closed (trimesh is_watertight is False); TetGen needs a closed one")
    # TetGen reports self-intersections but corrupts the heap doing so (measured: "free(): invalid next size"
    # and an abort later): detect them first (CGAL, exact predicates)
    pairs = np.asarray(  # igl's stubs type the result ArrayLike
        igl.copyleft.cgal.remesh_self_intersections(V, F.astype(np.int64), detect_only=True, first_only=True)[2]
    )
    if len(pairs):
        raise ValueError(f"F: the surface intersects itself (faces {int(pairs[0, 0])} and {int(pairs[0, 1])} cross)")
    switches = "pMQ" + ("q1.414" if quality else "")  # M: no merging of coplanar facets, the surface is kept
    if max_volume is not None:
        if not np.isfinite(max_volume) or max_volume <= 0:
            raise ValueError(f"max_volume: expected None or a positive volume, got {max_volume}")
        switches += f"a{float(max_volume):.17g}"
    try:
        with quiet_stdout():
            TV, TT = tetgen.TetGen(V, F.astype(np.int32)).tetrahedralize(switches=switches)[:2]
    except RuntimeError as error:
        raise ValueError(f"F: TetGen failed to tetrahedralize the surface ({error})") from None
    return tet_mesh(np.asarray(TV, np.float64), np.asarray(TT, np.int64))


def read_tet_mesh(path: str | os.PathLike) -> TetMesh:
    """Read the tetrahedra of a volume mesh file (any format meshio reads: .vtu, .vtk, .msh, .mesh, ...).

    All "tetra" cell blocks are taken, other cells ignored; nodes in no tetrahedron (gmsh's geometry points,
    nodes of surface-only parts) are dropped and the others renumbered in their order.

    Args:
        path: the file.
    Returns:
        The ``TetMesh``.
    Raises:
        ValueError: a file meshio cannot read, one without tetrahedra, degenerate tets.
    """
    path = Path(path)
    try:
        mesh = meshio.read(path)
    # meshio raises SystemExit (it calls sys.exit) on a file it cannot parse in the format its suffix names
    except (meshio.ReadError, OSError, KeyError, ValueError, SystemExit) as error:
        reason = "no reader of its suffix's formats accepts it" if isinstance(error, SystemExit) else repr(error)
        raise ValueError(f"path: meshio cannot read {str(path)!r} ({reason})") from None
    blocks = [np.asarray(block.data) for block in mesh.cells if block.type == "tetra"]
    if not blocks:
        types = sorted({block.type for block in mesh.cells})
        raise ValueError(f"path: {str(path)!r} has no tetra cells (cell types: {types})")
    T = np.concatenate(blocks).astype(np.int64)
    points = np.asarray(mesh.points)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"path: {str(path)!r} holds points of shape {points.shape}, expected (n, 3)")
    used, T = np.unique(T, return_inverse=True)
    return tet_mesh(points[used], T.reshape(-1, 4))


def _face_matching(T):
    """``tet_face_matching`` of the checked tets T."""
    return tet_face_matching(_host_tets(T))


def boundary_faces(T: Int[npt.ArrayLike, "m 4"]) -> Int[np.ndarray, "k 3"]:
    """The boundary triangles: faces used by exactly one tet, oriented outward (their normal points away
    from their tet when T is positively oriented).

    Args:
        T: (m, 4) int tets.
    Returns:
        (k, 3) int64 numpy triangles, in the order of ``np.nonzero(element_adjacency(T) < 0)`` (by tet, then
        by the local vertex the face is opposite to).

    Examples:
        >>> import xfem
        >>> xfem.boundary_faces(xfem.one_tet().T).shape  # a lone tetrahedron: its four faces
        (4, 3)
    """
    return tet_boundary_faces(_host_tets(T))


def element_adjacency(T: Int[npt.ArrayLike, "m 4"]) -> Int[np.ndarray, "m 4"]:
    """The neighbours of the tets across their faces.

    Args:
        T: (m, 4) int tets.
    Returns:
        (m, 4) int64 numpy: entry (e, a) is the tet sharing the face of tet e opposite its local vertex a,
        -1 on the boundary.
    Raises:
        ValueError: a face shared by more than two tets.
    """
    faces, inverse, _ = _face_matching(T)
    order = np.argsort(inverse, kind="stable")
    pair = np.flatnonzero(inverse[order][1:] == inverse[order][:-1])  # counts <= 2: consecutive equal keys
    first, second = order[pair], order[pair + 1]
    adjacency = np.full(inverse.shape, -1, np.int64)
    adjacency[first] = second // 4
    adjacency[second] = first // 4
    return adjacency.reshape(-1, 4)


def node_rings(
    T: Int[npt.ArrayLike, "m 4"], n: int | None = None
) -> tuple[Int[np.ndarray, " n+1"], Int[np.ndarray, " 4*m"]]:
    """The tets incident to each node (the one-ring E^i of sec. 3.2), in compressed-row form.

    Args:
        T: (m, 4) int tets.
        n: the number of nodes (>= T.max() + 1); None: T.max() + 1.
    Returns:
        offsets (n + 1,) and elements (4m,) int64 numpy: the tets of node i are
        ``elements[offsets[i]:offsets[i + 1]]``, in increasing order.
    """
    T = _host_tets(T)
    needed = int(T.max()) + 1 if T.size else 0
    if n is None:
        n = needed
    elif int(n) != n or n < needed:
        raise ValueError(f"n: expected an int >= T.max() + 1 = {needed}, got {n!r}")
    flat = T.ravel()
    elements = np.argsort(flat, kind="stable") // 4
    offsets = np.concatenate([[0], np.cumsum(np.bincount(flat, minlength=int(n)))])
    return offsets, elements
