"""Viewer pages in headless Chromium, for the browser tests (tests/viewer) and benchmarks/bench_viewer.py: Debian's
``chromium`` and ``chromium-driver`` driven by selenium (a dev dependency), never anything downloaded.

Headless Chromium has no GPU here: WebGL runs on SwiftShader, the software renderer. ``--use-angle=swiftshader
--enable-unsafe-swiftshader`` ask for it explicitly: Debian's Chromium 150 still falls back to it without them,
but Chromium is phasing out that automatic fallback for WebGL, after which a page without them would get no
WebGL context (and report it)."""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
)
# what a test or a script reads of window.jaxcgaViewer (its functions left out)
STATE = (
    "ready errors meshes clips clip duration time frame interpolation playing speed loop sequenceFps fps rendered "
    "frameChanges updateMs decodeMs loadMs joint renderer antialias labels"
).split()


def chromium_missing() -> str | None:
    """Why headless Chromium cannot run here (the binary, the driver or selenium missing), or None."""
    for name in ("chromium", "chromedriver"):
        if shutil.which(name) is None:
            return f"no {name} on PATH (Debian: apt-get install chromium chromium-driver)"
    try:
        import selenium  # noqa: F401
    except ImportError:
        return "selenium is not installed (pip install -e '.[dev]')"
    return None


class Browser:
    """One headless Chromium (``width`` x ``height`` window) with a private profile folder, removed by ``quit``."""

    def __init__(self, width: int = 1000, height: int = 700):
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service

        missing = chromium_missing()
        if missing:
            raise RuntimeError(f"headless Chromium: {missing}")
        self._profile = tempfile.mkdtemp(prefix="jaxcga-chromium-")
        options = webdriver.ChromeOptions()
        options.binary_location = str(shutil.which("chromium"))
        for flag in (*FLAGS, f"--window-size={width},{height}", f"--user-data-dir={self._profile}"):
            options.add_argument(flag)
        # the Debian driver, given by path: selenium-manager never looks for (or downloads) one
        self.driver = webdriver.Chrome(service=Service(str(shutil.which("chromedriver"))), options=options)

    def open(self, path: str | Path, timeout: float = 120.0) -> dict:
        """Load the page at ``path`` (file://) and wait until it is ready or reports an error; returns its state."""
        self.driver.get(Path(path).resolve().as_uri())
        end = time.monotonic() + timeout
        while True:
            state = self.state()
            if state["ready"] or state["errors"] or time.monotonic() > end:
                return state
            time.sleep(0.05)

    def state(self) -> dict:
        """``window.jaxcgaViewer``'s fields (``STATE``); errors only when the page did not run at all."""
        text = self.driver.execute_script(
            "const v = window.jaxcgaViewer;"
            "if (!v) return JSON.stringify({ready: false, errors: ['no window.jaxcgaViewer']});"
            f"return JSON.stringify(Object.fromEntries({json.dumps(STATE)}.map((k) => [k, v[k]])));"
        )
        return json.loads(text)

    def call(self, script: str):
        """Run ``script`` with ``v`` bound to ``window.jaxcgaViewer``; returns its value (JSON-serialized)."""
        text = self.driver.execute_script(
            f"const v = window.jaxcgaViewer; return JSON.stringify((() => {{{script}}})());"
        )
        return None if text is None else json.loads(text)

    def positions(self, mesh: int, time_: float | None = None):
        """Input ``mesh``'s vertices as drawn, (n, 3), paused at ``time_`` (or at the current time)."""
        import numpy as np

        at = "" if time_ is None else f"v.pause(); v.setTime({float(time_)!r});"
        return np.asarray(self.call(f"{at} return v.vertexPositions({int(mesh)});"), np.float64).reshape(-1, 3)

    def screenshot(self):
        """The window as an (h, w, 3) uint8 array."""
        import io

        import numpy as np
        from PIL import Image

        png = self.driver.get_screenshot_as_png()
        return np.asarray(Image.open(io.BytesIO(png)).convert("RGB"))

    def quit(self) -> None:
        self.driver.quit()
        shutil.rmtree(self._profile, ignore_errors=True)
