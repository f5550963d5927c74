"""Viewer benchmark: a large mesh sequence (a grid of 100k vertices under a travelling wave, 200 frames) written by
``deform.view`` as one page (int16 positions in base64 blocks), loaded in headless Chromium (SwiftShader: software
WebGL, no GPU) and played for a few seconds.

Figures: the page's size, the seconds from opening the page to its first frame drawn (``loadMs``), the frames
rendered per second while playing (the page's own count, read with the sequence's frame advancing) and while
paused (drawing only: what the renderer allows), and the milliseconds of one time step on the page's thread (the
positions decoded and interpolated, ``updateMs``), and the seconds the page takes to read its data (``decodeMs``:
the config parsed, the blocks decoded, the geometries built; the rest of the load is parsing the HTML and the
first frames drawn). The baseline is the naive format the issue rules out, the same
frames as per-frame JSON arrays of numbers, drawn by the same page: at the full size its page (about 1.2 GB)
passes Chromium's limit on one string, so both formats are also loaded at a tenth of the frames, which gives the
ratios ``load_vs_json`` (JSON load time / ours), ``decode_vs_json`` (the same for reading the data) and
``megabytes_vs_json`` (JSON page size / ours) and the JSON
page's frame rate.

    python benchmarks/bench_viewer.py [--vertices 100000] [--frames 200] [--seconds 5] [--quick] [--json PATH]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
from _report import RATIO_UNIT, add_json_argument, print_device, write_json  # noqa: E402

from _jaxcga_shared.viewer import page  # noqa: E402
from _jaxcga_shared.viewer._inputs import read_arrays  # noqa: E402
from _jaxcga_shared.viewer.browser import Browser  # noqa: E402


def wave(vertices: int, frames: int):
    """A square grid of about ``vertices`` vertices in z = 0 and ``frames`` frames of a wave travelling along x."""
    side = int(round(np.sqrt(vertices)))
    x, y = np.meshgrid(np.linspace(-1, 1, side), np.linspace(-1, 1, side), indexing="ij")
    index = np.arange(side * side).reshape(side, side)
    a, b, c, d = index[:-1, :-1].ravel(), index[1:, :-1].ravel(), index[1:, 1:].ravel(), index[:-1, 1:].ravel()
    F = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    phase = 2 * np.pi * np.arange(frames)[:, None] / frames
    z = 0.15 * np.sin(6 * x.ravel()[None] - phase) * np.cos(2 * y.ravel()[None])
    V = np.broadcast_to(np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1), (frames, side * side, 3)).copy()
    V[..., 2] = z
    return V, F


def measure(browser: Browser, path: Path, seconds: float) -> dict:
    """Open the page, play it for ``seconds``, and read the frame rate while it plays. The load time is the page's
    own (navigation start to ready, ``loadMs``): the driver's replies wait for the page's thread between frames
    and would add seconds at a few frames per second."""
    state = browser.open(path, timeout=600)
    load = state["loadMs"] / 1000
    if state["errors"] or not state["ready"]:
        raise RuntimeError(f"{path.name}: the page did not load: {state['errors'] or 'timed out'}")
    browser.call("v.setLoop(true); v.play(); return null;")
    time.sleep(1.0)  # past the first frames' uploads
    before, t0 = browser.state(), time.perf_counter()
    time.sleep(seconds)
    after = browser.state()
    elapsed = time.perf_counter() - t0
    if after["frameChanges"] - before["frameChanges"] < 2:
        raise RuntimeError(f"{path.name}: the sequence did not advance while playing")
    # paused, the page only draws: what drawing alone allows on this renderer
    browser.call("v.pause(); return null;")
    time.sleep(0.5)
    paused, t1 = browser.state(), time.perf_counter()
    time.sleep(seconds)
    drawn = (browser.state()["rendered"] - paused["rendered"]) / (time.perf_counter() - t1)
    return {
        "load": load,
        "fps": (after["rendered"] - before["rendered"]) / elapsed,
        "paused_fps": drawn,
        "update_ms": after["updateMs"],
        "decode": state["decodeMs"] / 1000,
        "page_fps": after["fps"],
        "frame_changes": (after["frameChanges"] - before["frameChanges"]) / elapsed,
        "megabytes": path.stat().st_size / 2**20,
        "renderer": f"{state['renderer']} ({'multisampled' if state['antialias'] else 'no multisampling'})",
    }


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--vertices", type=int, default=100_000)
    parser.add_argument("--frames", type=int, default=200)
    parser.add_argument("--seconds", type=float, default=5.0, help="seconds of playing per page (default 5)")
    parser.add_argument("--quick", action="store_true", help="10k vertices, 20 frames, 1 s (a smoke run)")
    parser.add_argument("--screenshot", type=Path, default=None, help="PNG of the large page while it plays")
    add_json_argument(parser)
    args = parser.parse_args()
    vertices, frames, seconds = (10_000, 20, 1.0) if args.quick else (args.vertices, args.frames, args.seconds)
    print_device("bench_viewer")
    size = f"{vertices // 1000}k_{frames}"
    small = f"{vertices // 1000}k_{max(frames // 10, 10)}"
    folder = Path(tempfile.mkdtemp(prefix="bench_viewer-"))
    browser = Browser(1000, 700)
    try:
        V, F = wave(vertices, frames)
        n = V.shape[1]
        print(f"{n} vertices, {len(F)} triangles, {frames} frames")
        results = {}
        for name, count, encoding in ((size, frames, "int16"), (small, max(frames // 10, 10), "int16"),
                                      (small, max(frames // 10, 10), "json")):  # fmt: skip
            path = folder / f"{encoding}_{name}.html"
            start = time.perf_counter()
            sequence = read_arrays((V[:count], F), "wave", "frames")
            path.write_text(page([sequence], fps=30.0, encoding=encoding).html)
            write = time.perf_counter() - start
            results[encoding, name] = measure(browser, path, seconds) | {"write": write}
            r = results[encoding, name]
            if len(results) == 1:
                print(f"WebGL renderer: {r['renderer']}")
            print(
                f"{encoding:5s} {name}: {r['megabytes']:8.1f} MB (written in {write:.1f} s), loaded in "
                f"{r['load']:.2f} s (data read in {r['decode']:.2f} s), {r['fps']:.1f} frames/s rendered while "
                f"playing ({r['frame_changes']:.1f} new sequence frames/s; a time step {r['update_ms']:.1f} ms), "
                f"{r['paused_fps']:.1f} frames/s paused"
            )
            if args.screenshot is not None and (encoding, name) == ("int16", size):
                args.screenshot.parent.mkdir(parents=True, exist_ok=True)
                browser.driver.save_screenshot(str(args.screenshot))
            path.unlink()
    finally:
        browser.quit()
    ours, ours_small, naive = results["int16", size], results["int16", small], results["json", small]
    figures = {
        f"viewer_fps_{size}": ours["fps"],
        f"viewer_fps_paused_{size}": ours["paused_fps"],
        f"update_ms_{size}": ours["update_ms"],
        "page_megabytes": ours["megabytes"],
        "load_seconds": ours["load"],
        f"load_seconds_{small}": ours_small["load"],
        f"json_load_seconds_{small}": naive["load"],
        "decode_seconds": ours["decode"],
        f"decode_seconds_{small}": ours_small["decode"],
        f"json_decode_seconds_{small}": naive["decode"],
        f"json_fps_{small}": naive["fps"],
    }
    ratios = {
        "load_vs_json": naive["load"] / ours_small["load"],
        "megabytes_vs_json": naive["megabytes"] / ours_small["megabytes"],
        "decode_vs_json": naive["decode"] / ours_small["decode"],
    }
    units = {name: "frames/s" for name in figures if "fps" in name}
    units |= {name: "s" for name in figures if "seconds" in name} | {"page_megabytes": "MB"}
    units[f"update_ms_{size}"] = "ms"
    units |= {name: RATIO_UNIT for name in ratios}
    units["megabytes_vs_json"] = "x (JSON page size / ours)"
    print(
        f"against per-frame JSON: loads {ratios['load_vs_json']:.1f}x faster, reads its data "
        f"{ratios['decode_vs_json']:.1f}x faster, {ratios['megabytes_vs_json']:.1f}x smaller"
    )
    write_json(args.json, {"figures": figures, "ratios": ratios, "units": units})


if __name__ == "__main__":
    main()
