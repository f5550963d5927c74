"""``jaxcga animate-batch``: many different rigged models animated in one compiled call, over every device of one
process or of several processes (``jax.distributed``), each process writing the models its devices computed.

The models are packed (``deform.pack_models``) into one block per row of a device mesh with axes ``"models"``
(the rows) and ``"time"`` (``--time-shards`` devices per row, splitting the frames) and skinned by
``deform.skin_packed``. The devices are ordered by process, so every row lies on one process and a process writes
whole models. Every process loads and packs all the models (identical on each, and small next to the skinning) and
places its own devices' pieces of the global arrays.

OUT holds one run: ``<stem>.npy`` per model (named after its file; ``-2``, ``-3``, ... for repeated stems),
float64 (frames, n, 3) world-space positions, and ``batch.json`` (models, frames, which process wrote which file,
the packed capacities and padding). Each process writes its files into a private folder inside OUT and moves them
in once every process has computed and written its share; process 0 writes ``batch.json`` last, after every
process has moved its files in, so a folder with ``batch.json`` holds a complete run. OUT must be empty unless
``--force``; with it, this run's files replace those of the same names (no other file is removed).
"""

from __future__ import annotations

import argparse
import contextlib
import os
import re
import warnings
from collections.abc import Iterator
from pathlib import Path

from jaxcga_cli import arguments

HELP = (
    "animate many different rigged models at once, over every device of one machine or of several machines "
    "(one process each), and write each model's frames of skinned vertex positions"
)
EXAMPLE = "jaxcga animate-batch tests/data/CesiumMan.glb tests/data/RiggedSimple.glb --frames 30 --out out/batch"
MANIFEST = "batch.json"
DISTRIBUTED_HELP = "the same command once per process (one per machine or one per GPU), each with its --process-id"
# Peak memory per packed vertex slot and frame on a process (the skinned positions on the device and their float64
# copies on the host): the growth of the peak resident size from 1024 to 8192 frames of CesiumMan and Arm5 in one
# block, with headroom; the guard refuses a request that would not fit.
MEASURED_BYTES_PER_SLOT_FRAME = 33
HEADROOM = 1.5
BYTES_PER_SLOT_FRAME = int(MEASURED_BYTES_PER_SLOT_FRAME * HEADROOM)
TIMEOUT = 300  # seconds, jax.distributed.initialize's own default


def add_arguments(parser) -> None:
    parser.add_argument(
        "models",
        nargs="*",
        metavar="MODEL",
        help="glTF (.gltf/.glb), or FBX/COLLADA through assimp, any number, repeats allowed; default: the built-in arm",
    )
    arguments.weld_argument(parser)
    parser.add_argument(
        "--frames", type=int, default=60, help="frames per model, spread evenly over its clip (default 60)"
    )
    parser.add_argument("--method", choices=arguments.METHODS, default="cga", help=arguments.METHODS_HELP)
    arguments.clip_argument(parser)
    arguments.interpolation_argument(parser)
    parser.add_argument(
        "--time-shards",
        type=int,
        default=1,
        help="devices that split each block's frames (the mesh axis 'time'; default 1); the other devices split "
        "the models. It must divide every process's device count and --frames",
    )
    group = parser.add_argument_group("several processes", DISTRIBUTED_HELP)
    group.add_argument(
        "--coordinator",
        metavar="HOST:PORT",
        help="address of process 0, which every process connects to (default: $JAX_COORDINATOR_ADDRESS, as "
        "jax.distributed.initialize reads it). Given (either way), the run uses jax.distributed",
    )
    group.add_argument(
        "--num-processes",
        type=int,
        metavar="P",
        help="number of processes (default: $JAX_NUM_PROCESSES, else a cluster jax.distributed detects, else 1)",
    )
    group.add_argument(
        "--process-id",
        type=int,
        metavar="I",
        help="this process's index, 0 to P-1 (default: $JAX_PROCESS_ID, else a cluster jax.distributed detects)",
    )
    group.add_argument(
        "--timeout",
        type=float,
        default=TIMEOUT,
        metavar="SECONDS",
        help=f"give up when the other processes have not all connected within this many seconds (default {TIMEOUT}); "
        "a status line says whom this process waits for",
    )
    group.add_argument(
        "--distributed",
        action="store_true",
        help="use jax.distributed and let it detect what is not given (coordinator, P, I) from its cluster "
        "environment: Slurm (srun), Open MPI (mpirun), Kubernetes, ...",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="write into a non-empty OUT: this run's files replace those of the same names; other files stay",
    )
    parser.add_argument(
        "--out",
        type=Path,
        required=True,
        help=f"folder for one float64 (frames, n, 3) STEM.npy per model and {MANIFEST} (with several processes: "
        "each writes its models' files; on a shared file system they meet in one folder)",
    )


