"""`focustrack bench mmcore` times the backend and bare MMCore calls on the demo devices and
writes its figures (no timing is asserted: the machine decides them)."""

from __future__ import annotations

import json
from pathlib import Path

from focustrack import cli


def test_bench_mmcore_writes_both_modes(tmp_path: Path, capsys) -> None:
    out = tmp_path / "mmcore.json"
    argv = ["bench", "mmcore", "--frames", "3", "--stacks", "2", "--json", str(out)]
    assert cli.main(argv) == 0
    figures = json.loads(out.read_text())
    assert (figures["frames"], figures["stacks"]) == (3, 2)
    assert figures["target_overhead_ms_per_plane"] == 2.0
    for mode in ("snapped", "sequenced"):  # the demo's focus stage sequences
        assert set(figures[mode]) == {
            "bare_ms_per_plane", "backend_ms_per_plane", "overhead_ms_per_plane"
        }  # fmt: skip
        assert figures[mode]["bare_ms_per_plane"] > 0
    printed = capsys.readouterr().out
    assert "| snapped |" in printed and "| sequenced |" in printed


def test_bench_mmcore_refuses_bad_settings(capsys) -> None:
    assert cli.main(["bench", "mmcore", "--frames", "0"]) == 2
    assert "at least 1" in capsys.readouterr().out
