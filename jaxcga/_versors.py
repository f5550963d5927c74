"""Rotations, translations and dilations as versors (cut/tear/drill paper, section 2.4, eq. 8-14),
their products (motors, similitudes), conversions to matrices, quaternions and dual quaternions, and
the generated affine form of a versor acting on Euclidean points.

Conventions (checked against scipy's rotations in the tests):

* rotor ``R = cos(phi/2) - sin(phi/2) u I3`` (eq. 8) rotates by +phi about the unit axis u;
  ``u I3 = u1 e23 - u2 e13 + u3 e12``.
* translator ``T = 1 - t einf / 2`` (eq. 10) translates by t.
* dilator (eq. 12) scales by d > 0 about the origin; returned normalized, ``D ~D = 1``:
  ``D = cosh(ln d / 2) + sinh(ln d / 2) eo^einf``, which is eq. 12 times (1 + d) / (2 sqrt d).
* a product ``M = Mn ... M1`` applies M1 first (eq. 14): ``motor(R, t) = T R``,
  ``similitude(R, t, d) = T R D`` maps x to d R x + t.
"""

from __future__ import annotations

import functools
import operator
from collections.abc import Iterator
from fractions import Fraction

import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from _jaxcga_shared.broadcast import lift_rank
from _jaxcga_shared.checks import check_finite, check_vectors, non_finite, require
from _jaxcga_shared.pallas_rows import RowFunction, fits, rowwise
from _jaxcga_shared.platform import EXACT, per_platform
from jaxcga import _algebra as alg
from jaxcga import _codegen
from jaxcga._multivector import KINDS, Multivector, broadcast_batch
from jaxcga._objects import POINT_BLADES

_ROTOR = KINDS["rotor"]  # 1, e12, e13, e23


def _stack(*columns: Float[Array, "*batch"], blades: tuple[int, ...]) -> Multivector:
    batch = jnp.broadcast_shapes(*(jnp.shape(c) for c in columns))
    return Multivector(jnp.stack([jnp.broadcast_to(c, batch) for c in columns], axis=-1), blades)


def translator(t: Float[ArrayLike, "... 3"]) -> Multivector:
    """Translator ``T = 1 - t einf / 2`` by the Euclidean vector t (eq. 10).

    Args:
        t: (..., 3) translation vectors.
    Returns:
        The translators (1, e1inf, e2inf, e3inf), batch shape (...).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.translator(jnp.array([1.0, 2.0, 3.0]))
        >>> T.names, T.values.tolist()
        (('1', 'e1inf', 'e2inf', 'e3inf'), [1.0, -0.5, -1.0, -1.5])
    """
    t = check_finite("t", check_vectors("t", t))
    one = jnp.ones(t.shape[:-1], t.dtype)
    return _stack(one, -0.5 * t[..., 0], -0.5 * t[..., 1], -0.5 * t[..., 2], blades=KINDS["translator"])


def _rotor_in_plane(
    name: str, plane: Float[Array, "... 3"], angle: Float[ArrayLike, "*batch"], what: str
) -> Multivector:
    """``exp(-b angle / 2)`` for the Euclidean bivector b = plane (e12, e13, e23), normalized here."""
    angle = check_finite("angle", jnp.asarray(angle, plane.dtype))
    length = jnp.linalg.norm(plane, axis=-1)
    length = require(length, (jnp.any(length == 0), f"{name}: zero-length {what}"))
    b = plane / length[..., None]
    c, s = jnp.cos(angle / 2), jnp.sin(angle / 2)
    return _stack(c, -s * b[..., 0], -s * b[..., 1], -s * b[..., 2], blades=_ROTOR)


def rotor(axis: Float[ArrayLike, "... 3"], angle: Float[ArrayLike, "*batch"]) -> Multivector:
    """Rotor by ``angle`` (radians, right-handed) about ``axis`` (normalized here), eq. 8:
    the rotation plane is u I3 = u1 e23 - u2 e13 + u3 e12.

    Args:
        axis: (..., 3) rotation axes (normalized here; non-zero).
        angle: (...) angles in radians, counter-clockwise looking down the axis.
    Returns:
        The rotors (1, e12, e13, e23), batch shape broadcast from both.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> R = cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2)
        >>> (cga.apply_to_points(R, jnp.array([1.0, 0, 0])).round(6) + 0.0).tolist()  # + 0.0: no negative zeros
        [0.0, 1.0, 0.0]
    """
    u = check_finite("axis", check_vectors("axis", axis))
    plane = jnp.stack([u[..., 2], -u[..., 1], u[..., 0]], axis=-1)
    return _rotor_in_plane("axis", plane, angle, "rotation axis")


