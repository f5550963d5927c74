"""Packed batches of different rigged models (deform.pack_models / skin_packed): each model of a batch against
skinning it alone (deform.skin_model), padding, compile reuse, sharding over devices, and bad input."""

from __future__ import annotations

from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import deform
from tests.deform._rigs import random_model, scaled_keys_model
from tests.shared import run_on_host_devices

DATA = Path(__file__).resolve().parents[1] / "data"


@pytest.fixture(scope="module")
def crowd(tmp_path_factory):
    """Models of different vertex, bone, joint, influence and clip counts: two files, a rig with a scale-keyed
    clip, two rigs without clips (one with 2 influences per vertex)."""
    return [
        deform.load_model(DATA / "CesiumMan.glb"),
        deform.load_model(DATA / "RiggedSimple.glb"),
        scaled_keys_model(tmp_path_factory.mktemp("keys") / "keys.glb"),
        random_model(0),
        random_model(3, parents=(-1, 0, 0, 1, 2, 3, 3), n=100, influences=2),
    ]


def _alone(model, times, method, interpolation="gltf"):
    return np.asarray(jax.jit(jax.vmap(lambda t: deform.skin_model(model, t, method, 0, interpolation)))(times))


def _assert_each_model_alone(models, packed, times, out, method, interpolation="gltf"):
    frames = packed.unpack(out)
    assert len(frames) == len(models)
    for model, own_times, result in zip(models, times, frames, strict=True):
        expected = _alone(model, jnp.asarray(own_times), method, interpolation)
        assert result.shape == expected.shape
        # equal to rounding: the batched 4x4 products of the packed bones round differently in the last bits
        scale = float(np.ptp(expected.reshape(-1, 3), axis=0).max())
        np.testing.assert_allclose(result, expected, rtol=0, atol=1e-13 * scale)


def test_capacity_levels():
    levels = [deform.capacity(n) for n in range(0, 5000)]
    assert levels[:9] == [1, 1, 2, 3, 4, 5, 6, 7, 8]
    for n, c in enumerate(levels[1:], start=1):
        assert n <= c <= max(8, 1.25 * n)
    assert all(a <= b for a, b in zip(levels, levels[1:]))
    # four levels per octave past 8: few distinct shapes, so new batches reuse compiled functions
    assert sorted({c for c in levels if 1024 < c <= 2048}) == [1280, 1536, 1792, 2048]


@pytest.mark.slow
@pytest.mark.parametrize("method", ["cga", "lbs"])
def test_each_model_of_a_packed_batch_equals_skinning_it_alone(crowd, method):
    packed = deform.pack_models(crowd)
    times = packed.frame_times(5)
    out = deform.skin_packed(packed, times, method)
    c = packed.capacities
    assert out.shape == (1, 5, c.vertices, 3)
    assert bool(jnp.all(jnp.isfinite(out)))  # padded vertices too
    _assert_each_model_alone(crowd, packed, times, out, method)


@pytest.mark.slow
@pytest.mark.parametrize(
    "method, interpolation", [("cga_motor_blend", "gltf"), ("dqs", "gltf"), ("cga", "log"), ("lbs", "log")]
)
def test_every_method_and_sampling_of_a_packed_batch(crowd, method, interpolation):
    # dual quaternions have no dilation: the scale-keyed rig is refused by skin_model as by skin_packed
    models = [m for i, m in enumerate(crowd) if method != "dqs" or i != 2]
    packed = deform.pack_models(models)
    times = packed.frame_times(4)
    out = deform.skin_packed(packed, times, method, interpolation=interpolation)
    _assert_each_model_alone(models, packed, times, out, method, interpolation)


