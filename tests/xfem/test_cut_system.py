"""Slab cuts whose placement is a parameter (``xfem.cut_system``, ``xfem.plane_cuts``): the replayed system equals
``XFEMModel.cut(plane_cut_solid(...))`` + ``system()`` (manifold3d's Booleans); its gradients with respect to the
plane match central differences of that Boolean path, and the closed form of the mass below a tilted slab through
a bar of cross-section A: ``rho A (c - eps / (2 cos theta))``."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import xfem

RHO, EPS = 1e3, 1e-2
# a bar 0.2 x 0.2 x 1 hanging from its top face; 8 layers of 0.125, cut inside the layer 0.375-0.5
AREA, CENTRE = 0.04, np.array([0.1, 0.1])


def _bar():
    mesh = xfem.box_tets((2, 2, 8), (0.2, 0.2, 1.0))
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1 - 1e-9)
    return xfem.xfem_model(mesh, RHO, fixed=fixed)


@pytest.fixture(scope="module")
def bar():
    return _bar()


def _normal(theta):
    """The unit normal tilted by theta about y."""
    return jnp.stack([jnp.sin(theta), jnp.zeros_like(theta), jnp.cos(theta)])


def _point(height):
    return jnp.stack([jnp.asarray(CENTRE[0]), jnp.asarray(CENTRE[1]), height])


def _boolean_system(point, normal, extent=5.0):
    model = _bar()
    model.cut(xfem.plane_cut_solid(np.asarray(point), np.asarray(normal), extent, EPS))
    return model.system()


_FIELDS = ("volumes", "mass_values", "mass_data", "force")


def _close(system, reference):
    for name in ("T", "grads", "mass_rows", "mass_cols", "fixed"):
        np.testing.assert_array_equal(np.asarray(getattr(system, name)), np.asarray(getattr(reference, name)))
    assert system.n == reference.n
    for name in _FIELDS:
        a, b = np.asarray(getattr(system, name)), np.asarray(getattr(reference, name))
        assert np.abs(a - b).max() <= 1e-12 * np.abs(b).max(), name


@pytest.mark.parametrize("height, theta", [(0.43, 0.0), (0.41, 0.3), (0.47, -0.15)])
def test_equals_the_boolean_cut(bar, height, theta):
    point, normal = np.asarray(_point(height)), np.asarray(_normal(theta))
    n_before = bar.system().n
    system = xfem.cut_system(bar, point, normal, EPS)
    _close(system, _boolean_system(point, normal))
    assert bar.system().n == n_before  # the model is left uncut


def _weights(system, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.normal(size=np.shape(getattr(system, name))) for name in _FIELDS]


def _scalar(system, weights):
    """A random linear functional of every differentiable field."""
    return sum(jnp.sum(getattr(system, name) * w) for name, w in zip(_FIELDS, weights))


@pytest.mark.slow
@pytest.mark.parametrize("which", ["height", "tilt"])
def test_gradient_matches_central_differences_of_the_booleans(bar, which):
    """``cut_system`` (no options: its default) differentiated in the plane: within 1e-6 of central differences
    of the Boolean path (each side cut anew)."""
    height, theta = 0.43, 0.2
    weights = _weights(xfem.cut_system(bar, _point(height), _normal(theta), EPS))

    def f(t):
        h, th = (height + t, theta) if which == "height" else (height, theta + t)
        return _scalar(xfem.cut_system(bar, _point(h), _normal(th), EPS), weights)

    gradient = jax.grad(f)(0.0)
    step = 1e-5
    difference = (f(step) - f(-step)) / (2 * step)
    assert abs(gradient - difference) <= 1e-6 * abs(difference)


@pytest.mark.slow
def test_mass_below_a_tilted_slab(bar):
    """The mass of the released piece and its derivatives in the height and the tilt: closed forms."""
    height, theta = 0.43, 0.3
    cuts = xfem.plane_cuts(bar, [(_point(height), _normal(theta), EPS)])
    count, component = cuts.model.components()
    assert count == 2
    fixed = np.asarray(cuts.model.system().fixed)
    below = component != component[fixed[0]]

    def mass(h, th):
        system = cuts.system(_point(h)[None], _normal(th)[None])
        rows, cols = system.mass_rows, system.mass_cols
        return jnp.sum(jnp.where(below[rows] & below[cols], system.mass_values, 0.0))

    value, (dh, dth) = jax.value_and_grad(mass, argnums=(0, 1))(jnp.asarray(height), jnp.asarray(theta))
    np.testing.assert_allclose(value, RHO * AREA * (height - EPS / (2 * np.cos(theta))), rtol=1e-12)
    np.testing.assert_allclose(dh, RHO * AREA, rtol=1e-10)
    np.testing.assert_allclose(dth, -RHO * AREA * EPS * np.sin(theta) / (2 * np.cos(theta) ** 2), rtol=1e-9)


def test_crossing_slabs(bar):
    """Two slabs that cross inside the bar: pieces clipped by both, each system equal to the Booleans'."""
    planes = [(_point(0.43), _normal(0.0), EPS), (_point(0.45), _normal(-0.3), EPS)]
    cuts = xfem.plane_cuts(bar, planes)
    reference = _bar()
    for (point, normal, _), system in zip(planes, cuts.systems(cuts.points, cuts.normals)):
        reference.cut(xfem.plane_cut_solid(np.asarray(point), np.asarray(normal), 5.0, EPS))
        _close(system, reference.system())