def rotor_from_bivector(plane: Float[ArrayLike, "... 3"], angle: Float[ArrayLike, "*batch"]) -> Multivector:
    """Rotor ``exp(-b angle / 2)`` in the plane of the Euclidean bivector b with components
    (e12, e13, e23) (normalized here), eq. 8.

    Args:
        plane: (..., 3) the rotation plane's bivector components (e12, e13, e23), normalized here.
        angle: (...) angles in radians.
    Returns:
        The rotors (1, e12, e13, e23).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> R = cga.rotor_from_bivector(jnp.array([1.0, 0, 0]), jnp.pi / 2)  # in the e12 plane: about +z
        >>> (cga.apply_to_points(R, jnp.array([1.0, 0, 0])).round(6) + 0.0).tolist()
        [0.0, 1.0, 0.0]
    """
    b = check_finite("plane", check_vectors("plane", plane))
    return _rotor_in_plane("plane", b, angle, "bivector")


def _float_scalar(value: ArrayLike) -> Float[Array, "*batch"]:
    """Keep a floating input's dtype (float32 stays float32); integers become the default float."""
    value = jnp.asarray(value)
    return value if jnp.issubdtype(value.dtype, jnp.floating) else value.astype(jnp.result_type(float))


def dilator(scale: Float[ArrayLike, "*batch"]) -> Multivector:
    """Normalized dilator about the origin by the factor ``scale`` > 0 (eq. 12-13).

    Args:
        scale: (...) scale factors > 0.
    Returns:
        The unit dilators (1, eoinf).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> cga.apply_to_points(cga.dilator(2.0), jnp.array([1.0, 2.0, 3.0])).round(6).tolist()
        [2.0, 4.0, 6.0]
    """
    d = check_finite("scale", _float_scalar(scale))
    d = require(d, (jnp.any(d <= 0), "scale: dilation factor must be > 0"))
    root = jnp.sqrt(d)
    return _stack((1 + d) / (2 * root), (d - 1) / (2 * root), blades=KINDS["dilator"])


def dilator_paper(scale: Float[ArrayLike, "*batch"]) -> Multivector:
    """The paper's un-normalized dilator ``D = 1 + (1 - d)/(1 + d) einf^eo`` (eq. 12).

    Args:
        scale: (...) scale factors > 0.
    Returns:
        The un-normalized dilators (1, eoinf) of eq. 12.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> D = cga.dilator_paper(2.0)
        >>> [round(v, 6) for v in D.values.tolist()], cga.apply_to_points(D, jnp.ones(3)).round(6).tolist()
        ([1.0, 0.333333], [2.0, 2.0, 2.0])
    """
    d = _float_scalar(scale)
    return _stack(jnp.ones_like(d), (d - 1) / (d + 1), blades=KINDS["dilator"])


def _require_blades(name: str, m: Multivector, kind: str) -> None:
    if not isinstance(m, Multivector) or not set(m.blades) <= set(KINDS[kind]):
        raise ValueError(f"{name}: expected a {kind} Multivector (blades {list(_names(kind))})")


def _names(kind: str) -> Iterator[str]:
    return (alg.blade_name(b) for b in KINDS[kind])


def motor(rotation: Multivector, translation: Float[ArrayLike, "... 3"]) -> Multivector:
    """Motor ``T R``: rotate by the rotor, then translate by ``translation``.

    Args:
        rotation: rotors (``rotor``), batch shape broadcasting with the translations'.
        translation: (..., 3) translation vectors.
    Returns:
        The motors (8 components: 1, e12, e13, e23, e1inf, e2inf, e3inf, e123inf).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2), jnp.array([1.0, 0, 0]))
        >>> (cga.apply_to_points(M, jnp.array([1.0, 0, 0])).round(6) + 0.0).tolist()  # rotated, then moved
        [1.0, 1.0, 0.0]
    """
    _require_blades("rotation", rotation, "rotor")
    return (translator(translation) * rotation).embed(KINDS["motor"])


def similitude(
    rotation: Multivector, translation: Float[ArrayLike, "... 3"], scale: Float[ArrayLike, "*batch"]
) -> Multivector:
    """Similitude ``T R D``: x -> scale R x + translation (16 even components).

    Args:
        rotation: rotors (``rotor``); the three arguments broadcast together.
        translation: (..., 3) translation vectors.
        scale: (...) scale factors > 0.
    Returns:
        The similitudes (the 16 even blades).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.similitude(cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2), jnp.array([0, 0, 1.0]), 2.0)
        >>> (cga.apply_to_points(S, jnp.array([1.0, 0, 0])).round(6) + 0.0).tolist()
        [0.0, 2.0, 1.0]
    """
    _require_blades("rotation", rotation, "rotor")
    return (translator(translation) * rotation * dilator(scale)).embed(KINDS["similitude"])


