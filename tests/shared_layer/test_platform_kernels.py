"""Every kernel with per-platform formulations (``_jaxcga_shared.platform``): on the CPU, the GPU variant
computes what the CPU variant computes (values and vector-Jacobian products, float64 and float32), the
dispatch picks the running backend's variant (the GPU's under ``--gpu-variants``), and a lowering for CUDA holds
the GPU variant (no barriers)."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
import jaxcga as cga
from _jaxcga_shared.platform import PLATFORM_KERNELS, PerPlatform, per_platform
from tests.shared import import_library, lowered_operations, needs_cuda_lowering
from tests.shared_layer._platform_examples import EXAMPLES, example

import_library()  # every module that registers a kernel
KERNELS = sorted(PLATFORM_KERNELS)
DTYPES = {jnp.float64: 1e-12, jnp.float32: 2e-5}  # tolerance relative to the largest entry


def test_kernels_are_registered():
    assert {
        "apply_to_points",
        "table_product",
        "deform.skin_dqs",
        "deform.skin_cga_motor_blend",
        "deform.blend_dilations",
        "deform.motor_field",
        "deform.forward_kinematics",
        "deform.largest_quartic_root",
    } <= set(KERNELS)


def test_every_kernel_has_examples():
    """A kernel registered without inputs to compare its variants on would go untested: each has some, and
    every entry of the examples names a registered kernel (a renamed kernel leaves none behind)."""
    assert set(EXAMPLES) == set(KERNELS), (
        f"registered kernels without examples: {sorted(set(KERNELS) - set(EXAMPLES))}; "
        f"examples of no registered kernel: {sorted(set(EXAMPLES) - set(KERNELS))}"
    )
    for name in KERNELS:
        assert EXAMPLES[name](), f"{name}: an empty list of examples"


def _cast(tree, dtype):
    return jax.tree.map(
        lambda a: a.astype(dtype) if jnp.issubdtype(a.dtype, jnp.floating) else a, jax.tree.map(jnp.asarray, tree)
    )


def _assert_close(got, expected, rtol):
    got_leaves, got_tree = jax.tree.flatten(got)
    expected_leaves, expected_tree = jax.tree.flatten(expected)
    assert got_tree == expected_tree
    for g, e in zip(got_leaves, expected_leaves):
        assert g.shape == e.shape and g.dtype == e.dtype
        scale = float(np.max(np.abs(e), initial=0.0))
        assert scale > 0, "an example with an all-zero result compares nothing"
        np.testing.assert_allclose(np.asarray(g), np.asarray(e), rtol=0, atol=rtol * scale)


def _jitted(kernel, static):
    return jax.jit(functools.partial(kernel, **static))


def _cases(kernel: PerPlatform, dtype):
    examples = EXAMPLES[kernel.name]()
    return [example(*_cast(e.args, dtype), **e.static) for e in examples]


def _float_leaves(args):
    """The floating leaves of ``args`` (integer indices have no cotangent) and how to put them back."""
    leaves, tree = jax.tree.flatten(args)
    floating = [jnp.issubdtype(a.dtype, jnp.floating) for a in leaves]

    def rebuild(xs):
        xs = iter(xs)
        return jax.tree.unflatten(tree, [next(xs) if f else a for a, f in zip(leaves, floating)])

    return [a for a, f in zip(leaves, floating) if f], rebuild


def _value_and_vjp(f, args):
    """``f(*args)`` and, with a fixed random cotangent, its vector-Jacobian product for the floating
    arguments, in one compiled call."""
    floats, rebuild = _float_leaves(args)

    def run(*xs):
        value, vjp = jax.vjp(lambda *ys: f(*rebuild(ys)), *xs)
        rng = np.random.default_rng(0)
        cotangent = jax.tree.map(lambda a: jnp.asarray(rng.normal(size=a.shape), a.dtype), value)
        return value, vjp(cotangent)

    return jax.jit(run)(*floats)


@pytest.mark.parametrize("dtype", list(DTYPES), ids=["float64", "float32"])
@pytest.mark.parametrize("name", KERNELS)
def test_gpu_variant_equals_cpu_variant(name, dtype):
    """Values on every example; where the kernel is differentiated in practice, in float64, on its first
    example also vector-Jacobian products (one compile each: they dominate the test's time)."""
    kernel = PLATFORM_KERNELS[name]
    if dtype == jnp.float32 and not kernel.float32:
        pytest.skip(f"{name} takes float64 only")
    for i, (args, static) in enumerate(_cases(kernel, dtype)):
        cpu, gpu = (functools.partial(kernel.variants[v], **static) for v in ("cpu", "gpu"))
        if kernel.differentiated and dtype == jnp.float64 and i == 0:
            _assert_close(_value_and_vjp(gpu, args), _value_and_vjp(cpu, args), DTYPES[dtype])
        else:
            _assert_close(jax.jit(gpu)(*args), jax.jit(cpu)(*args), DTYPES[dtype])


@pytest.mark.parametrize("name", KERNELS)
def test_dispatch_is_the_backends_variant(name, running_variant):
    """Bit for bit: the conditional is resolved at lowering and leaves the code of the backend's variant (the CPU
    variant in CI, the GPU variant where the suite runs on a GPU or with ``--gpu-variants``)."""
    kernel = PLATFORM_KERNELS[name]
    variant = kernel.variants[running_variant]
    for args, static in EXAMPLES[name]():
        got, expected = (_jitted(f, static)(*args) for f in (kernel, variant))
        for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
            np.testing.assert_array_equal(g, e)


@pytest.mark.cpu_formulation("a lowering for the CPU holds the CPU variant")
@needs_cuda_lowering
@pytest.mark.parametrize("name", KERNELS)
def test_lowering_picks_the_platform_variant(name):
    """Lowered for the CPU the dispatch holds the CPU variant's operations, lowered for CUDA the GPU
    variant's, and the two differ (a registered kernel whose variants lower alike would be pointless)."""
    kernel = PLATFORM_KERNELS[name]
    args, static = EXAMPLES[name]()[-1]
    dispatch = functools.partial(kernel, **static)
    cpu, gpu = (functools.partial(kernel.variants[v], **static) for v in ("cpu", "gpu"))
    assert lowered_operations(dispatch, args, "cpu") == lowered_operations(cpu, args, "cpu")
    assert lowered_operations(cpu, args, "cpu") != lowered_operations(gpu, args, "cpu")
    try:
        assert lowered_operations(dispatch, args, "cuda") == lowered_operations(gpu, args, "cuda")
        assert lowered_operations(cpu, args, "cuda") != lowered_operations(gpu, args, "cuda")
    except ValueError as error:
        if "lowering platform" not in str(error):
            raise
        pytest.skip(f"{name} calls the host (a solve or a runtime check): lowering it for CUDA needs a CUDA backend")


def _public_calls():
    rng = np.random.default_rng(5)
    n, joints = 30, 4
    V = jnp.asarray(rng.normal(size=(n, 3)))
    J = jnp.asarray(rng.integers(0, joints, size=(n, 2)), jnp.int32)
    W = jnp.full((n, 2), 0.5)
    motors = cga.exp_motor(cga.Multivector(rng.normal(size=(joints, 6)), cga.MOTOR_GENERATOR))
    dq = cga.motor_to_dual_quaternion(motors)
    return {
        "apply_to_points": (
            lambda m, x: cga.apply_to_points(cga.Multivector(m, "motor"), x),
            (jnp.asarray(rng.normal(size=(n, 8))), V),
        ),
        "skin_dqs": (lambda d: deform.skin_dqs(V, J, W, d), (dq,)),
        "skin_cga_motor_blend": (
            lambda m: deform.skin_cga_motor_blend(V, J, W, cga.Multivector(m, "motor")),
            (motors.values,),
        ),
        "skin_dqs_batch": (lambda d: deform.skin_dqs(V, J, W, d), (jnp.stack([dq, dq]),)),
    }


@pytest.mark.cpu_formulation("the CPU formulations' barriers")
@needs_cuda_lowering
@pytest.mark.parametrize("case", sorted(_public_calls()))
def test_public_functions_lowered_for_cuda_have_no_barriers(case):
    """The public functions whose CPU formulation relies on ``optimization_barrier`` lose it when
    lowered for CUDA: CI (CPU only) covers that the GPU path is the one picked."""
    fn, args = _public_calls()[case]
    assert lowered_operations(fn, args, "cpu")["optimization_barrier"] > 0
    assert lowered_operations(fn, args, "cuda")["optimization_barrier"] == 0


def test_static_options_and_transformations_pass_through(running_variant):
    """Keyword options are bound to both formulations; vmap and grad go through the choice."""
    calls = []

    def cpu(x, y, *, power):
        calls.append("cpu")
        return jax.lax.optimization_barrier(x**power) * y

    def gpu(x, y, *, power):
        calls.append("gpu")
        return x**power * y

    kernel = PerPlatform("test.power", cpu=cpu, gpu=gpu)
    try:
        x = jnp.arange(1.0, 4.0)
        np.testing.assert_allclose(kernel(x, 2.0, power=3), 2 * x**3)
        assert calls == [running_variant]  # outside jit the platform is known: one formulation runs
        np.testing.assert_allclose(jax.vmap(lambda a: kernel(a, 2.0, power=3))(x), 2 * x**3)
        np.testing.assert_allclose(jax.jit(jax.grad(lambda a: kernel(a, 2.0, power=3)))(1.5), 6 * 1.5**2)
        with pytest.raises(ValueError, match="name: a platform kernel named 'test.power'"):
            PerPlatform("test.power", cpu=cpu, gpu=gpu)
    finally:
        del PLATFORM_KERNELS["test.power"]


def test_flag_form_binds_cpu(running_variant):
    @per_platform("test.flag")
    def kernel(x, *, cpu: bool):
        """Doubles on the CPU, triples elsewhere."""
        return 2 * x if cpu else 3 * x

    try:
        assert kernel.__doc__ == "Doubles on the CPU, triples elsewhere."
        assert float(jax.jit(kernel)(1.0)) == {"cpu": 2.0, "gpu": 3.0}[running_variant]
        assert float(kernel.variants["cpu"](1.0)) == 2.0
        assert float(kernel.variants["gpu"](1.0)) == 3.0
    finally:
        del PLATFORM_KERNELS["test.flag"]
