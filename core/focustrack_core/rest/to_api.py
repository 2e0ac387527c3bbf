"""Domain values (`focustrack_core.domain`) as REST models (`focustrack_client.models`).

Heights that are not finite (NaN where a map has no value yet) are null in JSON.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from typing import Any

from focustrack_client import models as api
from focustrack_core.domain import (
    Acquisition,
    Measurement,
    Outcome,
    SlideSettings,
    ZRangePolicy,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import finite_or_none


def grid(scan_grid: ScanGrid) -> api.Grid:
    """The API grid of a scan grid."""
    return api.Grid(
        rows=scan_grid.rows,
        cols=scan_grid.cols,
        pitch_um=scan_grid.pitch_um,
        origin_x_um=scan_grid.origin_x_um,
        origin_y_um=scan_grid.origin_y_um,
    )


def policy(z_policy: ZRangePolicy) -> api.ZRangePolicy:
    """The API policy of a z-range policy."""
    return api.ZRangePolicy(
        k_sigma=z_policy.k_sigma,
        z_step_um=z_policy.z_step_um,
        min_frames=z_policy.min_frames,
        max_frames=z_policy.max_frames,
    )


def slide_create(
    strategy: str, settings: SlideSettings, params: Mapping[str, Any] | None = None
) -> api.SlideCreate:
    """The body of `POST /slides` for a slide of `strategy` with these settings and parameters
    (the inverse of `to_domain.slide_settings`)."""
    return api.SlideCreate(
        strategy=strategy,
        params=dict(params or {}),
        grid=grid(settings.grid),
        start_z_um=settings.start_z_um,
        start_sigma_um=settings.start_sigma_um,
        dof_um=settings.dof_um,
        noise_sigma_um=settings.noise_sigma_um,
        z_range=policy(settings.policy),
    )


def next_step(acquisition: Acquisition | None, scan_grid: ScanGrid) -> api.Next:
    """The `GET /next` reply asking for `acquisition` on `scan_grid` (None: the scan is done)."""
    if acquisition is None:
        return api.Next(done=True)
    x_um, y_um = scan_grid.stage_xy_um(acquisition.row, acquisition.col)
    z = acquisition.z
    return api.Next(
        done=False,
        sequence=acquisition.index,
        row=acquisition.row,
        col=acquisition.col,
        stage_x_um=x_um,
        stage_y_um=y_um,
        z_center_um=z.center_um,
        z_low_um=z.low_um,
        z_high_um=z.high_um,
        z_step_um=z.step_um,
        n_frames=z.n_frames,
        predicted_z_um=finite_or_none(acquisition.predicted_um),
        predicted_sigma_um=finite_or_none(acquisition.predicted_sigma_um),
        purpose=api.Purpose(acquisition.purpose),
        measure=acquisition.measure,
    )


def is_height(z_um: float) -> bool:
    """Whether `z_um` is a height the API takes (finite, within +/-MAX_ABS_UM)."""
    return math.isfinite(z_um) and abs(z_um) <= api.MAX_ABS_UM


def sigma_within_bounds(sigma_um: float) -> float | None:
    """A sigma (um) another service stated, as the API takes it: None where it is no
    positive finite number (the slide's noise sigma stands in), else within MIN_SIGMA_UM
    ..MAX_ABS_UM (a focus service or a laser stating a picometre must not end a scan)."""
    if not (math.isfinite(sigma_um) and sigma_um > 0):
        return None
    return min(max(sigma_um, api.MIN_SIGMA_UM), api.MAX_ABS_UM)


def measurement_in(acquisition: Acquisition, measurement: Measurement) -> api.MeasurementIn:
    """The body of `POST /measurements` reporting `measurement` for `acquisition`."""
    return api.MeasurementIn(
        row=acquisition.row,
        col=acquisition.col,
        sequence=acquisition.index,
        z_um=measurement.z_um,
        sigma_um=measurement.sigma_um,
        flags=[api.FocusFlag(flag) for flag in sorted(measurement.flags)],
        runner_up_z_um=measurement.runner_up_z_um,
        chosen_probability=measurement.chosen_probability,
        frame_out_of_focus=measurement.frame_out_of_focus,
    )


def outcome_out(sequence: int, outcome: Outcome) -> api.OutcomeOut:
    """The `POST /measurements` reply: what the measurement of `sequence` did."""
    return api.OutcomeOut(
        sequence=sequence,
        row=outcome.row,
        col=outcome.col,
        accepted=outcome.accepted,
        prior_um=finite_or_none(outcome.prior_um),
        prior_sigma_um=finite_or_none(outcome.prior_sigma_um),
        posterior_um=finite_or_none(outcome.posterior_um),
        posterior_sigma_um=finite_or_none(outcome.posterior_sigma_um),
        innovation_um=finite_or_none(outcome.innovation_um),
        nis=finite_or_none(outcome.nis),
        planes_um=list(outcome.planes_um),
    )