# ---------------------------------------------------------------- the versor acting on points
_EO_EINF = 0b11000  # the bits of eo and einf: the dilation plane eo^einf


def _factored_pairs(blades_v: tuple[int, ...]) -> tuple[tuple[int, int], ...]:
    """Index pairs (X, X^eo^einf) of V's blades: a dilation's two halves."""
    index = {b: k for k, b in enumerate(blades_v)}
    return tuple((index[b], index[b | _EO_EINF]) for b in blades_v if not b & _EO_EINF and b | _EO_EINF in index)


@functools.cache
def _point_map(blades_v: tuple[int, ...]) -> dict[tuple[int, int], tuple[tuple[tuple[int, int], float], ...]]:
    """Generated affine form of ``V X ~V`` on up-projected points. Rows e1, e2, e3, eo of the output,
    columns e1, e2, e3, eo (=1), einf (=|x|^2/2) of the input: {(row, col): ((i, j), coef)...}.

    The terms are written in V's factored components (``_FactoredColumns``): for a blade pair
    (X, Y = X^eo^einf), ``v_X + v_Y`` and ``v_X - v_Y`` instead of v_X and v_Y. A dilation by d puts
    sqrt(d) on one of them and 1/sqrt(d) on the other, and in these components every entry of the map
    is a sum of products of such factors; in v_X, v_Y each entry of size 1/d came out of terms of size
    d that cancel (~d^2 ulps lost instead of ~d)."""
    rows = {b: k for k, b in enumerate(POINT_BLADES[:4])}
    pairs = _factored_pairs(blades_v)
    # v_X = (z_X + z_Y) / 2 and v_Y = (z_X - z_Y) / 2 in the factored components z
    substitute: dict[int, tuple[tuple[int, Fraction], ...]] = {i: ((i, Fraction(1)),) for i in range(len(blades_v))}
    for x, y in pairs:
        substitute[x] = ((x, Fraction(1, 2)), (y, Fraction(1, 2)))
        substitute[y] = ((x, Fraction(1, 2)), (y, Fraction(-1, 2)))
    entries: dict[tuple[int, int], dict[tuple[int, int], Fraction]] = {}
    for out, terms in _codegen.sandwich_terms(blades_v, POINT_BLADES):
        if out not in rows:
            continue
        for (i, j, col), coef in terms:
            acc = entries.setdefault((rows[out], col), {})
            for a, ca in substitute[i]:
                for b, cb in substitute[j]:
                    key = (min(a, b), max(a, b))
                    acc[key] = acc.get(key, 0) + Fraction(coef) * ca * cb
    return {
        key: tuple((ij, float(c)) for ij, c in sorted(acc.items()) if c != 0)
        for key, acc in entries.items()
        if any(c != 0 for c in acc.values())
    }


class _FactoredColumns:
    """V's factored components (``_point_map``), each computed on first use from the stored ones."""

    def __init__(self, columns: _codegen.Columns, pairs: tuple[tuple[int, int], ...]):
        self._columns = columns
        self._pairs = {x: (x, y, 1) for x, y in pairs} | {y: (x, y, -1) for x, y in pairs}
        self._cache: dict[int, Array] = {}

    def __getitem__(self, i: int) -> Array:
        if i not in self._pairs:
            return self._columns[i]
        if i not in self._cache:
            x, y, sign = self._pairs[i]
            self._cache[i] = self._columns[x] + self._columns[y] if sign > 0 else self._columns[x] - self._columns[y]
        return self._cache[i]


def _map_entries(v: Multivector, columns: _codegen.Columns | None = None) -> dict[tuple[int, int], Array]:
    cols: _codegen.Columns = _codegen.LazyColumns(v.values) if columns is None else columns
    return _map_entries_of(v.blades, cols, v.batch_shape)


def _map_entries_of(
    blades: tuple[int, ...], cols: _codegen.Columns, batch_shape: tuple[int, ...]
) -> dict[tuple[int, int], Array]:
    pairs = _factored_pairs(blades)
    if pairs:
        cols = _FactoredColumns(cols, pairs)
    entries = {}
    for key, terms in _point_map(blades).items():
        _, (value,) = _codegen.emit(((0, terms),), (cols, cols), batch_shape)
        entries[key] = value
    return entries


