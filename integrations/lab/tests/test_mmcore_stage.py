"""A focus stage's refusal (past its travel) reaches the lab naming the tile and the stack."""

from __future__ import annotations

import pytest
import useq

from focustrack.lab_sim import SimScope, simulated_core
from focustrack_client import EstimatorClient
from focustrack_lab.mmcore import FocusTrackEngine

#: Where the simulated stage's travel ends, um: the first stack (+/- 2 x 5 um) passes it.
TOP_UM = 3.0


def test_a_stage_limit_names_the_tile_the_z_and_the_stack(
    estimator: EstimatorClient, small_scope: SimScope
) -> None:
    """Micro-Manager's "Position out of range" came alone: no tile, no z, no stack."""
    core = simulated_core(small_scope)
    move = core.setZPosition

    def limited(z_um: float) -> None:
        if z_um > TOP_UM:
            raise RuntimeError("Position out of range")
        move(z_um)

    core.setZPosition = limited  # type: ignore[method-assign]
    grid = small_scope.microscope.slides[small_scope.slide].grid
    engine = FocusTrackEngine(
        core, estimator, strategy="kf-2d", noise_sigma_um=0.1, start_sigma_um=5.0
    )
    core.mda.set_engine(engine)
    sequence = useq.MDASequence(
        grid_plan=useq.GridRowsColumns(
            rows=grid.rows, columns=grid.cols, fov_width=grid.pitch_um, fov_height=grid.pitch_um
        )
    )
    with pytest.raises(
        RuntimeError,
        match=r"could not move to z = [\d.]+ um at tile \(0, 0\), a frame of a \d+-frame stack "
        r"from -[\d.]+ to [\d.]+ um: Position out of range",
    ) as raised:
        core.mda.run(sequence)
    assert str(raised.value.__cause__) == "Position out of range"
