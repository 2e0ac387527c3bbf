"""`focustrack bench scale`: one in-process case and one served restart, on small grids."""

from __future__ import annotations

import pytest

from focustrack.bench.scale import case_in_process, case_rest


def test_an_in_process_case_reports_time_per_tile_map_and_memory() -> None:
    result = case_in_process("kf-2d", 6)
    assert result["tiles"] == 36
    assert 0 < result["tile_mean_ms"] <= result["tile_p99_ms"]
    assert result["final_map_s"] > 0
    assert result["peak_rss_mb"] >= result["rss_before_scan_mb"] > 0


@pytest.mark.slow
def test_a_served_case_restarts_after_kill_and_loses_nothing() -> None:
    result = case_rest("kf-2d", 6, unsnapshotted=3, every=10)
    assert result["lost_nothing"]
    assert result["replayed_at_first_start"] == 3
    assert set(result["map_s"]) == {"json", "csv", "npy", "png"}
