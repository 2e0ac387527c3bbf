"""The estimator's REST models (`focustrack_client.models`) in the domain's words, and back.

The scheduler plans with the domain's `Acquisition`, `Measurement` and
`Outcome`; the client speaks the API's models. These three functions are the
one translation between them.
"""

from __future__ import annotations

from focustrack_client import models as api
from focustrack_core.domain import Acquisition, Measurement, Outcome, Purpose, ZRange


def acquisition_of(step: api.Next) -> Acquisition | None:
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


def measurement_in(acquisition: Acquisition, measurement: Measurement) -> api.MeasurementIn:
    """The body of `POST /measurements` reporting `measurement` for `acquisition`."""
    return api.MeasurementIn(
        row=acquisition.row,
        col=acquisition.col,
        sequence=acquisition.index,
        z_um=measurement.z_um,
        sigma_um=measurement.sigma_um,
        flags=[api.FocusFlag(flag) for flag in sorted(measurement.flags)],
    )


def outcome_of(reply: api.OutcomeOut) -> Outcome:
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
