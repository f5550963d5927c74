"""The quick set (``make bench-quick``): every benchmark, one after the other, at sizes that take a few minutes
together on 2 cores, into one JSON for ``benchmarks/compare.py``.

The figures the issues name keep the sizes they are defined at wherever they are cheap: one pose of 100k-vertex
skinning, 100k points, the 100k-face cut, tear and drill, the motor fields at 100k vertices. Only the expensive parts
shrink (``QUICK``): fewer repeats, 20 poses for the 1,000-pose batch, the 10k ARAP mesh without the 40k one, the
7.2k-DOF FEM block alone, the XFEM scenes, the batch of models and the viewer at their ``--quick`` sizes (their
names then stand for those sizes: compare quick runs with quick runs). Times: benchmarks/README.md, "Quick set and
comparisons". The names are prefixed with the benchmark, ``skinning.cga_motor_blend_vs_dqs_f32``; the JSON's
"benchmarks" records each one's arguments, wall time and exit status. A benchmark that fails is reported (the end
of its log) and the others run; the exit status is then 1.

``--library DIR`` measures the packages in DIR with these benchmark scripts (``_report.LIBRARY_VARIABLE``).

    python benchmarks/quick.py [--out out/bench-quick] [--only skinning kernel] [--library DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import LIBRARY_VARIABLE, ROOT  # noqa: E402

QUICK = {
    "kernel": ["--repeats", "20"],
    "skinning": ["--poses", "20", "--repeats", "150", "--batch-repeats", "1"],
    "cutting": ["--repeats", "15"],
    "deform": ["--repeats", "7", "--harmonic-repeats", "2"],
    "arap": ["--vertices", "10000", "--repeats", "2"],
    "fem": ["--sizes", "7k", "--steps", "3"],
    "xfem": ["--quick", "--no-background"],
    "batch": ["--quick", "--figures", "skinning"],
    "viewer": ["--quick"],
    "cli": ["--repeats", "1"],
}


def viewer_missing() -> str | None:
    """Why the viewer's benchmark cannot run here (no headless Chromium), or None."""
    from _jaxcga_shared.viewer.browser import chromium_missing

    return chromium_missing()


def run_one(name: str, out: Path, library: Path | None) -> dict:
    """Run ``bench_<name>.py`` with its quick arguments; its log to ``out/<name>.log``, its JSON to
    ``out/<name>.json``. Returns its record: arguments, seconds, exit status and (when it wrote one) its result."""
    env = dict(os.environ)
    env.pop(LIBRARY_VARIABLE, None)
    if library is not None:
        env[LIBRARY_VARIABLE] = str(library)
    path = out / f"{name}.json"
    path.unlink(missing_ok=True)
    command = [sys.executable, str(ROOT / "benchmarks" / f"bench_{name}.py"), *QUICK[name], "--json", str(path)]
    start = time.perf_counter()
    with open(out / f"{name}.log", "w") as log:
        code = subprocess.run(command, stdout=log, stderr=subprocess.STDOUT, env=env, cwd=ROOT).returncode
    record = {"arguments": QUICK[name], "seconds": round(time.perf_counter() - start, 1), "returncode": code}
    if code == 0 and path.exists():
        record["result"] = json.loads(path.read_text())
    return record


def merged(records: dict[str, dict]) -> dict:
    """One JSON of the benchmarks' results, names prefixed ``<benchmark>.``; platform, device and library from the
    first that ran."""
    sections = ("figures", "ratios", "units")
    result = {key: {} for key in sections}
    for name, record in records.items():
        one = record.get("result")
        if one is None:
            continue
        for key in sections:
            result[key].update({f"{name}.{figure}": value for figure, value in one[key].items()})
        for key in ("platform", "device", "library"):
            result.setdefault(key, one.get(key))
    result["benchmarks"] = {name: {k: v for k, v in r.items() if k != "result"} for name, r in records.items()}
    return result


def run(names: list[str], out: Path, library: Path | None = None) -> tuple[dict, list[str]]:
    """The quick set of ``names``, written to ``out/quick.json``; returns the merged result and the failures."""
    out.mkdir(parents=True, exist_ok=True)
    records, failed = {}, []
    for name in names:
        if name == "viewer" and (missing := viewer_missing()):
            print(f"  viewer   skipped: {missing}", flush=True)
            continue
        record = run_one(name, out, library)
        records[name] = record
        status = "ok" if "result" in record else f"FAILED (exit status {record['returncode']})"
        print(f"  {name:8s} {record['seconds']:6.1f} s  {status}", flush=True)
        if "result" not in record:
            failed.append(name)
            tail = (out / f"{name}.log").read_text().splitlines()[-15:]
            print("\n".join(f"    | {line}" for line in tail), flush=True)
    result = merged(records)
    (out / "quick.json").write_text(json.dumps(result, indent=1))
    return result, failed


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench-quick", help="logs and JSON go here")
    parser.add_argument("--only", nargs="+", choices=QUICK, default=list(QUICK), help="these benchmarks only")
    parser.add_argument("--library", type=Path, default=None, help="measure the packages in this directory")
    args = parser.parse_args(argv)
    library = None if args.library is None else args.library.absolute()
    start = time.perf_counter()
    print(f"quick set: {' '.join(args.only)}; library {library or ROOT}", flush=True)
    _, failed = run(args.only, args.out, library)
    print(f"quick set: {time.perf_counter() - start:.0f} s in all; {args.out / 'quick.json'}", flush=True)
    if failed:
        print(f"failed: {' '.join(failed)} (their logs in {args.out})", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