def test_solid_cuts_between_the_planes(bar):
    """A schedule of a plane, a partial notch meeting its pieces (which become constants) and a second plane through
    the notched elements: every system equals the Booleans'."""
    notch = xfem.plane_cut_solid(np.array([0.09, 0.1, 0.45]), np.array([1.0, 0.0, 0.0]), 0.15, 0.02)
    cuts = [(_point(0.43), _normal(0.1), EPS), (notch, 0.0), (_point(0.47), _normal(-0.2), EPS)]
    replayed = xfem.plane_cuts(bar, cuts)
    assert replayed.points.shape == (2, 3)
    reference = _bar()
    for cut, system in zip(cuts, replayed.systems(replayed.points, replayed.normals)):
        reference.cut(
            cut[0] if len(cut) == 2 else xfem.plane_cut_solid(np.asarray(cut[0]), np.asarray(cut[1]), 5.0, EPS)
        )
        _close(system, reference.system())


def test_holds_while_the_combinatorics_do(bar):
    """``holds`` is True near the planes found and False once the slab passes a node layer (z = 0.5) or a tilt
    moves a piece's corner across it."""
    cuts = xfem.plane_cuts(bar, [(_point(0.43), _normal(0.2), EPS)])
    holds = jax.jit(lambda h, th: cuts.holds(_point(h)[None], _normal(th)[None]))
    assert holds(0.43, 0.2) and holds(0.431, 0.2) and holds(0.43, 0.21)
    assert not holds(0.52, 0.2) and not holds(0.43, 0.6)


@pytest.mark.slow
def test_jit_and_two_planes(bar):
    """Two cuts: the second system depends on both planes; it equals the Booleans', and the jitted gradient of
    ``plane_cuts(...).systems`` is within 1e-6 of central differences of the Boolean path (``plane_cuts`` at the
    shifted planes)."""
    planes = [(_point(0.43), _normal(0.2), EPS), (_point(0.71), _normal(-0.1), EPS)]
    cuts = xfem.plane_cuts(bar, planes)
    assert [r.dof_source is not None for r in cuts.reports] == [True, True]
    reference = _bar()
    for point, normal, _ in planes:
        reference.cut(xfem.plane_cut_solid(np.asarray(point), np.asarray(normal), 5.0, EPS))
    first, second = cuts.systems(cuts.points, cuts.normals)
    _close(second, reference.system())
    _close(first, xfem.cut_system(bar, *planes[0]))
    weights = _weights(second, seed=1)

    @jax.jit
    def f(thetas):
        normals = jax.vmap(_normal)(thetas)
        return _scalar(cuts.systems(cuts.points, normals)[1], weights)

    thetas = np.array([0.2, -0.1])
    gradient = jax.grad(f)(thetas)
    step = 1e-5
    for k in range(2):
        values = []
        for sign in (1, -1):
            shifted = thetas + sign * step * np.eye(2)[k]
            system = xfem.plane_cuts(bar, [(p, _normal(t), EPS) for (p, _, _), t in zip(planes, shifted)]).system(
                cuts.points, jax.vmap(_normal)(shifted)
            )
            values.append(_scalar(system, weights))
        difference = (values[0] - values[1]) / (2 * step)
        assert abs(gradient[k] - difference) <= 1e-6 * abs(difference)


