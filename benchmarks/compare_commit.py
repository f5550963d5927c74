"""``make bench-compare BASE=<commit>``: the quick set (``benchmarks/quick.py``) on BASE's packages and on this
working tree's, in alternation (BASE, tree, BASE, tree: machine load falls on both), then ``benchmarks/compare.py``
of the two.

Both sides run this working tree's benchmark scripts, so the measurement code is the same; only the packages
measured differ. BASE's packages (those ``pyproject.toml`` ships) are exported with ``git archive`` into
``out/bench-compare/base/`` and put first on the scripts' ``sys.path`` (``_report.LIBRARY_VARIABLE``); the tree's
are its own, uncommitted changes included. A script that calls what BASE lacks fails on BASE's side with that
error in its log; the other benchmarks go on, and the exit status is 1. Each side's runs are merged per name by
``compare.best_of`` (the best time or rate, the median ratio, and the runs' spread, by which ``compare.py`` marks
the moves beyond the noise). The export is deleted at the end, also on an interrupt; the runs' logs and JSON stay in
``out/bench-compare/`` (``base.json`` and ``tree.json``: the merged sides).

    python benchmarks/compare_commit.py BASE [--rounds 2] [--only skinning kernel] [--threshold 0.1]
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import signal
import subprocess
import sys
import tarfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import compare  # noqa: E402
import quick  # noqa: E402
from _report import PACKAGES, ROOT  # noqa: E402


def git(*args: str) -> str:
    return subprocess.run(["git", *args], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()


def export_library(commit: str, folder: Path) -> list[str]:
    """Write ``commit``'s packages (``PACKAGES``, those it has) into ``folder``; returns their names."""
    present = [name for name in PACKAGES if git("ls-tree", "--name-only", commit, name)]
    if not present:
        raise SystemExit(f"{commit} has none of the packages {', '.join(PACKAGES)}")
    archive = subprocess.run(["git", "archive", commit, *present], cwd=ROOT, capture_output=True, check=True).stdout
    with tarfile.open(fileobj=io.BytesIO(archive)) as tar:
        tar.extractall(folder, filter="data")
    return present


def _interrupted(signum, frame):
    raise KeyboardInterrupt  # SIGTERM as Ctrl-C: the export is deleted on the way out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("base", help="the commit to compare with (any git revision: main, 44f94fc~1, HEAD)")
    parser.add_argument("--rounds", type=int, default=2, help="runs of the quick set on each side (default 2: ABAB)")
    parser.add_argument("--only", nargs="+", choices=quick.QUICK, default=list(quick.QUICK), help="these only")
    parser.add_argument("--threshold", type=float, default=0.1, help="list moves larger than this (default 0.1)")
    parser.add_argument("--out", type=Path, default=ROOT / "out" / "bench-compare", help="logs and JSON go here")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error("--rounds must be at least 1")
    try:
        commit = git("rev-parse", "--verify", f"{args.base}^{{commit}}")
    except subprocess.CalledProcessError as error:
        parser.error(f"{args.base} is not a commit here: {error.stderr.strip()}")
    tree = git("rev-parse", "--short", "HEAD") + (" with changes" if git("status", "--porcelain") else "")
    library = args.out / "base"
    shutil.rmtree(library, ignore_errors=True)  # an earlier run's, if it was killed
    signal.signal(signal.SIGTERM, _interrupted)
    failed, start = set(), time.perf_counter()
    try:
        packages = export_library(commit, library)
        print(f"BASE {args.base} = {commit[:12]} ({', '.join(packages)} in {library}); tree: {tree}", flush=True)
        runs = {"base": [], "tree": []}
        for n in range(1, args.rounds + 1):
            for side, measured in (("base", library.absolute()), ("tree", None)):
                print(f"round {n}, {side}:", flush=True)
                result, side_failed = quick.run(args.only, args.out / f"{side}-{n}", measured)
                runs[side].append(result)
                failed |= {f"{name} ({side})" for name in side_failed}
    finally:
        shutil.rmtree(library, ignore_errors=True)
    merged = {}
    for side, results in runs.items():
        merged[side] = compare.best_of(results) | {"commit": commit if side == "base" else tree}
        (args.out / f"{side}.json").write_text(json.dumps(merged[side], indent=1))
    took = time.perf_counter() - start
    print(f"\n{args.rounds} rounds in {took:.0f} s; per side the best time or rate of its runs, the median ratio")
    print(compare.report(merged["base"], merged["tree"], f"BASE {args.base}", "tree", args.threshold), flush=True)
    if failed:
        print(f"failed: {', '.join(sorted(failed))} (logs in {args.out})", flush=True)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
