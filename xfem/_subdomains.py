"""Nodal and element subdomains cut by mesh Booleans: sec. 4.2 (nodal subdomains Omega^{i,s} = Omega^i minus
the cuts, their connected components, the enrichments of eqs. 15-18) and sec. 4.4 (per node and per element
triangle meshes, collision culling, connected components, DOF duplication) of the XFEM paper, Algorithm 1
lines 1-19.

Every node i keeps a list of nodal subdomains, initially one: its 1-ring Omega^i (the union of its incident
tets, bounded by the outward boundary faces of that sub-mesh); every element e keeps a list of element
subdomains, initially one: the tet itself (sec. 4.3, eq. 20). Each subdomain is a closed solid held as a
``manifold3d.Manifold`` (float64 ``Mesh64`` input) and has an integer id, unique within its kind (nodal ids
start as the node index, element ids as the element index; pieces made by cuts get fresh ids). ``apply_cut``
subtracts a cut solid Gamma^c (``xfem._cuts.cut_solid``) from every subdomain it meets and replaces the
subdomain by the connected components of the difference (``Manifold.decompose``):

- several components: the subdomain is split; the children get fresh ids and record the old id as their
  ``parent``, so that the caller duplicates the parent's DOF values into them (Algorithm 1 line 7, which
  keeps the displacement field of eq. 18 unchanged);
- one component: the subdomain keeps its id (and DOFs) but its geometry becomes the difference. Algorithm 1
  keeps the old geometry in this case; keeping the difference instead lets a later cut that completes a
  partial one (the next time step of a swept scalpel) split the subdomain, and makes the element volumes
  exact (the removed slab E^- of eq. 20 is not integrated);
- no component (the subdomain lies inside the cut): it disappears, with its DOFs.

Culling (sec. 4.4). Primary: the tets' axis-aligned bounding boxes against the cut's box, then the tets
against the cut's triangles (their boxes, then the separating axis test of tet and triangle); a tet in the
box that meets no triangle meets the cut only if it lies inside it (winding number of a corner). All of it is
vectorized numpy over tets (the paper uses an AABB tree). Secondary, exact: the element Booleans themselves. An
element subdomain is met by the cut when the difference lost volume (more than ``1e-12`` of the subdomain's);
a nodal 1-ring (a union of tets) is met exactly when one of its tets is, so only the nodes of met elements get
nodal Booleans. Triangle meshes are built lazily: a node or element no cut meets never gets one.

Robustness (sec. 6.1, cuts aligned with element faces, edges and vertices). manifold3d is exact in its
topology (symbolic perturbation) and always returns closed manifolds, but a cut face coplanar with a tet face
may leave sliver components of rounding-size volume: components below ``1e-12`` of the subdomain's volume are
dropped. ``apply_cut(..., perturb=h)`` applies the paper's gentle perturbation instead: while a node of a
candidate tet lies within ``h / 100`` of the cut's surface, the cut is moved by a random rigid motion of size
h (a rotation by ``h / size`` about its box centre and a translation of length h, both of random direction).
"""

from __future__ import annotations

import contextlib
import itertools
import os
import time
from concurrent.futures import Executor, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import NamedTuple

import igl
import manifold3d
import numpy as np
from jaxtyping import Float, Int
from scipy.spatial.transform import Rotation

from _jaxcga_shared.mesh import TET_FACES
from xfem._tetmesh import TetMesh, node_rings

# pieces and volume changes below this fraction of a subdomain's volume are rounding, not material
_RELATIVE_VOLUME = 1e-12
# the cores this process may run on, at least 2 (CI's) and at most 8: a cut's ~2,000 Booleans make ~70 tasks
_CORES = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 2
BOOLEAN_THREADS = min(8, max(2, _CORES))  # a cut's Boolean threads (XFEMModel's pool)
_BOOLEAN_CHUNK = 32  # subdomains per task
# attempts of the gentle perturbation before giving up, and the alignment distance relative to the motion
_PERTURB_TRIES = 16
_ALIGNED = 1e-2
# tet-triangle pairs tested at once in the culling, and its contact tolerance relative to the boxes' size
_PAIRS = 1 << 20
_SLACK = 1e-12


