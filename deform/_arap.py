"""As-rigid-as-possible surface modeling with rotors: sec. VII of the CGA mesh-deformation paper
(eq. 9-13), after Sorkine & Alexa 2007, with libigl's precompute / solve split.

Two energies, libigl's two for triangle meshes, both with one rotor M_i per vertex and the cotangent
weights ``c_fe = cot(angle opposite e in f) / 2`` (``igl.cotmatrix_entries``)::

    spokes (eq. 9, 11; igl.ARAP_ENERGY_TYPE_SPOKES), the paper's:
        E(p') = sum_i sum_{j in N(i)} w_ij |v'_ij - M_i v_ij ~M_i|^2,   v_ij = p_i - p_j,
    spokes and rims (igl.ARAP_ENERGY_TYPE_SPOKES_AND_RIMS, libigl's default for triangles in 3D):
        E(p') = sum_i sum_{faces f at i} sum_{edges e of f} c_fe |v'_e - M_i v_e ~M_i|^2,

with ``w_ij = sum of c_fe over the faces of edge ij`` the off-diagonal of ``igl.cotmatrix``. A cell of the
spokes energy is its vertex's spokes; with obtuse triangles (negative weights) a cell's energy can be
negative and the iterations can fall away from a rigid map of all handles (they do on Arm5). A cell of
spokes-and-rims also holds the rims, the edges opposite the vertex: each face's term is the cotangent
(Dirichlet) energy of a piecewise-linear map, never negative whatever the angles, so E >= 0 with equality
exactly at rigid maps. Each iteration alternates

* local step: M_i maximizes ``sum_e c_e (M_i v_e ~M_i) . v'_e`` over its cell; it is the eigenvector of the
  largest eigenvalue of Horn's symmetric 4x4 matrix P built from ``S = sum_e c_e v_e v'_e^T``
  (the paper's P). A rim is a difference of two spokes (``v'_jk = v'_ik - v'_ij``), so both energies'
  S is ``sum_j y_ij v'_ij^T`` over the one-ring with precomputed y_ij (``w_ij v_ij`` for spokes). The
  eigenvector is read as the rotor ``q0 - qz e12 - qx e23 - qy e31``. Batched over all vertices in closed
  form: P is traceless, its largest eigenvalue is the largest root of the characteristic
  quartic ``l^4 - 2|S|^2 l^2 - 8 det(S) l + det(P)``, found by Newton's method from the upper bound
  ``sqrt(3) |S|_F`` (monotone for a polynomial with real roots), and the eigenvector is a column of
  the adjugate of ``P - l I`` (rank one, ``c q q^T``, when the eigenvalue is simple). The same
  eigenvalue gives the energy for free: ``E = sum c (|v'|^2 + |v|^2) - 2 sum_i l_i`` (for spokes and
  rims ``sum c |v'|^2`` over all cells is 3/2 of ``sum_ij w_ij |v'_ij|^2``: every face is in three cells).
* global step (eq. 12): ``-L p' = C`` with L the cotangent Laplacian for both energies, where
  ``C_i = 1/2 sum_j (M_i + M_j) w_ij v_ij`` (spokes) or
  ``C_i = 1/3 sum_{faces f at i} (M_i + M_j + M_k) sum_{edges e of f at i} c_fe v_e`` (spokes and rims;
  the rotors of the face's three vertices, e oriented away from i). Both are ``s (M_i u_i + sum_j M_j z_ij)``
  over the one-ring, with u_i = sum_j w_ij v_ij, so one padded gather serves both. The handle
  constraints ``p'_b = bc`` are substituted (rows and columns of b removed, their columns moved to the
  right-hand side); ``-L_ff`` is positive definite and factored once (CHOLMOD) in ``arap_precompute``.
  On a mesh of several connected parts the bridges of ``deform._parts`` join L as extra spokes (weight w_b in
  both cells for spokes; for spokes and rims 3/2 w_b in both cells, so that the cells' quadratic term is still
  3/2 of ``sum_ij w_ij |v'_ij|^2``: y_ij and z_ij get 3/2 w_b v_ij, and ``own_i``, the vector turned by M_i,
  gets the extra 1/2 w_b v_ij over u_i).
  (Eq. 13's normal equations are not needed: after substitution the system is square.)

libigl's conventions, matched with ``tolerance=None, acceleration="none"`` (checked against ``igl.arap_solve`` in
the tests, both energies): an iteration is "place the handles, local step on the current positions, global step";
``max_iter`` counts these iterations; the initial guess is the caller's U0 (libigl's default for an empty U0 is
zero; ours is the rest positions with the handles placed). ``igl.arap_solve`` fits rotations with a
single-precision 3x3 SVD: on well-shaped meshes it agrees with us to ~1e-7 of the diagonal, but cells whose
covariance is nearly singular with a reflection (det S < 0, as on Arm5) amplify its float32 error to ~1e-4.
libigl's own algorithm with its double-precision rotation fit (``igl.fit_rotations(S, False)``) gives our result
to ~1e-14 (tested).

By default the iterations stop on the fixed-point residual ``max |G(x) - x|`` over the rest diagonal (G: one
local and one global step), not on the energy (whose decrease stalls at rounding long before the positions
converge, and which the spokes energy lets go negative). Local/global converges linearly, slowly where a
rotation must spread along a long body, so its map is Anderson-accelerated (Walker & Ni 2011) with the energy as
safeguard (Peng et al. 2018): an extrapolated point is kept only if its energy is below the current one.

Gradients of the converged positions with respect to ``bc`` are implicit at the fixed point
``x* = G(x*, bc)`` (G = one local + global iteration): the adjoint ``(I - dG/dx)^T u = g`` is solved with
GMRES (lineax, restarted every 200 steps) whose matrix-vector products are vjp's of G (each one
back-substitution with the same factorization), continued where it falls short by Anderson-accelerated
iterations of ``u = (dG/dx)^T u + g``, and the gradient is ``(dG/dbc)^T u``; an adjoint that neither solves
raises an error. The loop is never unrolled.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable

import equinox as eqx
import igl
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import scipy.sparse as sp
from jax.core import Tracer
from jax.typing import DTypeLike
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from _jaxcga_shared.checks import check_choice, check_index_range, check_triangle_mesh, checked_jit, require
from _jaxcga_shared.ell import padded_rows
from _jaxcga_shared.host import to_device
from _jaxcga_shared.platform import EXACT, per_platform
from _jaxcga_shared.sparse import SparseSolver
from deform._parts import UNHANDLED, mesh_parts
from jaxcga import KINDS, Multivector, align_points, apply_to_points

ENERGIES = ("spokes_and_rims", "spokes")
ACCELERATIONS = ("anderson", "none")
_ANDERSON_MEMORY = 5  # Anderson's history: more costs a wider least squares per iteration and rarely helps


class ARAPData(eqx.Module):
    """Precomputed ARAP data (``arap_precompute``): the rest mesh as padded one-rings, each spoke's rest
    vectors for the local and the global step (the energy's) and the factored constrained Laplacian."""

    V: Float[Array, "n 3"]  # rest positions
    b: Int[Array, " nb"]  # handle vertices
    free: Int[Array, " nf"]  # the other vertices, in order
    ring: Int[Array, "n d"]  # one-ring neighbours, padded with the vertex itself (weight 0)
    w: Float[Array, "n d"]  # cotangent weights w_ij
    own: Float[Array, "n 3"]  # turned by the cell's own rotor in the global step: sum_j w_ij v_ij, v_ij = p_i - p_j
    # (plus the bridges' extra 1/2 w_b v_ij in the spokes-and-rims energy)
    y: Float[Array, "n d 3"]  # the local step's vectors y_ij: S_i = sum_j y_ij v'_ij^T
    z: Float[Array, "n d 3"]  # the global step's vectors z_ij: rhs_i = s (M_i own_i + sum_j M_j z_ij)
    degree: Float[Array, " n"]  # sum_j w_ij, the diagonal of -L
    rest_energy: Float[Array, ""]  # sum over every cell's edges of c |v|^2
    diagonal: Float[Array, ""]  # the rest bounding-box diagonal, the unit of the fixed-point residual
    solver: SparseSolver = eqx.field(static=True)  # -L_ff, factored
    n: int = eqx.field(static=True)
    energy: str = eqx.field(static=True)
    rhs_scale: float = eqx.field(static=True)  # s: 1/2 (spokes) or 1/3 (spokes and rims)
    quadratic_scale: float = eqx.field(static=True)  # sum over cells of c |v'|^2 = this x sum_ij w_ij |v'_ij|^2
    parts: int = eqx.field(static=True)  # connected parts of the mesh (deform.mesh_parts)
    handled_parts: int = eqx.field(static=True)  # those holding a handle; the others follow them


def arap_precompute(
    V: Float[ArrayLike, "n 3"],
    F: Int[ArrayLike, "m 3"],
    b: Int[ArrayLike, " nb"],
    *,
    energy: str = "spokes_and_rims",
    unhandled: str = "follow",
) -> ARAPData:
    """Precompute ARAP (cotangent weights) for a mesh with handle vertices ``b``.

    A connected part of the mesh without a handle (eyes, teeth, clothing, an inner mesh) follows the part it is
    attached or nearest to (``deform.mesh_parts``): its vertices facing that part are tied to their nearest
    vertices there by bridges, spokes of the energy like the mesh's edges (weight ``min(1, (l / length)^2)``,
    l the mean edge length; in the spokes-and-rims energy each bridge is a spoke of both its vertices' cells
    with 3/2 of that weight, so that its share of the quadratic term matches the Laplacian's). A rigid motion of
    every handle still gives that rigid map on every part, and the system is never singular.

    Args:
        V: (n, 3) rest positions.
        F: (m, 3) int triangles.
        b: (nb,) distinct int handle vertex indices, nb >= 1 (with no handle the energy has no unique
            minimizer).
        energy: ``"spokes_and_rims"`` (default; libigl's default for triangle meshes in 3D: never negative,
            so moving every handle by one rigid motion gives that rigid map) or ``"spokes"`` (the paper's
            eq. 9; with obtuse triangles it can go negative and drift away from rigid maps, as on Arm5).
        unhandled: ``"follow"`` (default: parts without a handle follow, as above) or ``"error"`` (a
            ValueError naming those parts).
    Returns:
        ``ARAPData``, the argument of ``arap_solve``."""
    check_choice("energy", energy, ENERGIES)
    check_choice("unhandled", unhandled, UNHANDLED)
    V, F = check_triangle_mesh(V, F)
    n = len(V)
    b = np.asarray(b)
    if b.ndim != 1 or len(b) == 0 or not np.issubdtype(b.dtype, np.integer):
        raise ValueError(f"b: expected a non-empty (nb,) integer array of handle vertices, got {b.dtype} {b.shape}")
    check_index_range("b", b, n, "handle")
    if len(np.unique(b)) != len(b):
        raise ValueError("b: repeated handle vertices")
    b = b.astype(np.int64)
    parts = mesh_parts(V, F, b, unhandled=unhandled, name="b")
    L = sp.csr_matrix(igl.cotmatrix(V, F))
    if len(parts.bridges):
        L = L + parts.laplacian()
    free = np.setdiff1d(np.arange(n), b)
    if len(free) == 0:
        raise ValueError("b: every vertex is a handle; nothing to solve")
    try:
        solver = SparseSolver(-L[free][:, free], symmetric=True)
    except ValueError as error:
        raise ValueError(f"F, b: the constrained Laplacian is singular: {error}") from None
    # corner k of every face: its vertex i, the other two (j1, j2) and the weights of the edges i-j1
    # (opposite j2) and i-j2 (opposite j1); the rim j1-j2 is opposite i
    C = np.asarray(igl.cotmatrix_entries(V, F))  # (m, 3): column k is the edge opposite corner k
    corners = [
        (F[:, k], F[:, (k + 1) % 3], F[:, (k + 2) % 3], C[:, (k + 2) % 3], C[:, (k + 1) % 3], C[:, k]) for k in range(3)
    ]
    i, j1, j2, c1, c2, c_rim = (np.concatenate(x) for x in zip(*corners))
    # global step: the face's share at i, its two edges at i, is turned by all three rotors of the face
    u = c1[:, None] * (V[i] - V[j1]) + c2[:, None] * (V[i] - V[j2])
    # local step: a rim is a difference of spokes, p'_j1 - p'_j2 = v'_ij2 - v'_ij1, so the cell's covariance
    # stays a sum over its spokes: the rim's c (p_j1 - p_j2) joins y_ij2 and leaves y_ij1
    rim = c_rim[:, None] * (V[j1] - V[j2])
    # the bridges, both ways: spokes of weight w_b (spokes), of 3/2 w_b in both cells (spokes and rims)
    bi, bj = parts.bridges[:, 0], parts.bridges[:, 1]
    bridge_share = 0.0 if energy == "spokes" else 0.5
    bv = parts.weights[:, None] * (V[bi] - V[bj])
    # the bridges' extra share of the own rotor's term, sum_j 1/2 w_b v_ij at both ends (spokes and rims)
    bridge_sum = np.stack([np.bincount(bi, bv[:, k], n) - np.bincount(bj, bv[:, k], n) for k in range(3)], 1)
    # one-rings from the faces' edges (not from L's nonzeros: an edge of weight 0 still has rims)
    keys, inverse = np.unique(np.concatenate([i * n + j1, i * n + j2, bi * n + bj, bj * n + bi]), return_inverse=True)

    def per_edge(values):
        return np.stack([np.bincount(inverse, values[:, k], len(keys)) for k in range(values.shape[1])], 1)

    w_edge = np.bincount(inverse, np.concatenate([c1, c2, parts.weights, parts.weights]), len(keys))
    z_edge = per_edge(np.concatenate([u, u, 1.5 * bv, -1.5 * bv]))
    rim_edge = per_edge(np.concatenate([-rim, rim, bridge_share * bv, -bridge_share * bv]))
    ring, (w, z, rim) = padded_rows(keys // n, keys % n, [w_edge, z_edge, rim_edge], n)
    wv = w[..., None] * (V[:, None, :] - V[ring])
    if energy == "spokes":
        y, z, rhs_scale, quadratic_scale = wv, wv, 0.5, 1.0
    else:
        # every face's edges are in three cells; sum_ij w_ij |v'_ij|^2 counts every edge twice
        y, rhs_scale, quadratic_scale = wv + rim, 1.0 / 3.0, 1.5
    # put on the device as they are (jnp.asarray would compile a copy per array and shape: a run's lowerings)
    return ARAPData(
        V=to_device(V),
        b=to_device(b),
        free=to_device(free),
        ring=to_device(ring),
        w=to_device(w),
        own=to_device(wv.sum(1) + bridge_share * bridge_sum),
        y=to_device(y),
        z=to_device(z),
        degree=to_device(w.sum(1)),
        rest_energy=to_device(quadratic_scale * np.einsum("ndk,ndk->", wv, V[:, None, :] - V[ring])),
        diagonal=to_device(np.linalg.norm(np.ptp(V, axis=0))),
        solver=solver,
        n=n,
        energy=energy,
        rhs_scale=rhs_scale,
        quadratic_scale=quadratic_scale,
        parts=parts.count,
        handled_parts=int(parts.handled.sum()),
    )


def _entries(a):
    """The entries ``a[..., i, j]`` of (..., r, c) matrices as nested lists, sliced by lax: the cofactor formulas
    below index them hundreds of times, and numpy-style indexing would trace a gather for each."""
    rows = [jax.lax.index_in_dim(a, i, a.ndim - 2, keepdims=False) for i in range(a.shape[-2])]
    return [[jax.lax.index_in_dim(r, j, r.ndim - 1, keepdims=False) for j in range(a.shape[-1])] for r in rows]


def _det3_of(e):
    """The determinant of 3 x 3 matrices given by their entries ``e[i][j]``."""
    return (
        e[0][0] * (e[1][1] * e[2][2] - e[1][2] * e[2][1])
        - e[0][1] * (e[1][0] * e[2][2] - e[1][2] * e[2][0])
        + e[0][2] * (e[1][0] * e[2][1] - e[1][1] * e[2][0])
    )


def _det3(a):
    return _det3_of(_entries(a))


def _adjugate_and_det4(a):
    """Adjugate (transpose of the cofactor matrix) and determinant of (..., 4, 4) matrices."""
    e = _entries(a)
    idx = [[k for k in range(4) if k != i] for i in range(4)]
    cof = [
        [(-1.0) ** (i + j) * _det3_of([[e[r][c] for c in idx[j]] for r in idx[i]]) for j in range(4)] for i in range(4)
    ]
    adjugate = jnp.stack([jnp.stack([cof[j][i] for j in range(4)], -1) for i in range(4)], -2)
    return adjugate, sum(e[0][j] * cof[0][j] for j in range(4))


@per_platform("deform.largest_quartic_root")
def _largest_quartic_root(c2, c1, c0, start, *, newton_steps: int, cpu: bool):
    """The largest root of ``l^4 + c2 l^2 + c1 l + c0`` by Newton from ``start`` (above it), elementwise. A rolled
    loop on the CPU (unrolled, differentiating the steps compiled 3x slower there and ran no faster); unrolled
    elsewhere, where each step of a loop is its own launches (3 on an H100, 72 an ARAP iteration) and the
    unrolled steps are one kernel."""

    def newton(_, lam):
        p = ((lam * lam + c2) * lam + c1) * lam + c0
        dp = (4.0 * lam * lam + 2.0 * c2) * lam + c1
        # from above the largest root Newton decreases monotonically; dp > 0 there (dp = 0: at a multiple root)
        return jnp.where(dp > 0, lam - p / jnp.where(dp > 0, dp, 1.0), lam)

    return jax.lax.fori_loop(0, newton_steps, newton, start, unroll=1 if cpu else True)


def horn_rotors(S: Float[Array, "n 3 3"], newton_steps: int = 24) -> tuple[Multivector, Float[Array, " n"]]:
    """Rotors maximizing ``sum_j w_j (M v_j ~M) . v'_j`` for ``S = sum_j w_j v_j v'_j^T`` (sec. VII):
    the top eigenvector of Horn's matrix P, in closed form (Newton on the characteristic quartic,
    then the adjugate of ``P - l I``).

    Args:
        S: (n, 3, 3) covariances ``sum_j w_j v_j v'_j^T``, one per cell.
        newton_steps: Newton iterations on the characteristic quartic.
    Returns:
        The rotors (a rotor Multivector, batch (n,)) and the largest eigenvalues l (n,)."""
    sxx, sxy, sxz = S[:, 0, 0], S[:, 0, 1], S[:, 0, 2]
    syx, syy, syz = S[:, 1, 0], S[:, 1, 1], S[:, 1, 2]
    szx, szy, szz = S[:, 2, 0], S[:, 2, 1], S[:, 2, 2]
    P = jnp.stack(
        [
            jnp.stack([sxx + syy + szz, syz - szy, szx - sxz, sxy - syx], -1),
            jnp.stack([syz - szy, sxx - syy - szz, sxy + syx, szx + sxz], -1),
            jnp.stack([szx - sxz, sxy + syx, -sxx + syy - szz, syz + szy], -1),
            jnp.stack([sxy - syx, szx + sxz, syz + szy, -sxx - syy + szz], -1),
        ],
        -2,
    )
    norm2 = jnp.sum(S * S, axis=(1, 2))
    c2, c1 = -2.0 * norm2, -8.0 * _det3(S)
    _, c0 = _adjugate_and_det4(P)

    lam = _largest_quartic_root(c2, c1, c0, jnp.sqrt(3.0 * norm2), newton_steps=newton_steps)
    adj, _ = _adjugate_and_det4(P - lam[:, None, None] * jnp.eye(4, dtype=S.dtype)[None])
    # adj = c q q^T: its column with the largest diagonal entry is the best-conditioned copy of q
    diag = jnp.abs(jnp.diagonal(adj, axis1=-2, axis2=-1))
    k = jnp.argmax(diag, axis=-1)
    q = jnp.take_along_axis(adj, k[:, None, None], axis=-1)[..., 0]
    length = jnp.linalg.norm(q, axis=-1)
    # S = 0 or a multiple top eigenvalue (no unique rotation, e.g. collinear spokes): keep the identity
    ok = diag.max(-1) > 1e-24 * jnp.maximum(norm2, jnp.finfo(S.dtype).tiny) ** 1.5
    q = jnp.where(ok[:, None], q / jnp.where(ok, length, 1.0)[:, None], jnp.array([1.0, 0, 0, 0], S.dtype))
    q = q * jnp.where(q[:, :1] < 0, -1.0, 1.0)
    rotor = Multivector(jnp.stack([q[:, 0], -q[:, 3], q[:, 2], -q[:, 1]], -1), KINDS["rotor"])  # q0 - qz e12 - ...
    return rotor, lam


def _local(data: ARAPData, x):
    """Local step: rotors of all cells and the energy E(x) = min over rotors."""
    spokes = x[:, None, :] - x[data.ring]
    rotors, lam = horn_rotors(jnp.einsum("ndk,ndl->nkl", data.y, spokes, precision=EXACT))
    quadratic = data.quadratic_scale * jnp.einsum("nd,ndk,ndk->", data.w, spokes, spokes, precision=EXACT)
    return rotors, quadratic + data.rest_energy - 2.0 * jnp.sum(lam)


def _global_system(data: ARAPData, rotors: Multivector, bc):
    """The global step's (eq. 12) right-hand side over the free vertices, the handles substituted, and the
    positions with the handles set (the free rows to be filled by the solve)."""
    own = apply_to_points(rotors, data.own, fused=True)
    neighbours = Multivector(rotors.values[data.ring], rotors.blades)
    rhs = data.rhs_scale * (own + jnp.sum(apply_to_points(neighbours, data.z, fused=True), axis=1))
    y = jnp.zeros((data.n, 3), bc.dtype).at[data.b].set(bc)
    Ly = data.degree[:, None] * y - jnp.einsum("nd,ndk->nk", data.w, y[data.ring], precision=EXACT)  # -L y
    return (rhs - Ly)[data.free], y


def _global(data: ARAPData, rotors: Multivector, bc, previous):
    """Global step (eq. 12) with the handles substituted; ``previous`` positions are the device solve's first
    guess (an iterative solve from them stops sooner as the iterations converge)."""
    rhs, y = _global_system(data, rotors, bc)
    return y.at[data.free].set(data.solver(rhs, previous[data.free]))


def default_tolerance(dtype: DTypeLike) -> float:
    """``arap_solve``'s default tolerance for positions of ``dtype``: 50 ulps of the diagonal (1.1e-14 in float64,
    6.0e-6 in float32), above the rounding floor of the fixed-point residual and tight enough for central
    differences of the converged positions to match the implicit gradient to 1e-6.

    Args:
        dtype: the positions' float dtype.
    Returns:
        The tolerance, relative to the rest bounding-box diagonal.
    """
    return 50.0 * float(jnp.finfo(dtype).eps)


def _residual(data: ARAPData, f):
    return jnp.max(jnp.abs(f)) / data.diagonal.astype(f.dtype)


def _anderson(g, f, dG, dF):
    """Anderson's extrapolation ``g - sum_k gamma_k dG_k`` with gamma minimizing ``|f - sum_k gamma_k dF_k|``
    (unused history slots are zero and get zero weight; near-dependent ones are cut by the pseudo-inverse)."""
    A = dF.reshape(dF.shape[0], -1).T
    rcond = float(jnp.finfo(f.dtype).eps) ** 0.5
    gamma = jnp.linalg.lstsq(A, f.ravel(), rcond=rcond)[0]
    return g - jnp.tensordot(gamma, dG, axes=1, precision=EXACT)


# One iteration is split at its linear solve: ``_before_solve`` (Anderson's candidate, the local step, the global
# step's right-hand side) and ``_after_solve`` (the solved positions placed). The compiled loop runs both with the
# solver between them in one while loop; ``arap_solve(..., host_loop=True)`` runs them compiled apart, calling
# CHOLMOD on the host between them, so that no compiled piece holds a host callback.
# state: (x, energy, g = G(x), f = g - x, previous (g, f), history, energies, k)


def _start(data, bc, V0, max_iterations, memory):
    """The first iteration up to its solve: (its partial state, the global system (rhs, y), the solve's guess)."""
    x0 = V0.at[data.b].set(bc)
    rotors, energy = _local(data, x0)
    energies = jnp.full((max_iterations + 1,), jnp.nan, energy.dtype).at[0].set(energy)
    history = jnp.zeros((2, max(memory, 1)) + x0.shape, bc.dtype)  # the last differences of G(x) and G(x) - x
    return (x0, energy, history, energies, jnp.asarray(0)), _global_system(data, rotors, bc), x0


def _started(data, partial, y, x_free):
    """The state after the first iteration's solve (``x_free``: the free vertices' positions)."""
    x0, energy, history, energies, k = partial
    g = y.at[data.free].set(x_free)
    return x0, energy, g, g - x0, jnp.stack([g, g - x0]), history, energies, k


def _before_solve(data, bc, memory, state):
    """An iteration up to its solve: (its partial state, the global system (rhs, y), the solve's guess)."""
    x, energy, g, f, previous, history, energies, k = state
    if memory == 0:
        x, (rotors, energy) = g, _local(data, g)
    else:
        # a new pair of differences once there is a previous iterate, into the oldest slot
        delta = jnp.stack([g - previous[0], f - previous[1]])
        history = history.at[:, k % memory].set(jnp.where(k > 0, delta, history[:, k % memory]))
        candidate = _anderson(g, f, history[0], history[1])
        rotors_a, energy_a = _local(data, candidate)
        x, rotors, energy = jax.lax.cond(
            energy_a <= energy,
            lambda: (candidate, rotors_a, energy_a),
            lambda: (g, *_local(data, g)),
        )
    partial = (x, energy, jnp.stack([g, f]), history, energies.at[k + 1].set(energy), k + 1)
    return partial, _global_system(data, rotors, bc), x


def _after_solve(data, partial, y, x_free):
    """The state after an iteration's solve."""
    x, energy, previous, history, energies, k = partial
    g = y.at[data.free].set(x_free)
    return x, energy, g, g - x, previous, history, energies, k


def _go_on(data, max_iterations, tolerance, state):
    """Whether another iteration runs (the tolerance not yet met, iterations left)."""
    k, f = state[7], state[3]
    if tolerance is None:  # static: run every iteration
        return k + 1 < max_iterations
    return (k + 1 < max_iterations) & (_residual(data, f) > tolerance)


def _result(data, state):
    """(U, energies, iterations, residual) of the last state: the energy after the last iteration, at U."""
    _, _, U, f, _, _, energies, k = state
    return U, energies.at[k + 1].set(_local(data, U)[1]), k + 1, _residual(data, f)


def _solved(data, system, guess):
    rhs, _ = system
    return data.solver(rhs, guess[data.free])


def _iterate(data, bc, V0, max_iterations, tolerance, memory, progress=None):
    """Local/global iterations from V0, Anderson-accelerated when ``memory`` > 0, until the fixed-point residual
    ``max |G(x) - x| / diagonal`` is at most ``tolerance`` (None: exactly ``max_iterations``). Each iteration ends
    with a global step; an Anderson point is kept only if its energy is below the current one (else the plain
    step's), so the energy never increases (Peng et al. 2018, "Anderson acceleration for geometry optimization
    and physics simulation", Alg. 2)."""
    partial, system, guess = _start(data, bc, V0, max_iterations, memory)
    state = _started(data, partial, system[1], _solved(data, system, guess))

    def body(state):
        partial, system, guess = _before_solve(data, bc, memory, state)
        state = _after_solve(data, partial, system[1], _solved(data, system, guess))
        if progress is not None:  # static: no callback compiled in without one
            jax.debug.callback(progress, state[7] + 1, state[1], _residual(data, state[3]), ordered=True)
        return state

    if progress is not None:  # the first iteration, before the loop
        jax.debug.callback(progress, 1, state[1], _residual(data, state[3]), ordered=True)
    state = jax.lax.while_loop(functools.partial(_go_on, data, max_iterations, tolerance), body, state)
    return _result(data, state)


def _iterate_on_host(data, bc, V0, max_iterations, tolerance, memory, progress=None, runner=None):
    """``_iterate`` with its loop and its solves on the host: one compiled call between two solves (no host
    callback in it), CHOLMOD called directly between them. ``runner(name, step, *args)`` runs each compiled step
    (``arap_solve``'s ``runner``), on the data without its factor, which no step reads."""
    run = _call if runner is None else runner
    arrays = _without_factor(data)
    statics = (max_iterations, tolerance, memory)
    if V0 is None:
        V0 = run("arap_aligned_rest", _aligned_rest, arrays, bc)
    partial, (rhs, y) = run("arap_start", _start_on_host, arrays, bc, V0, *statics)
    first = np.asarray(True)  # an array: one program for the first solve and the others
    while True:
        x_free = data.solver.host_solve(np.asarray(rhs)).astype(bc.dtype)
        state, go_on, residual, partial, (rhs, y) = run(
            "arap_between_solves", _between_solves, arrays, bc, partial, y, x_free, first, *statics
        )
        if progress is not None:
            progress(state[7] + 1, state[1], residual)
        first = np.asarray(False)
        if not go_on:
            return run("arap_result", _result_on_host, arrays, state)


def _call(name: str, step, *args):
    return step(*args)


def _without_factor(data: ARAPData) -> ARAPData:
    """``data`` with no solver: what the host loop's compiled steps read, a tree of arrays and values (the factor,
    an object hashed by identity, would make every new ARAPData a new program)."""
    return dataclasses.replace(data, solver=None)


@functools.partial(jax.jit, static_argnums=(3, 4, 5))
def _start_on_host(data, bc, V0, max_iterations, tolerance, memory):
    """``_start`` with its partial state shaped as ``_before_solve``'s (``previous`` set after the solve)."""
    (x0, energy, history, energies, k), system, _ = _start(data, bc, V0, max_iterations, memory)
    return (x0, energy, jnp.zeros((2,) + x0.shape, x0.dtype), history, energies, k), system


@functools.partial(jax.jit, static_argnums=(6, 7, 8))
def _between_solves(data, bc, partial, y, x_free, first, max_iterations, tolerance, memory):
    """The state after a solve (the first iteration's when ``first``: a traced flag, one executable for all),
    whether another iteration runs, its residual, and the next iteration up to its solve."""
    x, energy, g, f, previous, history, energies, k = _after_solve(data, partial, y, x_free)
    state = (x, energy, g, f, jnp.where(first, jnp.stack([g, f]), previous), history, energies, k)
    partial, system, _ = _before_solve(data, bc, memory, state)
    return state, _go_on(data, max_iterations, tolerance, state), _residual(data, f), partial, system


_result_on_host = jax.jit(_result)


@eqx.filter_custom_vjp
def _solve(bc, data, V0, max_iterations, tolerance, memory, progress):
    return _iterate(data, bc, V0, max_iterations, tolerance, memory, progress)


@_solve.def_fwd
def _solve_fwd(perturbed, bc, data, V0, max_iterations, tolerance, memory, progress):
    out = _iterate(data, bc, V0, max_iterations, tolerance, memory, progress)
    return out, out[0]


@_solve.def_bwd
def _solve_bwd(x, grads, perturbed, bc, data, V0, max_iterations, tolerance, memory, progress):
    g = grads[0]
    if g is None:
        return None

    def step(x, bc):
        return _global(data, _local(data, x)[0], bc, x)

    _, vjp = jax.vjp(step, x, bc)
    # (I - dG/dx)^T u = g; the handle rows of G do not depend on x, so the system is regular
    operator = lx.FunctionLinearOperator(lambda u: u - vjp(u)[0], jax.ShapeDtypeStruct(x.shape, x.dtype))
    # a long restart: on multi-part characters (weak bridges, contraction near 1) short restarts stagnate
    solver = lx.GMRES(rtol=_ADJOINT_RTOL, atol=0.0, restart=200, max_steps=2000)
    u = lx.linear_solve(operator, g, solver, throw=False).value
    # where GMRES still fell short, the adjoint fixed point u = (dG/dx)^T u + g, Anderson-accelerated as the
    # forward (it contracts at the forward's rate), continues from its value; it stops at once where GMRES met rtol
    u, relative = _adjoint_fixed_point(lambda u: vjp(u)[0] + g, u, g, memory or _ANDERSON_MEMORY)
    u = eqx.error_if(
        u,
        ~(relative <= _ADJOINT_RTOL),
        "arap_solve's gradient: the adjoint system (I - dG/dx)^T u = g did not converge (GMRES, then "
        f"{_ADJOINT_ITERATIONS} Anderson iterations); the forward solve is likely not at a fixed point",
    )
    return vjp(u)[1]


_ADJOINT_RTOL = 1e-10  # relative 2-norm residual of the adjoint system
_ADJOINT_ITERATIONS = 5000


def _adjoint_fixed_point(H, u, g, memory):
    """Anderson-accelerated iterations of the linear fixed point u = H(u) from ``u`` until
    ``|H(u) - u| <= _ADJOINT_RTOL |g|`` (2-norms) or ``_ADJOINT_ITERATIONS``: (u, the relative residual)."""
    scale = jnp.linalg.norm(g)
    scale = jnp.where(scale > 0, scale, 1.0)
    h = H(u)
    history = jnp.zeros((2, memory) + u.shape, u.dtype)

    def cond(state):
        _, _, f, _, _, k = state
        return (k < _ADJOINT_ITERATIONS) & ~(jnp.linalg.norm(f) <= _ADJOINT_RTOL * scale)

    def body(state):
        u, h, f, previous, history, k = state
        delta = jnp.stack([h - previous[0], f - previous[1]])
        history = history.at[:, k % memory].set(jnp.where(k > 0, delta, history[:, k % memory]))
        u = _anderson(h, f, history[0], history[1])
        h = H(u)
        return u, h, h - u, jnp.stack([h, h - u]), history, k + 1

    state = (u, h, h - u, jnp.stack([h, h - u]), history, jnp.asarray(0))
    u, _, f, _, _, _ = jax.lax.while_loop(cond, body, state)
    return u, jnp.linalg.norm(f) / scale


class ARAPResult(eqx.Module):
    """``arap_solve``'s output.

    Attributes:
        U: (n, 3) deformed positions.
        energies: (max_iterations + 1,) the energy at the positions each iteration starts from and, at index
            ``iterations``, at U; NaN past it (not differentiated).
        iterations: () local/global iterations done (each ends with a global step).
        residual: () the last iteration's fixed-point residual ``max |G(x) - x|`` over the rest bounding-box
            diagonal (G: one local and one global step; U = G(x)).
        converged: () bool, whether ``residual`` met the tolerance (the dtype's default tolerance when the
            iterations were fixed, ``tolerance=None``).
    """

    U: Float[Array, "n 3"]
    energies: Float[Array, " k1"]
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    converged: Bool[Array, ""]


@checked_jit  # one compiled call, not the alignment's operations dispatched one by one
def _aligned_rest(data: ARAPData, bc) -> Float[Array, "n 3"]:
    rest = data.V.astype(bc.dtype)
    if len(data.b) < 3:
        return rest
    return apply_to_points(align_points(rest[data.b], bc), rest)


_DEFAULT = "default"


def arap_solve(
    data: ARAPData,
    bc: Float[ArrayLike, "nb 3"],
    *,
    V0: Float[ArrayLike, "n 3"] | None = None,
    max_iterations: int = 1000,
    tolerance: float | str | None = _DEFAULT,
    acceleration: str = "anderson",
    progress: Callable[[Array, Array, Array], object] | None = None,
    host_loop: bool = False,
    runner: Callable | None = None,
) -> ARAPResult:
    """Deform the mesh so that the handles ``data.b`` sit at ``bc``, as rigidly as possible.

    By default the iterations run until the positions are a fixed point of the local/global map to
    ``tolerance``, Anderson-accelerated (local/global alone converges linearly, slowly where a rotation must
    spread along a long body), so that U and its implicit gradient are those of the energy's minimizer.

    Args:
        data: ``arap_precompute``'s output.
        bc: (nb, 3) handle positions, in the order of ``b``.
        V0: (n, 3) initial guess; the handles are placed on it. Default: the rest positions moved by the
            motor that best aligns the handles' rest positions with ``bc`` (Horn's method, ``align_points``;
            the rest positions with fewer than 3 handles), so that a rigid motion of every handle gives that
            rigid map at once and the iterations only have to find the non-rigid part.
        max_iterations: at most this many local/global iterations (libigl's ``max_iter``); when they run out
            before the tolerance is met, ``converged`` is False.
        tolerance: stop when the fixed-point residual ``max |G(x) - x|`` is at most ``tolerance`` times the rest
            bounding-box diagonal. ``"default"``: ``default_arap_tolerance(dtype)`` (1.1e-14 in float64, 6.0e-6
            in float32). None: no tolerance, exactly ``max_iterations`` iterations, libigl-like (with
            ``acceleration="none"``, libigl's algorithm); its U is then approximate, and so is its gradient
            (implicit, at a fixed point U is not).
        acceleration: ``"anderson"`` (default: Anderson acceleration of the local/global map with the last 5
            iterates, safeguarded by the energy, which never increases) or ``"none"`` (plain local/global
            iterations, as libigl).
        progress: None, or a function called on the host after each iteration with three () arrays: the
            iteration's number (from 1), the energy at the positions it started from and its fixed-point residual
            (``ARAPResult.residual``'s measure), in order, also under ``jit`` (``jax.debug.callback``); for a
            progress bar.
        host_loop: run the iterations from Python, on concrete input only (not under jit, vmap or grad): each
            iteration's compiled pieces before and after its sparse solve hold no host callback, so that JAX's
            persistent compilation cache keeps them, and the solve calls CHOLMOD directly between them (a few
            microseconds of dispatch more per iteration). The same iterations and result; not differentiable.
        runner: with ``host_loop``, how its compiled steps run: None calls them; else a function
            ``runner(name, step, *args)`` that returns ``step(*args)`` by its own means, e.g. programs kept between
            processes (the command line's ``jax.export`` cache). ``step`` is a function JAX can trace; the arguments
            are arrays, trees of arrays (the ARAP data without its factor) and hashable values; ``name`` is a
            stable name of the step.
    Returns:
        ``ARAPResult(U, energies, iterations, residual, converged)``. U is differentiable (reverse mode) with
        respect to bc, implicitly at the fixed point, so its gradient is exact when the solve has converged;
        the other fields are not differentiated. jit and vmap work (the sparse solve runs one batch element at
        a time)."""
    if not isinstance(data, ARAPData):
        raise ValueError("data: expected the ARAPData returned by arap_precompute")
    bc = jnp.asarray(bc)
    if bc.shape != (len(data.b), 3) or not jnp.issubdtype(bc.dtype, jnp.floating):
        raise ValueError(f"bc: expected float handle positions of shape ({len(data.b)}, 3), got {bc.dtype} {bc.shape}")
    if runner is not None and not (host_loop and callable(runner)):
        raise ValueError("runner: expected a function, with host_loop=True (the compiled loop has no steps to run)")
    if V0 is None and not host_loop:  # the host loop aligns the rest by its runner
        V0 = _aligned_rest(data, bc)
    if V0 is not None:
        V0 = jnp.asarray(V0, bc.dtype)
        if V0.shape != (data.n, 3):
            raise ValueError(f"V0: expected shape ({data.n}, 3), got {V0.shape}")
    if not isinstance(max_iterations, (int, np.integer)) or max_iterations < 1:
        raise ValueError(f"max_iterations: expected an int >= 1, got {max_iterations!r}")
    check_choice("acceleration", acceleration, ACCELERATIONS)
    if isinstance(tolerance, str):
        check_choice("tolerance", tolerance, (_DEFAULT,))
        tolerance = default_tolerance(bc.dtype)
    elif tolerance is not None:
        if isinstance(tolerance, bool) or not isinstance(tolerance, (float, int, np.floating, np.integer)):
            raise ValueError(f"tolerance: expected a float > 0, None or 'default', got {tolerance!r}")
        if not tolerance > 0:
            raise ValueError(f"tolerance: expected > 0 (None for a fixed number of iterations), got {tolerance!r}")
        tolerance = float(tolerance)
    # concrete handles are checked by numpy: no eager operations to compile (a command's run)
    finite = jnp.all(jnp.isfinite(bc)) if isinstance(bc, Tracer) else np.all(np.isfinite(np.asarray(bc)))
    bc = require(bc, (~finite, "bc: non-finite handle positions"))
    memory = _ANDERSON_MEMORY if acceleration == "anderson" else 0
    # the fixed point does not depend on the initial guess: no gradient flows to V0
    if progress is not None and not callable(progress):
        raise ValueError(f"progress: expected None or a function, got {type(progress).__name__}")
    if host_loop:
        if any(isinstance(a, Tracer) for a in (bc, V0)):
            raise ValueError("host_loop: runs on concrete input only, not under jit, vmap or grad")
        U, energies, iterations, residual = _iterate_on_host(
            data, bc, V0, int(max_iterations), tolerance, memory, progress, runner
        )
    else:
        U, energies, iterations, residual = _solve(
            bc, data, jax.lax.stop_gradient(V0), int(max_iterations), tolerance, memory, progress
        )
    residual = jax.lax.stop_gradient(residual)
    converged = residual <= (default_tolerance(bc.dtype) if tolerance is None else tolerance)
    return ARAPResult(U, jax.lax.stop_gradient(energies), iterations, residual, converged)
