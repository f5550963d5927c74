"""Every product and operation of jaxcga against the ``clifford`` package's G(4,1) (g3c).

Operands are random multivectors on every blade set in ``jaxcga.KINDS`` (all pairs for binary
products), converted to clifford through ``_reference`` (null blades = clifford outer products of
e1, e2, e3, eo, einf). Tolerance 1e-12.
"""

from __future__ import annotations

import itertools

import jax.numpy as jnp
import numpy as np
import pytest

import jaxcga
from jaxcga import Multivector

# the generated product tables behind every public product, checked against the reference algebra
from jaxcga._multivector import product as generated_product

from . import _reference as ref

KIND_NAMES = tuple(jaxcga.KINDS)
BATCH = 2  # every random operand is a batch of two, checked element by element
TOL = 1e-12


def _random_operands(seed: int) -> dict[str, Multivector]:
    rng = np.random.default_rng(seed)
    return {kind: ref.random_multivector(rng, kind, (BATCH,)) for kind in KIND_NAMES}


OPERANDS_A = _random_operands(1)
OPERANDS_B = _random_operands(2)
PAIRS = list(itertools.product(KIND_NAMES, KIND_NAMES))


def _elements(m: Multivector) -> list:
    return ref.to_clifford_list(m)


def _grades(m: Multivector) -> set[int]:
    return {bin(b).count("1") for b in m.blades}


def _project(mv, grades):
    """Grade projection in clifford, through its own grade masks (``mv(g)`` would compile a numba
    kernel per grade literal)."""
    mask = np.zeros(ref.LAYOUT.gaDims, dtype=bool)
    for g in grades:
        mask |= ref.LAYOUT.grade_mask(g)
    return ref.LAYOUT.MultiVector(np.where(mask, mv.value, 0.0))


# ---------------------------------------------------------------- binary products, all kind pairs
BINARY = {
    "geometric": (lambda a, b: a * b, lambda a, b: a * b),
    "outer": (lambda a, b: a ^ b, lambda a, b: a ^ b),
    "inner": (lambda a, b: a | b, lambda a, b: a | b),
    "left_contraction": (jaxcga.left_contraction, lambda a, b: a.lc(b)),
    "meet": (jaxcga.meet, lambda a, b: a.vee(b)),
    "commutator": (jaxcga.commutator, lambda a, b: (a * b - b * a) / 2),
}


@pytest.mark.parametrize("kind_a,kind_b", PAIRS, ids=[f"{a}-{b}" for a, b in PAIRS])
def test_binary_products_match_clifford(kind_a, kind_b):
    a, b = OPERANDS_A[kind_a], OPERANDS_B[kind_b]
    xs, ys = _elements(a), _elements(b)
    for op, (ours, theirs) in BINARY.items():
        out = ours(a, b)
        assert isinstance(out, Multivector)
        assert out.batch_shape == (BATCH,)
        expected = [theirs(x, y) for x, y in zip(xs, ys)]
        ref.assert_mv_close(out, expected, atol=TOL, rtol=TOL, err_msg=f"{op}({kind_a}, {kind_b})")
    out = jaxcga.scalar_product(a, b)
    assert out.shape == (BATCH,)
    expected = [(x * y).value[0] for x, y in zip(xs, ys)]
    np.testing.assert_allclose(np.asarray(out), expected, atol=TOL, rtol=TOL, err_msg="scalar_product")


ALIASES = {
    "geometric": (jaxcga.geometric, lambda a, b: a * b),
    "outer": (jaxcga.outer, lambda a, b: a ^ b),
    "inner": (jaxcga.inner, lambda a, b: a | b),
    "intersect": (jaxcga.intersect, lambda a, b: a.vee(b)),
    "sum": (lambda a, b: a + b, lambda a, b: a + b),
    "difference": (lambda a, b: a - b, lambda a, b: a - b),
    "rsub": (lambda a, b: b.__rsub__(a), lambda a, b: a - b),
    "rxor_scalar": (lambda a, b: 2.0 ^ b, lambda a, b: 2.0 ^ b),
    "ror_scalar": (lambda a, b: 2.0 | b, lambda a, b: 2.0 | b),  # zero: no scalar part in |
}
ALIAS_PAIRS = [(k, k) for k in KIND_NAMES] + [("motor", "vector"), ("vector", "full"), ("full", "scalar")]


