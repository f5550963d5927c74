"""The XFEM cutting simulation (XFEM paper sec. 4.2-4.4, eq. 16-18, 21, Algorithm 1): an uncut model is plain FEM
(``fem_from_mesh``, identical steps); a cut keeps the displacement and velocity fields of eq. 18 (DOF duplication,
checked against the barycentric interpolation of the nodal values before the cut); the mass after a cut is rho
times the body's volume minus the volume of the cut inside it (manifold3d's Boolean volume); a body cut through
separates and its free part falls with g."""

import logging
import threading
from concurrent.futures import Future

import jax
import jax.numpy as jnp
import manifold3d
import numpy as np
import pytest
import scipy.sparse as sp

from tests.shared import assert_same_run
from tests.xfem._models import EPS, MATERIAL, NORMAL, POINT, RHO, G, H, deformed_state, plane, random_points, tall_box
from xfem import (
    BackgroundCuts,
    CompiledSteps,
    State,
    backward_euler_step,
    boundary_faces,
    box_tets,
    fem_from_mesh,
    five_tet_cube,
    xfem_model,
)


def _mass(system):
    return sp.csr_matrix(
        (np.asarray(system.mass_values), (np.asarray(system.mass_rows), np.asarray(system.mass_cols))),
        shape=(system.n, system.n),
    )


@pytest.mark.slow
@pytest.mark.parametrize("make", [five_tet_cube, lambda: box_tets((2, 2, 2))])
def test_uncut_model_is_plain_fem(make):
    mesh = make()
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] < 1e-9)
    model = xfem_model(mesh, RHO, fixed=fixed, state=deformed_state(mesh))
    system, reference = model.system(), fem_from_mesh(mesh, RHO, fixed=fixed)
    np.testing.assert_array_equal(np.asarray(system.T), np.asarray(reference.T))
    np.testing.assert_array_equal(np.asarray(system.fixed), np.asarray(reference.fixed))
    np.testing.assert_allclose(np.asarray(system.volumes), np.asarray(reference.volumes), rtol=0, atol=1e-15)
    np.testing.assert_allclose(_mass(system).toarray(), _mass(reference).toarray(), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(system.force), np.asarray(reference.force), rtol=0, atol=1e-12)
    state = deformed_state(mesh)
    for _ in range(5):
        model.step(H, MATERIAL)
        state = backward_euler_step(reference, state, H, MATERIAL, newton_iterations=1, tolerance=None)  # as step
    np.testing.assert_allclose(np.asarray(model.state.x), np.asarray(state.x), rtol=0, atol=1e-12)
    np.testing.assert_allclose(np.asarray(model.state.v), np.asarray(state.v), rtol=0, atol=1e-12)
    assert model.pieces() == 1


def test_cut_keeps_displacement_and_velocity():
    mesh = tall_box()
    state = deformed_state(mesh)
    model = xfem_model(mesh, RHO, state=state)
    points, elements, w = random_points(mesh, 400)
    # eq. 18 before any cut is the barycentric interpolation of the nodal values
    T = np.asarray(mesh.T)[elements]
    u0 = np.einsum("ka,kaj->kj", w, np.asarray(state.x)[T] - np.asarray(mesh.X)[T])
    v0 = np.einsum("ka,kaj->kj", w, np.asarray(state.v)[T])
    np.testing.assert_allclose(model.displacement_at(points, elements), u0, rtol=0, atol=1e-12)
    report = model.cut(plane())
    added = sum(len(c) - 1 for c in report.node_children.values())
    assert added > 0 and len(model.dof_sid) == mesh.X.shape[0] + added
    # material points only: outside the slab of thickness EPS (with a margin)
    n = NORMAL / np.linalg.norm(NORMAL)
    keep = np.abs((points - POINT) @ n) > EPS
    assert keep.sum() > 350
    np.testing.assert_allclose(model.displacement_at(points[keep], elements[keep]), u0[keep], rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.velocity_at(points[keep], elements[keep]), v0[keep], rtol=0, atol=1e-12)
    # the two sides now move independently: the DOFs of a split node on either side are copies
    assert model.pieces() == 2
    # a second, crossing cut splits subdomains made by the first: four pieces, the fields still unchanged
    point, normal = np.array([0.43, 0.5, 0.75]), np.array([1.0, 0.06, -0.03])
    model.cut(plane(point, normal))
    keep &= np.abs((points - point) @ (normal / np.linalg.norm(normal))) > EPS
    np.testing.assert_allclose(model.displacement_at(points[keep], elements[keep]), u0[keep], rtol=0, atol=1e-12)
    np.testing.assert_allclose(model.velocity_at(points[keep], elements[keep]), v0[keep], rtol=0, atol=1e-12)
    assert model.pieces() == 4


