"""The estimator's REST models and the domain translate both ways; the defaults are the API's."""

from __future__ import annotations

import math

import pytest

from focustrack_client import models as api
from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    Measurement,
    Outcome,
    Purpose,
    ZRange,
    ZRangePolicy,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api, to_domain


def test_a_next_reply_is_an_acquisition_and_done_is_none() -> None:
    reply = api.Next(
        done=False, sequence=4, row=1, col=2, z_low_um=-1.0, z_high_um=1.0, z_step_um=0.5,
        n_frames=5, predicted_z_um=0.1, predicted_sigma_um=0.3, purpose=api.Purpose.RETRY,
        measure=True,
    )  # fmt: skip
    acquisition = to_domain.acquisition(reply)
    assert acquisition is not None
    assert (acquisition.index, acquisition.row, acquisition.col) == (4, 1, 2)
    assert acquisition.z == ZRange(-1.0, 0.5, 5) and acquisition.purpose is Purpose.RETRY
    assert to_domain.acquisition(api.Next(done=True)) is None
    with pytest.raises(ValueError, match="incomplete"):
        to_domain.acquisition(api.Next(done=False, sequence=1))


def test_an_acquisition_goes_to_the_api_and_back_unchanged() -> None:
    grid = ScanGrid(3, 4, pitch_um=150.0, origin_x_um=10.0, origin_y_um=-5.0)
    acquisition = Acquisition(
        7, 2, 3, ZRange(-2.0, 0.25, 9), Purpose.PLANES, False, predicted_um=0.5,
        predicted_sigma_um=0.2,
    )  # fmt: skip
    step = to_api.next_step(acquisition, grid)
    assert (step.stage_x_um, step.stage_y_um) == grid.stage_xy_um(2, 3)
    assert (step.z_center_um, step.z_high_um) == (-1.0, 0.0)
    assert to_domain.acquisition(api.Next.model_validate_json(step.model_dump_json())) == (
        acquisition
    )
    assert to_api.next_step(None, grid) == api.Next(done=True)


def test_a_prediction_that_is_not_finite_is_null() -> None:
    acquisition = Acquisition(0, 0, 0, ZRange(0.0, 0.5, 5), Purpose.SCAN, True, math.nan, math.inf)
    step = to_api.next_step(acquisition, ScanGrid(1, 1))
    assert (step.predicted_z_um, step.predicted_sigma_um) == (None, None)


def test_a_measurement_is_the_body_the_estimator_validates_and_reads_back() -> None:
    acquisition = Acquisition(0, 0, 3, ZRange(0.0, 0.5, 3), Purpose.SCAN, True)
    flags = frozenset({FocusFlag.MULTI_PEAK, FocusFlag.EDGE_LOW})
    body = to_api.measurement_in(acquisition, Measurement(None, None, flags))
    assert body.flags == [api.FocusFlag.EDGE_LOW, api.FocusFlag.MULTI_PEAK]
    assert (body.row, body.col, body.sequence, body.z_um) == (0, 3, 0, None)
    measured = Measurement(1.25, 0.3, frozenset({FocusFlag.AMBIGUOUS}))
    parsed = api.MeasurementIn.model_validate_json(
        to_api.measurement_in(acquisition, measured).model_dump_json()
    )
    assert to_domain.measurement(parsed) == measured


def test_an_outcome_goes_to_the_api_and_back_with_nan_as_null() -> None:
    outcome = Outcome(
        0, 3, True, prior_um=1.0, prior_sigma_um=2.0, posterior_um=1.5, posterior_sigma_um=0.1,
        innovation_um=0.5, nis=0.06, planes_um=(1.0, 1.5),
    )  # fmt: skip
    reply = to_api.outcome_out(9, outcome)
    assert reply.sequence == 9
    assert to_domain.outcome(api.OutcomeOut.model_validate_json(reply.model_dump_json())) == outcome
    unsure = to_api.outcome_out(0, Outcome(0, 0, False, prior_um=math.nan))
    assert unsure.prior_um is None and unsure.planes_um == []


def test_slide_settings_go_to_the_api_and_back_unchanged() -> None:
    grid = ScanGrid(5, 6, pitch_um=300.0, origin_x_um=1.0, origin_y_um=2.0)
    settings = to_domain.default_settings(
        grid, start_z_um=3.0, dof_um=0.8, policy=ZRangePolicy(3.0, 0.25, 7, 31)
    )
    config = to_api.slide_create("kf-2d", settings, {"q": 0.2})
    assert (config.strategy, config.params) == ("kf-2d", {"q": 0.2})
    assert to_domain.slide_settings(api.SlideCreate.model_validate_json(config.model_dump_json()))
    assert to_domain.slide_settings(config) == settings


def test_the_defaults_are_the_apis() -> None:
    grid = ScanGrid(2, 2)
    settings = to_domain.default_settings(grid)
    config = api.SlideCreate(strategy="kf-2d", grid=api.Grid(rows=2, cols=2))
    assert settings == to_domain.slide_settings(config)
    assert to_domain.default_policy() == to_domain.policy(api.ZRangePolicy())
    assert to_domain.default_policy(max_frames=21).max_frames == 21
    with pytest.raises(ValueError):  # the API's bounds hold on the defaults' changes too
        to_domain.default_policy(min_frames=50, max_frames=21)