@pytest.mark.parametrize("op", list(ALIASES))
def test_product_functions_and_operators_match_clifford(op):
    ours, theirs = ALIASES[op]
    for kind_a, kind_b in ALIAS_PAIRS:
        a, b = OPERANDS_A[kind_a], OPERANDS_B[kind_b]
        expected = [theirs(x, y) for x, y in zip(_elements(a), _elements(b))]
        ref.assert_mv_close(ours(a, b), expected, atol=TOL, rtol=TOL, err_msg=f"{op}({kind_a}, {kind_b})")


def test_products_are_not_all_trivial():
    """Guard for the comparisons above: the reference itself distinguishes the products."""
    a, b = _elements(OPERANDS_A["full"])[0], _elements(OPERANDS_B["full"])[0]
    results = [a * b, a ^ b, a | b, a.lc(b), a.vee(b)]
    for x, y in itertools.combinations(results, 2):
        assert not np.allclose(x.value, y.value)


# ---------------------------------------------------------------- unary operations, every kind
UNARY = {
    "reverse_op": (lambda m: ~m, lambda m: ~m),
    "reverse": (jaxcga.reverse, lambda m: ~m),
    "involution": (jaxcga.involution, lambda m: m.gradeInvol()),
    "conjugate": (jaxcga.conjugate, lambda m: m.conjugate()),
    "dual": (jaxcga.dual, lambda m: m.dual()),
    "dual_paper": (jaxcga.dual, lambda m: -(m * ref.I5)),  # m* = -m I (eq. 7)
    "undual": (jaxcga.undual, lambda m: m * ref.I5),
}
ARITHMETIC = {
    "negate": (lambda m: -m, lambda m: -m),
    "scale": (lambda m: 2.5 * m, lambda m: 2.5 * m),
    "divide": (lambda m: m / 4.0, lambda m: m / 4.0),
    "add_scalar": (lambda m: m + 1.5, lambda m: m + 1.5),
    "radd_scalar": (lambda m: 1.5 + m, lambda m: m + 1.5),
    "rsub_scalar": (lambda m: 1.5 - m, lambda m: 1.5 - m),
}


@pytest.mark.parametrize("kind", KIND_NAMES)
@pytest.mark.parametrize("op", list(UNARY))
def test_unary_matches_clifford(op, kind):
    ours, theirs = UNARY[op]
    m = OPERANDS_A[kind]
    out = ours(m)
    assert out.batch_shape == (BATCH,)
    ref.assert_mv_close(out, [theirs(x) for x in _elements(m)], atol=TOL, rtol=TOL, err_msg=f"{op}({kind})")


@pytest.mark.parametrize("op", list(ARITHMETIC))
def test_scalar_arithmetic_matches_clifford(op):
    ours, theirs = ARITHMETIC[op]
    for kind in ("scalar", "vector", "motor", "full"):
        m = OPERANDS_A[kind]
        ref.assert_mv_close(ours(m), [theirs(x) for x in _elements(m)], atol=TOL, rtol=TOL, err_msg=f"{op}({kind})")


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_grade_projection_matches_clifford(kind):
    m = OPERANDS_A[kind]
    elements = _elements(m)
    # the odd and the even grades (together every grade), by function and by method
    for grades, out in [((1, 3, 5), jaxcga.grade(m, 1, 3, 5)), ((0, 2, 4), m.grade(0, 2, 4))]:
        assert _grades(out) <= set(grades)
        ref.assert_mv_close(out, [_project(x, grades) for x in elements], atol=TOL, rtol=TOL)
    if kind == "full":
        for g in range(6):
            out = m.grade(g)
            assert _grades(out) == {g}
            ref.assert_mv_close(out, [_project(x, (g,)) for x in elements], atol=TOL, rtol=TOL)


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_norm_and_norm2_match_clifford(kind):
    m = OPERANDS_A[kind]
    elements = _elements(m)
    np.testing.assert_allclose(np.asarray(jaxcga.norm2(m)), [x.mag2() for x in elements], atol=TOL, rtol=TOL)
    np.testing.assert_allclose(np.asarray(jaxcga.norm(m)), [abs(x) for x in elements], atol=TOL, rtol=TOL)


