"""``jaxcga animate``: an animated glTF whose clip is re-sampled through the multivector (versor) path."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "re-sample a rigged model's animation at FRAMES times through conformal-geometric-algebra versors "
    "(rotation, translation and scale in one object) and write it as an animated glTF"
)
EXAMPLE = "jaxcga animate tests/data/CesiumMan.glb --frames 120 --interpolation log --out walk.glb"

# Peak memory per bone and frame while sampling (the vmapped versors, their TRS and the glTF buffers): the growth
# of the peak resident size from 16k to 64k frames of CesiumMan (20 bones; the built-in arm's 4 bones take less),
# with headroom for other machines' allocators: the guard below refuses a request that would not fit.
MEASURED_BYTES_PER_BONE_FRAME = 940
HEADROOM = 1.5
BYTES_PER_BONE_FRAME = int(MEASURED_BYTES_PER_BONE_FRAME * HEADROOM)


def add_arguments(parser) -> None:
    arguments.model_argument(parser)
    parser.add_argument("--frames", type=int, default=60, help="frames to sample (default 60)")
    arguments.clip_argument(parser)
    arguments.interpolation_argument(parser)
    parser.add_argument("--out", type=Path, required=True, help="OUT.glb or OUT.gltf")


def check_paths(args) -> None:
    from jaxcga_cli.output import GLTF_OUTPUTS, check_files

    check_files(args, ("model",), {"out": args.out}, GLTF_OUTPUTS, gltf=True)


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    from jaxcga_cli.models import load_model

    model = load_model(args.model, weld=args.weld)
    arguments.check_clip(model, args.clip, interpolation=args.interpolation)
    return model.name, animate_command(model, args.frames, args.out, args.clip, args.interpolation)


def available_memory() -> int:
    """Bytes of memory available to a new allocation now: /proc/meminfo's MemAvailable (free memory and the
    caches the kernel can drop), else the free pages."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")


def check_memory(frames: int, bones: int) -> None:
    """Refuse, before allocating anything, ``frames`` samples of ``bones`` bones that would not fit in the
    memory available now."""
    need = frames * bones * BYTES_PER_BONE_FRAME
    have = available_memory()
    if need > have:
        fit = max(2, have // (bones * BYTES_PER_BONE_FRAME))
        raise ValueError(
            f"frames: {frames} frames of {bones} bones need about {need / 2**30:.1f} GiB, more than the "
            f"{have / 2**30:.1f} GiB of memory available now; give at most --frames {fit}"
        )


def animate_command(model, frames: int, out: Path, clip: int | str = 0, interpolation: str = "gltf") -> dict:
    """Write an animated glTF: the model's clip re-sampled at ``frames`` times as similitudes, its keys
    interpolated by ``interpolation`` (``"gltf"``: the specification's; ``"log"``: logarithmic
    blending of key versors, sec. 4.1), or generated keyframes (linear blending) when the model has
    no clip."""
    if frames < 2:
        raise ValueError(f"frames: expected at least 2, got {frames}")
    check_memory(frames, model.skeleton.num_bones)
    import jax
    import jax.numpy as jnp

    import deform
    from jaxcga_cli.report import status

    with status("animate", f"sampling {frames} frames of {model.skeleton.num_bones} bones (compiling)"):
        if model.clips:
            source = model.clip(clip)
            times = jnp.linspace(source.start, source.end, frames, dtype=model.mesh.V.dtype)
            local = jax.jit(jax.vmap(lambda t: deform.sample_pose(model, t, "cga", clip, interpolation)))(times)
            name = f"{source.name}_cga"
        else:
            keys = generated_keyframes(model)
            times = jnp.linspace(0.0, float(keys.times[-1]), frames, dtype=model.mesh.V.dtype)
            local = jax.jit(jax.vmap(lambda t: deform.sample_keyframes(keys, t)))(times)
            name = "generated_keyframes"
        animation = deform.clip_from_poses(times, local, name)
    deform.save_model(deform.RiggedModel(model.mesh, model.skeleton, (animation,), model.name), out)
    return {"frames": frames, "clip": name, "bones": model.skeleton.num_bones, "out": str(out)}


def generated_keyframes(model, duration: float = 2.0):
    """Keyframes made on the fly (sec. 2.5 / 4.1): rest, every bone bent about its local x axis with
    the deepest bone dilated by 1.25, and rest again; blended linearly by ``deform.sample_keyframes``."""
    import jax.numpy as jnp
    import numpy as np

    import deform
    import jaxcga as cga

    skeleton = model.skeleton
    rest = deform.local_versors(skeleton)
    depth = np.zeros(skeleton.num_bones, int)
    for i, p in enumerate(skeleton.parents):
        depth[i] = 0 if p < 0 else depth[p] + 1
    dtype = rest.dtype
    bend = cga.rotor(jnp.asarray([1.0, 0.0, 0.0], dtype), jnp.asarray(0.35 * (depth > 0), dtype))
    scale = jnp.where(jnp.asarray(depth == depth.max()), 1.25, 1.0).astype(dtype)
    bent = (rest * bend * cga.dilator(scale)).embed(cga.KINDS["similitude"])
    poses = cga.Multivector(jnp.stack([rest.values, bent.values, rest.values]), rest.blades)
    return deform.Keyframes(jnp.asarray([0.0, duration / 2, duration], dtype), poses)
