"""The time state of the Kalman strategies (drift and its settling rate) and revisits."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import Purpose
from focustrack_core.drift import ThermalDrift
from focustrack_core.geometry import ScanGrid, Tile
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import add_measurement_noise, family_spec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.replay import replay, score, simulated_measurement
from focustrack_estimator.row_model import N_PLANE
from focustrack_estimator.serpentine import SerpentineFilter
from focustrack_estimator.snapshot import encode, restore
from focustrack_estimator.spatial import RowBankFilter
from focustrack_estimator.strategy import Strategy
from focustrack_estimator.time_state import N_DRIFT, DriftModel, ScanClock, TimeStateParams

DOF_UM = 0.89
NOISE_UM = 0.1
TIME = {"drift_walk_um2_per_s": 0.0015, "drift_rate_sigma_um_per_s": 0.02}


def _maps(size: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    truth = generate_surfaces(family_spec("standard", size, size), 1, seed)[0]
    return truth, add_measurement_noise(truth[None], NOISE_UM, seed)[0]


def test_a_decaying_rate_integrates_to_an_exponential_settling() -> None:
    model = DriftModel(0.0, 0.01, 200.0)
    x = np.array([0.0, 0.01])  # 0.01 um/s at the start: 2 um once settled
    F, _ = model.transition(1.0)
    trajectory = []
    for _ in range(600):
        x = F @ x
        trajectory.append(x[0])
    expected = 2.0 * -np.expm1(-np.arange(1, 601) / 200.0)
    np.testing.assert_allclose(trajectory, expected, rtol=1e-9)
    # over 10 s at once, the same as ten steps of 1 s (the exact discretisation)
    np.testing.assert_allclose(np.linalg.matrix_power(F, 10), model.transition(10.0)[0])


def test_process_noise_is_positive_semidefinite_and_grows_with_time() -> None:
    model = DriftModel(0.0015, 0.01, 200.0, rate_q_um2_per_s3=1e-6)
    for dt_s in (0.01, 1.0, 100.0):
        assert np.linalg.eigvalsh(model.transition(dt_s)[1]).min() >= -1e-15
    assert model.transition(10.0)[1][0, 0] > model.transition(1.0)[1][0, 0]


def test_the_time_state_is_off_by_default_and_adds_two_states_when_on() -> None:
    assert DriftModel.of(TimeStateParams()) is None
    # Each of the three alone moves the drift: a rate walk alone was once ignored.
    for moves in ("drift_walk_um2_per_s", "drift_rate_sigma_um_per_s", "drift_rate_q_um2_per_s3"):
        assert DriftModel.of(TimeStateParams(**{moves: 1e-4})) is not None
    settings = default_settings(ScanGrid(4, 5))
    off = registry.create("kf-2d-lean", settings)
    on = registry.create("kf-2d-lean", settings, TIME)
    assert isinstance(off, RowBankFilter) and isinstance(on, RowBankFilter)
    assert off.x.shape[1] == N_PLANE + 2 * 5
    assert on.x.shape[1] == N_PLANE + 2 * 5 + N_DRIFT
    assert off.drift is None and on.drift == DriftModel(0.0015, 0.02, 200.0)


def test_the_scan_clock_counts_moves_and_frames() -> None:
    grid, clock = ScanGrid(2, 2), ScanClock()
    clock.advance(grid, Tile(0, 0), 3)
    assert clock.clock_s == pytest.approx(clock.timing.stack_s(3))
    arrival_s = clock.arrival_s(grid, Tile(0, 1))
    assert arrival_s == pytest.approx(clock.clock_s + clock.timing.move_s(grid.pitch_um))


@pytest.mark.parametrize("name", ["kf-2d-lean", "kf-2d"])
def test_the_time_state_tracks_thermal_drift(name: str) -> None:
    size = 16
    truth, measured = _maps(size, 4)
    drift = ThermalDrift(settle_um=2.0, settle_tau_s=30.0, walk_um_per_sqrt_min=0.3, seed=4)
    settings = default_settings(ScanGrid(size, size), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)
    strategy = registry.create(name, settings, TIME)
    assert isinstance(strategy, RowBankFilter)
    run = replay(strategy, truth, measured, drift=drift)
    true_um = (run.truth_um - truth).ravel()
    estimate_um = strategy.tile_drift_um.ravel()
    assert np.corrcoef(true_um, estimate_um)[0, 1] > 0.9
    # the drift moved by ~2 um; the estimate ends within half a um (the start is the
    # surface's offset: what the first rows drifted is partly taken as the surface)
    assert abs(strategy.drift_um()[0] - true_um[np.argmax(np.abs(true_um))]) < 1.0
    assert score([run], DOF_UM).in_focus_fraction >= 0.99


def test_a_quiet_time_state_leaves_a_still_slide_as_it_was() -> None:
    size = 12
    truth, measured = _maps(size, 5)
    settings = default_settings(ScanGrid(size, size), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)
    off = score([replay(registry.create("kf-2d-lean", settings), truth, measured)], DOF_UM)
    on = score([replay(registry.create("kf-2d-lean", settings, TIME), truth, measured)], DOF_UM)
    assert on.in_focus_fraction >= off.in_focus_fraction - 0.01
    assert on.images_per_tile == pytest.approx(off.images_per_tile, rel=0.1)


@pytest.mark.parametrize("name", ["kf-wiener0", "kf-wiener1", "kf-gm1"])
def test_one_dimensional_filters_carry_the_time_state(name: str) -> None:
    size = 8
    truth, measured = _maps(size, 6)
    settings = default_settings(ScanGrid(size, size), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)
    drift = ThermalDrift(settle_um=2.0, settle_tau_s=20.0, seed=6)
    run = replay(registry.create(name, settings, TIME), truth, measured, drift=drift)
    fm = run.focus_map
    assert np.isfinite(fm.smoothed_um).all()
    # the smoother's last tile is the filter's last posterior (RTS)
    last = settings.grid.serpentine[-1]
    assert fm.smoothed_um[last.row, last.col] == pytest.approx(fm.posterior_um[last.row, last.col])
    assert np.mean(np.abs(fm.posterior_um - run.truth_um)) < 0.2


def test_revisits_measure_a_tile_of_the_row_again_and_only_where_asked() -> None:
    size = 12
    truth, measured = _maps(size, 7)
    settings = default_settings(ScanGrid(size, size), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)
    drift = ThermalDrift(settle_um=3.0, settle_tau_s=20.0, walk_um_per_sqrt_min=1.0, seed=7)
    params = {**TIME, "drift_walk_um2_per_s": 0.02, "revisit_drift_share": 0.2}
    strategy = registry.create("kf-2d-lean", settings, params)
    imaged: set[tuple[int, int]] = set()
    n_revisits = 0
    while (acquisition := strategy.next_acquisition()) is not None:
        tile = (acquisition.row, acquisition.col)
        if acquisition.purpose is Purpose.REVISIT:
            n_revisits += 1
            assert tile in imaged  # a tile measured before
            assert acquisition.z.n_frames == 3
        else:
            imaged.add(tile)
        t_s = strategy.clock.arrival_s(strategy.grid, Tile(*tile))
        measurement = simulated_measurement(acquisition, measured[tile] + drift.at(t_s))
        strategy.record(acquisition, measurement)
    assert n_revisits > 0
    assert len(imaged) == size * size
    quiet = registry.create("kf-2d-lean", settings, {**params, "revisit_drift_share": 0.0})
    run = replay(quiet, truth, measured, drift=drift)
    assert run.n_revisits == 0


@pytest.mark.parametrize(
    ("name", "params"),
    [
        ("kf-2d-lean", {**TIME, "revisit_drift_share": 0.2, "drift_walk_um2_per_s": 0.05}),
        ("kf-wiener1", TIME),
        ("kf-2d-laser", {}),
    ],
)
def test_a_snapshot_holds_the_clock_and_the_drift(name: str, params: dict) -> None:
    size = 8
    _, measured = _maps(size, 11)
    settings = default_settings(ScanGrid(size, size), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)

    def steps(strategy: Strategy, n: int) -> list[tuple]:
        done = []
        for _ in range(n):
            acquisition = strategy.next_acquisition()
            if acquisition is None:
                break
            z_um = measured[acquisition.row, acquisition.col] + 0.01 * strategy.clock.clock_s
            outcome = strategy.record(acquisition, simulated_measurement(acquisition, z_um))
            done.append((acquisition, outcome))
        return done

    original = registry.create(name, settings, params)
    steps(original, 40)
    original.next_acquisition()
    restored = registry.create(name, settings, params)
    restored.next_acquisition()
    restore(restored, encode(original))
    assert isinstance(restored, SerpentineFilter)
    assert restored.clock.clock_s == original.clock.clock_s > 0
    assert steps(restored, 1000) == steps(original, 1000)