def test_norm2_can_be_negative():
    # e- = eo + einf/2 has square -1
    e_minus = Multivector(jnp.array([1.0, 0.5]), ("eo", "einf"))
    assert float(jaxcga.norm2(e_minus)) == pytest.approx(-1.0, abs=TOL)
    assert float(jaxcga.norm(e_minus)) == pytest.approx(1.0, abs=TOL)


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_inverse_matches_clifford(kind):
    m = OPERANDS_A[kind]
    inv = jaxcga.inverse(m)
    elements = _elements(m)
    expected = [x.inv() for x in elements]
    ref.assert_mv_close(inv, expected, atol=TOL, rtol=TOL, err_msg=kind)
    # and it is a two-sided inverse (products taken in clifford)
    one = (1.0 + 0 * ref.E1).value
    for x, y in zip(elements, _elements(inv)):
        np.testing.assert_allclose((x * y).value, one, atol=1e-10)
        np.testing.assert_allclose((y * x).value, one, atol=1e-10)


def test_division_is_multiplication_by_inverse():
    a, b = OPERANDS_A["full"], OPERANDS_B["full"]
    expected = [y * x.inv() for x, y in zip(_elements(a), _elements(b))]
    ref.assert_mv_close(b / a, expected, atol=1e-10, rtol=1e-10)


# ---------------------------------------------------------------- versors
def _versors() -> dict[str, Multivector]:
    rng = np.random.default_rng(7)
    axis = rng.normal(size=(BATCH, 3))
    angle = rng.uniform(-3.0, 3.0, size=BATCH)
    t = rng.normal(size=(BATCH, 3))
    scale = rng.uniform(0.3, 3.0, size=BATCH)
    R = jaxcga.rotor(axis, angle)
    normal = rng.normal(size=(BATCH, 3))
    return {
        "rotor": R,
        "translator": jaxcga.translator(t),
        "dilator": jaxcga.dilator(scale),
        "dilator_paper": jaxcga.dilator_paper(scale),
        "motor": jaxcga.motor(R, t),
        "motor_scaled": 3.0 * jaxcga.motor(R, t),
        "similitude": jaxcga.similitude(R, t, scale),
        "reflection_plane": jaxcga.plane(normal, rng.normal(size=BATCH)),
        "rotor_from_bivector": jaxcga.rotor_from_bivector(normal, angle),
    }


VERSORS = _versors()


@pytest.mark.parametrize("name", list(VERSORS))
def test_versor_inverse_matches_clifford(name):
    v = VERSORS[name]
    expected = [x.inv() for x in _elements(v)]
    ref.assert_mv_close(jaxcga.versor_inverse(v), expected, atol=1e-12, rtol=1e-12, err_msg=name)
    ref.assert_mv_close(jaxcga.inverse(v), expected, atol=1e-12, rtol=1e-12, err_msg=name)


@pytest.mark.parametrize("kind", KIND_NAMES)
@pytest.mark.parametrize("name", list(VERSORS))
def test_sandwich_matches_clifford(name, kind):
    v, x = VERSORS[name], OPERANDS_A[kind]
    grades = _grades(x)
    expected = [_project(vc * xc * vc.inv(), grades) for vc, xc in zip(_elements(v), _elements(x))]
    for out in (v >> x, jaxcga.sandwich(v, x)):
        assert _grades(out) <= grades
        ref.assert_mv_close(out, expected, atol=TOL, rtol=TOL, err_msg=f"{name} >> {kind}")


def test_versors_are_versors_in_clifford():
    """The versors used above satisfy V ~V = scalar, so V X V^-1 is a true versor action."""
    for name, v in VERSORS.items():
        for vc in _elements(v):
            vv = vc * ~vc
            assert np.allclose(vv.value[1:], 0.0, atol=1e-12), name
            assert abs(vv.value[0]) > 1e-3, name


