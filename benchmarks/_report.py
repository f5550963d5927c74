"""What every benchmark writes (DESIGN.md, "Tests and benchmarks"): ``{"figures", "ratios", "units"}``
as JSON with ``--json PATH``; a ratio is baseline time / ours (larger than 1: we are faster)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

RATIO_UNIT = "x (baseline time / ours)"


def add_json_argument(parser: argparse.ArgumentParser):
    parser.add_argument("--json", type=Path, default=None, help="write figures, ratios and units here")


def write_json(path: Path | None, result: dict):
    """Write ``result`` to ``path`` (parents created); nothing when ``path`` is None."""
    if path is None:
        return
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(result, indent=1))
