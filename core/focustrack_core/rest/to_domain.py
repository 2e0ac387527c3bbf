"""REST models (`focustrack_client.models`) into domain values (`focustrack_core.domain`)."""

from __future__ import annotations

import dataclasses
from typing import Any

from focustrack_client import models as api
from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRange,
    ZRangePolicy,
)
from focustrack_core.geometry import ScanGrid
from focustrack_core.rest import to_api


def grid(model: api.Grid) -> ScanGrid:
    """The scan grid of an API grid."""
    return ScanGrid(model.rows, model.cols, model.pitch_um, model.origin_x_um, model.origin_y_um)


def policy(model: api.ZRangePolicy) -> ZRangePolicy:
    """The z-range policy of an API policy."""
    return ZRangePolicy(model.k_sigma, model.z_step_um, model.min_frames, model.max_frames)


def slide_settings(config: api.SlideCreate) -> SlideSettings:
    """What a slide's strategy is told: the API slide's grid, prior and z-range policy."""
    return SlideSettings(
        grid=grid(config.grid),
        start_z_um=config.start_z_um,
        start_sigma_um=config.start_sigma_um,
        dof_um=config.dof_um,
        noise_sigma_um=config.noise_sigma_um,
        policy=policy(config.z_range),
    )


def default_policy(**changes: Any) -> ZRangePolicy:
    """The API's default z-range policy, with `changes` (fields by name) over it."""
    return policy(api.ZRangePolicy(**changes))


def default_settings(scan_grid: ScanGrid, **changes: Any) -> SlideSettings:
    """The settings of a slide on `scan_grid` with the API's defaults (`api.SlideCreate`),
    `changes` (domain fields by name: `noise_sigma_um`, `policy`, ...) over them."""
    # Unvalidated on purpose: no strategy is named; only the settings' defaults are read.
    defaults = api.SlideCreate.model_construct(strategy="", grid=to_api.grid(scan_grid))
    return dataclasses.replace(slide_settings(defaults), **changes)


def flags(values: list[api.FocusFlag]) -> frozenset[FocusFlag]:
    """The domain's flags of the API's."""
    return frozenset(FocusFlag(flag) for flag in values)


def measurement(body: api.MeasurementIn) -> Measurement:
    """The measurement a `POST /measurements` body reports (ValueError if it is not one)."""
    return Measurement(
        body.z_um,
        body.sigma_um,
        flags(body.flags),
        body.runner_up_z_um,
        body.chosen_probability,
        body.frame_out_of_focus,
    )


def acquisition(step: api.Next) -> Acquisition | None:
    """The acquisition a `GET /next` reply asks for (None when the scan is done)."""
    if step.done:
        return None
    if (
        step.sequence is None
        or step.row is None
        or step.col is None
        or step.z_low_um is None
        or step.z_step_um is None
        or step.n_frames is None
        or step.purpose is None
        or step.measure is None
    ):
        raise ValueError(f"the estimator's next acquisition is incomplete: {step}")
    return Acquisition(
        index=step.sequence,
        row=step.row,
        col=step.col,
        z=ZRange(step.z_low_um, step.z_step_um, step.n_frames),
        purpose=Purpose(step.purpose),
        measure=step.measure,
        predicted_um=step.predicted_z_um,
        predicted_sigma_um=step.predicted_sigma_um,
    )


def outcome(reply: api.OutcomeOut) -> Outcome:
    """The outcome a `POST /measurements` reply describes."""
    return Outcome(
        reply.row,
        reply.col,
        reply.accepted,
        prior_um=reply.prior_um,
        prior_sigma_um=reply.prior_sigma_um,
        posterior_um=reply.posterior_um,
        posterior_sigma_um=reply.posterior_sigma_um,
        innovation_um=reply.innovation_um,
        nis=reply.nis,
        planes_um=tuple(reply.planes_um),
    )
