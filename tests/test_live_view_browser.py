"""The live web view in a real headless browser (Debian's chromium) during a real demo scan.

The demo scans one strategy and no second pass (`--no-rescan`): the page is checked during
that one scan, which is all the live view needs; the second pass is the demo's own
(tests/test_scan_e2e.py runs it).

Runs when /usr/bin/chromium is installed (`apt-get install -y chromium`; README, set-up)
and skips otherwise. The screenshot is left in out/live_view.png for a person to look at.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from focustrack.browser import CHROMIUM, open_page

SCREENSHOT = Path(__file__).resolve().parents[1] / "out" / "live_view.png"
ROWS, COLS = 8, 10
TILES = ROWS * COLS

pytestmark = [
    pytest.mark.slow,
    pytest.mark.skipif(
        not CHROMIUM.exists(),
        reason="no /usr/bin/chromium: `apt-get install -y chromium` to run the browser test",
    ),
]


def live_url(demo: subprocess.Popen[str], timeout_s: float = 180.0) -> str:
    """The address the demo prints, once its services are up."""
    assert demo.stdout is not None
    deadline_s = time.monotonic() + timeout_s
    for line in demo.stdout:
        if line.startswith("live view at "):
            return line.removeprefix("live view at ").strip()
        assert time.monotonic() < deadline_s, "the demo printed no live view address"
    raise AssertionError(f"the demo ended without a live view: {demo.wait()}")


def test_the_live_view_fills_in_during_a_demo_scan(tmp_path: Path) -> None:
    pytest.importorskip("playwright.sync_api")
    command = [sys.executable, "-m", "focustrack", "demo", "--rows", str(ROWS), "--cols", str(COLS)]
    command += ["--size", "128", "--strategies", "kf-2d", "--out", str(tmp_path / "demo")]
    command += ["--no-rescan", "--no-progress"]
    env = os.environ | {"PYTHONUNBUFFERED": "1"}
    demo = subprocess.Popen(command, stdout=subprocess.PIPE, text=True, env=env)
    try:
        url = live_url(demo)
        with open_page(url) as page:
            # The map fills in while the scan runs, without a reload.
            page.wait_for_function(
                "Number(document.body.dataset.tilesDone || 0) >= 1", timeout=120_000
            )
            first = int(page.evaluate("document.body.dataset.tilesDone"))
            page.wait_for_function(  # more tiles arrive (unless the page came in at the end)
                f"Number(document.body.dataset.tilesDone) > {first} || {first} === {TILES}",
                timeout=120_000,
            )
            assert "tiles done" in page.inner_text("#status")
            coloured = page.evaluate(
                """() => {
                  const c = document.getElementById("z");
                  const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
                  let n = 0;
                  for (let i = 0; i < d.length; i += 4) if (d[i] !== 225 || d[i + 1] !== 225) n++;
                  return n;
                }"""
            )
            assert coloured >= 1  # tiles with a focus estimate are painted, not grey
            assert page.inner_text("#z-low") and page.inner_text("#z-high")  # the colour scale
            box = page.locator("#z").bounding_box()
            assert box is not None
            page.mouse.move(box["x"] + 3, box["y"] + 3)  # tile (0, 0), the first scanned
            assert "tile (0, 0)" in page.inner_text("#tip") and "um" in page.inner_text("#tip")
            page.wait_for_function("document.getElementById('curve-tile').textContent !== ''")
            # the kept tiles' thumbnails, and the in-focus share by the simulator's truth
            page.wait_for_function("document.getElementById('thumbs').naturalWidth > 0")
            assert "in focus" in page.inner_text("#status") and "truth" in page.inner_text(
                "#status"
            )
            SCREENSHOT.parent.mkdir(exist_ok=True)
            page.screenshot(path=str(SCREENSHOT), full_page=True)
        assert demo.wait(timeout=300) == 0
    finally:
        if demo.poll() is None:
            demo.terminate()
            demo.wait(timeout=30)
    assert SCREENSHOT.stat().st_size > 0
    assert (tmp_path / "demo" / "kf-2d" / "mosaic.ome.zarr" / "zarr.json").exists()
    assert (tmp_path / "demo" / "live_view.png").stat().st_size > 0  # the demo's own
