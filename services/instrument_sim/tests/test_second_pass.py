"""The simulator moves a slide for a second pass (`--z-offset-um`): the drift the
estimator's `kf-rescan` tracks."""

from __future__ import annotations

import numpy as np

from focustrack_instrument_sim import simulated
from focustrack_instrument_sim.simulator_options import SimulatorOptions


def test_the_simulator_moves_a_slide_for_a_second_pass() -> None:
    def truth(z_offset_um: float = 0.0) -> np.ndarray:
        options = SimulatorOptions(rows=3, cols=4, width=32, height=32, z_offset_um=z_offset_um)
        microscope = simulated.microscope_from_options(options)
        return microscope.truth_um("slide-0")[0]

    assert np.allclose(truth(12.0) - truth(), 12.0)