def fused_point_coordinates(
    v: Multivector, x: Float[Array, "... 3"], batch: tuple[int, ...]
) -> list[Float[Array, "*batch"]]:
    """The three coordinates (each of shape ``batch``) of ``apply_to_points(v, x, fused=True)``, written
    elementwise so that XLA fuses them with the computation of v; the caller chooses how to stack them
    (e.g. coordinate-major, then moved last: XLA:CPU's transpose emitter runs that 1.3x faster than a
    stack along the last axis for per-vertex blended motors)."""
    v, x = _same_batch_rank(v, x)
    return [jnp.broadcast_to(c, batch) for c in _mapped_coordinates(_map_entries(v), [x[..., i] for i in range(3)])]


def _mapped_coordinates(a: dict[tuple[int, int], Array], xs: list[Array]) -> list[Array]:
    """The three coordinates of the points ``xs`` (x, y, z columns) under the affine map ``a`` (``_map_entries``),
    divided by its eo row."""
    inputs = _map_inputs(a, xs)
    inv_w = 1.0 / _map_row(a, inputs, 3)
    return [_map_row(a, inputs, k) * inv_w for k in range(3)]


def _map_inputs(a: dict[tuple[int, int], Array], xs: list[Array]) -> dict[int, Array]:
    """The map's input columns but eo (= 1): e1, e2, e3 (the coordinates xs) and einf (|x|^2 / 2, where used)."""
    inputs = dict(enumerate(xs))
    if any(col == 4 for (_, col) in a):
        inputs[4] = 0.5 * (xs[0] ** 2 + xs[1] ** 2 + xs[2] ** 2)
    return inputs


def _map_row(a: dict[tuple[int, int], Array], inputs: dict[int, Array], r: int) -> Array:
    """Row r of the affine map ``a`` (``_map_entries``) applied to the input columns."""
    terms = [a[(r, c)] if c == 3 else a[(r, c)] * inputs[c] for c in range(5) if (r, c) in a]
    return functools.reduce(operator.add, terms)


