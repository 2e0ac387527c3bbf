"""Predictive focus for lab software that drives its own microscope: one tile at a time.

The lab's acquisition loop visits tiles in the estimator's serpentine order and,
at each tile, calls `FocusTracker.focus(row, col, acquire)`. The tracker asks the
estimator (over REST, `focustrack_client`) for the tile's z-range, has `acquire`
take the stack, measures its focus here with the focus service's pure functions
(`focustrack_focus.pipeline.focus_stack`), posts the measurement, takes another
stack when the estimator asks for one (an edge peak, a flat curve), and returns
the height to image the tile at: the estimator's posterior, else the measured
best focus, else the prediction. The estimator bounds the stacks of a tile: a
flat curve (nothing in view, or images that do not change with z) gets one
widest stack, then the tile is given up and imaged at the prediction; its
`TileFocus.flags` say so, and `FocusTracker.summary` counts such tiles. The
pymmcore-plus engine (`mmcore.py`) and the Bluesky plan (`bluesky.py`) are built
on it.
"""

from __future__ import annotations

import math
import operator
from collections import Counter
from collections.abc import Callable, Generator
from dataclasses import dataclass
from typing import TypeVar

import httpx
import numpy as np
from pydantic import TypeAdapter, ValidationError

from focustrack_client import EstimatorClient, EstimatorError, ServerError
from focustrack_client.models import FocusFlag, Grid, MeasurementIn, Next, Purpose, SlideCreate
from focustrack_core.domain import FocusFlag as DomainFlag
from focustrack_core.domain import Measurement
from focustrack_focus.peak import MIN_CURVE_FRAMES
from focustrack_focus.pipeline import FocusResult, FocusSettings, focus_stack

T = TypeVar("T")

#: Takes a z-stack at the current tile: z of every frame (n,) in um -> frames (n, H, W[, C]).
AcquireStack = Callable[[np.ndarray], np.ndarray]


class TileOrderError(RuntimeError):
    """The lab visited a tile other than the one the estimator expects next, or the slide
    asks for acquisitions a tile-by-tile loop cannot take (`check_slide`)."""


#: Strategies whose acquisitions include readings of a laser (reflection) autofocus: the
#: tracker takes camera stacks only, and a frame posted as a laser reading wastes a stack.
LASER_STRATEGIES = frozenset({"kf-2d-laser"})


def check_slide(config: SlideCreate) -> None:
    """Raise TileOrderError when the estimator would ask this slide for an acquisition the
    tracker cannot take or read: a laser reading, or a measured stack of fewer than
    MIN_CURVE_FRAMES frames (the focus maths here locates a peak between the outer two of
    three frames at least; a pair needs the focus service's learnt curve).

    Checked before the scan: such a stack used to be taken, then fail to read, and every
    retry of it failed alike, so the slide could never finish.
    """
    params = config.params
    problems = []
    if config.strategy in LASER_STRATEGIES:
        problems.append(f"strategy {config.strategy} asks for laser autofocus readings")
    if config.z_range.min_frames < MIN_CURVE_FRAMES:
        problems.append(f"z_range.min_frames is {config.z_range.min_frames}")
    short_frames = _as(int, params.get("short_frames"))
    if short_frames is not None and short_frames < MIN_CURVE_FRAMES:
        problems.append(f"params short_frames is {short_frames} (a 2-frame pair)")
    if _as(bool, params.get("look_first")):
        problems.append("params look_first is true (a tile's first stack starts with 1 frame)")
    if problems:
        raise TileOrderError(
            f"the tracker cannot scan this slide: {'; '.join(problems)}. It reads a focus "
            f"from camera stacks of {MIN_CURVE_FRAMES} frames or more (or a 1-frame look); "
            "create the slide with "
            f"z_range.min_frames >= {MIN_CURVE_FRAMES}, without short_frames below "
            f"{MIN_CURVE_FRAMES} or look_first, and a camera strategy (kf-2d, kf-2d-lean, ...)"
        )


