"""Stable neo-Hookean elasticity (Smith, de Goes & Kim 2018, "Stable Neo-Hookean Flesh Simulation", ACM TOG
37(2), cited [SGK18] in sec. 5 of the XFEM paper, whose scenes use E = 1e6, nu = 0.4): energy density, first
Piola-Kirchhoff stress, and per-tetrahedron energy, gradient and PSD-projected Hessian for the backward
Euler solve (eq. 10 of the XFEM paper).

Energy density ([SGK18] eq. 14, sec. 3.4), with ``I_C = |F|_F^2`` and ``J = det F``::

    Psi(F) = mu'/2 (I_C - 3) + lam'/2 (J - alpha)^2 - mu'/2 log(I_C + 1) - Psi_0,
    alpha  = 1 + mu'/lam' - mu'/(4 lam') = 1 + 3 mu' / (4 lam'),
    Psi_0  = lam'/2 (1 - alpha)^2 - mu'/2 log 4.

``alpha`` makes the rest state stress free, ``P(I) = 0``; the constant ``Psi_0`` (no force, no stiffness)
makes ``Psi(I) = 0``. The log term keeps the energy, its stress and its Hessian finite for every F,
inverted (J < 0) and collapsed (F = 0) included. Computed as the equal

    Psi(F) = mu'/2 (e - log(1 + e/4)) + lam'/2 (J - 1)^2 - 3/4 mu' (J - 1),   e = I_C - 3,

(``lam' (1 - alpha) = -3/4 mu'``), which has no cancellation of large terms near rest: ``Psi(I) = 0`` and
``P(I) = 0`` hold exactly in floating point. (The paper is not among /work/shared/papers; its formulas
are re-derived here and checked against autodiff and hand-derived closed forms by the tests.)

Lamé mapping ([SGK18] sec. 3.4, after eq. 14): with ``(mu, lam)`` the Lamé parameters of the wanted linear material
(``lame(young, poisson)``), ``mu' = 4/3 mu`` and ``lam' = lam + 5/6 mu``. Derivation: the stress is

    P(F) = mu' (1 - 1/(I_C + 1)) F + lam' (J - alpha) cof F,

and its derivative at F = I in a direction eps is, using ``d cof F = tr(eps) I - eps^T`` at I,
``1 - alpha = -3 mu'/(4 lam')`` and ``d(1/(I_C + 1)) = -2 tr(eps)/16``,

    dP = 3/4 mu' (eps + eps^T) + (lam' - 5/8 mu') tr(eps) I.

Matching linear elasticity ``2 mu sym(eps) + lam tr(eps) I`` gives ``3/2 mu' = 2 mu`` and
``lam' - 5/8 mu' = lam``, i.e. the mapping above (and the skew part of eps, an infinitesimal rotation,
gives no stress). For ``-1 < nu < 1/2``, ``lam' = E (5 + 2 nu) / (12 (1 + nu)(1 - 2 nu)) > 0``.

Stiffness ``dP/dF`` (9 x 9, F flattened row-major, ``f = vec F``, ``g = vec cof F``, ``H_J`` the Hessian of
det, ``d^2 J / dF_ij dF_kl = eps_ikm eps_jln F_mn``)::

    dP/dF = mu' (1 - 1/(I_C + 1)) Id + 2 mu'/(I_C + 1)^2 f f^T + lam' g g^T + lam' (J - alpha) H_J.

Its eigensystem in closed form ([SGK18] sec. 4): with the rotation-variant SVD ``F = U diag(s) V^T``
(U, V rotations, s_3 carries the sign of J) and ``c = mu' (1 - 1/(I_C + 1))``, ``b = lam' (J - alpha)``,

* 3 twist modes ``U (e_i e_j^T - e_j e_i^T) V^T / sqrt 2``: eigenvalue ``c + b s_k``,
* 3 flip modes ``U (e_i e_j^T + e_j e_i^T) V^T / sqrt 2``: eigenvalue ``c - b s_k``
  ({i, j, k} = {0, 1, 2}),
* 3 scaling modes ``U diag(q) V^T`` with (lambda, q) the eigenpairs of the symmetric 3 x 3 matrix
  ``c Id + 2 mu'/(I_C + 1)^2 s s^T + lam' h h^T + b [[0, s_2, s_1], [s_2, 0, s_0], [s_1, s_0, 0]]``,
  ``h = (s_1 s_2, s_0 s_2, s_0 s_1)`` (solved numerically, as in the paper).

The projected stiffness keeps the modes with their eigenvalues clamped at 0. These formulas hold for any
valid SVD, so repeated singular values (F = I, F = 0) need no special case and there is no division.
The SVD and the 3 x 3 eigendecomposition are batched Jacobi rotations in jnp (``xfem._jacobi3``: each
decision is taken once, inside a rotation's computation, so XLA's kernels agree at repeated singular values).
They take about half the time of LAPACK's batched 3 x 3 SVD and eigh (benchmarks/README.md, "Element
Hessians").

Element quantities: ``F_e = sum_a x_a grads_a^T`` (x: deformed node positions, grads: gradients of the
linear shape functions with respect to the rest position), energy ``vol Psi(F_e)``, gradient
``g_(a,k) = vol sum_j P_kj grads_aj`` and Hessian ``H_(a,k),(b,l) = vol sum_jn grads_aj (dP/dF)_(kj),(ln)
grads_bn`` (node-major ordering ``[x0, y0, z0, x1, ...]``).

Differentiation: everything is closed form except the projection, whose derivative is defined by the
Daleckii-Krein formula for the spectral function ``max(lambda, 0)``: with the eigensystem ``Q, lambda``,
``d A_+ = Q (G o (Q^T dA Q)) Q^T``, ``G_ij = (max(l_i, 0) - max(l_j, 0)) / (l_i - l_j)`` (``1[l_i > 0]`` when
``l_i = l_j``), finite at repeated eigenvalues, where the derivatives of the SVD are not.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import require
from _jaxcga_shared.platform import EXACT
from xfem._jacobi3 import eigh3, svd3

_LEVI_CIVITA = np.zeros((3, 3, 3))
for _i, _j, _k in ((0, 1, 2), (1, 2, 0), (2, 0, 1)):
    _LEVI_CIVITA[_i, _j, _k], _LEVI_CIVITA[_i, _k, _j] = 1.0, -1.0
# (i, j, k): twist/flip pairs (i, j) with k the third axis
_PAIRS = ((1, 2, 0), (0, 2, 1), (0, 1, 2))


def lame(
    young: float | Float[ArrayLike, "*#batch"], poisson: float | Float[ArrayLike, "*#batch"]
) -> tuple[Float[ArrayLike, "*batch"], Float[ArrayLike, "*batch"]]:
    """Lamé parameters of a linear isotropic material, the ``(mu, lam)`` the functions of this module take.

    Args:
        young: Young's modulus E > 0; python float, array or JAX array (traced too), any shape.
        poisson: Poisson's ratio nu in (-1, 1/2), broadcastable against ``young``.
    Returns:
        ``(mu, lam) = (E / (2 (1 + nu)), E nu / ((1 + nu)(1 - 2 nu)))``, broadcast shape (python floats for python
        floats).

    Examples:
        >>> import xfem
        >>> mu, lam = xfem.lame(1e6, 0.25)
        >>> round(float(mu)), round(float(lam))
        (400000, 400000)
    """
    bad = ~(jnp.asarray(young) > 0) | ~jnp.isfinite(young)
    outside = ~((jnp.asarray(poisson) > -1) & (jnp.asarray(poisson) < 0.5))
    young = require(
        young,
        (bad, "young: Young's modulus must be finite and > 0"),
        (outside, "poisson: Poisson's ratio must lie in (-1, 0.5)"),
    )
    mu = young / (2 * (1 + poisson))
    lam = young * poisson / ((1 + poisson) * (1 - 2 * poisson))
    return mu, lam


def _check_F(F):
    F = jnp.asarray(F)
    if F.ndim < 2 or F.shape[-2:] != (3, 3) or not jnp.issubdtype(F.dtype, jnp.floating):
        raise ValueError(f"F: expected floating deformation gradients of shape (..., 3, 3), got {F.dtype} {F.shape}")
    return F


def _material(mu, lam, dtype, batch: tuple[int, ...]):
    """``(mu', lam')`` of [SGK18] (module docstring) with shape ``batch``, from Lamé ``mu``, ``lam``, checked."""
    mu, lam = jnp.asarray(mu, dtype), jnp.asarray(lam, dtype)
    mu = require(mu, (~(mu > 0), "mu: the shear modulus must be > 0"))
    lam = require(lam, (~(lam + 5 / 6 * mu > 0), "lam: lam + 5/6 mu must be > 0 (holds for Poisson's ratio > -1)"))
    return _modified_lame(mu, lam, dtype, batch)


def _modified_lame(mu, lam, dtype, batch: tuple[int, ...]):
    """``_material`` without its value checks, for Lamé parameters that ``lame`` made from checked ``young`` and
    ``poisson`` (then mu > 0 and lam + 5/6 mu = E / (1 + nu) (nu / (1 - 2 nu) + 5/12) > 0): a check under jit is
    a host round trip on a GPU, and a step evaluates the energy a few times."""
    mu, lam = jnp.asarray(mu, dtype), jnp.asarray(lam, dtype)
    for name, v in (("mu", mu), ("lam", lam)):
        try:
            jnp.broadcast_shapes(v.shape, batch)
        except ValueError:
            raise ValueError(f"{name}: expected a scalar or an array broadcastable to {batch}, got {v.shape}") from None
    mu_s = 4 / 3 * mu
    lam_s = lam + 5 / 6 * mu
    return jnp.broadcast_to(mu_s, batch), jnp.broadcast_to(lam_s, batch)


def _cofactor(F):
    """``cof F = d det F / dF`` (rows: cross products of the other two rows) and ``det F = F_0 . cof_0``: the
    same J in energy, stress and stiffness."""
    r0, r1, r2 = F[..., 0, :], F[..., 1, :], F[..., 2, :]
    cof = jnp.stack([jnp.cross(r1, r2), jnp.cross(r2, r0), jnp.cross(r0, r1)], axis=-2)
    return cof, jnp.sum(r0 * cof[..., 0, :], axis=-1)


def _psi(F, mu_s, lam_s):
    # eq. 14 - Psi_0 rearranged (module docstring): no cancellation between large terms near rest
    e = jnp.sum(F * F, axis=(-2, -1)) - 3
    j = _cofactor(F)[1] - 1
    return 0.5 * mu_s * (e - jnp.log1p(e / 4)) + 0.5 * lam_s * j**2 - 0.75 * mu_s * j


def _pk1(F, mu_s, lam_s):
    ic = jnp.sum(F * F, axis=(-2, -1))
    cof, J = _cofactor(F)
    c = mu_s * (1 - 1 / (ic + 1))
    b = lam_s * (J - 1) - 0.75 * mu_s  # lam' (J - alpha)
    return c[..., None, None] * F + b[..., None, None] * cof


def _dpdf(F, mu_s, lam_s):
    """Unprojected stiffness dP/dF, (..., 9, 9), F flattened row-major."""
    ic = jnp.sum(F * F, axis=(-2, -1))
    cof, J = _cofactor(F)
    f = F.reshape(*F.shape[:-2], 9)
    g = cof.reshape(*F.shape[:-2], 9)
    eps = jnp.asarray(_LEVI_CIVITA, F.dtype)
    hess_det = jnp.einsum("ikm,jln,...mn->...ijkl", eps, eps, F, precision=EXACT).reshape(*F.shape[:-2], 9, 9)
    c = mu_s * (1 - 1 / (ic + 1))
    d = 2 * mu_s / (ic + 1) ** 2
    b = lam_s * (J - 1) - 0.75 * mu_s  # lam' (J - alpha)
    return (
        c[..., None, None] * lift_rank(jnp.eye(9, dtype=F.dtype), c.ndim + 2)
        + d[..., None, None] * f[..., :, None] * f[..., None, :]
        + lam_s[..., None, None] * g[..., :, None] * g[..., None, :]
        + b[..., None, None] * hess_det
    )


def _eigensystem(F, mu_s, lam_s):
    """Eigenvalues (..., 9) and orthonormal eigenmatrices (..., 9, 3, 3) of dP/dF, [SGK18] sec. 4."""
    U, s, Vt = svd3(F)  # rotation-variant: det U = det V = 1, prod(s) = J
    s0, s1, s2 = s[..., 0], s[..., 1], s[..., 2]
    ic = jnp.sum(s * s, axis=-1)
    c = mu_s * (1 - 1 / (ic + 1))
    d = 2 * mu_s / (ic + 1) ** 2
    b = lam_s * (s0 * s1 * s2 - 1) - 0.75 * mu_s  # lam' (J - alpha)
    h = jnp.stack([s1 * s2, s0 * s2, s0 * s1], axis=-1)
    zero = jnp.zeros_like(s0)
    offdiag = jnp.stack(
        [jnp.stack([zero, s2, s1], -1), jnp.stack([s2, zero, s0], -1), jnp.stack([s1, s0, zero], -1)], -2
    )
    scaling = (
        c[..., None, None] * lift_rank(jnp.eye(3, dtype=F.dtype), c.ndim + 2)
        + d[..., None, None] * s[..., :, None] * s[..., None, :]
        + lam_s[..., None, None] * h[..., :, None] * h[..., None, :]
        + b[..., None, None] * offdiag
    )
    lam_scaling, q = eigh3(scaling)
    # uv[..., i, j, :, :] = u_i v_j^T
    Ut = U.swapaxes(-1, -2)
    uv = Ut[..., :, None, :, None] * Vt[..., None, :, None, :]
    r = 1 / math.sqrt(2.0)
    modes = [jnp.einsum("...i,...iiab->...ab", q[..., :, n], uv, precision=EXACT) for n in range(3)]
    values = [lam_scaling[..., n] for n in range(3)]
    for i, j, k in _PAIRS:
        modes += [r * (uv[..., i, j, :, :] - uv[..., j, i, :, :]), r * (uv[..., i, j, :, :] + uv[..., j, i, :, :])]
        values += [c + b * s[..., k], c - b * s[..., k]]
    return jnp.stack(values, axis=-1), jnp.stack(modes, axis=-3)


def _sandwich(grads, stiffness, volumes):
    """Element Hessians ``vol B^T A B`` (m, 12, 12) of stiffnesses A = dP/dF (m, 9, 9), B = dvec(F)/dx."""
    A = stiffness.reshape(-1, 3, 3, 3, 3)
    left = jnp.einsum("maj,mkjln->makln", grads, A, precision=EXACT)
    return (volumes[:, None, None, None, None] * jnp.einsum("makln,mbn->makbl", left, grads, precision=EXACT)).reshape(
        -1, 12, 12
    )


@jax.custom_jvp
def _projected_hessian(F, grads, volumes, mu_s, lam_s):
    """``vol B^T (dP/dF)_+ B`` (m, 12, 12), summed mode by mode: ``B^T vec(M) = vec(grads M^T)``."""
    values, modes = _eigensystem(F, mu_s, lam_s)
    return _modal_sum(volumes[:, None] * jnp.maximum(values, 0), _node_modes(modes, grads))


def _node_modes(modes, grads):
    """(m, 9, 12) the eigenmatrices of dP/dF mapped to the nodes, ``B^T vec(M) = vec(grads M^T)``."""
    return jnp.einsum("mnkj,maj->mnak", modes, grads, precision=EXACT).reshape(*modes.shape[:2], 12)


def _modal_sum(weight, w):
    """``sum_n weight_n w_n w_n^T`` (m, 12, 12)."""
    return jnp.einsum("mn,mni,mnj->mij", weight, w, w, precision=EXACT)


@_projected_hessian.defjvp
def _projected_hessian_jvp(primals, tangents):
    F, grads, volumes, mu_s, lam_s = primals
    dF, dgrads, dvolumes, dmu_s, dlam_s = tangents
    values, modes = _eigensystem(F, mu_s, lam_s)
    Q = modes.reshape(*modes.shape[:-2], 9).swapaxes(-1, -2)  # eigenvectors as columns
    plus = jnp.maximum(values, 0)
    # Daleckii-Krein: divided differences of max(., 0), its derivative on ties
    gap = values[..., :, None] - values[..., None, :]
    same = gap == 0
    divided = jnp.where(
        same,
        jnp.broadcast_to((values[..., :, None] > 0).astype(values.dtype), gap.shape),
        (plus[..., :, None] - plus[..., None, :]) / jnp.where(same, 1, gap),
    )
    dA = jax.jvp(_dpdf, (F, mu_s, lam_s), (dF, dmu_s, dlam_s))[1]
    A_plus = jnp.einsum("...ik,...k,...jk->...ij", Q, plus, Q, precision=EXACT)
    dA_plus = jnp.einsum(
        "...ik,...kl,...jl->...ij",
        Q,
        divided * jnp.matmul(jnp.matmul(Q.swapaxes(-1, -2), dA, precision=EXACT), Q, precision=EXACT),
        Q,
        precision=EXACT,
    )
    return jax.jvp(_sandwich, (grads, A_plus, volumes), (dgrads, dA_plus, dvolumes))


_psi_jit, _pk1_jit = eqx.filter_jit(_psi), eqx.filter_jit(_pk1)


def stable_neohookean_energy(
    F: Float[ArrayLike, "*batch 3 3"], mu: float | Float[ArrayLike, "*#batch"], lam: float | Float[ArrayLike, "*#batch"]
) -> Float[Array, "*batch"]:
    """Stable neo-Hookean energy density Psi(F) ([SGK18] eq. 14, module docstring), ``Psi(I) = 0``.

    Args:
        F: (..., 3, 3) deformation gradients (inverted and degenerate ones allowed).
        mu: Lamé parameters of the linear material it matches at rest (``lame``), scalars or arrays
            broadcastable to F's batch shape ``...`` (e.g. (m,) per element); mu > 0, lam + 5/6 mu > 0.
        lam: see ``mu``.
    Returns:
        (...) energy densities."""
    F = _check_F(F)
    return _psi_jit(F, *_material(mu, lam, F.dtype, F.shape[:-2]))


def stable_neohookean_pk1(
    F: Float[ArrayLike, "*batch 3 3"], mu: float | Float[ArrayLike, "*#batch"], lam: float | Float[ArrayLike, "*#batch"]
) -> Float[Array, "*batch 3 3"]:
    """First Piola-Kirchhoff stress ``P = dPsi/dF = mu' (1 - 1/(I_C + 1)) F + lam' (J - alpha) cof F``.

    Args:
        F: (..., 3, 3) deformation gradients.
        mu: Lamé parameters, as in ``stable_neohookean_energy``.
        lam: see ``mu``.
    Returns:
        (..., 3, 3) stresses, ``P(I) = 0``."""
    F = _check_F(F)
    return _pk1_jit(F, *_material(mu, lam, F.dtype, F.shape[:-2]))


def _check_elements(x, grads, volumes):
    x, grads, volumes = jnp.asarray(x), jnp.asarray(grads), jnp.asarray(volumes)
    if x.ndim != 3 or x.shape[1:] != (4, 3) or not jnp.issubdtype(x.dtype, jnp.floating):
        raise ValueError(f"x: expected floating node positions of shape (m, 4, 3), got {x.dtype} {x.shape}")
    m = x.shape[0]
    if grads.shape != (m, 4, 3) or grads.dtype != x.dtype:
        raise ValueError(f"grads: expected shape ({m}, 4, 3) and dtype {x.dtype}, got {grads.dtype} {grads.shape}")
    if volumes.shape != (m,) or volumes.dtype != x.dtype:
        raise ValueError(f"volumes: expected shape ({m},) and dtype {x.dtype}, got {volumes.dtype} {volumes.shape}")
    return x, grads, volumes


@eqx.filter_jit
def _element_energy(x, grads, volumes, mu_s, lam_s):
    return volumes * _psi(jnp.einsum("mai,maj->mij", x, grads, precision=EXACT), mu_s, lam_s)


def element_energy(
    x: Float[ArrayLike, "m 4 3"],
    grads: Float[ArrayLike, "m 4 3"],
    volumes: Float[ArrayLike, " m"],
    mu: float | Float[ArrayLike, " m"],
    lam: float | Float[ArrayLike, " m"],
) -> Float[Array, " m"]:
    """Elastic energy ``vol Psi(F_e)`` of each linear tetrahedron, ``F_e = sum_a x[e, a] grads[e, a]^T``.

    Args:
        x: (m, 4, 3) deformed positions of each tet's nodes.
        grads: (m, 4, 3) gradients of the 4 linear shape functions with respect to the rest position.
        volumes: (m,) rest volumes.
        mu: Lamé parameters (``lame``), scalars or (m,) per element.
        lam: see ``mu``.
    Returns:
        (m,) energies."""
    x, grads, volumes = _check_elements(x, grads, volumes)
    return _element_energy(x, grads, volumes, *_material(mu, lam, x.dtype, x.shape[:1]))


@eqx.filter_jit
def _element_gradient_hessian(x, grads, volumes, mu_s, lam_s, project):
    m = x.shape[0]
    F = jnp.einsum("mai,maj->mij", x, grads, precision=EXACT)
    g = volumes[:, None, None] * jnp.einsum("mkj,maj->mak", _pk1(F, mu_s, lam_s), grads, precision=EXACT)
    if project:
        H = _projected_hessian(F, grads, volumes, mu_s, lam_s)
    else:
        H = _sandwich(grads, _dpdf(F, mu_s, lam_s), volumes)
    return g.reshape(m, 12), H


@eqx.filter_jit
def _element_gradient_hessians(x, grads, volumes, mu_s, lam_s):
    """The gradients (m, 12) and both Hessians (m, 12, 12), projected and true, from one eigensystem: the true
    Hessian ``vol sum_n lambda_n w_n w_n^T`` over all 9 modes, the projected one over ``max(lambda_n, 0)``. Not for
    differentiation (the projected Hessian's derivative is ``_projected_hessian``'s)."""
    m = x.shape[0]
    F = jnp.einsum("mai,maj->mij", x, grads, precision=EXACT)
    g = volumes[:, None, None] * jnp.einsum("mkj,maj->mak", _pk1(F, mu_s, lam_s), grads, precision=EXACT)
    values, modes = _eigensystem(F, mu_s, lam_s)
    w = _node_modes(modes, grads)
    true = _modal_sum(volumes[:, None] * values, w)
    projected = _modal_sum(volumes[:, None] * jnp.maximum(values, 0), w)
    return g.reshape(m, 12), (projected, true)


def element_gradient_hessian(
    x: Float[ArrayLike, "m 4 3"],
    grads: Float[ArrayLike, "m 4 3"],
    volumes: Float[ArrayLike, " m"],
    mu: float | Float[ArrayLike, " m"],
    lam: float | Float[ArrayLike, " m"],
    project: bool = True,
) -> tuple[Float[Array, "m 12"], Float[Array, "m 12 12"]]:
    """Gradient and Hessian of ``element_energy`` with respect to each tet's 12 node coordinates.

    Args:
        x: (m, 4, 3) deformed positions of each tet's nodes.
        grads: (m, 4, 3) gradients of the linear shape functions with respect to the rest position.
        volumes: (m,) rest volumes.
        mu: Lamé parameters (``lame``), scalars or (m,) per element.
        lam: see ``mu``.
        project: python bool; clamp the negative eigenvalues of dP/dF to 0 ([SGK18] sec. 4, closed-form
            eigensystem) so that every H is positive semidefinite and Newton's direction descends.
    Returns:
        g: (m, 12) gradients, node-major ``[x0, y0, z0, x1, ...]``.
        H: (m, 12, 12) symmetric Hessians, same ordering."""
    x, grads, volumes = _check_elements(x, grads, volumes)
    return _element_gradient_hessian(x, grads, volumes, *_material(mu, lam, x.dtype, x.shape[:1]), bool(project))
