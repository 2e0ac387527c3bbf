"""Debian's chromium, headless, through Playwright: how the demo and tests look at the live view.

Playwright drives the system's /usr/bin/chromium (`apt-get install -y chromium`); its own
browser downloads are never used. Without chromium or playwright, `open_page` says why.
"""

from __future__ import annotations

import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

CHROMIUM = Path("/usr/bin/chromium")
#: The flags that work in this sandbox (with a fresh --user-data-dir per run).
CHROMIUM_FLAGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


class NoBrowserError(RuntimeError):
    """Chromium or Playwright is not installed."""


@contextmanager
def open_page(url: str, width_px: int = 1500, height_px: int = 900) -> Iterator[Any]:
    """A Playwright page showing `url` in headless chromium (closed after the block)."""
    if not CHROMIUM.exists():
        raise NoBrowserError(f"no {CHROMIUM}: `apt-get install -y chromium`")
    try:
        from playwright.sync_api import sync_playwright  # a test and demo extra, not a service's
    except ImportError as error:
        raise NoBrowserError("playwright is not installed (`pip install playwright`)") from error
    with tempfile.TemporaryDirectory() as profile, sync_playwright() as playwright:
        context = playwright.chromium.launch_persistent_context(
            profile,  # the fresh --user-data-dir
            executable_path=str(CHROMIUM),
            args=list(CHROMIUM_FLAGS),
            viewport={"width": width_px, "height": height_px},
        )
        try:
            page = context.new_page()
            page.goto(url)
            yield page
        finally:
            context.close()


def screenshot_live_view(url: str, path: Path) -> Path:
    """A PNG of the live view at `url` once its map has drawn (raises NoBrowserError)."""
    with open_page(url) as page:
        page.wait_for_function("document.body.dataset.tilesDone !== undefined", timeout=30_000)
        page.wait_for_timeout(500)  # the next animation frame paints the canvases
        path.parent.mkdir(parents=True, exist_ok=True)
        page.screenshot(path=str(path), full_page=True)
    return path