@dataclass(frozen=True)
class TileFocus:
    """What the tracker found at one tile (heights in um).

    z_um: where to image the tile. n_frames, n_stacks: frames and stacks acquired for
    focus on it, every stack counted. last: the focus result of its last measured stack
    (the through-focus curve, best z, sigma, flags), None when the estimator only asked
    for an image.
    planes_um: where one image is too unsure to be in focus (the slide's
    risk_out_of_focus), the heights of the frames to image it at instead, ascending, each
    within a depth of field of the next: one of them is in focus. Empty: image at z_um.
    """

    row: int
    col: int
    z_um: float
    sigma_um: float | None
    n_frames: int
    n_stacks: int
    last: FocusResult | None
    planes_um: tuple[float, ...] = ()

    @property
    def flags(self) -> frozenset[DomainFlag]:
        """The flags of its last measured stack: empty where it found a focus (flat: nothing
        that changes with z; edge_low / edge_high: the peak beyond the stack)."""
        return frozenset() if self.last is None else self.last.flags

    @property
    def unfocused(self) -> bool:
        """True when its stacks found no focus (the last measured one has no best z): it is
        imaged at the estimator's prediction. A tile the estimator only asked an image of
        (it was sure enough) is not."""
        return self.last is not None and self.last.best_z_um is None


@dataclass(frozen=True)
class ScanSummary:
    """What a scan's tiles came to: counts, and the tiles imaged without a measured focus.

    unfocused: (row, col) -> the flags of its last stack, for every tile whose stacks
    found no best focus (it was imaged at the estimator's prediction).
    """

    n_tiles: int
    n_stacks: int
    n_frames: int
    unfocused: dict[tuple[int, int], frozenset[DomainFlag]]

    def __str__(self) -> str:
        stacks = (
            f"{self.n_stacks} stacks ({self.n_frames} frames) for focus on {self.n_tiles} tiles"
        )
        if not self.unfocused:
            return f"{stacks}; no tile without a focus"
        counts = Counter(flag for flags in self.unfocused.values() for flag in flags)
        named = ", ".join(f"{flag}: {n}" for flag, n in sorted(counts.items()))
        return (
            f"{stacks}; {len(self.unfocused)} of {self.n_tiles} tiles without a focus "
            f"({named}), imaged at the estimator's prediction: "
            f"{sorted(self.unfocused)}"
        )


#: `FocusTracker.tile`: yields the z (n,) um of each stack, is sent its frames, returns the focus.
TileSteps = Generator[np.ndarray, np.ndarray, TileFocus]


