"""The bus attacks of `focustrack bench chaos` (`focustrack.bench.bus_attacks`).

The forged stack and the count of values taken are checked alone; then each attack runs
on a small real stack (a router and the three services on loopback) and gives its
figures. How many replayed or forged results a scan takes depends on the defences in
the build: the tests check that the attacks ran and were counted, not the counts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from focustrack.bench import bus_attacks
from focustrack.bench.chaos import (
    MemoryWatch,
    forgery_attack,
    memory_attacks,
    replay_attack,
)
from focustrack.demo import LocalStack
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire.session import loopback_endpoint, open_session
from focustrack_focus.pipeline import FocusSettings, focus_stack
from focustrack_scheduler.settings import BEST_KALMAN


def test_a_forged_stack_is_sharpest_where_the_forger_put_its_plane() -> None:
    z_um = [-1.0, -0.5, 0.0, 0.5, 1.0]
    header = instrument_pb2.ZStackHeader(z_um=z_um, dtype="<u2", shape=[5, 96, 96, 3], bit_depth=12)
    frames = bus_attacks.forged_stack(header, sharp_index=1)
    assert frames.shape == (5, 96, 96, 3) and frames.dtype == np.dtype("<u2")
    assert frames.max() <= 4095  # within the header's bit depth
    result = focus_stack(frames, np.asarray(z_um), FocusSettings())
    assert result.best_z_um is not None  # a clean peak, measured as a genuine one would be
    assert abs(result.best_z_um - z_um[1]) < bus_attacks.FORGED_TOLERANCE_UM


def test_taken_counts_the_measurements_that_took_a_value_sent(tmp_path: Path) -> None:
    log = tmp_path / "scan_log.jsonl"
    entries = [
        {"event": "acquired", "row": 0, "col": 0, "sequence": 0},
        {"event": "measured", "row": 0, "col": 0, "sequence": 0, "z_um": 1.5},
        {"event": "measured", "row": 0, "col": 1, "sequence": 1, "z_um": 2.0},
        {"event": "measured", "row": 0, "col": 2, "sequence": 2, "z_um": None},
        {"event": "measured", "row": 0, "col": 3, "sequence": 3, "z_um": 3.0},
    ]
    log.write_text("".join(json.dumps(entry) + "\n" for entry in entries))
    sent = {(0, 0, 0): 1.5, (0, 1, 1): 2.1, (0, 2, 2): 0.0, (0, 3, 4): 3.0}
    assert bus_attacks.taken(log, sent, 1e-6) == 1  # (0, 3) is another sequence
    assert bus_attacks.taken(log, sent, 0.2) == 2


def test_a_replayed_result_is_found_by_its_scores_flat_ones_too(tmp_path: Path) -> None:
    log = tmp_path / "scan_log.jsonl"
    entries = [
        {"event": "measured", "row": 0, "col": 0, "sequence": 0, "curve_scores": [1.0, 2.5, 1.0]},
        {"event": "measured", "row": 0, "col": 1, "sequence": 1, "curve_scores": [0.1, 0.1, 0.1]},
        {"event": "measured", "row": 0, "col": 2, "sequence": 2, "curve_scores": [1.0, 2.0, 1.5]},
        {"event": "measured", "row": 0, "col": 3, "sequence": 3, "curve_scores": None},
    ]
    log.write_text("".join(json.dumps(entry) + "\n" for entry in entries))
    with open_session(listen=[loopback_endpoint()]) as session:
        replay = bus_attacks.ResultReplay(session, "slide-0")
        replay.replayed = {
            (0, 0, 0): [1.0, 2.5, 1.0],  # taken
            (0, 1, 1): [0.1, 0.1, 0.1],  # taken: a flat result, no best z
            (0, 2, 2): [1.0, 2.0, 1.4999],  # the new images' curve, not the replayed one
            (0, 3, 3): [1.0],
        }
        assert replay.accepted(log) == 2


#: Small enough for a test: what each attack sends, not the issue's gigabytes.
SMALL = bus_attacks.MemoryAttackSizes(
    big_frames=2,
    big_frame_bytes=64 << 20,
    big_frame_sent_bytes=4 << 20,
    incomplete_stacks=3,
    incomplete_frame_bytes=1 << 20,
    repeated_index=50,
)


@pytest.mark.slow  # four processes, four scans
@pytest.mark.timeout(600)
def test_each_attack_runs_on_a_small_stack_and_is_counted(tmp_path: Path) -> None:
    args = argparse.Namespace(
        rows=3, cols=3, strategy=BEST_KALMAN, out=tmp_path, replay_offset_um=8.0
    )
    instrument_args = ["--seed", "1", "--slides", "1", "--rows", "3", "--cols", "3"]
    instrument_args += ["--width", "96", "--height", "96"]
    with (
        LocalStack(tmp_path, instrument_args, router_process=True) as stack,
        open_session(connect=[stack.endpoint]) as attacker,
    ):
        memory = MemoryWatch(stack)
        replay = replay_attack(stack, args, memory)
        forgery = forgery_attack(stack, args, memory)
        attacks = memory_attacks(stack, attacker, SMALL)

    assert replay["results_recorded"] >= 9  # a result for every tile of the recorded scan
    assert replay["recorded_scan"]["completed"] and replay["replayed_scan"]["completed"]
    assert replay["replayed_scan"]["measurements_lost"] == 0
    # the first stack of the second scan is the first of the first: it is always replayed
    assert 1 <= replay["results_replayed"] <= replay["results_recorded"]
    assert 0 <= replay["replayed_results_accepted"] <= replay["results_replayed"]
    assert forgery["scan"]["completed"] and forgery["stacks_forged"] >= 9
    assert 0 <= forgery["forged_results_accepted"] <= forgery["stacks_forged"]

    assert list(attacks) == ["big-frames", "incomplete-stacks", "repeated-frames-request"]
    services = {"router", "instrument", "focus", "estimator"}
    for figures in attacks.values():
        assert set(figures["baseline_mb"]) == set(figures["peak_mb"]) == services
        assert all(mb > 0 for mb in figures["peak_mb"].values())
    assert attacks["big-frames"]["sent"]["sent_bytes"] == 2 * (4 << 20)
    assert attacks["incomplete-stacks"]["sent"]["sent_bytes"] == 3 * (1 << 20)
    frames = attacks["repeated-frames-request"]["sent"]
    assert 1 <= frames["replies"] <= 50  # each copy on main; one where they are deduplicated
    assert frames["reply_bytes"] == frames["replies"] * 96 * 96 * 3 * 2  # RGB, 16 bits