# ---------------------------------------------------------------- normalize
MOTOR_SUBSETS = [k for k in KIND_NAMES if set(jaxcga.KINDS[k]) <= set(jaxcga.KINDS["motor"])]


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_normalize_matches_clifford(kind):
    m = OPERANDS_A[kind]
    out = jaxcga.normalize(m)
    expected = []
    for x in _elements(m):
        if kind in MOTOR_SUBSETS:
            # exact motor normalization: M (1 - p/(2s) P) / sqrt(s), M ~M = s + p P, P = e123inf
            P = ref.E1 ^ ref.E2 ^ ref.E3 ^ ref.EINF
            mm = x * ~x
            s = mm.value[0]
            p = (mm - s).value @ np.linalg.pinv(P.value[None, :])
            p = float(p[0])
            assert np.allclose((mm - s - p * P).value, 0.0, atol=1e-12)
            n = x * (1.0 - p / (2 * s) * P) / np.sqrt(s)
            assert np.allclose((n * ~n).value, (1.0 + 0 * ref.E1).value, atol=1e-12)
            expected.append(n)
        else:
            expected.append(x.normal())
    ref.assert_mv_close(out, expected, atol=TOL, rtol=TOL, err_msg=kind)


def test_normalize_random_motor_is_unit_and_differs_from_naive():
    """For a general motor M ~M has an e123inf part; the naive m/|m| is not unit, ours is."""
    m = OPERANDS_A["motor"]
    out = jaxcga.normalize(m)
    for x, n in zip(_elements(m), ref.to_clifford_list(out)):
        naive = x.normal()
        assert not np.allclose((naive * ~naive).value, (1.0 + 0 * ref.E1).value, atol=1e-6)
        np.testing.assert_allclose((n * ~n).value, (1.0 + 0 * ref.E1).value, atol=1e-12)


# ---------------------------------------------------------------- pseudoscalar, dual
def test_pseudoscalar_is_paper_I():
    I = jaxcga.pseudoscalar()
    ref.assert_mv_close(I, ref.I5, atol=0, rtol=0)
    ref.assert_mv_close(I, ref.LAYOUT.pseudoScalar, atol=0, rtol=0)
    # I^2 = -1
    ref.assert_mv_close(I * I, -1.0 + 0 * ref.E1, atol=0, rtol=0)
    assert I.dtype == jnp.float64
    assert jaxcga.pseudoscalar(jnp.float32).dtype == jnp.float32


def test_dual_of_point_is_sphere_direct_form():
    """Paper eq. 7: the dual of a vector is the 4-blade of its direct form (up to scale)."""
    X = jaxcga.up(jnp.array([1.0, -2.0, 0.5]))
    d = jaxcga.dual(X)
    assert _grades(d) == {4}
    ref.assert_mv_close(d, -(ref.to_clifford(X) * ref.I5), atol=TOL, rtol=TOL)
    ref.assert_mv_close(jaxcga.undual(d), ref.to_clifford(X), atol=TOL, rtol=TOL)


# ---------------------------------------------------------------- structure: full, embed, access
@pytest.mark.parametrize("kind", KIND_NAMES)
def test_full_round_trip_and_embed(kind):
    m = OPERANDS_A[kind]
    full = m.full()
    assert full.shape == (BATCH, 32)
    back = Multivector.from_full(full)
    assert back.blades == jaxcga.ALL_BLADES
    ref.assert_mv_close(back, ref.to_clifford_values(m), atol=0, rtol=0)
    # canonical order: column j of full() is blade ALL_BLADES[j]
    full_np = np.asarray(full)
    for j, blade in enumerate(jaxcga.ALL_BLADES):
        name = jaxcga.blade_name(blade)
        np.testing.assert_array_equal(full_np[..., j], np.asarray(m[name]))
    for target in ("full", "even" if set(m.blades) <= set(jaxcga.KINDS["even"]) else "full"):
        e = m.embed(target)
        assert e.blades == jaxcga.KINDS[target]
        ref.assert_mv_close(e, ref.to_clifford_values(m), atol=0, rtol=0)


def test_full_is_not_identity_on_values():
    m = Multivector(jnp.array([1.0, 2.0]), ("e12", "e1"))  # non-canonical order
    full = np.asarray(m.full())
    assert full[jaxcga.ALL_BLADES.index(0b11)] == 1.0
    assert full[jaxcga.ALL_BLADES.index(0b1)] == 2.0
    assert np.count_nonzero(full) == 2


