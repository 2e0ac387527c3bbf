"""`focustrack bench transport` runs both paths between two processes and writes its figures."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from focustrack import cli


@pytest.mark.slow
def test_bench_transport_measures_tcp_and_shared_memory(tmp_path: Path, capsys) -> None:
    out = tmp_path / "transport.json"
    argv = ["bench", "transport", "--size", "128", "--frames", "5", "--stacks", "2"]
    assert cli.main([*argv, "--json", str(out)]) == 0
    figures = json.loads(out.read_text())
    assert figures["stack_mb"] == pytest.approx(5 * 128 * 128 * 2 / 1e6)
    assert figures["memcpy_gb_per_s"] > 0
    for path in ("tcp", "shm"):
        measured = figures[path]
        assert measured["gb_per_s"] > 0 and measured["frames_per_s"] > 0
        assert measured["memcpy_ratio"] == pytest.approx(
            measured["gb_per_s"] / figures["memcpy_gb_per_s"]
        )
        assert 0 < measured["focus_latency_ms"] < 5000
    assert set(figures["ceilings"]) == {"zenoh_tcp", "socket_tcp", "two_copies"}
    for ceiling in figures["ceilings"].values():
        assert ceiling["gb_per_s"] > 0
        assert ceiling["memcpy_ratio"] == pytest.approx(
            ceiling["gb_per_s"] / figures["memcpy_gb_per_s"]
        )
    assert set(figures["targets"]) == {
        "tcp_gb_per_s", "tcp_memcpy_ratio", "shm_memcpy_ratio", "focus_latency"
    }  # fmt: skip
    printed = capsys.readouterr().out
    assert "| shm |" in printed and "| socket_tcp |" in printed
    assert out.with_suffix(".png").stat().st_size > 0


def test_bench_transport_refuses_bad_sizes(capsys) -> None:
    with pytest.raises(SystemExit) as stopped:
        cli.main(["bench", "transport", "--frames", "2"])
    assert stopped.value.code == 2
    assert "argument --frames: must be in [3, 10000], got 2" in capsys.readouterr().err
