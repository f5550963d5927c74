"""Input validation of the multivector API, runtime errors, and float32 support."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga
from jaxcga import Multivector


# ---------------------------------------------------------------- construction
def test_wrong_last_axis_names_values():
    with pytest.raises(ValueError, match=r"values: expected last axis of length 8 .* got shape \(4, 5\)"):
        Multivector(jnp.zeros((4, 5)), "motor")
    with pytest.raises(ValueError, match="values: expected last axis of length 1"):
        Multivector(jnp.float64(1.0), ("1",))  # 0-d values have no blade axis


def test_unknown_kind_names_blades():
    with pytest.raises(ValueError, match=r"blades: unknown kind 'motr'.*'motor'"):
        Multivector(jnp.zeros(8), "motr")
    with pytest.raises(ValueError, match="blades: unknown kind"):
        jaxcga.zeros("spinor")


def test_unknown_blade_name_names_blades():
    with pytest.raises(ValueError, match=r"blades: unknown blade name 'e9'"):
        Multivector(jnp.zeros(2), ("e1", "e9"))
    with pytest.raises(ValueError, match=r"blades: unknown blade name 'e21'"):
        Multivector(jnp.zeros(1), ("e21",))  # only canonical order
    with pytest.raises(ValueError, match=r"blades: unknown blade name 'einfo'"):
        jaxcga.basis_vector("einfo")
    m = Multivector(jnp.zeros(5), "vector")
    with pytest.raises(ValueError, match=r"blades: unknown blade name 'e6'"):
        m["e6"]


def test_bad_blade_bitmasks_and_repeats():
    with pytest.raises(ValueError, match=r"blades: expected blade names or bitmasks in \[0, 32\)"):
        Multivector(jnp.zeros(1), (32,))
    with pytest.raises(ValueError, match="blades: repeated blade"):
        Multivector(jnp.zeros(2), ("e1", "e1"))


def test_good_construction_from_names_and_bitmasks_agree():
    a = Multivector(jnp.array([1.0, 2.0]), ("e1", "e12"))
    b = Multivector(jnp.array([1.0, 2.0]), (0b1, 0b11))
    assert a.blades == b.blades == (1, 3)
    np.testing.assert_array_equal(np.asarray(a.values), np.asarray(b.values))
    # integer input is promoted to the default float type
    c = Multivector(jnp.arange(5), "vector")
    assert c.dtype == jnp.float64


def test_embed_into_smaller_set_names_blades():
    with pytest.raises(ValueError, match=r"blades: cannot embed, \[.*'e1inf'.*\] not in target set"):
        jaxcga.translator(jnp.array([1.0, 0.0, 0.0])).embed("rotor")


# ---------------------------------------------------------------- batch shapes
BINARY = {
    "geometric": lambda a, b: a * b,
    "outer": lambda a, b: a ^ b,
    "inner": lambda a, b: a | b,
    "left_contraction": jaxcga.left_contraction,
    "scalar_product": jaxcga.scalar_product,
    "meet": jaxcga.meet,
    "commutator": jaxcga.commutator,
    "add": lambda a, b: a + b,
    "sub": lambda a, b: a - b,
}


@pytest.mark.parametrize("op", list(BINARY))
def test_non_broadcasting_batches_name_the_operands(op):
    a = Multivector(jnp.zeros((4, 5)), "vector")
    b = Multivector(jnp.zeros((3, 8)), "motor")
    with pytest.raises(ValueError, match=r"a and b: batch shapes \(4,\) and \(3,\) do not broadcast"):
        BINARY[op](a, b)


def test_non_broadcasting_sandwich_names_v_and_x():
    v = Multivector(jnp.ones((4, 8)), "motor")
    x = Multivector(jnp.zeros((3, 5)), "vector")
    with pytest.raises(ValueError, match=r"v and x: batch shapes \(4,\) and \(3,\) do not broadcast"):
        _ = v >> x


def test_sandwich_rejects_non_multivectors():
    with pytest.raises(ValueError, match="sandwich: v and x must be Multivectors"):
        jaxcga.sandwich(Multivector(jnp.ones(8), "motor"), jnp.zeros(5))  # pyright: ignore[reportArgumentType]


# ---------------------------------------------------------------- non-finite input
def test_up_with_nan_raises_eagerly_and_under_jit():
    x = jnp.array([[0.0, 1.0, 2.0], [jnp.nan, 0.0, 0.0]])
    with pytest.raises(ValueError, match="x: non-finite values"):  # concrete input: a plain error, no banner
        jaxcga.up(x)
    with pytest.raises(RuntimeError, match="x: non-finite values"):
        jax.block_until_ready(jax.jit(jaxcga.up)(x))  # on a GPU the check fails when the result is ready
    with pytest.raises(ValueError, match="x: non-finite values"):
        jaxcga.up(jnp.array([jnp.inf, 0.0, 0.0]))
    # finite input passes, inside jit too
    ok = jax.jit(jaxcga.up)(jnp.array([1.0, 2.0, 2.0]))
    assert float(ok["einf"]) == 4.5


def test_up_wrong_shape_names_x():
    with pytest.raises(ValueError, match=r"x: expected an array of shape \(\.\.\., 3\), got shape \(4, 2\)"):
        jaxcga.up(jnp.zeros((4, 2)))


# ---------------------------------------------------------------- singular input
@pytest.mark.parametrize(
    "blades,values",
    [
        (("eo",), [1.0]),  # null vectors
        (("einf",), [1.0]),
        (("1", "e1"), [1.0, 1.0]),  # (1 + e1)(1 - e1) = 0
        (("1",), [0.0]),
    ],
    ids=["eo", "einf", "1+e1", "zero"],
)
def test_inverse_of_singular_multivector_raises(blades, values):
    m = Multivector(jnp.asarray(values), blades)
    with pytest.raises(ValueError, match="inverse: multivector is not invertible"):
        jaxcga.inverse(m)


def test_division_by_singular_multivector_raises():
    X = jaxcga.up(jnp.array([1.0, 2.0, 0.5]))  # a conformal point is a null vector
    with pytest.raises(ValueError, match="inverse: multivector is not invertible"):
        _ = Multivector(jnp.ones(1), ("1",)) / X


def test_inverse_of_singular_multivector_raises_under_jit():
    inverse = jax.jit(jaxcga.inverse)
    with pytest.raises(RuntimeError, match="inverse: multivector is not invertible"):
        jax.block_until_ready(inverse(Multivector(jnp.array([0.0, 1.0]), ("e1", "eo"))))  # eo
    # the same compiled function accepts an invertible input
    inv = inverse(Multivector(jnp.array([2.0, 0.0]), ("e1", "eo")))  # 2 e1
    np.testing.assert_allclose(np.asarray(inv["e1"]), 0.5)
    np.testing.assert_allclose(np.asarray(inv["eo"]), 0.0)


def test_inverse_raises_if_any_batch_element_is_singular():
    m = Multivector(jnp.array([[2.0, 0.0], [1.0, 1.0]]), ("1", "e1"))
    with pytest.raises(ValueError, match="not invertible"):
        jaxcga.inverse(m)
    # the invertible element alone is fine
    np.testing.assert_allclose(np.asarray(jaxcga.inverse(Multivector(m.values[0], m.blades)).values[0]), 0.5)


def test_near_singular_but_invertible_passes():
    # 1 + 0.999 e1 is invertible: (1 + a e1)^-1 = (1 - a e1) / (1 - a^2)
    a = 0.999
    inv = jaxcga.inverse(Multivector(jnp.array([1.0, a]), ("1", "e1")))
    np.testing.assert_allclose(np.asarray(inv.values), np.array([1.0, -a]) / (1 - a * a), rtol=1e-9)


def test_versor_inverse_of_null_raises():
    with pytest.raises(ValueError, match="versor_inverse: v ~v is zero"):
        jaxcga.versor_inverse(jaxcga.basis_vector("einf"))


def test_normalize_zero_raises():
    with pytest.raises(ValueError, match="normalize: m has zero norm"):
        jaxcga.normalize(jaxcga.zeros("vector"))
    with pytest.raises(RuntimeError, match="normalize: m has zero norm"):
        jax.block_until_ready(jax.jit(jaxcga.normalize)(jaxcga.zeros("full", (2,))))
    with pytest.raises(ValueError, match="normalize: motor has non-positive norm"):
        jaxcga.normalize(jaxcga.zeros("motor"))
    with pytest.raises(ValueError, match="normalize: m has zero norm"):
        jaxcga.normalize(jaxcga.up(jnp.array([1.0, 2.0, 3.0])))  # a null vector


# ---------------------------------------------------------------- float32
@pytest.mark.slow
def test_float32_round_trip():
    f32 = jnp.float32
    x = jnp.array([[1.0, 2.0, 3.0], [-0.5, 0.25, 4.0]], f32)
    X = jaxcga.up(x)
    assert X.dtype == f32
    R = jaxcga.rotor(jnp.array([0.0, 0.0, 1.0], f32), f32(np.pi / 2))
    M = jaxcga.motor(R, jnp.array([1.0, 0.0, 0.0], f32))
    assert R.dtype == M.dtype == f32
    Y = M >> X
    assert Y.dtype == f32
    y = jaxcga.down(Y)
    assert y.dtype == f32
    # rotate +90 degrees about z, then translate by e1
    expected = np.stack([1.0 - x[:, 1], x[:, 0], x[:, 2]], axis=-1)
    np.testing.assert_allclose(np.asarray(y), expected, atol=1e-5)
    # back again with the inverse
    x_back = jaxcga.down(jaxcga.versor_inverse(M) >> Y)
    assert x_back.dtype == f32
    np.testing.assert_allclose(np.asarray(x_back), np.asarray(x), atol=1e-5)

    X0, X1 = Multivector(X.values[0], X.blades), Multivector(X.values[1], X.blades)
    results = {
        "geometric": M * X,
        "meet": jaxcga.meet(X, M),
        "sum": M + 1.0,
        "dual": jaxcga.dual(X),
        "inverse": jaxcga.inverse(M),
        "normalize_motor": jaxcga.normalize(3.0 * M),
        "pseudoscalar": jaxcga.pseudoscalar(f32),
        "line": jaxcga.line(X0, X1),
    }
    for name, out in results.items():
        assert out.dtype == f32, name
    for name, out in {
        "scalar_product": jaxcga.scalar_product(X, X),
        "component": M["e12"],
        "missing component": M["eoinf"],
        "distance": jaxcga.distance(X0, X1),
    }.items():
        assert out.dtype == f32, name
    np.testing.assert_allclose(float(jaxcga.distance(X0, X1)), np.linalg.norm(x[0] - x[1]), rtol=1e-6)
    # and the float32 values agree with the float64 computation
    M64 = Multivector(M.values.astype(jnp.float64), M.blades)
    np.testing.assert_allclose(np.asarray(jaxcga.inverse(M).values), np.asarray(jaxcga.inverse(M64).values), atol=1e-5)
    np.testing.assert_allclose(np.asarray((M * M).values), np.asarray((M64 * M64).values), atol=1e-5)


def test_float32_under_jit():
    f32 = jnp.float32
    M = jaxcga.motor(jaxcga.rotor(jnp.array([1.0, 0.0, 0.0], f32), f32(0.3)), jnp.array([0.0, 1.0, 0.0], f32))
    X = jaxcga.up(jnp.ones((3, 3), f32))
    out = jax.jit(jaxcga.sandwich)(M, X)
    assert out.dtype == f32
    np.testing.assert_allclose(np.asarray(out.values), np.asarray((M >> X).values), rtol=1e-6)


def test_mixed_precision_is_rejected_under_strict_promotion():
    a = Multivector(jnp.ones(5, jnp.float32), "vector")
    b = Multivector(jnp.ones(5, jnp.float64), "vector")
    with pytest.raises(Exception, match="promotion"):
        _ = a * b


def test_float32_dilator_and_similitude():
    f32 = jnp.float32
    assert jaxcga.dilator(jnp.asarray(2.0, f32)).dtype == f32
    assert jaxcga.dilator_paper(jnp.asarray(2.0, f32)).dtype == f32
    R = jaxcga.rotor(jnp.array([0.0, 0.0, 1.0], f32), f32(0.3))
    S = jaxcga.similitude(R, jnp.array([1.0, 0.0, 0.0], f32), jnp.asarray(2.0, f32))
    assert S.dtype == f32
