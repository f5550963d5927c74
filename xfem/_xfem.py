"""The cutting simulation of the XFEM paper: generalized enrichments (sec. 4.2, eq. 15-18), exact integration of
the enriched mass and forces over element subdomains (sec. 3.5 and 4.3, eq. 13, 14, 19-21) and the per-step
Algorithm 1 (sec. 4.4): cut the subdomains (lines 1-19, ``xfem._subdomains.apply_cut``), duplicate DOFs (line
7), recompute the touched elements (lines 20-25) and step the FEM core (line 26, ``backward_euler_step``).
The steps run the system padded to a capacity level (``xfem._capacity``); ``xfem._background`` computes cuts in a
worker process while a model steps.

DOFs. Every current nodal subdomain Omega^{i,s} carries one DOF, the coefficient u_i^s of eq. 18 (here the
position ``X_i + u_i^s`` and the velocity). When a cut splits Omega^{i,s}, each piece gets a copy of its x and
v (line 7): the pieces' indicators sum to the parent's on the material, so eq. 18 keeps its value at every
material point. DOFs are numbered node by node, a node's subdomains by id (creation order); an uncut model has
DOF i = node i. A nodal subdomain that no element piece reaches (possible only through dropped rounding-size
slivers) gets no DOF. A thin sliver that is kept (e.g. left by a perturbed cut next to a node layer, 1e-7
thick) gives its DOF a mass near rounding (entries of either sign): the step's matrix ``M + h^2 K`` stays positive
definite through the sliver's stiffness, and the runs stay stable (tests/xfem/test_robustness.py), but such a
DOF's velocity means little.

Element pieces. Every current element subdomain p of element e (a "piece") is an element of the FEM core: its
4 DOFs, the shape gradients of e (the enriched basis is phi_i on p), the weight |p| (the elastic energy is
psi(F) |p|, sec. 4.3), and its exact 4 x 4 mass ``rho int_p phi_a phi_b`` and loads ``int_p phi_a`` (eq. 13,
14 by eq. 21, ``xfem._integration``). Elements no cut has met keep the closed forms of the whole tet (vectorized,
no Booleans): ``rho V (1 + delta_ab) / 20`` and ``V / 4``, the plain FEM values.

Enrichment (eq. 16). The DOF of local node a of piece p is that of the subdomain s of node i = T[e, a] whose
indicator psi_i^s is 1 on p: the one with the smallest distance to a point X_p strictly inside p. The distance
to a solid (not to its boundary: eq. 16 compares ``dist(X, Omega^{i,s})``) is 0 where the winding number of its
boundary mesh exceeds 1/2 (``xfem._winding``: libigl's ``winding_number`` sums, for many meshes in one call) and
the unsigned distance to the boundary mesh (libigl ``point_mesh_squared_distance``) elsewhere. X_p is the
centroid of p's largest boundary triangle moved inward, along the triangle's normal, by 1e-6 times the square root
of its area: the point lies inside p (and so inside exactly one of node i's subdomains, which are disjoint and at
least the cut's thickness apart, eq. 17) unless p is thinner than that offset there. A node with a single
subdomain needs no query.
"""

from __future__ import annotations

import dataclasses
import itertools
import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import igl
import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jaxtyping import Array, Float, Int
from scipy.sparse.csgraph import connected_components

from _jaxcga_shared.checks import check_positive, check_real
from xfem._assembly import sorted_unique
from xfem._backward_euler import FEMSystem, State, fem_system
from xfem._capacity import Capacities, CompiledSteps, PaddedSystem, padded_state
from xfem._integration import element_piece_integrals, linear_shape_coefficients, moments_of_pieces
from xfem._linear_tet import shape_gradients
from xfem._material import Material
from xfem._subdomains import (
    BOOLEAN_THREADS,
    CutReport,
    MeshSolid,
    Subdomains,
    SubdomainsDelta,
    apply_cut,
    check_cut,
    solid_mesh,
    subdomains,
)
from xfem._tetmesh import TetMesh

_INWARD = 1e-6  # inward offset of a piece's query point, relative to the square root of its triangle's area


def _interior_points(V: np.ndarray, F: np.ndarray, piece: np.ndarray, k: int) -> np.ndarray:
    """(k, 3) a point strictly inside each of k solids whose boundary triangles F (into V) carry their solid's
    index in ``piece``: the solid's largest triangle's centroid moved inward (module docstring)."""
    corners = V[F]
    normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
    areas2 = np.linalg.norm(normals, axis=1)
    order = np.lexsort((-areas2, piece))
    largest = order[np.searchsorted(piece[order], np.arange(k))]  # the first of each piece: its largest
    inward = -normals[largest] / areas2[largest, None]
    return corners[largest].mean(axis=1) + _INWARD * np.sqrt(areas2[largest, None] / 2) * inward


