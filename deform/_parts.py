"""Meshes of several connected parts (eyes, teeth, clothing layers, a character cut into pieces, an inner skeleton
mesh): the bridges that tie the parts together so that a part without a handle follows the others.

A solve with Dirichlet (handle) constraints, harmonic fields or ARAP, is singular on a connected part that holds
no constrained vertex (nothing fixes its values there), and a part whose only handle is one end's (a shoe, when
the feet are fixed) would not feel the others. The rule used by every deformer of ``deform`` with handles:

* The parts are the connected components of the graph of the faces' edges; a vertex on no face is a part of its
  own. A part is *handled* when it holds a constrained vertex. ``l`` is the mesh's mean edge length.
* Attached parts are tied along their seams: every vertex within ``l`` of another part gets a *bridge* to its
  nearest vertex there (a piece of a character that touches or overlaps the next piece, a layer of clothing on
  the skin, an inner mesh just under it), whether the parts hold handles or not. Parts tied this way form groups.
* A group without a handle follows the one it is nearest to, attached one at a time, nearest first (Prim's
  order): the next group is the one with the smallest distance ``d`` between its vertices and the vertices
  already reached (those of the groups with a handle and of the groups attached before). Every vertex of it
  within ``d + l`` of the reached vertices gets a bridge to its nearest reached vertex: the patch that faces its
  neighbour (an eye in its socket). A chain of such groups resolves: a group nearest only to another one without
  a handle is attached to it after that one has been attached.
* Of the bridges from one part that end on the same vertex only the shortest is kept, so a vertex gains few
  neighbours. A bridge is one more edge of the Laplacian, of weight ``min(1, (l / |p_i - p_j|)^2)``: as stiff as
  a typical mesh edge (cotangent weights are of order one) up to one edge length, weaker as it gets longer, so
  that a far part does not steer its anchor's neighbourhood. Rows still sum to zero, so harmonic fields stay a
  partition of unity and a rigid motion of every handle still moves every part by exactly that motion; the
  constrained system is positive definite (every free vertex has a path to a constraint).

``unhandled="error"`` adds no bridge and refuses a mesh with a part that holds no constrained vertex, naming it.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import equinox as eqx
import numpy as np
from jaxtyping import ArrayLike, Bool, Float, Int

from _jaxcga_shared.checks import check_choice, check_index_range, check_triangle_mesh

if TYPE_CHECKING:
    import scipy.sparse as sp

# scipy's sparse and spatial packages are imported where they are used: a caller that only reads UNHANDLED (the
# command line's argument check) does not load them
UNHANDLED = ("follow", "error")


class MeshParts(eqx.Module):
    """The connected parts of a mesh and the bridges that tie them together (``mesh_parts``).

    Attributes:
        labels: (n,) the part of every vertex, 0 .. count - 1.
        handled: (count,) bool, whether each part holds a constrained vertex.
        groups: (count,) the group of parts attached to each other along seams that each part belongs to.
        bridges: (k, 2) int vertex pairs (i, j) of different parts, each an extra edge of the Laplacian.
        weights: (k,) the bridges' Laplacian weights, in (0, 1].
    """

    labels: Int[np.ndarray, " n"]
    handled: Bool[np.ndarray, " count"]
    groups: Int[np.ndarray, " count"]
    bridges: Int[np.ndarray, "k 2"]
    weights: Float[np.ndarray, " k"]

    @property
    def count(self) -> int:
        return len(self.handled)

    def laplacian(self) -> sp.csr_matrix:
        """The bridges' Laplacian (n, n): ``w`` off the diagonal at each bridge, rows summing to zero."""
        import scipy.sparse as sp

        n = len(self.labels)
        i, j = self.bridges[:, 0], self.bridges[:, 1]
        W = sp.csr_matrix((np.concatenate([self.weights] * 2), (np.r_[i, j], np.r_[j, i])), shape=(n, n))
        return (W - sp.diags(np.asarray(W.sum(axis=1)).ravel())).tocsr()


def _components(n: int, edges: np.ndarray) -> tuple[int, np.ndarray]:
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    graph = sp.coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    return connected_components(graph, directed=False)


def _shortest_per_anchor(follower, anchor, distance, labels):
    """The bridges (follower, anchor) with, of those from one part to one anchor, only the shortest."""
    if len(follower) == 0:
        return follower, anchor, distance
    order = np.lexsort((distance, anchor, labels[follower]))
    follower, anchor, distance = follower[order], anchor[order], distance[order]
    key = labels[follower].astype(np.int64) * len(labels) + anchor
    first = np.r_[True, key[1:] != key[:-1]]
    return follower[first], anchor[first], distance[first]


def _seams(V, labels, length):
    from scipy.spatial import KDTree

    """Every vertex within ``length`` of another part, bridged to its nearest vertex there: (i, j, distance)."""
    pairs = KDTree(V).query_pairs(length, output_type="ndarray")
    pairs = pairs[labels[pairs[:, 0]] != labels[pairs[:, 1]]]
    i, j = np.r_[pairs[:, 0], pairs[:, 1]], np.r_[pairs[:, 1], pairs[:, 0]]
    d = np.linalg.norm(V[i] - V[j], axis=1)
    order = np.lexsort((d, i))
    i, j, d = i[order], j[order], d[order]
    first = np.r_[True, i[1:] != i[:-1]][: len(i)]
    i, j, d = i[first], j[first], d[first]
    # a pair chosen from both ends is one bridge
    nearest = np.full(len(V), -1)
    nearest[i] = j
    mutual = (nearest[j] == i) & (i > j)
    return _shortest_per_anchor(i[~mutual], j[~mutual], d[~mutual], labels)