def check_paths(args) -> None:
    from _jaxcga_shared.output import check_input, check_run_folder

    inputs = {f"model {i + 1}": check_input(path, "model") for i, path in enumerate(args.models)}
    names = file_names(args.models)
    check_run_folder(
        args.out,
        run_files(names),
        args.force,
        f"files {', '.join(names[:3])}{', ...' if len(names) > 3 else ''}",
        inputs=inputs,
    )


def file_names(paths: list[str]) -> list[str]:
    """The output file name of each model: its file's stem (``default_arm`` for the built-in arm) with ``.npy``;
    a stem met again, in any case (case-insensitive file systems), gets ``-2``, ``-3``, ..."""
    taken: set[str] = set()
    names = []
    for path in paths or [None]:
        stem = Path(path).stem.lstrip(".") if path is not None else "default_arm"
        name, k = stem or "model", 1
        while name.lower() in taken:
            k += 1
            name = f"{stem}-{k}"
        taken.add(name.lower())
        names.append(f"{name}.npy")
    return names


def run_files(names: list[str]) -> re.Pattern:
    """The files of a run writing ``names``: these and the manifest."""
    return re.compile("|".join(re.escape(n) for n in [*names, MANIFEST]))


def _given(args, option: str, variable: str) -> tuple[int | None, str]:
    """The integer of ``option``, else of the environment ``variable``, else None; and where it came from."""
    value = getattr(args, option[2:].replace("-", "_"))
    if value is not None:
        return value, f"{option} {value}"
    text = os.environ.get(variable, "")
    if not text:
        return None, option
    try:
        return int(text), f"${variable} = {text}"
    except ValueError:
        raise ValueError(f"{option[2:].replace('-', '_')}: ${variable} = {text!r} is not an integer") from None


def distributed_options(args) -> dict | None:
    """The arguments of ``jax.distributed.initialize`` from the options, or their environment variables, or None
    for one process: the coordinator's address, the process count and this process's index (None: left to
    JAX's cluster detection)."""
    coordinator = args.coordinator or os.environ.get("JAX_COORDINATOR_ADDRESS") or None
    count, count_from = _given(args, "--num-processes", "JAX_NUM_PROCESSES")
    index, index_from = _given(args, "--process-id", "JAX_PROCESS_ID")
    if count is not None and count < 1:
        raise ValueError(f"num_processes: expected --num-processes >= 1, got {count_from}")
    if index is not None and (index < 0 or (count is not None and index >= count)):
        limit = f"0 to {count - 1} for {count_from}" if count is not None else "at least 0"
        raise ValueError(f"process_id: {index_from} is out of range (expected {limit})")
    if coordinator is None and not args.distributed:
        if count not in (None, 1):
            raise ValueError(
                f"coordinator: {count_from} needs --coordinator HOST:PORT (the address of process 0), "
                "or $JAX_COORDINATOR_ADDRESS, or --distributed in a cluster jax.distributed detects"
            )
        if index not in (None, 0):
            raise ValueError(f"coordinator: {index_from} needs --coordinator HOST:PORT and --num-processes")
        return None
    return {"coordinator_address": coordinator, "num_processes": count, "process_id": index}


# jax.distributed's own deadline, past ours: its expiry aborts the process natively (a C++ stack), so the watchdog
# below must fire first.
_GRACE = 30


