"""The live view's HTTP endpoints during a real scan of a small virtual tissue slide: the
instrument, focus and estimator services in processes, the scan in this process with a
real live server, read over HTTP while it runs and once it is over."""

from __future__ import annotations

import io
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from matplotlib.image import imread

from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack
from focustrack_core.domain import kept_in_focus
from focustrack_scheduler.clients import InstrumentClient, truth_empty
from focustrack_scheduler.live import BY_TRUTH
from focustrack_scheduler.live_view import LiveServer
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.scan import ScanJob, run_scan
from focustrack_scheduler.settings import BEST_KALMAN, ScanOptions

pytestmark = pytest.mark.slow  # services in processes

ROWS = COLS = 4
SIZE = 128


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LocalStack]:
    instrument_args = [
        "--tissue-slide", "--overlap", "0.1", "--seed", "3", "--slides", "1",
        "--rows", str(ROWS), "--cols", str(COLS), "--width", str(SIZE), "--height", str(SIZE),
    ]  # fmt: skip
    with LocalStack(tmp_path_factory.mktemp("stack"), instrument_args) as running:
        yield running


def opaque_cells(png: bytes) -> np.ndarray:
    """Which tiles' cells of the thumbnails PNG hold an image, (rows, cols) bool."""
    rgba = imread(io.BytesIO(png))
    cell = rgba.shape[0] // ROWS
    alpha = rgba[..., 3].reshape(ROWS, cell, COLS, cell)
    return np.asarray(alpha.min(axis=(1, 3)) == 1.0)


def test_the_live_view_shows_thumbnails_and_the_in_focus_share_during_a_real_scan(
    http: httpx.Client, stack: LocalStack, tmp_path: Path
) -> None:
    assert stack.session is not None
    session = stack.session
    with LiveServer() as server:
        job = ScanJob(
            request=ScanOptions.defaults().request(INSTRUMENT, SLIDE, BEST_KALMAN),
            estimator_url=stack.estimator_url,
            out_dir=tmp_path,
            progress=False,
            label=BEST_KALMAN,
            live=server,
        )
        reports: list[dict[str, Any]] = []
        scanning = threading.Thread(target=lambda: reports.append(run_scan(session, job)))
        scanning.start()
        during: list[tuple[dict[str, Any], bytes]] = []  # (state, thumbnails) while it ran
        deadline_s = time.monotonic() + 180
        while scanning.is_alive() and time.monotonic() < deadline_s:
            state = http.get(server.url + "live/state")
            if state.status_code == 200 and 0 < state.json()["tiles_done"] < ROWS * COLS:
                png = http.get(server.url + "live/thumbnails.png")
                assert png.status_code == 200 and png.headers["content-type"] == "image/png"
                during.append((state.json(), png.content))
            time.sleep(0.05)
        scanning.join(60)
        assert reports, "the scan did not finish"
        assert http.get(server.url + "healthz").json() == {"status": "ok", "scan": BEST_KALMAN}
        final = http.get(server.url + "live/state").json()
        thumbnails = http.get(server.url + "live/thumbnails.png").content
    assert during, "no look at the scan while it ran"
    for state, png in during:  # each tile done by then has its thumbnail, in its cell
        done = np.zeros((ROWS, COLS), bool)
        for row, col, *_, is_done, _flags, _phase in state["tiles"]:
            done[row, col] = is_done
        assert (opaque_cells(png) >= done).all()
        share = state["in_focus"]
        assert share["by"] == BY_TRUTH and share["tissue_only"]
        assert 0 <= share["tiles"] <= share["judged"] <= state["tiles_done"]
    assert final["finished"] and final["tiles_done"] == ROWS * COLS
    assert opaque_cells(thumbnails).all()
    assert final["thumbnails_version"] >= ROWS * COLS
    # by the truth, the tissue tiles judged (empty glass left out), each on its kept frames
    instrument = InstrumentClient(session, INSTRUMENT)
    truth_um, glass = instrument.truth_um(SLIDE), truth_empty(instrument.slide_truth(SLIDE))
    assert glass is not None and 0 < glass.sum() < ROWS * COLS  # the slide has both
    record = ScanRecord(tmp_path)  # the scan's log, read back
    tally = record.tally
    record.close()
    in_focus = [
        kept_in_focus(tally.planes.get(tile, [z_um]), truth_um[tile], reports[0]["dof_um"])
        for tile, z_um in tally.kept.items()
        if not glass[tile]
    ]
    assert final["in_focus"] == {
        "tiles": sum(in_focus),
        "judged": ROWS * COLS - int(glass.sum()),
        "by": BY_TRUTH,
        "tissue_only": True,
    }
    rgba = imread(io.BytesIO(thumbnails))
    assert rgba[..., :3].std() > 0.01  # images of the slide, not blank cells