def _solid(V: np.ndarray, F: np.ndarray, what: str) -> manifold3d.Manifold:
    """A Manifold from its vertices V and outward triangles F (into V)."""
    mesh = manifold3d.Mesh64(
        vert_properties=np.ascontiguousarray(V, np.float64), tri_verts=np.ascontiguousarray(F, np.uint64)
    )
    solid = manifold3d.Manifold(mesh)
    if solid.status() != manifold3d.Error.NoError or solid.volume() <= 0:
        raise ValueError(
            f"mesh: manifold3d rejected the boundary of {what} (status {solid.status().name}); "
            "the mesh must be manifold around every node"
        )
    return solid


class MeshSolid(NamedTuple):
    """A closed solid as its float64 triangle mesh, for a trip between processes (``xfem._cut_process``): a
    ``manifold3d.Manifold`` does not pickle. ``build`` gives the Manifold; ``solid_mesh`` the other way."""

    V: np.ndarray  # (k, 3) float64 vertices
    F: np.ndarray  # (f, 3) int64 outward triangles
    tolerance: float  # the Manifold's tolerance (its Mesh64's), kept so that its Booleans round alike

    def build(self) -> manifold3d.Manifold:
        # copies: manifold3d takes writable arrays only, and a received mesh may be a read-only view
        return manifold3d.Manifold(
            manifold3d.Mesh64(
                vert_properties=np.array(self.V, np.float64, order="C"),
                tri_verts=np.array(self.F, np.uint64, order="C"),
                tolerance=self.tolerance,
            )
        )


def solid_mesh(solid: manifold3d.Manifold) -> MeshSolid:
    """The ``MeshSolid`` of a Manifold (its vertices and triangles also feed the integrals and distance queries)."""
    mesh = solid.to_mesh64()
    return MeshSolid(
        np.ascontiguousarray(np.asarray(mesh.vert_properties, np.float64)[:, :3]),
        np.ascontiguousarray(np.asarray(mesh.tri_verts, np.int64)),
        float(solid.get_tolerance()),
    )


@dataclass
class _Kind:
    """The subdomains of one kind (nodal or element), indexed by id.

    Attributes:
        live: per owner (node or element), the ids of its current subdomains.
        owner: per id, its node or element.
        parent: per id, the id it was split from; -1 for the initial ones.
        solids: per id, its Manifold; None for an initial subdomain not built yet or a retired id; a
            ``MeshSolid`` for one received in a delta (``Subdomains.apply_delta``), built on first use.
        alive: per id, whether it is current.
        retired: the ids retired by cuts, in order (``Subdomains.delta``).
        reshaped: the ids whose solid a cut replaced (one component left), in order (``Subdomains.delta``).
    """

    live: list[list[int]]
    owner: list[int]
    parent: list[int]
    solids: list[manifold3d.Manifold | MeshSolid | None]
    alive: list[bool]
    retired: list[int] = field(default_factory=list)
    reshaped: list[int] = field(default_factory=list)

    @classmethod
    def initial(cls, n: int) -> _Kind:
        return cls([[i] for i in range(n)], list(range(n)), [-1] * n, [None] * n, [True] * n)

    def add(self, owner: int, parent: int, solid: manifold3d.Manifold) -> int:
        self.owner.append(owner)
        self.parent.append(parent)
        self.solids.append(solid)
        self.alive.append(True)
        return len(self.owner) - 1

    def retire(self, sid: int) -> None:
        self.alive[sid] = False
        self.solids[sid] = None
        self.retired.append(sid)

    def reshape(self, sid: int, solid: manifold3d.Manifold) -> None:
        self.solids[sid] = solid
        self.reshaped.append(sid)

    def mark(self) -> tuple[int, int, int]:
        return len(self.owner), len(self.retired), len(self.reshaped)

    def delta(self, since: tuple[int, int, int]) -> KindDelta:
        start, retired, reshaped = since
        retired, reshaped = self.retired[retired:], self.reshaped[reshaped:]
        changed = sorted(
            {s for s in range(start, len(self.owner)) if self.alive[s]} | {s for s in reshaped if self.alive[s]}
        )
        owners = {self.owner[s] for s in (*range(start, len(self.owner)), *retired, *reshaped)}
        return KindDelta(
            start,
            np.asarray(self.owner[start:], np.int64),
            np.asarray(self.parent[start:], np.int64),
            np.asarray(retired, np.int64),
            np.asarray(reshaped, np.int64),
            {o: list(self.live[o]) for o in sorted(owners)},
            np.asarray(changed, np.int64),
            pack_meshes([_as_mesh(self.solids[s]) for s in changed]),
        )

    def apply(self, delta: KindDelta) -> None:
        added = len(delta.owner)
        self.owner.extend(delta.owner.tolist())
        self.parent.extend(delta.parent.tolist())
        self.alive.extend([True] * added)
        self.solids.extend([None] * added)
        for sid in delta.retired.tolist():
            self.retire(sid)
        self.reshaped.extend(delta.reshaped.tolist())
        for owner, ids in delta.live.items():
            self.live[owner] = list(ids)
        for sid, mesh in zip(delta.changed.tolist(), unpack_meshes(delta.meshes)):
            self.solids[sid] = mesh  # built into a Manifold on first use (Subdomains.node_solid)


