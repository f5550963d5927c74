"""Cut surfaces and thin cut solids, sec. 4.1 ("Cut Modeling") of the XFEM paper (Ton-That, Kry, Andrews,
"Generalized eXtended Finite Element Method for Deformable Cutting via Boolean Operations").

A cut Gamma^c is the surface swept by a tool's sharp edge, a curve approximated by a polyline in the tool's
frame, moving between poses. The poses are key motors blended with the kernel's logarithmic interpolation
``M_i exp(t log(M_i^-1 M_{i+1}))`` (cut/tear/drill paper sec. 2.5), so a constant-velocity screw between
two keys is reproduced exactly (every sample is the screw by t times the key's angle and displacement).
The swept positions form a grid joined into a triangle strip (``swept_surface``; ``sweep_between`` joins
two polylines directly). The paper then "injects a thickness epsilon > 0 along the normal direction" to make
the cut a thin closed solid whose boundary is a triangle mesh fit for mesh Booleans [ZGZJ16]:
``thicken`` offsets the open surface by +-epsilon/2 along angle-weighted vertex normals and closes it with
side walls along the boundary; ``cut_solid`` builds the ``manifold3d.Manifold`` (float64 ``Mesh64``) used
by the Booleans; ``plane_cut_solid`` is a flat square cut.

Vertex positions are JAX functions of the motors / input positions (differentiable); the triangle
indices come from the sizes and are host numpy arrays.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
import numpy.typing as npt
from jaxtyping import Array, Float, Int

import jaxcga as cga
from _jaxcga_shared.checks import check_faces, check_finite, check_vectors, require


def _grid_faces(q: int, p: int) -> np.ndarray:
    """(2 (q-1)(p-1), 3) triangles of a q x p vertex grid (vertex j p + i is row j, column i), two per
    quad, ordered so that the normal is (column direction) x (row direction)."""
    j, i = np.meshgrid(np.arange(q - 1), np.arange(p - 1), indexing="ij")
    a = (j * p + i).ravel()
    b, c, d = a + 1, a + p + 1, a + p
    return np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)]).astype(np.int64)


def _polyline(name: str, edge) -> Float[Array, "p 3"]:
    edge = check_finite(name, check_vectors(name, edge))
    if edge.ndim != 2 or edge.shape[0] < 2:
        raise ValueError(f"{name}: expected a polyline of shape (p, 3) with p >= 2, got shape {edge.shape}")
    return edge


def swept_surface(
    edge: Float[Array, "p 3"], motors: cga.Multivector, samples_per_interval: int = 4
) -> tuple[Float[Array, "q 3"], Int[np.ndarray, "r 3"]]:
    """The surface swept by a tool edge placed by key motors blended logarithmically.

    Between consecutive keys M_i, M_{i+1} the poses ``blend_log(M_i, M_{i+1}, t)`` for
    t = 0, 1/s, ..., (s-1)/s are sampled (s = samples_per_interval), then the last key: n = (k-1) s + 1
    poses. Every pose places the p edge points; pose j, point i is vertex j p + i.

    Args:
        edge: (p, 3) the tool's sharp edge as a polyline in the tool's frame, p >= 2.
        motors: motor Multivector (rotors and translators are accepted) with batch shape (k,), k >= 2:
            the key poses of the tool, in order.
        samples_per_interval: s >= 1 poses per interval between keys.

    Returns:
        V: (n p, 3) swept positions (a JAX function of ``edge`` and ``motors``).
        F: (2 (n-1)(p-1), 3) host int64 triangles, consistently oriented with normal
            (edge direction) x (sweep direction). Edge points that do not move between two samples (on
            the rotation axis, or a key repeated) give degenerate triangles, which ``thicken`` refuses.
    """
    edge = _polyline("edge", edge)
    if not isinstance(motors, cga.Multivector) or not set(motors.blades) <= set(cga.KINDS["motor"]):
        raise ValueError("motors: expected a motor Multivector (rotor, translator or motor blades)")
    if len(motors.batch_shape) != 1 or motors.batch_shape[0] < 2:
        raise ValueError(f"motors: expected batch shape (k,) with k >= 2 key poses, got {motors.batch_shape}")
    if not isinstance(samples_per_interval, int) or samples_per_interval < 1:
        raise ValueError(f"samples_per_interval: expected an int >= 1, got {samples_per_interval!r}")
    points = _sweep_points(edge, motors.embed(cga.KINDS["motor"]), samples_per_interval)
    n, p = points.shape[0], points.shape[1]
    return points.reshape(n * p, 3), _grid_faces(n, p)


@functools.partial(jax.jit, static_argnums=2)
def _sweep_points(edge, motors, s):
    """(n, p, 3) the edge placed by the n = (k-1) s + 1 log-blended poses."""
    t = jnp.asarray(np.arange(s) / s, motors.dtype)
    # (k-1, s) blended poses, flattened interval by interval, then the last key closes the sweep
    blended = cga.blend_log(motors[:-1][:, None], motors[1:][:, None], t[None, :])
    poses = jnp.concatenate([blended.values.reshape(-1, blended.values.shape[-1]), motors.values[-1:]])
    versors = cga.Multivector(poses, motors.blades)[:, None]  # a Multivector (its __getitem__ is typed loosely)
    return cga.apply_to_points(versors, edge.astype(poses.dtype)[None])  # pyright: ignore[reportArgumentType]


def sweep_between(
    edge_a: Float[Array, "p 3"], edge_b: Float[Array, "p 3"], samples: int = 1
) -> tuple[Float[Array, "q 3"], Int[np.ndarray, "r 3"]]:
    """The ruled surface between two polylines: rows ``(1 - t) edge_a + t edge_b``, t = 0, 1/s, ..., 1.

    Args:
        edge_a: (p, 3) first polyline, p >= 2.
        edge_b: (p, 3) second polyline, same shape.
        samples: s >= 1 intervals between the two.

    Returns:
        V: ((s+1) p, 3) positions; F: (2 s (p-1), 3) host int64 triangles with normal
        (edge direction) x (direction from edge_a to edge_b), as in ``swept_surface``.
    """
    edge_a, edge_b = _polyline("edge_a", edge_a), _polyline("edge_b", edge_b)
    if edge_a.shape != edge_b.shape:
        raise ValueError(f"edge_b: expected the shape of edge_a {edge_a.shape}, got {edge_b.shape}")
    if not isinstance(samples, int) or samples < 1:
        raise ValueError(f"samples: expected an int >= 1, got {samples!r}")
    dtype = jnp.result_type(edge_a.dtype, edge_b.dtype)
    t = jnp.asarray(np.linspace(0.0, 1.0, samples + 1), dtype)[:, None, None]
    rows = (1 - t) * edge_a.astype(dtype)[None] + t * edge_b.astype(dtype)[None]
    p = edge_a.shape[0]
    return rows.reshape(-1, 3), _grid_faces(samples + 1, p)


def _boundary_edges(F: np.ndarray, n: int) -> np.ndarray:
    """(b, 2) boundary half-edges (a, b) as oriented in their face, after checking that F is an oriented
    2-manifold with boundary: ValueError naming F otherwise."""
    half = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    if np.any(half[:, 0] == half[:, 1]):
        raise ValueError("F: a triangle repeats a vertex")
    keys = half[:, 0] * n + half[:, 1]
    unique_half, counts = np.unique(keys, return_counts=True)
    if np.any(counts > 1):
        raise ValueError("F: non-manifold or inconsistently oriented (a directed edge is used twice)")
    twin = np.isin(half[:, 1] * n + half[:, 0], unique_half)
    boundary = half[~twin]
    if boundary.shape[0] == 0:
        raise ValueError("F: the surface is closed (no boundary edge); a cut surface must be open")
    # one outgoing boundary edge per boundary vertex: otherwise the boundary pinches (a non-manifold vertex)
    if np.unique(boundary[:, 0]).shape[0] != boundary.shape[0]:
        raise ValueError("F: non-manifold boundary vertex (two boundary loops touch)")
    return boundary


@jax.jit
def _offset(V, F, h):
    """The top and bottom copies V +- h N (angle-weighted unit normals N) stacked, and the flags: a
    degenerate triangle, a vertex normal at >= 90 degrees from one of its faces, an offset triangle
    turned against its face normal."""
    x = V[F]
    cross = jnp.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area2 = jnp.linalg.norm(cross, axis=-1)
    scale = jnp.max(jnp.linalg.norm(x[:, 1:] - x[:, :1], axis=-1), axis=-1) ** 2
    degenerate = jnp.any(area2 <= 1e-12 * scale)
    face_normal = cross / area2[:, None]
    # tip angle of each triangle at each of its corners
    e1 = jnp.roll(x, -1, axis=1) - x
    e2 = jnp.roll(x, 1, axis=1) - x
    angle = jnp.arctan2(jnp.linalg.norm(jnp.cross(e1, e2), axis=-1), jnp.sum(e1 * e2, axis=-1))
    normal_sum = jnp.zeros_like(V).at[F.ravel()].add((angle[:, :, None] * face_normal[:, None]).reshape(-1, 3))
    N = normal_sum / jnp.linalg.norm(normal_sum, axis=-1, keepdims=True)
    fold = jnp.any(jnp.sum(N[F] * face_normal[:, None], axis=-1) <= 0)
    V2 = jnp.concatenate([V + h * N, V - h * N])
    n = V.shape[0]
    y = jnp.stack([V2[F], V2[F + n]])
    turned = jnp.sum(jnp.cross(y[:, :, 1] - y[:, :, 0], y[:, :, 2] - y[:, :, 0]) * face_normal[None], axis=-1) <= 0
    return V2, degenerate, fold, jnp.any(turned)


def _positive(name: str, value, what: str) -> float:
    """A concrete real scalar > 0 as a float, or ValueError naming it."""
    if np.ndim(value) != 0 or not np.isrealobj(value) or not np.isfinite(value) or value <= 0:
        raise ValueError(f"{name}: expected a finite {what} > 0 (a concrete number), got {value!r}")
    return float(value)


def thicken(
    V: Float[Array, "n 3"], F: Int[np.ndarray, "m 3"], epsilon: float
) -> tuple[Float[Array, "2n 3"], Int[np.ndarray, "r 3"]]:
    """Close an open oriented surface into a solid of thickness epsilon (sec. 4.1).

    Every vertex moves by +-epsilon/2 along its angle-weighted unit normal (the sum of its faces' unit
    normals weighted by the triangles' tip angles at the vertex, normalized). Angle weights, rather than
    area weights, make the normal independent of how a quad strip is split into triangles (on a swept
    grid a vertex sees one triangle of one quad and two of the next, which tilts area-weighted normals).
    On a flat surface the solid is the exact prism of volume area * epsilon; on a curved one the
    thickness along a face normal is epsilon times the cosine between face and vertex normals. The top
    copy keeps F's orientation, the bottom copy is reversed, and each boundary edge gets a side-wall quad,
    so the solid is closed and outward oriented (the top copy lies on the side of F's normals).

    Detected and refused: a fold whose offset flips a triangle (its top or bottom copy turns against the
    face normal, i.e. the surface folds tighter than epsilon) or a vertex normal at 90 degrees or more
    from one of its faces. Not detected: parts of the surface that are far apart along the surface but
    closer than epsilon in space (the solid would self-intersect).

    Args:
        V: (n, 3) float vertex positions; every vertex must be in a face.
        F: (m, 3) int triangles (host, concrete): an oriented 2-manifold with boundary, no degenerate
            triangle.
        epsilon: thickness > 0 (a concrete number).

    Returns:
        V2: (2n, 3) positions: the top copy (V + epsilon/2 N) then the bottom copy (V - epsilon/2 N).
        F2: (2m + 2b, 3) host int64 triangles (b boundary edges), outward oriented.
    """
    V = check_finite("V", check_vectors("V", V, rows="n"))
    n = V.shape[0]
    F = check_faces("F", F, n)
    if np.unique(F).shape[0] != n:
        raise ValueError("V: every vertex must be in a face (unreferenced vertices found)")
    epsilon = _positive("epsilon", epsilon, "thickness")
    boundary = _boundary_edges(F, n)

    V2, degenerate, fold, flipped = _offset(V, jnp.asarray(F), jnp.asarray(epsilon / 2, V.dtype))
    V2 = require(
        V2,
        (degenerate, "F: degenerate (zero-area) triangle"),
        (fold, "V: a vertex normal is at 90 degrees or more from one of its faces (fold)"),
        (flipped, f"epsilon: an offset copy flips a triangle (the surface folds tighter than epsilon = {epsilon})"),
    )
    a, b = boundary[:, 0], boundary[:, 1]
    walls = np.concatenate([np.stack([a + n, b + n, b], -1), np.stack([a + n, b, a], -1)])
    F2 = np.concatenate([F, F[:, ::-1] + n, walls])
    return V2, F2


def cut_solid(V: Float[Array, "n 3"], F: Int[np.ndarray, "m 3"], epsilon: float) -> manifold3d.Manifold:
    """The thin closed cut solid of sec. 4.1 as a ``manifold3d.Manifold`` (float64 ``Mesh64`` input):
    ``thicken(V, F, epsilon)`` then construction.

    Args:
        V: (n, 3) float positions of the open cut surface.
        F: (m, 3) int triangles (host), an oriented 2-manifold with boundary.
        epsilon: thickness > 0.

    Returns:
        The Manifold (status NoError, positive volume), or ValueError naming the argument when
        manifold3d rejects the thickened mesh.
    """
    V2, F2 = thicken(V, F, epsilon)
    # writable C-contiguous copies: the bindings refuse read-only (JAX-backed) buffers
    mesh = manifold3d.Mesh64(
        vert_properties=np.array(V2, np.float64, order="C"), tri_verts=np.array(F2, np.uint64, order="C")
    )
    solid = manifold3d.Manifold(mesh)
    if solid.status() != manifold3d.Error.NoError or solid.volume() <= 0:
        raise ValueError(
            f"V, F: manifold3d rejected the thickened cut (status {solid.status().name}, volume {solid.volume()})"
        )
    return solid


def plane_cut_solid(
    point: Float[npt.ArrayLike, " 3"], normal: Float[npt.ArrayLike, " 3"], extent: float, epsilon: float
) -> manifold3d.Manifold:
    """A flat square cut of side ``extent`` centred at ``point`` across ``normal``, thickened by epsilon
    (a slab extent x extent x epsilon).

    Args:
        point: (3,) centre of the square.
        normal: (3,) its normal (normalized here; nonzero).
        extent: side length > 0.
        epsilon: thickness > 0.

    Returns:
        The slab as a closed manifold3d solid, to pass to ``XFEMModel.cut`` or a schedule.
    """
    point = np.asarray(check_finite("point", check_vectors("point", np.asarray(point))), np.float64)
    normal = np.asarray(check_finite("normal", check_vectors("normal", np.asarray(normal))), np.float64)
    if point.shape != (3,) or normal.shape != (3,):
        raise ValueError(f"point, normal: expected shape (3,), got {point.shape} and {normal.shape}")
    length = np.linalg.norm(normal)
    if length == 0:
        raise ValueError("normal: zero-length normal")
    extent = _positive("extent", extent, "side length")
    nz = normal / length
    # u, w orthonormal with u x w = n, so that the swept square's normal is n
    helper = np.eye(3)[np.argmin(np.abs(nz))]
    u = np.cross(helper, nz)
    u /= np.linalg.norm(u)
    w = np.cross(nz, u)
    half = extent / 2
    edge_a = np.stack([point - half * u - half * w, point + half * u - half * w])
    V, F = sweep_between(jnp.asarray(edge_a), jnp.asarray(edge_a + extent * w))
    return cut_solid(V, F, epsilon)


def blade_solid(
    handle: Float[npt.ArrayLike, "k 3"],
    tip: Float[npt.ArrayLike, "k 3"],
    epsilon: float,
    blade_points: int = 8,
) -> manifold3d.Manifold:
    """The cut solid of a blade moved along a path (a scalpel's samples, as ``cutting.Scalpel`` holds them): the
    ruled surface swept by the segment from ``handle[i]`` to ``tip[i]`` between consecutive samples (each blade a
    polyline of ``blade_points`` points, the samples' rows joined into a grid), thickened by epsilon
    (``cut_solid``). It cuts the body only where the blade passed, so a short path makes a slit, not a severed part.

    Args:
        handle: (k, 3) the handle end of the blade at each of k >= 2 samples.
        tip: (k, 3) its other end.
        epsilon: the cut's thickness > 0.
        blade_points: points along the blade (>= 2).
    Returns:
        The ``manifold3d.Manifold``.
    """
    handle = np.asarray(check_finite("handle", check_vectors("handle", np.asarray(handle, np.float64))))
    tip = np.asarray(check_finite("tip", check_vectors("tip", np.asarray(tip, np.float64))))
    if handle.ndim != 2 or len(handle) < 2:
        raise ValueError(f"handle: expected (k, 3) samples with k >= 2, got shape {handle.shape}")
    if tip.shape != handle.shape:
        raise ValueError(f"tip: expected the shape of handle {handle.shape}, got {tip.shape}")
    if isinstance(blade_points, bool) or not isinstance(blade_points, int) or blade_points < 2:
        raise ValueError(f"blade_points: expected an int >= 2, got {blade_points!r}")
    if np.any(np.linalg.norm(tip - handle, axis=1) <= 0):
        raise ValueError("handle, tip: a sample's blade has zero length")
    s = np.linspace(0.0, 1.0, blade_points)[None, :, None]
    rows = (1 - s) * handle[:, None] + s * tip[:, None]  # (k, p, 3): sample by sample, handle to tip
    return cut_solid(jnp.asarray(rows.reshape(-1, 3)), _grid_faces(len(handle), blade_points), epsilon)
