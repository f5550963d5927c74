"""The cutting simulation of the XFEM paper: generalized enrichments (sec. 4.2, eq. 15-18), exact integration of
the enriched mass and forces over element subdomains (sec. 3.5 and 4.3, eq. 13, 14, 19-21) and the per-step
Algorithm 1 (sec. 4.4): cut the subdomains (lines 1-19, ``xfem._subdomains.apply_cut``), duplicate DOFs (line
7), recompute the touched elements (lines 20-25) and step the FEM core (line 26, ``backward_euler_step``).

DOFs. Every current nodal subdomain Omega^{i,s} carries one DOF, the coefficient u_i^s of eq. 18 (here the
position ``X_i + u_i^s`` and the velocity). When a cut splits Omega^{i,s}, each piece gets a copy of its x and
v (line 7): the pieces' indicators sum to the parent's on the material, so eq. 18 keeps its value at every
material point. DOFs are numbered node by node, a node's subdomains by id (creation order); an uncut model has
DOF i = node i. A nodal subdomain that no element piece reaches (possible only through dropped rounding-size
slivers) gets no DOF. A thin sliver that is kept (e.g. left by a perturbed cut next to a node layer, 1e-7
thick) gives its DOF a mass near rounding (~1e-19, entries of either sign ~1e-17): the step's matrix
``M + h^2 K`` stays positive definite through the sliver's stiffness, and the runs stay stable
(tests/xfem/test_robustness.py), but such a DOF's velocity means little.

Element pieces. Every current element subdomain p of element e (a "piece") is an element of the FEM core: its
4 DOFs, the shape gradients of e (the enriched basis is phi_i on p), the weight |p| (the elastic energy is
psi(F) |p|, sec. 4.3), and its exact 4 x 4 mass ``rho int_p phi_a phi_b`` and loads ``int_p phi_a`` (eq. 13,
14 by eq. 21, ``xfem._integration``). Elements no cut has met keep the closed forms of the whole tet (vectorized,
no Booleans): ``rho V (1 + delta_ab) / 20`` and ``V / 4``, the plain FEM values.

Enrichment (eq. 16). The DOF of local node a of piece p is that of the subdomain s of node i = T[e, a] whose
indicator psi_i^s is 1 on p: the one with the smallest distance to a point X_p strictly inside p. The distance
to a solid (not to its boundary: eq. 16 compares ``dist(X, Omega^{i,s})``) is 0 where the winding number of its
boundary mesh exceeds 1/2 (libigl ``winding_number``) and the unsigned distance to the boundary mesh (libigl
``point_mesh_squared_distance``) elsewhere. X_p is the centroid of p's largest boundary triangle moved inward,
along the triangle's normal, by 1e-6 times the square root of its area: the point lies inside p (and so inside
exactly one of node i's subdomains, which are disjoint and at least the cut's thickness apart, eq. 17) unless p
is thinner than that offset there. A node with a single subdomain needs no query.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
import weakref
from collections import deque
from concurrent.futures import Future, ThreadPoolExecutor, wait
from typing import NamedTuple

import igl
import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from jaxcga._support import to_device, to_devices
from xfem._assembly import CapacityError
from xfem._backward_euler import FEMSystem, State, SystemCapacity, compiled_step, fem_system
from xfem._cut_process import CutProcess, CutProcessError, pack_meshes, reserve_worker_core, unpack_meshes
from xfem._integration import element_piece_integrals, linear_shape_coefficients, moments_of_pieces
from xfem._linear_tet import shape_gradients
from xfem._material import Material
from xfem._subdomains import CutReport, MeshSolid, Subdomains, apply_cut, check_cut, solid_mesh, subdomains
from xfem._tetmesh import TetMesh

_INWARD = 1e-6  # inward offset of a piece's query point, relative to the square root of its triangle's area
_HEADROOM = 1.25  # capacity level 0 over the uncut model's sizes
_GROWTH = 1.5  # capacity growth per level
# the smallest capacities (nodes, elements, mass entries, nonzeros): a small model's first cuts stay in level 0,
# and its padded step costs little (a level holds ~1.3-2x its system: the per-element Hessians' cost grows with
# the padded elements, 4.8 ms for 512 of them against 1.6 ms for 161)
_FLOOR = (128, 128, 1024, 9 * 1024)
# the cut worker process builds and sends a new padded system up to this size (``_padded_bytes_at_least``); a
# larger one is built only by the model's worker thread, from the system arrays. Since messages carry arrays out
# of band (``xfem._cut_process``: no copy to unpickle, none to put on the device), sending costs the model little
# more than the pipe; building took 180-360 ms of the worker thread's CPU beside the steps (accordion's system is
# 59 MB). Slowest cut-window frame over the average, one scene per process, alternated: accordion 1.72, 2.07,
# 1.95 sent, 2.44, 2.09, 2.31 built; thin 1.26, 1.28 sent, 1.32, 1.49 built. The limit keeps a huge model's
# system (and its copy in the worker process) out of the pipe.
_SENT_SYSTEM_BYTES = 256 << 20


class _Compilation:
    """A step compiled (or being compiled) for one capacity and set of options."""

    def __init__(self):
        self.step = None
        self.thread: threading.Thread | None = None  # the background thread building it, if any
        self.ready = threading.Event()  # set when a build has ended (step None: it failed)

    def build(self, arrays, capacity: SystemCapacity, h, material: Material, newton_iterations: int,
              system: FEMSystem | None = None):
        """Compile the step of ``system``, already padded to ``capacity``, or of the system ``arrays``
        (``XFEMModel._system_arrays``) padded here."""
        try:
            if system is None:
                try:
                    system = fem_system(*arrays, capacity=capacity)
                except CapacityError:  # too small for this system's nonzeros: the model moves to a larger level
                    return
            zeros = to_device(np.zeros((capacity.nodes, 3)))  # only the state's shape matters
            self.step = compiled_step(system, State(zeros, zeros), h, material, newton_iterations)
        finally:
            self.ready.set()


class _Live(NamedTuple):
    """The system the steps run: padded to capacity ``level``, made from ``arrays`` (``_system_arrays``) over n
    DOFs."""

    system: FEMSystem
    level: int
    arrays: tuple
    n: int


class _StagedCut(NamedTuple):
    """A prepared cut waiting to take effect (``XFEMModel.commit_cuts``): the new DOF numbering, the row of the
    old numbering each new DOF copies its x and v from (Algorithm 1 line 7), and the new live system."""

    dof_sid: np.ndarray
    dof_node: np.ndarray
    source: np.ndarray
    live: _Live


class _Turns:
    """The steps and the pieces of the cut worker thread's GIL-bound work (pickling a request, unpickling a reply,
    applying it, putting the new system on the device: 0.05-0.5 ms each on sticks) take turns instead of sharing
    the GIL, whose hand-overs cost a step more than the work itself. Where ``paced`` (short steps,
    ``_SHORT_STEP_S``), a piece waits for the end of a step after the previous piece, so that a step waits for one
    piece at most (on sticks, the pieces of a reply in a row made their frame 1.5-2.5x the average; paced, frames
    with a piece average 1.1x, and the slowest frame while cutting fell from a median of 2.04 to 1.88-1.90 over 20
    runs); unless the model's thread waits for the worker (``hurry``: a commit, a query) or nobody steps for
    ``_PATIENCE`` seconds."""

    def __init__(self):
        self.paced = False
        self._lock = threading.Lock()
        self._stepped = threading.Condition()
        self._steps = 0  # steps ended
        self._steps_at_piece = -1  # steps ended when the last piece ended
        self._hurried = 0

    @contextlib.contextmanager
    def step(self):
        with self._lock:
            yield
        with self._stepped:
            self._steps += 1
            self._stepped.notify_all()

    @contextlib.contextmanager
    def piece(self):
        if self.paced:
            with self._stepped:
                self._stepped.wait_for(lambda: self._steps > self._steps_at_piece or self._hurried, _PATIENCE)
        with self._lock:
            yield
        with self._stepped:
            self._steps_at_piece = self._steps

    @contextlib.contextmanager
    def hurry(self):
        """The model's thread waits for the worker thread: its pieces go without waiting for steps."""
        with self._stepped:
            self._hurried += 1
            self._stepped.notify_all()
        try:
            yield
        finally:
            with self._stepped:
                self._hurried -= 1