class KindDelta(NamedTuple):
    """What cuts changed in the subdomains of one kind since a mark (``Subdomains.delta``).

    Attributes:
        start: the number of ids at the mark; the new ids follow.
        owner, parent: (k,) int64 the new ids' owners and parents.
        retired: (r,) int64 the ids retired since the mark.
        reshaped: (s,) int64 the ids whose solid a cut replaced since the mark.
        live: owner -> the ids of its current subdomains, for every owner of a new, retired or reshaped id.
        changed: (c,) int64 the current ids among the new and reshaped, whose solids ``meshes`` holds.
        meshes: their ``MeshSolid``s, ``pack_meshes``.
    """

    start: int
    owner: np.ndarray
    parent: np.ndarray
    retired: np.ndarray
    reshaped: np.ndarray
    live: dict[int, list[int]]
    changed: np.ndarray
    meshes: tuple


class SubdomainsDelta(NamedTuple):
    """What cuts changed in ``Subdomains`` since a mark: ``Subdomains.delta``, for ``Subdomains.apply_delta``."""

    nodes: KindDelta
    elements: KindDelta


def _as_mesh(solid) -> MeshSolid:
    return solid if isinstance(solid, MeshSolid) else solid_mesh(solid)


def pack_meshes(meshes: list[MeshSolid]) -> tuple:
    """``MeshSolid``s as a few flat arrays (one pickle of thousands of small arrays holds the GIL for long)."""
    if not meshes:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    return (
        np.concatenate([m.V for m in meshes]),
        np.concatenate([m.F for m in meshes]),
        np.array([len(m.V) for m in meshes]),
        np.array([len(m.F) for m in meshes]),
        np.array([m.tolerance for m in meshes], np.float64),
    )


def unpack_meshes(packed: tuple) -> list[MeshSolid]:
    """``pack_meshes`` undone (views into the flat arrays)."""
    V, F, vertex_counts, face_counts, tolerances = packed
    vertex_ends, face_ends = np.cumsum(vertex_counts).tolist(), np.cumsum(face_counts).tolist()
    return [
        MeshSolid(V[v_end - nv : v_end], F[f_end - nf : f_end], tol)
        for v_end, nv, f_end, nf, tol in zip(
            vertex_ends, vertex_counts.tolist(), face_ends, face_counts.tolist(), tolerances.tolist()
        )
    ]


