"""A 6x6 useq MDA grid on a real UniMMCore, focused by FocusTrack against a real estimator."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import useq

from focustrack.mmcore_sim import SimScope, simulated_core
from focustrack_client import EstimatorClient
from focustrack_core.wire.session import free_port
from focustrack_estimator.service import spawn
from focustrack_instrument_sim.microscope import Microscope, MicroscopeSpec, slides_from_seed
from focustrack_instrument_sim.surfaces import SurfaceSpec
from focustrack_lab.mmcore import FocusTrackEngine
from focustrack_lab.tracker import TileOrderError

ROWS = COLS = 6
PITCH_UM = 200.0
START_SIGMA_UM = 5.0


@pytest.fixture
def estimator(tmp_path: Path) -> Iterator[EstimatorClient]:
    port = free_port()
    process = spawn(tmp_path / "estimator.sqlite", port, timeout_s=120)
    try:
        with EstimatorClient(f"http://127.0.0.1:{port}") as client:
            yield client
    finally:
        process.terminate()
        process.wait(timeout=10)


@pytest.mark.slow
def test_an_mda_grid_is_imaged_in_focus_with_fewer_frames_than_autofocus_per_position(
    estimator: EstimatorClient,
) -> None:
    slides = slides_from_seed(7, 1, SurfaceSpec(ROWS, COLS), pitch_um=PITCH_UM)
    scope = SimScope(Microscope(slides, MicroscopeSpec(height=256, width=256)), "slide-0")
    dof_um = scope.microscope.spec.optics.depth_of_field_um
    core = simulated_core(scope)
    engine = FocusTrackEngine(
        core,
        estimator,
        strategy="kf-2d",
        dof_um=dof_um,
        noise_sigma_um=0.1,
        start_sigma_um=START_SIGMA_UM,
    )
    core.mda.set_engine(engine)
    kept: list[tuple[int, float, np.ndarray]] = []  # (grid index, z um, image) per MDA frame

    @core.mda.events.frameReady.connect
    def keep(image: np.ndarray, event: useq.MDAEvent, _meta: object) -> None:
        kept.append((event.index["g"], scope.z_um, image))

    grid = useq.GridRowsColumns(rows=ROWS, columns=COLS, fov_width=PITCH_UM, fov_height=PITCH_UM)
    core.mda.run(useq.MDASequence(grid_plan=grid))

    assert engine.tracker is not None
    tiles = engine.tracker.tiles
    assert [(tile.row, tile.col) for tile in tiles] == [
        (row, col)
        for row in range(ROWS)
        for col in (range(COLS) if row % 2 == 0 else range(COLS)[::-1])
    ]
    assert len(kept) == ROWS * COLS
    truth_um = scope.truth_um()
    for (_, z_um, image), tile in zip(kept, tiles, strict=True):
        assert z_um == tile.z_um
        assert image.shape == (256, 256) and image.std() > 0
        assert abs(z_um - truth_um[tile.row, tile.col]) <= dof_um / 2, (
            tile,
            truth_um[tile.row, tile.col],
        )
    # Autofocus on every position would take the first position's stack (the prior's
    # whole width) at each of them; FocusTrack narrows the stacks as it learns.
    autofocus_frames = tiles[0].n_frames * ROWS * COLS
    assert engine.tracker.n_frames == scope.n_frames - len(kept)
    assert engine.tracker.n_frames < autofocus_frames / 2
    frames_per_position = engine.tracker.n_frames / len(kept)
    print(f"FocusTrack {frames_per_position:.1f} frames/position, autofocus {tiles[0].n_frames}")

    # The scan is done: another visit is refused, naming why.
    with pytest.raises(TileOrderError, match="the scan is done"):
        engine.tracker.focus(0, 0, lambda z_um: np.zeros((len(z_um), 8, 8)))
    # FocusTrack chooses z: a sequence with a z plan is refused before anything moves.
    with pytest.raises(ValueError, match="drop the z_plan"):
        engine.setup_sequence(
            useq.MDASequence(grid_plan=grid, z_plan=useq.ZRangeAround(range=4, step=1))
        )
