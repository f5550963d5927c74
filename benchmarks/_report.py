"""What every benchmark writes (DESIGN.md, "Tests and benchmarks"): ``{"figures", "ratios", "units"}``
as JSON with ``--json PATH``; a ratio is baseline time / ours (larger than 1: we are faster). Every benchmark
prints the platform and the device it runs on; on a GPU its names carry a ``_gpu`` suffix
(``per_point_f64_vs_matrix_gpu``), so CPU and GPU figures never mix.

Importing this module puts the checkout to measure first on ``sys.path``: ``$JAXCGA_BENCH_LIBRARY`` when set (make
bench-compare measures another commit's packages with this checkout's benchmarks, ``benchmarks/compare_commit.py``),
else this one (not the editable install, which may be another worktree's). A benchmark imports it before any of the
project's packages; ``print_device`` and ``write_json`` check that it did."""

from __future__ import annotations

import argparse
import json
import os
import sys
import tomllib
from pathlib import Path

import jax

RATIO_UNIT = "x (baseline time / ours)"
ROOT = Path(__file__).resolve().parents[1]
LIBRARY_VARIABLE = "JAXCGA_BENCH_LIBRARY"
LIBRARY = Path(os.environ.get(LIBRARY_VARIABLE) or ROOT).absolute()
# the project's import packages, as the distribution ships them
PACKAGES = tuple(
    pattern.rstrip("*")
    for pattern in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"]["find"][
        "include"
    ]
)
sys.path.insert(0, str(LIBRARY))


def check_library():
    """Raise unless every package of the project imported so far comes from ``LIBRARY`` (by the path it was found
    on, or with symbolic links resolved: a checkout reached through a link)."""
    for name in PACKAGES:
        module = sys.modules.get(name)
        if module is None:
            continue
        path = Path(module.__file__ or "")
        if not (path.is_relative_to(LIBRARY) or path.resolve().is_relative_to(LIBRARY.resolve())):
            raise RuntimeError(
                f"the benchmark imported {name} from {module.__file__}, not from {LIBRARY} ({LIBRARY_VARIABLE}): "
                "it must import benchmarks/_report.py before the project's packages"
            )


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
    """One line: the script, the platform and the device, e.g. ``bench_kernel: gpu, NVIDIA H100 80GB HBM3``, and the
    library measured where it is not this checkout."""
    check_library()
    library = "" if LIBRARY == ROOT else f"; library {LIBRARY}"
    print(f"{script}: {platform()}, {jax.devices()[0].device_kind}{library}", flush=True)


def with_suffix(result: dict, on: str | None = None) -> dict:
    """``result`` with every figure, ratio and unit name suffixed for platform ``on`` (``suffix``), and the
    platform, the device and the library measured recorded beside them."""
    end = suffix(on)
    named = {
        key: {f"{name}{end}": value for name, value in result[key].items()} for key in ("figures", "ratios", "units")
    }
    return named | {
        "platform": platform() if on is None else on,
        "device": jax.devices()[0].device_kind,
        "library": str(LIBRARY),
    }


def write_json(path: Path | None, result: dict):
    """Write ``result`` to ``path`` (parents created), its names suffixed for this platform (``with_suffix``);
    nothing when ``path`` is None."""
    if path is None:
        return
    check_library()  # again: a benchmark may import parts of the project late
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(with_suffix(result), indent=1))