def initialize(options: dict, timeout: float = TIMEOUT) -> None:
    """``jax.distributed.initialize`` (before anything touches a JAX backend), its missing-value errors naming the
    command's options; a status line while it waits for the other processes, and a one-line error and exit 2 when
    they have not all connected within ``timeout`` seconds."""
    import math
    import threading
    import time

    import jax

    from jaxcga_cli.report import say

    count, index = options["num_processes"], options["process_id"]
    address = options["coordinator_address"] or "the address jax.distributed detects"
    others = f"{count - 1} more process{'es' if count > 2 else ''}" if count is not None else "the other processes"
    me = f"process {index} of {count}: " if index is not None and count is not None else ""
    say("animate-batch", f"{me}waiting for {others} at {address} (at most {timeout:g} s, --timeout)")
    connected = threading.Event()

    def watchdog() -> None:
        if connected.wait(timeout):
            return
        say(
            "animate-batch",
            f"error: coordinator: {me}still waiting for {others} at {address} after {timeout:g} s (--timeout); "
            "start every process with the same --coordinator and --num-processes and its own --process-id",
        )
        os._exit(2)  # the connection runs in native code, which no Python exception interrupts

    start = time.perf_counter()
    threading.Thread(target=watchdog, name="jaxcga-distributed-timeout", daemon=True).start()
    try:
        jax.distributed.initialize(**options, initialization_timeout=math.ceil(timeout) + _GRACE)
    except ValueError as error:
        text = str(error)
        for what, option in (
            ("coordinator", "--coordinator HOST:PORT (or $JAX_COORDINATOR_ADDRESS)"),
            ("number of processes", "--num-processes (or $JAX_NUM_PROCESSES)"),
            ("process id", "--process-id (or $JAX_PROCESS_ID)"),
        ):
            if what in text.lower():
                name = option[2:].split()[0].replace("-", "_")
                raise ValueError(
                    f"{name}: not given and no cluster detected by jax.distributed; give {option}"
                ) from None
        raise
    finally:
        connected.set()
    say("animate-batch", f"{me}connected: {jax.process_count()} processes in {time.perf_counter() - start:.1f} s")


def run(args: argparse.Namespace) -> tuple[str, dict[str, object]]:
    if args.frames < 1:
        raise ValueError(f"frames: expected --frames >= 1, got {args.frames}")
    if args.time_shards < 1:
        raise ValueError(f"time_shards: expected --time-shards >= 1, got {args.time_shards}")
    if args.frames % args.time_shards:
        raise ValueError(
            f"time_shards: --frames {args.frames} do not split over --time-shards {args.time_shards} devices; give "
            "a multiple"
        )
    if not 0 < args.timeout < 10**6:
        raise ValueError(f"timeout: expected --timeout in (0, 1e6) seconds, got {args.timeout:g}")
    options = distributed_options(args)
    import jax

    if options is not None:
        initialize(options, args.timeout)
    try:
        return batch_command(
            args.models,
            args.out,
            args.frames,
            args.method,
            args.clip,
            args.interpolation,
            time_shards=args.time_shards,
            weld=args.weld,
        )
    finally:
        if options is not None:
            # every process, also after an error: lets its peers shut down instead of waiting for its heartbeat
            jax.distributed.shutdown()


def check_memory(frames: int, blocks: int, slots: int) -> None:
    """Refuse, before skinning, ``frames`` frames of this process's ``blocks`` blocks of ``slots`` vertex slots each
    when they would not fit in the memory available now (``BYTES_PER_SLOT_FRAME``)."""
    from jaxcga_cli.animate import available_memory

    need = frames * blocks * slots * BYTES_PER_SLOT_FRAME
    have = available_memory()
    if need > have:
        fit = have // (blocks * slots * BYTES_PER_SLOT_FRAME)
        raise ValueError(
            f"frames: {frames} frames of {blocks} block{'s' if blocks > 1 else ''} of {slots} vertex slots need about "
            f"{need / 2**30:.1f} GiB on this process, more than the {have / 2**30:.1f} GiB of memory available now; "
            + (f"give at most --frames {fit}" if fit else "give fewer or smaller models per process")
        )


def device_mesh(time_shards: int):
    """A mesh over every process's devices with axes ("models", "time"), ``time_shards`` devices per row, ordered
    by process so that every row lies on one process."""
    import jax
    import numpy as np
    from jax.sharding import Mesh

    devices = sorted(jax.devices(), key=lambda d: (d.process_index, d.id))
    counts = {p: sum(d.process_index == p for d in devices) for p in range(jax.process_count())}
    if any(n % time_shards for n in counts.values()):
        raise ValueError(
            f"time_shards: --time-shards {time_shards} does not divide every process's device count "
            f"({', '.join(f'process {p}: {n}' for p, n in counts.items())}); a block's frames stay on one process"
        )
    return Mesh(np.array(devices).reshape(-1, time_shards), ("models", "time"))