# a worker thread's piece waits at most this long for a step (a model that is not stepping)
_PATIENCE = 0.05


# While cuts are pending, the model's worker thread wakes to read each worker process's reply, to build a large
# system from it and to compile new capacity levels' steps (its other pieces take turns with the steps, ``_Turns``);
# the steps' Python parts (dispatch, the host callbacks, the small systems' CHOLMOD call) would wait for it up to the
# switch interval each time (5 ms by default, 3x a sticks frame). When the cut ran in that thread, on sticks (latency
# 25) the slowest cut-window frame was 2.4x the average frame at 10 us, 4.2x at 0.1 and 1 ms, 4.8x at 5 ms.
_SWITCH_INTERVAL = 1e-5
_switching = {"models": 0, "saved": None}
_SWITCHING_LOCK = threading.Lock()


# A model whose steps take less than this keeps the process's threads off the cut worker's core while its background
# cuts are pending (``reserve_worker_core``), and paces the worker thread's pieces one per step (``_Turns``): a
# thread that waits behind the worker for a scheduler tick (4 ms at Linux's usual 250 Hz), or a reply's pieces in
# a row (~1 ms on sticks), make such a frame 1.5x or more. Longer steps (thin's 0.1 s, accordion's 0.3 s) use both
# cores (kept off one, thin's slowest cut-window frames were 1.8-2.6x the average, against 1.2-1.6x), and pacing
# would only delay their cuts: a piece is a small part of their frame.
_SHORT_STEP_S = 0.01


def _cutting_in_background(started: bool, reserve_core: bool = False) -> None:
    """Count the models with pending background cuts; the first lowers the interpreter's switch interval, the
    last restores it. ``reserve_core``: the model keeps the worker's core free meanwhile (``_SHORT_STEP_S``), the
    same at its start and its end."""
    if reserve_core:
        reserve_worker_core(started)
    with _SWITCHING_LOCK:
        if started:
            if _switching["models"] == 0 and sys.getswitchinterval() > _SWITCH_INTERVAL:
                _switching["saved"] = sys.getswitchinterval()
                sys.setswitchinterval(_SWITCH_INTERVAL)
            _switching["models"] += 1
        else:
            _switching["models"] -= 1
            if _switching["models"] == 0 and _switching["saved"] is not None:
                sys.setswitchinterval(_switching["saved"])
                _switching["saved"] = None


# compiled steps by (capacity, newton iterations, shapes of the material's parameters), for every model in the process
_COMPILED: dict[tuple, _Compilation] = {}
_COMPILED_LOCK = threading.Lock()


def wait_for_compilations() -> None:
    """Wait until every step compiling in a background thread (the next capacity level's, ``XFEMModel.step``)
    is ready. A compilation takes seconds of CPU beside the steps; a benchmark calls this after its warm-up run
    so that the warm-up's last compilation does not run into the timed frames."""
    with _COMPILED_LOCK:
        threads = [entry.thread for entry in _COMPILED.values() if entry.thread is not None]
    for thread in threads:
        thread.join()


def _padded_state(state: State, n: int, nodes: int) -> State:
    """The state with zero rows for the padded DOF nodes, in host arrays: a compiled step takes numpy arrays for
    ~6 us each, a device_put costs ~80-170 us (and a JAX pad would compile anew for every size)."""
    x, v = np.zeros((nodes, 3)), np.zeros((nodes, 3))
    x[:n], v[:n] = np.asarray(state.x), np.asarray(state.v)
    return State(x, v)


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


