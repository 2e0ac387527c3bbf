"""The bus attacks of `focustrack bench chaos` (`focustrack.bench.bus_attacks`).

The forged stack and the counts of values taken are checked alone here; every attack
runs against the real services in `tests/test_bench_chaos.py`, which asserts that none
succeeds.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from focustrack.bench import bus_attacks
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire.session import loopback_endpoint, open_session
from focustrack_focus.pipeline import FocusSettings, focus_stack


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
