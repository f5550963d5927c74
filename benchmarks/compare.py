"""Compare two benchmark JSON files (``make bench-compare``'s, or two runs of any benchmark's ``--json``): every
figure and ratio that moved by more than the threshold (default 10%), the worse first, then the better, then those
whose unit does not say which way is better (counts, differences); the names on one side only listed apart.

Worse is read from the unit (``direction``): a time or a memory size that grew, a ratio (``_report.RATIO_UNIT``,
or any name under "ratios": larger than 1 means we are faster) or a rate (``points/s``, ``frames/s``) that fell.
Within each group the largest move comes first (|log(new / old)|). Where both files merge several runs
(``best_of``: make bench-compare's), the moves that every run of one side makes against every run of the other
(their "spread" apart) are marked ``*`` and come first in their group: the others are within the machine's noise.
The exit status is 0 whatever moved.

    python benchmarks/compare.py OLD.json NEW.json [--threshold 0.1]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _report import RATIO_UNIT  # noqa: E402

SECTIONS = ("figures", "ratios")
LOWER_IS_BETTER = {"ns", "us", "ms", "s", "min", "h", "B", "KB", "KiB", "MB", "MiB", "GB", "GiB"}


def direction(section: str, unit: str | None) -> int:
    """1 where larger is better (ratios, rates), -1 where smaller is (times, memory), 0 where the unit does not say.
    A unit's first word decides: ``"s (slowest frame while cutting)"`` is a time."""
    if section == "ratios" or unit == RATIO_UNIT:
        return 1
    head = (unit or "").split(" ", 1)[0]
    if head.endswith("/s"):
        return 1
    return -1 if head in LOWER_IS_BETTER else 0


def entries(result: dict) -> dict[str, tuple[str, float, str | None]]:
    """name -> (section, value, unit) over the figures and ratios of one benchmark JSON."""
    units = result.get("units", {})
    return {name: (section, value, units.get(name)) for section in SECTIONS for name, value in result[section].items()}


def best_of(results: list[dict]) -> dict:
    """One result from several runs of the same benchmarks: per name the best value of a time or a rate (machine
    noise only slows a run down), the median of a ratio (the noise falls on both sides of its fraction) and of a
    value without a direction; of the finite values where there are any. "spread": name -> [smallest, largest] over
    the runs. Names missing from some runs are kept from the others; the other keys (platform, device, ...) are the
    first run's."""
    merged = {key: value for key, value in results[0].items() if key not in (*SECTIONS, "units")}
    merged |= {key: {} for key in (*SECTIONS, "units", "spread")}
    values: dict[str, list[float]] = {}
    for result in results:
        for name, (section, value, unit) in entries(result).items():
            values.setdefault(name, []).append(value)
            merged[section][name] = value
            if unit is not None:
                merged["units"][name] = unit
    for section in SECTIONS:
        for name in merged[section]:
            unit = merged["units"].get(name)
            sign = 0 if section == "ratios" or unit == RATIO_UNIT else direction(section, unit)
            finite = [v for v in values[name] if math.isfinite(v)] or values[name]
            merged[section][name] = {1: max, -1: min}.get(sign, statistics.median)(finite)
            merged["spread"][name] = [min(finite), max(finite)]
    return merged


class Move:
    """One name on both sides: its values, its change (new / old - 1), its size either way (|log(new / old)|: 10%
    up and its inverse, 9.1% down, weigh alike) and whether it is worse."""

    def __init__(self, name: str, section: str, old: float, new: float, unit: str | None):
        self.name, self.old, self.new, self.unit = name, old, new, unit
        finite = math.isfinite(old) and math.isfinite(new)
        self.sign = direction(section, unit) if finite else 0  # NaN or infinity: no way is better
        self.change = new / old - 1 if old != 0 else math.copysign(math.inf, new)
        self.size = abs(math.log(new / old)) if finite and old != 0 and new / old > 0 else math.inf
        self.worse = self.sign * self.change < 0
        self.apart = False  # every run of one side beyond every run of the other (``compare``)

    def line(self, width: int) -> str:
        unit = f"  {self.unit}" if self.unit else ""
        mark = "*" if self.apart else " "
        return f"{mark} {self.name:{width}s} {self.old:11.4g} -> {self.new:<11.4g} {100 * self.change:+8.1f}%{unit}"