def test_layout_capacities_and_padding(crowd):
    packed = deform.pack_models(crowd)
    c = packed.capacities
    sizes = [m.mesh.num_vertices for m in crowd]
    assert c.blocks == 1 and c.models == len(crowd)
    assert c.vertices == deform.capacity(sum(sizes))
    assert c.bones == deform.capacity(max(m.skeleton.num_bones for m in crowd))
    assert c.influences == 4
    assert packed.vertex_count == tuple(sizes)
    assert packed.vertex_offset == tuple(np.cumsum([0] + sizes[:-1]))
    real = sum(n * int(m.mesh.J.shape[1]) for n, m in zip(sizes, crowd, strict=True))
    assert packed.padding == pytest.approx(c.vertices * c.influences / real)
    assert packed.padding <= 1.5
    # models spread over blocks with balanced vertex totals, each block's models in the order given
    four = deform.pack_models(crowd, blocks=3)
    loads = [sum(n for n, b in zip(sizes, four.block, strict=True) if b == k) for k in range(3)]
    assert sorted(loads)[-1] == max(sizes) and len(set(four.block)) == 3
    assert four.capacities.vertices == deform.capacity(max(loads))


def test_frame_times_and_clip_choice(crowd):
    packed = deform.pack_models(crowd)
    times = packed.frame_times(3)
    assert times.shape == (len(crowd), 3)
    for model, row in zip(crowd, times, strict=True):
        if model.clips:
            np.testing.assert_allclose(row, np.linspace(model.clips[0].start, model.clips[0].end, 3))
        else:
            assert not row.any()
    name = crowd[0].clips[0].name
    with pytest.raises(ValueError, match="clip: model 1 .* has no clip"):
        packed.clip_indices(name)
    assert list(packed.clip_indices([0, -1, 0, 0, 0])) == [0, 0, 0, 0, 0]
    with pytest.raises(ValueError, match="clip: model 0 .* has 1 clips, no clip 3"):
        packed.clip_indices(3)
    with pytest.raises(ValueError, match="clip: expected one clip or 5"):
        packed.clip_indices([0, 0])
    with pytest.raises(ValueError, match="frames: expected an int >= 1"):
        packed.frame_times(0)


@pytest.mark.slow
def test_a_new_batch_packed_at_least_as_large_reuses_the_shapes(crowd):
    first = deform.pack_models(crowd)
    second = deform.pack_models(crowd[1:4], at_least=first.capacities)
    assert second.capacities == first.capacities

    def signature(packed):
        arrays, static = eqx.partition(packed.rigs, eqx.is_array)
        return jax.tree.structure(packed.rigs), jax.tree.map(lambda x: (x.shape, x.dtype), arrays)

    # same tree (static channel groups included), shapes and dtypes: skin_packed's compiled function is reused
    assert signature(second) == signature(first)
    times = second.frame_times(5)
    _assert_each_model_alone(crowd[1:4], second, times, deform.skin_packed(second, times), "cga")
    with pytest.raises(ValueError, match="at_least: packed for 1 blocks, asked for 2"):
        deform.pack_models(crowd, blocks=2, at_least=first.capacities)


def test_one_time_row_for_every_model_and_padding_rows_are_inert(crowd):
    packed = deform.pack_models(crowd[1:])
    times = jnp.asarray([0.0, 0.3])
    out = deform.skin_packed(packed, times, "lbs")
    alone = deform.pack_models(crowd[1:2])
    np.testing.assert_allclose(
        packed.unpack(out)[0], alone.unpack(deform.skin_packed(alone, times, "lbs"))[0], rtol=0, atol=1e-14
    )


@pytest.mark.slow
def test_a_model_with_a_non_uniform_scale_fails_by_name_in_a_batch(crowd):
    odd = random_model(5)
    skeleton = eqx.tree_at(lambda s: s.scale, odd.skeleton, odd.skeleton.scale.at[1].set(jnp.asarray([1.0, 2.0, 1.0])))
    odd = deform.RiggedModel(odd.mesh, skeleton, (), "odd")
    packed = deform.pack_models([crowd[1], odd])
    with pytest.raises(ValueError, match="non-uniform or non-positive bone scale"):
        deform.skin_packed(packed, jnp.zeros(2), "cga")
    assert bool(jnp.all(jnp.isfinite(deform.skin_packed(packed, jnp.zeros(2), "lbs"))))