@pytest.mark.parametrize("kind", KIND_NAMES)
def test_component_access_matches_clifford(kind):
    """m["e12"]: the coefficient of a blade, recovered independently from the clifford value."""
    m = OPERANDS_A[kind]
    coeffs = ref.null_coefficients(ref.to_clifford_values(m))  # (BATCH, 32) by bitmask
    for blade in jaxcga.ALL_BLADES:
        name = jaxcga.blade_name(blade)
        got = np.asarray(m[name])
        assert got.shape == (BATCH,)
        np.testing.assert_allclose(got, coeffs[:, blade], atol=1e-12, rtol=0, err_msg=f"{kind} {name}")
        if blade not in m.blades:
            np.testing.assert_array_equal(got, 0.0)
    # from_clifford inverts to_clifford
    back = ref.from_clifford(ref.to_clifford(Multivector(m.values[0], m.blades)))
    np.testing.assert_allclose(np.asarray(back.values), np.asarray(m.full()[0]), atol=1e-12)


def test_component_access_names():
    m = Multivector(jnp.arange(1.0, 6.0), "vector")
    assert m.names == ("e1", "e2", "e3", "eo", "einf")
    assert float(m["e1"]) == 1.0
    assert float(m["eo"]) == 4.0
    assert float(m["einf"]) == 5.0
    assert float(m["e12"]) == 0.0
    assert float(m.scalar()) == 0.0
    # eo and einf are the null vectors of the reference
    ref.assert_mv_close(Multivector(jnp.array([1.0]), ("eo",)), ref.EO, atol=0, rtol=0)
    ref.assert_mv_close(Multivector(jnp.array([1.0]), ("einf",)), ref.EINF, atol=0, rtol=0)
    ref.assert_mv_close(jaxcga.basis_vector("e3inf"), ref.E3 ^ ref.EINF, atol=0, rtol=0)
    # eo . einf = -1 (paper sec. 2.2)
    eo, einf = jaxcga.basis_vector("eo"), jaxcga.basis_vector("einf")
    assert float(jaxcga.scalar_product(eo, einf)) == -1.0
    assert float(jaxcga.scalar_product(eo, eo)) == 0.0


# ---------------------------------------------------------------- batch broadcasting
BATCH_OPS = {
    "geometric": (jaxcga.geometric, lambda a, b: a * b),
    "outer": (jaxcga.outer, lambda a, b: a ^ b),
    "inner": (jaxcga.inner, lambda a, b: a | b),
    "left_contraction": (jaxcga.left_contraction, lambda a, b: a.lc(b)),
    "meet": (jaxcga.meet, lambda a, b: a.vee(b)),
    "commutator": (jaxcga.commutator, lambda a, b: (a * b - b * a) / 2),
    "add": (lambda a, b: a + b, lambda a, b: a + b),
}


@pytest.mark.parametrize("op", list(BATCH_OPS))
def test_batch_broadcasting_matches_per_element(op):
    """Batch shapes (4, 1) and (3,) broadcast to (4, 3); element [i, j] is the product of a[i, 0]
    and b[j] (checked against clifford element by element), in both operand orders."""
    rng = np.random.default_rng(11)
    a = ref.random_multivector(rng, "motor", (4, 1))
    b = ref.random_multivector(rng, "vector", (3,))
    ours, theirs = BATCH_OPS[op]
    out, out_r = ours(a, b), ours(b, a)
    assert out.batch_shape == out_r.batch_shape == (4, 3)
    xs, ys = _elements(a), _elements(b)
    got, got_r = ref.to_clifford_values(out), ref.to_clifford_values(out_r)
    for i in range(4):
        for j in range(3):
            np.testing.assert_allclose(got[i, j], theirs(xs[i], ys[j]).value, atol=TOL, rtol=TOL)
            np.testing.assert_allclose(got_r[i, j], theirs(ys[j], xs[i]).value, atol=TOL, rtol=TOL)