def test_mass_after_cuts_is_body_minus_cuts():
    mesh = tall_box()
    model = xfem_model(mesh, RHO)
    # two crossing cuts: the second one also splits pieces made by the first
    cut = plane() + plane((0.43, 0.5, 0.75), (1.0, 0.06, -0.03))
    model.cut(plane())
    model.cut(plane((0.43, 0.5, 0.75), (1.0, 0.06, -0.03)))
    X, T = np.asarray(mesh.X), np.asarray(mesh.T)
    F = boundary_faces(T)
    body = manifold3d.Manifold(
        manifold3d.Mesh64(vert_properties=np.array(X, np.float64), tri_verts=np.array(F, np.uint64))
    )
    volume = body.volume() - (body ^ cut).volume()
    system = model.system()
    _, _, piece_volume, _, load = model.piece_arrays()
    assert abs(_mass(system).sum() - RHO * volume) <= 1e-12 * RHO * volume
    assert abs(piece_volume.sum() - volume) <= 1e-12 * volume
    assert abs(load.sum() - volume) <= 1e-12 * volume
    np.testing.assert_allclose(np.asarray(system.force).sum(axis=0), RHO * volume * G, rtol=1e-12, atol=1e-9)
    # each row's piece id, and the model's arrays kept from the callers' writes
    element, ids = model.piece_arrays()[0], model.piece_ids()
    assert ids.tolist() == [sid for e in range(len(T)) for sid in model.sub.element_subdomains(e)]
    assert element.tolist() == [model.sub.element_of(sid) for sid in ids.tolist()]
    with pytest.raises(ValueError, match="read-only"):
        piece_volume[0] = 0.0


@pytest.mark.slow
def test_cut_through_hanging_body_separates():
    mesh = tall_box()
    top = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    model = xfem_model(mesh, RHO, fixed=top)
    assert model.pieces() == 1
    model.cut(plane())
    count, label = model.components()
    assert count == 2 == model.pieces()
    masses = np.asarray(_mass(model.system()).sum(axis=1)).ravel()  # int rho phi_i psi_i^s: COM weights
    lower = label != label[np.isin(model.dof_node, top)][0]
    assert not np.any(np.isin(model.dof_node[lower], top))

    def com(values, part):
        return masses[part] @ np.asarray(values)[part] / masses[part].sum()

    lower_x0, upper_x0 = com(model.state.x, lower), com(model.state.x, ~lower)
    previous = com(model.state.v, lower)
    for _ in range(6):
        model.step(H, MATERIAL, newton_iterations=3)
        velocity = com(model.state.v, lower)
        acceleration, previous = (velocity - previous) / H, velocity
    # the free part is in free fall: its centre of mass accelerates with g (backward Euler conserves its momentum
    # up to the inexact Newton solves)
    np.testing.assert_allclose(acceleration, G, rtol=0, atol=1e-2)
    fall = lower_x0[2] - com(model.state.x, lower)[2]
    assert fall > 0.5 * 9.81 * (6 * H) ** 2
    # the held part stays: it sags elastically (rho g L^2 / E ~ 1e-3) by far less than the fall
    assert np.linalg.norm(com(model.state.x, ~lower) - upper_x0) < 0.1 * fall


