"""A scan through every service on Micro-Manager's demo devices (`--backend mmcore`), whose
camera never changes with focus: it ends cleanly, every tile flagged `flat`, a bounded
number of stacks per tile, and a report and a summary that say so."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import mm_test_adapters
import pytest

from focustrack.local_stack import INSTRUMENT, SLIDE, LocalStack
from focustrack_scheduler import outputs
from focustrack_scheduler.scan import ScanJob, run_scan, summary_line
from focustrack_scheduler.settings import ScanOptions

pytestmark = pytest.mark.slow  # real services in processes: `make test-fast` skips them

ROWS = COLS = 3


def test_a_device_without_focus_ends_every_tile_flat_with_few_stacks(tmp_path: Path) -> None:
    adapters = mm_test_adapters.device_adapter_path()
    instrument_args = [
        "--backend", "mmcore", "--mm-config", f"{adapters}/MMConfig_demo.cfg",
        "--mm-adapter-path", adapters, "--mm-rows", str(ROWS), "--mm-cols", str(COLS),
        "--mm-z-min-um", "-100", "--mm-z-max-um", "100",
    ]  # fmt: skip
    # Micro-Manager knows no true focus: the instrument serves none
    with LocalStack(tmp_path, instrument_args, serve_truth=False) as stack:
        assert stack.session is not None
        job = ScanJob(
            request=ScanOptions.defaults().request(INSTRUMENT, SLIDE, "kf-2d-lean"),
            estimator_url=stack.estimator_url,
            out_dir=tmp_path / "scan",
            progress=False,
            trust=stack.trust,
        )
        report = run_scan(stack.session, job)
    n_tiles = ROWS * COLS
    assert report["tiles_imaged"] == n_tiles  # every tile still has its image
    assert report["tiles_without_focus"] == n_tiles
    assert report["tiles_flagged"] == {"flat": n_tiles}
    assert report["in_focus_fraction"] is None and report["mae_um"] is None  # no truth
    # bounded: the estimator widens the search once, then gives the tile up
    stacks_per_tile = Counter((entry["row"], entry["col"]) for entry in _acquisitions(tmp_path))
    assert len(stacks_per_tile) == n_tiles and max(stacks_per_tile.values()) <= 3
    assert f"WARNING: no focus found on {n_tiles} of {n_tiles} tiles (flags: flat {n_tiles})" in (
        summary_line(report)
    )


def _acquisitions(work_dir: Path) -> list[dict[str, Any]]:
    """The scan log's acquisitions (one per stack)."""
    lines = (work_dir / "scan" / outputs.LOG_FILE).read_text().splitlines()
    return [entry for entry in map(json.loads, lines) if entry["event"] == "acquired"]
