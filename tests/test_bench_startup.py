"""`focustrack bench startup` starts every service for real and times its first answer."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from focustrack import cli


@pytest.mark.slow
def test_every_service_is_timed_to_its_first_answer(tmp_path: Path) -> None:
    out = tmp_path / "startup.json"
    assert cli.main(["bench", "startup", "--runs", "1", "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    services = {"floor (FastAPI)", "estimator", "focus", "instrument", "scan --help"}
    assert set(figures["services"]) == services
    for name, times in figures["services"].items():
        assert 0 < times["min_s"] <= times["median_s"] <= times["max_s"] < 60, name
    assert figures["compared"] == {}


def test_a_run_count_below_one_or_a_missing_python_is_refused(tmp_path: Path) -> None:
    with pytest.raises(SystemExit) as stopped:
        cli.main(["bench", "startup", "--runs", "0"])
    assert stopped.value.code == 2
    missing = str(tmp_path / "python")
    assert cli.main(["bench", "startup", "--runs", "1", "--compare", missing]) == 2
