"""The material of the FEM and XFEM steps: Young's modulus and Poisson's ratio, one convention for every public
function (``backward_euler_step``, ``rollout``, ``simulate``, ``XFEMModel.step``, the scenes and the CLI).

The stable neo-Hookean kernels (``xfem._neohookean``) take Lamé parameters; ``Material.lame`` derives them
inside JAX, so a gradient with respect to the Lamé parameters reaches ``young`` and ``poisson``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.core
import numpy as np
from jaxtyping import ArrayLike, Float

from xfem._neohookean import lame


class Material(eqx.Module):
    """A linear isotropic material matched by the stable neo-Hookean energy at rest (``xfem._neohookean``), with
    optional stiffness-proportional Rayleigh damping.

    A pytree of its array leaves: differentiate, jit and vmap through it like an array (``jax.grad`` of a function
    of a ``Material`` returns a ``Material`` of derivatives).

    Damping. ``damping`` beta (seconds) adds the force ``-beta K v`` (K the stiffness), as the backward Euler step
    integrates it: the energy ``beta h [U(x) - grad U(x_t) . x]``, whose gradient is ``beta h (grad U(x) -
    grad U(x_t))``, ``beta h K (x - x_t)`` to first order (``xfem._backward_euler``). It damps the body's
    deformation, never its rigid motion: the elastic forces of every state sum to zero, so a free piece still falls
    at g. None (the default) leaves the term out of the step altogether; 0.0 keeps it at zero, for a gradient with
    respect to it.

    Attributes:
        young: Young's modulus E > 0: a python float, numpy or JAX scalar, or (m,) per element.
        poisson: Poisson's ratio nu in (-1, 1/2), broadcastable against ``young``.
        damping: None, or the Rayleigh stiffness coefficient beta >= 0 in seconds, a scalar.
    """

    young: Float[ArrayLike, "*#batch"] | float
    poisson: Float[ArrayLike, "*#batch"] | float
    damping: Float[ArrayLike, ""] | float | None = None

    def __check_init__(self):
        # concrete values are checked now (a ValueError naming the argument); traced ones by ``lame``'s
        # check (``require``) where the step uses them
        if self.damping is not None and not isinstance(self.damping, jax.core.Tracer):
            damping = np.asarray(self.damping)
            if damping.shape != () or not np.issubdtype(damping.dtype, np.number) or not damping >= 0:
                raise ValueError(f"damping: expected None or a scalar >= 0 (seconds), got {self.damping!r}")
        if not any(isinstance(a, jax.core.Tracer) for a in (self.young, self.poisson)):
            young, poisson = np.asarray(self.young), np.asarray(self.poisson)
            for name, a in (("young", young), ("poisson", poisson)):
                if not np.issubdtype(a.dtype, np.floating) and not np.issubdtype(a.dtype, np.integer):
                    raise ValueError(f"{name}: expected a real scalar or array, got {a.dtype}")
            try:
                np.broadcast_shapes(young.shape, poisson.shape)
            except ValueError:
                raise ValueError(f"young, poisson: shapes {young.shape} and {poisson.shape} do not broadcast") from None
            lame(young, poisson)

    def lame(self) -> tuple[Float[ArrayLike, "*batch"], Float[ArrayLike, "*batch"]]:
        """The Lamé parameters ``(mu, lam) = (E / (2 (1 + nu)), E nu / ((1 + nu)(1 - 2 nu)))`` (``xfem.lame``)."""
        return lame(self.young, self.poisson)