def test_batch_broadcasting_scalar_product_and_sandwich():
    rng = np.random.default_rng(12)
    a = ref.random_multivector(rng, "full", (4, 1))
    b = ref.random_multivector(rng, "full", (3,))
    s = np.asarray(jaxcga.scalar_product(a, b))
    assert s.shape == (4, 3)
    for i in range(4):
        for j in range(3):
            ai, bj = (
                ref.to_clifford(Multivector(a.values[i, 0], a.blades)),
                ref.to_clifford(Multivector(b.values[j], b.blades)),
            )
            assert s[i, j] == pytest.approx((ai * bj).value[0], abs=TOL)
    # sandwich: versors (2, 1) with points (3,)
    motor = VERSORS["motor"]
    V = Multivector(motor.values[:, None, :], motor.blades)
    X = jaxcga.up(rng.normal(size=(3, 3)))
    out = V >> X
    assert out.batch_shape == (2, 3)
    got = ref.to_clifford_values(out)
    vs, xs = _elements(motor), _elements(X)
    for i in range(2):
        for j in range(3):
            np.testing.assert_allclose(got[i, j], _project(vs[i] * xs[j] * vs[i].inv(), (1,)).value, atol=TOL, rtol=TOL)


def test_scaling_by_batch_array():
    m = Multivector(jnp.ones((3, 5)), "vector")
    out = m * jnp.array([1.0, 2.0, 3.0])
    np.testing.assert_array_equal(np.asarray(out.values[:, 0]), [1.0, 2.0, 3.0])
    out = 2.0 * m
    np.testing.assert_array_equal(np.asarray(out.values), np.full((3, 5), 2.0))
    out = m / jnp.array([1.0, 2.0, 4.0])
    np.testing.assert_array_equal(np.asarray(out.values[:, 4]), [1.0, 0.5, 0.25])


# ---------------------------------------------------------------- the structure-tensor evaluation
TABLE_KINDS = {
    "geometric": lambda a, b: a * b,
    "outer": lambda a, b: a ^ b,
    "inner": lambda a, b: a | b,
    "left_contraction": lambda a, b: a.lc(b),
}


@pytest.mark.slow
def test_table_product_equals_generated_product_on_every_kind_pair():
    """The generated products are checked against clifford on every pair above; the structure-tensor
    evaluation must give the same blades and values on every pair too (pairs with the full 32-blade
    set, slow to evaluate eagerly, are left to the clifford test below)."""
    for kind_a, kind_b in (pair for pair in PAIRS if "full" not in pair):
        a, b = OPERANDS_A[kind_a], OPERANDS_B[kind_b]
        for kind in TABLE_KINDS:
            ours, generated = jaxcga.table_product(kind, a, b), generated_product(kind, a, b)
            assert ours.blades == generated.blades, (kind, kind_a, kind_b)
            np.testing.assert_allclose(
                np.asarray(ours.values),
                np.asarray(generated.values),
                atol=TOL,
                rtol=TOL,
                err_msg=f"table_product({kind!r}, {kind_a}, {kind_b})",
            )


@pytest.mark.parametrize("kind_a,kind_b", [("similitude", "similitude"), ("motor", "vector"), ("full", "full")])
def test_table_product_matches_clifford(kind_a, kind_b):
    a, b = OPERANDS_A[kind_a], OPERANDS_B[kind_b]
    xs, ys = _elements(a), _elements(b)
    for kind, theirs in TABLE_KINDS.items():
        ref.assert_mv_close(
            jaxcga.table_product(kind, a, b),
            [theirs(x, y) for x, y in zip(xs, ys)],
            atol=TOL,
            rtol=TOL,
            err_msg=f"table_product({kind!r}, {kind_a}, {kind_b})",
        )


def test_table_product_gradient_equals_generated_product():
    import jax

    a, b = OPERANDS_A["similitude"], OPERANDS_B["similitude"]
    weights = jnp.asarray(np.random.default_rng(3).normal(size=(BATCH, 16)))

    def loss(values, product):
        return jnp.sum(weights * product("geometric", Multivector(values, a.blades), b).values)

    ours = jax.grad(loss)(a.values, jaxcga.table_product)
    generated = jax.grad(loss)(a.values, generated_product)
    np.testing.assert_allclose(np.asarray(ours), np.asarray(generated), atol=TOL, rtol=TOL)
    assert np.abs(np.asarray(ours)).max() > 0.1


def test_table_product_rejects_unknown_kind():
    with pytest.raises(ValueError, match="kind: expected one of"):
        jaxcga.table_product("dot", OPERANDS_A["motor"], OPERANDS_B["motor"])
