"""The lean acquisition rule: the kept image alone, a short stack or a full one, by risk."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.stats import norm, poisson

from focustrack_core.geometry import ScanGrid
from focustrack_core.rest.to_domain import default_policy, default_settings
from focustrack_core.surfaces import SurfaceSpec, family_spec, generate_surfaces
from focustrack_core.timing import TimingModel
from focustrack_estimator import registry
from focustrack_estimator.bank import tempered_weights
from focustrack_estimator.lean import (
    COARSE_STEP_UM,
    SHORT_FRAMES,
    choose_stack,
    kept_planes,
    mixture_skip_risk,
    out_of_focus_risk,
    planes_risk,
    planes_stack,
    search_cost,
    skip_risk,
    summarise_risk,
)
from focustrack_estimator.replay import limit_time_s, reliability, replay, score

POLICY = default_policy()
DOF_UM = 1.0


def test_risk_is_the_gaussian_mass_outside_the_depth_of_field() -> None:
    assert out_of_focus_risk(0.0, 0.2, 0.0, DOF_UM) == pytest.approx(2 * norm.sf(0.5 / 0.2))
    # kept 0.3 um off the mean: the near edge is 0.2 um away, the far one 0.8 um
    expected = norm.sf(0.2 / 0.1) + norm.cdf(-0.8 / 0.1)
    assert out_of_focus_risk(0.3, 0.1, 0.0, DOF_UM) == pytest.approx(expected)
    assert out_of_focus_risk(0.0, 0.0, 0.4, DOF_UM) == 0.0
    assert out_of_focus_risk(0.0, 0.0, 0.6, DOF_UM) == 1.0


def test_a_mixture_s_risk_is_its_members_weighed_not_one_gaussian_s() -> None:
    # members of 0.08 and 0.2 um weighted 3 to 1, imaged at their common mean
    weights = np.array([0.75, 0.25])
    risk = mixture_skip_risk(np.zeros(2), np.array([0.08, 0.2]) ** 2, weights, 0.0, 0.89, 1.0)
    expected = 0.75 * 2 * norm.sf(0.445 / 0.08) + 0.25 * 2 * norm.sf(0.445 / 0.2)
    assert risk == pytest.approx(expected)
    # the Gaussian of the same variance (0.12 um) states a tenth of it
    one_sigma_um = math.sqrt(weights @ np.array([0.08, 0.2]) ** 2)
    assert 2 * norm.sf(0.445 / one_sigma_um) < risk / 10
    # members off the kept height count their offset; the scale widens every member
    off = mixture_skip_risk(
        np.array([0.3, -0.3]), np.full(2, 0.1**2), np.full(2, 0.5), 0.0, 1.0, 1.0
    )
    assert off == pytest.approx(norm.sf(0.2 / 0.1) + norm.sf(0.8 / 0.1))
    wider = mixture_skip_risk(np.zeros(2), np.full(2, 0.1**2), weights, 0.0, 0.89, 2.0)
    assert wider == pytest.approx(2 * norm.sf(0.445 / 0.2))


def test_tempered_weights_keep_what_the_evidence_has_not_ruled_out() -> None:
    log_likelihoods = np.array([0.0, -3.0, -30.0])
    bayes, tempered = tempered_weights(log_likelihoods, 1.0), tempered_weights(log_likelihoods, 3.0)
    assert bayes.sum() == pytest.approx(1.0) and tempered.sum() == pytest.approx(1.0)
    assert bayes[1] == pytest.approx(math.exp(-3.0) / (1 + math.exp(-3.0) + math.exp(-30.0)))
    assert tempered[1] == pytest.approx(math.exp(-1.0) / (1 + math.exp(-1.0) + math.exp(-10.0)))
    assert tempered[2] < 1e-4  # a member ruled out stays out


def test_kf_2d_lean_misses_no_more_than_it_states_on_maps_no_member_of_its_bank_is() -> None:
    # Precise measurements (0.03 um, the slide bench's focus service) on the standard maps:
    # a smoothed exponential field, which kf-2d's smoothest members fit along one row and
    # then predict far too surely. As one Gaussian of the bank's weights the rule missed
    # 21 tiles here where it stated 2.8; its members' tempered mixture misses 3 of 3.2.
    size, dof_um, noise_um = 10, 0.89, 0.03
    settings = default_settings(ScanGrid(size, size), noise_sigma_um=0.05, dof_um=dof_um)
    truth = np.concatenate(
        [
            generate_surfaces(family_spec("standard", size, size), 1, seed)
            for seed in range(1000, 1020)
        ]
    )
    noise = noise_um * np.random.default_rng(77).standard_normal(truth.shape)
    runs = [
        replay(registry.create("kf-2d-lean", settings), t, t + e)
        for t, e in zip(truth, noise, strict=True)
    ]
    stated = sum(float(np.nansum(r.focus_map.out_of_focus_risk)) for r in runs)
    misses = round((1.0 - score(runs, dof_um).in_focus_fraction) * truth.size)
    assert stated > 1.0
    # as many misses as a Poisson count of mean `stated` reaches 1 time in 1000, at most
    assert misses <= poisson.ppf(0.999, stated)


def _choose(sigma_um: float, r_um: float = 0.1, risk: float = 0.01):  # type: ignore[no-untyped-def]
    if_skipped = skip_risk(sigma_um, DOF_UM, 1.0)
    return choose_stack(5.0, sigma_um**2, r_um**2, DOF_UM, POLICY, risk, if_skipped, 3)


def test_a_sure_prediction_takes_the_kept_image_only() -> None:
    # 0.5 / 0.18 = 2.78 sigmas: a risk of 0.55%, within 1%
    choice = _choose(0.18)
    assert not choice.measure and choice.z.n_frames == 1 and choice.z.center_um == 5.0
    assert choice.skip_risk == pytest.approx(2 * norm.sf(0.5 / 0.18))
    # the same prediction with a stricter risk is measured, with a short stack
    stricter = _choose(0.18, risk=0.001)
    assert stricter.measure and stricter.z.n_frames == SHORT_FRAMES
    assert stricter.z.center_um == pytest.approx(5.0)


def test_an_unsure_prediction_takes_the_cheaper_search_that_reaches_the_peak() -> None:
    # innovation sigma 1 um: 3 frames then 5-frame retries (reach 0.5, 2, 3.5, 5 um) cost
    # 3 + 5 (62% + 4.6% + ...) = 6.3 frames in expectation, the full stack 11
    sigma_um = math.hypot(1.0, 0.1)
    choice = _choose(1.0)
    assert choice.measure and choice.z.n_frames == SHORT_FRAMES
    assert choice.expected_frames == pytest.approx(search_cost(choice.z, sigma_um, POLICY, 3, 0.01))
    assert choice.expected_frames < POLICY.around(5.0, sigma_um).n_frames
    # at 2.5 um the short start's retries miss beyond 5 um in 4.5% of tiles: the full stack
    wide = _choose(2.5)
    assert wide.z == POLICY.around(5.0, math.hypot(2.5, 0.1))


def test_search_cost_counts_retries_and_refuses_a_likely_give_up() -> None:
    short = POLICY.around(0.0, 0.01)  # min_frames: 5 frames, +/- 1 um
    assert short.n_frames == POLICY.min_frames
    tiny = search_cost(short, 0.01, POLICY, 3, 0.01)
    assert tiny == pytest.approx(5.0)  # never misses
    wide = search_cost(short, 1.0, POLICY, 3, 0.01)
    # misses beyond 1 um (32%), then 2.5 um, then 4 um: each costs a 5-frame block
    expected = 5 + 5 * sum(2 * norm.sf(reach) for reach in (1.0, 2.5, 4.0))
    assert wide == pytest.approx(expected)
    assert search_cost(short, 10.0, POLICY, 3, 0.01) is None  # 3 retries reach 5.5 um only


def test_a_tile_too_unsure_for_one_frame_keeps_the_fewest_frames_that_meet_the_risk() -> None:
    frames_um = np.arange(-3.0, 3.01, 0.5)  # a full stack, 0.5 um steps
    # sure: the kept frame alone
    assert kept_planes(0.1, 0.1, frames_um, 0.0, DOF_UM, 0.01, 5) == (0.0,)
    # sigma 0.6 um: one frame leaves 2 Phi(-0.5 / 0.6) = 40%; frames a depth of field apart
    planes = kept_planes(0.1, 0.6, frames_um, 0.0, DOF_UM, 0.01, 5)
    assert planes == (-1.0, 0.0, 1.0, 2.0) or planes == (-2.0, -1.0, 0.0, 1.0)
    assert planes_risk(0.1, 0.6, planes, DOF_UM) <= 0.01
    assert planes_risk(0.1, 0.6, planes[1:], DOF_UM) > 0.01  # none of them is spare
    # capped, and only frames that were acquired within a depth of field of the next
    assert len(kept_planes(0.0, 3.0, frames_um, 0.0, DOF_UM, 0.01, 3)) == 3
    assert kept_planes(0.0, 3.0, np.array([0.0, 1.5]), 0.0, DOF_UM, 0.01, 5) == (0.0,)
    # the windows join: their risk is the Gaussian's mass outside [low - dof/2, high + dof/2]
    assert planes_risk(0.0, 1.0, (-1.0, 0.0, 1.0), DOF_UM) == pytest.approx(2 * norm.sf(1.5))


def test_the_frames_a_tile_lacks_are_a_stack_a_depth_of_field_apart() -> None:
    stack = planes_stack(0.0, 0.6, 0.0, DOF_UM, 0.5, 0.01, 5)
    assert stack is not None and stack.step_um == 1.0 and stack.n_frames == 5
    assert stack.center_um == 0.0
    # 3 are enough where the sigma is smaller; none where the kept frame alone is
    small = planes_stack(0.0, 0.35, 0.0, DOF_UM, 0.5, 0.01, 5)
    assert small is not None and small.n_frames == 3
    assert planes_stack(0.0, 0.01, 0.0, DOF_UM, 0.5, 0.01, 5) is None
    # frames further apart than the depth of field would leave gaps: none
    assert planes_stack(0.0, 0.6, 0.0, DOF_UM, 1.5, 0.01, 5) is None
    assert planes_stack(0.0, 0.6, 0.0, DOF_UM, 0.5, 0.01, 1) is None


def test_a_risk_summary_counts_imaged_tiles_and_says_when_the_stated_risk_is_not_met() -> None:
    risk = np.array([[0.001, 0.002, np.nan], [0.03, np.nan, np.nan]])
    summary = summarise_risk(risk, 0.01, DOF_UM, 1.5)
    assert summary is not None
    assert (summary.n_tiles, summary.n_over_stated) == (3, 1)
    assert summary.expected_out_of_focus == pytest.approx(0.011)
    assert summary.note is not None and "1.0%" in summary.note and "1.5 um" in summary.note
    # within the stated risk on average: one tile above it is no failure of the setting
    met = summarise_risk(np.array([[0.001, 0.002, 0.02]]), 0.01, DOF_UM, 0.1)
    assert met is not None and met.note is None and met.n_over_stated == 1
    # no stated risk (kf-2d): counted, never over
    unstated = summarise_risk(risk, None, DOF_UM, 1.5)
    assert unstated is not None and (unstated.n_over_stated, unstated.note) == (0, None)
    assert summarise_risk(np.full((2, 2), np.nan), 0.01, DOF_UM, 1.5) is None


def test_risk_must_be_a_probability() -> None:
    with pytest.raises(ValueError, match="risk"):
        _choose(0.1, risk=0.0)
    settings = default_settings(ScanGrid(3, 3))
    with pytest.raises(ValueError, match="risk_out_of_focus"):
        registry.create("kf-2d-lean", settings, {"risk_out_of_focus": 1.5})
    assert registry.parameters("kf-2d-lean")["risk_out_of_focus"] == 0.01
    assert registry.parameters("kf-wiener0")["risk_out_of_focus"] == 0.0  # off: full stacks


def _smooth_maps(n_maps: int, size: int) -> np.ndarray:
    return generate_surfaces(SurfaceSpec(rows=size, cols=size), n_maps, seed=7)


def test_kf_2d_lean_takes_fewer_frames_at_the_risk_it_states() -> None:
    truth = _smooth_maps(3, 12)
    noise = np.random.default_rng(3).standard_normal(truth.shape) * 0.1
    settings = default_settings(ScanGrid(12, 12), noise_sigma_um=0.1, dof_um=DOF_UM)
    runs = {
        name: [
            replay(registry.create(name, settings), t, t + e)
            for t, e in zip(truth, noise, strict=True)
        ]
        for name in ("kf-2d", "kf-2d-lean")
    }
    lean, full = score(runs["kf-2d-lean"], DOF_UM), score(runs["kf-2d"], DOF_UM)
    assert lean.images_per_tile < 0.6 * full.images_per_tile
    assert lean.in_focus_fraction >= 0.99
    assert lean.scan_time_s < full.scan_time_s
    # some tiles were imaged at their prediction alone: posterior sigma = prior sigma there
    skipped = [
        np.isclose(r.focus_map.posterior_sigma_um, r.focus_map.prior_sigma_um)
        for r in runs["kf-2d-lean"]
    ]
    assert 0 < np.mean(skipped) < 1
    # every tile states its risk, and the reliability table covers every tile once
    assert all(np.all(np.isfinite(r.focus_map.out_of_focus_risk)) for r in runs["kf-2d-lean"])
    bins = reliability(runs["kf-2d-lean"], DOF_UM)
    assert sum(b.n_tiles for b in bins) == truth.size
    assert all(b.low <= b.predicted < b.high or b.high == 1.0 for b in bins)


def test_a_slide_start_is_searched_coarsely_then_measured_with_a_short_stack() -> None:
    truth = np.full((2, 2), 7.3)  # 7.3 um from the start, 10 um unsure
    strategy = registry.create("kf-2d-lean", default_settings(ScanGrid(2, 2), noise_sigma_um=0.1))
    first = strategy.next_acquisition()
    # +/- 2 sigmas of about 10.2 um (kf-2d's offset and field) at 4 um: 13 frames, not 41 + 41
    assert first is not None and first.z.step_um == COARSE_STEP_UM == 4.0
    assert first.z.n_frames == 13
    run = replay(strategy, truth, truth)
    assert run.outcomes[0].accepted is False  # the coarse peak only centres the next stack
    assert run.outcomes[1].accepted and run.focus_map.z_used_um[0, 0] == pytest.approx(7.3)
    assert run.n_images - 13 <= 4 * 3  # a short stack per tile at most after the coarse one


def test_the_physical_limit_is_moves_and_one_frame_per_tile() -> None:
    grid, timing = ScanGrid(2, 3), TimingModel()
    expected = 5 * timing.move_s(grid.distance_um(grid.serpentine[0], grid.serpentine[1]))
    assert limit_time_s(grid, timing) == pytest.approx(expected + 6 * timing.stack_s(1))
