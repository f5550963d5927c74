"""Volumes from real surfaces: robust tetrahedralization of open, self-intersecting, multi-part triangle
surfaces by fTetWild (Hu et al. 2020, "Fast Tetrahedral Meshing in the Wild", MPL-2.0), the user's surface
embedded in the tets, and the tets' quality.

``tetrahedralize_surface`` meshes the inside of a surface as fTetWild defines it (the generalized winding number
of the input above 1/2, within an envelope of width ``epsilon``), so a character's clothing layers, inner meshes
and open seams are all accepted; the tets do not keep the surface, they only come within the envelope of it.
The surface therefore rides along *embedded*: ``embed_points`` gives every point its tet and barycentric
coordinates, and ``SurfaceEmbedding.positions`` carries it along with the tets' nodes by that sparse linear map
(differentiable in the nodes). ``tet_quality`` measures the mesh: the smallest dihedral angle and the volume
ratio ``6 sqrt(2) V / e_rms^3`` (1 for a regular tet, 0 for a flat one; e_rms is the root mean square of its
six edge lengths). After an XFEM cut ``cut_surface`` gives the surface in pieces, each triangle following the
side of the cut its centroid lies on.
"""

from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Array, ArrayLike, Float, Int

from _jaxcga_shared.checks import check_faces, check_points, check_triangle_mesh
from _jaxcga_shared.mesh import bounding_diagonal
from _jaxcga_shared.platform import EXACT
from _jaxcga_shared.tetmeshing import embed, ftetwild
from xfem._tetmesh import TetMesh, tet_mesh
from xfem._xfem import XFEMModel

# the defaults, as fractions of the bounding-box diagonal: coarse enough that a character meshes in about a minute
EDGE_LENGTH = 0.05
EPSILON = 1e-3

# the six edges of a tet (corner pairs) and, for the dihedral angle at each, the two faces (opposite corners)
# that meet there: edge (i, j) lies on the faces opposite the other two corners
_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]])
_EDGE_FACES = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]])


class TetQuality(NamedTuple):
    """The quality of a tet mesh (``tet_quality``).

    Attributes:
        tets, nodes: the counts.
        min_dihedral_deg, max_dihedral_deg: the smallest and largest dihedral angle in degrees (a regular tet's
            are all arccos(1/3) = 70.53).
        min_volume_ratio, mean_volume_ratio: the worst and the mean volume ratio ``6 sqrt(2) V / e_rms^3``, V the
            tet's volume and e_rms the root mean square of its six edge lengths: 1 for a regular tet, towards 0
            for a flat one.
    """

    tets: int
    nodes: int
    min_dihedral_deg: float
    max_dihedral_deg: float
    min_volume_ratio: float
    mean_volume_ratio: float


def volume_ratios(x: np.ndarray) -> np.ndarray:
    """(m,) ``6 sqrt(2) volume / rms edge^3`` of the tets of corners x (m, 4, 3), signed: 1 for a regular tet, 0 for
    a flat one, negative for an inverted one (``tet_quality``'s volume ratio is its magnitude)."""
    edges = x[:, _EDGES[:, 1]] - x[:, _EDGES[:, 0]]
    rms = np.sqrt(np.mean(np.einsum("med,med->me", edges, edges), axis=1))
    volume = np.einsum("md,md->m", x[:, 1] - x[:, 0], np.cross(x[:, 2] - x[:, 0], x[:, 3] - x[:, 0])) / 6
    return 6 * np.sqrt(2) * volume / rms**3


