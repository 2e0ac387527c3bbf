"""`focustrack bench phase` on a tiny setting: its table, JSON keys and figure."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import pytest

from focustrack.bench.phase import run


def test_the_bench_writes_its_table_json_and_figure(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "phase.json"
    args = argparse.Namespace(json=out, sweep=False, seed=1, size_px=16, repeats=1)
    assert run(args) == 0
    result = json.loads(out.read_text())
    assert set(result) == {"data_set_1", "sweep", "figure", "paper"}
    methods = [row["method"] for row in result["data_set_1"]]
    assert methods[0] == "sparse ACEKF (ours)" and len(methods) == 4
    row = result["data_set_1"][0]
    assert set(row) == {"method", "gamma", "planes", "phase_rmse_rad", "intensity_rmse", "time_s"}
    assert row["planes"] == 100 and row["time_s"] > 0 and row["phase_rmse_rad"] > 0
    assert result["paper"]["sparse ACEKF (paper)"]["phase_rmse_rad"] == 0.0143
    assert (tmp_path / result["figure"]).stat().st_size > 1000
    assert "sparse ACEKF (paper)" in capsys.readouterr().out