class FocusTracker:
    """One slide at the estimator, focused tile by tile (see the module docstring)."""

    def __init__(
        self,
        estimator: EstimatorClient,
        slide_id: str,
        settings: FocusSettings | None = None,
    ) -> None:
        self.estimator = estimator
        self.slide_id = slide_id
        self.settings = settings or FocusSettings()
        self.tiles: list[TileFocus] = []
        # The estimator's sequence number of the stack `tile` last yielded (None before
        # the first): a plan that records its frames can say which acquisition they are.
        self.stack_sequence: int | None = None
        # The tile whose last call raised, to go on with (see `tile`).
        self._progress: _TileProgress | None = None

    @classmethod
    def create(
        cls,
        estimator: EstimatorClient,
        slide: SlideCreate,
        settings: FocusSettings | None = None,
    ) -> FocusTracker:
        """A tracker of a new estimator slide scanned as `slide` says.

        Raises TileOrderError, creating nothing, where the slide would ask for what the
        tracker cannot take (`check_slide`).
        """
        check_slide(slide)
        return cls(estimator, estimator.create_slide(slide).id, settings)

    @classmethod
    def open(
        cls,
        estimator: EstimatorClient,
        slide_id: str,
        settings: FocusSettings | None = None,
    ) -> FocusTracker:
        """A tracker of an existing estimator slide, checked as `create` checks a new one
        (the constructor asks the estimator nothing)."""
        check_slide(estimator.slide(slide_id).config)
        return cls(estimator, slide_id, settings)

    @property
    def n_frames(self) -> int:
        """Frames acquired for focus so far, on every tile."""
        return sum(tile.n_frames for tile in self.tiles)

    def summary(self) -> ScanSummary:
        """The tiles focused so far: counts, and those without a measured focus."""
        return ScanSummary(
            n_tiles=len(self.tiles),
            n_stacks=sum(tile.n_stacks for tile in self.tiles),
            n_frames=self.n_frames,
            unfocused={(tile.row, tile.col): tile.flags for tile in self.tiles if tile.unfocused},
        )

    def focus(self, row: int, col: int, acquire: AcquireStack) -> TileFocus:
        """Every stack the estimator asks of tile (row, col), taken by `acquire`; where to image it.

        Raises TileOrderError when the estimator expects another tile (or none) first.
        Called again for a tile whose call raised, it goes on where that one stopped (`tile`).
        """
        steps = self.tile(row, col)
        try:
            z_um = next(steps)
            while True:
                z_um = steps.send(acquire(z_um))
        except StopIteration as done:
            return done.value

    def tile(self, row: int, col: int) -> TileSteps:
        """`focus` as a generator, for plans that acquire by yielding (Bluesky's).

        Yields the z of every frame of each stack to take, (n,) in um; is sent its
        frames (n, H, W[, C]); returns the TileFocus.

        Called again for a tile whose call raised, it goes on where that one stopped: a
        measurement whose post met a connection error or a server error (recorded or not,
        no one knows) is posted again first, as the estimator answers a repeat as the
        first; the stacks already taken stay counted. Without that, a reply lost after
        the estimator recorded the tile's last stack lost the tile: the estimator had
        moved on to the next one.
        """
        row, col = _tile_index(row, "row"), _tile_index(col, "col")
        progress = self._progress
        if progress is None or (progress.row, progress.col) != (row, col):
            progress = self._progress = _TileProgress(row, col)
        if progress.unposted is not None:
            self._post(progress, progress.unposted)
        while (step := self.estimator.next(self.slide_id)).row == row and step.col == col:
            _check_step(step)  # before `_frames_z_um`: a laser reading may have no z-range
            frames_z_um = _frames_z_um(step)
            self.stack_sequence = _required(step.sequence)
            frames = np.asarray((yield frames_z_um))
            if frames.dtype == object:  # None, or what is no array of numbers
                raise ValueError(
                    "acquire must give the stack's frames, (n, H, W[, C]) numbers: an array "
                    f"or a list of frames of one shape; got {frames.dtype} {frames.shape}"
                )
            measurement = Measurement(None)
            if step.measure:
                progress.last = focus_stack(frames, frames_z_um, self.settings)
                measurement = progress.last.measurement()
            # Counted once taken as frames: a stack refused (None, the wrong count, NaN) is not.
            progress.n_frames += len(frames_z_um)
            progress.n_stacks += 1
            progress.unposted = _Unposted(step, self.stack_sequence, measurement)
            self._post(progress, progress.unposted)
        self._progress = None
        if progress.z_um is None:
            if step.purpose == Purpose.SURVEY:
                raise TileOrderError(
                    f"the estimator surveys tile ({step.row}, {step.col}) next, not tile "
                    f"({row}, {col}): a survey strategy visits its survey points first, then "
                    "every tile, two passes a tile-by-tile loop cannot follow; scan this "
                    "slide with a Kalman strategy (kf-2d, kf-2d-lean, ...)"
                )
            raise TileOrderError(self._order_problem(step, row, col))
        tile = TileFocus(
            row,
            col,
            progress.z_um,
            progress.sigma_um,
            progress.n_frames,
            progress.n_stacks,
            progress.last,
            progress.planes_um,
        )
        self.tiles.append(tile)
        return tile

    def _order_problem(self, step: Next, row: int, col: int) -> str:
        """Why tile (row, col) is not the one to visit: the scan is over, the tile is off
        the slide's grid, or another tile comes first."""
        if step.done:
            return f"the scan is done: no tile is pending (tile ({row}, {col}) was asked for)"
        grid = self._grid()
        if grid is not None and not (0 <= row < grid.rows and 0 <= col < grid.cols):
            return (
                f"tile ({row}, {col}) is outside the {grid.rows}x{grid.cols} grid: rows run "
                f"0..{grid.rows - 1}, columns 0..{grid.cols - 1}; the estimator expects "
                f"tile ({step.row}, {step.col}) next"
            )
        return (
            f"the estimator expects tile ({step.row}, {step.col}) next, not tile ({row}, {col}): "
            "visit the tiles in its serpentine order (row 0 left to right, row 1 right to "
            "left, ...)"
        )

    def _grid(self) -> Grid | None:
        """The slide's grid, or None where the estimator cannot say (the error being
        explained matters more than this detail)."""
        try:
            return self.estimator.slide(self.slide_id).config.grid
        except (EstimatorError, httpx.HTTPError):
            return None

    def _post(self, progress: _TileProgress, unposted: _Unposted) -> None:
        """Post the tile's `unposted` measurement; where to image the tile, from its outcome.

        Keeps it unposted when the post's fate is unknown (a connection error, a server
        error), so that the tile's next call posts it again; drops it when the estimator
        refused it (a 4xx: nothing recorded, it asks for the stack again).
        """
        measurement = unposted.measurement
        try:
            outcome = self.estimator.measure(
                self.slide_id,
                MeasurementIn(
                    row=progress.row,
                    col=progress.col,
                    sequence=unposted.sequence,
                    z_um=measurement.z_um,
                    sigma_um=measurement.sigma_um,
                    flags=[FocusFlag(flag.value) for flag in sorted(measurement.flags)],
                ),
            )
        except EstimatorError as error:
            if not isinstance(error, ServerError):
                progress.unposted = None
            raise
        progress.unposted = None
        progress.planes_um = tuple(outcome.planes_um)
        step = unposted.step
        progress.z_um, progress.sigma_um = _best(
            (outcome.posterior_um, outcome.posterior_sigma_um),
            (measurement.z_um, measurement.sigma_um),
            (step.predicted_z_um, step.predicted_sigma_um),
            (step.z_center_um, None),
        )


