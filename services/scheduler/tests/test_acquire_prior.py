"""Each stack is asked for with the estimator's prediction of the tile's focus (the focus
service weighs the stack's peaks with it), within the limits the instrument's info states."""

from __future__ import annotations

import math

import pytest

from focustrack_core.domain import Acquisition, Purpose, ZRange
from focustrack_core.v1 import instrument_pb2
from focustrack_scheduler.clients import acquire_request, stage_limits
from focustrack_scheduler.plan import StageLimits


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


@pytest.mark.parametrize(
    ("z_min_um", "z_max_um", "max_frames", "limits"),
    [
        (-100.0, 100.0, 64, StageLimits(-100.0, 100.0, 64)),
        (0.0, 0.0, 0, StageLimits()),  # an instrument older than the fields sends zeros
        (5.0, -5.0, 8, StageLimits(max_frames=8)),  # no travel at all: not a stated one
        (-math.inf, 100.0, 8, StageLimits(max_frames=8)),
    ],
)
def test_the_stage_limits_are_what_the_info_states(
    z_min_um: float, z_max_um: float, max_frames: int, limits: StageLimits
) -> None:
    info = instrument_pb2.InstrumentInfo(
        z_min_um=z_min_um, z_max_um=z_max_um, max_frames=max_frames
    )
    assert stage_limits(info) == limits
