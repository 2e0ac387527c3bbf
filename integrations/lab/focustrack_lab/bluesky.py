"""FocusTrack as a Bluesky plan: a grid of tiles, each imaged at the z the estimator chooses.

    RE(focustrack_grid(camera, x, y, z, tracker, rows=6, cols=6, pitch_um=200.0))

A plan in Bluesky's sense: a generator of messages that the RunEngine executes,
one run. For every tile in the estimator's serpentine order it moves the x and
y motors to the tile, and while the estimator asks for stacks (`FocusTracker.tile`)
moves z through each and reads the camera (stream "focus_stack": the through-focus
images with their z). It then moves z to the tile's best focus and reads the camera,
the motors and the tile's focus (stream "primary"): one event per tile, with
`focustrack_row`, `focustrack_col`, `focustrack_z_um`, `focustrack_sigma_um`,
`focustrack_frames`, `focustrack_flags` and `focustrack_planes`, so Bluesky's callbacks
(LiveTable, databroker, tiled) see the focus map as it is made.

Where one image of a tile is too unsure to be in focus (a slide with a stated risk, as
strategy kf-2d-lean keeps: `TileFocus.planes_um`), the plan first reads the camera at
each of the tile's planes (stream "focustrack_planes", with the tile's focus, so each
event names its tile): one of them is in focus, and their fusion
(`focustrack_core.fusion.fuse_planes`) is the tile's image. `focustrack_planes` in the
primary event counts them (0: the primary image is the tile's).

Tile (row, col) sits at x = x0_um + col * pitch_um, y = y0_um - row * pitch_um
(useq's grids put row 0 at the top, as here). Motor positions are in um.
"""

from __future__ import annotations

from collections.abc import Generator, Mapping
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.utils import Msg
from ophyd import Component, Device, Signal

from focustrack_core.geometry import ScanGrid
from focustrack_lab.tracker import FocusTracker, TileFocus

Plan = Generator[Msg, Any, Any]

#: The stream of through-focus images (the primary stream holds one event per tile).
STACK_STREAM = "focus_stack"
#: The stream of the images kept at a tile's planes, where one image is too unsure.
PLANES_STREAM = "focustrack_planes"


class TileFocusReading(Device):
    """A tile's focus as ophyd signals, read into each primary event (heights in um)."""

    row = Component(Signal, value=-1, kind="hinted")
    col = Component(Signal, value=-1, kind="hinted")
    z_um = Component(Signal, value=float("nan"), kind="hinted")
    sigma_um = Component(Signal, value=float("nan"), kind="hinted")
    frames = Component(Signal, value=0, kind="normal")
    flags = Component(Signal, value="", kind="normal")
    planes = Component(Signal, value=0, kind="normal")  # images kept at planes_um

    def show(self, tile: TileFocus) -> Plan:
        """Set the signals to `tile`'s values (a plan stub)."""
        flags = "" if tile.last is None else ",".join(sorted(str(f) for f in tile.last.flags))
        sigma_um = float("nan") if tile.sigma_um is None else tile.sigma_um
        yield from bps.mv(
            self.row,
            tile.row,
            self.col,
            tile.col,
            self.z_um,
            tile.z_um,
            self.sigma_um,
            sigma_um,
            self.frames,
            tile.n_frames,
            self.flags,
            flags,
            self.planes,
            len(tile.planes_um),
        )


def focustrack_grid(
    camera: Any,
    x: Any,
    y: Any,
    z: Any,
    tracker: FocusTracker,
    *,
    rows: int,
    cols: int,
    pitch_um: float,
    x0_um: float = 0.0,
    y0_um: float = 0.0,
    md: Mapping[str, Any] | None = None,
) -> Plan:
    """Image a rows x cols grid of tiles, each at FocusTrack's best z (module docstring).

    camera: a triggerable, readable device whose reading is the image (H, W[, C]);
    x, y, z: movable motors in um. Returns the TileFocus of every tile, in scan order.
    """
    reading = TileFocusReading(name="focustrack")
    metadata = {
        "plan_name": "focustrack_grid",
        "focustrack_slide_id": tracker.slide_id,
        "shape": [rows, cols],
        "pitch_um": pitch_um,
        **(md or {}),
    }

    @bpp.run_decorator(md=metadata)
    def run() -> Plan:
        for tile in ScanGrid(rows, cols).serpentine:
            yield from bps.mv(x, x0_um + tile.col * pitch_um, y, y0_um - tile.row * pitch_um)
            focus = yield from _focus_tile(camera, z, tracker, tile.row, tile.col)
            yield from reading.show(focus)
            for plane_um in focus.planes_um:
                yield from bps.mv(z, plane_um)
                yield from bps.trigger_and_read([camera, z, reading], name=PLANES_STREAM)
            yield from bps.mv(z, focus.z_um)
            yield from bps.trigger_and_read([camera, x, y, z, reading])
        return tracker.tiles[-rows * cols :]

    return (yield from run())


def _focus_tile(camera: Any, z: Any, tracker: FocusTracker, row: int, col: int) -> Plan:
    """The stacks the estimator asks of tile (row, col), read through the RunEngine."""
    steps = tracker.tile(row, col)
    try:
        z_um = next(steps)
        while True:
            frames = []
            for z_frame_um in z_um:
                yield from bps.mv(z, float(z_frame_um))
                readings = yield from bps.trigger_and_read([camera, z], name=STACK_STREAM)
                frames.append(readings[camera.name]["value"])
            z_um = steps.send(np.stack(frames))
    except StopIteration as done:
        return done.value
