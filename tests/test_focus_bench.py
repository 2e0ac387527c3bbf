"""`focustrack bench focus --quick`: runs end to end and writes the figures the issue names."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from focustrack.bench import focus


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