def _nearest_subdomain(meshes: list[tuple[np.ndarray, ...]], points: np.ndarray) -> np.ndarray:
    """(k,) for each point, the index of the solid at the smallest distance (0 inside; the first such solid),
    eq. 16. meshes: (V, F, lower, upper) of each solid, its mesh and bounding box. A point inside a solid needs
    no distance: the winding numbers are taken first, and only for the points in the solid's bounding box (all
    boxes tested at once); the distances only for the points inside none of the solids."""
    chosen = np.full(len(points), -1, np.int64)
    lower, upper = np.stack([m[2] for m in meshes]), np.stack([m[3] for m in meshes])
    boxed = np.all((points[None] >= lower[:, None]) & (points[None] <= upper[:, None]), axis=2)  # (solids, points)
    for s in np.flatnonzero(boxed.any(axis=1)).tolist():
        at = np.flatnonzero(boxed[s] & (chosen < 0))
        if len(at):
            V, F = meshes[s][:2]
            chosen[at[igl.winding_number(V, F, points[at]) > 0.5]] = s
    rest = np.flatnonzero(chosen < 0)
    if len(rest):
        distance = np.stack([igl.point_mesh_squared_distance(points[rest], V, F)[0] for V, F, _, _ in meshes])
        chosen[rest] = np.argmin(distance, axis=0)
    return chosen


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
        fixed_nodes: (nb,) int64 mesh nodes whose every DOF is fixed.
        dof_node: (n_dofs,) int64 the mesh node of each DOF.
        dof_sid: (n_dofs,) int64 the nodal subdomain of each DOF.
        state: the ``State`` over the DOFs; ``step`` and the cuts keep it in host (numpy) arrays, which cost
            nothing to pass to the compiled step (a device copy per step cost more than a small body's step).

    Cuts in the background (``cut_async``). A cut's work (Booleans, integrals, enrichment, the new system, its
    compiled step) depends on the rest geometry and the earlier cuts only, never on the state, so it can run
    while the model steps its current system; ``commit_cuts`` then makes it take effect: the DOFs are renumbered,
    their x and v copied (Algorithm 1 line 7) from the state at that moment, and the next step runs the new
    system. The result equals that of ``cut`` called at the moment of the commit (to the rounding of manifold3d's
    Booleans, which the worker runs one at a time, leaving the other core to the steps). The work runs in a
    worker process (``xfem._cut_process``: manifold3d and libigl hold the GIL through each call) that keeps a
    replica of this bookkeeping and sends back what each cut changed; the model's worker thread sends it the next
    pending cut, then applies the reply, in pieces that take turns with the steps (``_Turns``), and compiles the step
    of a new capacity level. The process runs on one core at the lowest priority (``xfem._cut_process``). While a
    model whose steps take under 10 ms has cuts pending, the process's threads stay off that core and the worker
    thread's pieces come one per step (``_SHORT_STEP_S``): with ~1.5 ms steps, a wait behind the worker process
    for a scheduler tick, or a reply's pieces in a row, would be a frame of 2-4x the average. It starts
    with the first ``cut_async`` (or ``start_cut_worker``), replaying the cuts made before; from then on ``cut``
    goes through it too, and it ends with the model. Pending cuts run one after the other, in order; a query
    (``piece_arrays``, ``system``, ``displacement_at``, ...) or ``cut`` first waits for them and commits them
    (``components`` and ``pieces`` answer for the committed cuts). A failed cut (or a worker that died) raises at
    its commit; the next cut starts a new worker.
    """

    def __init__(self, mesh: TetMesh, rho: np.ndarray, gravity: np.ndarray, fixed: np.ndarray, state: State):
        self.mesh = mesh
        self.sub: Subdomains = subdomains(mesh)
        self.X, self.T = self.sub.X, self.sub.T
        self.rho, self.gravity, self.fixed_nodes = rho, gravity, fixed
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
        self._node_meshes: dict[int, tuple] = {}  # nodal sid -> (its solid, V, F, lower, upper): _node_mesh
        self.dof_node = np.arange(len(self.X), dtype=np.int64)
        self.dof_sid = np.arange(len(self.X), dtype=np.int64)
        # the numbering of the rest-space bookkeeping below: ahead of dof_sid while cuts are pending
        self._staged_sid, self._staged_node = self.dof_sid, self.dof_node
        self._sorted_sids: tuple = (None,)  # (_staged_sid it was made for, argsort, sorted ids): _dof_index's cache
        self.state = state
        self._system: FEMSystem | None = None
        self._arrays: tuple | None = None  # of the staged numbering
        self._padded: FEMSystem | None = None
        self._level = 0
        self._live: _Live | None = None  # the committed system that step runs
        self._pending: deque[Future] = deque()  # cut_async's cuts, in order
        self._staged: deque[_StagedCut] = deque()  # prepared by the worker, in order, not yet committed
        self._worker: ThreadPoolExecutor | None = None
        self._turns = _Turns()  # the steps and the worker thread's GIL-bound pieces
        # the cut worker process (xfem._cut_process) and the cuts made so far, which it replays when it starts:
        # (the cut solid's mesh, perturb, parallel)
        self._process: CutProcess | None = None
        self._process_closer: weakref.finalize | None = None
        self._remote = False  # set by the first cut_async: every later cut goes through the worker process
        self._failed = False  # a worker cut failed: the ones queued after it are dropped until commit_cuts raises
        self._unsent: deque[tuple] = deque()  # the pending cuts' requests not yet sent to the worker process
        self._cut_log: list[tuple[MeshSolid, float, bool]] = []
        # a replica in the worker process: the largest padded system it builds and sends (``_SENT_SYSTEM_BYTES``)
        self._sent_system_bytes: int | None = None
        self._committed: weakref.WeakSet[Future] = weakref.WeakSet()
        self._step_options: tuple | None = None  # (h, material, newton_iterations) of the last step
        self._last_step_seconds = float("inf")  # wall-clock time of the last step
        self._end_background = lambda: None  # ends the pending cuts' settings (``_start_background``)
        _, _, _, M, _, _ = self._system_arrays()
        # capacity level 0 is _HEADROOM times these (nodes, elements, mass entries, nonzeros), at least _FLOOR
        self._base = (len(self.X), len(self.T), M.nnz, 9 * M.nnz)

    # ---------------------------------------------------------------------------------------------------
    # pieces

    def _piece_nodal_sids(self, e: int, sid: int) -> np.ndarray:
        """(4,) the nodal subdomains whose indicators are 1 on piece sid of element e (eq. 16)."""
        if sid in self._enriched:
            return self._enriched[sid]
        return np.array([self.sub.node_subdomains(int(i))[0] for i in self.T[e]], np.int64)

    def _enrich(self, elements: np.ndarray) -> None:
        """Assign the nodal subdomains of every piece of the given elements at nodes with several (eq. 16); one
        distance query per such node and subdomain, for all its pieces' points at once."""
        queries: dict[int, list[tuple[int, int, np.ndarray]]] = {}  # node -> (piece sid, local node, point)
        for e in elements.tolist():
            several = [a for a in range(4) if len(self.sub.node_subdomains(int(self.T[e, a]))) > 1]
            for sid in self.sub.element_subdomains(e):
                self._enriched.pop(sid, None)
                if not several:
                    continue
                if e in self._exact:
                    point = self._integrals[sid][3]
                else:  # the whole tet: its centroid is inside
                    point = self.X[self.T[e]].mean(axis=0)
                self._enriched[sid] = np.array([self.sub.node_subdomains(int(i))[0] for i in self.T[e]], np.int64)
                for a in several:
                    queries.setdefault(int(self.T[e, a]), []).append((sid, a, point))
        for i, rows in queries.items():
            options = self.sub.node_subdomains(i)
            meshes = [self._node_mesh(s) for s in options]
            chosen = _nearest_subdomain(meshes, np.stack([point for _, _, point in rows]))
            for (sid, a, _), k in zip(rows, chosen.tolist()):
                self._enriched[sid][a] = options[k]

    def _node_mesh(self, sid: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(V, F, lower, upper): the mesh and bounding box of nodal subdomain sid's solid, kept until a cut
        changes the solid (a node's subdomains are queried again by every later cut near it)."""
        solid = self.sub.node_solid(sid)
        kept = self._node_meshes.get(sid)
        if kept is None or kept[0] is not solid:
            V, F, _ = solid_mesh(solid)
            kept = self._node_meshes[sid] = (solid, V, F, V.min(axis=0), V.max(axis=0))
        return kept[1:]

    def _integrate(self, elements: np.ndarray) -> int:
        """Exact mass, loads and volume of every piece of the given elements (eq. 13, 14, 21), one batch;
        returns the number of pieces."""
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
            return 0
        owner = np.asarray(owner)
        Xe = self.X[self.T[owner]]
        origin = Xe.mean(axis=1)  # the tets' centroids: the moments stay relative to the piece's size
        V, F, piece = np.concatenate(V), np.concatenate(F), np.concatenate(piece)
        moments = moments_of_pieces(V, F, piece, len(sids), origin)
        c, g = linear_shape_coefficients(Xe, origin)
        mass, load, volume = element_piece_integrals(c, g, moments, self.rho[owner])
        points = _interior_points(V, F, piece, len(sids))
        for k, sid in enumerate(sids):
            self._integrals[sid] = (float(volume[k]), mass[k], load[k], points[k])
        return len(sids)

    def _pieces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``piece_arrays`` with the nodal subdomain ids (P, 4) of eq. 16 in place of the DOFs."""
        uncut = np.ones(len(self.T), bool)
        uncut[list(self._exact)] = False
        element = [np.flatnonzero(uncut)]
        nodal = [self.T[element[0]]]  # the initial nodal subdomain of node i has id i
        volume, mass, load = [self._tet_volume[uncut]], [self._tet_mass[uncut]], [self._tet_load[uncut]]
        # an uncut tet's piece id is the element
        enriched = [sid for sid in self._enriched if sid < len(self.T) and uncut[sid]]
        if enriched:
            nodal[0][np.searchsorted(element[0], enriched)] = np.stack([self._enriched[sid] for sid in enriched])
        for e in sorted(self._exact):
            for sid in self.sub.element_subdomains(e):
                vol, ms, ld, _ = self._integrals[sid]
                element.append(np.array([e]))
                nodal.append(self._piece_nodal_sids(e, sid)[None])
                volume.append(np.array([vol]))
                mass.append(ms[None])
                load.append(ld[None])
        element = np.concatenate(element)
        order = np.argsort(element, kind="stable")
        return (element[order], np.concatenate(nodal)[order], np.concatenate(volume)[order],
                np.concatenate(mass)[order], np.concatenate(load)[order])

    def _piece_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``piece_arrays`` in the staged numbering (no wait for pending cuts)."""
        element, nodal, volume, mass, load = self._pieces()
        return element, self._dof_index(nodal), volume, mass, load

    def piece_arrays(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """The element pieces, element by element (an uncut model: one piece per tet, in mesh order).

        Returns:
            element (P,) int64 parent element, dofs (P, 4) int64 DOF indices, volume (P,), mass (P, 4, 4)
            ``rho int_p phi_a phi_b``, load (P, 4) ``int_p phi_a``.
        """
        self.commit_cuts()
        return self._piece_arrays()

    def _dof_index(self, sids: np.ndarray) -> np.ndarray:
        """The DOF indices of nodal subdomains (-1 for one without a DOF) in the staged numbering."""
        if self._sorted_sids[0] is not self._staged_sid:  # the sort is redone only when the DOFs change
            order = np.argsort(self._staged_sid)
            self._sorted_sids = (self._staged_sid, order, self._staged_sid[order])
        _, order, ordered = self._sorted_sids
        at = np.minimum(np.searchsorted(ordered, sids), len(order) - 1)
        return np.where(ordered[at] == sids, order[at], -1)

    # ---------------------------------------------------------------------------------------------------
    # Algorithm 1

    def _system_arrays(self):
        """The arguments of ``fem_system`` for the current pieces (cached until the next cut): elements =
        pieces with their parents' shape gradients and volumes |p|, mass assembled from the piece masses,
        gravity loads, the DOFs of the fixed nodes."""
        if self._arrays is None:
            element, dofs, volume, mass, load = self._piece_arrays()
            n = len(self._staged_sid)
            rows = np.broadcast_to(dofs[:, :, None], mass.shape).ravel()
            cols = np.broadcast_to(dofs[:, None, :], mass.shape).ravel()
            M = sp.csr_matrix((mass.ravel(), (rows, cols)), shape=(n, n))
            M = (M + M.T) * 0.5  # summing duplicates in another order leaves M_ij != M_ji in the last bit
            weights = load * self.rho[element][:, None]
            force = np.zeros((n, 3))
            np.add.at(force, dofs, weights[:, :, None] * self.gravity)
            fixed = np.flatnonzero(np.isin(self._staged_node, self.fixed_nodes))
            self._arrays = (dofs, self._grads[element], volume, M, force, fixed)
        return self._arrays

    def system(self) -> FEMSystem:
        """The ``FEMSystem`` of the current pieces (cached until the next cut), one DOF node per row of
        ``state``; ``step`` runs the same system padded to a capacity (module docstring)."""
        self.commit_cuts()
        if self._system is None:
            dofs, grads, volume, M, force, fixed = self._system_arrays()
            self._system = fem_system(dofs, grads, volume, M, force, fixed)
        return self._system

    # ---------------------------------------------------------------------------------------------------
    # capacities: padded systems so that a cut rarely changes the compiled step

    def _capacity(self, level: int) -> SystemCapacity:
        scale = _HEADROOM * _GROWTH**level
        size = [max(f, int(np.ceil(b * scale))) for b, f in zip(self._base, _FLOOR)]
        # as many fixed rows as real nodes: padded fixed nodes cost next to nothing (the reduced system leaves
        # them out), so the fixed count, which cuts through a clamped face multiply, never forces a larger level
        fixed = size[0]
        nodes = size[0] + fixed  # room for the padded fixed nodes
        # the padded free nodes' unit masses add a mass entry and a 3 x 3 block each
        return SystemCapacity(nodes=nodes, elements=size[1], mass_entries=size[2] + nodes, fixed=fixed,
                              nonzeros=size[3] + 9 * nodes)

    def _fits(self, level: int, arrays: tuple, n: int) -> bool:
        """Whether the system ``arrays`` over n DOFs fits capacity ``level`` (its nonzeros aside)."""
        dofs, _, _, M, _, fixed = arrays
        capacity = self._capacity(level)
        return (n <= capacity.nodes - capacity.fixed and len(dofs) <= capacity.elements
                and M.nnz <= capacity.mass_entries - capacity.nodes and len(fixed) <= capacity.fixed)

    def _padded_system(self) -> tuple[FEMSystem, int]:
        """The staged system padded to the smallest capacity level (not below the last one) that holds it."""
        if self._padded is None:
            level, arrays = self._level, self._system_arrays()
            while not self._fits(level, arrays, len(self._staged_sid)):
                level += 1
            dofs, grads, volume, M, force, fixed = arrays
            while True:
                try:
                    system = fem_system(dofs, grads, volume, M, force, fixed,
                                        capacity=self._capacity(level))
                    break
                except CapacityError:  # more matrix nonzeros than the level holds
                    level += 1
            self._padded, self._level = system, level
        return self._padded, self._level

    def _compiled(self, live: _Live, level: int, h, material: Material, newton_iterations: int, background: bool):
        """The step compiled for capacity ``level`` (``compiled_step``), shared by all models through
        ``_COMPILED``: found there, or compiled now (``background=False``), or compiled in a background thread
        that the step needing it will wait for (``background=True``; returns None). ``live``: the system it
        is for (a level above ``live.level`` pads ``live.arrays`` anew)."""
        capacity = self._capacity(level)
        key = (capacity, newton_iterations, np.shape(material.young), np.shape(material.poisson))
        system = live.system if level == live.level else None
        with _COMPILED_LOCK:  # held briefly: a compilation in one thread must not stall another's lookups
            entry = _COMPILED.get(key)
            created = entry is None
            if created:
                if background and not self._fits(level, live.arrays, live.n):
                    return None
                entry = _COMPILED[key] = _Compilation()
                if background:  # never run a step here: two steps' host callbacks at once can deadlock XLA
                    entry.thread = threading.Thread(target=entry.build, args=(live.arrays, capacity, h, material,
                                                                              newton_iterations, system))
                    entry.thread.start()  # not a daemon: XLA must not be cut off at exit
        if background:
            return None
        if created:
            entry.build(live.arrays, capacity, h, material, newton_iterations, system)
        entry.ready.wait()
        if entry.step is None:  # its background build failed (e.g. too few nonzeros): build it here
            entry.build(live.arrays, capacity, h, material, newton_iterations, system)
        return entry.step

    def _live_system(self) -> _Live:
        """The committed system the steps run (built from the staged one when no cut is pending)."""
        if self._live is None:
            system, level = self._padded_system()
            self._live = _Live(system, level, self._system_arrays(), len(self._staged_sid))
        return self._live

    def cut(self, solid: manifold3d.Manifold, perturb: float = 0.0) -> CutReport:
        """Cut the body by a closed cut solid (Algorithm 1 lines 1-25): split the subdomains, copy the split
        nodal subdomains' x and v to their pieces (line 7), integrate the touched elements' pieces (eq. 21),
        re-enrich the elements around split nodes (eq. 16) and renumber the DOFs. Pending ``cut_async`` cuts
        take effect first. Once the model has a cut worker process (``cut_async``, ``start_cut_worker``), the
        cut is made there (with both cores' Booleans) and takes effect at once.

        Args:
            solid: the cut solid Gamma^c (``xfem._cuts.cut_solid``, ``plane_cut_solid``).
            perturb: 0, or the size of the gentle perturbation (``apply_cut``).
        Returns:
            The ``CutReport`` of ``apply_cut``.
        """
        if self._remote:
            check_cut(solid, perturb)
            return self.commit_cuts(until=self._submit(solid, perturb, parallel=True))[-1]
        self.commit_cuts()
        check_cut(solid, perturb)
        # the cut as the worker process would get it (the log replays it there): a Manifold rebuilt from its mesh
        cut = solid_mesh(solid)
        report = self._prepare(cut.build(), perturb)
        self._cut_log.append((cut, perturb, True))
        if report.staged:
            report.dof_source = self._commit(self._staged.popleft())
        return report

    def cut_async(self, solid: manifold3d.Manifold, perturb: float = 0.0) -> Future:
        """Start a cut in the model's cut worker process (class docstring); the model keeps stepping its current
        system until ``commit_cuts`` makes the cut take effect.

        Args:
            solid, perturb: as ``cut`` (checked now).
        Returns:
            A ``concurrent.futures.Future`` of the cut's ``CutReport``; pass it to ``commit_cuts``.
        """
        check_cut(solid, perturb)
        self._live_system()  # the steps' system must not be built from the worker's bookkeeping
        return self._submit(solid, perturb, parallel=False)

    def start_cut_worker(self, wait: bool = True) -> None:
        """Start the cut worker process now (``cut_async`` starts it when needed; it takes a few seconds: the
        imports, the replica of the model, the replay of the cuts made so far).

        Args:
            wait: return once it is ready (its errors, if any, raised here).
        """
        self._remote = True
        future = self._executor().submit(lambda: self._cut_process().wait_ready())
        if wait:
            future.result()

    def _executor(self) -> ThreadPoolExecutor:
        if self._worker is None:
            self._worker = ThreadPoolExecutor(1, thread_name_prefix="xfem-cut")
        return self._worker

    def _submit(self, solid: manifold3d.Manifold, perturb: float, parallel: bool) -> Future:
        """Queue a checked cut for the worker process; it becomes pending."""
        self._remote = True
        request = (solid_mesh(solid), perturb, parallel)
        self._unsent.append(request)
        if not self._pending:  # before the worker thread wakes the worker process, which may then take this core
            self._start_background()
        try:
            future = self._executor().submit(self._prepare_remote, request)
        except BaseException:
            self._unsent.pop()
            if not self._pending:
                self._end_background()
            raise
        self._pending.append(future)
        return future

    def _start_background(self) -> None:
        """Pending cuts from now on: the process-wide settings for background cuts (``_cutting_in_background``),
        undone by ``_end_background``, or when the model is collected with cuts still pending."""
        reserve = self._turns.paced = self._last_step_seconds < _SHORT_STEP_S
        _cutting_in_background(True, reserve)
        self._end_background = weakref.finalize(self, _cutting_in_background, False, reserve)

    @property
    def pending_cuts(self) -> int:
        """The ``cut_async`` cuts not yet committed."""
        return len(self._pending)

    def commit_cuts(self, until: Future | None = None) -> list[CutReport]:
        """Make pending ``cut_async`` cuts take effect, in order: wait for each, renumber the DOFs, copy x and v
        from the current state to the new DOFs (Algorithm 1 line 7) and switch the steps to the new system.

        Args:
            until: a cut's future: commit it and the cuts started before it (later ones stay pending); nothing
                if it is committed already (e.g. by a query); None: all pending cuts.
        Returns:
            The committed cuts' ``CutReport``s, in order. A cut that failed in the worker raises its error here
            (the cuts after it are dropped: they were prepared on its partial bookkeeping).
        """
        if until is not None and until not in self._pending:
            if until in self._committed:
                return []
            raise ValueError("until: expected a cut of this model (a cut_async future)")
        reports = []
        while self._pending:
            future = self._pending.popleft()
            try:
                with self._turns.hurry():
                    report = future.result()
            except BaseException:
                for later in self._pending:
                    later.cancel()
                wait(self._pending)  # one already running stops at once (``_failed``)
                self._pending.clear()
                self._unsent.clear()
                self._staged.clear()
                self._failed = False
                self._end_background()
                raise
            if report.staged:
                report.dof_source = self._commit(self._staged.popleft())
            self._committed.add(future)
            reports.append(report)
            if not self._pending:
                self._end_background()
            if future is until:
                break
        return reports

    def _commit(self, staged: _StagedCut) -> np.ndarray:
        """A prepared cut takes effect: its numbering, the state copied to it (line 7), its system. Returns the
        copy map (``CutReport.dof_source``)."""
        self.dof_sid, self.dof_node = staged.dof_sid, staged.dof_node
        # gathered on the host: a JAX gather would compile anew for every DOF count
        self.state = State(np.asarray(self.state.x)[staged.source], np.asarray(self.state.v)[staged.source])
        self._live, self._system = staged.live, None
        return staged.source

    def _prepare(self, solid: manifold3d.Manifold, perturb: float, parallel: bool = True) -> CutReport:
        """A cut's work up to its commit (``cut``): the subdomains, integrals and enrichment, the new numbering
        and system (and its compiled step for the options of the last step), queued in ``_staged``."""
        report = apply_cut(self.sub, solid, perturb, parallel=parallel)  # in the background: one core each
        report.staged = False
        if len(report.elements_touched) == 0:
            return report
        touched = report.elements_touched
        for sid in report.element_children:  # retired pieces
            self._integrals.pop(sid, None)
            self._enriched.pop(sid, None)
        self._exact.update(touched.tolist())
        start = time.perf_counter()
        report.pieces_integrated = self._integrate(touched)
        report.integration_seconds = time.perf_counter() - start
        start = time.perf_counter()
        # nodes whose subdomain lists changed: their elements' pieces are enriched anew (line 21)
        changed = {self.sub.node_of(s) for s in report.node_children} | set(report.nodes_split.tolist())
        ring = [self.sub.ring_elements[self.sub.ring_offsets[i]:self.sub.ring_offsets[i + 1]] for i in changed]
        self._enrich(np.unique(np.concatenate([touched, *ring])))
        source = self._renumber()
        report.enrichment_seconds = time.perf_counter() - start
        self._arrays = self._padded = None
        self._stage(source)
        report.staged = True
        return report

    def _stage(self, source: np.ndarray) -> None:
        """Queue the staged numbering and system in ``_staged``, with the step compiled for its capacity level
        and the options of the last step. A replica queues no system (live None) where the model builds it."""
        if self._sent_system_bytes is not None and self._padded_bytes_at_least() > self._sent_system_bytes:
            self._staged.append(_StagedCut(self._staged_sid, self._staged_node, source, None))
            return
        system, level = self._padded_system()
        live = _Live(system, level, self._system_arrays(), len(self._staged_sid))
        if self._step_options is not None:  # the new level's step, compiled before the commit needs it
            self._compiled(live, level, *self._step_options, background=False)
        self._staged.append(_StagedCut(self._staged_sid, self._staged_node, source, live))

    def _padded_bytes_at_least(self) -> int:
        """A lower bound of the staged padded system's size: its Hessian scatter map (144 int32 per element) at the
        smallest level that holds its elements, nodes and mass entries."""
        level, arrays = self._level, self._system_arrays()
        while not self._fits(level, arrays, len(self._staged_sid)):
            level += 1
        return 144 * 4 * self._capacity(level).elements

    # ---------------------------------------------------------------------------------------------------
    # the cut worker process (xfem._cut_process)

    def _cut_process(self) -> CutProcess:
        """The worker process, started (with the cuts made so far to replay) if there is none; worker thread."""
        if self._process is None:
            process = CutProcess(dict(
                x64=bool(jax.config.jax_enable_x64), X=np.asarray(self.X), T=np.asarray(self.T), rho=self.rho,
                gravity=self.gravity, fixed=self.fixed_nodes, log=list(self._cut_log),
                sent_system_bytes=_SENT_SYSTEM_BYTES))
            self._process = process
            self._process_closer = weakref.finalize(self, process.close)
        return self._process

    def _drop_process(self) -> None:
        """Stop the worker process (a new one starts with the next cut, from the model's own log)."""
        if self._process_closer is not None:
            self._process_closer()
        self._process = self._process_closer = None

    def _prepare_remote(self, request: tuple[MeshSolid, float, bool]) -> CutReport:
        """``_prepare`` done by the worker process (worker thread): send the cut (unless it went with the last
        reply), wait for what it changed, send the next pending cut, apply the changes to this model's bookkeeping
        and stage them."""
        if self._failed:
            raise CutProcessError("an earlier background cut failed: this one, prepared after it, was dropped")
        try:
            process = self._cut_process()
            if any(r is request for r in self._unsent):
                while self._unsent[0] is not request:  # requests of cuts cancelled after a failure
                    self._unsent.popleft()
                process.send(self._unsent.popleft(), self._turns.piece())
            report, delta = process.receive(self._turns.piece())
            if self._unsent:  # the child works on it while this reply is applied
                try:
                    process.send(self._unsent.popleft(), self._turns.piece())
                except CutProcessError:  # the child exited after its reply: that cut's receive raises it
                    pass
            if delta is not None:
                with self._turns.piece():
                    source = self._apply_remote(report, delta)
                with self._turns.piece():
                    self._take_system(delta)
                self._stage(source)  # builds a large system, or compiles a new level's step: beside the steps
        except BaseException:
            self._failed = True
            self._drop_process()  # its replica ran part of the failed cut, or disagrees with this model
            raise
        self._cut_log.append(request)
        return report

    def _replica_cut(self, cut: MeshSolid, perturb: float, parallel: bool, delta: bool = True):
        """In the worker process: ``_prepare`` on the replica, and what it changed (``_apply_remote``).

        Returns:
            The ``CutReport`` and None (nothing touched, or ``delta`` False: a replay) or a dict: the id counts
            before the cut, per kind the new ids' owners and parents, the retired ids, the touched owners' live
            lists and the meshes of the solids that changed; the touched pieces' integrals; the enrichment
            entries set and removed; the new numbering, its source rows (line 7), system arrays, capacity level
            and padded system (host arrays; None, level None, where it would exceed ``_SENT_SYSTEM_BYTES``: the
            replica does not build it, the model does).
        """
        nodes, elements = self.sub._nodes, self.sub._elements
        counts = (len(nodes.owner), len(elements.owner))
        solids = (list(nodes.solids), list(elements.solids))
        enriched = dict(self._enriched)
        report = self._prepare(cut.build(), perturb, parallel)
        self._cut_log.append((cut, perturb, parallel))
        if not report.staged:
            return report, None
        staged = self._staged.popleft()  # the replica never steps: it takes the numbering at once
        self.dof_sid, self.dof_node = staged.dof_sid, staged.dof_node
        if not delta:
            return report, None

        def kind_delta(kind, start, before, owners, children):
            live = {o: list(kind.live[o]) for o in owners.tolist()}
            changed = [s for ids in live.values() for s in ids if s >= start or kind.solids[s] is not before[s]]
            return dict(owner=kind.owner[start:], parent=kind.parent[start:], retired=list(children), live=live,
                        changed=changed, meshes=pack_meshes([solid_mesh(kind.solids[s]) for s in changed]))

        pieces = [sid for e in report.elements_touched.tolist() for sid in self.sub.element_subdomains(e)]
        integrals = [self._integrals[sid] for sid in pieces]  # none if the cut swallowed every touched element
        volume, mass, load, point = (np.array([v[0] for v in integrals]).reshape(-1),
                                     *(np.stack([v[k] for v in integrals]) if integrals else np.zeros((0, *shape))
                                       for k, shape in ((1, (4, 4)), (2, (4,)), (3, (3,)))))
        set_enriched = [sid for sid, value in self._enriched.items() if enriched.get(sid) is not value]
        live = staged.live
        return report, dict(
            counts=counts,
            nodes=kind_delta(nodes, counts[0], solids[0], report.nodes_touched, report.node_children),
            elements=kind_delta(elements, counts[1], solids[1], report.elements_touched, report.element_children),
            pieces=np.asarray(pieces, np.int64),
            integrals=(volume, mass, load, point),
            enriched=(np.asarray(set_enriched, np.int64),
                      np.stack([self._enriched[sid] for sid in set_enriched]) if set_enriched
                      else np.zeros((0, 4), np.int64)),
            unenriched=np.asarray([sid for sid in enriched if sid not in self._enriched], np.int64),
            numbering=(staged.dof_sid, staged.dof_node, staged.source),
            arrays=self._system_arrays() if live is None else live.arrays, level=None if live is None else live.level,
            system=None if live is None else jax.tree.unflatten(jax.tree.structure(live.system),
                                                                [np.asarray(a) for a in jax.tree.leaves(live.system)]))

    def _apply_remote(self, report: CutReport, delta: dict) -> np.ndarray:
        """Apply what the worker process's cut changed (``_replica_cut``) to the bookkeeping and the staged
        numbering (worker thread, in its turn; the system: ``_take_system``). Returns the new DOFs' source rows,
        for ``_stage``."""
        sub = self.sub
        counts = (len(sub._nodes.owner), len(sub._elements.owner))
        if tuple(delta["counts"]) != counts:
            raise CutProcessError(f"the cut worker process's replica has {delta['counts']} nodal and element "
                                  f"subdomain ids, this model {counts}")
        for kind, change in ((sub._nodes, delta["nodes"]), (sub._elements, delta["elements"])):
            added = len(change["owner"])
            kind.owner.extend(change["owner"])
            kind.parent.extend(change["parent"])
            kind.alive.extend([True] * added)
            kind.solids.extend([None] * added)
            for sid in change["retired"]:
                kind.alive[sid] = False
                kind.solids[sid] = None
            for owner, ids in change["live"].items():
                kind.live[owner] = ids
            for sid, mesh in zip(change["changed"], unpack_meshes(change["meshes"])):
                kind.solids[sid] = mesh  # built into a Manifold on first use (Subdomains.node_solid)
        for sid in delta["nodes"]["retired"]:
            self._node_meshes.pop(sid, None)
        for sid in delta["elements"]["retired"]:
            self._integrals.pop(sid, None)
            self._enriched.pop(sid, None)
        self._exact.update(report.elements_touched.tolist())
        volume, mass, load, point = delta["integrals"]
        for k, sid in enumerate(delta["pieces"].tolist()):
            self._integrals[sid] = (float(volume[k]), mass[k], load[k], point[k])
        for sid in delta["unenriched"].tolist():
            self._enriched.pop(sid, None)
        sids, nodal = delta["enriched"]
        for k, sid in enumerate(sids.tolist()):
            self._enriched[sid] = nodal[k].copy()  # _enrich writes into its entries
        self._staged_sid, self._staged_node, source = delta["numbering"]
        return source

    def _take_system(self, delta: dict) -> None:
        """The staged system from a worker process's reply: its arrays, and its padded system put on the device
        where the reply holds one (else ``_stage`` builds it from the arrays)."""
        self._arrays, self._padded = delta["arrays"], None
        if delta["system"] is not None:
            system = delta["system"]
            self._padded = jax.tree.unflatten(jax.tree.structure(system), to_devices(*jax.tree.leaves(system)))
            self._level = delta["level"]

    def _renumber(self) -> np.ndarray:
        """The staged DOFs become the live nodal subdomains that a piece reaches, ordered by node, then id
        (creation order). Returns, for each, the DOF of the previous numbering whose x and v it copies: its own,
        or its parent's for a subdomain made by this cut (line 7)."""
        sids = np.unique(self._pieces()[1])
        nodes = np.array([s if s < len(self.X) else self.sub.node_of(int(s)) for s in sids], np.int64)
        order = np.lexsort((sids, nodes))
        sids, nodes = sids[order], nodes[order]
        source = self._dof_index(sids)
        for k in np.flatnonzero(source < 0).tolist():
            origin = int(sids[k])
            while source[k] < 0:
                origin = self.sub.node_parent(origin)
                source[k] = self._dof_index(np.array([origin]))[0]
        self._staged_sid, self._staged_node = sids, nodes
        return source

    def step(self, h, material: Material, newton_iterations: int = 1) -> State:
        """One backward Euler step (eq. 10, Algorithm 1 line 26) of the current system; updates and returns
        ``state``. material: the ``Material``, scalar parameters. Pending ``cut_async`` cuts do not take effect here
        (``commit_cuts``).

        The system is padded to a capacity level (module docstring); the step of the next level is compiled
        in the background meanwhile."""
        if int(newton_iterations) != newton_iterations or newton_iterations < 1:
            raise ValueError(f"newton_iterations: expected an int >= 1, got {newton_iterations!r}")
        start = time.perf_counter()
        with self._turns.step():  # the cut worker thread's Python waits (``_Turns``)
            live = self._live_system()
            options = (h, material, int(newton_iterations))
            step = self._compiled(live, live.level, *options, background=False)
            stepped = step(live.system, _padded_state(self.state, live.n, live.system.n), h, material)
            # host views of the result, sliced (a JAX slice would compile anew for every DOF count)
            self.state = State(np.asarray(stepped.x)[:live.n], np.asarray(stepped.v)[:live.n])
            self._step_options = options
            self._compiled(live, live.level + 1, *options, background=True)
        self._last_step_seconds = time.perf_counter() - start
        return self.state

    # ---------------------------------------------------------------------------------------------------
    # queries

    def _field(self, values: np.ndarray, points, elements) -> np.ndarray:
        """sum_i sum_s values_i^s phi_i(X) psi_i^s(X) (eq. 18) at points X in the given elements."""
        points = np.asarray(points, np.float64)
        elements = np.asarray(elements)
        if points.ndim != 2 or points.shape[1] != 3 or not np.all(np.isfinite(points)):
            raise ValueError(f"points: expected finite points of shape (k, 3), got {points.shape}")
        if elements.shape != (len(points),) or not np.issubdtype(elements.dtype, np.integer) or (
                elements.size and (elements.min() < 0 or elements.max() >= len(self.T))):
            raise ValueError(f"elements: expected ({len(points)},) element indices in [0, {len(self.T)})")
        c, _ = linear_shape_coefficients(self.X[self.T[elements]], points)  # phi_a(X): barycentric coordinates
        result = np.zeros((len(points), values.shape[1]))
        for a in range(4):
            nodes = self.T[elements, a]
            for i in np.unique(nodes).tolist():
                at = np.flatnonzero(nodes == i)
                options = self.sub.node_subdomains(i)
                if len(options) == 1:
                    chosen = np.zeros(len(at), np.int64)
                else:
                    chosen = _nearest_subdomain([self._node_mesh(s) for s in options], points[at])
                dofs = self._dof_index(np.asarray(options, np.int64))[chosen]
                if np.any(dofs < 0):
                    raise ValueError(f"points: a point's nodal subdomain of node {i} has no material (no DOF)")
                result[at] += c[at, a, None] * values[dofs]
        return result

    def displacement_at(self, points, elements) -> np.ndarray:
        """u(X) = sum_i sum_s u_i^s phi_i(X) psi_i^s(X) (eq. 18), u_i^s = x_i^s - X_i.

        Args:
            points: (k, 3) material points.
            elements: (k,) int the element containing each point.
        Returns:
            (k, 3) displacements.
        """
        self.commit_cuts()
        return self._field(np.asarray(self.state.x) - self.X[self.dof_node], points, elements)

    def velocity_at(self, points, elements) -> np.ndarray:
        """The velocity field of eq. 18 (coefficients v_i^s) at points (k, 3) in elements (k,); (k, 3)."""
        self.commit_cuts()
        return self._field(np.asarray(self.state.v), points, elements)

    def components(self) -> tuple[int, np.ndarray]:
        """The connected pieces of the body: components of the graph of element pieces sharing a DOF (of the
        committed cuts: pending ``cut_async`` cuts are not waited for).

        Returns:
            count, and (n_dofs,) int the component of each DOF.
        """
        if self._pending:  # the committed pieces: the live system's elements
            dofs, n = self._live.arrays[0], self._live.n
        else:
            dofs, n = self._piece_arrays()[1], len(self.dof_sid)
        rows = np.repeat(dofs[:, :1], 3, axis=1).ravel()
        graph = sp.csr_matrix((np.ones(len(rows)), (rows, dofs[:, 1:].ravel())), shape=(n, n))
        return connected_components(graph, directed=False)

    def pieces(self) -> int:
        """The number of connected pieces of the body (``components``)."""
        return self.components()[0]


def replica_model(init: dict) -> XFEMModel:
    """The cut worker process's replica (``xfem._cut_process``) of a model: made from its construction
    arguments, then its past cuts replayed (``XFEMModel._cut_process`` gives ``init``)."""
    X = np.asarray(init["X"], np.float64)
    zeros = np.zeros_like(X)
    model = XFEMModel(TetMesh(X=X, T=np.asarray(init["T"], np.int64)), init["rho"], init["gravity"], init["fixed"],
                      State(zeros, zeros))
    model._sent_system_bytes = init["sent_system_bytes"]
    for cut, perturb, parallel in init["log"]:
        model._replica_cut(cut, perturb, parallel, delta=False)
    return model


def xfem_model(mesh: TetMesh, density, gravity=(0.0, 0.0, -9.81), fixed=(), state: State | None = None) -> XFEMModel:
    """An uncut XFEM model: one DOF per node (its 1-ring), one piece per tet.

    Args:
        mesh: the ``TetMesh``.
        density: scalar or (m,) positive mass density per tet.
        gravity: (3,) gravitational acceleration (body force density ``density * gravity``).
        fixed: (nb,) int mesh nodes held in place (all their DOFs, also after cuts); () for none.
        state: the initial ``State`` over the n nodes (float64); None: at rest in the rest positions.
    Returns:
        The ``XFEMModel``.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh: expected a TetMesh, got {type(mesh).__name__}")
    m, n = mesh.T.shape[0], mesh.X.shape[0]
    rho = np.asarray(density)
    if rho.shape not in ((), (m,)) or not np.issubdtype(rho.dtype, np.number) or not np.all(
            np.isfinite(rho) & (rho > 0)):
        raise ValueError(f"density: expected finite positive values of shape () or ({m},), got {rho.shape}")
    rho = np.broadcast_to(rho.astype(np.float64), (m,)).copy()
    gravity = np.asarray(gravity, np.float64)
    if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
        raise ValueError(f"gravity: expected a finite (3,) acceleration, got {gravity.shape}")
    fixed = np.asarray(fixed).reshape(-1)
    if fixed.size and (not np.issubdtype(fixed.dtype, np.integer) or fixed.min() < 0 or fixed.max() >= n
                       or len(np.unique(fixed)) != len(fixed)):
        raise ValueError(f"fixed: expected distinct int node indices in [0, {n})")
    fixed = fixed.astype(np.int64)
    if state is None:
        X = jnp.asarray(mesh.X, jnp.float64)
        state = State(X, jnp.zeros_like(X))
    elif not isinstance(state, State) or jnp.shape(state.x) != (n, 3) or jnp.shape(state.v) != (n, 3) or \
            jnp.result_type(state.x) != jnp.float64 or jnp.result_type(state.v) != jnp.float64:
        raise ValueError(f"state: expected a float64 State with x, v of shape ({n}, 3)")
    return XFEMModel(mesh, rho, gravity, fixed, state)