def test_bad_input_names_the_argument(crowd):
    with pytest.raises(ValueError, match="models: expected at least one"):
        deform.pack_models([])
    with pytest.raises(ValueError, match="models: item 1 is a str"):
        deform.pack_models([crowd[1], "model.glb"])  # pyright: ignore[reportArgumentType]
    single = deform.RiggedModel(
        jax.tree.map(lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, crowd[3].mesh),
        crowd[3].skeleton,
    )
    with pytest.raises(ValueError, match="models: every model needs the same float dtype"):
        deform.pack_models([crowd[3], single])
    with pytest.raises(ValueError, match="blocks: expected an int >= 1"):
        deform.pack_models(crowd, blocks=0)
    with pytest.raises(ValueError, match="at_least: expected the Capacities"):
        deform.pack_models(crowd, at_least=(1, 2))  # type: ignore[arg-type]
    packed = deform.pack_models(crowd[1:3])
    with pytest.raises(ValueError, match="packed: expected the PackedModels"):
        deform.skin_packed(crowd[1], jnp.zeros(2))  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="method: expected one of"):
        deform.skin_packed(packed, jnp.zeros(2), "quaternion")
    with pytest.raises(ValueError, match=r"times: expected shape \(2, T\)"):
        deform.skin_packed(packed, jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="times: contains NaN"):
        deform.skin_packed(packed, jnp.asarray([0.0, jnp.nan]))
    with pytest.raises(ValueError, match="mesh: expected a jax.sharding.Mesh"):
        deform.skin_packed(packed, jnp.zeros(2), mesh="cpu")  # type: ignore[arg-type]
    mesh = jax.make_mesh((1,), ("batch",))
    with pytest.raises(ValueError, match="mesh: expected axes named 'models' and 'time'"):
        deform.skin_packed(packed, jnp.zeros(2), mesh=mesh)
    with pytest.raises(ValueError, match="mesh: its 'models' axis has 1 devices; pack the models with blocks=1"):
        deform.skin_packed(
            deform.pack_models(crowd[1:3], blocks=2), jnp.zeros(2), mesh=jax.make_mesh((1,), ("models",))
        )
    with pytest.raises(ValueError, match=r"positions: expected shape \(1, T,"):
        packed.unpack(np.zeros((1, 2, 5, 3)))


@pytest.mark.slow
def test_sharded_over_models_and_time_equals_one_device(crowd, tmp_path):
    """The batch split over 4 forced host devices (blocks over "models", frames over "time") in a fresh process
    (XLA_FLAGS must be set first), against one device in this process."""
    script = f"""
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        import deform
        from tests.deform._rigs import random_model, scaled_keys_model
        assert len(jax.devices()) == 4, jax.devices()
        data, keys = {str(DATA)!r}, {str(tmp_path / "keys.glb")!r}
        crowd = [deform.load_model(data + "/CesiumMan.glb"), deform.load_model(data + "/RiggedSimple.glb"),
                 scaled_keys_model(keys), random_model(0), random_model(3, (-1, 0, 0, 1, 2, 3, 3), 100, 2)]
        times = deform.pack_models(crowd).frame_times(8)
        for shape in [(4, 1), (2, 2)]:
            packed = deform.pack_models(crowd, blocks=shape[0])
            out = deform.skin_packed(packed, times, "cga", mesh=jax.make_mesh(shape, ("models", "time")))
            assert len(out.sharding.device_set) == 4
            for m, frames in enumerate(packed.unpack(out)):
                np.save({str(tmp_path)!r} + f"/{{shape[0]}}_{{m}}.npy", frames)
        print("sharded ok")
    """
    assert "sharded ok" in run_on_host_devices(script)
    packed = deform.pack_models(crowd)
    times = packed.frame_times(8)
    expected = packed.unpack(deform.skin_packed(packed, times, "cga"))
    for blocks in (4, 2):
        for m, frames in enumerate(expected):
            np.testing.assert_allclose(np.load(tmp_path / f"{blocks}_{m}.npy"), frames, rtol=0, atol=1e-13)