class Subdomains:
    """The nodal and element subdomains of a tet mesh (host data; build with ``subdomains``, update with
    ``apply_cut``).

    Attributes:
        X: (n, 3) float64 node positions.
        T: (m, 4) int64 tets.
        ring_offsets, ring_elements: the tets of node i are ``ring_elements[ring_offsets[i]:ring_offsets[i+1]]``.
        tet_low, tet_high: (m, 3) the tets' bounding boxes.
    """

    def __init__(self, mesh: TetMesh):
        self.X = np.asarray(mesh.X, np.float64)
        self.T = np.asarray(mesh.T, np.int64)
        self.ring_offsets, self.ring_elements = node_rings(self.T, len(self.X))
        corners = self.X[self.T]
        self.tet_low, self.tet_high = corners.min(axis=1), corners.max(axis=1)
        self._nodes = _Kind.initial(len(self.X))
        self._elements = _Kind.initial(len(self.T))

    @property
    def n_nodes(self) -> int:
        return len(self.X)

    @property
    def n_elements(self) -> int:
        return len(self.T)

    def mark(self) -> tuple:
        """A mark of the subdomains as they are now, for ``delta``."""
        return self._nodes.mark(), self._elements.mark()

    def delta(self, since: tuple) -> SubdomainsDelta:
        """What the cuts made since the mark ``since`` (``mark``) changed: new, retired and reshaped ids, the
        touched owners' lists and the changed solids as meshes. ``apply_delta`` makes another ``Subdomains`` of the
        same mesh, as it was at the mark, equal to this one (a replica in another process: ``xfem._background``)."""
        return SubdomainsDelta(self._nodes.delta(since[0]), self._elements.delta(since[1]))

    def apply_delta(self, delta: SubdomainsDelta) -> None:
        """Apply ``delta`` (from ``delta`` of a ``Subdomains`` of the same mesh that was equal to this one at its
        mark); ValueError, before any change, if this one's ids do not match the mark's."""
        if not isinstance(delta, SubdomainsDelta):
            raise ValueError(f"delta: expected a SubdomainsDelta, got {type(delta).__name__}")
        counts = (len(self._nodes.owner), len(self._elements.owner))
        if (delta.nodes.start, delta.elements.start) != counts:
            raise ValueError(
                f"delta: made from subdomains with {delta.nodes.start} nodal and {delta.elements.start} "
                f"element ids, these have {counts[0]} and {counts[1]}"
            )
        self._nodes.apply(delta.nodes)
        self._elements.apply(delta.elements)

    def node_subdomains(self, i: int) -> list[int]:
        """The ids of node i's current nodal subdomains S(i) (eq. 18), in creation order."""
        return list(self._nodes.live[i])

    def first_node_subdomains(self) -> Int[np.ndarray, " n"]:
        """(n,) int64 the first current nodal subdomain of every node (its initial one, id i, until a cut splits
        it), -1 for a node with none left."""
        return np.fromiter((ids[0] if ids else -1 for ids in self._nodes.live), np.int64, len(self.X))

    def node_subdomain_counts(self) -> Int[np.ndarray, " n"]:
        """(n,) int64 the number of current nodal subdomains of every node."""
        return np.fromiter(map(len, self._nodes.live), np.int64, len(self.X))

    def element_subdomain_arrays(self, elements: Int[np.ndarray, " k"]) -> tuple[np.ndarray, np.ndarray]:
        """The current element subdomains of the given elements, flattened: (p,) int64 their elements and (p,) int64
        their ids, element by element, each element's in creation order."""
        lists = [self._elements.live[e] for e in np.asarray(elements, np.int64).tolist()]
        counts = np.fromiter(map(len, lists), np.int64, len(lists))
        ids = np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(counts.sum()))
        return np.repeat(np.asarray(elements, np.int64), counts), ids

    def element_subdomains(self, e: int) -> list[int]:
        """The ids of element e's current element subdomains (eq. 20), in creation order."""
        return list(self._elements.live[e])

    def node_of(self, sid: int) -> int:
        """The node of nodal subdomain sid."""
        return self._nodes.owner[sid]

    def element_of(self, sid: int) -> int:
        """The element of element subdomain sid."""
        return self._elements.owner[sid]

    def node_parent(self, sid: int) -> int:
        """The nodal subdomain that sid was split from (its DOFs are the parent's at the cut), -1 if initial."""
        return self._nodes.parent[sid]

    def element_parent(self, sid: int) -> int:
        """The element subdomain that sid was split from, -1 if initial."""
        return self._elements.parent[sid]

    def node_alive(self, sid: int) -> bool:
        """Whether nodal subdomain sid is current (not split or removed since)."""
        return self._nodes.alive[sid]

    def element_alive(self, sid: int) -> bool:
        """Whether element subdomain sid is current."""
        return self._elements.alive[sid]

    def node_solid(self, sid: int) -> manifold3d.Manifold:
        """The closed solid of current nodal subdomain sid (built on first use for an uncut 1-ring)."""
        if not self._nodes.alive[sid]:
            raise ValueError(f"sid: nodal subdomain {sid} was split or removed by a cut")
        if self._nodes.solids[sid] is None:  # an unbuilt subdomain is the initial one, whose id is the node
            self._build_initial([sid], ())
        elif isinstance(self._nodes.solids[sid], MeshSolid):
            # pyright does not narrow solids[sid] (a variable index): a MeshSolid here, a Manifold once built
            self._nodes.solids[sid] = self._nodes.solids[sid].build()  # pyright: ignore[reportAttributeAccessIssue, reportOptionalMemberAccess]
        return self._nodes.solids[sid]  # pyright: ignore[reportReturnType]

    def element_solid(self, sid: int) -> manifold3d.Manifold:
        """The closed solid of current element subdomain sid (built on first use for an uncut tet)."""
        if not self._elements.alive[sid]:
            raise ValueError(f"sid: element subdomain {sid} was split or removed by a cut")
        if self._elements.solids[sid] is None:
            self._build_initial((), [sid])
        elif isinstance(self._elements.solids[sid], MeshSolid):
            # as in node_solid
            self._elements.solids[sid] = self._elements.solids[sid].build()  # pyright: ignore[reportAttributeAccessIssue, reportOptionalMemberAccess]
        return self._elements.solids[sid]  # pyright: ignore[reportReturnType]

    def _build_initial(self, node_sids, element_sids) -> None:
        """Build the solids of the given subdomains that are initial and not built yet, in one vectorized pass:
        a 1-ring's boundary faces (``boundary_faces`` of its tets, in their order) on its vertices in index
        order, a tet's faces on its sorted nodes. ``apply_cut`` builds all those a cut needs at once: built one
        by one, the per-ring numpy calls took as long as the Booleans themselves, holding the GIL the Boolean
        threads share."""
        n = len(self.X)
        nodes = np.array(
            [s for s in node_sids if s < n and self._nodes.solids[s] is None and self._nodes.alive[s]], np.int64
        )
        if len(nodes):
            counts = self.ring_offsets[nodes + 1] - self.ring_offsets[nodes]
            owner = np.repeat(np.arange(len(nodes)), counts)
            first = np.cumsum(counts) - counts
            tets = self.ring_elements[np.repeat(self.ring_offsets[nodes] - first, counts) + np.arange(counts.sum())]
            faces = self.T[tets][:, TET_FACES].reshape(-1, 3)  # by ring, by tet, as boundary_faces of each ring
            face_owner = np.repeat(owner, 4)
            keys = np.sort(faces, axis=1)
            order = np.lexsort((keys[:, 2], keys[:, 1], keys[:, 0], face_owner))
            rows = np.column_stack([face_owner, keys])[order]
            same = np.all(rows[1:] == rows[:-1], axis=1)
            shared = np.zeros(len(rows), bool)
            shared[1:] |= same
            shared[:-1] |= same
            once = np.empty(len(rows), bool)
            once[order] = ~shared
            F, F_owner = faces[once], face_owner[once]  # each ring's boundary faces, in ring order
            # per ring, its vertices in index order (np.unique, as _solid)
            used, local = np.unique(F_owner[:, None] * n + F, return_inverse=True)
            vertex_start = np.searchsorted(used // n, np.arange(len(nodes) + 1))
            face_start = np.searchsorted(F_owner, np.arange(len(nodes) + 1))
            local = local.reshape(-1, 3) - vertex_start[F_owner][:, None]
            vertices = self.X[used % n]
            for j, i in enumerate(nodes.tolist()):
                self._nodes.solids[i] = _solid(
                    vertices[vertex_start[j] : vertex_start[j + 1]],
                    local[face_start[j] : face_start[j + 1]],
                    f"the 1-ring of node {i}",
                )
        m = len(self.T)
        elements = np.array(
            [s for s in element_sids if s < m and self._elements.solids[s] is None and self._elements.alive[s]],
            np.int64,
        )
        if len(elements):
            T = self.T[elements]
            rank = np.argsort(np.argsort(T, axis=1), axis=1)  # each node's place among its tet's sorted nodes
            V, F = self.X[np.sort(T, axis=1)], rank[:, TET_FACES]
            for j, e in enumerate(elements.tolist()):
                self._elements.solids[e] = _solid(V[j], F[j], f"tet {e}")

    def node_built(self, i: int) -> bool:
        """Whether node i's subdomains have triangle meshes (False until a cut meets its 1-ring)."""
        return self._nodes.live[i] != [i] or self._nodes.solids[i] is not None

    def element_built(self, e: int) -> bool:
        """Whether element e's subdomains have triangle meshes (False until a cut meets the tet)."""
        return self._elements.live[e] != [e] or self._elements.solids[e] is not None


def subdomains(mesh: TetMesh) -> Subdomains:
    """The initial subdomains of a tet mesh: one per node (its 1-ring) and one per element (the tet).

    Args:
        mesh: the ``TetMesh`` (positively oriented tets, as its constructors guarantee).
    Returns:
        The ``Subdomains``; no triangle mesh is built until a cut meets it.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh: expected a TetMesh, got {type(mesh).__name__}")
    return Subdomains(mesh)


@dataclass(frozen=True)
class CutStats:
    """The work of one cut and its wall time.

    Attributes:
        n_booleans: the Boolean differences computed.
        boolean_seconds: wall time in them (difference, decomposition and volumes).
        pieces_integrated: element pieces whose integrals were recomputed (``XFEMModel.cut``; 0 in ``apply_cut``).
        integration_seconds: wall time in those integrals (eq. 21; Table 2's EI is this over the pieces).
        enrichment_seconds: wall time in the indicator queries (eq. 16) and the DOF renumbering.
    """

    n_booleans: int = 0
    boolean_seconds: float = 0.0
    pieces_integrated: int = 0
    integration_seconds: float = 0.0
    enrichment_seconds: float = 0.0


@dataclass(frozen=True, eq=False)
class CutReport:
    """What one cut changed (``apply_cut``; ``XFEMModel.cut`` adds the DOF copy map and its own stats).

    Attributes:
        boxed: (b,) int64 elements whose bounding box meets the cut's bounding box.
        candidates: (c,) int64 those of them that meet the cut solid by the exact-up-to-rounding culling test
            (tet-triangle separating axes, winding number); they get element Booleans.
        elements_touched: (t,) int64 elements whose subdomains the cut met (lost volume).
        nodes_touched: (u,) int64 nodes of those elements (the 1-rings the cut met).
        node_children: nodal subdomain id -> the ids of its pieces, for every nodal subdomain split (two or
            more pieces; the caller copies the parent's DOFs to each, Algorithm 1 line 7) or removed (empty).
        element_children: the same for element subdomains.
        nodes_split: (p,) int64 nodes that gained subdomains.
        elements_split: (q,) int64 elements that gained subdomains.
        motion: (3, 4) the rigid motion applied to the cut by the perturbation (identity when none).
        stats: the ``CutStats``.
        dof_source: (n_dofs,) int64, for each DOF after the cut, the DOF before it whose x and v it copies
            (Algorithm 1 line 7: a linear map of the state, ``x_new = x_old[dof_source]``); None from
            ``apply_cut``, and from an ``XFEMModel`` cut that met no element (nothing changed).
    """

    boxed: Int[np.ndarray, " b"]
    candidates: Int[np.ndarray, " c"]
    elements_touched: Int[np.ndarray, " t"]
    nodes_touched: Int[np.ndarray, " u"]
    node_children: dict[int, tuple[int, ...]]
    element_children: dict[int, tuple[int, ...]]
    nodes_split: Int[np.ndarray, " p"]
    elements_split: Int[np.ndarray, " q"]
    motion: Float[np.ndarray, "3 4"] = field(default_factory=lambda: np.eye(4)[:3])
    stats: CutStats = CutStats()
    dof_source: Int[np.ndarray, " n_dofs"] | None = None


def _difference(solid: manifold3d.Manifold, cut: manifold3d.Manifold):
    """The components of solid minus cut, or None when the cut does not meet the solid (no volume lost)."""
    before = solid.volume()
    pieces = (solid - cut).decompose()
    volumes = [p.volume() for p in pieces]
    tiny = _RELATIVE_VOLUME * before
    if before - sum(volumes) <= tiny:
        return None
    return [p for p, v in zip(pieces, volumes) if v > tiny]


def _differences(sids: list[int], solid_of, cut: manifold3d.Manifold, tally: list, pool: Executor | None) -> list:
    """``_difference`` of the solids of the subdomains sids (built on first use by ``solid_of``), in parallel
    on the ``pool``'s threads (manifold3d releases the GIL) or, pool None, in this thread; ``tally`` ([count,
    seconds]) counts them and their wall time (with the building of the solids)."""
    start = time.perf_counter()

    def difference(sid):
        return _difference(solid_of(sid), cut)

    def differences(chunk):
        return [difference(sid) for sid in chunk]

    if pool is None or len(sids) < 2 * _BOOLEAN_CHUNK:
        results = differences(sids)
    else:
        # a task per chunk: ThreadPoolExecutor.map ignores its chunksize, and a future per Boolean cost about a
        # quarter of the Booleans' wall time
        chunks = [sids[k : k + _BOOLEAN_CHUNK] for k in range(0, len(sids), _BOOLEAN_CHUNK)]
        results = list(itertools.chain.from_iterable(pool.map(differences, chunks)))
    tally[0] += len(sids)
    tally[1] += time.perf_counter() - start
    return results


def _cut_kind(
    kind: _Kind,
    owners,
    solid_of,
    cut: manifold3d.Manifold,
    tally: list,
    children: dict[int, tuple[int, ...]],
    pool: Executor | None,
) -> tuple[list[int], list[int]]:
    """Algorithm 1 lines 2-8 (or 12-17) for the given owners: the owners met and those split."""
    met, split = [], []
    sids = [sid for owner in owners for sid in kind.live[owner]]
    results = dict(zip(sids, _differences(sids, solid_of, cut, tally, pool)))
    for owner in owners:
        old = kind.live[owner]
        new_live, hit = [], False
        for sid in old:
            pieces = results[sid]
            if pieces is None:
                new_live.append(sid)
                continue
            hit = True
            if len(pieces) == 1:  # reshaped, same DOFs
                kind.reshape(sid, pieces[0])
                new_live.append(sid)
                continue
            kind.retire(sid)
            ids = tuple(kind.add(owner, sid, p) for p in pieces)
            children[sid] = ids
            new_live.extend(ids)
        if hit:
            met.append(owner)
        if len(new_live) > len(old):
            split.append(owner)
        kind.live[owner] = new_live
    return met, split


def _aligned(sub: Subdomains, candidates: np.ndarray, cut: manifold3d.Manifold, tol: float) -> bool:
    """Whether a node of the candidate tets lies within tol of the cut's surface."""
    if len(candidates) == 0:
        return False
    mesh = cut.to_mesh64()
    V = np.asarray(mesh.vert_properties, np.float64)[:, :3]
    F = np.asarray(mesh.tri_verts, np.int64)
    points = sub.X[np.unique(sub.T[candidates])]
    distance2 = igl.point_mesh_squared_distance(points, V, F)[0]
    return bool(np.min(distance2) < tol * tol)


def _candidates(sub: Subdomains, cut: manifold3d.Manifold) -> tuple[np.ndarray, np.ndarray]:
    """The tets whose box meets the cut's box, and those of them that meet the cut solid (primary culling).

    A tet meets the closed solid iff it meets a boundary triangle (box filter, then the separating axis test,
    ``xfem._overlap``) or, meeting none, lies inside the solid (winding number of one corner)."""
    from xfem._overlap import tet_triangle_overlap  # numba: imported on first use

    box = np.asarray(cut.bounding_box(), np.float64)
    boxed = np.flatnonzero(np.all((sub.tet_low <= box[3:]) & (sub.tet_high >= box[:3]), axis=1))
    if len(boxed) == 0:
        return boxed, boxed
    mesh = cut.to_mesh64()
    V = np.asarray(mesh.vert_properties, np.float64)[:, :3]
    F = np.asarray(mesh.tri_verts, np.int64)
    triangles = V[F]
    tri_low, tri_high = triangles.min(axis=1), triangles.max(axis=1)
    low, high = sub.tet_low[boxed], sub.tet_high[boxed]
    slack = _SLACK * float(np.max(box[3:] - box[:3]) + np.max(high - low))
    near = np.zeros(len(boxed), bool)
    chunk = max(1, _PAIRS // len(boxed))  # bounds the (tets, triangles) pair arrays
    for start in range(0, len(F), chunk):
        t_low, t_high = tri_low[start : start + chunk], tri_high[start : start + chunk]
        pairs = np.all((low[:, None] <= t_high[None] + slack) & (high[:, None] >= t_low[None] - slack), axis=2)
        pairs[near] = False  # already known to meet the cut
        k, j = np.nonzero(pairs)
        hit = tet_triangle_overlap(sub.X[sub.T[boxed[k]]], triangles[start + j], slack)
        near[k[hit]] = True
    far = boxed[~near]
    inside = np.asarray(igl.winding_number(V, F, sub.X[sub.T[far, 0]])) > 0.5  # igl's stubs: ArrayLike
    return boxed, np.sort(np.concatenate([boxed[near], far[inside]]))


def check_cut(cut: manifold3d.Manifold, perturb: float) -> None:
    """``apply_cut``'s checks of its cut solid and perturbation size (ValueError)."""
    if not isinstance(cut, manifold3d.Manifold):
        raise ValueError(f"cut: expected a manifold3d.Manifold, got {type(cut).__name__}")
    if cut.status() != manifold3d.Error.NoError or cut.is_empty() or cut.volume() <= 0:
        raise ValueError(f"cut: expected a valid non-empty solid (status {cut.status().name}, volume {cut.volume()})")
    if not np.isfinite(perturb) or perturb < 0:
        raise ValueError(f"perturb: expected a distance >= 0, got {perturb!r}")


def apply_cut(
    sub: Subdomains,
    cut: manifold3d.Manifold,
    perturb: float = 0.0,
    seed: int = 0,
    parallel: bool = True,
    pool: Executor | None = None,
) -> CutReport:
    """Cut all subdomains by one cut solid (Algorithm 1 lines 1-19), in place.

    Args:
        sub: the ``Subdomains`` to update.
        cut: the closed cut solid Gamma^c (``xfem._cuts.cut_solid``), non-empty.
        perturb: 0, or a distance h > 0: while a node of a candidate tet lies within h / 100 of the cut's
            surface, move the cut by a random rigid motion of size h (sec. 6.1, gentle perturbation);
            ValueError if still aligned after 16 tries.
        seed: seed of the perturbation's random motions.
        parallel: run the Booleans on several threads: ``pool``'s, or without one ``BOOLEAN_THREADS`` threads of
            this call's own (ended before it returns); False: in the calling thread (a cut in the background leaves
            the other core to the steps).
        pool: None, or the ``concurrent.futures.Executor`` to run the Booleans on (``XFEMModel``'s, which it
            owns and closes).
    Returns:
        The ``CutReport``.
    """
    if not isinstance(sub, Subdomains):
        raise ValueError(f"sub: expected Subdomains, got {type(sub).__name__}")
    check_cut(cut, perturb)
    motion = np.eye(4)[:3]
    boxed, candidates = _candidates(sub, cut)
    if perturb > 0:
        rng = np.random.default_rng(seed)
        box = np.asarray(cut.bounding_box(), np.float64)
        centre, size = (box[:3] + box[3:]) / 2, np.linalg.norm(box[3:] - box[:3])
        original, tries = cut, 0
        while _aligned(sub, candidates, cut, _ALIGNED * perturb):
            if tries == _PERTURB_TRIES:
                raise ValueError(
                    f"perturb: the cut stays within {_ALIGNED * perturb} of mesh nodes after {tries} random motions"
                )
            tries += 1
            axis = rng.normal(size=3)
            R = Rotation.from_rotvec(axis / np.linalg.norm(axis) * perturb / size).as_matrix()
            shift = rng.normal(size=3)
            t = centre - R @ centre + perturb * shift / np.linalg.norm(shift)
            motion = np.concatenate([R, t[:, None]], axis=1)
            cut = original.transform(motion)
            boxed, candidates = _candidates(sub, cut)
    with contextlib.ExitStack() as stack:
        if parallel and pool is None:  # a pool of this call's own, ended before it returns
            pool = stack.enter_context(ThreadPoolExecutor(BOOLEAN_THREADS, thread_name_prefix="xfem-boolean"))
        return _split(sub, cut, boxed, candidates, motion, pool if parallel else None)


def _split(sub: Subdomains, cut, boxed, candidates, motion, pool: Executor | None) -> CutReport:
    """``apply_cut`` after the cut's placement: the subdomains split, on ``pool``'s threads (None: this one)."""
    tally = [0, 0.0]  # Booleans and their seconds
    element_children: dict[int, tuple[int, ...]] = {}
    node_children: dict[int, tuple[int, ...]] = {}
    start = time.perf_counter()  # the solids' building counts as Boolean time (as when built one by one)
    sub._build_initial((), candidates.tolist())
    tally[1] += time.perf_counter() - start
    met, elements_split = _cut_kind(
        sub._elements, candidates.tolist(), sub.element_solid, cut, tally, element_children, pool
    )
    elements_touched = np.asarray(met, np.int64)
    nodes_touched = np.unique(sub.T[elements_touched]) if met else np.zeros(0, np.int64)
    start = time.perf_counter()
    sub._build_initial(nodes_touched.tolist(), ())
    tally[1] += time.perf_counter() - start
    _, nodes_split = _cut_kind(sub._nodes, nodes_touched.tolist(), sub.node_solid, cut, tally, node_children, pool)
    return CutReport(
        boxed,
        candidates,
        elements_touched,
        nodes_touched,
        node_children,
        element_children,
        np.asarray(nodes_split, np.int64),
        np.asarray(elements_split, np.int64),
        motion,
        CutStats(n_booleans=tally[0], boolean_seconds=tally[1]),
    )
