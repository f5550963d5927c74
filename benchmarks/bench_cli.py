"""Command-line benchmark: a command's first run against its second, with JAX's persistent compilation cache that
the command line turns on, and the time ``jaxcga --help`` takes.

Each run is a fresh process (``python -m jaxcga_cli``, from the checkout measured), timed from its start to its exit:
the first with an empty cache directory (a new temporary one, ``JAXCGA_CACHE_DIR``), the second with what the first
wrote. The checkout's modules are compiled to bytecode first, as an installed package's are. The commands are the
README's, on CesiumMan: ``skin`` (one pose), ``cut`` (a plane across the body), ``deform ffd`` (a 4x4x4 motor
lattice bent 60 degrees) and ``arap`` (bent 60 degrees, to convergence).
``cli_first_vs_second_run_COMMAND`` is the first run's time over the second's (larger: the second run is faster);
medians over ``--repeats`` pairs, each with its own empty cache.

    python benchmarks/bench_cli.py [--repeats 3] [--commands skin cut deform arap] [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import compileall
import os
import re
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import LIBRARY, RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

MODEL = LIBRARY / "tests" / "data" / "CesiumMan.glb"
COMMANDS = {
    "skin": ["skin", str(MODEL), "--time", "0.5", "--out", "{out}/posed.glb"],
    "cut": ["cut", str(MODEL), "--plane", "0", "1", "0", "0.7", "--out", "{out}/upper.glb", "{out}/lower.glb"],
    "deform": ["deform", "ffd", str(MODEL), "--bend", "60", "--out", "{out}/bent.npy"],
    "arap": ["arap", str(MODEL), "--bend", "60", "--out", "{out}/arap.npy"],
}


def run(argv: list[str], cache: Path | None) -> float:
    """Seconds of one ``jaxcga ARGV`` in a fresh process, the cache in ``cache`` (None: turned off)."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAXCGA_NO_CACHE", "JAXCGA_CACHE_DIR")}
    if cache is None:
        env["JAXCGA_NO_CACHE"] = "1"
    else:
        env["JAXCGA_CACHE_DIR"] = str(cache)
    start = time.perf_counter()
    done = subprocess.run([sys.executable, "-m", "jaxcga_cli", *argv], cwd=LIBRARY, env=env, capture_output=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"jaxcga {' '.join(argv)} failed:\n{done.stderr.decode()[-3000:]}")
    return seconds


def first_and_second(command: str, repeats: int) -> tuple[float, float]:
    """Median seconds of the first run (empty cache) and of the second (the first's cache) of ``command``."""
    firsts, seconds = [], []
    for _ in range(repeats):
        with tempfile.TemporaryDirectory() as scratch:
            argv = [a.format(out=scratch) for a in COMMANDS[command]]
            firsts.append(run(argv, Path(scratch) / "cache"))
            seconds.append(run(argv, Path(scratch) / "cache"))
    return statistics.median(firsts), statistics.median(seconds)


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=3, help="pairs of runs per command (medians; default 3)")
    parser.add_argument("--commands", nargs="+", choices=tuple(COMMANDS), default=tuple(COMMANDS))
    parser.add_argument("--quick", action="store_true", help="skin only, one pair (a smoke run for the tests)")
    add_json_argument(parser)
    args = parser.parse_args()
    commands, repeats = (("skin",), 1) if args.quick else (args.commands, args.repeats)
    print_device("bench_cli")
    # bytecode as an installed package has it (pip compiles at install): where PYTHONDONTWRITEBYTECODE is set, as
    # here, every run would compile the checkout's changed modules again, a cost of neither run being compared
    compileall.compile_dir(str(LIBRARY), quiet=1, rx=re.compile(r"/(\.venv|\.git|out|site|notebooks)/"))
    figures, ratios = {}, {}
    helps = [run(["--help"], None) for _ in range(3 if args.quick else 7)]
    figures["cli_help_s"] = statistics.median(helps)
    print(f"jaxcga --help: {figures['cli_help_s']:.3f} s (median of {len(helps)})")
    for command in commands:
        first, second = first_and_second(command, repeats)
        figures[f"cli_{command}_first_s"], figures[f"cli_{command}_second_s"] = first, second
        ratios[f"cli_first_vs_second_run_{command}"] = first / second
        print(f"jaxcga {command}: first run {first:.2f} s, second run {second:.2f} s, ratio {first / second:.2f}")
    units = {name: "s" for name in figures} | {name: RATIO_UNIT for name in ratios}
    write_json(args.json, {"figures": figures, "ratios": ratios, "units": units})


if __name__ == "__main__":
    main()