def mesh_parts(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    constrained: Int[ArrayLike, " c"],
    *,
    unhandled: str = "follow",
    name: str = "constrained",
) -> MeshParts:
    """The connected parts of (V, F) and the bridges that tie attached parts together and let every part without
    a constrained vertex follow the part it is attached or nearest to (the rule in this module's docstring).

    Args:
        V: (n, 3) vertex positions.
        F: (m, 3) int triangles.
        constrained: (c,) int vertex indices with prescribed values (handles), c >= 1.
        unhandled: ``"follow"`` (bridges as above) or ``"error"`` (no bridge; a ValueError naming the parts
            without a constrained vertex when there is any).
        name: the argument name that ``constrained`` has in the caller, for the error messages.
    Returns:
        ``MeshParts`` (no bridges for a mesh of one part)."""
    from scipy.spatial import KDTree

    check_choice("unhandled", unhandled, UNHANDLED)
    V, F = check_triangle_mesh(V, F)
    constrained = np.asarray(constrained).reshape(-1)
    if len(constrained) == 0 or not np.issubdtype(constrained.dtype, np.integer):
        raise ValueError(f"{name}: expected at least one constrained vertex index, got {constrained!r}")
    check_index_range(name, constrained, len(V))
    n = len(V)
    edges = np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]])
    count, labels = _components(n, edges)
    handled = np.zeros(count, bool)
    handled[labels[constrained]] = True
    if count == 1 or (unhandled == "error" and handled.all()):
        return MeshParts(labels, handled, np.zeros(count, np.int64), np.zeros((0, 2), np.int64), np.zeros(0))
    if unhandled == "error":
        free_parts = np.flatnonzero(~handled)
        examples = ", ".join(f"part {p} (vertex {int(np.argmax(labels == p))})" for p in free_parts[:5])
        raise ValueError(
            f"{name}: {len(free_parts)} of the mesh's {count} connected part(s) hold no constrained vertex "
            f"({examples}{', ...' if len(free_parts) > 5 else ''}); their values are undefined. Put a handle on "
            "each, or pass unhandled='follow' to let each follow the part it is attached or nearest to"
        )
    length = float(np.mean(np.linalg.norm(V[edges[:, 0]] - V[edges[:, 1]], axis=1)))
    if not length > 0:  # every face degenerate: the bounding box sets the scale instead
        length = float(np.linalg.norm(V.max(0) - V.min(0))) or 1.0
    follower, anchor, distance = _seams(V, labels, length)
    bridges, distances = [np.stack([follower, anchor], 1)], [distance]
    group_count, group_of_vertex = _components(n, np.concatenate([edges, bridges[0]]))
    groups = np.zeros(count, np.int64)
    groups[labels] = group_of_vertex
    group_handled = np.zeros(group_count, bool)
    group_handled[group_of_vertex[constrained]] = True
    # Prim's order over the groups without a handle: the distance and nearest reached vertex of every vertex not
    # yet reached, updated as groups are attached
    reached = group_handled[group_of_vertex]
    distance = np.full(n, np.inf)
    nearest = np.full(n, -1, np.int64)
    waiting = np.flatnonzero(~reached)
    if len(waiting):
        targets = np.flatnonzero(reached)
        d, k = KDTree(V[targets]).query(V[waiting])
        distance[waiting], nearest[waiting] = d, targets[np.asarray(k)]
    order = np.argsort(group_of_vertex, kind="stable")
    starts = np.searchsorted(group_of_vertex[order], np.arange(group_count))
    ends = np.r_[starts[1:], n]
    for _ in range(int((~group_handled).sum())):
        group_distance = np.minimum.reduceat(np.where(reached, np.inf, distance)[order], starts)
        group = int(np.argmin(group_distance))
        members = order[starts[group] : ends[group]]
        close = members[distance[members] <= group_distance[group] + length]
        f, a, d = _shortest_per_anchor(close, nearest[close], distance[close], labels)
        bridges.append(np.stack([f, a], 1))
        distances.append(d)
        reached[members] = True
        # only the waiting vertices that this group's bounding box could bring nearer need a query
        waiting = np.flatnonzero(~reached)
        lo, hi = V[members].min(0), V[members].max(0)
        gap = np.linalg.norm(np.maximum(0.0, np.maximum(lo - V[waiting], V[waiting] - hi)), axis=1)
        waiting = waiting[gap < distance[waiting]]
        if len(waiting):
            d, k = KDTree(V[members]).query(V[waiting])
            d, k = np.asarray(d), np.asarray(k)
            better = d < distance[waiting]
            distance[waiting[better]], nearest[waiting[better]] = d[better], members[k[better]]
    d = np.concatenate(distances)
    weights = np.where(d <= length, 1.0, (length / np.where(d <= length, 1.0, d)) ** 2)
    return MeshParts(labels, handled, groups, np.concatenate(bridges).astype(np.int64), weights)
