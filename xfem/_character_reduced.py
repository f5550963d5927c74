"""Real-time secondary dynamics of a character body in a subspace of skinning eigenmodes: the reduction of Fast
Complementary Dynamics (Benchekroun, Zhang, Chaudhuri, Jacobson, Kaufman 2023, sec. 4-5: "skinning eigenmodes"
with the rig carrying the modes), in its simplest form.

Subspace (``character_subspace``). With the driven nodes fixed, the generalized eigenproblem at the body's rest
configuration ``K phi = lambda M phi`` over the free DOFs, ``K`` the Hessian at rest of the stable neo-Hookean
energy for Young's modulus 1 and the given Poisson's ratio (there it is linear elasticity with the same Lamé
parameters), ``M`` the consistent mass (density ``body.density``); its ``k`` lowest pairs by shift-invert Lanczos
(scipy ``eigsh``, a small negative shift so that a part with no driven node, whose rigid motions cost no energy,
factors too). ``Phi`` (3 n_free, k) is mass-orthonormal, ``Phi^T M Phi = I``, ``Phi^T K Phi = Lambda``.

Play (``play_reduced``; ``simulate_character(..., subspace=...)`` calls it), the reduced form of
``simulate_character``'s formulation: frames k = 0..N, h = 1/fps, clip time ``t_k = start + k h``, ``S_k`` the tet
nodes skinned at t_k. The nodes are

    x_k = S_k + B_k q_k,    (B_k q)_i = R_i(t_k) (Phi q)_i,    R_i(t) = sum_j w_ij A_j(t),

``A_j(t) = L_j(t) L_j(rest)^-1`` the linear (3 x 3) part of joint j's skinning matrix at t relative to the rest
pose (the rest configuration is the skeleton's rest pose), ``w_ij`` the nodes' transferred weights: the rig carries
the modes, and the driven nodes (zero rows of Phi) follow S_k exactly. The elastic energy is that of the
displacement from the skinned shape, which the rest shape follows, ``E/2 q^T Lambda q`` (exact to second order
where the rig moves an element rigidly), with ``E`` the material's Young's modulus. Backward Euler, with the
scaled energy of the full mode (inertia, gravity ``g = body.gravity`` on the full consistent mass, and
stiffness-proportional Rayleigh damping ``beta`` integrated as ``beta h [U(q) - grad U(q_{k-1}) . q]``):

    q_k = argmin 1/2 |S_k + B_k q - x_{k-1} - h v_{k-1}|_M^2 + (h^2 + beta h) E/2 q^T Lambda q
                 - beta h E q_{k-1}^T Lambda q - h^2 (M g)^T B_k q,

one k x k solve per frame:

    (B_k^T M B_k + (h^2 + beta h) E Lambda) q_k = B_k^T M (x_{k-1} + h v_{k-1} - S_k + h^2 g) + beta h E Lambda q_{k-1},

then ``x_k = S_k + B_k q_k`` and ``v_k = (x_k - x_{k-1}) / h``. Frame 0 is the rig (q_0 = 0) with the rig's
velocity ``v_0 = (S_1 - S_0) / h``. The rig's inertia (its
acceleration through ``x_{k-1} + h v_{k-1} - S_k``) is what makes the flesh lag and jiggle; with every node driven
or a very stiff material ``q -> 0`` and the body is the skinned one. The surface is carried by the body's
embedding. The whole play is one compiled ``lax.scan``, the rig skinned and its joints' linear parts
blended inside it, frame by frame. The reduced mass ``B_k^T M B_k`` is not formed from the nodes: with
``M = m (x) I_3`` and ``R_i`` linear in the joints' ``A_j``, it is a sum over the joint pairs (j, p) that share a tet
of ``(A_j^T A_p)[c, d]`` times mass products computed once with the subspace (``CharacterSubspace.pair_mass``), so a
frame costs the pairs' 9 k^2 products rather than the nodes' 3 k^2 each (the way Fast Complementary Dynamics
precomputes its rig-carried terms).

Left out of Fast Complementary Dynamics: its rotation-strain clustered modes and cubature (the energy here is
quadratic in q, so large local rotations of the flesh relative to the rig are not corrected), its complementarity
constraint (the modes are orthogonal to nothing but the driven nodes), and its contact.
"""

from __future__ import annotations

import time
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
from jax.core import Tracer
from jaxtyping import Array, Float, Int

import deform
from _jaxcga_shared.checks import check_choice
from _jaxcga_shared.platform import EXACT
from xfem._character_body import CharacterBody
from xfem._linear_tet import consistent_mass, shape_gradients
from xfem._material import Material
from xfem._neohookean import element_gradient_hessian, lame

