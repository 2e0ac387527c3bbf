"""The estimator's prediction in a stack's header weighs the focus service's choice between
two peaks (a fold, or dust above the section): the peak near the prediction is taken, the
other reported as the runner-up with `multi_peak`."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest

from focustrack_core.domain import FocusFlag
from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import keys
from focustrack_core.wire.codec import describe_pixels, frame_header, raw_payload
from focustrack_focus.pipeline import FocusSettings
from focustrack_focus.service import FrameAnalyser

Z_UM = np.arange(-4.0, 4.01, 0.5)
LOW_UM, HIGH_UM = -2.5, 2.5
KEY = keys.zframe_key("s1", 2, 3)


def _two_planes(render: Callable[..., np.ndarray]) -> np.ndarray:
    """A stack of two fields of cells, one in focus at LOW_UM, the other at HIGH_UM."""
    low = render(96, Z_UM, LOW_UM, 3).astype(np.float64)
    high = render(96, Z_UM, HIGH_UM, 8).astype(np.float64)
    return np.rint((low + high) / 2.0).astype(np.uint16)[..., None]


def _analyse(frames: np.ndarray, sequence: int, **prior: float):
    header = instrument_pb2.ZStackHeader(
        slide="s1", row=2, col=3, sequence=sequence, z_um=list(Z_UM), pixel_size_um=0.1,
        channel_order="L", **prior,
    )  # fmt: skip
    describe_pixels(header, frames)
    analyser = FrameAnalyser(FocusSettings(), na=0.85)
    results = [
        analyser.add(
            KEY, raw_payload(frames[i]), frame_header(header, i, frames[i]).SerializeToString()
        )
        for i in range(len(frames))
    ]
    assert results[:-1] == [None] * (len(frames) - 1)
    assert results[-1] is not None
    return results[-1]


@pytest.mark.parametrize("prior_um", [LOW_UM, HIGH_UM])
def test_the_peak_near_the_prior_is_taken(
    render: Callable[..., np.ndarray], prior_um: float
) -> None:
    frames = _two_planes(render)
    result = _analyse(frames, 1, prior_z_um=prior_um, prior_sigma_um=1.0)
    other_um = HIGH_UM if prior_um == LOW_UM else LOW_UM
    assert abs(result.best_z_um - prior_um) < 0.5
    assert abs(result.runner_up_z_um - other_um) < 0.75
    assert FocusFlag.MULTI_PEAK.proto in result.flags


def test_without_a_prior_the_curve_alone_chooses(
    render: Callable[..., np.ndarray],
) -> None:
    frames = _two_planes(render)
    plain = _analyse(frames, 2)
    assert FocusFlag.MULTI_PEAK.proto in plain.flags
    assert min(abs(plain.best_z_um - LOW_UM), abs(plain.best_z_um - HIGH_UM)) < 0.5


@pytest.mark.parametrize(
    ("z_um", "sigma_um", "field"),
    [
        (0.0, -1.0, "sigma_um"),
        (0.0, 1e-200, "sigma_um"),
        (0.0, 1e200, "sigma_um"),
        (1e300, 1, "z_um"),
    ],
)
def test_a_bad_prior_is_answered_with_an_error(
    render: Callable[..., np.ndarray], z_um: float, sigma_um: float, field: str
) -> None:
    frames = render(96, Z_UM, 0.0, 3)[..., None]
    result = _analyse(frames, 3, prior_z_um=z_um, prior_sigma_um=sigma_um)
    assert result.error.code == common_pb2.ERROR_CODE_BAD_STACK
    assert f"prior's {field}" in result.error.message