def test_cut_outside_is_a_no_op():
    mesh = box_tets((2, 2, 2))
    model = xfem_model(mesh, RHO, state=deformed_state(mesh))
    before = model.piece_arrays()
    report = model.cut(plane(point=(0.5, 0.5, 2.0)))
    assert len(report.elements_touched) == 0
    for a, b in zip(before, model.piece_arrays()):
        np.testing.assert_array_equal(a, b)
    assert len(model.dof_sid) == mesh.X.shape[0]
    np.testing.assert_array_equal(np.asarray(model.state.x), np.asarray(deformed_state(mesh).x))


def test_partial_cut_keeps_one_piece():
    mesh = tall_box()
    model = xfem_model(mesh, RHO)
    # a square of side 1.2 centred on the box's x = 0 face: it cuts x < 0.6 only, through the 1-rings of the
    # nodes at x = 0 but not of those at x = 0.5
    report = model.cut(plane(point=(0.0, 0.5, 0.61), extent=1.2))
    assert len(report.elements_touched) > 0 and len(report.nodes_split) > 0
    assert model.pieces() == 1
    _, _, volume, _, _ = model.piece_arrays()
    assert 1.5 - 0.6 * EPS * 1.1 < volume.sum() < 1.5 - 0.6 * EPS * 0.9


def test_bad_input():
    mesh = five_tet_cube()
    with pytest.raises(ValueError, match="density"):
        xfem_model(mesh, -1.0)
    with pytest.raises(ValueError, match="fixed"):
        xfem_model(mesh, RHO, fixed=[0, 8])
    with pytest.raises(ValueError, match="state"):
        xfem_model(mesh, RHO, state=State(jnp.zeros((3, 3)), jnp.zeros((3, 3))))
    with pytest.raises(ValueError, match="points"):
        xfem_model(mesh, RHO).displacement_at(np.zeros((2, 2)), np.zeros(2, int))


def test_models_own_their_threads_and_runs_interleave():
    """Two models stepped and cut in interleaved order in one process give what each gives alone; after close()
    no thread of theirs remains (the cuts' Boolean pool, the next level's compilation) and a closed model refuses
    to step; models sharing a bounded ``CompiledSteps`` compile once and keep at most its limit."""
    earlier = set(threading.enumerate())  # other tests' models may still compile
    mesh = tall_box()
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    cuts = {"a": plane(), "b": plane(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0))}

    def alone(name):
        with xfem_model(mesh, RHO, gravity=G, fixed=fixed) as model:
            model.step(H, MATERIAL)
            model.cut(cuts[name])
            model.step(H, MATERIAL)
            return np.array(model.state.x)

    expected = {name: alone(name) for name in cuts}
    a = xfem_model(mesh, RHO, gravity=G, fixed=fixed)
    b = xfem_model(mesh, RHO, gravity=G, fixed=fixed)
    b.step(H, MATERIAL)
    a.step(H, MATERIAL)
    a.cut(cuts["a"])
    b.cut(cuts["b"])
    b.step(H, MATERIAL)
    a.step(H, MATERIAL)
    for name, model in (("a", a), ("b", b)):
        np.testing.assert_allclose(model.state.x, expected[name], rtol=0, atol=1e-12)
    a.close()
    b.close()
    left = [t.name for t in set(threading.enumerate()) - earlier if t.name.startswith(("xfem-boolean", "xfem-compile"))]
    assert not left
    assert a.closed and b.closed
    with pytest.raises(ValueError, match="closed"):
        a.step(H, MATERIAL)
    with CompiledSteps(limit=1) as shared:
        first = xfem_model(mesh, RHO, gravity=G, fixed=fixed, steps=shared)
        second = xfem_model(mesh, RHO, gravity=G, fixed=fixed, steps=shared)
        first.step(H, MATERIAL)
        shared.wait()
        assert len(shared) == 1  # the step's level; the next level's replaced it (the limit)
        second.step(H, MATERIAL, newton_iterations=2)
        assert len(shared) == 1
        first.close()  # shared steps are left to their owner
        assert not shared.closed
    assert shared.closed and len(shared) == 0
    with pytest.raises(ValueError, match="limit"):
        CompiledSteps(limit=0)