MODES = 24  # the default subspace size: Benchekroun et al. 2023 play their characters with 10-50 modes
POISSON = 0.4


class CharacterSubspace(NamedTuple):
    """Skinning eigenmodes of a character body (``character_subspace``; module docstring).

    Attributes:
        modes: (3 n_free, k) float64 ``Phi``, rows node-major ``[x, y, z]`` of each free node, mass-orthonormal.
        eigenvalues: (k,) float64 ``Lambda``, ascending, for Young's modulus 1: a material of modulus E swings mode j
            at the angular frequency ``sqrt(E Lambda_j)``.
        free: (n_free,) int64 the free (not driven) nodes, sorted.
        poisson: the Poisson's ratio the modes were computed for.
        density: the body's density (the mass of the modes).
        basis: (n, 3, k) float64 ``Phi`` on every node (zero rows at the driven nodes): what the play carries.
        mass_rows, mass_cols, mass_values: (nnz,) the consistent mass's entries ``M[rows, cols]`` on the free rows
            (rows index ``free``, cols every node).
        pair_joints: (P, 2) int64 the joint pairs (j, p), j <= p, that weight two free nodes coupled by the mass.
        pair_mass: (P, 3, 3, k, k) float64 their mass products ``P_jp[c, d] = sum_il m_il w_ij w_lp Phi_i[c]^T
            Phi_l[d]`` (halved where j = p), so that the reduced mass of a pose is ``B^T M B = S + S^T`` with
            ``S = sum_jp sum_cd (A_j^T A_p)[c, d] P_jp[c, d]``: a frame's cost is the pairs' (P 9 k^2), not the
            nodes'. It holds P 9 k^2 doubles (a character couples a few hundred pairs).
        lumped: (n_free,) float64 the free nodes' masses (rows of M summed): the weight of gravity.
        rest_linear: (j, 3, 3) float64 the inverses of the joints' linear parts at the rest pose, ``L_j(rest)^-1``.
        seconds: the wall time of the eigensolve and the pair products.
    """

    modes: Float[np.ndarray, "d k"]
    eigenvalues: Float[np.ndarray, " k"]
    free: Int[np.ndarray, " nf"]
    poisson: float
    density: float
    basis: Float[np.ndarray, "n 3 k"]
    mass_rows: Int[np.ndarray, " nnz"]
    mass_cols: Int[np.ndarray, " nnz"]
    mass_values: Float[np.ndarray, " nnz"]
    pair_joints: Int[np.ndarray, "P 2"]
    pair_mass: Float[np.ndarray, "P 3 3 k k"]
    lumped: Float[np.ndarray, " nf"]
    rest_linear: Float[np.ndarray, "j 3 3"]
    seconds: float


def _stiffness(X: np.ndarray, T: np.ndarray, poisson: float) -> sp.csr_matrix:
    """(3n, 3n) the stable neo-Hookean Hessian at rest for Young's modulus 1 (node-major DOFs)."""
    grads, volumes = shape_gradients(X, T)
    mu, lam = lame(1.0, poisson)
    _, H = element_gradient_hessian(jnp.asarray(X[T]), grads, volumes, mu, lam, project=False)
    dofs = (3 * T[:, :, None] + np.arange(3)).reshape(len(T), 12)
    rows = np.broadcast_to(dofs[:, :, None], (len(T), 12, 12))
    cols = np.broadcast_to(dofs[:, None, :], (len(T), 12, 12))
    K = sp.csr_matrix((np.asarray(H).ravel(), (rows.ravel(), cols.ravel())), shape=(3 * len(X), 3 * len(X)))
    return (K + K.T) * 0.5


