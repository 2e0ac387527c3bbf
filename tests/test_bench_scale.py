"""`focustrack bench scale`: one in-process case and one served restart, on small grids."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from focustrack.bench.scale import case_in_process, case_rest, run


def test_an_in_process_case_reports_time_per_tile_map_and_memory() -> None:
    result = case_in_process("kf-2d", 6)
    assert result["tiles"] == 36
    assert 0 < result["tile_mean_ms"] <= result["tile_p99_ms"]
    assert 0 < result["tile_cpu_mean_ms"] <= result["tile_cpu_p99_ms"]
    assert result["final_map_s"] > 0 and result["final_map_cpu_s"] > 0
    assert result["peak_rss_mb"] >= result["rss_before_scan_mb"] > 0


@pytest.mark.slow
def test_a_served_case_restarts_after_kill_and_loses_nothing() -> None:
    result = case_rest("kf-2d", 6, unsnapshotted=3, every=10)
    assert result["lost_nothing"]
    assert result["replayed_at_first_start"] == 3
    assert set(result["map_s"]) == set(result["map_cpu_s"]) == {"json", "csv", "npy", "png"}
    assert result["up_after_kill_cpu_s"] > 0 and result["first_answer_after_kill_cpu_s"] >= 0


@pytest.mark.slow  # four child processes, each importing the estimator
def test_the_command_writes_a_table_json_and_a_plot(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "scale.json"
    args = argparse.Namespace(
        sizes=[4, 6], strategies=["kf-2d", "kf-wiener0"], rest=[], snapshot_every=200,
        unsnapshotted=150, jobs=2, json=out, plot=None,
    )  # fmt: skip
    assert run(args) == 0
    figures = json.loads(out.read_text())
    cases = [(r["strategy"], r["cols"]) for r in figures["in_process"]]
    assert cases == [("kf-2d", 4), ("kf-wiener0", 4), ("kf-2d", 6), ("kf-wiener0", 6)]
    assert all(r["case_cpu_s"] > 0 for r in figures["in_process"])
    assert figures["cpu_s"] == pytest.approx(sum(r["case_cpu_s"] for r in figures["in_process"]))
    assert out.with_suffix(".png").read_bytes().startswith(b"\x89PNG")
    table = capsys.readouterr().out
    assert "kf-wiener0" in table and "CPU p99" in table