def compare(old: dict, new: dict, threshold: float = 0.1) -> dict:
    """The names that moved by more than ``threshold`` (|new / old - 1|), as ``Move``s grouped "worse", "better" and
    "unknown" (no direction), each group those whose runs lie apart first, then the largest move first; "only_old"
    and "only_new": (name, value) on one side only; "common": how many names both have."""
    a, b = entries(old), entries(new)
    spread_a, spread_b = old.get("spread", {}), new.get("spread", {})
    moves = []
    for name in a.keys() & b.keys():
        (section, before, unit), (_, after, new_unit) = a[name], b[name]
        if before == after or (math.isnan(before) and math.isnan(after)):
            continue
        move = Move(name, section, before, after, new_unit or unit)
        if name in spread_a and name in spread_b:
            (low_a, high_a), (low_b, high_b) = spread_a[name], spread_b[name]
            move.apart = high_a < low_b or high_b < low_a
        if not abs(move.change) <= threshold:  # NaN on one side counts as moved
            moves.append(move)
    moves.sort(key=lambda m: (not m.apart, -m.size, m.name))
    return {
        "worse": [m for m in moves if m.sign and m.worse],
        "better": [m for m in moves if m.sign and not m.worse],
        "unknown": [m for m in moves if not m.sign],
        "only_old": sorted((name, a[name][1]) for name in a.keys() - b.keys()),
        "only_new": sorted((name, b[name][1]) for name in b.keys() - a.keys()),
        "common": len(a.keys() & b.keys()),
    }


def report(old: dict, new: dict, old_name: str, new_name: str, threshold: float = 0.1) -> str:
    """The comparison as text: a summary line, notes where the runs differ in kind, then one name a line."""
    found = compare(old, new, threshold)
    moved = [*found["worse"], *found["better"], *found["unknown"]]
    names = [m.name for m in moved] + [name for name, _ in found["only_old"] + found["only_new"]]
    width = max(map(len, names), default=0)
    lines = [
        f"{old_name} -> {new_name}: {found['common']} figures and ratios on both sides, {len(moved)} moved by more "
        f"than {100 * threshold:g}%"
    ]
    if old.get("spread") and new.get("spread"):
        lines.append("marked *: every run of one side beyond every run of the other; the rest within the runs' noise")
    for key in ("platform", "device"):
        if old.get(key) != new.get(key):
            lines.append(f"note: the {key} differs: {old.get(key)} -> {new.get(key)}")
    for bench, run in sorted(new.get("benchmarks", {}).items()):
        before = old.get("benchmarks", {}).get(bench)
        if before is not None and before.get("arguments") != run.get("arguments"):
            lines.append(f"note: {bench} ran with other arguments: {before.get('arguments')} -> {run.get('arguments')}")
    for key, title in (
        ("worse", "worse (a time or memory up, a ratio or rate down)"),
        ("better", "better"),
        ("unknown", "moved, the unit does not say which way is better"),
    ):
        if found[key]:
            lines.append(f"{title}: {len(found[key])}")
            lines.extend(move.line(width) for move in found[key])
    for key, name in (("only_old", old_name), ("only_new", new_name)):
        if found[key]:
            lines.append(f"only in {name}: {len(found[key])}")
            lines.extend(f"  {n:{width}s} {value:11.4g}" for n, value in found[key])
    return "\n".join(lines)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("old", type=Path, help="the earlier run's JSON")
    parser.add_argument("new", type=Path, help="the later run's JSON")
    parser.add_argument("--threshold", type=float, default=0.1, help="list moves larger than this (default 0.1: 10%%)")
    args = parser.parse_args(argv)
    if args.threshold < 0:
        parser.error("--threshold must not be negative")
    old, new = (json.loads(path.read_text()) for path in (args.old, args.new))
    print(report(old, new, str(args.old), str(args.new), args.threshold))
    return 0


if __name__ == "__main__":
    sys.exit(main())