def character_subspace(body: CharacterBody, modes: int = MODES, *, poisson: float = POISSON) -> CharacterSubspace:
    """The ``modes`` lowest skinning eigenmodes of a body, the driven nodes fixed (module docstring).

    Args:
        body: the ``CharacterBody`` (``character_body``).
        modes: the subspace size k, 1 <= k < 3 n_free.
        poisson: Poisson's ratio in (-1, 1/2) of the stiffness the modes diagonalize; the play's material must
            have the same.
    Returns:
        The ``CharacterSubspace``.
    """
    if not isinstance(body, CharacterBody):
        raise ValueError(f"body: expected a CharacterBody (xfem.character_body), got {type(body).__name__}")
    if not isinstance(poisson, (int, float, np.floating)) or not -1 < poisson < 0.5:
        raise ValueError(f"poisson: expected a Poisson's ratio in (-1, 0.5), got {poisson!r}")
    X, T = np.asarray(body.tets.X, np.float64), np.asarray(body.tets.T, np.int64)
    n = len(X)
    free = np.setdiff1d(np.arange(n), body.driven)
    if isinstance(modes, bool) or int(modes) != modes or not 1 <= modes < 3 * len(free):
        raise ValueError(
            f"modes: expected an int in [1, {3 * len(free)}) (3 x the {len(free)} free nodes), got {modes!r}"
        )
    modes = int(modes)
    start = time.perf_counter()
    dofs = (3 * free[:, None] + np.arange(3)).ravel()
    K = _stiffness(X, T, float(poisson))[dofs][:, dofs].tocsc()
    M1 = consistent_mass(X, T, body.density)
    M = sp.kron(M1[free][:, free], sp.eye(3), format="csc")
    # the shift: far below the lowest elastic eigenvalue yet enough for a part with no driven node to factor
    shift = -1e-8 * K.diagonal().sum() / M.diagonal().sum()
    values, vectors = spla.eigsh(K, k=modes, M=M, sigma=shift, which="LM")
    order = np.argsort(values)
    values, vectors = values[order], vectors[:, order]
    # eigsh's vectors are M-orthonormal to its tolerance; one Cholesky sweep makes it exact in float64
    gram = vectors.T @ (M @ vectors)
    vectors = vectors @ np.linalg.inv(np.linalg.cholesky(gram)).T
    values = np.einsum("dk,dk->k", vectors, K @ vectors)
    basis = np.zeros((n, 3, modes))
    basis[free] = vectors.reshape(len(free), 3, modes)
    model = body.node_model
    rest_linear = np.linalg.inv(np.asarray(_joint_linear(model, deform.local_matrices(model.skeleton))))
    mass_free = M1[free][:, free].tocsr()
    weights = np.zeros((n, len(rest_linear)))
    np.add.at(weights, (np.arange(n)[:, None], np.asarray(model.mesh.J)), np.asarray(model.mesh.W))
    pair_joints, pair_mass = _pair_mass(mass_free, weights[free], basis[free])
    seconds = time.perf_counter() - start
    rows = M1[free].tocoo()
    return CharacterSubspace(
        modes=vectors,
        eigenvalues=values,
        free=free.astype(np.int64),
        poisson=float(poisson),
        density=float(body.density),
        basis=basis,
        mass_rows=rows.row.astype(np.int64),
        mass_cols=rows.col.astype(np.int64),
        mass_values=rows.data,
        pair_joints=pair_joints,
        pair_mass=pair_mass,
        lumped=np.asarray(M1[free].sum(axis=1)).ravel(),
        rest_linear=rest_linear,
        seconds=seconds,
    )