def _point_major(v: Multivector, x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Point-major: three coordinates, written elementwise and stacked last, left for XLA to fuse."""
    batch = broadcast_batch("v", v.batch_shape, "x", x.shape[:-1])
    return jnp.stack(fused_point_coordinates(v, x, batch), axis=-1)


def _same_batch_rank(v: Multivector, x: Array) -> tuple[Multivector, Array]:
    """v and x with as many batch axes (leading unit axes added), as numpy would broadcast them."""
    n = max(v.values.ndim, x.ndim)
    return Multivector(lift_rank(v.values, n), v.blades), lift_rank(x, n)


def _rows_of_points(v: Multivector, x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """GPUs: one Triton kernel over blocks of points (``_jaxcga_shared.pallas_rows``) where V is one versor or one
    per point, of x's dtype; other broadcasts and mixed dtypes leave the layout to XLA (``_point_major``)."""
    batch = broadcast_batch("v", v.batch_shape, "x", x.shape[:-1])
    stored = v.batch_shape in ((), batch) and x.shape[:-1] == batch and v.dtype == x.dtype
    if not batch or not stored or not fits(v.values, x):
        return _point_major(v, x)
    return _rows_apply(v.blades, v.values, x)


def _rows_apply(blades: tuple[int, ...], values: Array, x: Array) -> Array:
    per_row, shared = ([values.reshape(-1, values.shape[-1])], []) if values.ndim > 1 else ([], [values])

    def without_triton(x_rows, v_rows):
        return _point_major(Multivector(v_rows, blades), x_rows)

    coordinates = row_coordinates(blades)
    return rowwise(coordinates, [x.reshape(-1, 3), *per_row], shared, 3, otherwise=without_triton).reshape(x.shape)


def row_coordinates(blades: tuple[int, ...]) -> RowFunction:
    """The ``rowwise`` function of ``_rows_apply``: x's columns first, then V's (per row or shared)."""

    def coordinates(row_columns, shared_columns):
        (x_cols, *v_cols) = row_columns
        cols = v_cols[0] if v_cols else shared_columns[0]
        return _mapped_coordinates(_map_entries_of(blades, cols, jnp.shape(cols[0])), x_cols)

    return coordinates


@per_platform("apply_to_points", gpu=_rows_of_points)
def _component_major(v: Multivector, x: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """Component-major: XLA:CPU then vectorizes the generated arithmetic along the points (measured 2-3x
    faster than on the interleaved (..., k) layout); the barriers keep XLA from fusing the transposes back
    into the arithmetic. On a GPU barriers cost more than they save (``_rows_of_points``)."""
    batch = broadcast_batch("v", v.batch_shape, "x", x.shape[:-1])
    v, x = _same_batch_rank(v, x)
    v_rows, x_rows = jax.lax.optimization_barrier((jnp.moveaxis(v.values, -1, 0), jnp.moveaxis(x, -1, 0)))
    coordinates = _mapped_coordinates(_map_entries(v, columns=v_rows), [x_rows[0], x_rows[1], x_rows[2]])
    # Three separate outputs form one multi-output loop that shares the generated products between
    # the rows; a stacked output would recompute them for every coordinate.
    rows = jax.lax.optimization_barrier(tuple(jnp.broadcast_to(c, batch) for c in coordinates))
    out = jax.lax.optimization_barrier(jnp.stack(rows, axis=0))
    return jnp.moveaxis(out, 0, -1)


def apply_to_points(v: Multivector, x: Float[ArrayLike, "... 3"], fused: bool = False) -> Float[Array, "... 3"]:
    """Apply a versor (rotor, translator, dilator, motor, similitude) to Euclidean points: the
    sandwich ``V up(x) V^-1`` down-projected, evaluated as the affine map whose entries are generated
    from V's components. Batch shapes of v and x broadcast: one motor per point or one for all.

    ``fused=True`` leaves the memory layout to XLA: use it when V is itself computed elementwise per
    point in the same jit (e.g. motors blended per vertex), so that the whole computation fuses into
    one loop instead of materializing V. The default is chosen per platform when the computation is
    lowered: on the CPU it re-lays V and x out component-major behind optimization barriers (measured
    2-3x faster for stored per-point versors); on GPUs, for one versor per point or one for all, it is one Triton
    kernel over blocks of points (``_jaxcga_shared.pallas_rows``; XLA's fused loop computes each coordinate in its
    own thread), and the fused formulation otherwise.

    Precision: with a dilation by d the map is evaluated in the dilation's factored components
    (``_point_map``); a normalized versor's 16 stored components determine it to ~max(d, 1/d) ulps.

    Hot path: x is checked for shape here, but values are not checked for NaN (that would cost a
    pass over the data); ``up``/``point`` check them.

    Args:
        v: versors (rotors, translators, dilators, motors, similitudes), batch shape broadcasting with x's (...).
        x: (..., 3) Euclidean points.
        fused: leave the memory layout to XLA (above).
    Returns:
        (..., 3) the moved points.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> T = cga.translator(jnp.array([0, 0, 1.0]))
        >>> cga.apply_to_points(T, jnp.zeros((2, 3))).tolist()  # one versor for all points
        [[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]
    """
    if not isinstance(v, Multivector):
        raise ValueError("v: expected a versor Multivector")
    x = check_vectors("x", x)
    broadcast_batch("v", v.batch_shape, "x", x.shape[:-1])
    if fused:
        return _point_major(v, x)
    return _component_major(v, x)


def versor_to_matrix(v: Multivector, normalized: bool = True) -> Float[Array, "... 4 4"]:
    """Homogeneous 4x4 matrix of a motor or similitude (V must be a versor: the |x|^2 column of its
    sandwich then vanishes).

    With ``normalized=False`` the matrix is the sandwich's own linear map on (x, 1): its last row is
    (0, 0, 0, lambda), lambda the eo-coefficient of ``V up(x) V^-1`` (1 / scale for a normalized
    similitude, 1 for a motor), and the top rows are lambda times those of the normalized matrix.

    Args:
        v: motors or similitudes.
        normalized: return the homogeneous matrix with last row (0, 0, 0, 1); False: the sandwich's own map (above).
    Returns:
        (..., 4, 4) the matrices.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2), jnp.array([1.0, 2.0, 3.0]))
        >>> (cga.versor_to_matrix(M).round(6) + 0.0).tolist()
        [[0.0, -1.0, 0.0, 1.0], [1.0, 0.0, 0.0, 2.0], [0.0, 0.0, 1.0, 3.0], [0.0, 0.0, 0.0, 1.0]]
    """
    a = _map_entries(v)
    zero = jnp.zeros(v.batch_shape, v.dtype)
    w = a[(3, 3)]
    if normalized:
        rows = [[a.get((r, c), zero) / w for c in range(4)] for r in range(3)]
        rows.append([zero, zero, zero, jnp.ones(v.batch_shape, v.dtype)])
    else:
        rows = [[a.get((r, c), zero) for c in range(4)] for r in range(3)]
        rows.append([zero, zero, zero, w])
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


# ---------------------------------------------------------------- quaternions
def rotor_to_quaternion(r: Multivector) -> Float[Array, "... 4"]:
    """Unit quaternion (w, x, y, z) of the same rotation as the rotor (same sign convention as
    scipy's ``Rotation.from_quat(..., scalar_first=True)``).

    Args:
        r: rotors.
    Returns:
        (..., 4) unit quaternions (w, x, y, z).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> q = cga.rotor_to_quaternion(cga.rotor(jnp.array([0, 0, 1.0]), jnp.pi / 2))
        >>> [round(v, 6) + 0.0 for v in q.tolist()]
        [0.707107, 0.0, 0.0, 0.707107]
    """
    _require_blades("r", r, "motor")
    return jnp.stack([r["1"], -r["e23"], r["e13"], -r["e12"]], axis=-1)


def quaternion_to_rotor(q: Float[ArrayLike, "... 4"]) -> Multivector:
    """Rotor of a quaternion (w, x, y, z) (normalized here).

    Args:
        q: (..., 4) quaternions (w, x, y, z), non-zero.
    Returns:
        The rotors (1, e12, e13, e23).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> R = cga.quaternion_to_rotor(jnp.array([1.0, 0, 0, 1.0]))  # a quarter turn about z
        >>> (cga.apply_to_points(R, jnp.array([1.0, 0, 0])).round(6) + 0.0).tolist()
        [0.0, 1.0, 0.0]
    """
    q = check_vectors("q", q, 4)
    length = jnp.linalg.norm(q, axis=-1)
    length = require(length, non_finite("q", q), (jnp.any(length == 0), "q: zero quaternion"))
    unit = q / length[..., None]
    return _stack(unit[..., 0], -unit[..., 3], unit[..., 2], -unit[..., 1], blades=_ROTOR)


def _quat_mul(p: Float[Array, "... 4"], q: Float[Array, "... 4"]) -> Float[Array, "... 4"]:
    pw, px, py, pz = (p[..., i] for i in range(4))
    qw, qx, qy, qz = (q[..., i] for i in range(4))
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def motor_rotor_translation(m: Multivector) -> tuple[Multivector, Float[Array, "... 3"]]:
    """Split a motor ``M = T R`` into its rotor R (a Multivector) and translation t (..., 3).

    Args:
        m: motors.
    Returns:
        (the rotors R, (..., 3) the translations t) with ``m = translator(t) R``.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 1.0, 0]), 0.3), jnp.array([1.0, 2.0, 3.0]))
        >>> R, t = cga.motor_rotor_translation(M)
        >>> t.round(6).tolist()
        [1.0, 2.0, 3.0]
    """
    _require_blades("m", m, "motor")
    m = m.embed(KINDS["motor"])
    r = Multivector(jnp.stack([m["1"], m["e12"], m["e13"], m["e23"]], axis=-1), _ROTOR)
    # T = M ~R / (R ~R); T = 1 - t einf / 2.
    t_part = m * ~r
    scale = r.values[..., 0] ** 2 + jnp.sum(r.values[..., 1:] ** 2, axis=-1)
    t = -2.0 * jnp.stack([t_part["e1inf"], t_part["e2inf"], t_part["e3inf"]], axis=-1) / scale[..., None]
    return r, t


# a motor's blades, rotor first; the einf part is the translator's, -(1/2) t einf R
_MOTOR_ROTOR, _MOVED_ORIGIN = KINDS["motor"][:4], KINDS["motor"][4:]
_DILATED_ROTOR = alg.parse_blades(("eoinf", "e12oinf", "e13oinf", "e23oinf"))  # R (eo^einf) on the rotor blades


def _components(v: Multivector, blades: tuple[int, ...]) -> Float[Array, "... k"]:
    return jnp.stack([v.values[..., v.blades.index(b)] for b in blades], axis=-1)


def similitude_dilation(s: Multivector) -> tuple[Float[Array, "... 4"], Float[Array, "*batch"], Float[Array, "*batch"]]:
    """The rotor part ``rc`` (..., 4) of a similitude ``S = k T R D(e^lam)`` (k a nonzero scalar factor; ``s``
    embedded in the similitude blades), its squared length ``c2`` and the log scale ``lam`` (S scales points by
    e^lam about the origin).

    S = k (R D - (1/2) e^(-lam/2) t einf R) with R D = R (cosh(lam/2) + sinh(lam/2) eo^einf): the rotor blades
    hold ``rc = k R cosh``, the ``eo^einf`` blades ``rs = k R sinh``, and ``<rc, rs> / <rc, rc> = tanh(lam/2)``.
    A runtime error when ``|rs| >= |rc|`` (not a similitude versor)."""
    rc, c2, lam, bad = _similitude_dilation_unchecked(s)
    return rc, require(c2, (bad, "s: not a similitude versor")), lam


def _similitude_dilation_unchecked(s: Multivector):
    """``similitude_dilation`` without its check, and where it fails (``|rs| >= |rc|``: NaN there)."""
    rc, rs = _components(s, _MOTOR_ROTOR), _components(s, _DILATED_ROTOR)
    c2, s2, cs = jnp.sum(rc * rc, -1), jnp.sum(rs * rs, -1), jnp.sum(rc * rs, -1)
    return rc, c2, 2.0 * jnp.arctanh(cs / c2), c2 <= s2


def similitude_motor_log_scale(s: Multivector) -> tuple[Multivector, Float[Array, "*batch"]]:
    """Factor a similitude ``S = T R D`` as its motor ``T R`` (unit rotor R) and the log of its scale, lam: S moves
    a point as the motor does after scaling it by e^lam about the origin. Products of the components only, no
    matrix.

    Args:
        s: similitudes (motors, dilators, any scalar factor), batch shape (...).
    Returns:
        the motors, batch shape (...), and lam (...).

    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.similitude(cga.rotor(jnp.array([0, 0, 1.0]), 0.5), jnp.zeros(3), 2.0)
        >>> M, lam = cga.similitude_motor_log_scale(S)
        >>> round(float(jnp.exp(lam)), 6)
        2.0
    """
    motors, lam, bad = similitude_motor_log_scale_unchecked(s)
    return Multivector(require(motors.values, (bad, "s: not a similitude versor")), motors.blades), lam


def similitude_motor_log_scale_unchecked(s: Multivector) -> tuple[Multivector, Float[Array, "*batch"], Array]:
    """``similitude_motor_log_scale`` without its check, and where it fails (not a similitude versor: NaN there),
    for callers that check once their result is computed (``deform.skin_cga_motor_blend``: on a GPU a check is a
    host round trip)."""
    if not isinstance(s, Multivector) or not set(s.blades) <= set(KINDS["similitude"]):
        raise ValueError("s: expected a similitude Multivector (even blades)")
    s = s.embed(KINDS["similitude"])
    rc, c2, lam, bad = _similitude_dilation_unchecked(s)
    # S's einf blades are k e^(-lam/2) times the unit motor's, and k cosh(lam/2) = sqrt(c2)
    moved = _components(s, _MOVED_ORIGIN) * (0.5 * (1.0 + jnp.exp(lam)))[..., None]
    inv = jax.lax.rsqrt(c2)[..., None]
    return Multivector(jnp.concatenate([rc * inv, moved * inv], axis=-1), KINDS["motor"]), lam, bad


def motor_to_dual_quaternion(m: Multivector) -> Float[Array, "... 8"]:
    """Unit dual quaternion (real w, x, y, z, dual w, x, y, z) with dual part t q / 2.

    Args:
        m: motors.
    Returns:
        (..., 8) unit dual quaternions: real part (w, x, y, z), then dual part (w, x, y, z).
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.motor(cga.rotor(jnp.array([0, 0, 1.0]), 0.0), jnp.array([2.0, 0, 0]))
        >>> dq = cga.motor_to_dual_quaternion(M)
        >>> (dq.round(6) + 0.0).tolist()
        [1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0]
    """
    r, t = motor_rotor_translation(m)
    q = rotor_to_quaternion(r)
    t_quat = jnp.concatenate([jnp.zeros(t.shape[:-1] + (1,), t.dtype), t], axis=-1)
    return jnp.concatenate([q, 0.5 * _quat_mul(t_quat, q)], axis=-1)


def dual_quaternion_to_motor(dq: Float[ArrayLike, "... 8"]) -> Multivector:
    """Motor of a unit dual quaternion (real part, dual part), translation t = 2 q_d q_r^*.

    Args:
        dq: (..., 8) unit dual quaternions: real part (w, x, y, z), then dual part (w, x, y, z).
    Returns:
        The motors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> M = cga.dual_quaternion_to_motor(jnp.array([1.0, 0, 0, 0, 0, 1.0, 0, 0]))  # a translation by (2, 0, 0)
        >>> (cga.apply_to_points(M, jnp.zeros(3)).round(6) + 0.0).tolist()
        [2.0, 0.0, 0.0]
    """
    dq = check_finite("dq", check_vectors("dq", dq, 8))
    q, qd = dq[..., :4], dq[..., 4:]
    norm2 = jnp.sum(q * q, axis=-1, keepdims=True)
    norm2 = require(norm2, (jnp.any(norm2 == 0), "dq: zero real part"))
    conj = q * jnp.asarray([1.0, -1.0, -1.0, -1.0], q.dtype)
    t = 2.0 * _quat_mul(qd, conj)[..., 1:] / norm2
    return motor(quaternion_to_rotor(q), t)


def matrix_to_quaternion(rotation: Float[ArrayLike, "... 3 3"]) -> Float[Array, "... 4"]:
    """Quaternion (w, x, y, z), w >= 0, of a rotation matrix (Shepperd's method: the best-
    conditioned of four formulas, chosen per matrix).

    Args:
        rotation: (..., 3, 3) rotation matrices.
    Returns:
        (..., 4) unit quaternions (w, x, y, z) with w >= 0.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> cga.matrix_to_quaternion(jnp.eye(3)).tolist()
        [1.0, 0.0, 0.0, 0.0]
    """
    m = jnp.asarray(rotation)
    tr = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    cands = jnp.stack(
        [
            jnp.stack(
                [1 + tr, m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
            ),
            jnp.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + 2 * m[..., 0, 0] - tr,
                    m[..., 0, 1] + m[..., 1, 0],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                -1,
            ),
            jnp.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 0, 1] + m[..., 1, 0],
                    1 + 2 * m[..., 1, 1] - tr,
                    m[..., 1, 2] + m[..., 2, 1],
                ],
                -1,
            ),
            jnp.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 1, 2] + m[..., 2, 1],
                    1 + 2 * m[..., 2, 2] - tr,
                ],
                -1,
            ),
        ],
        axis=-2,
    )
    pivots = jnp.stack([tr, m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]], axis=-1)
    best = jnp.argmax(pivots, axis=-1)
    q = jnp.take_along_axis(cands, best[..., None, None], axis=-2)[..., 0, :]
    q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return q * jnp.where(q[..., :1] < 0, -1.0, 1.0)