@dataclass(frozen=True)
class _Unposted:
    """A measurement of stack `sequence`, asked for by `step`, not yet acknowledged."""

    step: Next
    sequence: int
    measurement: Measurement


@dataclass
class _TileProgress:
    """A tile's focus so far (heights in um): what `FocusTracker.tile` resumes from."""

    row: int
    col: int
    n_frames: int = 0
    n_stacks: int = 0
    last: FocusResult | None = None
    unposted: _Unposted | None = None
    z_um: float | None = None
    sigma_um: float | None = None
    planes_um: tuple[float, ...] = ()


def _as(kind: type[T], value: object) -> T | None:
    """`value` read as the estimator's parameter models read it (1 and "true" are True, "2"
    is 2); None where it is absent or they would refuse it (the estimator then says why)."""
    if value is None:
        return None
    try:
        return TypeAdapter(kind).validate_python(value)
    except ValidationError:
        return None


def _required(value: int | None) -> int:
    if value is None:
        raise ValueError("the estimator's next acquisition has no sequence number")
    return value


def _check_step(step: Next) -> None:
    """TileOrderError, before anything is acquired, for an acquisition the tracker cannot
    take or read (`check_slide` refuses the slides known to ask for them): a laser reading,
    or a measured stack of 2 to MIN_CURVE_FRAMES - 1 frames."""
    where = f"at tile ({step.row}, {step.col})"
    if step.purpose == Purpose.LASER:
        raise TileOrderError(
            f"the estimator asks for a laser autofocus reading {where}; the tracker takes "
            "camera stacks only: scan this slide with a camera strategy (kf-2d, kf-2d-lean, ...)"
        )
    # One frame is a look (`focus_stack` reads whether anything is in view: the estimator
    # asks for one in glass); two are a pair, which needs the focus service's learnt curve.
    n = step.n_frames
    if step.measure and n is not None and 1 < n < MIN_CURVE_FRAMES:
        raise TileOrderError(
            f"the estimator asks for a {n}-frame stack {where} ({step.purpose}); the tracker "
            f"reads a focus from 1 frame (a look) or {MIN_CURVE_FRAMES} frames or more: create the "
            f"slide with z_range.min_frames >= {MIN_CURVE_FRAMES}, without short_frames below "
            f"{MIN_CURVE_FRAMES} or look_first"
        )


def _frames_z_um(step: Next) -> np.ndarray:
    """The z of every frame of the acquisition `step` names, (n_frames,) in um."""
    low_um, step_um, n = step.z_low_um, step.z_step_um, step.n_frames
    if low_um is None or step_um is None or n is None:
        raise ValueError(f"the estimator's next acquisition has no z-range: {step}")
    return low_um + step_um * np.arange(n)


def _best(*candidates: tuple[float | None, float | None]) -> tuple[float | None, float | None]:
    """The first (z_um, sigma_um) whose z is a finite number; (None, None) if none is."""
    for z_um, sigma_um in candidates:
        if z_um is not None and math.isfinite(z_um):
            return z_um, sigma_um
    return None, None


def _tile_index(value: object, name: str) -> int:
    """`value` as a tile index: an int, a numpy integer; TypeError naming `name` for a str,
    a float or None (they used to reach the estimator's model after the stack was taken,
    or a TileOrderError saying "expects (0, 0), not tile (0, 0)")."""
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError:
        raise TypeError(f"{name} must be an integer, got {value!r}") from None