def _pair_mass(mass: sp.csr_matrix, weights: np.ndarray, Phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The joint pairs and their mass products (``CharacterSubspace.pair_mass``) from the free nodes' mass
    (nf, nf), weights (nf, joints) and modes (nf, 3, k)."""
    nf, _, k = Phi.shape
    weighted = weights != 0
    # (j, p) couple where a node weighted by j and a node weighted by p share a tet
    coupled = sp.csr_matrix(weighted.T.astype(np.float64)) @ (mass != 0) @ sp.csr_matrix(weighted.astype(np.float64))
    pairs = np.argwhere(np.triu(coupled.toarray()) > 0)
    table = np.empty((len(pairs), 3, 3, k, k))
    for p in np.unique(pairs[:, 1]):
        MU = mass @ (weights[:, p, None, None] * Phi).reshape(nf, 3 * k)  # M U_p
        for row in np.flatnonzero(pairs[:, 1] == p):
            j = pairs[row, 0]
            support = np.flatnonzero(weighted[:, j])  # U_j's nonzero rows
            U = (weights[support, j, None, None] * Phi[support]).reshape(-1, 3 * k)
            block = (U.T @ MU[support]).reshape(3, k, 3, k).transpose(0, 2, 1, 3)
            table[row] = 0.5 * block if j == p else block  # S + S^T counts a pair (j, j) twice
    return pairs.astype(np.int64), table


class _Rig(eqx.Module):
    """What the compiled play takes: the node model and the subspace's arrays (traced, so a new body reuses the
    compilation of one of the same sizes)."""

    node_model: deform.RiggedModel
    rest_linear: Float[Array, "j 3 3"]  # L_j(rest)^-1
    basis: Float[Array, "nf 3 k"]
    free: Int[Array, " nf"]
    eigenvalues: Float[Array, " k"]
    mass_rows: Int[Array, " nnz"]
    mass_cols: Int[Array, " nnz"]
    mass_values: Float[Array, " nnz"]
    pair_joints: Int[Array, "P 2"]
    pair_mass: Float[Array, "P 3 3 k k"]
    lumped: Float[Array, " nf"]
    gravity: Float[Array, " 3"]
    embed_nodes: Int[Array, "s 4"]
    embed_weights: Float[Array, "s 4"]


def _joint_linear(model: deform.RiggedModel, local: Array) -> Array:
    """(j, 3, 3) the linear parts of the joint matrices of local bone matrices (b, 4, 4)."""
    globals_ = deform.forward_kinematics_matrices(model.skeleton.parents, local)
    return deform.joint_matrices(model.mesh, globals_)[:, :3, :3]


def _skin(rig: _Rig, t, method: str, clip, interpolation: str):
    """(n, 3) the nodes skinned at time t."""
    return deform.skin_model(rig.node_model, t, method, clip, interpolation)


def _joint_blend(rig: _Rig, t, clip, interpolation: str):
    """(j, 3, 3) the joints' linear parts at time t relative to the rest pose, ``A_j(t)`` (module docstring)."""
    model = rig.node_model
    if model.clips:
        local = deform.sample_pose(model, t, "lbs", clip, interpolation)
    else:
        local = deform.local_matrices(model.skeleton)
    return jnp.einsum("jab,jbc->jac", _joint_linear(model, local), rig.rest_linear, precision=EXACT)  # pyright: ignore[reportArgumentType]


def _mass_times(rig: _Rig, r, cols):
    """(nf, ...) the free rows of M r for r (n, ...) with ``cols`` the columns ``r``'s rows are."""
    products = rig.mass_values.reshape((-1,) + (1,) * (r.ndim - 1)) * r[cols]
    return jax.ops.segment_sum(products, rig.mass_rows, num_segments=rig.free.shape[0], indices_are_sorted=True)


@eqx.filter_jit
def _play(rig: _Rig, times, h, young, damping, method: str, clip, interpolation: str):
    # the rig is skinned inside the scan, frame by frame: all frames at once would hold every node's influences
    # (n x 8 transforms) for every frame
    S0 = _skin(rig, times[0], method, clip, interpolation)
    v0 = (_skin(rig, times[1], method, clip, interpolation) - S0) / h  # the rig's velocity, as the full mode's
    k = rig.eigenvalues.shape[0]
    stiffness = young * rig.eigenvalues
    gravity_force = rig.lumped[:, None] * rig.gravity[None]  # (M g) on the free rows: M's rows sum to the lumped masses
    joints, weights = rig.node_model.mesh.J[rig.free], rig.node_model.mesh.W[rig.free]

    def step(carry, t):
        x_prev, v_prev, q_prev = carry
        S_k, A_k = _skin(rig, t, method, clip, interpolation), _joint_blend(rig, t, clip, interpolation)
        R_k = jnp.einsum("ni,niab->nab", weights, A_k[joints], precision=EXACT)  # the free nodes' R_i(t_k)
        # B_k^T M B_k from the joint pairs' mass products (CharacterSubspace.pair_mass)
        G = jnp.einsum("pac,pad->pcd", A_k[rig.pair_joints[:, 0]], A_k[rig.pair_joints[:, 1]], precision=EXACT)
        S = jnp.einsum("pcd,pcdkl->kl", G, rig.pair_mass, precision=EXACT)
        A = S + S.T + jnp.diag((h**2 + damping * h) * stiffness)
        r = _mass_times(rig, x_prev + h * v_prev - S_k, rig.mass_cols) + h**2 * gravity_force
        # B_k^T r = sum_i Phi_i^T R_i^T r_i and B_k q = R_i (Phi q)_i: B_k itself (nf x 3 x k) is never formed
        b = jnp.einsum("nck,nc->k", rig.basis, jnp.einsum("nac,na->nc", R_k, r, precision=EXACT), precision=EXACT)
        q = jnp.linalg.solve(A, b + damping * h * stiffness * q_prev)
        modal = jnp.einsum("nbk,k->nb", rig.basis, q, precision=EXACT)
        x = S_k.at[rig.free].add(jnp.einsum("nab,nb->na", R_k, modal, precision=EXACT))
        v = (x - x_prev) / h
        return (x, v, q), (x, v, q)

    q0 = jnp.zeros(k, S0.dtype)
    _, (x, v, q) = jax.lax.scan(step, (S0, v0, q0), times[1:])
    x, v, q = (jnp.concatenate([a[None], b]) for a, b in ((S0, x), (v0, v), (q0, q)))
    surface = jnp.einsum("sa,fsad->fsd", rig.embed_weights, x[:, rig.embed_nodes], precision=EXACT)
    return x, v, surface, q


