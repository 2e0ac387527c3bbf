"""The focus service's command line -> its `FocusSettings`."""

from __future__ import annotations

import argparse

from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.service import add_arguments, settings_from_args


def parse(*argv: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser()
    add_arguments(parser)
    return parser.parse_args(list(argv))


def test_the_metric_constants_default_to_none_learnt() -> None:
    peak = settings_from_args(parse()).peak
    assert peak.min_relative_noise == 0.0 and peak.systematic_sigma_um == 0.0


def test_a_metric_calibrated_on_the_microscope_reaches_the_peak_settings() -> None:
    args = parse(
        "--metric", "jpeg_size", "--focus-mode", "valley",
        "--min-relative-noise", "0.001", "--systematic-sigma-um", "0.15",
    )  # fmt: skip
    settings = settings_from_args(args)
    assert settings.metric == "jpeg_size"
    assert settings.peak == PeakSettings(
        mode=PeakMode.VALLEY, min_relative_noise=0.001, systematic_sigma_um=0.15
    )
