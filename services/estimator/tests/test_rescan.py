"""`kf-rescan`: the last pass's map as the prior, the drift between passes estimated."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.drift import ThermalDrift
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


def test_a_wandering_offset_is_followed_where_an_integrated_walk_lags() -> None:
    """A drift that walks in its offset (the last pass's walk frozen in its map, this
    pass's own): with `offset_q_um2_per_s` the unmeasured tiles' sigma grows with time as
    the walk's, and the tiles are kept in focus; with the rate's noise alone the sigma
    stays small between measurements while the offset wanders off."""
    truth = np.zeros(GRID.shape)
    walk = ThermalDrift(walk_um_per_sqrt_min=2.0, seed=3)  # 0.067 um^2/s
    base = {"prior_map_um": truth.ravel().tolist(), "prior_map_sigma_um": [0.03]}
    common = {**base, "local_sigma_um": 0.0, "risk_out_of_focus": 0.002}

    def run(**params: float) -> tuple[float, float]:
        strategy = registry.create("kf-rescan", SETTINGS, {**common, **params})
        done = replay(strategy, truth, truth, drift=walk)
        errors = np.abs(done.focus_map.z_used_um - done.truth_um)
        return float(np.mean(errors <= SETTINGS.dof_um / 2)), done.n_images / GRID.n_tiles

    walked, walked_frames = run(offset_q_um2_per_s=2.0**2 / 60.0)  # the walk, as simulated
    integrated, integrated_frames = run()
    assert walked == 1.0  # at the price of the frames such a walk needs
    assert integrated < 0.8 and integrated_frames < walked_frames


def test_a_frame_found_out_of_focus_is_followed_by_a_measured_stack_of_its_tile() -> None:
    """The scheduler's first-frame check: a tile imaged once at its prediction whose frame
    is posted `frame_out_of_focus` is not finished; the policy's stack about the
    prediction follows, is measured as any, and the tile is imaged at the frame nearest
    its posterior. The replay's `frame_check` posts it so: a tile 0.6 um off the map (4.4
    sigma), which the rule images once, ends in focus with the check and out of focus
    without."""
    truth = np.zeros(GRID.shape)
    off = GRID.serpentine[-1]
    moved = truth.copy()
    moved[off.row, off.col] = 0.6  # the slide changed there since the last pass

    def check(row: int, col: int, z_um: float, truth_um: float) -> bool:
        return abs(z_um - truth_um) > SETTINGS.dof_um / 2

    unchecked = replay(_rescan(truth), moved, moved)
    checked = replay(_rescan(truth), moved, moved, frame_check=check)
    assert not unchecked.in_focus(SETTINGS.dof_um)[off.row, off.col]
    assert checked.in_focus(SETTINGS.dof_um).all()
    tile_outcomes = [o for o in checked.outcomes if (o.row, o.col) == (off.row, off.col)]
    assert len(tile_outcomes) == 2 and tile_outcomes[0].posterior_um is None
    assert tile_outcomes[1].accepted
    policy = SETTINGS.policy
    assert checked.n_images - unchecked.n_images == policy.min_frames  # the stack, 1 um wide
    # every other tile as without the check
    others = np.ones(GRID.shape, dtype=bool)
    others[off.row, off.col] = False
    np.testing.assert_array_equal(
        checked.focus_map.z_used_um[others], unchecked.focus_map.z_used_um[others]
    )


def test_a_frame_out_of_focus_survives_the_log() -> None:
    from focustrack_core.domain import Measurement
    from focustrack_estimator.records import measurement_of, measurement_record

    for flagged in (True, False):
        measurement = Measurement(z_um=None, frame_out_of_focus=flagged)
        record = measurement_record(measurement)
        assert ("frame_out_of_focus" in record) is flagged  # older logs read as before
        assert measurement_of(record) == measurement


def test_a_step_the_gate_lets_through_is_the_tiles_own_not_the_drifts() -> None:
    """With the NIS gate on, kf-rescan used to stop at the first step it let through ("cannot
    take a gated step"), its slide jammed for good. A fold of 3 um over part of the slide:
    the scan ends, the fold's measured tiles are taken at their height (patience 0: a step
    at once), and the drift, which the fold is not, stays near 0."""
    truth = np.zeros(GRID.shape)
    truth[4:7, 2:8] += 3.0
    params = {"prior_map_um": [0.0] * GRID.n_tiles, "gate_nis": 9.0, "gate_patience": 0}
    strategy = registry.create("kf-rescan", SETTINGS, params)
    run = replay(strategy, truth, truth)
    assert np.all(strategy.scanned)
    assert abs(strategy.drift_um) < 0.3
    steps = [o for o in run.outcomes if o.accepted and abs(o.innovation_um or 0.0) > 2.0]
    assert steps and all(abs(o.posterior_um - 3.0) < 0.1 for o in steps)