class ReducedPlay(NamedTuple):
    """The frames of a reduced play (``play_reduced``).

    Attributes:
        x, v: (N + 1, n, 3) the tet nodes' positions and velocities per frame.
        surface: (N + 1, s, 3) the embedded surface per frame.
        q: (N + 1, k) the modal coordinates per frame.
    """

    x: Float[Array, "f n 3"]
    v: Float[Array, "f n 3"]
    surface: Float[Array, "f s 3"]
    q: Float[Array, "f k"]


def play_reduced(
    body: CharacterBody,
    subspace: CharacterSubspace,
    times: Float[np.ndarray, " f"],
    clip: int | str | None,
    material: Material,
    method: str = "cga",
    interpolation: str = "gltf",
) -> ReducedPlay:
    """Play a clip on a body in a subspace (module docstring): ``simulate_character(..., subspace=...)``, which
    checks the clip and makes the times, calls it.

    Args:
        body: the ``CharacterBody``.
        subspace: its ``CharacterSubspace`` (``character_subspace(body, ...)``).
        times: (N + 1,) the clip times of the frames, evenly spaced (N >= 1): h = times[1] - times[0].
        clip: the clip's name or index; None for a model without clips (its rest pose).
        material: the ``Material``: a scalar Young's modulus (differentiable), the subspace's Poisson's ratio and
            the Rayleigh ``damping`` beta in seconds (None: none).
        method: the skinning method, one of ``deform.METHODS``.
        interpolation: the clip's interpolation, one of ``deform.INTERPOLATIONS``.
    Returns:
        The ``ReducedPlay`` (JAX arrays, differentiable in the material).
    """
    if not isinstance(subspace, CharacterSubspace):
        raise ValueError(
            f"subspace: expected a CharacterSubspace (xfem.character_subspace), got {type(subspace).__name__}"
        )
    n = body.tets.n_nodes
    if subspace.basis.shape[0] != n or not np.array_equal(subspace.free, np.setdiff1d(np.arange(n), body.driven)):
        raise ValueError("subspace: it was computed for another body (its free nodes differ from the body's)")
    if subspace.density != body.density:
        raise ValueError(f"subspace: computed for density {subspace.density}, the body's is {body.density}")
    check_choice("method", method, deform.METHODS)
    check_choice("interpolation", interpolation, deform.INTERPOLATIONS)
    if np.shape(material.young) != () or np.shape(material.poisson) != ():
        raise ValueError("material: the reduced mode takes a scalar Young's modulus and Poisson's ratio")
    poisson = material.poisson
    if not isinstance(poisson, Tracer) and float(np.asarray(poisson)) != subspace.poisson:
        raise ValueError(
            f"material: Poisson's ratio {float(np.asarray(poisson))} differs from the subspace's {subspace.poisson}; "
            "compute the subspace with character_subspace(body, poisson=...)"
        )
    times = np.asarray(times, np.float64)
    rig = _Rig(
        node_model=body.node_model,
        rest_linear=jnp.asarray(subspace.rest_linear),
        basis=jnp.asarray(subspace.basis[subspace.free]),
        free=jnp.asarray(subspace.free),
        eigenvalues=jnp.asarray(subspace.eigenvalues),
        mass_rows=jnp.asarray(subspace.mass_rows),
        mass_cols=jnp.asarray(subspace.mass_cols),
        mass_values=jnp.asarray(subspace.mass_values),
        pair_joints=jnp.asarray(subspace.pair_joints),
        pair_mass=jnp.asarray(subspace.pair_mass),
        lumped=jnp.asarray(subspace.lumped),
        gravity=jnp.asarray(body.gravity),
        embed_nodes=jnp.asarray(body.embedding.nodes),
        embed_weights=jnp.asarray(body.embedding.weights),
    )
    h = float(times[1] - times[0])
    damping = 0.0 if material.damping is None else material.damping
    young, damping = (jnp.asarray(a, jnp.float64) for a in (material.young, damping))
    return ReducedPlay(*_play(rig, jnp.asarray(times), jnp.asarray(h), young, damping, method, clip, interpolation))
