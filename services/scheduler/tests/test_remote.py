"""The estimator's REST models and the scheduler's domain objects translate both ways."""

from __future__ import annotations

import pytest

from focustrack_client import models as api
from focustrack_core.domain import FocusFlag, Measurement, Purpose, ZRange
from focustrack_scheduler.remote import acquisition_of, measurement_in, outcome_of


def test_a_next_reply_is_an_acquisition_and_done_is_none() -> None:
    reply = api.Next(
        done=False, sequence=4, row=1, col=2, z_low_um=-1.0, z_high_um=1.0, z_step_um=0.5,
        n_frames=5, predicted_z_um=0.1, predicted_sigma_um=0.3, purpose=api.Purpose.RETRY,
        measure=True,
    )  # fmt: skip
    acquisition = acquisition_of(reply)
    assert acquisition is not None
    assert (acquisition.index, acquisition.row, acquisition.col) == (4, 1, 2)
    assert acquisition.z == ZRange(-1.0, 0.5, 5) and acquisition.purpose is Purpose.RETRY
    assert acquisition_of(api.Next(done=True)) is None
    with pytest.raises(ValueError, match="incomplete"):
        acquisition_of(api.Next(done=False, sequence=1))


def test_a_measurement_is_the_body_the_estimator_validates() -> None:
    acquisition = acquisition_of(
        api.Next(
            done=False, sequence=0, row=0, col=3, z_low_um=0.0, z_step_um=0.5, n_frames=3,
            purpose=api.Purpose.SCAN, measure=True,
        )
    )  # fmt: skip
    assert acquisition is not None
    flags = frozenset({FocusFlag.MULTI_PEAK, FocusFlag.EDGE_LOW})
    body = measurement_in(acquisition, Measurement(None, None, flags))
    assert body.flags == [api.FocusFlag.EDGE_LOW, api.FocusFlag.MULTI_PEAK]
    assert (body.row, body.col, body.sequence, body.z_um) == (0, 3, 0, None)
    reply = api.OutcomeOut(
        sequence=0, row=0, col=3, accepted=False, prior_um=1.0, prior_sigma_um=2.0,
        posterior_um=None, posterior_sigma_um=None, innovation_um=None, nis=None,
    )  # fmt: skip
    outcome = outcome_of(reply)
    assert (outcome.row, outcome.col, outcome.accepted, outcome.prior_um) == (0, 3, False, 1.0)
