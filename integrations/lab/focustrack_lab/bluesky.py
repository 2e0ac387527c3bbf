"""FocusTrack as a Bluesky plan: a grid of tiles, each imaged at the z the estimator chooses.

    RE(focustrack_grid(camera, x, y, z, tracker, rows=6, cols=6, pitch_um=200.0))

A plan in Bluesky's sense: a generator of messages that the RunEngine executes,
one run. For every tile in the estimator's serpentine order it moves the x and
y motors to the tile, and while the estimator asks for stacks (`FocusTracker.tile`)
moves z through each and reads the camera (stream "focus_stack": the through-focus
images with their z, each event naming its tile, stack and frame). It then moves z to
the tile's best focus and reads the camera, the motors and the tile's focus (stream
"primary"): one event per tile, with `focustrack_row`, `focustrack_col`,
`focustrack_z_um`, `focustrack_sigma_um`, `focustrack_frames`, `focustrack_flags` and
`focustrack_planes`, so Bluesky's callbacks (LiveTable, databroker, tiled) see the focus
map as it is made. Last, the estimator's final maps, (rows, cols) arrays, make the one
event of stream "focustrack_map".

Where one image of a tile is too unsure to be in focus (a slide with a stated risk, as
strategy kf-2d-lean keeps: `TileFocus.planes_um`), the plan first reads the camera at
each of the tile's planes (stream "focustrack_planes", with the tile's focus, so each
event names its tile): one of them is in focus, and their fusion
(`focustrack_core.fusion.fuse_planes`) is the tile's image. `focustrack_planes` in the
primary event counts them (0: the primary image is the tile's).

Tile (row, col) sits at x = x0_um + col * pitch_um, y = y0_um - row * pitch_um
(useq's grids put row 0 at the top, as here). Motor positions are in um. Every array
of tiles is (rows, cols) with row 0 first, as the y axis of the scheduler's OME-Zarr
mosaic (row 0 at the top), and the start document describes the grid as
`bluesky.plans.grid_scan` does (motors y then x, their extents from row 0 and column 0),
so a viewer draws row 0 at the top too.

Every data key FocusTrack adds states its `units` (None for indices and labels) and
`dtype_numpy`; arrays their `shape` and `dims`.
"""

from __future__ import annotations

import math
from collections.abc import Generator, Mapping, Sequence
from typing import Any

import bluesky.plan_stubs as bps
import bluesky.preprocessors as bpp
import numpy as np
from bluesky.utils import Msg
from ophyd import Component, Device, Signal

from focustrack_core.domain import FocusFlag
from focustrack_core.geometry import ScanGrid, Tile
from focustrack_lab.tracker import FocusTracker, TileFocus, check_slide

Plan = Generator[Msg, Any, Any]

#: The stream of through-focus images (the primary stream holds one event per tile).
STACK_STREAM = "focus_stack"
#: The stream of the images kept at a tile's planes, where one image is too unsure.
PLANES_STREAM = "focustrack_planes"
#: The stream of the estimator's final maps: one event, after the last tile.
MAP_STREAM = "focustrack_map"

#: Heights and positions (event-model's `units`).
UM = "um"
#: Wide enough for the longest flag's name (numpy's fixed-width unicode): `TileFocus.last`'s.
FLAG_DTYPE = np.dtype(f"<U{max(len(flag.value) for flag in FocusFlag)}")


def with_data_key(
    description: dict[str, dict[str, Any]],
    units: str | None,
    dtype: np.dtype[Any],
    shape: Sequence[int | None] = (),
    dims: Sequence[str] = (),
) -> dict[str, dict[str, Any]]:
    """`description` (an ophyd `describe()`) with every key stating `units`, the numpy
    `dtype` (event-model's `dtype_numpy`, and the JSON `dtype` it implies), `shape`
    (None: a side of any length) and, for arrays, the names of their `dims`.

    The JSON dtype is set from the numpy one because ophyd infers it from the value at hand:
    a motor at integer 0 (SynAxis before its first move) says "integer", and a reader that
    trusts it truncates every later um.
    """
    described = {}
    for key, data_key in description.items():
        described[key] = {
            **data_key,
            "dtype": _json_dtype(dtype, shape),
            "dtype_numpy": dtype.str,
            "shape": list(shape),
            "units": units,
        }
        if dims:
            described[key]["dims"] = list(dims)
    return described


def _json_dtype(dtype: np.dtype[Any], shape: Sequence[int | None]) -> str:
    """event-model's JSON `dtype` of values of numpy `dtype` and `shape`."""
    if shape:
        return "array"
    return {"b": "boolean", "i": "integer", "u": "integer", "U": "string"}.get(dtype.kind, "number")


class DescribedSignal(Signal):
    """A soft signal whose data key states its units, numpy dtype, shape and dims
    (`with_data_key`)."""

    def __init__(
        self,
        *args: Any,
        units: str | None,
        dtype_numpy: str,
        shape: Sequence[int | None] = (),
        dims: Sequence[str] = (),
        **kwargs: Any,
    ) -> None:
        super().__init__(*args, **kwargs)
        self.units = units
        self.dtype_numpy = np.dtype(dtype_numpy)
        self.data_shape = tuple(shape)
        self.dims = tuple(dims)

    def describe(self) -> dict[str, dict[str, Any]]:
        return with_data_key(
            super().describe(), self.units, self.dtype_numpy, self.data_shape, self.dims
        )