def matrix_to_motor(matrix: Float[ArrayLike, "... 4 4"]) -> Multivector:
    """Motor of a rigid homogeneous 4x4 matrix (rotation block must be orthonormal, det +1).

    Args:
        matrix: (..., 4, 4) rigid homogeneous matrices.
    Returns:
        The motors.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> A = jnp.array([[0, -1.0, 0, 1], [1, 0, 0, 2], [0, 0, 1, 3], [0, 0, 0, 1]])  # a quarter turn about z, moved
        >>> (cga.versor_to_matrix(cga.matrix_to_motor(A)).round(6) + 0.0).tolist() == A.tolist()
        True
    """
    matrix = jnp.asarray(matrix)
    if matrix.ndim < 2 or matrix.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"matrix: expected shape (..., 4, 4) or (..., 3, 4), got {matrix.shape}")
    rot = matrix[..., :3, :3]
    err = jnp.max(
        jnp.abs(
            jnp.matmul(jnp.swapaxes(rot, -1, -2), rot, precision=EXACT)
            - lift_rank(jnp.eye(3, dtype=rot.dtype), rot.ndim)
        ),
        initial=0.0,
    )
    rigid = (err > 1e-5) | jnp.any(jnp.linalg.det(rot) < 0), "matrix: not a rigid motion"
    rot = require(rot, non_finite("matrix", matrix), rigid)
    return motor(quaternion_to_rotor(matrix_to_quaternion(rot)), matrix[..., :3, 3])


