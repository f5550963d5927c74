"""kingdon peer for the motor-sandwich benchmark.

``make_kingdon_sandwich(dtype)`` returns a ``jax.jit``-ed ``f(motors, points)``
that applies CGA motors to Euclidean points with kingdon's sandwich operator
``M >> X`` in ``Algebra(4, 1)``.

Conventions
-----------
* ``motors``: (N, 8) or (8,) with components (1, e12, e13, e23, e1inf, e2inf,
  e3inf, e123inf) in the null basis eo = (e- - e+)/2, einf = e- + e+.
* kingdon's ``Algebra(4, 1)`` has signature [1, 1, 1, 1, -1], so e+ = e4 and
  e- = e5: einf = e4 + e5, eo = (e5 - e4)/2, and e_i^einf = e_i4 + e_i5,
  e123^einf = e1234 + e1235.  The motor conversion is therefore just a
  duplication of the translational components (no arithmetic).
* Up-projection X = x + 0.5|x|^2 einf + eo gives the e4/e5 coefficients
  0.5|x|^2 - 0.5 and 0.5|x|^2 + 0.5; down-projection divides the Euclidean part
  by the eo coefficient -X.einf = X_e5 - X_e4.

kingdon generates (and CSEs) a specialised sandwich for the sparse motor key
set x vector at trace time; XLA then compiles it.  Component arrays carry the
blade index first, i.e. values of shape (k, N).
"""

from functools import cache

import jax
import jax.numpy as jnp
from kingdon import Algebra

_MOTOR_KEYS = ("e", "e12", "e13", "e23", "e14", "e15", "e24", "e25", "e34", "e35", "e1234", "e1235")


@cache
def _algebra():
    return Algebra(4, 1)


def make_kingdon_sandwich(dtype):
    alg = _algebra()

    @jax.jit
    def f(motors, points):
        m = jnp.asarray(motors, dtype).T  # (8, N) or (8,)
        p = jnp.asarray(points, dtype).T  # (3, N)
        s, b12, b13, b23, t1, t2, t3, q = m
        M = alg.evenmv(keys=_MOTOR_KEYS, values=[s, b12, b13, b23, t1, t1, t2, t2, t3, t3, q, q])
        h = 0.5 * jnp.sum(p * p, axis=0)
        X = alg.vector(values=[p[0], p[1], p[2], h - 0.5, h + 0.5])
        Y = M >> X
        w = Y.e5 - Y.e4  # eo coefficient = -Y.einf
        return jnp.stack([Y.e1, Y.e2, Y.e3], axis=-1) / w[..., None]

    return f
