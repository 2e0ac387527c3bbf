"""Each stack is asked for with the estimator's prediction of the tile's focus: the focus
service weighs the stack's peaks with it."""

from __future__ import annotations

import math

import pytest

from focustrack_core.domain import Acquisition, Purpose, ZRange
from focustrack_scheduler.clients import acquire_request


def _acquisition(predicted_um: float | None, sigma_um: float | None) -> Acquisition:
    return Acquisition(7, 1, 2, ZRange(-1.0, 0.5, 5), Purpose.SCAN, True, predicted_um, sigma_um)


def test_the_prediction_travels_with_the_request() -> None:
    request = acquire_request("slide-0", _acquisition(0.3, 0.8), b"n" * 16)
    assert request.HasField("prior_z_um") and request.HasField("prior_sigma_um")
    assert (request.prior_z_um, request.prior_sigma_um) == (0.3, 0.8)
    assert (request.sequence, request.n_frames) == (7, 5)


@pytest.mark.parametrize(
    ("z_um", "sigma_um"), [(None, None), (0.3, None), (math.inf, 1.0), (0.3, 0.0), (0.3, math.nan)]
)
def test_no_usable_prediction_no_prior(z_um: float | None, sigma_um: float | None) -> None:
    request = acquire_request("slide-0", _acquisition(z_um, sigma_um), b"n" * 16)
    assert not request.HasField("prior_z_um") and not request.HasField("prior_sigma_um")