def test_earlier_non_planar_cut_is_a_constant():
    """A bar notched by a partial slab (it ends inside the bar, so the notched pieces are not half-spaces of
    their tets) and then cut across the notch: the notched pieces come from their meshes and are clipped."""
    model = _bar()
    notch = xfem.plane_cut_solid(np.array([0.09, 0.1, 0.45]), np.array([1.0, 0.0, 0.0]), 0.15, 0.02)
    model.cut(notch)
    point, normal = np.array([0.1, 0.1, 0.44]), np.asarray(_normal(0.1))
    system = xfem.cut_system(model, point, normal, EPS)
    reference = _bar()
    reference.cut(notch)
    reference.cut(xfem.plane_cut_solid(point, normal, 5.0, EPS))
    _close(system, reference.system())


def test_bad_input(bar):
    point, normal = np.array([0.1, 0.1, 0.43]), np.array([0.0, 0.0, 1.0])
    with pytest.raises(ValueError, match="normal: expected a unit normal"):
        xfem.cut_system(bar, point, 2 * normal, EPS)
    with pytest.raises(ValueError, match="normal: expected a unit normal"):
        xfem.cut_system(bar, point, 0 * normal, EPS)
    with pytest.raises(ValueError, match="epsilon"):
        xfem.cut_system(bar, point, normal, 0.0)
    with pytest.raises(ValueError, match="point: expected"):
        xfem.cut_system(bar, point[:2], normal, EPS)
    with pytest.raises(ValueError, match="misses the body"):
        xfem.cut_system(bar, np.array([0.1, 0.1, 3.0]), normal, EPS)
    with pytest.raises(ValueError, match=r"cuts\[1\]: expected"):
        xfem.plane_cuts(bar, [(point, normal, EPS), (point, normal)])  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match=r"normal\[1\]"):
        xfem.plane_cuts(bar, [(point, normal, EPS), (point, 2 * normal, EPS)])
    cuts = xfem.plane_cuts(bar, [(point, normal, EPS)])
    with pytest.raises(ValueError, match="normals: expected finite nonzero"):
        cuts.system(point[None], 0 * normal[None])
    with pytest.raises(ValueError, match=r"points, normals: expected shape \(1, 3\)"):
        cuts.system(point, normal)
    with pytest.raises(ValueError, match="point: cut_system .* concrete"):
        jax.jit(lambda p: xfem.cut_system(bar, p, normal, EPS).volumes)(point)


@pytest.mark.slow
def test_gradient_of_a_step_outcome(bar):
    """The hanging part's sag after one backward Euler step at the defaults (converged), differentiated with respect
    to the cut's height through the step's implicit gradient: within 1e-6 of central differences of the Boolean
    path."""
    height, theta = 0.43, 0.2
    cuts = xfem.plane_cuts(bar, [(_point(height), _normal(theta), EPS)])
    X = jnp.asarray(cuts.model.X[cuts.model.dof_node])
    state = xfem.State(X, jnp.zeros_like(X))
    material = xfem.Material(1e5, 0.3)
    weights = np.random.default_rng(2).normal(size=X.shape[0])

    def f(t):
        system = xfem.cut_system(bar, _point(height + t), _normal(theta), EPS)
        x = xfem.backward_euler_step(system, state, 0.01, material).x
        return jnp.sum(weights * x[:, 2])

    gradient = jax.grad(f)(0.0)
    step = 1e-5
    difference = (f(step) - f(-step)) / (2 * step)
    assert abs(gradient - difference) <= 1e-6 * abs(difference)
