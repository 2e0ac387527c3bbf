"""`focustrack bench mmcore` times the backend and bare MMCore calls on the demo devices and
writes its figures (no timing is asserted: the machine decides them)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from focustrack import cli


def test_bench_mmcore_writes_both_modes(tmp_path: Path, capsys) -> None:
    out = tmp_path / "mmcore.json"
    argv = ["bench", "mmcore", "--frames", "3", "--stacks", "2", "--no-scan", "--json", str(out)]
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
    assert "scan" not in figures


@pytest.mark.slow
def test_a_slide_scans_alike_through_the_simulator_and_through_mmcore(
    tmp_path: Path, capsys
) -> None:
    """Every service scans one slide with --backend sim and with --backend mmcore-sim: the
    frames are the same, so are the focus found, the frames per tile and the accuracy."""
    out = tmp_path / "mmcore.json"
    argv = [
        "bench", "mmcore", "--frames", "3", "--stacks", "1", "--rows", "3", "--cols", "4",
        "--size", "128", "--out", str(tmp_path / "work"), "--json", str(out),
    ]  # fmt: skip
    assert cli.main(argv) == 0
    scan = json.loads(out.read_text())["scan"]
    sim, mmcore = scan["sim"], scan["mmcore-sim"]
    assert mmcore["images_per_tile"] == sim["images_per_tile"] >= 1
    assert mmcore["in_focus_fraction"] == sim["in_focus_fraction"] > 0
    assert mmcore["mae_um"] == pytest.approx(sim["mae_um"], abs=1e-6)
    assert "| mmcore-sim |" in capsys.readouterr().out


def test_bench_mmcore_refuses_bad_settings(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        cli.main(["bench", "mmcore", "--frames", "0"])
    assert stopped.value.code == 2
    assert "argument --frames: must be in [1, 10000], got 0" in capsys.readouterr().err
