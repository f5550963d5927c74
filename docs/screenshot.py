"""A PNG of a viewer page (``jaxcga view``, ``jaxcga physics``'s view.html, ...) paused at a time, in headless
Chromium (``_jaxcga_shared.viewer.browser``: Debian's chromium and chromium-driver, selenium), for the README's
pictures::

    python docs/screenshot.py out/physics/view.html --time 1.0 --out docs/physics_cut.png

Fails (exit 1, one line) when the page reports an error or is not ready in time."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from _jaxcga_shared.viewer.browser import Browser


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("page", type=Path, help="the viewer page (.html)")
    parser.add_argument("--time", type=float, default=0.0, help="the time shown, seconds (default 0)")
    parser.add_argument("--width", type=int, default=1000, help="window width, pixels (default 1000)")
    parser.add_argument("--height", type=int, default=700, help="window height, pixels (default 700)")
    parser.add_argument("--out", type=Path, required=True, help="the PNG to write")
    args = parser.parse_args(argv)
    if not args.page.is_file():
        parser.exit(1, f"screenshot: no such page {args.page}\n")
    browser = Browser(args.width, args.height)
    try:
        state = browser.open(args.page)
        if state["errors"] or not state["ready"]:
            parser.exit(1, f"screenshot: the page failed: {state['errors'] or 'not ready in time'}\n")
        shown = browser.call(f"v.pause(); return v.setTime({args.time!r});")
        args.out.parent.mkdir(parents=True, exist_ok=True)
        browser.driver.save_screenshot(str(args.out))
    finally:
        browser.quit()
    print(f"screenshot: {args.page} at {shown:.3f} s -> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
