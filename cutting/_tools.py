"""The tools of cut, tear and drill as explicit values: ``Plane`` (Algorithm 1), ``Scalpel``
(Algorithm 2) and ``Drill`` (Algorithm 3).

Each is an ``eqx.Module`` (a pytree) of arrays: JAX arrays (tracers included) are kept as given, anything
else becomes float64 numpy. The host topology functions read the tool as float64 numpy, and the
``*_positions`` functions take it as JAX arrays, so ``jax.grad`` with respect to a tool returns a tool of
the same kind holding the gradients.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

import jaxcga as cga

# What a tool's fields are given as: arrays (numpy or JAX, traced under jax.grad) or nested lists of numbers.
Given = ArrayLike | Sequence[float] | Sequence[Sequence[float]]


def _array(value: Given) -> Array | np.ndarray:
    # JAX arrays stay (tracers, device arrays: differentiable, no transfer); the rest is float64 on the host,
    # so that a topology computed without x64 keeps full precision
    return value if isinstance(value, jax.Array) else np.asarray(value, np.float64)


class Plane(eqx.Module):
    """A cutting plane: the points x with ``normal . x = distance`` (eq. 5); its positive side is
    ``normal . x > distance``.

    Attributes:
        normal: (3,) its normal; need not be unit length (the plane is the same scaled).
        distance: () the offset d.
    """

    normal: Float[Array | np.ndarray, "3"] = eqx.field(converter=_array)
    distance: Float[Array | np.ndarray, ""] = eqx.field(converter=_array)

    @classmethod
    def through(cls, point: Given, normal: Given) -> Plane:
        """The plane through ``point`` (3,) with ``normal`` (3,) (JAX arrays stay differentiable)."""
        point, normal = _array(point), _array(normal)
        return cls(normal, sum(normal[k] * point[k] for k in range(3)))

    @classmethod
    def from_multivector(cls, plane: cga.Multivector) -> Plane:
        """The plane of a jaxcga plane vector ``n + d einf`` (eq. 5)."""
        normal, distance = cga.plane_normal_distance(plane)
        return cls(normal, distance)


class Scalpel(eqx.Module):
    """A scalpel sampled at time steps t_0 .. t_k: the segment from ``handle[i]`` to ``tip[i]`` at t_i.
    The handle end counts where the segment crosses the surface more than once (the crossing nearest
    the handle is the tear point).

    Attributes:
        handle: (k+1, 3) the handle end at each time step.
        tip: (k+1, 3) the other end.
    """

    handle: Float[Array | np.ndarray, "s 3"] = eqx.field(converter=_array)
    tip: Float[Array | np.ndarray, "s 3"] = eqx.field(converter=_array)


class Drill(eqx.Module):
    """A cylindrical drill: its axis from ``base`` to ``tip`` and its radius. It drills every sheet of the
    surface that meets the cylinder between base and tip; the hole in a sheet follows it as far as it
    stays inside the (unbounded) cylinder.

    Attributes:
        tip: (3,) the tip A.
        base: (3,) the base B.
        radius: () the radius r > 0.
    """

    tip: Float[Array | np.ndarray, "3"] = eqx.field(converter=_array)
    base: Float[Array | np.ndarray, "3"] = eqx.field(converter=_array)
    radius: Float[Array | np.ndarray, ""] = eqx.field(converter=_array)


def check_plane(plane: Plane) -> tuple[np.ndarray, float]:
    """(unit normal (3,), distance) of a ``Plane`` as float64, with clear errors."""
    if not isinstance(plane, Plane):
        raise ValueError(
            f"plane: expected a cutting.Plane (Plane(normal, distance), Plane.through(point, normal) "
            f"or Plane.from_multivector), got {type(plane).__name__}"
        )
    n = np.asarray(plane.normal, np.float64)
    d = np.asarray(plane.distance, np.float64)
    if n.shape != (3,) or d.shape != ():
        raise ValueError(f"plane: expected a (3,) normal and a scalar distance, got shapes {n.shape}, {d.shape}")
    if not np.all(np.isfinite(n)) or not np.isfinite(d):
        raise ValueError("plane: normal and distance must be finite")
    length = float(np.linalg.norm(n))
    if length == 0:
        raise ValueError("plane: zero-length normal")
    return n / length, float(d) / length


def joined_scalpel(scalpel: Scalpel | Sequence[Scalpel]) -> Scalpel:
    """One ``Scalpel`` of a sequence of them in order (each of one sample, (3,) ends, or of several, (m, 3));
    a ``Scalpel`` as it is. JAX arrays stay JAX arrays (differentiable)."""
    if isinstance(scalpel, Scalpel):
        return scalpel
    if isinstance(scalpel, np.ndarray | jax.Array | str) or not isinstance(scalpel, Sequence):
        raise ValueError(
            f"scalpel: expected a cutting.Scalpel(handle, tip) or a sequence of them, got {type(scalpel).__name__}"
        )
    if not all(isinstance(part, Scalpel) for part in scalpel):
        kinds = sorted({type(part).__name__ for part in scalpel if not isinstance(part, Scalpel)})
        raise ValueError(f"scalpel: expected a sequence of cutting.Scalpel, got items of type {', '.join(kinds)}")
    ends = []
    for k, part in enumerate(scalpel):
        handle, tip = part.handle, part.tip
        if handle.shape not in ((3,), (len(handle), 3)) or tip.shape != handle.shape:
            raise ValueError(
                f"scalpel[{k}]: expected handle and tip ends of shape (3,) or (m, 3), got {handle.shape}, {tip.shape}"
            )
        ends.append((handle.reshape(-1, 3), tip.reshape(-1, 3)))
    if not ends:
        raise ValueError("scalpel: expected at least two samples, got an empty sequence")
    stack = jnp.concatenate if any(isinstance(x, jax.Array) for pair in ends for x in pair) else np.concatenate
    return Scalpel(stack([h for h, _ in ends]), stack([t for _, t in ends]))


def check_scalpel(scalpel: Scalpel | Sequence[Scalpel]) -> np.ndarray:
    """The scalpel's samples (a ``Scalpel`` or a sequence of them, ``joined_scalpel``) as one float64
    (k+1, 2, 3) array (handle end first), with clear errors."""
    scalpel = joined_scalpel(scalpel)
    handle, tip = np.asarray(scalpel.handle, np.float64), np.asarray(scalpel.tip, np.float64)
    if handle.ndim != 2 or handle.shape[1:] != (3,) or handle.shape != tip.shape or len(handle) < 2:
        raise ValueError(
            f"scalpel: expected handle and tip ends of shape (k+1, 3) at k+1 >= 2 time steps, got "
            f"shapes {handle.shape}, {tip.shape}"
        )
    samples = np.stack([handle, tip], axis=1)
    if not np.all(np.isfinite(samples)):
        raise ValueError("scalpel: endpoints must be finite")
    if np.any(np.linalg.norm(tip - handle, axis=1) == 0):
        raise ValueError("scalpel: a sample has equal handle and tip ends")
    return samples


def check_drill(drill: Drill) -> tuple[np.ndarray, np.ndarray, float]:
    """(tip (3,), base (3,), radius) of a ``Drill`` as float64, with clear errors."""
    if not isinstance(drill, Drill):
        raise ValueError(f"drill: expected a cutting.Drill(tip, base, radius), got {type(drill).__name__}")
    ends = []
    for name, value in (("tip", drill.tip), ("base", drill.base)):
        point = np.asarray(value, np.float64)
        if point.shape != (3,) or not np.all(np.isfinite(point)):
            raise ValueError(f"drill.{name}: expected 3 finite coordinates, got {point.tolist()}")
        ends.append(point)
    radius = np.asarray(drill.radius, np.float64)
    if radius.shape != () or not (np.isfinite(radius) and radius > 0):
        raise ValueError(f"drill.radius: expected a positive finite number, got {radius.tolist()}")
    if np.linalg.norm(ends[0] - ends[1]) == 0:
        raise ValueError("drill.tip, drill.base: the drill's endpoints coincide (no axis)")
    return ends[0], ends[1], float(radius)