def tet_quality(mesh: TetMesh) -> TetQuality:
    """The tet count, dihedral angles and volume ratios of a mesh (``TetQuality``; host, numpy).

    Args:
        mesh: the ``TetMesh``.
    Returns:
        The ``TetQuality``.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh: expected a TetMesh, got {type(mesh).__name__}")
    X, T = np.asarray(mesh.X, np.float64), np.asarray(mesh.T, np.int64)
    x = X[T]  # (m, 4, 3)
    # outward normals of the face opposite each corner: n_k points away from corner k
    normals = np.stack(
        [np.cross(x[:, (k + 2) % 4] - x[:, (k + 1) % 4], x[:, (k + 3) % 4] - x[:, (k + 1) % 4]) for k in range(4)],
        axis=1,
    )
    normals *= np.sign(np.einsum("mkd,mkd->mk", normals, x[:, [(k + 1) % 4 for k in range(4)]] - x))[..., None]
    normals /= np.linalg.norm(normals, axis=2, keepdims=True)
    cosines = np.einsum("med,med->me", normals[:, _EDGE_FACES[:, 0]], normals[:, _EDGE_FACES[:, 1]])
    dihedral = 180.0 - np.degrees(np.arccos(np.clip(cosines, -1.0, 1.0)))  # interior angle = pi - normals' angle
    ratio = np.abs(volume_ratios(x))
    return TetQuality(
        tets=len(T),
        nodes=len(X),
        min_dihedral_deg=float(dihedral.min()),
        max_dihedral_deg=float(dihedral.max()),
        min_volume_ratio=float(ratio.min()),
        mean_volume_ratio=float(ratio.mean()),
    )


class SurfaceEmbedding(eqx.Module):
    """Points embedded in a tet mesh (``embed_points``): each point moves with the linear interpolation of its tet's
    nodes, ``p = sum_a weights[:, a] x[nodes[:, a]]``.

    Attributes:
        element: (s,) int64 the tet of each point: the one containing it, else the nearest one.
        nodes: (s, 4) int64 that tet's nodes.
        weights: (s, 4) float64 the point's barycentric coordinates in it (they sum to 1; outside the tet they
            extrapolate its linear map, so an affine motion of the nodes still moves the point by that motion).
        distance: (s,) float64 the point's distance to the tet mesh (0 inside).
    """

    element: Int[np.ndarray, " s"]
    nodes: Int[np.ndarray, "s 4"]
    weights: Float[np.ndarray, "s 4"]
    distance: Float[np.ndarray, " s"]

    @property
    def n_points(self) -> int:
        return len(self.element)

    def positions(self, x: Float[ArrayLike, "n 3"]) -> Float[Array, "s 3"]:
        """The embedded points carried by node positions x (JAX, differentiable in x).

        Args:
            x: (n, 3) node positions (the rest positions give the points back).
        Returns:
            (s, 3) the points.
        """
        x = jnp.asarray(x)
        if x.ndim != 2 or x.shape[1] != 3 or not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(f"x: expected float node positions of shape (n, 3), got {x.dtype} {x.shape}")
        if self.nodes.size and int(self.nodes.max()) >= x.shape[0]:
            raise ValueError(f"x: expected at least {int(self.nodes.max()) + 1} nodes, got {x.shape[0]}")
        return jnp.einsum("sk,skd->sd", jnp.asarray(self.weights, x.dtype), x[jnp.asarray(self.nodes)], precision=EXACT)

    def matrix(self, n_nodes: int) -> sp.csr_matrix:
        """The (s, n_nodes) sparse matrix of the map: ``positions(x) == matrix(n) @ x``."""
        if int(n_nodes) != n_nodes or (self.nodes.size and n_nodes <= int(self.nodes.max())):
            raise ValueError(f"n_nodes: expected an int > {int(self.nodes.max(initial=-1))}, got {n_nodes!r}")
        rows = np.repeat(np.arange(self.n_points), 4)
        return sp.csr_matrix((self.weights.ravel(), (rows, self.nodes.ravel())), shape=(self.n_points, int(n_nodes)))


def embed_points(mesh: TetMesh, P: Float[npt.ArrayLike, "s 3"]) -> SurfaceEmbedding:
    """Embed points in a tet mesh: the tet containing each point (libigl ``in_element`` on an AABB tree) and its
    barycentric coordinates; a point in no tet takes the tet of the nearest boundary face (libigl
    ``point_mesh_squared_distance``) and extrapolated coordinates.

    Args:
        mesh: the ``TetMesh``.
        P: (s, 3) finite points.
    Returns:
        The ``SurfaceEmbedding``.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh: expected a TetMesh, got {type(mesh).__name__}")
    P = check_points("P", P)
    X, T = np.asarray(mesh.X, np.float64), np.asarray(mesh.T, np.int64)
    element, weights, distance = embed(X, T, P)
    return SurfaceEmbedding(element, T[element], weights, distance)


class SurfaceTets(NamedTuple):
    """A surface's tetrahedralization (``tetrahedralize_surface``).

    Attributes:
        mesh: the ``TetMesh``.
        embedding: the surface's vertices embedded in it (``SurfaceEmbedding``).
        quality: the mesh's ``TetQuality``.
        seconds: the wall time of the meshing (fTetWild) and the embedding.
    """

    mesh: TetMesh
    embedding: SurfaceEmbedding
    quality: TetQuality
    seconds: float