@pytest.mark.slow
def test_cuts_within_a_capacity_level_reuse_the_compiled_step(caplog):
    """Steps run on the system padded to a capacity level: cuts that stay within it compile nothing for the step,
    and the padded step equals the real system's step."""
    mesh = tall_box()
    model = xfem_model(mesh, RHO, gravity=G, fixed=np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9))
    cuts = [plane(), plane(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0))]
    model.step(H, MATERIAL)
    model.wait_for_compilations()  # the next level, compiled in the background
    for cut in cuts:
        model.cut(cut)
        before = model.state
        with jax.log_compiles(), caplog.at_level(logging.WARNING):
            caplog.clear()
            model.step(H, MATERIAL)
        assert not [r for r in caplog.records if "Compiling" in r.getMessage() and "_step" in r.getMessage()]
        expected = backward_euler_step(model.system(), before, H, MATERIAL, newton_iterations=1, tolerance=None)
        np.testing.assert_allclose(model.state.x, expected.x, rtol=0, atol=1e-12)


@pytest.mark.slow
def test_background_cut_takes_effect_at_commit():
    """``BackgroundCuts.submit`` prepares a cut in the worker process while the model steps its old system;
    ``commit`` makes it take effect with the state of that moment: the same model as ``cut`` called then (to the
    rounding of manifold3d's parallel Booleans, which differs between calling threads). Until then the model's
    queries answer for the committed cuts."""
    mesh = tall_box()
    fixed = np.flatnonzero(np.asarray(mesh.X)[:, 2] > 1.5 - 1e-9)
    model, inline = (xfem_model(mesh, RHO, gravity=G, fixed=fixed) for _ in range(2))
    for m in (model, inline):
        m.step(H, MATERIAL)
    background = BackgroundCuts(model)
    first = background.submit(plane())
    second = background.submit(plane(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0)))
    n = len(model.dof_sid)
    for m in (model, inline):  # the old system: no new DOFs yet
        m.step(H, MATERIAL)
    second.result()  # both prepared, neither in effect
    assert len(model.dof_sid) == n and model.pieces() == 1 and len(model.piece_arrays()[0]) == len(mesh.T)
    assert_same_run(np.asarray(model.state.x), np.asarray(inline.state.x), atol=1e-12)
    with pytest.raises(ValueError, match="until"):
        background.commit(until=Future())
    reports = background.commit(until=first)
    assert len(reports) == 1 and reports[0] is first.result() and background.pending == 1
    expected = inline.cut(plane())
    np.testing.assert_array_equal(reports[0].dof_source, expected.dof_source)
    assert model.pieces() == inline.pieces() == 2
    for m in (model, inline):
        m.step(H, MATERIAL)
    np.testing.assert_allclose(np.asarray(model.state.x), np.asarray(inline.state.x), rtol=0, atol=1e-12)
    inline.cut(plane(point=(0.5, 0.5, 0.9), normal=(0.03, 0.05, 1.0)))
    assert len(background.commit()) == 1 and background.pending == 0
    for a, b in zip(model.piece_arrays(), inline.piece_arrays()):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=0)
    assert background.commit(until=first) == [] == background.commit()  # committed already
    for m in (model, inline):
        m.step(H, MATERIAL)
    np.testing.assert_allclose(np.asarray(model.state.x), np.asarray(inline.state.x), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="cut"):
        background.submit(None)  # pyright: ignore[reportArgumentType]
    with pytest.raises(ValueError, match="perturb"):
        background.submit(plane(), perturb=-1.0)
    with pytest.raises(ValueError, match="model"):
        BackgroundCuts(inline.sub)  # pyright: ignore[reportArgumentType]
    background.close()
