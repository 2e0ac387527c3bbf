"""kf-2d-laser: a laser reading per tile fused with image measurements, the offset learned."""

from __future__ import annotations

import math

import numpy as np
import pytest

from focustrack_core.domain import Measurement, Purpose, SlideSettings
from focustrack_core.drift import ThermalDrift
from focustrack_core.geometry import ScanGrid
from focustrack_core.laser import LaserSpec, coverslip_offsets
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import add_measurement_noise, family_spec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.laser import LaserFilter
from focustrack_estimator.replay import ReplayLaser, replay, score

DOF_UM = 0.89
NOISE_UM = 0.1
SIZE = 16


def _scene(seed: int) -> tuple[np.ndarray, np.ndarray, ReplayLaser]:
    truth = generate_surfaces(family_spec("standard", SIZE, SIZE), 1, seed)[0]
    measured = add_measurement_noise(truth[None], NOISE_UM, seed)[0]
    spec = LaserSpec()
    return truth, measured, ReplayLaser(coverslip_offsets((SIZE, SIZE), seed, spec), spec)


def _settings() -> SlideSettings:
    return default_settings(ScanGrid(SIZE, SIZE), dof_um=DOF_UM, noise_sigma_um=NOISE_UM)


def test_every_tile_is_read_first_and_most_are_imaged_once_in_focus() -> None:
    truth, measured, laser = _scene(8)
    drift = ThermalDrift.thermal(8)
    strategy = registry.create("kf-2d-laser", _settings())
    run = replay(strategy, truth, measured, drift=drift, laser=laser)
    assert run.n_laser_readings == SIZE * SIZE
    s = score([run], DOF_UM)
    assert s.in_focus_fraction >= 0.99
    assert s.images_per_tile <= 1.5  # a stack only where the risk rule asks
    # kf-2d-lean, measuring the focus from images alone, takes more
    lean = replay(registry.create("kf-2d-lean", _settings()), truth, measured, drift=drift)
    assert score([lean], DOF_UM).images_per_tile > s.images_per_tile + 0.3
    # the offset learned is the coverslip's: smoothed focus = reading + offset
    assert isinstance(strategy, LaserFilter)
    assert np.isfinite(run.focus_map.smoothed_um).all()
    learned = run.focus_map.smoothed_um - strategy.laser_um
    assert np.mean(np.abs(learned - laser.offsets_um)) < 0.15


def test_a_laser_reading_comes_before_each_tiles_frames() -> None:
    truth, _, laser = _scene(9)
    strategy = registry.create("kf-2d-laser", _settings())
    last_read: tuple[int, int] | None = None
    while (acquisition := strategy.next_acquisition()) is not None:
        tile = (acquisition.row, acquisition.col)
        if acquisition.purpose is Purpose.LASER:
            last_read = tile
            z = truth[tile] - laser.offsets_um[tile]
            strategy.record(acquisition, Measurement(z_um=float(z), sigma_um=0.05))
            continue
        assert last_read == tile
        if acquisition.measure:
            strategy.record(acquisition, Measurement(z_um=float(truth[tile]), sigma_um=0.1))
        else:
            strategy.record(acquisition, Measurement(z_um=None))


@pytest.mark.parametrize(
    ("params", "offset_um", "offset_sigma_um"),
    [
        ({}, LaserSpec.offset_um, LaserSpec.offset_sigma_um),
        ({"offset_um": -7.0, "offset_sigma_um": 0.2}, -7.0, 0.2),
    ],
)
def test_the_first_tile_is_predicted_from_the_calibrated_offset(
    params: dict[str, float], offset_um: float, offset_sigma_um: float
) -> None:
    strategy = registry.create("kf-2d-laser", _settings(), params)
    reading = strategy.next_acquisition()
    assert reading is not None and reading.purpose is Purpose.LASER
    strategy.record(reading, Measurement(z_um=-3.0, sigma_um=0.05))
    first = strategy.next_acquisition()
    assert first is not None and first.purpose is Purpose.SCAN and first.measure
    # the reading plus the calibration, as unsure as the calibration and the reading
    assert first.predicted_um == pytest.approx(-3.0 + offset_um, abs=1e-9)
    assert first.predicted_sigma_um == pytest.approx(math.hypot(offset_sigma_um, 0.05), rel=0.02)
    # a short stack there, not a coarse search of the start's 10 um (4 um apart)
    assert first.z.n_frames <= 3 and first.z.step_um == _settings().policy.z_step_um


def test_a_missing_reading_leaves_the_tile_to_its_images() -> None:
    strategy = registry.create("kf-2d-laser", default_settings(ScanGrid(2, 2)))
    reading = strategy.next_acquisition()
    assert reading is not None and reading.purpose is Purpose.LASER
    outcome = strategy.record(reading, Measurement(z_um=None))
    assert not outcome.accepted
    first = strategy.next_acquisition()
    assert first is not None and first.purpose is Purpose.SCAN and first.measure
    assert first.predicted_sigma_um is not None and first.predicted_sigma_um > 5.0


def test_replay_needs_a_laser_for_a_laser_strategy() -> None:
    truth, measured, _ = _scene(10)
    with pytest.raises(ValueError, match="laser"):
        replay(registry.create("kf-2d-laser", _settings()), truth, measured)
