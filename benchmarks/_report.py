"""What every benchmark writes (DESIGN.md, "Tests and benchmarks"): ``{"figures", "ratios", "units"}``
as JSON with ``--json PATH``; a ratio is baseline time / ours (larger than 1: we are faster). Every benchmark
prints the platform and the device it runs on; on a GPU its names carry a ``_gpu`` suffix
(``per_point_f64_vs_matrix_gpu``), so CPU and GPU figures never mix."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

RATIO_UNIT = "x (baseline time / ours)"


def add_json_argument(parser: argparse.ArgumentParser):
    parser.add_argument("--json", type=Path, default=None, help="write figures, ratios and units here")


def platform() -> str:
    """The platform the benchmark's computations run on: ``cpu`` or ``gpu``."""
    return jax.default_backend()


def suffix(on: str | None = None) -> str:
    """The names' suffix on platform ``on`` (default: this process's): none on the CPU, ``_gpu`` on a GPU."""
    on = platform() if on is None else on
    return "" if on == "cpu" else f"_{on}"


def print_device(script: str):
    """One line: the script, the platform and the device, e.g. ``bench_kernel: gpu, NVIDIA H100 80GB HBM3``."""
    print(f"{script}: {platform()}, {jax.devices()[0].device_kind}", flush=True)


def with_suffix(result: dict, on: str | None = None) -> dict:
    """``result`` with every figure, ratio and unit name suffixed for platform ``on`` (``suffix``), and the
    platform and device recorded beside them."""
    end = suffix(on)
    named = {
        key: {f"{name}{end}": value for name, value in result[key].items()} for key in ("figures", "ratios", "units")
    }
    return named | {"platform": platform() if on is None else on, "device": jax.devices()[0].device_kind}


def write_json(path: Path | None, result: dict):
    """Write ``result`` to ``path`` (parents created), its names suffixed for this platform (``with_suffix``);
    nothing when ``path`` is None."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(with_suffix(result), indent=1))
