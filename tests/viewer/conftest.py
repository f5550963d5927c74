"""The browser of the viewer's tests: one headless Chromium for the whole session (``_jaxcga_shared.viewer.browser``),
skipped with the reason where Chromium, its driver or selenium is not installed."""

from __future__ import annotations

import pytest

from _jaxcga_shared.viewer.browser import Browser, chromium_missing


@pytest.fixture(scope="session")
def browser():
    missing = chromium_missing()
    if missing:
        pytest.skip(f"browser tests skipped: {missing}")
    chromium = Browser()
    yield chromium
    chromium.quit()
