"""`focustrack demo` on a small virtual tissue slide: the instrument has a laser autofocus
that kf-2d-laser reads on every tile, the lean scan measures with pairs of frames, and the
table says how many tissue tiles each scan kept in focus, by the instrument's truth."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from focustrack.demo import DEFAULT_STRATEGIES, LASER, LEAN, STRATEGY_PARAMS
from focustrack_scheduler import outputs


def _acquisitions(scan_dir: Path) -> list[dict]:
    entries = [json.loads(line) for line in (scan_dir / outputs.LOG_FILE).read_text().splitlines()]
    return [entry for entry in entries if entry["event"] == "acquired"]


@pytest.mark.slow
@pytest.mark.timeout(600)
def test_the_demo_scans_a_tissue_slide_with_a_laser_and_scores_its_tissue(tmp_path: Path) -> None:
    assert LASER in DEFAULT_STRATEGIES and LEAN in DEFAULT_STRATEGIES
    assert STRATEGY_PARAMS[LEAN]["short_frames"] == STRATEGY_PARAMS[LASER]["short_frames"] == 2
    out_json = tmp_path / "demo.json"
    command = [
        sys.executable, "-m", "focustrack", "demo", "--tissue-slide", "--seed", "4",
        "--rows", "3", "--cols", "4", "--size", "128", "--strategies", LEAN, LASER,
        "--no-rescan", "--no-progress", "--no-screenshot", "--out", str(tmp_path / "demo"),
        "--json", str(out_json),
    ]  # fmt: skip
    demo = subprocess.run(command, capture_output=True, text=True, timeout=540)
    assert demo.returncode == 0, demo.stderr
    assert "virtual tissue slide" in demo.stdout and "tissue tiles (not empty glass)" in demo.stdout
    strategies = json.loads(out_json.read_text())["strategies"]
    assert list(strategies) == [LEAN, LASER]
    for figures in strategies.values():
        assert 0 < figures["tissue_tiles"] <= 12
        assert 0 <= figures["tissue_in_focus"] <= figures["tissue_tiles"]
    # the instrument has a laser: kf-2d-laser reads it once on every tile, without an image
    laser = _acquisitions(tmp_path / "demo" / LASER)
    readings = [entry for entry in laser if entry["purpose"] == "laser"]
    assert len(readings) == 12 and all(entry["n_frames"] == 0 for entry in readings)
    # its start is the reading plus the instrument's calibrated offset: no coarse search
    # over the start's unknown height (13-15 frames 4 um apart), a pair or a short stack
    assert max(entry["n_frames"] for entry in laser if entry["purpose"] == "scan") <= 5
    # both look first: each tile's first frame is a look (one frame), and on tissue the look
    # is the lower frame of the lean scan's pair, read by the focus service with the
    # slide's curve (three frames only where a coarse search's peak centres them)
    assert STRATEGY_PARAMS[LEAN]["look_first"] and STRATEGY_PARAMS[LASER]["look_first"]
    per_tile: dict[tuple[int, int], list[int]] = {}
    for entry in _acquisitions(tmp_path / "demo" / LEAN):
        if entry["purpose"] == "scan":
            per_tile.setdefault((entry["row"], entry["col"]), []).append(entry["n_frames"])
    assert all(frames[0] == 1 for frames in per_tile.values())
    assert [1, 1] in per_tile.values()
    frames = [n for tile_frames in per_tile.values() for n in tile_frames]
    assert frames.count(3) <= sum(n >= 7 for n in frames)
