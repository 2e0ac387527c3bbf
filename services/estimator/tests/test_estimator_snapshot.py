"""Snapshots of strategy state: a restored strategy continues exactly as the original would."""

from __future__ import annotations

import dataclasses
import io
import json

import numpy as np
import pytest

from focustrack_core.domain import Purpose
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.replay import simulated_measurement
from focustrack_estimator.restored import check_restored
from focustrack_estimator.serpentine import SerpentineFilter
from focustrack_estimator.snapshot import SnapshotError, encode, restore
from focustrack_estimator.strategy import Strategy

ROWS, COLS = 6, 5


def _measured() -> np.ndarray:
    truth_um = generate_surfaces(SurfaceSpec(rows=ROWS, cols=COLS), 1, seed=3)[0]
    measured_um = truth_um + np.random.default_rng(3).normal(0.0, 1.5, truth_um.shape)
    measured_um[2, 3] += 9.0  # an edge peak: a retry is pending at some snapshots
    return measured_um


def _steps(strategy: Strategy, measured_um: np.ndarray, n: int) -> list[dict]:
    """Up to `n` acquisitions and their outcomes, as records."""
    records = []
    for _ in range(n):
        acquisition = strategy.next_acquisition()
        if acquisition is None:
            break
        outcome = strategy.record(
            acquisition,
            simulated_measurement(acquisition, measured_um[acquisition.row, acquisition.col]),
        )
        records.append({"a": dataclasses.asdict(acquisition), "o": dataclasses.asdict(outcome)})
    return records


def _maps(strategy: Strategy) -> dict[str, np.ndarray | None]:
    return dataclasses.asdict(strategy.focus_map())


@pytest.mark.parametrize("name", sorted(registry.STRATEGIES))
@pytest.mark.parametrize("at", [7, 15])  # 15: inside the retries of the edge peak
def test_a_restored_strategy_continues_as_the_original(name: str, at: int) -> None:
    settings = default_settings(ScanGrid(ROWS, COLS))
    measured_um = _measured()
    original = registry.create(name, settings)
    _steps(original, measured_um, at)
    original.next_acquisition()  # a pending acquisition is part of the state
    blob = encode(original)
    restored = registry.create(name, settings)
    restored.next_acquisition()  # as a freshly built slide does
    restore(restored, blob)
    assert _steps(restored, measured_um, 1000) == _steps(original, measured_um, 1000)
    for layer, value in _maps(original).items():
        np.testing.assert_array_equal(_maps(restored)[layer], value, err_msg=layer)


def test_enums_come_back_as_enums_not_their_values() -> None:
    """A pending acquisition's purpose (a StrEnum, so also a str) is restored as the enum."""
    settings = default_settings(ScanGrid(ROWS, COLS))
    original = registry.create("kf-2d", settings)
    _steps(original, _measured(), 3)
    pending = original.next_acquisition()
    restored = registry.create("kf-2d", settings)
    restore(restored, encode(original))
    assert pending is not None and restored.next_acquisition() == pending
    assert type(restored.next_acquisition().purpose) is Purpose  # type: ignore[union-attr]


def test_a_snapshot_of_another_strategy_is_refused() -> None:
    settings = default_settings(ScanGrid(ROWS, COLS))
    blob = encode(registry.create("kf-2d", settings))
    with pytest.raises(SnapshotError, match="not format"):
        restore(registry.create("kf-wiener0", settings), blob)
    with pytest.raises(SnapshotError, match="unreadable"):
        restore(registry.create("kf-2d", settings), b"not an archive")


def test_a_snapshot_names_no_class_outside_the_project() -> None:
    """A crafted tree naming another module's class is refused, not imported."""
    settings = default_settings(ScanGrid(ROWS, COLS))
    strategy = registry.create("kf-wiener0", settings)
    with np.load(io.BytesIO(encode(strategy)), allow_pickle=False) as archive:
        arrays = {key: archive[key] for key in archive.files}
    tree = json.loads(arrays["__tree__"].tobytes())
    tree["state"]["settings"]["dc"] = "subprocess:Popen"
    arrays["__tree__"] = np.frombuffer(json.dumps(tree).encode(), dtype=np.uint8)
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)
    with pytest.raises(SnapshotError, match="may not name 'subprocess:Popen'"):
        restore(registry.create("kf-wiener0", settings), buffer.getvalue())


def test_a_restore_keeps_equal_plain_values_and_stores_float_lists_as_arrays() -> None:
    """The strategy's own grid object survives (with its cached serpentine order), and the
    innovations (a list of floats) come back bit for bit from one array, not a JSON node each."""
    settings = default_settings(ScanGrid(ROWS, COLS))
    original = registry.create("kf-wiener0", settings)
    _steps(original, _measured(), 12)
    blob = encode(original)
    with np.load(io.BytesIO(blob), allow_pickle=False) as archive:
        tree = archive["__tree__"].tobytes().decode()
    assert '"fl"' in tree
    restored = registry.create("kf-wiener0", settings)
    grid = restored.grid
    restore(restored, blob)
    assert restored.grid is grid
    assert isinstance(restored, SerpentineFilter) and isinstance(original, SerpentineFilter)
    assert restored.innovations()[0].tolist() == original.innovations()[0].tolist()


@pytest.mark.parametrize("name", sorted(registry.STRATEGIES))
@pytest.mark.parametrize("at", [1, 7, 15, 1000])  # 1000: the scan is complete
def test_every_strategys_own_snapshot_passes_the_checks_of_a_restore(name: str, at: int) -> None:
    """A genuine snapshot is used (`restored.check_restored`), never discarded for a replay."""
    settings = default_settings(ScanGrid(ROWS, COLS))
    original = registry.create(name, settings)
    measured_um = _measured()
    outcomes = []
    for _ in range(at):
        acquisition = original.next_acquisition()
        if acquisition is None:
            break
        measurement = simulated_measurement(
            acquisition, measured_um[acquisition.row, acquisition.col]
        )
        outcomes.append(original.record(acquisition, measurement))
    if original.next_acquisition() is None:
        original.focus_map()  # as a finished slide is snapshotted: with its final map
    restored = registry.create(name, settings)
    restore(restored, encode(original))
    check_restored(restored, settings, len(outcomes), outcomes[-1])