def _nearest_subdomains(
    meshes: list[tuple[np.ndarray, ...]], first: np.ndarray, group: np.ndarray, points: np.ndarray
) -> np.ndarray:
    """Eq. 16 for points in groups, each group with its own solids: (k,) for each point, the index within its
    group of the solid at the smallest distance (0 inside; the first such solid).

    meshes: (V, F) of every solid, its boundary mesh, group after group; first: (groups + 1,) where each group's
    solids start; group: (k,) the group of each point. A point inside a solid needs no distance: the winding
    numbers are taken first (all of them in one call, ``xfem._winding``), and only in the solids' bounding boxes;
    the distances only for the points inside none of their solids."""
    from xfem._winding import winding_numbers  # numba: imported on first use

    count = np.diff(first)[group]
    point = np.repeat(np.arange(len(points)), count)  # one query per point and solid of its group
    option = np.arange(len(point)) - np.repeat(np.cumsum(count) - count, count)
    solid = first[group][point] + option
    sizes = np.array([(len(V), len(F)) for V, F in meshes], np.int64).reshape(-1, 2)
    vertex_start, face_start = (np.concatenate([[0], np.cumsum(sizes[:, k])]) for k in (0, 1))
    vertices = np.concatenate([V for V, _ in meshes]).astype(np.float64, copy=False)
    triangles = np.concatenate([F for _, F in meshes]).astype(np.int64, copy=False)
    # the bounding boxes of all solids in two calls (a min and a max a solid took longer than its winding numbers)
    lower, upper = (f.reduceat(vertices, vertex_start[:-1]) for f in (np.minimum, np.maximum))
    boxed = np.flatnonzero(np.all((points[point] >= lower[solid]) & (points[point] <= upper[solid]), axis=1))
    winding = winding_numbers(vertices, triangles, vertex_start, face_start, solid[boxed], points[point[boxed]])
    inside = boxed[winding > 0.5]
    none = int(first[-1])  # more than any group's solids
    chosen = np.full(len(points), none, np.int64)
    np.minimum.at(chosen, point[inside], option[inside])
    rest = np.flatnonzero(chosen == none)
    for g in np.unique(group[rest]).tolist():  # inside none of the group's solids (rare): the nearest boundary
        at = rest[group[rest] == g]
        solids = meshes[first[g] : first[g + 1]]
        distance = np.stack([igl.point_mesh_squared_distance(points[at], V, F)[0] for V, F in solids])
        chosen[at] = np.argmin(distance, axis=0)
    return chosen


class CutDelta(NamedTuple):
    """What cuts changed in a model's rest-space bookkeeping since a mark (``XFEMModel.delta``), for
    ``XFEMModel.apply_delta`` on a model equal to it at the mark (a replica in another process keeps the model in
    step this way, ``xfem._background``).

    Attributes:
        subdomains: the ``SubdomainsDelta``.
        pieces: (P,) int64 the current pieces of the elements the cuts met; volume (P,), mass (P, 4, 4),
            load (P, 4), point (P, 3): their integrals and interior points.
        enriched: (E,) int64 pieces whose nodal subdomains were set, and nodal (E, 4) int64 those subdomains.
        unenriched: (U,) int64 pieces that lost their entry (every node of theirs has one subdomain).
        dof_sid, dof_node: the numbering after the cuts.
        cuts: the cuts, as the model logs them (``MeshSolid``, perturb, parallel).
    """

    subdomains: SubdomainsDelta
    pieces: np.ndarray
    volume: np.ndarray
    mass: np.ndarray
    load: np.ndarray
    point: np.ndarray
    enriched: np.ndarray
    nodal: np.ndarray
    unenriched: np.ndarray
    dof_sid: np.ndarray
    dof_node: np.ndarray
    cuts: tuple


