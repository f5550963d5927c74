"""Meshes of several connected parts (eyes, teeth, clothing layers, an inner skeleton mesh): which parts hold a
handle, and the bridges that let every other part follow one that does.

A solve with Dirichlet (handle) constraints, harmonic fields or ARAP, is singular on a connected part that holds
no constrained vertex: nothing fixes its values there. The rule used by every deformer of ``deform``:

* The parts are the connected components of the graph of the faces' edges; a vertex on no face is a part of its
  own. A part is *handled* when it holds a constrained vertex.
* The other parts are attached one at a time, nearest first (Prim's order): the next part is the unattached part
  P with the smallest distance ``d_P`` between its vertices and the vertices already reached (the handled parts'
  and the parts attached before). Every vertex of P within ``d_P + l`` of the reached vertices (``l``: the
  mesh's mean edge length) gets a *bridge* to its nearest reached vertex: a part that touches or overlaps another
  is tied along the whole seam, a detached one (an eye in its socket) along the patch facing its neighbour. Of
  the bridges of P that end on the same reached vertex only the shortest is kept (so that no vertex's
  neighbourhood grows by more than one edge per part). A chain of unhandled parts resolves: a part nearest only
  to another unhandled part is attached to it after that part has been attached.
* A bridge is one more edge of the Laplacian, of weight ``min(1, (l / |p_i - p_j|)^2)``: as stiff as a typical
  mesh edge (cotangent weights are of order one) up to one edge length, weaker as it gets longer, so that a
  far part does not steer its anchor's neighbourhood. Rows still sum to zero, so harmonic fields stay a
  partition of unity and a rigid motion of every handle still moves every part, followers included, by exactly
  that motion; the constrained system is positive definite (every free vertex now has a path to a constraint).

``unhandled="error"`` refuses such a mesh instead, naming the parts.
"""

from __future__ import annotations

import equinox as eqx
import numpy as np
import scipy.sparse as sp
from jaxtyping import Float, Int
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from _jaxcga_shared.checks import check_choice, check_index_range, check_triangle_mesh

UNHANDLED = ("follow", "error")


class MeshParts(eqx.Module):
    """The connected parts of a mesh and the bridges that tie its unhandled parts to handled ones (``mesh_parts``).

    Attributes:
        labels: (n,) the part of every vertex, 0 .. count - 1.
        handled: (count,) whether each part holds a constrained vertex.
        parent: (count,) the part each unhandled part was attached to (-1 for a handled part); following
            ``parent`` from any part ends at a handled part.
        bridges: (k, 2) vertex pairs (follower, anchor), the anchor on a part reached before the follower's.
        weights: (k,) the bridges' Laplacian weights.
    """

    labels: Int[np.ndarray, " n"]
    handled: np.ndarray
    parent: Int[np.ndarray, " count"]
    bridges: Int[np.ndarray, "k 2"]
    weights: Float[np.ndarray, " k"]

    @property
    def count(self) -> int:
        return len(self.handled)

    def laplacian(self) -> sp.csr_matrix:
        """The bridges' Laplacian (n, n): ``w`` off the diagonal at each bridge, rows summing to zero."""
        n = len(self.labels)
        i, j = self.bridges[:, 0], self.bridges[:, 1]
        W = sp.coo_matrix((np.concatenate([self.weights] * 2), (np.r_[i, j], np.r_[j, i])), shape=(n, n)).tocsr()
        return (W - sp.diags(np.asarray(W.sum(axis=1)).ravel())).tocsr()


def _labels(n: int, F: np.ndarray) -> tuple[int, np.ndarray]:
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)


def mesh_parts(
    V: Float[np.ndarray, "n 3"],
    F: Int[np.ndarray, "m 3"],
    constrained: Int[np.ndarray, " c"],
    *,
    unhandled: str = "follow",
    name: str = "constrained",
) -> MeshParts:
    """The connected parts of (V, F) and the bridges by which each part without a constrained vertex follows the
    part it is attached or nearest to (the rule in this module's docstring).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int triangles.
        constrained: (c,) int vertex indices with prescribed values (handles), c >= 1.
        unhandled: ``"follow"`` (bridge every unhandled part) or ``"error"`` (a ValueError naming the unhandled
            parts when there is any).
        name: the argument name that ``constrained`` has in the caller, for the error messages.
    Returns:
        ``MeshParts`` (no bridges when every part holds a constrained vertex)."""
    check_choice("unhandled", unhandled, UNHANDLED)
    V, F = check_triangle_mesh(V, F)
    constrained = np.asarray(constrained).reshape(-1)
    if len(constrained) == 0:
        raise ValueError(f"{name}: expected at least one constrained vertex")
    check_index_range(name, constrained, len(V))
    n = len(V)
    count, labels = _labels(n, F)
    handled = np.zeros(count, bool)
    handled[labels[constrained]] = True
    parent = np.full(count, -1, np.int64)
    if handled.all():
        return MeshParts(labels, handled, parent, np.zeros((0, 2), np.int64), np.zeros(0))
    if unhandled == "error":
        free_parts = np.flatnonzero(~handled)
        examples = ", ".join(f"part {p} (vertex {int(np.argmax(labels == p))})" for p in free_parts[:5])
        raise ValueError(
            f"{name}: {len(free_parts)} of the mesh's {count} connected part(s) hold no constrained vertex "
            f"({examples}{', ...' if len(free_parts) > 5 else ''}); their values are undefined. Put a handle on "
            "each, or pass unhandled='follow' to let each follow the part it is attached or nearest to"
        )
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    length = float(np.mean(np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)))
    if not length > 0:  # every face degenerate: the bounding box sets the scale instead
        length = float(np.linalg.norm(V.max(0) - V.min(0))) or 1.0
    # distance and nearest reached vertex of every vertex not yet reached, updated as parts are attached
    reached = handled[labels]
    tree_index = np.flatnonzero(reached)
    distance = np.full(n, np.inf)
    nearest = np.full(n, -1, np.int64)
    waiting = np.flatnonzero(~reached)
    distance[waiting], k = cKDTree(V[tree_index]).query(V[waiting])
    nearest[waiting] = tree_index[k]
    order = np.argsort(labels, kind="stable")
    starts = np.searchsorted(labels[order], np.arange(count))
    bridges, weights = [], []
    for _ in range(int((~handled).sum())):
        part_distance = np.minimum.reduceat(np.where(reached, np.inf, distance)[order], starts)
        part = int(np.argmin(part_distance))
        members = order[starts[part] : (starts[part + 1] if part + 1 < count else n)]
        close = members[distance[members] <= part_distance[part] + length]
        # the shortest bridge to each anchor
        close = close[np.argsort(distance[close], kind="stable")]
        parent[part] = labels[nearest[close[0]]]
        _, first = np.unique(nearest[close], return_index=True)
        close = close[first]
        bridges.append(np.stack([close, nearest[close]], 1))
        d = distance[close]
        weights.append(np.where(d <= length, 1.0, (length / np.where(d <= length, 1.0, d)) ** 2))
        reached[members] = True
        # only the waiting vertices that this part's bounding box could bring nearer need a query
        waiting = np.flatnonzero(~reached)
        lo, hi = V[members].min(0), V[members].max(0)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - V[waiting], V[waiting] - hi)), axis=1)
        waiting = waiting[gap < distance[waiting]]
        if len(waiting):
            d, k = cKDTree(V[members]).query(V[waiting])
            better = d < distance[waiting]
            distance[waiting[better]], nearest[waiting[better]] = d[better], members[k[better]]
    return MeshParts(labels, handled, parent, np.concatenate(bridges).astype(np.int64), np.concatenate(weights))