def _field(
    value: Any,
    units: str | None,
    dtype_numpy: str,
    kind: str = "normal",
    shape: Sequence[int | None] = (),
    dims: Sequence[str] = (),
) -> Component:
    """A `DescribedSignal` component of a device."""
    return Component(
        DescribedSignal,
        value=value,
        units=units,
        dtype_numpy=dtype_numpy,
        shape=shape,
        dims=dims,
        kind=kind,
    )


class TileFocusReading(Device):
    """A tile's focus as ophyd signals, read into each primary event (heights in um).

    `stack`, `stack_frame` and `sequence` (the estimator's sequence number of the
    acquisition) number the focus_stack events only (kind "omitted": they are read one by
    one there, never with the device).
    """

    row = _field(-1, None, "<i8", "hinted")
    col = _field(-1, None, "<i8", "hinted")
    z_um = _field(float("nan"), UM, "<f8", "hinted")
    sigma_um = _field(float("nan"), UM, "<f8", "hinted")
    frames = _field(0, None, "<i8")
    # as many as the tile's flags: a side of any length
    flags = _field([], None, FLAG_DTYPE.str, shape=[None], dims=["flag"])
    planes = _field(0, None, "<i8")  # images kept at planes_um
    stack = _field(-1, None, "<i8", "omitted")
    stack_frame = _field(-1, None, "<i8", "omitted")
    sequence = _field(-1, None, "<i8", "omitted")

    def show(self, tile: TileFocus) -> Plan:
        """Set the signals to `tile`'s values (a plan stub)."""
        flags = [] if tile.last is None else sorted(str(flag) for flag in tile.last.flags)
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


#: The estimator's maps in the focustrack_map event, as `focustrack_<layer>` (um).
MAP_LAYERS = ("posterior_um", "posterior_sigma_um", "smoothed_um", "smoothed_sigma_um")


def focus_map_signals(rows: int, cols: int) -> list[DescribedSignal]:
    """A signal per layer of `MAP_LAYERS`: (rows, cols) float64 in um, row 0 first, NaN
    where the estimator has no value (all NaN for a strategy that smooths none).

    Their values are nested lists (rows of cols), not numpy arrays: tiled's writer
    (`bluesky.callbacks.tiled_writer`) stores event data with pyarrow, which takes nested
    lists but no 2-D array.
    """
    return [
        DescribedSignal(
            name=f"focustrack_{layer}",
            value=np.full((rows, cols), np.nan).tolist(),
            units=UM,
            dtype_numpy="<f8",
            shape=(rows, cols),
            dims=("row", "col"),
        )
        for layer in MAP_LAYERS
    ]


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
    ValueError, before any message, when the tracker's slide at the estimator has another
    grid (rows, cols, pitch) than the plan's: its map would be of another slide, and the
    plan would stop at the first tile past the smaller grid. TileOrderError, before any
    message, when the slide asks for what the tracker cannot take (`check_slide`).
    ValueError, before any message, when the camera's description shows no one reading to
    take as its image (`_image_key`).
    """
    config = tracker.estimator.slide(tracker.slide_id).config
    check_slide(config)
    grid = config.grid
    if (grid.rows, grid.cols) != (rows, cols) or not math.isclose(grid.pitch_um, pitch_um):
        raise ValueError(
            f"the plan's grid is {rows}x{cols} tiles {pitch_um:g} um apart, the estimator's "
            f"slide {tracker.slide_id} {grid.rows}x{grid.cols} tiles {grid.pitch_um:g} um "
            "apart: make the slide with the plan's grid"
        )
    # Found from the camera's description now, so that a camera without one image fails
    # before the run opens and the motors move; None: its reading says (a camera that
    # declares no shapes).
    described = _described_shapes(camera)
    image_key = _image_key(camera, described, final=False) or frozenset(described)
    reading = TileFocusReading(name="focustrack")
    maps = focus_map_signals(rows, cols)
    metadata: dict[str, Any] = {
        "plan_name": "focustrack_grid",
        "focustrack_slide_id": tracker.slide_id,
        "detectors": [camera.name],
        # As bluesky.plans.grid_scan describes a grid: the slow motor first, each motor's
        # (start, stop) from row 0 and column 0, the fast one snaking.
        "motors": [y.name, x.name],
        "shape": [rows, cols],
        "extents": [
            [y0_um, y0_um - (rows - 1) * pitch_um],
            [x0_um, x0_um + (cols - 1) * pitch_um],
        ],
        "snaking": [False, True],
        "num_points": rows * cols,
        "pitch_um": pitch_um,
        **(md or {}),
    }
    metadata["hints"] = {
        "gridding": "rectilinear",
        "dimensions": [(_fields(y), "primary"), (_fields(x), "primary")],
        **metadata.get("hints", {}),
    }

    @bpp.run_decorator(md=metadata)
    def run() -> Plan:
        for tile in _tiles_left(tracker, rows, cols):
            yield from bps.mv(x, x0_um + tile.col * pitch_um, y, y0_um - tile.row * pitch_um)
            yield from bps.mv(reading.row, tile.row, reading.col, tile.col)
            focus = yield from _focus_tile(camera, z, tracker, reading, image_key)
            yield from reading.show(focus)
            for plane_um in focus.planes_um:
                yield from bps.mv(z, plane_um)
                yield from bps.trigger_and_read([camera, z, reading], name=PLANES_STREAM)
            yield from bps.mv(z, focus.z_um)
            yield from bps.trigger_and_read([camera, x, y, z, reading])
        yield from _read_focus_map(tracker, maps)
        return tracker.tiles[-rows * cols :]

    return (yield from run())


def _tiles_left(tracker: FocusTracker, rows: int, cols: int) -> tuple[Tile, ...]:
    """The serpentine's tiles from the one the estimator expects next: a plan run again on
    a slide an aborted run left part-scanned picks up where it stopped (the tracker resumes
    a tile cut short), where it once moved to tile (0, 0) and stopped at a TileOrderError.
    None where the scan is done (the plan then reads the map alone)."""
    pending = tracker.estimator.next(tracker.slide_id)
    tiles = ScanGrid(rows, cols).serpentine
    if pending.done:
        return ()
    first = next(i for i, t in enumerate(tiles) if (t.row, t.col) == (pending.row, pending.col))
    return tiles[first:]


def _fields(motor: Any) -> list[str]:
    """The data keys a motor hints (its name where it hints none), as grid_scan's dimensions."""
    return list(getattr(motor, "hints", {}).get("fields", [motor.name]))