class XFEMModel:
    """A cut elastic body: tet mesh, subdomains, DOFs and element pieces (host bookkeeping; build with
    ``xfem_model``, then ``cut`` and ``step``).

    Attributes:
        mesh: the ``TetMesh`` (never modified).
        sub: its ``Subdomains``.
        X: (n, 3) float64 rest positions of the mesh nodes.
        T: (m, 4) int64 tets.
        rho: (m,) float64 density per tet.
        gravity: (3,) float64 gravitational acceleration.
        fixed_nodes: (nb,) int64 mesh nodes whose every DOF is fixed (see ``anchors``).
        anchors: None, or (na,) int64 fixed nodes that hold the others: after cuts, a fixed node's DOF stays fixed
            only while its connected piece (``components``) holds a DOF of an anchor; the pieces cut away from
            every anchor move freely (a character's limb severed from the skeleton's root falls). Set by
            ``xfem_model``.
        dof_node: (n_dofs,) int64 the mesh node of each DOF.
        dof_sid: (n_dofs,) int64 the nodal subdomain of each DOF.
        state: the ``State`` over the DOFs; ``step`` and the cuts keep it in host (numpy) arrays, which the
            compiled step takes at little cost (a device copy per step costs more than a small body's step).
        cuts: the cuts made so far, in order: (the cut solid's ``MeshSolid``, perturb, parallel).

    A model owns threads: its cuts' Boolean thread pool and, unless given shared ones, its ``CompiledSteps`` (with
    the threads compiling the next capacity level's step). ``close()`` ends them; a closed model neither cuts in
    parallel nor steps. A context manager: ``with xfem_model(...) as model: ...`` closes it at the end.
    """

    def __init__(
        self,
        mesh: TetMesh,
        rho: Float[np.ndarray, " m"],
        gravity: Float[np.ndarray, " 3"],
        fixed: Int[np.ndarray, " nb"],
        state: State,
        steps: CompiledSteps | None = None,
    ):
        self.mesh = mesh
        self.sub: Subdomains = subdomains(mesh)
        self.X, self.T = self.sub.X, self.sub.T
        self.rho, self.gravity, self.fixed_nodes = rho, gravity, fixed
        self.anchors: np.ndarray | None = None
        grads, volumes = shape_gradients(mesh.X, mesh.T)
        self._grads = np.asarray(grads)
        # plain FEM closed forms of the whole tets (eq. 7, 8)
        volumes = np.asarray(volumes)
        self._tet_volume = volumes
        self._tet_mass = (rho * volumes / 20)[:, None, None] * (1 + np.eye(4))
        self._tet_load = np.repeat(volumes[:, None] / 4, 4, axis=1)
        self._exact: set[int] = set()  # elements met by a cut: their pieces come from Booleans
        # piece sid -> volume, mass, load, a point inside it
        self._integrals: dict[int, tuple[float, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._enriched: dict[int, np.ndarray] = {}  # piece sid -> (4,) nodal sids, where a node has several
        self._node_meshes: dict[int, tuple] = {}  # nodal sid -> (its solid, V, F): _node_mesh
        self.dof_node = np.arange(len(self.X), dtype=np.int64)
        self.dof_sid = np.arange(len(self.X), dtype=np.int64)
        self._sorted_sids: tuple = (None,)  # (dof_sid it was made for, argsort, sorted ids): _dof_index's cache
        self.state = state
        self.cuts: list[tuple[MeshSolid, float, bool]] = []
        # caches of the current pieces, cleared by a cut
        self._piece_cache: tuple[tuple[np.ndarray, ...], np.ndarray] | None = None  # _piece_table
        self._arrays: tuple | None = None  # _system_arrays
        self._system: FEMSystem | None = None  # system
        self._padded: PaddedSystem | None = None  # the padded system the steps run
        self._level = 0  # the capacity level of the last padded system: the levels never go down
        self._step_options: tuple | None = None  # (h, material, newton_iterations) of the last step
        _, _, _, M, _, _ = self._system_arrays()
        # capacity level 0 is the uncut model's sizes (nodes, elements, mass entries, nonzeros) with headroom
        self._capacities = Capacities((len(self.X), len(self.T), M.nnz, 9 * M.nnz))
        self._owns_steps = steps is None
        self._steps = CompiledSteps() if steps is None else steps
        self._pool: ThreadPoolExecutor | None = None  # the cuts' Booleans, made by the first parallel cut
        self._closed = False

    # ---------------------------------------------------------------------------------------------------
    # the threads it owns

    def __enter__(self) -> XFEMModel:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """End the model's threads: shut its Boolean pool down and close its own ``CompiledSteps`` (waiting for
        the compilations running); shared steps are left to their owner. Idempotent."""
        self._closed = True
        if self._pool is not None:
            self._pool.shutdown(wait=True)
            self._pool = None
        if self._owns_steps:
            self._steps.close()

    @property
    def closed(self) -> bool:
        """Whether ``close`` was called."""
        return self._closed

    def wait_for_compilations(self) -> None:
        """Wait until the step compiling in the background (the next capacity level's, ``step``) is ready: a
        compilation takes seconds of CPU beside the steps (a benchmark waits after its warm-up run)."""
        self._steps.wait()

    def _booleans(self) -> ThreadPoolExecutor:
        if self._closed:
            raise ValueError("model: closed (XFEMModel.close); make a new model to cut")
        if self._pool is None:
            self._pool = ThreadPoolExecutor(BOOLEAN_THREADS, thread_name_prefix="xfem-boolean")
        return self._pool

    # ---------------------------------------------------------------------------------------------------
    # pieces

    def _enrich(self, elements: np.ndarray) -> None:
        """Assign the nodal subdomains of every piece of the given elements at nodes with several (eq. 16); one
        distance query per such node, for all its pieces' points at once."""
        owner, sids = self.sub.element_subdomain_arrays(elements)
        for sid in sids.tolist():
            self._enriched.pop(sid, None)
        several = (self.sub.node_subdomain_counts() > 1)[self.T[owner]]  # (pieces, 4)
        enriched = several.any(axis=1)
        sids, owner, several = sids[enriched], owner[enriched], several[enriched]
        if not len(sids):
            return
        exact = np.isin(owner, np.fromiter(self._exact, np.int64, len(self._exact)))
        points = self.X[self.T[owner]].mean(axis=1)  # a whole tet's centroid is inside it
        if exact.any():
            points[exact] = np.stack([self._integrals[sid][3] for sid in sids[exact].tolist()])
        nodal = self.sub.first_node_subdomains()[self.T[owner]]
        piece, corner = np.nonzero(several)
        options, first, group = self._node_options(self.T[owner[piece], corner])
        chosen = _nearest_subdomains([self._node_mesh(s) for s in options.tolist()], first, group, points[piece])
        nodal[piece, corner] = options[first[group] + chosen]
        self._enriched.update(zip(sids.tolist(), nodal))

    def _node_options(self, nodes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The current nodal subdomains of the distinct nodes among ``nodes``, node after node (int64), where each
        node's start (int64, one more than the distinct nodes), and the distinct node of each of ``nodes``."""
        distinct, group = np.unique(nodes, return_inverse=True)
        lists = [self.sub.node_subdomains(i) for i in distinct.tolist()]
        first = np.concatenate([[0], np.cumsum([len(ids) for ids in lists])]).astype(np.int64)
        return np.fromiter(itertools.chain.from_iterable(lists), np.int64, int(first[-1])), first, group.ravel()

    def _node_mesh(self, sid: int) -> tuple[np.ndarray, np.ndarray]:
        """(V, F): the boundary mesh of nodal subdomain sid's solid, kept until a cut changes the solid (a node's
        subdomains are queried again by every later cut near it)."""
        solid = self.sub.node_solid(sid)
        kept = self._node_meshes.get(sid)
        if kept is None or kept[0] is not solid:
            V, F, _ = solid_mesh(solid)
            kept = self._node_meshes[sid] = (solid, V, F)
        return kept[1:]

    def _integrate(self, elements: np.ndarray) -> int:
        """Exact mass, loads and volume of every piece of the given elements (eq. 13, 14, 21), one batch;
        returns the number of pieces."""
        measured = self._piece_moments(elements)
        if measured is None:
            return 0
        sids, owner, Xe, origin, moments, points = measured
        c, g = linear_shape_coefficients(Xe, origin)
        mass, load, volume = element_piece_integrals(c, g, moments, self.rho[owner])
        for k, sid in enumerate(sids):
            self._integrals[sid] = (float(volume[k]), mass[k], load[k], points[k])
        return len(sids)

    def _piece_moments(self, elements: np.ndarray) -> tuple | None:
        """The pieces of the given elements and their exact moments (eq. 21), one batch: (sids, owner elements,
        their tets' corners (P, 4, 3), the moments' origins (P, 3), ``Moments``, a point inside each (P, 3)), or
        None when the elements have no pieces."""
        V, F, piece, sids, owner, offset = [], [], [], [], [], 0
        for e in elements.tolist():
            for sid in self.sub.element_subdomains(e):
                Vp, Fp, _ = solid_mesh(self.sub.element_solid(sid))
                V.append(Vp)
                F.append(Fp + offset)
                piece.append(np.full(len(Fp), len(sids), np.int64))
                offset += len(Vp)
                sids.append(sid)
                owner.append(e)
        if not sids:
            return None
        owner = np.asarray(owner)
        Xe = self.X[self.T[owner]]
        origin = Xe.mean(axis=1)  # the tets' centroids: the moments stay relative to the piece's size
        V, F, piece = np.concatenate(V), np.concatenate(F), np.concatenate(piece)
        moments = moments_of_pieces(V, F, piece, len(sids), origin)
        return sids, owner, Xe, origin, moments, _interior_points(V, F, piece, len(sids))

    def _pieces(self) -> tuple[np.ndarray, ...]:
        """``piece_arrays`` with the nodal subdomain ids (P, 4) of eq. 16 in place of the DOFs (cached until the
        next cut: the renumbering and the system both read them)."""
        return self._piece_table()[0]

    def piece_ids(self) -> Int[np.ndarray, " P"]:
        """(P,) int64 the element subdomain id of each piece row of ``piece_arrays`` (an uncut tet's is its
        element); read-only."""
        return self._piece_table()[1]

    def _piece_table(self) -> tuple[tuple[np.ndarray, ...], np.ndarray]:
        """``_pieces`` and ``piece_ids``, gathered together and cached until the next cut."""
        if self._piece_cache is None:
            *pieces, ids = self._gather_pieces()
            for array in (*pieces, ids):  # shared by every caller until the next cut
                array.flags.writeable = False
            self._piece_cache = (tuple(pieces), ids)
        return self._piece_cache

    def _gather_pieces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        exact = np.array(sorted(self._exact), np.int64)
        uncut = np.ones(len(self.T), bool)
        uncut[exact] = False
        whole = np.flatnonzero(uncut)  # an uncut tet's piece id is the element
        parts, sids = self.sub.element_subdomain_arrays(exact)
        integrals = [self._integrals[sid] for sid in sids.tolist()]
        element = np.concatenate([whole, parts])
        # a piece's nodal subdomains: each node's first, where the node has one (the initial one of node i has
        # id i), or those eq. 16 chose (``_enrich``)
        nodal = np.concatenate([self.T[whole], self.sub.first_node_subdomains()[self.T[parts]]])
        if self._enriched:
            # the row of each piece id (element subdomain ids are unique: an uncut tet's is its element)
            row = np.full(max(len(self.T), int(sids.max(initial=0)) + 1), -1, np.int64)
            row[whole], row[sids] = np.arange(len(whole)), len(whole) + np.arange(len(sids))
            keys = np.fromiter(self._enriched, np.int64, len(self._enriched))
            values = np.concatenate(list(self._enriched.values())).reshape(-1, 4)
            at = np.where(keys < len(row), row[np.minimum(keys, len(row) - 1)], -1)
            nodal[at[at >= 0]] = values[at >= 0]
        volume = np.concatenate([self._tet_volume[whole], np.array([v[0] for v in integrals], np.float64)])
        mass = np.concatenate([self._tet_mass[whole], np.array([v[1] for v in integrals]).reshape(-1, 4, 4)])
        load = np.concatenate([self._tet_load[whole], np.array([v[2] for v in integrals]).reshape(-1, 4)])
        order = np.argsort(element, kind="stable")
        ids = np.concatenate([whole, sids])
        return element[order], nodal[order], volume[order], mass[order], load[order], ids[order]

    def piece_arrays(
        self,
    ) -> tuple[
        Int[np.ndarray, " P"],
        Int[np.ndarray, "P 4"],
        Float[np.ndarray, " P"],
        Float[np.ndarray, "P 4 4"],
        Float[np.ndarray, "P 4"],
    ]:
        """The element pieces, element by element (an uncut model: one piece per tet, in mesh order).

        Returns:
            element (P,) int64 parent element, dofs (P, 4) int64 DOF indices, volume (P,), mass (P, 4, 4)
            ``rho int_p phi_a phi_b``, load (P, 4) ``int_p phi_a``; all but dofs read-only (the model's own, until
            the next cut).
        """
        element, nodal, volume, mass, load = self._pieces()
        return element, self._dof_index(nodal), volume, mass, load

    def _dof_index(self, sids: np.ndarray) -> np.ndarray:
        """The DOF indices of nodal subdomains (-1 for one without a DOF)."""
        if self._sorted_sids[0] is not self.dof_sid:  # the sort is redone only when the DOFs change
            order = np.argsort(self.dof_sid)
            self._sorted_sids = (self.dof_sid, order, self.dof_sid[order])
        _, order, ordered = self._sorted_sids
        at = np.minimum(np.searchsorted(ordered, sids), len(order) - 1)
        return np.where(ordered[at] == sids, order[at], -1)

    # ---------------------------------------------------------------------------------------------------
    # Algorithm 1

    def cut(self, solid: manifold3d.Manifold | MeshSolid, perturb: float = 0.0, parallel: bool = True) -> CutReport:
        """Cut the body by a closed cut solid (Algorithm 1 lines 1-25): split the subdomains, copy the split
        nodal subdomains' x and v to their pieces (line 7), integrate the touched elements' pieces (eq. 21),
        re-enrich the elements around split nodes (eq. 16) and renumber the DOFs.

        Args:
            solid: the cut solid Gamma^c (``xfem._cuts.cut_solid``, ``plane_cut_solid``), or its ``MeshSolid``.
            perturb: 0, or the size of the gentle perturbation (``apply_cut``).
            parallel: run the Booleans on several threads (``apply_cut``).
        Returns:
            The ``CutReport`` of ``apply_cut``, with this cut's ``CutStats`` and ``dof_source``.
        """
        if not isinstance(solid, MeshSolid):
            check_cut(solid, perturb)
            # as a worker process's replica gets it (``xfem._background``): a Manifold rebuilt from its mesh, so
            # that both give the same subdomains
            solid = solid_mesh(solid)
        built = solid.build()
        check_cut(built, perturb)
        report = apply_cut(self.sub, built, perturb, parallel=parallel, pool=self._booleans() if parallel else None)
        self._piece_cache = None
        self.cuts.append((solid, float(perturb), bool(parallel)))
        touched = report.elements_touched
        if len(touched) == 0:
            return report
        for sid in report.element_children:  # retired pieces
            self._integrals.pop(sid, None)
            self._enriched.pop(sid, None)
        for sid in report.node_children:
            self._node_meshes.pop(sid, None)
        self._exact.update(touched.tolist())
        start = time.perf_counter()
        integrated = self._integrate(touched)
        integration_seconds = time.perf_counter() - start
        start = time.perf_counter()
        # nodes whose subdomain lists changed: their elements' pieces are enriched anew (line 21)
        changed = {self.sub.node_of(s) for s in report.node_children} | set(report.nodes_split.tolist())
        ring = [self.sub.ring_elements[self.sub.ring_offsets[i] : self.sub.ring_offsets[i + 1]] for i in changed]
        self._enrich(np.unique(np.concatenate([touched, *ring])))
        source = self._renumber()
        enrichment_seconds = time.perf_counter() - start
        self._copy_state(source)
        stats = dataclasses.replace(
            report.stats,
            pieces_integrated=integrated,
            integration_seconds=integration_seconds,
            enrichment_seconds=enrichment_seconds,
        )
        return dataclasses.replace(report, stats=stats, dof_source=source)

    def _renumber(self) -> np.ndarray:
        """The DOFs become the live nodal subdomains that a piece reaches, ordered by node, then id (creation
        order). Returns, for each, the DOF of the previous numbering whose x and v it copies: its own, or its
        parent's for a subdomain made by this cut (line 7)."""
        sids = sorted_unique(self._pieces()[1])
        nodes = np.array([s if s < len(self.X) else self.sub.node_of(int(s)) for s in sids], np.int64)
        order = np.lexsort((sids, nodes))
        return self._number(sids[order], nodes[order])

    def _number(self, sids: np.ndarray, nodes: np.ndarray) -> np.ndarray:
        """Take the numbering (sids, nodes); returns the copy map from the previous one (``_renumber``)."""
        source = self._dof_index(sids)
        missing = np.flatnonzero(source < 0)  # made by this cut: up the parents, a generation at a time
        origin = sids[missing]
        while len(missing):
            origin = np.array([self.sub.node_parent(s) for s in origin.tolist()], np.int64)
            source[missing] = found = self._dof_index(origin)
            missing, origin = missing[found < 0], origin[found < 0]
        self.dof_sid, self.dof_node = sids, nodes
        return source

    def _copy_state(self, source: np.ndarray) -> None:
        """The state on the new DOFs (line 7); the caches of the old pieces are dropped."""
        # gathered on the host: a JAX gather would compile anew for every DOF count
        self.state = State(np.asarray(self.state.x)[source], np.asarray(self.state.v)[source])
        self._arrays = self._system = self._padded = None

    def _system_arrays(self):
        """The arguments of ``fem_system`` for the current pieces (cached until the next cut): elements =
        pieces with their parents' shape gradients and volumes |p|, mass assembled from the piece masses,
        gravity loads, the DOFs of the fixed nodes."""
        if self._arrays is None:
            element, dofs, volume, mass, load = self.piece_arrays()
            n = len(self.dof_sid)
            rows = np.broadcast_to(dofs[:, :, None], mass.shape).ravel()
            cols = np.broadcast_to(dofs[:, None, :], mass.shape).ravel()
            M = sp.csr_matrix((mass.ravel(), (rows, cols)), shape=(n, n))
            M = (M + M.T) * 0.5  # summing duplicates in another order leaves M_ij != M_ji in the last bit
            weights = load * self.rho[element][:, None]
            # three bincounts: they sum in order as np.add.at does, in a fifth of its time
            loads = (weights[:, :, None] * self.gravity).reshape(-1, 3)
            force = np.stack([np.bincount(dofs.ravel(), loads[:, k], minlength=n) for k in range(3)], axis=1)
            fixed = np.isin(self.dof_node, self.fixed_nodes)
            if self.anchors is not None:  # the fixed DOFs of pieces that hold an anchor
                _, label = _dof_components(dofs, n)
                anchored = np.zeros(label.max(initial=-1) + 1, bool)
                anchored[label[np.isin(self.dof_node, self.anchors)]] = True
                fixed &= anchored[label]
            self._arrays = (dofs, self._grads[element], volume, M, force, np.flatnonzero(fixed))
        return self._arrays

    def system(self) -> FEMSystem:
        """The ``FEMSystem`` of the current pieces (cached until the next cut), one DOF node per row of
        ``state``; ``step`` runs the same system padded to a capacity level (``xfem._capacity``)."""
        if self._system is None:
            self._system = fem_system(*self._system_arrays())
        return self._system

    def padded_system(self) -> PaddedSystem:
        """The system ``step`` runs: ``system`` padded to the smallest capacity level, not below the last one,
        that holds it (cached until the next cut)."""
        if self._padded is None:
            self._padded = self._capacities.pad(self._system_arrays(), len(self.dof_sid), self._level)
            self._level = self._padded.level
        return self._padded

    def replay(self, cuts: Sequence[tuple[MeshSolid, float, bool]]) -> None:
        """Make the cuts of another model of the same mesh (its ``cuts`` log: mesh solid, perturb, parallel), in
        order, with the same options: the Booleans are deterministic, so this model's subdomains and numbering
        become that model's (a worker's replica, a copy to cut further)."""
        for solid, perturb, parallel in cuts:
            self.cut(solid, perturb, parallel)

    def step(self, h: float | Float[Array, ""], material: Material, newton_iterations: int = 1) -> State:
        """One backward Euler step (eq. 10, Algorithm 1 line 26) of the current system; updates and returns
        ``state``.

        The system is padded to a capacity level (``padded_system``); the step of the next level is compiled in
        the background meanwhile, so that a cut that moves the model there finds it ready.

        Args:
            h: the positive time step.
            material: the ``Material`` (scalar parameters).
            newton_iterations: the Newton iterations (>= 1; 1 is the paper's), all of them run (no tolerance).
        Returns:
            The new ``State``: x and v of shape (n_dofs, 3), host arrays, and the step's ``SolveStats``.
        """
        if int(newton_iterations) != newton_iterations or newton_iterations < 1:
            raise ValueError(f"newton_iterations: expected an int >= 1, got {newton_iterations!r}")
        padded = self.padded_system()
        options = (h, material, int(newton_iterations))
        step = self._steps.compiled(self._capacities, padded, padded.level, *options, background=False)
        # compiled(background=False) returns the step (built here if its background build failed)
        stepped = step(padded.system, padded_state(self.state, padded.n, padded.system.n), h, material)  # pyright: ignore[reportOptionalCall]
        # host views of the result, sliced (a JAX slice would compile anew for every DOF count)
        self.state = State(
            np.asarray(stepped.x)[: padded.n],
            np.asarray(stepped.v)[: padded.n],
            jax.tree.map(np.asarray, stepped.stats),
        )
        self._step_options = options
        self._steps.compiled(self._capacities, padded, padded.level + 1, *options, background=True)
        return self.state

    # ---------------------------------------------------------------------------------------------------
    # replication: another model of the same mesh kept equal to this one (``xfem._background``)

    def mark(self) -> tuple:
        """A mark of the bookkeeping as it is now, for ``delta``."""
        return self.sub.mark(), dict(self._enriched), len(self.cuts)

    def delta(self, since: tuple) -> CutDelta:
        """What the cuts made since the mark ``since`` (``mark``) changed in the rest-space bookkeeping."""
        sub_mark, enriched, cuts = since
        changes = self.sub.delta(sub_mark)
        touched = list(changes.elements.live)  # the elements met: each lost, split or reshaped a piece
        pieces = [sid for e in touched for sid in self.sub.element_subdomains(e)]
        integrals = [self._integrals[sid] for sid in pieces]
        volume = np.array([v[0] for v in integrals], np.float64)
        mass, load, point = (
            np.stack([v[k] for v in integrals]) if integrals else np.zeros((0, *shape))
            for k, shape in ((1, (4, 4)), (2, (4,)), (3, (3,)))
        )
        set_enriched = [sid for sid, value in self._enriched.items() if enriched.get(sid) is not value]
        return CutDelta(
            changes,
            np.asarray(pieces, np.int64),
            volume,
            mass,
            load,
            point,
            np.asarray(set_enriched, np.int64),
            np.stack([self._enriched[sid] for sid in set_enriched]) if set_enriched else np.zeros((0, 4), np.int64),
            np.asarray([sid for sid in enriched if sid not in self._enriched], np.int64),
            self.dof_sid,
            self.dof_node,
            tuple(self.cuts[cuts:]),
        )

    def apply_delta(self, delta: CutDelta, padded: PaddedSystem | None = None) -> Int[np.ndarray, " n_dofs"]:
        """Make the cuts of ``delta`` (``delta`` of a model of the same mesh, equal to this one at its mark) take
        effect here, as ``cut`` would: the bookkeeping, the numbering, the state copied to it (line 7).

        Args:
            delta: the ``CutDelta``.
            padded: the new system padded (``padded_system`` of the model the delta is from), or None: built at
                the next step.
        Returns:
            The copy map of the state (``CutReport.dof_source`` over all the delta's cuts).
        Raises:
            ValueError: the delta is not from a model equal to this one at its mark (nothing is changed).
        """
        if not isinstance(delta, CutDelta):
            raise ValueError(f"delta: expected a CutDelta, got {type(delta).__name__}")
        self.sub.apply_delta(delta.subdomains)
        self._piece_cache = None
        for sid in delta.subdomains.nodes.retired.tolist():
            self._node_meshes.pop(sid, None)
        for sid in delta.subdomains.elements.retired.tolist():
            self._integrals.pop(sid, None)
            self._enriched.pop(sid, None)
        self._exact.update(delta.subdomains.elements.live)
        for k, sid in enumerate(delta.pieces.tolist()):
            self._integrals[sid] = (float(delta.volume[k]), delta.mass[k], delta.load[k], delta.point[k])
        for sid in delta.unenriched.tolist():
            self._enriched.pop(sid, None)
        for k, sid in enumerate(delta.enriched.tolist()):
            self._enriched[sid] = delta.nodal[k].copy()  # _enrich writes into its entries
        self.cuts.extend(delta.cuts)
        source = self._number(np.asarray(delta.dof_sid, np.int64), np.asarray(delta.dof_node, np.int64))
        self._copy_state(source)
        if padded is not None:
            self._arrays, self._padded, self._level = padded.arrays, padded, max(self._level, padded.level)
        return source

    def prepare_step(self, arrays: tuple, n: int, system: FEMSystem | None = None, level: int = 0) -> PaddedSystem:
        """A system for ``apply_delta``, made beside the steps: padded to this model's capacity levels (``system``,
        already padded to ``level``, or ``arrays`` over n DOFs padded here) with its step compiled for the options
        of the last step. Reads only the capacity levels and the last step's options (any thread)."""
        if system is None:
            result = self._capacities.pad(arrays, n, max(level, self._level))
        else:
            result = PaddedSystem(system, level, arrays, n)
        options = self._step_options
        if options is not None:
            self._steps.compiled(self._capacities, result, result.level, *options, background=False)
        return result

    # ---------------------------------------------------------------------------------------------------
    # queries

    def _field(self, values: np.ndarray, points, elements) -> np.ndarray:
        """sum_i sum_s values_i^s phi_i(X) psi_i^s(X) (eq. 18) at points X in the given elements."""
        weights, dofs = self.field_dofs(points, elements)
        return np.einsum("ka,kad->kd", weights, values[dofs])

    def field_dofs(
        self,
        points: Float[npt.ArrayLike, "k 3"],
        elements: Int[npt.ArrayLike, " k"],
        indicators: Float[npt.ArrayLike, "k 3"] | None = None,
    ) -> tuple[Float[np.ndarray, "k 4"], Int[np.ndarray, "k 4"]]:
        """The linear map of eq. 18 at material points: ``x(X) = sum_a weights[:, a] x[dofs[:, a]]`` for any
        DOF values x (positions, displacements, velocities).

        Args:
            points: (k, 3) material points (rest positions; outside their element the weights extrapolate it).
            elements: (k,) int the element of each point.
            indicators: None, or (k, 3) points at which eq. 16 picks each point's nodal subdomains instead of at
                the point itself (e.g. the centroid of the triangle a surface point belongs to).
        Returns:
            weights (k, 4) float64, the shape functions phi_a(X) of the element's nodes, and dofs (k, 4) int64.
        Raises:
            ValueError: bad shapes, indices out of range, a point whose nodal subdomain has no DOF.
        """
        points = np.asarray(points, np.float64)
        elements = np.asarray(elements)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise ValueError(f"points: expected finite points of shape (k, 3), got {points.shape}")
        if (
            elements.shape != (len(points),)
            or not np.issubdtype(elements.dtype, np.integer)
            or (elements.size and (elements.min() < 0 or elements.max() >= len(self.T)))
        ):
            raise ValueError(f"elements: expected ({len(points)},) element indices in [0, {len(self.T)})")
        if indicators is None:
            indicators = points
        else:
            indicators = np.asarray(indicators, np.float64)
            if indicators.shape != points.shape or not np.all(np.isfinite(indicators)):
                raise ValueError(f"indicators: expected finite points of shape {points.shape}, got {indicators.shape}")
        c, _ = linear_shape_coefficients(self.X[self.T[elements]], points)  # phi_a(X): barycentric coordinates
        dofs = np.empty((len(points), 4), np.int64)
        counts, firsts = self.sub.node_subdomain_counts(), self.sub.first_node_subdomains()
        for a in range(4):
            nodes = self.T[elements, a]
            chosen = firsts[nodes]
            at = np.flatnonzero(counts[nodes] > 1)
            if len(at):
                options, first, group = self._node_options(nodes[at])
                nearest = _nearest_subdomains(
                    [self._node_mesh(s) for s in options.tolist()], first, group, indicators[at]
                )
                chosen[at] = options[first[group] + nearest]
            dofs[:, a] = self._dof_index(chosen)
            if np.any(dofs[:, a] < 0):
                i = int(nodes[np.argmax(dofs[:, a] < 0)])
                raise ValueError(f"points: a point's nodal subdomain of node {i} has no material (no DOF)")
        return c, dofs

    def displacement_at(
        self, points: Float[npt.ArrayLike, "k 3"], elements: Int[npt.ArrayLike, " k"]
    ) -> Float[np.ndarray, "k 3"]:
        """u(X) = sum_i sum_s u_i^s phi_i(X) psi_i^s(X) (eq. 18), u_i^s = x_i^s - X_i.

        Args:
            points: (k, 3) material points.
            elements: (k,) int the element containing each point.
        Returns:
            (k, 3) displacements.
        """
        return self._field(np.asarray(self.state.x) - self.X[self.dof_node], points, elements)

    def velocity_at(
        self, points: Float[npt.ArrayLike, "k 3"], elements: Int[npt.ArrayLike, " k"]
    ) -> Float[np.ndarray, "k 3"]:
        """The velocity field of eq. 18 (coefficients v_i^s) at points (k, 3) in elements (k,); (k, 3)."""
        return self._field(np.asarray(self.state.v), points, elements)

    def components(self) -> tuple[int, Int[np.ndarray, " n_dofs"]]:
        """The connected pieces of the body: components of the graph of element pieces sharing a DOF.

        Returns:
            count, and (n_dofs,) int the component of each DOF.
        """
        return _dof_components(self._system_arrays()[0], len(self.dof_sid))

    def pieces(self) -> int:
        """The number of connected pieces of the body (``components``)."""
        return self.components()[0]


def _dof_components(dofs: np.ndarray, n: int) -> tuple[int, np.ndarray]:
    """The connected components of n DOFs joined by the element pieces ``dofs`` (P, 4)."""
    rows = np.repeat(dofs[:, :1], 3, axis=1).ravel()
    graph = sp.csr_matrix((np.ones(len(rows)), (rows, dofs[:, 1:].ravel())), shape=(n, n))
    return connected_components(graph, directed=False)


def xfem_model(
    mesh: TetMesh,
    density: float | Float[npt.ArrayLike, " m"],
    gravity: Float[npt.ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    fixed: Int[npt.ArrayLike, " nb"] = (),
    state: State | None = None,
    anchors: Int[npt.ArrayLike, " na"] | None = None,
    steps: CompiledSteps | None = None,
) -> XFEMModel:
    """An uncut XFEM model: one DOF per node (its 1-ring), one piece per tet. It owns threads: close it
    (``XFEMModel.close``, or ``with xfem_model(...) as model:``) when done.

    Args:
        mesh: the ``TetMesh``.
        density: scalar or (m,) positive mass density per tet.
        gravity: (3,) gravitational acceleration (body force density ``density * gravity``).
        fixed: (nb,) int mesh nodes held in place (all their DOFs, also after cuts, unless ``anchors``); () for none.
        state: the initial ``State`` over the n nodes (float64); None: at rest in the rest positions.
        anchors: None (every fixed DOF stays fixed), or (na,) int nodes among ``fixed``: after cuts, only the pieces
            holding a DOF of an anchor keep their fixed DOFs fixed (``XFEMModel.anchors``).
        steps: None (the model compiles and owns its steps), or a ``CompiledSteps`` shared with other models of
            this mesh (their steps then compile once; its owner closes it).
    Returns:
        The ``XFEMModel``.
    """
    if steps is not None and not isinstance(steps, CompiledSteps):
        raise ValueError(f"steps: expected None or an xfem.CompiledSteps, got {type(steps).__name__}")
    model = XFEMModel(*model_arguments(mesh, density, gravity, fixed, state), steps=steps)
    if anchors is not None:
        anchors = np.asarray(anchors).reshape(-1)
        if (
            anchors.size == 0
            or not np.issubdtype(anchors.dtype, np.integer)
            or not np.all(np.isin(anchors, model.fixed_nodes))
        ):
            raise ValueError("anchors: expected None or a non-empty set of int node indices among fixed")
        model.anchors = np.unique(anchors).astype(np.int64)
    return model


def model_arguments(mesh, density, gravity, fixed, state) -> tuple:
    """``xfem_model``'s arguments checked (ValueError naming the bad one) and converted: (mesh, rho (m,), gravity
    (3,), fixed (nb,) int64, state), the arguments of ``XFEMModel`` and of the models built like it."""
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh: expected a TetMesh, got {type(mesh).__name__}")
    m, n = mesh.T.shape[0], mesh.X.shape[0]
    rho = np.broadcast_to(check_positive("density", density, ((), (m,))), (m,)).copy()
    gravity = check_real("gravity", gravity, (3,), "a finite acceleration")
    fixed = np.asarray(fixed).reshape(-1)
    if fixed.size and (
        not np.issubdtype(fixed.dtype, np.integer)
        or fixed.min() < 0
        or fixed.max() >= n
        or len(np.unique(fixed)) != len(fixed)
    ):
        raise ValueError(f"fixed: expected distinct int node indices in [0, {n})")
    fixed = fixed.astype(np.int64)
    if state is None:
        X = jnp.asarray(mesh.X, jnp.float64)
        state = State(X, jnp.zeros_like(X))
    elif (
        not isinstance(state, State)
        or jnp.shape(state.x) != (n, 3)
        or jnp.shape(state.v) != (n, 3)
        or jnp.result_type(state.x) != jnp.float64
        or jnp.result_type(state.v) != jnp.float64
    ):
        raise ValueError(f"state: expected a float64 State with x, v of shape ({n}, 3)")
    return mesh, rho, gravity, fixed, state
