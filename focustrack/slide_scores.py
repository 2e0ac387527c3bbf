"""A scan of a virtual slide scored against the instrument's truth of what lies in each tile.

The simulator's virtual slide (`--tissue-slide`) knows, per tile, the section's height,
whether the tile is empty glass, the height of the coverslip's dust in view and of a
fold's upper layer. A tissue tile is in focus where its kept frame (or one of its kept
planes) lies within half the depth of field of the section or of a fold's upper layer;
it is focused on dust where its kept frame lies nearer the dust than the section.
`focustrack bench slide` and `focustrack demo --tissue-slide` score their scans so.

A slide of separate fields (a specimen's: `--specimen`) has no contents per tile in its
truth; its bare glass comes from the simulator's specimen (`bare_glass`), and a tile with
specimen in view counts as tissue. Heights in um.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from focustrack_core.geometry import ScanGrid
from focustrack_core.timing import TimingModel
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_estimator.replay import limit_time_s
from focustrack_instrument_sim.simulated import microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions
from focustrack_scheduler import outputs
from focustrack_scheduler.record import ScanRecord


@dataclass(frozen=True)
class SlideContents:
    """The instrument's truth of a virtual slide, (rows, cols) each: the section's height
    (um), empty glass, the height of the dust in view and of a fold's upper layer (um, NaN:
    none)."""

    focus_um: np.ndarray
    empty: np.ndarray
    dust_z_um: np.ndarray
    fold_z_um: np.ndarray

    @classmethod
    def of(cls, truth: instrument_pb2.SlideTruth, empty: np.ndarray | None = None) -> SlideContents:
        """A virtual slide's contents from its truth; a slide of separate fields has none
        there, so `empty` (rows, cols) says which of its tiles are bare glass (ValueError
        without it): no dust, no folds."""
        shape = (truth.rows, truth.cols)
        focus_um = np.array(truth.best_focus_um).reshape(shape)
        if len(truth.empty) != truth.rows * truth.cols:
            if empty is None:
                raise ValueError(f"slide {truth.slide!r} is no virtual slide: no contents per tile")
            none_um = np.full(shape, np.nan)
            return cls(focus_um, np.asarray(empty, dtype=bool).reshape(shape), none_um, none_um)
        return cls(
            focus_um,
            np.array(truth.empty, dtype=bool).reshape(shape),
            np.array(truth.dust_z_um).reshape(shape),
            np.array(truth.fold_z_um).reshape(shape),
        )


def tile_scores(
    contents: SlideContents,
    kept_z_um: np.ndarray,
    planes_um: dict[tuple[int, int], list[float]],
    frames: np.ndarray,
    dof_um: float,
    risk: np.ndarray,
) -> dict[str, Any]:
    """Per slide: tissue tiles in focus, tiles focused on dust, frames on empty tiles, the
    tissue tiles' summed focus error (um: the kept frame's distance to the section or a
    fold's upper layer, whichever is nearer; over the tiles with a kept frame), and the
    tissue tiles' summed out-of-focus risk as the estimator stated it (over those it states
    one for): the misses it expects, to set beside those there were.

    kept_z_um (rows, cols): the z of each tile's image (NaN: none); planes_um: the z of the
    frames a tile keeps besides; frames (rows, cols): frames acquired per tile; risk (rows,
    cols): the estimator's out-of-focus risk of each tile's image (NaN: none stated).
    """
    in_focus = np.abs(kept_z_um - contents.focus_um) <= dof_um / 2.0
    # a fold is section too: a tile imaged at its upper layer is in focus as well
    in_focus |= np.abs(kept_z_um - contents.fold_z_um) <= dof_um / 2.0
    for (row, col), z_um in planes_um.items():
        in_focus[row, col] |= bool(
            np.any(np.abs(np.array(z_um) - contents.focus_um[row, col]) <= dof_um / 2.0)
        )
    tissue = ~contents.empty
    has_dust = np.isfinite(contents.dust_z_um)
    to_dust = np.abs(kept_z_um - np.where(has_dust, contents.dust_z_um, np.inf))
    on_dust = has_dust & (to_dust < np.abs(kept_z_um - contents.focus_um))
    error_um = np.fmin(
        np.abs(kept_z_um - contents.focus_um), np.abs(kept_z_um - contents.fold_z_um)
    )
    imaged = tissue & np.isfinite(error_um)
    stated = tissue & np.isfinite(risk)
    return {
        "tissue_in_focus": int(np.sum(in_focus & tissue)),
        "tissue_tiles": int(tissue.sum()),
        "on_dust": int(on_dust.sum()),
        "dust_tiles": int(has_dust.sum()),
        "empty_tiles": int(contents.empty.sum()),
        "empty_frames": int(frames[contents.empty].sum()),
        "tissue_imaged": int(imaged.sum()),
        "tissue_error_um": float(error_um[imaged].sum()),
        "tissue_risk_stated": int(stated.sum()),
        "tissue_risk_sum": float(risk[stated].sum()),
    }


def bare_glass(options: SimulatorOptions, slide: str) -> np.ndarray:
    """(rows, cols) bool: the tiles of the simulator's slide `slide` (a slide of separate
    fields, as `options` describe it) with no specimen in view (`specimen_in_view`: no cell
    of a phase specimen, plasma alone on a stained smear)."""
    scope = microscope_from_options(options)
    try:
        return np.array([
            [not scope.specimen_in_view(slide, row, col) for col in range(options.cols)]
            for row in range(options.rows)
        ])  # fmt: skip
    finally:
        scope.close()


def scored_scan(
    session: zenoh.Session,
    instrument: str,
    slide: str,
    scan_dir: Path,
    report: dict[str, Any],
    empty: np.ndarray | None = None,
) -> dict[str, Any]:
    """The scan in `scan_dir` (its `report`) scored against the truth of `instrument`'s
    virtual slide `slide`, asked over `session`: `tile_scores` plus frames, tiles, scan and
    limit time and the seam error. A slide of separate fields has no contents per tile:
    `empty` (rows, cols) says which of its tiles are bare glass (`bare_glass`; ValueError
    without it)."""
    truth = rpc.call(
        session,
        keys.truth_key(instrument, slide),
        instrument_pb2.AcquireRequest(),
        instrument_pb2.SlideTruth,
        10.0,
    )
    info = rpc.call(
        session,
        keys.info_key(instrument),
        instrument_pb2.AcquireRequest(),
        instrument_pb2.InstrumentInfo,
        10.0,
    )
    layout = info.slides[0]
    grid = ScanGrid(
        layout.rows, layout.cols, layout.pitch_um, layout.origin_x_um, layout.origin_y_um
    )
    contents = SlideContents.of(truth, empty)
    record = ScanRecord(scan_dir)
    try:
        tally = record.tally
        frames = tally.images_per_tile(grid)
        risk = np.load(scan_dir / outputs.FOCUS_MAP_NPY)["out_of_focus_risk"]
        part = tile_scores(
            contents, tally.z_kept_um(grid), tally.planes, frames, info.depth_of_field_um, risk
        )
    finally:
        record.close()
    return part | {
        "frames": int(frames.sum()),
        "tiles": grid.n_tiles,
        "scan_time_s": report["scan_time_s"],
        "limit_time_s": limit_time_s(grid, TimingModel()),
        "seam_error_px": (
            float("nan") if report.get("seam_error_px") is None else report["seam_error_px"]
        ),
    }
