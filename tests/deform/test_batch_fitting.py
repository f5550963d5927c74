"""deform.fit_packed: fit_pose on every model of a packed batch at once, each fit equal to fit_pose of its model
alone (padded targets, bones and influences masked out)."""

from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
from _jaxcga_shared.mesh import bounding_diagonal
from tests.deform._rigs import random_model

DATA = Path(__file__).resolve().parents[1] / "data"


def _targets(model, seed):
    truth = deform.random_parameters(jax.random.PRNGKey(seed), model, rotation=0.3, translation=0.02, log_scale=0.1)
    return deform.skin_parameters(model, truth)


def _assert_equal_fits(models, fits, targets, vertices, **options):
    assert len(fits) == len(models)
    for model, fit, target, index in zip(models, fits, targets, vertices, strict=True):
        alone = deform.fit_pose(model, target, index, **options)
        diagonal = bounding_diagonal(deform.rest_pose(model, "lbs"))
        assert fit.params.shape == (model.skeleton.num_bones, deform.PARAMETERS_PER_BONE)
        assert bool(fit.converged) and bool(alone.converged)
        # equal to the solver's tolerance: the batched products round differently, and the step where a
        # solve meets its tolerance (so its last iterate) may differ by one or two
        np.testing.assert_allclose(fit.params, alone.params, atol=1e-7)
        np.testing.assert_allclose(fit.local.values, alone.local.values, atol=1e-7)
        assert fit.local.blades == alone.local.blades
        np.testing.assert_allclose(fit.positions, alone.positions, atol=1e-8 * diagonal)
        np.testing.assert_allclose(fit.max_error, alone.max_error, atol=1e-8 * diagonal)
        np.testing.assert_allclose(fit.rms_error, alone.rms_error, atol=1e-8 * diagonal)


@pytest.mark.slow
@pytest.mark.parametrize("solver", ["levenberg_marquardt", "gradient_descent"])
def test_fit_packed_equals_fit_pose_of_each_model_with_padded_targets_bones_and_influences(solver):
    # "lbs" compiles the solver in a third of the time of "cga"; the slow test below fits real models with "cga".
    # Model 0: 5 bones, 4 influences, 7 targets (padded to the 20 of model 1, masked out of the residual);
    # model 1: 3 bones (2 padded bones: their parameters must stay zero), 2 influences (2 padded, zero weights)
    models = [random_model(0, n=30), random_model(1, parents=(-1, 0, 1), n=20, influences=2)]
    vertices = [jnp.asarray([0, 3, 5, 11, 17, 22, 29]), None]
    targets = [_targets(models[0], 0)[vertices[0]], _targets(models[1], 1)]
    packed = deform.pack_models(models)
    assert packed.capacities.bones == 5 and packed.capacities.influences == 4
    # the regularization must see only the model's own bones, and only its own targets count
    # fit_packed shares fit_pose's solvers: gradient descent too (padded bones have zero gradients, so they stay zero)
    options: dict[str, Any] = dict(method="lbs", regularization=1e-4, solver=solver, max_steps=5_000)
    fits = deform.fit_packed(packed, targets, vertices, **options)
    _assert_equal_fits(models, fits, targets, vertices, **options)
    # the regularizer pulls model 0 (7 targets, 35 parameters) off its targets: the fit is not exact by itself
    assert float(fits[0].max_error) > 1e-9


def test_fit_packed_refuses_bad_input_naming_the_argument():
    models = [random_model(0, n=12), random_model(1, parents=(-1, 0), n=9)]
    packed = deform.pack_models(models)
    targets = [jnp.zeros((12, 3)), jnp.zeros((9, 3))]
    with pytest.raises(ValueError, match="packed"):
        deform.fit_packed(models, targets)  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"targets: expected one array per model \(2\), got 1"):
        deform.fit_packed(packed, targets[:1])
    with pytest.raises(ValueError, match="targets: expected a list"):
        deform.fit_packed(packed, jnp.zeros((2, 12, 3)))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match=r"targets\[1\]: expected shape \(9, 3\)"):
        deform.fit_packed(packed, [targets[0], jnp.zeros((9, 2))])
    with pytest.raises(ValueError, match=r"targets\[0\]: contains NaN"):
        deform.fit_packed(packed, [targets[0].at[3, 1].set(jnp.nan), targets[1]])
    with pytest.raises(ValueError, match=r"vertices: expected one array per model \(2\), got 3"):
        deform.fit_packed(packed, targets, [None, None, None])
    # an index of model 1 past its own 9 vertices, though within the packed block's 21
    with pytest.raises(ValueError, match=r"vertices\[1\]: vertex indices must lie in \[0, 9\)"):
        deform.fit_packed(packed, [targets[0], jnp.zeros((2, 3))], [None, jnp.asarray([0, 9])])
    with pytest.raises(ValueError, match=r"vertices\[0\]: expected a \(t,\) integer array"):
        deform.fit_packed(packed, [jnp.zeros((2, 3)), targets[1]], [jnp.asarray([0.0, 1.0]), None])
    with pytest.raises(ValueError, match="method: dual-quaternion skinning cannot represent dilations"):
        deform.fit_packed(packed, targets, method="dqs")
    with pytest.raises(ValueError, match="method: expected one of"):
        deform.fit_packed(packed, targets, method="nearest")
    with pytest.raises(ValueError, match="solver: expected one of"):
        deform.fit_packed(packed, targets, solver="newton")
    with pytest.raises(ValueError, match="regularization: expected >= 0"):
        deform.fit_packed(packed, targets, regularization=-1.0)
    with pytest.raises(ValueError, match="max_steps: expected an int >= 1"):
        deform.fit_packed(packed, targets, max_steps=0)


@pytest.mark.slow
def test_fit_packed_equals_fit_pose_on_real_models():
    # fit_pose's own slow test (tests/deform/test_models.py) recovers such poses of Arm5 from all its vertices;
    # every model's targets are padded to the largest target count (CesiumMan's would make it four CesiumMan fits)
    models = [deform.load_model(DATA / f"{name}.glb") for name in ("RiggedSimple", "Arm5")]
    models.append(random_model(2, parents=(-1, 0, 0, 1, 2, 3, 3), n=300, influences=3))
    targets = [_targets(model, seed) for seed, model in enumerate(models)]
    vertices = [None] * len(models)
    packed = deform.pack_models(models, blocks=2)
    fits = deform.fit_packed(packed, targets)
    _assert_equal_fits(models, fits, targets, vertices)
    for model, fit in zip(models, fits, strict=True):
        assert float(fit.max_error) <= 1e-6 * bounding_diagonal(deform.rest_pose(model, "lbs"))
