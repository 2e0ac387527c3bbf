"""The replay engine: simulated measurements (edge flags), costs, and pooled scores."""

from __future__ import annotations

import numpy as np
import pytest

from focustrack_core.domain import Acquisition, FocusFlag, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_settings
from focustrack_core.timing import TimingModel
from focustrack_estimator import registry
from focustrack_estimator.replay import replay, score, simulated_measurement

PITCH_UM = 200.0


def _acquisition(z: ZRange, *, measure: bool = True) -> Acquisition:
    return Acquisition(0, 0, 0, z, Purpose.SCAN, measure)


def test_measurement_inside_at_and_beyond_the_edges() -> None:
    stack = ZRange(-2.0, 0.5, 9)  # -2 .. 2 um
    assert simulated_measurement(_acquisition(stack), 0.3).z_um == 0.3
    assert simulated_measurement(_acquisition(stack), 2.0).is_observation  # an edge frame counts
    low = simulated_measurement(_acquisition(stack), -2.01)
    high = simulated_measurement(_acquisition(stack), 7.0)
    assert (low.z_um, low.flags) == (None, frozenset({FocusFlag.EDGE_LOW}))
    assert (high.z_um, high.flags) == (None, frozenset({FocusFlag.EDGE_HIGH}))
    assert not low.is_observation and not high.is_observation
    image_only = simulated_measurement(_acquisition(ZRange(0.3, 0.5, 1), measure=False), 0.3)
    assert image_only.z_um is None and not image_only.flags


def test_cost_of_a_scan_without_retries() -> None:
    timing = TimingModel(exposure_s=0.1, xy_settle_s=0.2)
    truth = np.zeros((2, 3))
    run = replay(
        registry.create("af-every-tile", default_settings(ScanGrid(2, 3))), truth, truth, timing
    )
    # Serpentine over 2x3: five one-tile moves, six 41-frame stacks.
    assert run.n_images == 6 * 41
    assert run.scan_time_s == pytest.approx(5 * timing.move_s(PITCH_UM) + 6 * timing.stack_s(41))
    assert len(run.outcomes) == 6 and all(o.accepted for o in run.outcomes)


@pytest.mark.parametrize(("height_um", "flag"), [(15.0, "edge_high"), (-15.0, "edge_low")])
def test_an_edge_peak_costs_a_retry_on_the_same_tile(height_um: float, flag: str) -> None:
    truth = np.full((2, 3), height_um)
    strategy = registry.create("af-every-tile", default_settings(ScanGrid(2, 3), start_z_um=0.0))
    first = strategy.next_acquisition()
    assert first is not None and not first.z.contains(height_um)
    assert simulated_measurement(first, height_um).flags == {FocusFlag(flag)}

    run = replay(strategy, truth, truth)
    timing = TimingModel()
    # The first tile needs a second 41-frame block beyond the edge; the retry needs no move.
    assert run.n_images == 7 * 41
    assert run.scan_time_s == pytest.approx(5 * timing.move_s(PITCH_UM) + 7 * timing.stack_s(41))
    assert [o.accepted for o in run.outcomes] == [False] + [True] * 6
    assert np.allclose(run.focus_map.posterior_um, height_um)


def test_a_survey_pass_pays_for_its_moves() -> None:
    timing = TimingModel()
    truth = np.zeros((3, 3))
    run = replay(
        registry.create("survey-bilinear", default_settings(ScanGrid(3, 3)), {"n_survey": 4}),
        truth,
        truth,
        timing,
    )
    # Survey (0,0) -> (0,2) -> (2,2) -> (2,0), back to (0,0), then 8 one-tile serpentine moves.
    expected_s = 4 * timing.move_s(2 * PITCH_UM) + 8 * timing.move_s(PITCH_UM)
    expected_s += 4 * timing.stack_s(41) + 9 * timing.stack_s(1)
    assert run.n_images == 4 * 41 + 9
    assert run.scan_time_s == pytest.approx(expected_s)


def test_scores_pool_maps() -> None:
    rng = np.random.default_rng(3)
    truths = [rng.normal(0.0, 2.0, (4, 5)) for _ in range(2)]
    measured = [t + rng.normal(0.0, 0.6, t.shape) for t in truths]
    settings = default_settings(ScanGrid(4, 5))
    runs = [
        replay(registry.create("af-every-tile", settings), t, m)
        for t, m in zip(truths, measured, strict=True)
    ]
    scores = score(runs, dof_um=1.0)

    error = np.concatenate([(m - t).ravel() for t, m in zip(truths, measured, strict=True)])
    assert scores.prior_mae_um is None and scores.prior_std_um is None
    assert scores.post_mae_um == pytest.approx(np.mean(np.abs(error)))
    assert scores.post_std_um == pytest.approx(np.std(error))
    assert scores.images_per_tile == 41.0
    assert scores.scan_time_s == pytest.approx(np.mean([r.scan_time_s for r in runs]))
    used = np.concatenate([(r.focus_map.z_used_um - r.truth_um).ravel() for r in runs])
    assert scores.in_focus_fraction == pytest.approx(np.mean(np.abs(used) <= 0.5))
    assert 0.0 < scores.in_focus_fraction < 1.0

    kalman = score([replay(registry.create("kf-wiener0", settings), truths[0], measured[0])], 1.0)
    assert kalman.prior_mae_um is not None and np.isfinite(kalman.prior_mae_um)


def test_replay_refuses_maps_of_another_shape() -> None:
    with pytest.raises(ValueError, match="differ from grid"):
        replay(
            registry.create("af-every-tile", default_settings(ScanGrid(2, 3))),
            np.zeros((3, 2)),
            np.zeros((3, 2)),
        )


def test_a_tile_that_keeps_several_frames_is_in_focus_when_one_of_them_is() -> None:
    rng = np.random.default_rng(5)
    settings = default_settings(ScanGrid(6, 6))
    truth = rng.normal(0.0, 2.0, (6, 6))
    run = replay(registry.create("kf-2d-lean", settings), truth, truth + rng.normal(0, 1.5, (6, 6)))
    assert run.planes_um  # at 1.5 um of noise against 1 um of depth of field, tiles keep several
    inside = run.in_focus(1.0)
    for (row, col), planes_um in run.planes_um.items():
        assert planes_um[0] <= run.focus_map.z_used_um[row, col] <= planes_um[-1]
        assert np.all(np.diff(planes_um) > 0) and np.all(np.diff(planes_um) <= 1.0 + 1e-9)
        assert inside[row, col] == any(abs(z - truth[row, col]) <= 0.5 for z in planes_um)
    single = np.abs(run.focus_map.z_used_um - truth) <= 0.5
    assert inside.sum() > single.sum() and np.all(inside >= single)
    scores = score([run], 1.0)
    assert scores.in_focus_fraction == pytest.approx(inside.mean())
    kept = 36 + sum(len(planes) - 1 for planes in run.planes_um.values())
    assert scores.frames_kept_per_tile == pytest.approx(kept / 36)