def _agree(ok: bool, what: str) -> None:
    """Wait for every process (a barrier) and raise here too when another process failed ``what``."""
    import jax
    import numpy as np
    from jax.experimental import multihost_utils

    if jax.process_count() == 1:
        return
    failed = np.flatnonzero(~np.asarray(multihost_utils.process_allgather(np.asarray(ok)), bool).reshape(-1))
    if len(failed) and ok:
        raise RuntimeError(f"process {', '.join(map(str, failed))} failed {what}; this process wrote nothing")


@contextlib.contextmanager
def _together(what: str) -> Iterator[None]:
    """The block on every process, then a barrier: when it fails on one process, that one raises its error and
    every other a RuntimeError naming it, instead of waiting for it at the next collective."""
    try:
        yield
    except (ValueError, OSError, RuntimeError):
        _agree(False, what)
        raise
    _agree(True, what)


def batch_command(
    paths: list[str],
    out: Path,
    frames: int,
    method: str = "cga",
    clip: int | str = 0,
    interpolation: str = "gltf",
    *,
    time_shards: int = 1,
    weld: bool = False,
) -> tuple:
    """Skin every model of ``paths`` (none: the built-in arm) at ``frames`` times over its clip in one call on the
    mesh of ``device_mesh`` and write this process's models to ``out`` (module docstring)."""
    import jax
    import numpy as np

    import deform
    from _jaxcga_shared.output import run_folder, write_json
    from jaxcga_cli.models import load_model
    from jaxcga_cli.report import status

    names = file_names(paths)
    mesh = device_mesh(time_shards)
    rows = mesh.shape["models"]
    me, processes = jax.process_index(), jax.process_count()
    models = [load_model(path, weld=weld) for path in paths or [None]]
    packed = deform.pack_models(models, blocks=rows)
    times = packed.frame_times(frames, clip)
    for m, model in enumerate(models):
        if not model.clips and interpolation != "gltf":
            warnings.warn(
                f"{packed.names[m]} has no clip: posed at rest, --interpolation {interpolation} ignored", stacklevel=2
            )
    mine = sum(int(mesh.devices[b, 0].process_index) == me for b in range(rows))
    check_memory(frames, mine, packed.capacities.vertices)
    where = f"process {me} of {processes}: " if processes > 1 else ""
    vertices = sum(packed.vertex_count)
    doing = f"{where}skinning {len(models)} models, {vertices} vertices, {frames} frames (compiling)"
    with _together("to skin its models"), status("animate-batch", doing):
        positions = deform.skin_packed(packed, times, method, clip=clip, interpolation=interpolation, mesh=mesh)
        local = packed.unpack_local(positions)
        for m, frames_m in local.items():
            if not np.all(np.isfinite(frames_m)):
                raise ValueError(f"model: {paths[m] if paths else 'the built-in arm'} gave non-finite positions")
    mine = run_files([names[m] for m in local] + ([MANIFEST] if me == 0 else []))
    with run_folder(out, mine, MANIFEST) as staging, _together("to write its files"):
        for m, frames_m in local.items():
            with open(staging / names[m], "wb") as file:
                np.save(file, np.asarray(frames_m, np.float64))
    _agree(True, "to move its files in")
    owner = [int(mesh.devices[b, 0].process_index) for b in range(rows)]
    clips = packed.clip_indices(clip)
    if me == 0:
        write_json(
            out / MANIFEST,
            {
                "frames": frames,
                "method": method,
                "clip": clip,
                "interpolation": interpolation,
                "dtype": "float64",
                "processes": processes,
                "mesh": {"models": rows, "time": time_shards},
                "capacities": packed.capacities._asdict(),
                "padding": packed.padding,
                "models": [
                    {
                        "file": names[m],
                        "source": str(paths[m]) if paths else "built-in arm",
                        "name": packed.names[m],
                        "shape": [frames, packed.vertex_count[m], 3],
                        "clip": packed.clip_names[m][clips[m]] if packed.clip_names[m] else None,
                        "start": float(times[m, 0]),
                        "end": float(times[m, -1]),
                        "block": packed.block[m],
                        "process": owner[packed.block[m]],
                    }
                    for m in range(len(models))
                ],
            },
        )
    wrote = sorted(names[m] for m in local)
    return f"{len(models)} models", {
        "frames": frames,
        "method": method,
        "process": f"{me} of {processes}",
        "mesh": f"{rows} x {time_shards}",
        "wrote": f"{len(wrote)} files",
        "padding": f"{packed.padding:.3g}",
        "out": str(out),
    }
