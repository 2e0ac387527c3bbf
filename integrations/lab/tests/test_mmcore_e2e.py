"""A 6x6 useq MDA grid on a real UniMMCore, focused by FocusTrack against a real estimator."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import useq

from focustrack.lab_sim import SimScope, simulated_core
from focustrack_client import EstimatorClient
from focustrack_client.models import SlideCreate
from focustrack_core.fusion import fuse_planes
from focustrack_focus.peak import PeakSettings
from focustrack_focus.pipeline import FocusSettings
from focustrack_lab.mmcore import FocusTrackEngine
from focustrack_lab.tracker import TileOrderError

START_SIGMA_UM = 5.0


@pytest.mark.slow
def test_an_mda_grid_is_imaged_in_focus_with_fewer_frames_than_autofocus_per_position(
    estimator: EstimatorClient, scope: SimScope
) -> None:
    dof_um = scope.microscope.spec.optics.depth_of_field_um
    slide = scope.microscope.slides[scope.slide].grid
    rows, cols, pitch_um = slide.rows, slide.cols, slide.pitch_um
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

    grid = useq.GridRowsColumns(rows=rows, columns=cols, fov_width=pitch_um, fov_height=pitch_um)
    core.mda.run(useq.MDASequence(grid_plan=grid))

    assert engine.tracker is not None
    tiles = engine.tracker.tiles
    assert [(tile.row, tile.col) for tile in tiles] == [(t.row, t.col) for t in slide.serpentine]
    assert len(kept) == rows * cols
    truth_um = scope.truth_um()
    for (_, z_um, image), tile in zip(kept, tiles, strict=True):
        assert z_um == tile.z_um
        assert image.shape == scope.microscope.spec.shape and image.std() > 0
        assert abs(z_um - truth_um[tile.row, tile.col]) <= dof_um / 2, (
            tile,
            truth_um[tile.row, tile.col],
        )
    # Autofocus on every position would take the first position's stack (the prior's
    # whole width) at each of them; FocusTrack narrows the stacks as it learns.
    autofocus_frames = tiles[0].n_frames * rows * cols
    assert engine.tracker.n_frames == scope.n_frames - len(kept)
    assert engine.tracker.n_frames < autofocus_frames / 2
    frames_per_position = engine.tracker.n_frames / len(kept)
    print(f"FocusTrack {frames_per_position:.1f} frames/position, autofocus {tiles[0].n_frames}")

    # The scan is done: another visit is refused, naming why.
    with pytest.raises(TileOrderError, match="the scan is done"):
        engine.tracker.focus(0, 0, lambda z_um: np.zeros((len(z_um), 8, 8)))


class RecordingEngine(FocusTrackEngine):
    """Keeps every stack it snaps (z um, frames), to check what the MDA frames are made of."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.snapped: list[tuple[tuple[float, ...], np.ndarray]] = []

    def _snap_stack(self, z_um: np.ndarray) -> np.ndarray:
        frames = super()._snap_stack(z_um)
        self.snapped.append((tuple(float(z) for z in z_um), frames))
        return frames


@pytest.mark.slow
def test_a_position_too_unsure_for_one_image_gets_the_fusion_of_its_planes(
    estimator: EstimatorClient, scope: SimScope, scope_slide: Callable[[str, float], SlideCreate]
) -> None:
    slide = scope_slide("kf-2d-lean", 1.5)
    core = simulated_core(scope)
    # A measure whose peak strays 1.5 um from the focus (as the thesis' noise): its sigma says so.
    noisy = FocusSettings(peak=PeakSettings(systematic_sigma_um=1.5))
    engine = RecordingEngine(
        core, estimator, focus=noisy, **slide.model_dump(exclude={"grid"}, exclude_unset=True)
    )
    core.mda.set_engine(engine)
    kept: dict[int, tuple[np.ndarray, useq.MDAEvent]] = {}

    @core.mda.events.frameReady.connect
    def keep(image: np.ndarray, event: useq.MDAEvent, _meta: object) -> None:
        kept[event.index["g"]] = (image, event)

    grid = slide.grid
    core.mda.run(
        useq.MDASequence(
            grid_plan=useq.GridRowsColumns(
                rows=grid.rows, columns=grid.cols, fov_width=grid.pitch_um, fov_height=grid.pitch_um
            )
        )
    )

    assert engine.tracker is not None
    tiles = engine.tracker.tiles
    assert len(kept) == len(tiles) == grid.rows * grid.cols  # one MDA frame per position
    with_planes = [(g, tile) for g, tile in enumerate(tiles) if tile.planes_um]
    assert with_planes, [tile.sigma_um for tile in tiles]
    stacks = dict(engine.snapped)  # the planes of a position: the stack snapped at them
    for g, tile in with_planes:
        image, event = kept[g]
        assert event.metadata["focustrack_planes_um"] == list(tile.planes_um)
        np.testing.assert_array_equal(image, fuse_planes(stacks[tile.planes_um]))
    for g, tile in enumerate(tiles):
        if not tile.planes_um:
            assert "focustrack_planes_um" not in kept[g][1].metadata
    # Every snap is a stack the estimator asked for, a position's planes or its one image.
    n_planes = sum(len(tile.planes_um) for _, tile in with_planes)
    n_single = len(tiles) - len(with_planes)
    assert scope.n_frames == engine.tracker.n_frames + n_planes + n_single
