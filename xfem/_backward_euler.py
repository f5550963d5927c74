"""Backward Euler time stepping of the XFEM paper, sec. 3.3: the equations of motion ``M u'' = -grad U + f``
(eq. 6) with the mass, force and elastic energy of eq. 7-9, integrated by eq. (10) as a minimization.

Step (eq. 10). With ``x~ = x_t + h v_t``, the new positions minimize

    E(x) = 1/2 (x - x~)^T M (x - x~) + h^2 (U(x) - f . x),

which has the same minimizer as the paper's ``1/2 |x - x~ - h^2 M^-1 f|_M^2 + h^2 U`` (they differ by a
constant) without inverting M; then ``v_{t+1} = (x_{t+1} - x_t) / h``. Dirichlet nodes are substituted:
their positions are set (to ``fixed_positions``, default where they are) and only the free nodes are
unknowns. Newton's method starts at x~ (fixed nodes placed) and solves ``(M + h^2 K_+) dx = -grad E`` on the
free DOFs, K_+ being the stiffness assembled from the PSD-projected element Hessians (so the direction is
one of descent), followed by a backtracking (Armijo) line search on E. By default the iterations go on, up to
``newton_iterations`` (50), until the largest entry of a Newton update is at most ``tolerance`` times the body's
size (the diagonal of the bounding box of its elements' nodes at time t; a relative stop, so a mesh in millimetres
converges as one in metres): 1e-10 in float64, 1e-5 in float32, what rounding lets a step reach. Newton converges
quadratically where the projection is inactive, so the last update is about the square of the one before: the
minimizer is then reached to rounding, and the implicit gradient below is the derivative of the step computed.
The paper takes one Newton iteration per step (``newton_iterations=1, tolerance=None``: no stop test), as the
scenes, the benchmarks and ``jaxcga fem`` do. Each result carries ``SolveStats``: whether the last update met the
tolerance (the default one when the paper's step has none), the iterations and that update relative to the size.

The system is generic over an element list: elements ``T`` index a DOF-node array, each with its shape
gradients and integration weight (``volumes``), plus any symmetric scalar (n, n) mass matrix and (n, 3)
forces. Nothing assumes the nodes are mesh vertices or that the mass is ``consistent_mass``, so XFEM's
enriched copies, sub-elements and custom mass entries go through the same code.

Linear solver (``_jaxcga_shared.sparse``), chosen per platform when the step is lowered. On the CPU, by
measurement (benchmarks/README.md, "FEM linear solver"; ``bench_fem.py`` times the step against CHOLMOD):
Jacobi-preconditioned CG on the host (``host_pcg``, compiled by numba without the GIL), one host call
(``_jaxcga_shared.host.host_call``) per Newton iteration. CHOLMOD's wheel carries the reference BLAS, so its
factorization is slow on large systems, and CG in JAX pays XLA's CPU gathers and scatters in every matrix-vector
product. Small systems are the exception: up to ``_DIRECT_DOFS`` = 1,000 unknowns one CHOLMOD factorization costs
less than CG's iterations, and the step solves exactly (``_host_newton_direction``). On a GPU, CG in JAX on the
device, preconditioned by the inverse 3 x 3 node blocks (``device_pcg``): no copy to the host and back; up to
``_DIRECT_DOFS`` unknowns a dense Cholesky factorization on the device, exact as on the CPU.
CG's Newton direction is solved to a relative residual of 1e-4 (an inexact Newton step: a tighter residual costs
more iterations and moves the positions by a small fraction of the displacement); after n iterations the iterate
is taken as it is (it still decreases the quadratic model, so it remains a descent direction).
With ``tolerance`` the relative residual is tightened to ``|grad E| / |grad E at the first iteration|`` (down
to 1e-11, or 100 times the unit roundoff in float32), so that Newton converges superlinearly where the
projection of the element Hessians is inactive near the solution (where it is active, projected Newton converges
linearly). Factored directions (``_newton``'s ``factored``, what ``xfem.simulate_character`` uses): each Newton matrix,
projected, is factored by CHOLMOD on the host and preconditions CG on the true Hessian, stopped at a direction of
negative curvature (``_host_factored_direction``); where the projection is active at the minimizer this converges
quadratically, projected Newton only linearly. For bodies whose factor stays sparse (a character's limbs); the
adjoint solve is then CHOLMOD's too. On a GPU the projected system's device solve, as above. The adjoint solve of the
gradients (below) must be accurate: it uses CHOLMOD (scipy's SuperLU when the true Hessian is not positive
definite), or above ``_DIRECT_DOFS`` unknowns CG to a relative residual of 1e-10, checked; on a GPU the dense
Cholesky factorization up to ``_DIRECT_DOFS`` unknowns, above them the device CG to 1e-10, and the host's solve
where either falls short.

Memory. The energy, its gradient and the Newton matrix are summed over chunks of elements (and M d over
chunks of mass entries, ``_in_chunks``), so that a step's temporaries stay small enough for glibc to reuse
them from one call to the next (a step over every element at once page-faulted a third of its time away).

Gradients (implicit differentiation). ``backward_euler_step`` is differentiable in reverse mode with
respect to ``state.x``, ``state.v``, the ``Material``, ``fixed_positions`` and, in the system, ``force``,
``grads``, ``volumes`` and ``mass_values`` (e.g. XFEM integration weights that depend on a cut); not ``h``.
At the minimizer x* the free-DOF gradient ``G(x*, theta) = grad_free E`` vanishes, so
``dx*/dtheta = -H^-1 dG/dtheta`` with H the TRUE (unprojected) Hessian ``M + h^2 K``: the backward pass
solves ``H u = x_bar`` once and returns ``-(dG/dtheta)^T u`` (a vjp of autodiff's gradient of E); the fixed
rows pass their cotangent to ``fixed_positions``. The Newton loop is never unrolled. This is the derivative
of the exact minimizer: it matches the computed step when the step is converged (the default,
``stats.converged``); after the paper's single Newton iteration it is the converged step's formula evaluated
at the executed iterate, an approximation (``xfem._rollout`` measures how close).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal, NamedTuple

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
import numpy.typing as npt
import scipy.sparse as sp
from jax.ad_checkpoint import checkpoint_name
from jaxtyping import Array, Bool, Float, Int

from _jaxcga_shared.checks import check_real, require
from _jaxcga_shared.host import host_call, to_devices
from _jaxcga_shared.platform import EXACT
from _jaxcga_shared.sparse import factorize, host_csr, host_direct, host_pcg, spd_solve
from xfem._assembly import (
    AssemblyPattern,
    CapacityError,
    _assembly_pattern,
    _host_elements,
    _host_fixed,
    _scalar_slots,
    add_element_hessians,
    restrict,
)
from xfem._linear_tet import body_force, consistent_mass, shape_gradients
from xfem._material import Material
from xfem._neohookean import (
    _element_energy,
    _element_gradient_hessian,
    _element_gradient_hessians,
    _modified_lame,
    element_energy,
)
from xfem._tetmesh import TetMesh

_CG_RTOL = 1e-4  # relative residual of the Newton direction (inexact Newton)
_DIRECT_DOFS = 1000  # Newton systems up to this many unknowns are factorized (CHOLMOD), larger ones go to CG
_CG_RTOL_MIN = 1e-11  # the tightest one asked for when converging (CG stalls near rounding)
# the factored direction's CG iterations at most: each costs a solve with the factor, and where the projection is
# active on many elements more buy little (the iterate is a descent direction wherever CG stops)
_FACTORED_CG_ITERATIONS = 30
# the default relative tolerance per dtype ("auto"): far enough above rounding to be reached (a float32 position
# holds ~7 digits), tight enough in float64 that the implicit gradient matches the executed step well within 1e-6
_TOLERANCE = {np.dtype(np.float64): 1e-10, np.dtype(np.float32): 1e-5}
_NEWTON_ITERATIONS = 50  # the default cap, far above what Newton's quadratic convergence needs
# the adjoint solve's CG residual: 5e-11 of CHOLMOD's solution on accordion's 37k unknowns, in a third of its time
_ADJOINT_RTOL = 1e-10
_ARMIJO = 1e-4  # sufficient-decrease constant of the line search
_HALVINGS = 30  # the line search gives up (takes no step) after this many halvings


class _Chunks(NamedTuple):
    """Rows per chunk of a sum over elements or mass entries (``_in_chunks``), per platform: small on the CPU
    (its temporaries stay in glibc's heap); on a GPU a chunk of 1,024 elements fills a few of its cores and pays a
    loop step of launches, so one chunk holds every element up to a bound on the temporaries (~3.5 KB an
    element: 460 MB at the bound)."""

    cpu: int
    device: int


_ELEMENT_CHUNK = _Chunks(cpu=1024, device=1 << 17)  # elements per chunk of the energy, its gradient and Hessians
_MASS_CHUNK = _Chunks(cpu=16384, device=1 << 20)  # mass entries per chunk of M d
_NEWTON_RESULT = "xfem_newton_result"  # checkpoint name of a step's minimizer, its implicit gradient's residual


class FEMSystem(eqx.Module):
    """Everything a backward Euler step needs besides the state and the material (``fem_system``,
    ``fem_from_mesh``).

    Attributes:
        T: (m, 4) int elements, indices into the n DOF nodes.
        grads: (m, 4, 3) shape-function gradients of each element (``F_e = sum_a x_{T[e,a]} grads[e,a]^T``).
        volumes: (m,) integration weights (rest volumes).
        mass_rows, mass_cols: (k,) int nonzero entries of the scalar (n, n) mass matrix, sorted by row (CSR).
        mass_values: (k,) their values (eq. 7's scalar factor; the 3n matrix is ``M (x) I3``).
        mass_data: (nnz,) ``M (x) I3`` restricted to the free DOFs, as data of ``pattern``.
        force: (n, 3) external nodal forces f (eq. 8).
        fixed: (nb,) int Dirichlet nodes.
        pattern: the ``AssemblyPattern`` of the free-DOF system (elements and mass couplings).
        n: the number of DOF nodes.
    """

    T: Int[Array | np.ndarray, "m 4"]
    grads: Float[Array | np.ndarray, "m 4 3"]
    volumes: Float[Array | np.ndarray, " m"]
    mass_rows: Int[Array | np.ndarray, " k"]
    mass_cols: Int[Array | np.ndarray, " k"]
    mass_values: Float[Array | np.ndarray, " k"]
    mass_data: Float[Array | np.ndarray, " nnz"]
    force: Float[Array | np.ndarray, "n 3"]
    fixed: Int[Array | np.ndarray, " nb"]
    pattern: AssemblyPattern
    n: int = eqx.field(static=True)


class SolveStats(eqx.Module):
    """How far a step's Newton minimization of E (eq. 10) went: one value per step (shape (), or (frames,) in a
    rollout's trajectory). A pytree of arrays, so it passes through jit, vmap and scan.

    Attributes:
        converged: bool, the last Newton update's ``residual`` is at most the tolerance (the one given, or with
            ``tolerance=None`` the dtype's default, ``"auto"``): the step's implicit gradient is then the
            derivative of the executed step. False after the paper's single iteration of a moving body.
        iterations: int, the Newton iterations run.
        residual: the largest entry of the last Newton update divided by the body's size (the diagonal of the
            bounding box of its elements' nodes at time t): the distance from the minimizer, relative.
    """

    converged: Bool[Array | np.ndarray, "*frames"]
    iterations: Int[Array | np.ndarray, "*frames"]
    residual: Float[Array | np.ndarray, "*frames"]


class State(eqx.Module):
    """Positions and velocities of the n DOF nodes (device or host arrays), and, on a step's result, how its
    minimization converged.

    Attributes:
        x: (n, 3) positions.
        v: (n, 3) velocities.
        stats: the ``SolveStats`` of the step (of every frame, for a rollout) that made this state; for a state
            made otherwise (``State(x, v)``), no step's: converged, 0 iterations, residual 0. Steps ignore it in
            their input; it is always there, so that a step's result and its input have one pytree structure (a
            ``jax.lax.scan`` carry).
    """

    x: Float[Array | np.ndarray, "n 3"]
    v: Float[Array | np.ndarray, "n 3"]
    stats: SolveStats

    def __init__(
        self,
        x: Float[Array | np.ndarray, "n 3"],
        v: Float[Array | np.ndarray, "n 3"],
        stats: SolveStats | None = None,
    ):
        self.x, self.v = x, v
        if stats is None:
            dtype = jnp.result_type(x) if jnp.issubdtype(jnp.result_type(x), jnp.floating) else np.float64
            stats = SolveStats(np.asarray(True), np.asarray(0, np.int32), np.zeros((), dtype))
        self.stats = stats


class SystemCapacity(NamedTuple):
    """The array sizes of a padded ``fem_system``: systems built to one capacity share every array shape, so
    ``backward_euler_step`` compiles once for all of them (XFEM's systems change with every cut).

    Padding: extra DOF nodes (the last ``fixed - nb`` of them fixed, the others free with unit mass, no
    elements and no force, so a state that puts them anywhere with zero velocity keeps them there), extra
    elements (copies of element 0 with weight 0), extra mass entries (zeros) and CSR slots
    (``assembly_pattern``'s ``nnz_capacity``). None of it changes the real DOFs' step.

    Attributes:
        nodes: DOF nodes n (>= the real nodes + the padded fixed nodes).
        elements: elements m.
        mass_entries: stored entries of the scalar mass matrix (>= the real ones + the padded nodes).
        fixed: Dirichlet nodes.
        nonzeros: stored entries of the reduced 3n x 3n matrix.
    """

    nodes: int
    elements: int
    mass_entries: int
    fixed: int
    nonzeros: int


def _pad(
    T, grads, volumes, mass, force, fixed, capacity: SystemCapacity
) -> tuple[np.ndarray, np.ndarray, np.ndarray, sp.csr_matrix, np.ndarray, np.ndarray]:
    """The padded arrays of ``SystemCapacity`` (host)."""
    n, m = mass.shape[0], len(T)
    extra_nodes, extra_fixed = capacity.nodes - n, capacity.fixed - len(fixed)
    if min(extra_nodes, extra_fixed, capacity.elements - m, extra_nodes - extra_fixed) < 0 or m < 1:
        raise CapacityError(f"capacity: {capacity} is too small for {n} nodes ({len(fixed)} fixed) and {m} elements")
    # numpy, not JAX: a JAX concatenate would compile anew for every size
    T = np.concatenate([T, np.repeat(T[:1], capacity.elements - m, axis=0)])
    grads = np.concatenate([grads, np.repeat(grads[:1], capacity.elements - m, axis=0)])
    volumes = np.concatenate([volumes, np.zeros(capacity.elements - m, volumes.dtype)])
    if extra_nodes:
        mass = sp.block_diag([mass, sp.identity(extra_nodes)], format="csr")
    force = np.concatenate([force, np.zeros((extra_nodes, 3), force.dtype)])
    fixed = np.concatenate([fixed, np.arange(capacity.nodes - extra_fixed, capacity.nodes)])
    # block_diag(format="csr") is typed as a coo matrix in scipy's stubs
    return T, grads, volumes, mass, force, fixed  # pyright: ignore[reportReturnType]


def fem_system(
    T: Int[npt.ArrayLike, "m 4"],
    grads: Float[npt.ArrayLike, "m 4 3"],
    volumes: Float[npt.ArrayLike, " m"],
    mass: sp.spmatrix | sp.sparray | Float[npt.ArrayLike, "n n"],
    force: Float[npt.ArrayLike, "n 3"],
    fixed: Int[npt.ArrayLike, " nb"] = (),
    capacity: SystemCapacity | None = None,
) -> FEMSystem:
    """Bundle an element list, a mass matrix, forces and Dirichlet nodes for ``backward_euler_step`` (host).

    Args:
        T: (m, 4) int elements, indices into the n DOF nodes.
        grads: (m, 4, 3) float shape-function gradients of the elements; their dtype is the system's.
        volumes: (m,) float non-negative integration weights.
        mass: (n, n) symmetric scalar mass matrix (scipy sparse or dense), positive definite on the free
            nodes; its nonzeros may couple nodes that share no element.
        force: (n, 3) float nodal forces.
        fixed: (nb,) distinct int Dirichlet nodes; () for none.
        capacity: None, or the ``SystemCapacity`` to pad to; the state of the padded system has
            ``capacity.nodes`` rows, the real nodes first (pad with zeros).
    Returns:
        The ``FEMSystem``.
    """
    return host_fem_system(T, grads, volumes, mass, force, fixed, capacity, on_host=False)


def host_fem_system(T, grads, volumes, mass, force, fixed=(), capacity=None, *, on_host: bool) -> FEMSystem:
    """``fem_system``, its arrays numpy ones with ``on_host`` (a system built for another process: the XFEM cut
    worker's), else on the device."""
    # numpy on the host, one device_put at the end: jnp.asarray of a numpy array compiles a copy per shape
    grads, volumes = np.asarray(grads), np.asarray(volumes)
    if grads.ndim != 3 or grads.shape[1:] != (4, 3) or not jnp.issubdtype(grads.dtype, jnp.floating):
        raise ValueError(f"grads: expected float shape gradients of shape (m, 4, 3), got {grads.dtype} {grads.shape}")
    dtype, m = grads.dtype, grads.shape[0]
    if volumes.shape != (m,) or not jnp.issubdtype(volumes.dtype, jnp.floating):
        raise ValueError(f"volumes: expected float weights of shape ({m},), got {volumes.dtype} {volumes.shape}")
    if not (np.all(np.isfinite(grads)) and np.all(np.isfinite(volumes)) and np.all(np.asarray(volumes) >= 0)):
        raise ValueError("grads, volumes: expected finite values and non-negative weights")
    mass = sp.csr_matrix(mass, dtype=np.float64)
    n = mass.shape[0]  # pyright: ignore[reportOptionalSubscript]  # scipy's stubs type a matrix's shape Optional
    if mass.shape != (n, n) or n < 1:
        raise ValueError(f"mass: expected a square (n, n) matrix, got shape {mass.shape}")
    mass.sum_duplicates()
    mass.eliminate_zeros()
    if not np.all(np.isfinite(mass.data)) or (mass.nnz and abs(mass - mass.T).max() > 1e-12 * abs(mass).max()):
        raise ValueError("mass: expected a finite symmetric matrix")
    T = _host_elements(T, n)
    if len(T) != m:
        raise ValueError(f"T: expected {m} elements (as in grads), got {len(T)}")
    force = np.asarray(force)
    if force.shape != (n, 3) or not np.all(np.isfinite(force)):
        raise ValueError(f"force: expected finite forces of shape ({n}, 3), got {force.shape}")
    fixed = _host_fixed(fixed, n)
    if len(fixed) == n:
        raise ValueError(f"fixed: all {n} DOF nodes are fixed, so there is nothing to solve for")
    nnz_capacity = None
    if capacity is not None:
        T, grads, volumes, mass, force, fixed = _pad(T, grads, volumes, mass, force, fixed, capacity)
        n, nnz_capacity = capacity.nodes, capacity.nonzeros
    pattern, host = _assembly_pattern(T, n, fixed, mass, nnz_capacity, on_host=on_host)
    coo = mass.tocoo()
    rows, cols, values = coo.row, coo.col, coo.data
    if capacity is not None:  # zero entries on the last node's diagonal keep the rows sorted
        if capacity.mass_entries < len(values):
            raise CapacityError(f"capacity: {capacity.mass_entries} mass entries, fewer than the {len(values)} needed")
        extra = capacity.mass_entries - len(values)
        rows, cols = (np.concatenate([a, np.full(extra, n - 1, a.dtype)]) for a in (rows, cols))
        values = np.concatenate([values, np.zeros(extra)])
    index = pattern.indices.dtype
    values = np.asarray(values, dtype)
    # on the host (no JAX op to dispatch: fem_system may run beside a step, in a compiling thread)
    slots = _scalar_slots(pattern, host, rows, cols)
    kept = slots < pattern.nnz
    # bincount sums in order as np.add.at does, 25% sooner (each slot holds one entry, and padding zeros)
    weights = np.broadcast_to(values[:, None], slots.shape)[kept]
    mass_data = np.bincount(slots[kept], weights, minlength=pattern.nnz).astype(dtype)
    return FEMSystem(  # the arrays in FEMSystem's field order
        *to_devices(
            T.astype(index),
            grads.astype(dtype),
            volumes.astype(dtype),
            rows.astype(index),
            cols.astype(index),
            values,
            mass_data,
            force.astype(dtype),
            fixed.astype(index),
            on_host=on_host,
        ),
        pattern=pattern,
        n=n,
    )


def fem_from_mesh(
    mesh: TetMesh,
    density: float | Float[npt.ArrayLike, " m"],
    gravity: Float[npt.ArrayLike, " 3"] = (0.0, 0.0, -9.81),
    fixed: Int[npt.ArrayLike, " nb"] = (),
) -> FEMSystem:
    """The FEM system of a tet mesh: linear elements, consistent mass (eq. 7), gravity as body force (eq. 8).

    Args:
        mesh: the ``TetMesh``.
        density: scalar or (m,) positive mass density per tet.
        gravity: (3,) gravitational acceleration; the body force density is ``density * gravity``.
        fixed: (nb,) distinct int Dirichlet nodes; () for none.
    Returns:
        The ``FEMSystem`` (n = the mesh's nodes).
    """
    gravity = check_real("gravity", gravity, (3,), "a finite acceleration")
    grads, volumes = shape_gradients(mesh.X, mesh.T)
    mass = consistent_mass(mesh.X, mesh.T, density)
    rho = np.asarray(density, np.float64)
    force = body_force(mesh.X, mesh.T, rho[..., None] * gravity)
    return fem_system(mesh.T, grads, volumes, mass, force, fixed)


# ---------------------------------------------------------------------------------------------------------
# host linear solves


def _host_adjoint(data, rhs, rtol, indptr, indices):
    """The implicit gradient's solve with the true Hessian: exact (``host_direct``) up to ``_DIRECT_DOFS``
    unknowns; above, Jacobi PCG to ``rtol`` (``_ADJOINT_RTOL``), checked, and the direct solve where CG falls short
    (an indefinite matrix)."""
    if len(rhs) > _DIRECT_DOFS:
        x = host_pcg(data, rhs, rtol, indptr, indices)
        if np.linalg.norm(host_csr(data, indptr, indices) @ x - rhs) <= 2 * rtol * np.linalg.norm(rhs):
            return x
    return host_direct(data, rhs, indptr, indices)


def _host_newton_direction(data, rhs, rtol, indptr, indices):
    """The Newton system's solve: CHOLMOD on systems of at most ``_DIRECT_DOFS`` unknowns, where one
    factorization costs less than CG's iterations (module docstring), Jacobi PCG to ``rtol`` otherwise and on
    a matrix CHOLMOD finds not positive definite."""
    if len(rhs) <= _DIRECT_DOFS:
        return _host_projected_direction(data, rhs, rtol, indptr, indices)
    return host_pcg(data, rhs, rtol, indptr, indices)


def _host_factored_direction(data, true_data, rhs, rtol, indptr, indices):
    """The factored Newton direction (``_newton``'s ``factored``): CG on the true Hessian (``true_data``)
    preconditioned by the CHOLMOD factor of the projected one (``data``), from 0, to the relative residual ``rtol``
    or ``_FACTORED_CG_ITERATIONS`` iterations, stopped where it meets a direction of negative curvature (Steihaug):
    its first iterate is the projected Newton direction, its limit the true Newton direction where the true Hessian
    is positive definite. Every iterate descends (the quadratic model falls along CG's positive-curvature
    directions). Jacobi PCG on the projected matrix where CHOLMOD finds it not positive definite."""
    try:
        precondition = factorize(host_csr(data, indptr, indices), symmetric=True)
    except ValueError:
        return host_pcg(data, rhs, rtol, indptr, indices)
    H = host_csr(true_data, indptr, indices)
    b = np.asarray(rhs, np.float64)

    def dot(u, v):  # not BLAS: numpy's threaded dot stalls on a loaded machine (_jaxcga_shared.pcg)
        return float(np.sum(u * v))

    x, r = np.zeros_like(b), b.copy()
    z = precondition(r)
    p, rz, stop = z.copy(), dot(r, z), float(rtol) ** 2 * dot(b, b)
    for k in range(_FACTORED_CG_ITERATIONS):
        Hp = H @ p
        curvature = dot(p, Hp)
        if not curvature > 0:  # the true Hessian is indefinite along p: keep the iterate (the first: P^-1 b)
            return (x if k else z).astype(rhs.dtype)
        alpha = rz / curvature
        x += alpha * p
        r -= alpha * Hp
        if dot(r, r) <= stop:
            break
        z = precondition(r)
        rz, previous = dot(r, z), rz
        p = z + (rz / previous) * p
    return x.astype(rhs.dtype)


def _host_projected_direction(data, rhs, rtol, indptr, indices):
    """The projected Newton direction by the CHOLMOD factor at every size (``_host_newton_direction``'s small
    systems; ``_newton``'s factored mode with a single iteration, which has no later iterations to converge with
    the true Hessian); Jacobi PCG where CHOLMOD finds the matrix not positive definite."""
    try:
        solve = factorize(host_csr(data, indptr, indices), symmetric=True)
    except ValueError:
        return host_pcg(data, rhs, rtol, indptr, indices)
    return solve(np.asarray(rhs, np.float64)).astype(rhs.dtype)


def _host_exact(data, rhs, rtol, indptr, indices):
    """The factored mode's adjoint solve: exact (``host_direct``: CHOLMOD, SuperLU where the true Hessian is not
    positive definite) at every size."""
    return host_direct(data, rhs, indptr, indices)


def _factored_solve(pattern: AssemblyPattern, data, true_data, rhs, rtol):
    """The factored Newton direction (``_host_factored_direction``; with ``true_data`` None the projected one,
    ``_host_projected_direction``) on the CPU; elsewhere the projected system's ``_solve`` (the device has no
    sparse factorization)."""

    def on_host(data, true_data, rhs, rtol):
        shape = jax.ShapeDtypeStruct(rhs.shape, rhs.dtype)
        indptr, indices = pattern.indptr, pattern.indices
        if true_data is None:
            return host_call(_host_projected_direction, shape, data, rhs, rtol, indptr, indices)
        return host_call(_host_factored_direction, shape, data, true_data, rhs, rtol, indptr, indices)

    def on_device(data, true_data, rhs, rtol):
        return _solve(_host_newton_direction, pattern, data, rhs, rtol, "accept")

    x = jax.lax.platform_dependent(data, true_data, rhs, jnp.asarray(rtol, rhs.dtype), cpu=on_host, default=on_device)
    return require(x, (~jnp.all(jnp.isfinite(x)), "the Newton system is singular or the state is not finite"))


def _solve(host, pattern: AssemblyPattern, data, rhs, rtol, on_failure: str):
    """The reduced system's solution (``_jaxcga_shared.sparse.spd_solve``): on the CPU ``host(data, rhs, rtol,
    indptr, indices)`` on the host, with numpy arrays (``host_call``); on a GPU a dense Cholesky factorization up to
    ``_DIRECT_DOFS`` unknowns, block-Jacobi PCG on the device to rtol above, ``on_failure`` saying what an
    unconverged one gives."""
    x = spd_solve(
        pattern.csr,
        data,
        rhs,
        rtol,
        host=host,
        on_failure=on_failure,
        what="the Newton system",
        dense_up_to=_DIRECT_DOFS,
    )
    return require(x, (~jnp.all(jnp.isfinite(x)), "the Newton system is singular or the state is not finite"))


# ---------------------------------------------------------------------------------------------------------
# the incremental potential E and its Newton minimization


class _Theta(eqx.Module):
    """The differentiable inputs of a step: E depends on them, the sparsity pattern does not."""

    x: Float[Array, "n 3"]  # x_t
    v: Float[Array, "n 3"]  # v_t
    mu: Float[Array, "*#batch"]  # Lamé parameters from Material.lame(), which checks young and poisson
    lam: Float[Array, "*#batch"]
    fixed_positions: Float[Array, "nb 3"]
    force: Float[Array, "n 3"]
    grads: Float[Array, "m 4 3"]
    volumes: Float[Array, " m"]
    mass_values: Float[Array, " k"]
    # Rayleigh damping (``Material.damping``): beta, and the elastic forces grad U(x_t) of its energy; None: undamped
    beta: Float[Array, ""] | None = None
    elastic_t: Float[Array, "n 3"] | None = None
    # a third starting point for Newton (no derivative flows to it: E does not depend on it); None: two
    guess: Float[Array, "n 3"] | None = None


def _elastic_weight(theta: _Theta, h):
    """The factor of U(x) in E: h^2, and beta h with damping."""
    return h**2 if theta.beta is None else h**2 + theta.beta * h


def _mass_times(system: FEMSystem, mass_values, d):
    """M d for the scalar mass (entries ``mass_values``) applied to each coordinate of d (n, 3), in chunks of
    entries (``_in_chunks``)."""

    def add_chunk(start, size, own, Md):
        take = _slicer(start, size)
        values = jnp.where(own, take(mass_values), 0)
        return Md.at[take(system.mass_rows)].add(values[:, None] * d[take(system.mass_cols)], indices_are_sorted=True)

    return _in_chunks(mass_values.shape[0], _MASS_CHUNK, add_chunk, jnp.zeros_like(d))


def mechanical_energy(
    system: FEMSystem, state: State, material: Material
) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
    """The energies of a state of ``system`` made of ``material``: kinetic ``1/2 v^T M v``, elastic ``U(x)``
    (eq. 9) and the potential of the external forces ``-f . x`` (gravity's, for body forces). Their sum is
    conserved by the exact dynamics; backward Euler dissipates it. Returns three scalars (JAX, differentiable).

    Args:
        system: the ``FEMSystem`` (mass matrix, external forces).
        state: the ``State`` (positions x, velocities v).
        material: the ``Material`` of the elastic energy.
    Returns:
        (kinetic, elastic, external): three scalars.
    """
    mu, lam = material.lame()
    kinetic = 0.5 * jnp.sum(state.v * _mass_times(system, system.mass_values, state.v))
    elastic = jnp.sum(element_energy(state.x[system.T], system.grads, system.volumes, mu, lam))
    return kinetic, elastic, -jnp.sum(system.force * state.x)


def _in_chunks(count: int, chunks: _Chunks, work, init):
    """``work(start, size, own, carry) -> carry`` over rows ``0:count`` in chunks of at most ``chunks.cpu`` rows
    on the CPU and ``chunks.device`` elsewhere (``jax.lax.platform_dependent``; one chunk, the whole range, when
    count is no larger); ``own`` (size,) masks the rows an earlier chunk took (the last chunk is moved back to end
    at count, so that every slice has the same size).

    Why chunks on the CPU: a step over all elements at once keeps every element's Hessian, eigensystem and gathers
    alive together (accordion's final system, 73k elements, 2M nonzeros: 337 MB of temporaries). XLA's CPU runtime
    allocates a program's temporaries afresh on every call, and glibc maps a block over 32 MB from the kernel
    and unmaps it on free: every step touched 86k new pages (a page fault and a page cleared each, in the
    kernel), and the faults of concurrent threads queue on the process's memory map. In chunks of 1,024
    elements (and 16,384 mass entries) the temporaries are 28 MB, mostly the Newton matrix's data, which glibc
    keeps in its heap: no page faults, and the step takes about half the time (benchmarks/README.md, "Element
    chunks"). A GPU's allocator keeps its memory, and its kernels want many elements at once."""

    def over(chunk: int):
        return lambda init: _over_chunks(count, chunk, work, init)

    if count <= min(chunks) or chunks.cpu == chunks.device:
        return over(chunks.cpu)(init)
    return jax.lax.platform_dependent(init, cpu=over(chunks.cpu), default=over(chunks.device))


def _over_chunks(count: int, chunk: int, work, init):
    """``_in_chunks`` with one chunk size."""
    if count <= chunk:
        return work(0, count, jnp.ones(count, bool), init)
    chunks = -(-count // chunk)
    size = -(-count // chunks)

    def body(k, carry):
        start = jnp.minimum(k * size, count - size)
        return work(start, size, start + jnp.arange(size) >= k * size, carry)

    return jax.lax.fori_loop(0, chunks, body, init)


def _energy(system: FEMSystem, x, theta: _Theta, h):
    """E(x) and a magnitude of its terms (for the line search's rounding slack)."""
    d = x - theta.x - h * theta.v
    kinetic = 0.5 * jnp.sum(d * _mass_times(system, theta.mass_values, d))
    m = system.T.shape[0]
    mu_s, lam_s = _modified_lame(theta.mu, theta.lam, x.dtype, (m,))  # theta's come from a checked Material

    def add_chunk(start, size, own, total):
        take = _slicer(start, size)
        volumes = jnp.where(own, take(theta.volumes), 0)
        return total + jnp.sum(_element_energy(x[take(system.T)], take(theta.grads), volumes, take(mu_s), take(lam_s)))

    elastic = _in_chunks(m, _ELEMENT_CHUNK, add_chunk, jnp.zeros((), x.dtype))
    work = jnp.sum(theta.force * x)
    # the elastic energy's rounding error is ~eps (mu + lam) volume whatever the strain: part of the scale
    stiffness = jnp.sum(theta.volumes * (theta.mu + theta.lam))
    weight = _elastic_weight(theta, h)
    energy = kinetic + weight * elastic - h**2 * work
    scale = kinetic + weight * (jnp.abs(elastic) + stiffness) + h**2 * jnp.abs(work)
    if theta.beta is not None:  # the damping energy's linear part, - beta h grad U(x_t) . x
        damping_work = theta.beta * h * jnp.sum(theta.elastic_t * x)
        energy, scale = energy - damping_work, scale + jnp.abs(damping_work)
    return energy, scale


def _slicer(start, size: int):
    """Rows ``start:start + size`` of an array (start may be traced)."""
    return lambda a: jax.lax.dynamic_slice_in_dim(a, start, size)


def _gradient_and_matrix(system: FEMSystem, x, theta: _Theta, h, project: bool):
    """grad E on the free DOFs (3 n_free,) and the CSR data of ``M + h^2 K`` (K projected or true), the
    element Hessians summed into the mass's data chunk by chunk (``_in_chunks``)."""

    def hessians(x, grads, volumes, mu_s, lam_s):
        g, H = _element_gradient_hessian(x, grads, volumes, mu_s, lam_s, project)
        return g, (H,)

    gradient, (data,) = _gradient_and_matrices(system, x, theta, h, hessians, 1)
    return gradient, data


def _gradient_and_matrices(system: FEMSystem, x, theta: _Theta, h, hessians, count: int):
    """grad E on the free DOFs and the CSR data of ``M + h^2 K`` for each of the ``count`` element Hessians that
    ``hessians(x, grads, volumes, mu_s, lam_s) -> (g, (H, ...))`` returns."""
    m = system.T.shape[0]
    mu_s, lam_s = _modified_lame(theta.mu, theta.lam, x.dtype, (m,))  # theta's come from a checked Material
    base, stride = system.pattern.hessian_base, system.pattern.hessian_stride

    def add_chunk(start, size, own, carry):
        forces, datas = carry
        take = _slicer(start, size)
        T, volumes = take(system.T), jnp.where(own, take(theta.volumes), 0)
        g, Hs = hessians(x[T], take(theta.grads), volumes, take(mu_s), take(lam_s))
        forces = forces.at[T.reshape(-1)].add(g.reshape(-1, 3))
        base_k, stride_k = take(base), take(stride)
        datas = tuple(add_element_hessians(d, base_k, stride_k, weight * H) for d, H in zip(datas, Hs))
        return forces, datas

    weight = _elastic_weight(theta, h)
    start = (jnp.zeros((system.n, 3), x.dtype), (system.mass_data,) * count)
    forces, datas = _in_chunks(m, _ELEMENT_CHUNK, add_chunk, start)
    d = x - theta.x - h * theta.v
    gradient = _mass_times(system, theta.mass_values, d) + weight * forces - h**2 * theta.force
    if theta.beta is not None:
        gradient = gradient - theta.beta * h * theta.elastic_t
    return restrict(system.pattern, gradient), datas


def _elastic_forces(system: FEMSystem, x, grads, volumes, mu, lam):
    """grad U(x) (n, 3), the elastic forces' negative, in chunks of elements (``_in_chunks``)."""
    m = system.T.shape[0]
    mu_s, lam_s = _modified_lame(mu, lam, x.dtype, (m,))

    def add_chunk(start, size, own, forces):
        take = _slicer(start, size)
        T, weights = take(system.T), jnp.where(own, take(volumes), 0)
        g = jax.grad(lambda y: jnp.sum(_element_energy(y, take(grads), weights, take(mu_s), take(lam_s))))(x[T])
        return forces.at[T.reshape(-1)].add(g.reshape(-1, 3))

    return _in_chunks(m, _ELEMENT_CHUNK, add_chunk, jnp.zeros((system.n, 3), x.dtype))


def _line_search(system: FEMSystem, x, step, slope, theta: _Theta, h, start):
    """The Armijo step length along ``step`` (n_free, 3) from x, whose ``_energy`` is ``start`` (E, its scale), and
    the ``_energy`` where it lands: (0, start) when no decrease is found."""
    free = system.pattern.free
    energy0, scale = start
    slack = 64 * jnp.finfo(x.dtype).eps * scale  # below this E differences are rounding

    def accepted(alpha, energy):
        return energy <= energy0 + _ARMIJO * alpha * slope + slack

    def trial(alpha):
        return _energy(system, x.at[free].add(alpha * step), theta, h)

    def cond(carry):
        alpha, (energy, _), k = carry
        return ~accepted(alpha, energy) & (k < _HALVINGS)

    def body(carry):
        alpha, _, k = carry
        return alpha / 2, trial(alpha / 2), k + 1

    one = jnp.ones((), x.dtype)
    alpha, landed, _ = jax.lax.while_loop(cond, body, (one, trial(one), 0))
    found = accepted(alpha, landed[0])
    return jnp.where(found, alpha, 0), jax.tree.map(lambda a, b: jnp.where(found, a, b), landed, start)


def _size(system: FEMSystem, x):
    """The diagonal of the bounding box of the elements' nodes (the scale of the stopping test; padded nodes, in
    no element, are left out: padding elements copy element 0)."""
    corners = x[system.T]
    extent = jnp.max(corners, axis=(0, 1)) - jnp.min(corners, axis=(0, 1))
    return jnp.maximum(jnp.sqrt(jnp.sum(extent**2)), jnp.finfo(x.dtype).tiny)


def _newton(theta: _Theta, system: FEMSystem, h, iterations: int, tolerance, line_search: bool, factored: bool):
    """The minimizer of E by at most ``iterations`` projected Newton iterations, stopped (tolerance not None) once
    an update's largest entry is at most ``tolerance`` times the body's size (``_size``); and its ``SolveStats``.
    ``factored``: each direction by CG on the true Hessian preconditioned by the factored projected one
    (``_host_factored_direction``), which converges quadratically where the projection stays active near the
    minimizer (a character's elements far from their rig shapes), where projected Newton converges linearly; with a
    single iteration (the paper's), the projected direction by the same factor (``_host_projected_direction``)."""
    free = system.pattern.free
    # start at x~ = x_t + h v_t or at x_t, whichever has the lower E: from x~ alone, one Newton iteration on a
    # violent state (large velocities) only lowers E below E(x~), far above the minimum, and the energy grows
    starts = [theta.x + h * theta.v, theta.x]  # inertial, previous: a tie keeps the inertial one
    if theta.guess is not None:  # e.g. a character's flesh carried along by its rig (a tie keeps the others)
        starts.append(theta.guess)
    starts = jnp.stack(starts).at[:, system.fixed].set(theta.fixed_positions)
    # the starts' energies in one pass over the elements (the shape gradients read once for all)
    energies = jax.vmap(lambda y: _energy(system, y, theta, h))(starts)
    best = jnp.argmin(energies[0])
    x0, e0 = starts[best], (energies[0][best], energies[1][best])
    # the paper's single iteration takes the factored projected direction (one Hessian); CG on the true Hessian
    # pays for a second one with the quadratic convergence of later iterations
    true_hessian = factored and iterations > 1
    size = _size(system, theta.x)
    dtype = np.dtype(x0.dtype)
    # without a stopping test (the paper's fixed iterations) convergence is still reported, at the dtype's default
    reported = _TOLERANCE.get(dtype, _TOLERANCE[np.dtype(np.float32)]) if tolerance is None else tolerance
    rtol_min = max(_CG_RTOL_MIN, 100 * float(jnp.finfo(dtype).eps))

    def cond(carry):
        k, _, _, _, residual, stalled = carry
        go = k < iterations
        if tolerance is not None:
            # converged, or stalled (the line search found no decrease above rounding)
            go &= (residual > tolerance) & ~stalled
        return go

    def body(carry):
        k, x, energy, first_norm, _, _ = carry
        true_data = None
        if true_hessian:
            gradient, (data, true_data) = _gradient_and_matrices(system, x, theta, h, _element_gradient_hessians, 2)
        else:
            gradient, data = _gradient_and_matrix(system, x, theta, h, project=True)
        norm = jnp.sqrt(jnp.sum(gradient**2))
        first_norm = jnp.where(k == 0, norm, first_norm)
        rtol = _CG_RTOL
        if tolerance is not None:  # converging: tighten the solves as grad E falls, for superlinear convergence
            rtol = jnp.clip(norm / first_norm, rtol_min, _CG_RTOL)
        if factored:
            step = -_factored_solve(system.pattern, data, true_data, gradient, rtol)
        else:
            step = -_solve(_host_newton_direction, system.pattern, data, gradient, rtol, "accept")
        alpha = 1
        if line_search:
            slope = jnp.dot(gradient, step, precision=EXACT)
            alpha, energy = _line_search(system, x, step.reshape(-1, 3), slope, theta, h, energy)
        x = x.at[free].add(alpha * step.reshape(-1, 3))
        residual = jnp.max(jnp.abs(step), initial=0) / size
        return k + 1, x, energy, first_norm, residual, jnp.asarray(alpha == 0)

    zero = jnp.zeros((), x0.dtype)
    start = (jnp.zeros((), jnp.int32), x0, e0, zero, jnp.asarray(jnp.inf, x0.dtype), jnp.asarray(False))
    k, x, _, _, residual, _ = jax.lax.while_loop(cond, body, start)
    return x, SolveStats(residual <= reported, k, residual)


@eqx.filter_custom_vjp
def _minimize(theta, system, h, iterations, tolerance, line_search, factored=False):
    return _newton(theta, system, h, iterations, tolerance, line_search, factored)


@_minimize.def_fwd
def _minimize_fwd(perturbed, theta, system, h, iterations, tolerance, line_search, factored=False):
    x, stats = _newton(theta, system, h, iterations, tolerance, line_search, factored)
    return (x, stats), checkpoint_name(x, _NEWTON_RESULT)


@_minimize.def_bwd
def _minimize_bwd(x, cotangents, perturbed, theta, system, h, iterations, tolerance, line_search, factored=False):
    pattern = system.pattern
    x_bar = cotangents[0]  # the stats have no derivative
    if x_bar is None:
        x_bar = jnp.zeros_like(x)

    def free_gradient(t: _Theta):  # G(x*, theta): the fixed rows of x follow theta's fixed positions
        y = x.at[system.fixed].set(t.fixed_positions)
        return restrict(pattern, jax.grad(lambda z: _energy(system, z, t, h)[0])(y))

    _, data = _gradient_and_matrix(system, x, theta, h, project=False)
    host = _host_exact if factored else _host_adjoint
    u = _solve(host, pattern, data, restrict(pattern, x_bar), _ADJOINT_RTOL, "host")
    grad = jax.vjp(free_gradient, theta)[1](-u)[0]
    grad = eqx.tree_at(lambda t: t.fixed_positions, grad, grad.fixed_positions + x_bar[system.fixed])
    return jax.tree.map(lambda g, p: g if p else None, grad, perturbed)


def _advance(
    system,
    state,
    h,
    mu,
    lam,
    fixed_positions,
    force,
    iterations,
    tolerance,
    line_search,
    beta=None,
    guess=None,
    factored: bool = False,
):
    """The step from ``state`` with Lamé parameters, the fixed nodes' new positions, the forces (n, 3), the
    Rayleigh damping beta (None: undamped), a guess of the new positions for Newton's start (None: none) and
    ``_newton``'s ``factored`` (the direction, and the adjoint solve exact, by CHOLMOD factors)."""
    elastic_t = None
    if beta is not None:  # grad U(x_t), of the step's own rest shape: a JAX function of theta's inputs
        beta = jnp.asarray(beta, state.x.dtype)
        elastic_t = _elastic_forces(system, state.x, system.grads, system.volumes, mu, lam)
    theta = _Theta(
        state.x,
        state.v,
        mu,
        lam,
        fixed_positions,
        force,
        system.grads,
        system.volumes,
        system.mass_values,
        beta,
        elastic_t,
        None if guess is None else jax.lax.stop_gradient(guess),
    )
    # theta carries every differentiable input; the rest of the system is structure
    x, stats = _minimize(theta, jax.lax.stop_gradient(system), h, iterations, tolerance, line_search, factored)
    return State(x, (x - state.x) / h, jax.lax.stop_gradient(stats))


@eqx.filter_jit
def _step(system, state, h, material, fixed_positions, iterations, tolerance, line_search):
    if fixed_positions is None:  # they stay where they are
        fixed_positions = state.x[system.fixed]
    mu, lam = material.lame()
    return _advance(
        system, state, h, mu, lam, fixed_positions, system.force, iterations, tolerance, line_search, material.damping
    )


def backward_euler_step(
    system: FEMSystem,
    state: State,
    h: float | Float[Array, ""],
    material: Material,
    fixed_positions: Float[Array | np.ndarray, "nb 3"] | None = None,
    newton_iterations: int = _NEWTON_ITERATIONS,
    tolerance: float | Literal["auto"] | None = "auto",
    line_search: bool = True,
) -> State:
    """One backward Euler step (eq. 10) of the stable neo-Hookean system (module docstring); jit-compiled,
    differentiable (reverse mode, implicitly) in state, the material, fixed_positions and the system's force,
    grads, volumes and mass_values.

    By default Newton runs to convergence, so that the implicit gradient is the derivative of the step computed.
    The paper's single iteration is ``newton_iterations=1, tolerance=None``: faster, but its gradient is the
    converged formula at an unconverged iterate, an approximation (``stats.converged`` is False).

    Args:
        system: the ``FEMSystem``.
        state: the ``State`` at time t, x and v of shape (n, 3) and the system's dtype.
        h: the positive time step.
        material: the ``Material`` (Young's modulus and Poisson's ratio, scalars or (m,) per element).
        fixed_positions: (nb, 3) positions of the fixed nodes at t + h (a moving boundary); None keeps them
            where they are, ``state.x[system.fixed]``.
        newton_iterations: the most Newton iterations (>= 1); 1 is the paper's.
        tolerance: stop once the largest entry of a Newton update is at most this fraction of the body's size
            (the diagonal of the bounding box of its elements' nodes at time t); ``"auto"``: 1e-10 in float64,
            1e-5 in float32 (what rounding lets a step reach); None: run all ``newton_iterations``.
        line_search: backtrack (Armijo) on E; False takes full Newton steps.
    Returns:
        The ``State`` at t + h: the fixed nodes at ``fixed_positions``, ``v = (x_{t+1} - x_t) / h``, and its
        ``stats`` (``SolveStats``: converged, iterations, residual).
    """
    return _step(
        *_step_arguments(system, state, h, material, fixed_positions, newton_iterations, tolerance, line_search)
    )


def _step_arguments(system, state, h, material, fixed_positions, newton_iterations, tolerance, line_search):
    """``backward_euler_step``'s checks; the arguments of ``_step``."""
    if not isinstance(system, FEMSystem) or not isinstance(state, State):
        raise ValueError("system, state: expected an FEMSystem (fem_system) and a State")
    dtype = system.grads.dtype
    for name, a in (("state.x", state.x), ("state.v", state.v)):
        if jnp.shape(a) != (system.n, 3) or jnp.result_type(a) != dtype:
            raise ValueError(
                f"{name}: expected shape ({system.n}, 3) and dtype {dtype}, got {jnp.result_type(a)} {jnp.shape(a)}"
            )
    if int(newton_iterations) != newton_iterations or newton_iterations < 1:
        raise ValueError(f"newton_iterations: expected an int >= 1, got {newton_iterations!r}")
    if isinstance(tolerance, str) and tolerance == "auto":
        tolerance = _TOLERANCE.get(np.dtype(dtype), _TOLERANCE[np.dtype(np.float32)])
    elif tolerance is not None and (isinstance(tolerance, (str, bool)) or not tolerance > 0):
        raise ValueError(f"tolerance: expected 'auto', None or a positive fraction of the size, got {tolerance!r}")
    elif tolerance is not None:
        tolerance = float(tolerance)
    if jnp.shape(h) != ():
        raise ValueError(f"h: expected a scalar time step, got shape {jnp.shape(h)}")
    material = _checked_material(material, system, dtype)
    h = _scalar(h, dtype)
    if fixed_positions is not None:
        fixed_positions = jnp.asarray(fixed_positions, dtype)
        if fixed_positions.shape != system.fixed.shape + (3,):
            raise ValueError(
                f"fixed_positions: expected shape ({system.fixed.shape[0]}, 3), got {fixed_positions.shape}"
            )
    # concrete values are checked in numpy: eager JAX checks cost a dispatch and a sync each, a large part of
    # a small system's step; traced ones by one require (one conditional), threaded through state.x
    checks = [
        (h, lambda h, xp: ~(h > 0) | ~xp.isfinite(h), "h: expected a finite positive time step"),
        (state.x, lambda a, xp: ~xp.isfinite(a), "state.x: non-finite values (NaN or inf)"),
        (state.v, lambda a, xp: ~xp.isfinite(a), "state.v: non-finite values (NaN or inf)"),
    ]
    traced = [(jnp.any(bad(a, jnp)), message) for a, bad, message in checks if isinstance(a, jax.core.Tracer)]
    for a, bad, message in checks:
        if not isinstance(a, jax.core.Tracer) and np.any(bad(np.asarray(a), np)):
            raise ValueError(message)
    state = State(require(state.x, *traced), state.v)
    return system, state, h, material, fixed_positions, int(newton_iterations), tolerance, line_search


def _checked_material(material, system: FEMSystem, dtype) -> Material:
    """``material`` with its parameters in ``dtype`` (``_scalar``), scalars or one per element of ``system``."""
    if not isinstance(material, Material):
        raise ValueError(f"material: expected an xfem.Material(young, poisson), got {type(material).__name__}")
    m = system.T.shape[0]
    for name, a in (("material.young", material.young), ("material.poisson", material.poisson)):
        if jnp.ndim(a) > 1 or (jnp.ndim(a) == 1 and jnp.shape(a) != (m,)):
            raise ValueError(f"{name}: expected a scalar or one value per element, shape ({m},), got {jnp.shape(a)}")
    # tree_map, not Material(...): its concrete checks already ran when it was made
    return jax.tree.map(lambda a: _scalar(a, dtype), material)


def _scalar(a, dtype):
    """A step's scalar or per-element parameter in ``dtype``: numpy for python and numpy values (a compiled
    call takes them at little cost, where a device_put is a large part of a small system's step), JAX for
    JAX arrays and tracers."""
    if isinstance(a, (jax.Array, jax.core.Tracer)):
        return jnp.asarray(a, dtype)
    return np.asarray(a, dtype)


def compiled_step(
    system: FEMSystem,
    state: State,
    h: float | Float[Array, ""],
    material: Material,
    newton_iterations: int = 1,
    tolerance: float | None = None,
    line_search: bool = True,
) -> Callable[[FEMSystem, State, float | Float[Array, ""], Material], State]:
    """``backward_euler_step`` compiled ahead of time (traced and compiled, not run) for systems shaped like
    ``system`` (same array shapes and static sizes, e.g. padded to one ``SystemCapacity``) and these options.

    Compiling is safe in a background thread while other steps run (it executes nothing), which is how XFEM
    prepares the step of the next capacity level before a cut needs it.

    Args:
        system: as ``backward_euler_step`` (only
            their shapes and dtypes matter, and the options' values).
        state: see ``system``.
        h: see ``system``.
        material: see ``system``.
        newton_iterations: see ``system``.
        tolerance: see ``system``.
        line_search: see ``system``.
    Returns:
        A function ``(system, state, h, material) -> State`` equal to ``backward_euler_step`` with these options
        (fixed nodes kept in place), for systems and states of the compiled shapes.
    """
    compiled = _step.lower(
        *_step_arguments(system, state, h, material, None, newton_iterations, tolerance, line_search)
    ).compile()

    def step(system: FEMSystem, state: State, h: float | Float[Array, ""], material: Material) -> State:
        return compiled(*_step_arguments(system, state, h, material, None, newton_iterations, tolerance, line_search))

    return step