def matrix_to_similitude(matrix: Float[ArrayLike, "... 4 4"], tolerance: float = 1e-5) -> Multivector:
    """Similitude ``T R D`` of a homogeneous matrix ``[s Q | t]`` with Q a rotation and s > 0 a
    uniform scale (glTF inverse bind matrices, node matrices with uniform scale).

    Args:
        matrix: (..., 4, 4) or (..., 3, 4).
        tolerance: allowed deviation of ``A^T A / s^2`` from the identity (shear or non-uniform scale
            beyond it raises a ValueError, inside jit a runtime error with the message).

    Returns:
        The similitudes.
    Examples:
        >>> import jax.numpy as jnp
        >>> import jaxcga as cga
        >>> S = cga.matrix_to_similitude(jnp.diag(jnp.array([2.0, 2.0, 2.0, 1.0])))
        >>> cga.apply_to_points(S, jnp.ones(3)).round(6).tolist()
        [2.0, 2.0, 2.0]
    """
    matrix = jnp.asarray(matrix)
    if matrix.ndim < 2 or matrix.shape[-2:] not in ((4, 4), (3, 4)):
        raise ValueError(f"matrix: expected shape (..., 4, 4) or (..., 3, 4), got {matrix.shape}")
    matrix = check_finite("matrix", matrix)
    a = matrix[..., :3, :3]
    det = jnp.linalg.det(a)
    det = require(det, (jnp.any(det <= 0), "matrix: not a similitude (determinant <= 0: reflection or singular)"))
    s = jnp.cbrt(det)
    rot = a / s[..., None, None]
    err = jnp.max(
        jnp.abs(
            jnp.matmul(jnp.swapaxes(rot, -1, -2), rot, precision=EXACT)
            - lift_rank(jnp.eye(3, dtype=rot.dtype), rot.ndim)
        ),
        initial=0.0,
    )
    rot = require(rot, (err > tolerance, "matrix: not a similitude (shear or non-uniform scale)"))
    return similitude(quaternion_to_rotor(matrix_to_quaternion(rot)), matrix[..., :3, 3], s)