def _described_shapes(camera: Any) -> dict[str, tuple[int, ...]]:
    """The shape of every data key the camera describes (its `describe()`)."""
    return {key: tuple(entry.get("shape") or ()) for key, entry in camera.describe().items()}


def _image_key(camera: Any, shapes: Mapping[str, Sequence[int]], *, final: bool) -> str | None:
    """The key of the camera's image among its data keys (key -> shape): its name where it
    has that key (an ophyd Signal), else its one key of 2 dimensions or more (an ophyd
    Device: an area detector's is e.g. `cam_image`). ValueError naming the keys where
    several are, or none is and `final`; None where none is and not `final`."""
    if camera.name in shapes:
        return str(camera.name)
    images = [key for key, shape in shapes.items() if len(shape) >= 2]
    if len(images) == 1:
        return images[0]
    if not images and not final:  # a description may leave shapes out: the reading says
        return None
    found = ", ".join(f"{key} {tuple(shape)}" for key, shape in shapes.items())
    raise ValueError(
        f"cannot tell which reading of camera {camera.name!r} is its image: it has no key "
        f"{camera.name!r} and {len(images)} readings of 2 dimensions or more, not one "
        f"(its readings: {found}); give the plan a camera whose reading holds one image"
    )


def _focus_tile(
    camera: Any,
    z: Any,
    tracker: FocusTracker,
    reading: TileFocusReading,
    image_key: str | frozenset[str],
) -> Plan:
    """The stacks the estimator asks of the tile `reading` names, read through the RunEngine,
    each focus_stack event with the tile, the run's stack number and the frame's in it.
    `image_key`: the camera's image among its readings, or the camera's data keys (its
    description did not say which is the image) to find it among in each reading."""
    steps = tracker.tile(reading.row.get(), reading.col.get())
    try:
        z_um = next(steps)
        while True:
            yield from bps.mv(
                reading.stack, reading.stack.get() + 1, reading.sequence, tracker.stack_sequence
            )
            frames = []
            for index, z_frame_um in enumerate(z_um):
                yield from bps.mv(z, float(z_frame_um), reading.stack_frame, index)
                readings = yield from bps.trigger_and_read(
                    [
                        camera,
                        z,
                        reading.row,
                        reading.col,
                        reading.stack,
                        reading.stack_frame,
                        reading.sequence,
                    ],
                    name=STACK_STREAM,
                )
                key = image_key
                if not isinstance(key, str):  # the camera's own readings, not z's or the tile's
                    shapes = {k: np.shape(readings[k]["value"]) for k in key if k in readings}
                    key = str(_image_key(camera, shapes, final=True))  # final: never None
                frames.append(readings[key]["value"])
            z_um = steps.send(np.stack(frames))
    except StopIteration as done:
        return done.value


def _read_focus_map(tracker: FocusTracker, maps: list[DescribedSignal]) -> Plan:
    """The estimator's final maps of the tracker's slide into the focustrack_map event."""
    focus_map = tracker.estimator.focus_map(tracker.slide_id)
    for signal, layer in zip(maps, MAP_LAYERS, strict=True):
        values = getattr(focus_map, layer)
        if values is not None:  # None is NaN: the strategy keeps no such layer
            yield from bps.mv(signal, np.array(values, dtype=np.float64).tolist())
    yield from bps.trigger_and_read(maps, name=MAP_STREAM)