def tetrahedralize_surface(
    V: Float[npt.ArrayLike, "v 3"],
    F: Int[npt.ArrayLike, "f 3"],
    *,
    edge_length: float = EDGE_LENGTH,
    epsilon: float = EPSILON,
    stop_quality: float = 10.0,
    max_iterations: int = 80,
    threads: int | None = None,
) -> SurfaceTets:
    """Tetrahedralize the inside of any triangle surface (open, self-intersecting, several parts) with fTetWild
    and embed the surface's vertices in the tets.

    The inside is where the generalized winding number of the surface is above 1/2 (fTetWild's filter, so
    the faces' orientation does not matter); the tets' boundary lies within the
    envelope ``epsilon`` of the surface where the surface is closed, and parts that enclose no volume (a single
    open sheet) get no tets: their vertices take the nearest tet, and a ``UserWarning`` says how far they lie.
    fTetWild is not deterministic, not even with ``threads=1``: two runs give other tets, their counts a few percent
    apart (fTetWild issue #72).

    Args:
        V: (v, 3) finite surface vertices.
        F: (f, 3) int triangles.
        edge_length: the target tet edge length, relative to the bounding box diagonal of V.
        epsilon: the envelope's width, relative to the bounding box diagonal of V.
        stop_quality: the AMIPS energy at which fTetWild's optimization stops (lower: better tets, slower).
        max_iterations: fTetWild's optimization passes at most.
        threads: fTetWild's worker threads; None: every core.
    Returns:
        The ``SurfaceTets``: mesh, embedding (one point per vertex of V), quality and seconds.
    Raises:
        ValueError: bad shapes or values, a surface without volume (every tet left out).
        RuntimeError: fTetWild failed (its child process ended with an error, named in the message).
    """
    V, F = check_triangle_mesh(V, F, min_faces=1)
    for name, value, high in (("edge_length", edge_length, 1.0), ("epsilon", epsilon, 0.1)):
        if not np.isfinite(value) or not 0 < value <= high:
            raise ValueError(f"{name}: expected a fraction of the bounding box diagonal in (0, {high}], got {value}")
    if not np.isfinite(stop_quality) or stop_quality < 3:  # the AMIPS energy of a regular tet is 3
        raise ValueError(f"stop_quality: expected an AMIPS energy >= 3, got {stop_quality}")
    if int(max_iterations) != max_iterations or max_iterations < 0:
        raise ValueError(f"max_iterations: expected an int >= 0, got {max_iterations!r}")
    if threads is not None and (int(threads) != threads or threads < 1):
        raise ValueError(f"threads: expected None or an int >= 1, got {threads!r}")
    diagonal = bounding_diagonal(V)
    if not diagonal > 0:
        raise ValueError("V: the surface has no extent (all vertices coincide)")
    start = time.perf_counter()
    TV, TT = ftetwild(V, F, edge_length, epsilon, stop_quality, int(max_iterations), threads)
    if len(TT) == 0:
        raise ValueError(
            "F: the surface encloses no volume (fTetWild kept no tet: the winding number is below 1/2 everywhere, "
            "as for an open sheet)"
        )
    used, TT = np.unique(TT, return_inverse=True)  # drop nodes in no tet
    mesh = tet_mesh(TV[used], TT.reshape(-1, 4))
    embedding = embed_points(mesh, V)
    seconds = time.perf_counter() - start
    far = embedding.distance > edge_length * diagonal
    if far.any():
        warnings.warn(
            f"V: {int(far.sum())} of {len(V)} surface vertices lie farther than the edge length from the tets "
            f"(at most {embedding.distance.max() / diagonal:.3g} of the diagonal: parts that enclose no volume, "
            "such as open sheets); they follow the nearest tet's linear map",
            stacklevel=2,
        )
    return SurfaceTets(mesh, embedding, tet_quality(mesh), seconds)


