"""`focustrack bench chaos`, small: a scan while the router and the focus service are killed
and restarted and a rogue peer publishes wrong results; nothing lost, nothing wrong taken.
Then the hostile REST requests, with 12 slides created one after another instead of the
bench's 2,000 (tests/test_hostile.py checks each request's status and the live-slide budget
with as many), and the bus attacks, with megabytes instead of gigabytes: no replayed or forged
result is taken, a frames request naming one frame 50 times gets it once, and the bench
exits 0."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow  # services in processes, killed and started again


@pytest.mark.timeout(600)  # four services started, two of them again, on a loaded machine
def test_a_small_chaos_run_loses_nothing_and_accepts_no_wrong_result(tmp_path: Path) -> None:
    out = tmp_path / "chaos.json"
    command = [
        sys.executable, "-m", "focustrack", "bench", "chaos", "--rows", "3", "--cols", "4",
        "--size", "96", "--scans", "1", "--seed", "1", "--faults", "2", "--gap-max-s", "3",
        "--down-max-s", "3", "--attack-sizes", "small", "--hostile-slides", "12",
        "--out", str(tmp_path / "work"), "--json", str(out),
    ]  # fmt: skip
    chaos = subprocess.run(command, capture_output=True, text=True, timeout=560)
    assert chaos.returncode == 0, chaos.stdout + chaos.stderr
    report = json.loads(out.read_text())
    attacks = report["memory_attacks"]
    assert report["replayed_results_accepted"] == 0
    assert report["forged_results_accepted"] == 0
    assert out.with_suffix(".png").stat().st_size > 0
    assert report["scans_completed"] == len(report["scans"]) >= 1  # scans go on while faults do
    assert len(report["faults"]) == 2
    assert report["measurements_lost"] == 0
    assert report["wrong_results_accepted"] == 0
    assert report["rogue_results_sent"] > 0 and report["focus_results_rejected"] > 0
    assert report["faults"][0]["service"] == "router"  # seed 1 kills the router first
    assert "chaos: killed router" in chaos.stdout
    assert set(report["peak_rss_mb"]) == {"router", "instrument", "focus", "estimator"}
    assert all(0 < mb < 1024 for mb in report["peak_rss_mb"].values())
    replay, forgery = report["replay"], report["forgery"]
    assert replay["results_recorded"] > 0 and replay["results_replayed"] >= 1
    assert replay["replayed_scan"]["completed"] and forgery["scan"]["completed"]
    assert forgery["stacks_forged"] > 0
    assert list(attacks) == ["big-frames", "incomplete-stacks", "repeated-frames-request"]
    for figures in attacks.values():
        assert set(figures["baseline_mb"]) == set(figures["peak_mb"]) == set(report["peak_rss_mb"])
    assert attacks["big-frames"]["sent"]["sent_bytes"] == 2 * (4 << 20)
    assert attacks["incomplete-stacks"]["sent"]["sent_bytes"] == 3 * (1 << 20)
    frames = attacks["repeated-frames-request"]["sent"]
    assert frames["replies"] == 1  # 50 copies of one index: the frame once
    assert frames["reply_bytes"] == 96 * 96 * 3 * 2  # RGB, 16 bits
    assert "replayed results taken:" in chaos.stdout and "under big-frames" in chaos.stdout
    hostile = report["hostile_requests"]  # the status of each, or why they were not fired
    if isinstance(hostile, dict):
        assert hostile and all(status < 500 for status in hostile.values()), hostile
    else:
        assert hostile.startswith("skipped: ")
