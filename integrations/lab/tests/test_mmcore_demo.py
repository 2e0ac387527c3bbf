"""The engine on Micro-Manager's demo devices (a real CMMCorePlus, DemoCamera, DStage, DXYStage)
against a real estimator: the stage's real positions, a lab's own z-stack, and a device
whose images do not change with z.

The demo camera's "Artificial Waves" move with time and dim away from z = 0, but never
blur: nothing on it goes in or out of focus, so every tile must come back flat.
"""

from __future__ import annotations

import logging
from pathlib import Path

import mm_test_adapters
import numpy as np
import pytest
import useq
from pymmcore_plus import CMMCorePlus

from focustrack_client import EstimatorClient
from focustrack_client.models import FocusFlag
from focustrack_lab.mmcore import FocusTrackEngine

SLIDE = {"strategy": "kf-2d", "dof_um": 1.0, "noise_sigma_um": 0.1, "start_sigma_um": 2.0}
#: The demo camera's frame, 512 px of 1 um at the demo config's default objective.
FOV_UM = 512.0


@pytest.fixture
def demo_core() -> CMMCorePlus:
    core = CMMCorePlus()
    adapters = mm_test_adapters.device_adapter_path()
    core.setDeviceAdapterSearchPaths([adapters])
    core.loadSystemConfiguration(str(Path(adapters) / "MMConfig_demo.cfg"))
    assert core.getPixelSizeUm() * core.getImageWidth() == FOV_UM
    return core


class Recorded:
    """Every MDA frame's event, stage position (x, y, z um) and image."""

    def __init__(self, core: CMMCorePlus) -> None:
        self.events: list[useq.MDAEvent] = []
        self.stage_um: list[tuple[float, float, float]] = []
        core.mda.events.frameReady.connect(self.keep)
        self.core = core

    def keep(self, _image: np.ndarray, event: useq.MDAEvent, _meta: object) -> None:
        self.events.append(event)
        x_um, y_um = self.core.getXYPosition()
        self.stage_um.append((x_um, y_um, self.core.getZPosition()))


@pytest.mark.slow
def test_a_device_that_never_focuses_ends_with_every_tile_flat_and_a_warning(
    estimator: EstimatorClient, demo_core: CMMCorePlus, caplog: pytest.LogCaptureFixture
) -> None:
    engine = FocusTrackEngine(demo_core, estimator, **SLIDE)
    demo_core.mda.set_engine(engine)
    recorded = Recorded(demo_core)
    grid = useq.GridRowsColumns(rows=2, columns=3)
    with caplog.at_level(logging.WARNING, logger="focustrack_lab.mmcore"):
        demo_core.mda.run(useq.MDASequence(grid_plan=grid))

    assert engine.tracker is not None and engine.summary is not None
    tiles = engine.tracker.tiles
    assert len(tiles) == len(recorded.events) == 6
    for tile, event in zip(tiles, recorded.events, strict=True):
        assert FocusFlag.FLAT in tile.flags and tile.unfocused, tile
        assert 1 <= tile.n_stacks <= 2  # the estimator's bound: one widest stack more at most
        assert event.metadata["focustrack_flags"] == sorted(str(f) for f in tile.flags)
        assert event.metadata["focustrack_z_um"] == tile.z_um
    assert sorted(engine.summary.unfocused) == sorted((t.row, t.col) for t in tiles)
    assert "6 of 6 tiles without a focus (flat: 6)" in str(engine.summary)
    assert "6 of 6 tiles without a focus" in caplog.text


@pytest.mark.slow
def test_the_estimator_slide_is_the_grid_the_stage_moves_with_overlap_and_origin(
    estimator: EstimatorClient, demo_core: CMMCorePlus
) -> None:
    engine = FocusTrackEngine(demo_core, estimator, **SLIDE)
    demo_core.mda.set_engine(engine)
    recorded = Recorded(demo_core)
    grid = useq.GridRowsColumns(rows=2, columns=3, overlap=20)
    centre = useq.Position(x=1000.0, y=-2000.0, z=0.0)
    demo_core.mda.run(useq.MDASequence(stage_positions=[centre], grid_plan=grid))

    assert engine.tracker is not None
    slide = estimator.slide(engine.tracker.slide_id).config.grid
    step_um = 0.8 * FOV_UM  # 20 % overlap: 409.6 um, not the field of view
    assert slide.pitch_um == pytest.approx(step_um)
    # Tile (0, 0): the grid's top-left position, the grid centred on the stage position.
    assert (slide.origin_x_um, slide.origin_y_um) == pytest.approx((1000.0 - step_um, -1795.2))
    for tile, (x_um, y_um, _) in zip(engine.tracker.tiles, recorded.stage_um, strict=True):
        # The stage's x grows with the column, its y shrinks with the row (useq's grid).
        expected = (slide.origin_x_um + tile.col * step_um, slide.origin_y_um - tile.row * step_um)
        assert (x_um, y_um) == pytest.approx(expected, abs=0.01)
    # The estimator takes one pitch: unequal row and column steps are refused, saying why.
    with pytest.raises(ValueError, match=r"460\.8 um between columns and 409\.6 um between rows"):
        engine.setup_sequence(
            useq.MDASequence(grid_plan=useq.GridRowsColumns(rows=2, columns=2, overlap=(10, 20)))
        )


@pytest.mark.slow
def test_a_relative_z_plan_is_a_z_stack_around_each_positions_focus(
    estimator: EstimatorClient, demo_core: CMMCorePlus
) -> None:
    engine = FocusTrackEngine(demo_core, estimator, **SLIDE)
    demo_core.mda.set_engine(engine)
    recorded = Recorded(demo_core)
    z_plan = useq.ZRangeAround(range=2.0, step=1.0)
    grid = useq.GridRowsColumns(rows=1, columns=2)
    demo_core.mda.run(useq.MDASequence(grid_plan=grid, z_plan=z_plan, axis_order="gz"))

    assert engine.tracker is not None
    tiles = engine.tracker.tiles
    assert len(recorded.events) == len(tiles) * 3
    for event, (_, _, z_um) in zip(recorded.events, recorded.stage_um, strict=True):
        tile = tiles[event.index["g"]]
        offset_um = list(z_plan)[event.index["z"]]
        assert z_um == pytest.approx(tile.z_um + offset_um, abs=1e-6)
        assert event.metadata["focustrack_z_um"] == tile.z_um
    # An absolute z plan cannot follow the focus: refused before anything moves.
    with pytest.raises(ValueError, match="absolute z plan"):
        engine.setup_sequence(
            useq.MDASequence(grid_plan=grid, z_plan=useq.ZTopBottom(top=2.0, bottom=-2.0, step=1.0))
        )
