"""Every matrix product in the library states its precision (``_jaxcga_shared.platform.EXACT``): on GPUs a float32
product left to JAX's default is TF32 (10-bit mantissas), which put joint motors, rigidity checks and Hessians off by
~1e-3 there while the CPU, exact either way, showed nothing. Two checks that CI (CPU) can run: the source (every
``jnp``/``lax`` product call passes ``precision=``) and the traced programs of public float32 calls (every
``dot_general`` is at the highest precision)."""

from __future__ import annotations

import ast
from pathlib import Path

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np
import pytest

import deform
import jaxcga as cga

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("_jaxcga_shared", "jaxcga", "deform", "cutting", "xfem", "jaxcga_cli")
PRODUCTS = {"einsum", "matmul", "dot", "tensordot", "inner", "vdot", "dot_general", "batch_matmul"}
JAX_MODULES = {"jnp", "jax.numpy", "jax.lax", "lax"}


def _products_without_precision(path: Path, root: Path = ROOT) -> list[str]:
    """``jnp.einsum(...)`` and the like without ``precision=``, and products passed as functions (``jnp.matmul``)
    other than through ``functools.partial(..., precision=...)``."""
    tree = ast.parse(path.read_text(), str(path))
    stated = set()  # the product attributes whose call (or partial) passes a precision
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and any(keyword.arg == "precision" for keyword in node.keywords):
            stated.add(id(node.func))
            stated.update(id(arg) for arg in node.args[:1])
    found = []
    for node in ast.walk(tree):
        if (
            isinstance(node, ast.Attribute)
            and node.attr in PRODUCTS
            and ast.unparse(node.value) in JAX_MODULES
            and id(node) not in stated
        ):
            found.append((node.lineno, f"{path.relative_to(root)}:{node.lineno}: {ast.unparse(node)}"))
    return [line for _, line in sorted(found)]


def test_every_jax_product_call_states_its_precision():
    found = [
        line
        for package in PACKAGES
        for path in sorted((ROOT / package).rglob("*.py"))
        for line in _products_without_precision(path)
    ]
    assert not found, "products left to the default precision (TF32 on GPUs):\n" + "\n".join(found)


def test_the_source_check_finds_a_product_without_precision(tmp_path):
    """The check above can fail."""
    source = tmp_path / "module.py"
    source.write_text(
        "import jax.numpy as jnp\nx = jnp.einsum('ij,j->i', a, b)\ny = jnp.matmul(a, b, precision=P)\n"
        "f = jnp.matmul\ng = functools.partial(jnp.matmul, precision=P)\n"
    )
    assert _products_without_precision(source, tmp_path) == ["module.py:2: jnp.einsum", "module.py:4: jnp.matmul"]


def _dot_precisions(fn, *args) -> list:
    """The precision of every ``dot_general`` in ``fn``'s program, sub-programs (jit, scan, custom rules) included."""
    found = []

    def visit(jaxpr):
        for eqn in jaxpr.eqns:
            if eqn.primitive.name == "dot_general":
                found.append(eqn.params["precision"])
            for value in eqn.params.values():
                for sub in value if isinstance(value, (tuple, list)) else (value,):
                    if isinstance(sub, jax.extend.core.ClosedJaxpr):
                        visit(sub.jaxpr)
                    elif isinstance(sub, jax.extend.core.Jaxpr):
                        visit(sub)

    visit(jax.make_jaxpr(fn)(*args).jaxpr)
    return found


def _float32_calls():
    rng = np.random.default_rng(0)
    f32 = jnp.float32
    n, joints = 40, 5
    V = jnp.asarray(rng.normal(size=(n, 3)), f32)
    J = jnp.asarray(rng.integers(0, joints, size=(n, 2)), jnp.int32)
    W = jnp.full((n, 2), 0.5, f32)
    motors = cga.exp_motor(cga.Multivector(jnp.asarray(rng.normal(size=(joints, 6)), f32), cga.MOTOR_GENERATOR))
    similitudes = cga.exp_similitude(
        cga.Multivector(jnp.asarray(rng.normal(size=(joints, 7)) * 0.3, f32), cga.SIMILITUDE_GENERATOR)
    )
    matrices = cga.versor_to_matrix(motors)
    weights = jnp.asarray(rng.dirichlet(np.ones(joints), size=n), f32)
    lattice = deform.bounding_lattice(np.asarray(V, np.float64), (3, 3, 3), padding=0.1)
    return {
        "skin_cga_motor_blend": (
            lambda m: deform.skin_cga_motor_blend(V, J, W, cga.Multivector(m, "motor")),
            (motors.values,),
        ),
        "skin_cga (similitudes, poses)": (
            lambda s: deform.skin_cga(V, J, W, cga.Multivector(s, similitudes.blades), normalize_points=False),
            (jnp.stack([similitudes.values, similitudes.values]),),
        ),
        "matrices_to_dual_quaternions": (deform.matrices_to_dual_quaternions, (matrices,)),
        "matrix_to_similitude": (cga.matrix_to_similitude, (cga.versor_to_matrix(similitudes),)),
        "table_product": (
            lambda a, b: (
                cga.table_product("geometric", cga.Multivector(a, "motor"), cga.Multivector(b, "motor")).values
            ),
            (motors.values, motors.values),
        ),
        "align_points": (lambda p, q: cga.align_points(p, q).values, (V, V + 1)),
        "log_similitude": (
            lambda s: cga.log_similitude(cga.Multivector(s, similitudes.blades)).values,
            (similitudes.values,),
        ),
        "blend_motors": (
            lambda w, m: deform.blend_motors(w, cga.Multivector(m, "motor")).values,
            (weights, motors.values),
        ),
        "blend_positions": (deform.blend_positions, (weights, jnp.asarray(rng.normal(size=(joints, 3)), f32))),
        "forward_kinematics_matrices": (
            lambda m: deform.forward_kinematics_matrices((-1, 0, 1, 1, 3), m),
            (matrices,),
        ),
        "ffd_weights": (lambda v: deform.ffd_weights(v, lattice), (V.astype(jnp.float64),)),
    }


@pytest.mark.parametrize("case", sorted(_float32_calls()))
def test_traced_products_are_at_the_highest_precision(case):
    fn, args = _float32_calls()[case]
    precisions = _dot_precisions(fn, *args)
    assert precisions, f"{case}: traces no matrix product (the case tests nothing)"
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert all(p == highest for p in precisions), f"{case}: precisions {precisions}"
