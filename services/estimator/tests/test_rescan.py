"""`kf-rescan`: the last pass's map as the prior, the drift between passes estimated."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.surfaces import SurfaceSpec, generate_surfaces
from focustrack_estimator import registry
from focustrack_estimator.lean import COARSE_STEP_UM
from focustrack_estimator.replay import Drift, replay, score
from focustrack_estimator.rescan import RescanFilter

GRID = ScanGrid(10, 10)
SETTINGS = default_settings(GRID, noise_sigma_um=0.1, dof_um=0.9)


def _rescan(base_um: np.ndarray, sigma_um: float = 0.03) -> RescanFilter:
    params = {"prior_map_um": base_um.ravel().tolist(), "prior_map_sigma_um": [sigma_um]}
    strategy = registry.create("kf-rescan", SETTINGS, params)
    assert isinstance(strategy, RescanFilter)
    return strategy


def test_a_drifted_slide_is_found_once_and_then_imaged_with_about_one_frame_a_tile() -> None:
    truth = generate_surfaces(SurfaceSpec(rows=10, cols=10), 1, seed=5)[0]
    noise = 0.1 * np.random.default_rng(1).standard_normal(truth.shape)
    drift = Drift(offset_um=8.0, rate_um_per_s=0.02)
    strategy = _rescan(truth)
    run = replay(strategy, truth, truth + noise, drift=drift)
    scores = score([run], SETTINGS.dof_um)
    assert scores.in_focus_fraction == 1.0
    assert scores.images_per_tile < 1.4
    # the offset at the last tile's stack, 8 um plus the rate over the scan, within the
    # filter's own 3 sigma (a few measurements of 0.1 um noise and 0.05 um local change)
    drift_sigma_um = float(np.sqrt(strategy.P[0, 0]))
    assert drift_sigma_um < 0.2  # the risk rule measures before it grows past the DOF
    assert abs(strategy.drift_um - drift.at(run.scan_time_s)) < 3 * drift_sigma_um
    assert strategy.drift_um_per_s == pytest.approx(0.02, abs=0.02)
    # the first tile was searched coarsely, then measured with a fine stack
    assert run.outcomes[0].accepted is False and run.outcomes[1].accepted
    # kf-2d without the map takes several times the frames
    fresh = replay(registry.create("kf-2d", SETTINGS), truth, truth + noise, drift=drift)
    assert fresh.n_images > 3 * run.n_images


def test_the_drift_is_tracked_between_measurements() -> None:
    truth = np.zeros(GRID.shape)
    strategy = _rescan(truth)
    run = replay(strategy, truth, truth, drift=Drift(0.0, 0.05))
    assert np.all(np.abs(run.focus_map.z_used_um - run.truth_um) <= SETTINGS.dof_um / 2)
    assert strategy.drift_um_per_s == pytest.approx(0.05, abs=0.01)


def test_a_prior_map_of_the_wrong_shape_is_refused() -> None:
    with pytest.raises(ValueError, match="prior map"):
        _rescan(np.zeros((3, 4)))
    without = registry.create("kf-rescan", SETTINGS)  # no map: every tile as unsure as the start
    first = without.next_acquisition()
    assert first is not None and first.z.step_um == COARSE_STEP_UM  # a coarse search