def cut_surface(
    model: XFEMModel, embedding: SurfaceEmbedding, V: Float[npt.ArrayLike, "s 3"], F: Int[npt.ArrayLike, "f 3"]
) -> tuple[Float[np.ndarray, "k 3"], Int[np.ndarray, "f 3"], Int[np.ndarray, " f"], Int[np.ndarray, " k"]]:
    """An embedded surface, deformed and in pieces, of a cut XFEM body (eq. 18 at the surface's points).

    A vertex moves with its tet's piece on its own side of the cuts (eq. 16 at the vertex). A triangle follows the
    side its centroid lies on: where a corner lies on another side than the centroid (the triangle straddles a
    cut), that corner moves by the linear map of the centroid's piece (its tet's shape functions, extrapolated to
    the corner, with the DOFs eq. 16 picks at the centroid), so the triangle moves whole with one side rather than
    being stretched across the gap. Such a corner gets its own copy of the vertex (one per triangle). The surface
    is not split along the cut: splitting an open, self-intersecting surface by the cut solid is no Boolean that
    manifold3d can do, and the triangle-sized jag along the cut is what the surface's resolution allows.

    Args:
        model: the ``XFEMModel`` whose mesh the surface is embedded in.
        embedding: the ``SurfaceEmbedding`` of V in ``model.mesh``.
        V: (s, 3) the surface's rest vertices (the embedded points).
        F: (f, 3) int its triangles.
    Returns:
        V' (k, 3) deformed vertices, F' (f, 3) int64 triangles into them (in F's order), piece (f,) int64 the
        connected piece of the body (``XFEMModel.components``) of each triangle, and vertex (k,) int64 the
        vertex of V each row of V' copies.
    """
    weights, dofs, faces, piece, vertex = surface_map(model, embedding, V, F)
    deformed = np.einsum("ka,kad->kd", weights, np.asarray(model.state.x)[dofs])
    return deformed, faces, piece, vertex


def surface_map(
    model: XFEMModel, embedding: SurfaceEmbedding, V: Float[npt.ArrayLike, "s 3"], F: Int[npt.ArrayLike, "f 3"]
) -> tuple[
    Float[np.ndarray, "k 4"],
    Int[np.ndarray, "k 4"],
    Int[np.ndarray, "f 3"],
    Int[np.ndarray, " f"],
    Int[np.ndarray, " k"],
]:
    """The linear map from a cut XFEM body's DOFs to its embedded surface in pieces (``cut_surface``'s rule): the
    surface's vertices are ``sum_a weights[:, a] x[dofs[:, a]]`` for any DOF positions x of the model's current
    cuts (e.g. every frame of a trajectory).

    Args:
        model: as ``cut_surface``.
        embedding: see ``model``.
        V: see ``model``.
        F: see ``model``.
    Returns:
        weights (k, 4) float64 and dofs (k, 4) int64 of the k vertices of V', F' (f, 3) int64 triangles into them,
        piece (f,) int64 the connected piece of each triangle, and vertex (k,) int64 the vertex of V each copies.
    """
    from xfem._integration import linear_shape_coefficients
    from xfem._xfem import XFEMModel

    if not isinstance(model, XFEMModel):
        raise ValueError(f"model: expected an XFEMModel, got {type(model).__name__}")
    if not isinstance(embedding, SurfaceEmbedding):
        raise ValueError(f"embedding: expected a SurfaceEmbedding, got {type(embedding).__name__}")
    V = check_points("V", V, rows="s")
    if len(V) != embedding.n_points:
        raise ValueError(f"V: expected the {embedding.n_points} embedded points, got {len(V)}")
    F = check_faces("F", F, len(V))
    if embedding.nodes.size and (
        int(embedding.nodes.max()) >= len(model.X) or not np.array_equal(model.T[embedding.element], embedding.nodes)
    ):
        raise ValueError("embedding: its tets are not those of model.mesh")
    X, T = model.X, model.T
    weights, dofs = model.field_dofs(V, embedding.element)  # each vertex on its own side
    corners = F.ravel()
    centroid = V[F].mean(axis=1)
    c_element = embed(X, T, centroid)[0]
    c_dofs = model.field_dofs(centroid, c_element)[1]  # the DOFs of the centroid's side
    # a corner is on the centroid's side where eq. 16 at the centroid picks the DOFs it picks at the corner
    at_centroid = model.field_dofs(V[corners], embedding.element[corners], np.repeat(centroid, 3, axis=0))[1]
    other = np.flatnonzero(np.any(at_centroid != dofs[corners], axis=1))
    triangle = other // 3
    other_weights, _ = linear_shape_coefficients(X[T[c_element[triangle]]], V[corners[other]])
    # rows of V': the s vertices, then one copy per corner on the other side
    all_weights = np.concatenate([weights, other_weights])
    all_dofs = np.concatenate([dofs, c_dofs[triangle]])
    index = corners.copy()
    index[other] = len(V) + np.arange(len(other))
    used = np.unique(index)  # vertices on no triangle are dropped
    rank = np.full(len(all_weights), -1, np.int64)
    rank[used] = np.arange(len(used))
    vertex = np.concatenate([np.arange(len(V)), corners[other]])[used]
    _, label = model.components()
    return (
        all_weights[used],
        all_dofs[used],
        rank[index].reshape(-1, 3),
        label[c_dofs[:, 0]].astype(np.int64),
        vertex,
    )
