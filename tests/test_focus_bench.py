"""`focustrack bench focus --quick`: runs end to end and writes the figures the issue names."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from focustrack.bench import focus
from focustrack.bench.focus_real import Reading, summarise, windows
from focustrack_core.domain import FocusFlag


def test_quick_bench_writes_every_figure_per_metric(tmp_path: Path, capsys) -> None:
    parser = argparse.ArgumentParser()
    focus.add_arguments(parser)
    out = tmp_path / "focus.json"
    args = parser.parse_args(["--quick", "--metrics", "normalised_variance", "--json", str(out)])
    assert focus.run(args) == 0
    figures = json.loads(out.read_text())
    assert figures["source"] == "instrument_sim"
    row = figures["metrics"]["normalised_variance"]
    for key in ("fps_2048_u16", "fps_1024_rgb", "copy_ratio", "mae_um", "p90_um", "zscore_std"):
        assert row[key] > 0, key
    assert row["empty_flat"] == 1.0  # every empty field is flagged, none measured
    assert set(row["by_field"]) == {f"{f} {s}px" for f in focus.SPECIMEN_FIELDS for s in (256, 128)}
    assert "accuracy on simulated stacks" in capsys.readouterr().out


def test_real_summary_counts_edges_coverage_and_silent_misses() -> None:
    """`bench focus --real`'s figures on hand-made readings (errors and sigma in steps)."""
    high, low = frozenset({FocusFlag.EDGE_HIGH}), frozenset({FocusFlag.EDGE_LOW})
    rows = [
        Reading(2, "5x1", 0.4, 0.1, frozenset(), 0),  # within 1, covered (0.4 <= 0.2 + 0.5)
        Reading(2, "5x1", 1.5, 0.2, frozenset(), 0),  # within 2, not covered
        Reading(2, "5x1", 5.0, 0.5, frozenset(), 0),  # silent: far, no flag, outside 2 sigma
        Reading(2, "5x1", 5.0, None, high, 1),  # label above, edge_high: right
        Reading(2, "5x1", -5.0, None, high, -1),  # label below, edge_high: wrong
        Reading(2, "5x1", -5.0, 0.3, frozenset({FocusFlag.MULTI_PEAK}), -1),  # warned
        Reading(2, "5x1", None, None, low, -1),  # right
    ]
    figures = summarise(rows)
    assert figures["within_1_step"] == 1 / 3 and figures["within_2_steps"] == 2 / 3
    assert figures["coverage_2sigma"] == 1 / 3
    assert figures["edge_right"] == 2 / 4 and figures["edge_wrong"] == 1 / 4
    assert figures["silent_miss"] == 1 / 7
    shapes = {w.kind for w in windows(100, 50)}
    assert "full" in shapes and {"5x1", "11x3"} <= shapes
