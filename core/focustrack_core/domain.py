"""The domain vocabulary every FocusTrack part speaks: flags, z-ranges, acquisitions, measurements.

These are the words of the contract between the services (proto/ carries the
same things on Zenoh, the estimator's REST API as JSON): `SlideSettings` say
what is known of a slide before its scan (with the `ZRangePolicy` that sizes its
stacks), an `Acquisition` asks for a z-stack at a tile, a `Measurement` is the
best focus found in it (with `FocusFlag`s saying why there is none), an
`Outcome` is what it did to the estimate, a `FocusMap` is the estimate of every
tile. Heights in um, shapes in docstrings. Pure: numpy only.

The defaults of the settings are the REST API's (`focustrack_client.models`, the
users' contract); `focustrack_core.rest.to_domain` makes these from them.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import cast

import numpy as np

from focustrack_core.geometry import ScanGrid
from focustrack_core.v1 import common_pb2

#: Largest |z| of a curve or a prior, um: a metre either way is no microscope (the
#: estimator's bound, the focus service's).
MAX_ABS_Z_UM = 1e6
#: A prior's sigma, um, from a picometre (a thousandth of a piezo stage's nanometre step: a
#: belief no stage can act on) to a metre (MAX_ABS_Z_UM: no belief at all). Within these
#: the maths stays in a float's range: 1 / sigma**2 <= 1e12, (z - z_prior)**2 <= 4e12.
MIN_PRIOR_SIGMA_UM = 1e-6
MAX_PRIOR_SIGMA_UM = 1e6


@dataclass(frozen=True)
class Prior:
    """The estimator's belief about a tile's focus before its stack: mean and std, um."""

    z_um: float
    sigma_um: float

    def __post_init__(self) -> None:
        # comparisons that NaN fails: a NaN is refused too
        if not abs(self.z_um) <= MAX_ABS_Z_UM:
            raise ValueError(
                f"a prior's z_um must be finite and within +/-{MAX_ABS_Z_UM:g} um, got {self.z_um}"
            )
        if not MIN_PRIOR_SIGMA_UM <= self.sigma_um <= MAX_PRIOR_SIGMA_UM:
            raise ValueError(
                f"a prior's sigma_um must be within [{MIN_PRIOR_SIGMA_UM:g}, "
                f"{MAX_PRIOR_SIGMA_UM:g}] um, got {self.sigma_um}"
            )


class FocusFlag(StrEnum):
    """Quality flags of a best-focus measurement (set by the focus service).

    The wire form is the proto enum `focustrack.v1.FocusFlag` (`FOCUS_FLAG_<NAME>`);
    JSON and this enum use the lower-case value. `proto` and `of_proto` convert.
    """

    EDGE_LOW = "edge_low"  # peak at the low-z end of the range: extend downwards
    EDGE_HIGH = "edge_high"  # peak at the high-z end: extend upwards
    FLAT = "flat"  # no peak in the curve (no contrast): no measurement
    EMPTY = "empty"  # with FLAT: nothing in view in any frame, so no other stack would help
    MULTI_PEAK = "multi_peak"  # more than one peak: measurement is less certain
    # the chosen peak is not clearly the focus (its probability is below the service's
    # threshold): two peaks (z and sigma are the chosen one's, the runner-up is given), or
    # a top drowned in noise (frames far from the chosen one as likely the top)
    AMBIGUOUS = "ambiguous"
    # with AMBIGUOUS: the curve falls to a sharp minimum between two maxima, below its far
    # frames: an unstained (phase-like) specimen, whose focus is that minimum (the
    # runner-up z; read it with mode valley), not the maximum
    VALLEY = "valley"

    @property
    def proto(self) -> common_pb2.FocusFlag:
        """This flag as the proto enum value (`FOCUS_FLAG_EDGE_LOW`, ...)."""
        return cast(common_pb2.FocusFlag, common_pb2.FocusFlag.Value(f"FOCUS_FLAG_{self.name}"))

    @classmethod
    def of_proto(cls, value: int) -> FocusFlag | None:
        """The flag of a proto enum value; None for one this version does not know."""
        name = common_pb2.FocusFlag.Name(value) if value in common_pb2.FocusFlag.values() else ""
        return cls.__members__.get(name.removeprefix("FOCUS_FLAG_"))


#: Flags that mean the stack holds no usable best focus.
NOT_AN_OBSERVATION = frozenset(
    {FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH, FocusFlag.FLAT, FocusFlag.EMPTY}
)


#: Frames a stack needs, at least, to teach the focus service the slide's curve: the width
#: and background it reads pairs and 3-frame stacks with (`focustrack_focus.curve_model`).
CURVE_LEARN_FRAMES = 7
#: Curves the focus service learns before it measures the spread of the slide's widths; until
#: then it takes a default spread, and pairs read with it come back with a sigma of about a um.
CURVE_SPREAD_CURVES = 3
#: Frames of a pair: a lean scan's short stack with `short_frames` 2, two frames one z step
#: apart whose scores' ratio places the peak (`focustrack_focus.pair`).
PAIR_FRAMES = 2
#: How far beyond its frames a pair (two frames one z step apart, a lean scan's short stack
#: with `short_frames` 2) places a peak: the focus service reads it from their scores' ratio
#: with the slide's learnt curve (`focustrack_focus.pair`), as far as the ratio stays
#: one-to-one (about a curve's half width: 1.75-3 um for the metrics' curves), in um.
PAIR_REACH_UM = 1.0


class Purpose(StrEnum):
    SCAN = "scan"  # image the tile (and measure its focus where the strategy asks)
    SURVEY = "survey"  # a survey point of a focus-map strategy, before the scan
    RETRY = "retry"  # the same tile again, after an edge peak or a flat curve
    PLANES = "planes"  # more frames of a measured tile, kept where one is too unsure
    REVISIT = "revisit"  # a tile measured before, measured again to track the drift in time
    LASER = "laser"  # a reading of the reflection autofocus (the coverslip's height), no image


@dataclass(frozen=True)
class ZRange:
    """Frames at low_um, low_um + step_um, ..., high_um (n_frames of them), in um."""

    low_um: float
    step_um: float
    n_frames: int

    def __post_init__(self) -> None:
        if self.n_frames < 1:
            raise ValueError(f"a z-range needs at least one frame, got {self.n_frames}")
        if not self.step_um > 0:
            raise ValueError(f"z step must be positive, got {self.step_um} um")

    @classmethod
    def centred(cls, center_um: float, n_frames: int, step_um: float) -> ZRange:
        return cls(center_um - (n_frames - 1) / 2.0 * step_um, step_um, n_frames)

    @property
    def high_um(self) -> float:
        return self.low_um + (self.n_frames - 1) * self.step_um

    @property
    def center_um(self) -> float:
        return (self.low_um + self.high_um) / 2.0

    def z_um(self) -> np.ndarray:
        """The z of every frame, shape (n_frames,), in um."""
        return self.low_um + self.step_um * np.arange(self.n_frames)

    def contains(self, z_um: float) -> bool:
        """True when a peak at `z_um` would lie inside the stack (not at its edge)."""
        return self.low_um <= z_um <= self.high_um


@dataclass(frozen=True)
class ZRangePolicy:
    """How wide a stack to take: +/- k_sigma predicted sigmas, within [min_frames, max_frames].

    The predicted sigma is that of the innovation (prediction and measurement
    noise together), because the measured peak, not the truth, must land in
    the stack. A retry after an edge peak continues beyond the edge (`beyond`).
    """

    k_sigma: float  # tuned on training seeds (docs/estimators.md)
    z_step_um: float
    min_frames: int
    max_frames: int

    def __post_init__(self) -> None:
        if not (self.k_sigma > 0 and self.z_step_um > 0):
            raise ValueError("k_sigma and z_step_um must be positive")
        if not 2 <= self.min_frames <= self.max_frames:
            raise ValueError(
                f"need 2 <= min_frames <= max_frames, got {self.min_frames}, {self.max_frames}"
            )

    def around(self, center_um: float, sigma_um: float) -> ZRange:
        """A stack centred on a prediction with innovation sigma `sigma_um`."""
        n_frames = 2 * math.ceil(self.k_sigma * sigma_um / self.z_step_um) + 1
        n_frames = min(max(n_frames, self.min_frames), self.max_frames)
        return ZRange.centred(center_um, n_frames, self.z_step_um)

    def wide(self, center_um: float) -> ZRange:
        """The widest stack the policy allows (autofocus without a prediction)."""
        return ZRange.centred(center_um, self.max_frames, self.z_step_um)

    def beyond(self, previous: ZRange, flag: FocusFlag) -> ZRange:
        """The stack to take after `previous` ended in an edge peak (or a flat curve).

        As wide as `previous` (at least `min_frames`), continuing past the edge
        that was hit and overlapping it by two frames, so that a peak on the old
        edge frame lies inside the new stack with both its flanks. A flat curve
        gets the widest stack, centred where the last one was.
        """
        n_frames = max(previous.n_frames, self.min_frames)
        overlap_um = self.z_step_um
        if flag is FocusFlag.EDGE_HIGH:
            return ZRange(previous.high_um - overlap_um, self.z_step_um, n_frames)
        if flag is FocusFlag.EDGE_LOW:
            high_um = previous.low_um + overlap_um
            return ZRange(high_um - (n_frames - 1) * self.z_step_um, self.z_step_um, n_frames)
        return self.wide(previous.center_um)

    @staticmethod
    def single(z_um: float, step_um: float) -> ZRange:
        """One frame at `z_um` (imaging a tile whose focus is already decided)."""
        return ZRange(z_um, step_um, 1)


@dataclass(frozen=True)
class SlideSettings:
    """What every strategy is told about the slide, whatever its kind (heights in um)."""

    grid: ScanGrid
    start_z_um: float  # the height to start from (for example the previous slide's)
    start_sigma_um: float  # how uncertain that start is
    dof_um: float  # depth of field of the objective
    noise_sigma_um: float  # default std of a best-focus measurement (R = noise**2)
    policy: ZRangePolicy


@dataclass(frozen=True)
class Acquisition:
    """What to acquire next: a tile and a z-range, and what the strategy expects of it."""

    index: int  # sequence number of this acquisition within the slide's scan
    row: int
    col: int
    z: ZRange
    purpose: Purpose
    measure: bool  # True: a best focus is expected back; False: only image the tile
    predicted_um: float | None = None  # the prior of this tile's focus, where there is one
    predicted_sigma_um: float | None = None  # the prior's standard deviation


@dataclass(frozen=True)
class Measurement:
    """The result of an acquisition: the best focus found in it, or why there is none.

    With `FocusFlag.MULTI_PEAK`, `runner_up_z_um` is the next most likely peak's z (um) and
    `chosen_probability` the chance (0..1) that the chosen peak at `z_um` is the focus, as
    the focus service weighed them (with the prior it was sent); None where not given.
    `frame_out_of_focus`: an image-only acquisition's frame (no best focus) that the
    scheduler found out of focus, less sharp than the first pass's image of the tile
    (`focustrack_scheduler.focus_check`): the tile is to be measured.
    """

    z_um: float | None
    sigma_um: float | None = None
    flags: frozenset[FocusFlag] = frozenset()
    runner_up_z_um: float | None = None
    chosen_probability: float | None = None
    frame_out_of_focus: bool = False

    def __post_init__(self) -> None:
        if self.z_um is not None and not math.isfinite(self.z_um):
            raise ValueError(f"measured z must be finite, got {self.z_um}")
        if self.sigma_um is not None and not (math.isfinite(self.sigma_um) and self.sigma_um > 0):
            raise ValueError(f"measurement sigma must be positive and finite, got {self.sigma_um}")
        if self.runner_up_z_um is not None and not math.isfinite(self.runner_up_z_um):
            raise ValueError(f"runner-up z must be finite, got {self.runner_up_z_um}")
        probability = self.chosen_probability
        if probability is not None and not 0.0 <= probability <= 1.0:
            raise ValueError(f"chosen probability must be in [0, 1], got {probability}")

    @property
    def is_observation(self) -> bool:
        return self.z_um is not None and not (self.flags & NOT_AN_OBSERVATION)


def kept_in_focus(z_kept_um: Sequence[float], truth_um: float, dof_um: float) -> bool:
    """Whether a tile kept at `z_kept_um` (its image, and any more frames it keeps) is in
    focus: one of them lies within half the depth of field of its true focus (um)."""
    return any(abs(z - truth_um) <= dof_um / 2.0 for z in z_kept_um)


@dataclass(frozen=True)
class Outcome:
    """What one measurement did to the estimate of its tile (heights in um)."""

    row: int
    col: int
    accepted: bool  # used as an observation (False: edge, flat, gated out or image only)
    prior_um: float | None = None
    prior_sigma_um: float | None = None
    posterior_um: float | None = None
    posterior_sigma_um: float | None = None
    innovation_um: float | None = None
    nis: float | None = None  # normalised innovation squared
    # The frames the tile keeps, z in um ascending, where it keeps more than its image at
    # z_used_um (the estimate is final and one frame is too unsure: `lean.kept_planes`).
    planes_um: tuple[float, ...] = ()


@dataclass
class FocusMap:
    """The estimates of every tile, each (rows, cols) in um, NaN where there is none yet.

    `z_used_um` is the height the tile was imaged at (the frame kept for the
    mosaic); it is what the in-focus fraction is judged on. `out_of_focus_risk`
    is the strategy's predicted probability that this frame lies outside the
    depth of field (0..1, NaN where the strategy states none).
    """

    prior_um: np.ndarray
    prior_sigma_um: np.ndarray
    posterior_um: np.ndarray
    posterior_sigma_um: np.ndarray
    z_used_um: np.ndarray
    smoothed_um: np.ndarray | None = None
    smoothed_sigma_um: np.ndarray | None = None
    out_of_focus_risk: np.ndarray | None = None

    @classmethod
    def empty(cls, grid: ScanGrid) -> FocusMap:
        def nan() -> np.ndarray:
            return np.full(grid.shape, np.nan)

        return cls(nan(), nan(), nan(), nan(), nan(), out_of_focus_risk=nan())
