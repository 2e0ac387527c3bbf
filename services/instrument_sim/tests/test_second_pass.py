"""The simulator moves a slide for a second pass (`--z-offset-um`): the drift the
estimator's `kf-rescan` tracks."""

from __future__ import annotations

import argparse

import numpy as np

from focustrack_instrument_sim import service


def test_the_simulator_moves_a_slide_for_a_second_pass() -> None:
    def truth(*extra: str) -> np.ndarray:
        parser = argparse.ArgumentParser()
        service.add_arguments(parser)
        args = parser.parse_args(
            ["--rows", "3", "--cols", "4", "--width", "32", "--height", "32", *extra]
        )
        microscope = service.microscope_from_args(args)
        return microscope.truth_um("slide-0")[0]

    assert np.allclose(truth("--z-offset-um", "12") - truth(), 12.0)
