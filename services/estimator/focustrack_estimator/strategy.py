"""What every scan strategy is: a plan that says where to look next and learns from what it saw.

A strategy answers two calls, whatever it is inside (a Kalman filter, tile
skipping, a survey followed by an interpolated map):

- `next_acquisition()` -> the next tile and the z-range to acquire there, or
  None when the scan is complete;
- `record(acquisition, measurement)` -> what the measurement did to the
  estimate (prior, posterior, innovation, NIS, accepted).

The benchmark, the estimator service and the scheduler all drive strategies
through these two calls only, so every strategy is costed and served alike.
Strategies are deterministic: replaying the same measurements rebuilds the
same state (the estimator service relies on that to survive restarts).

Each strategy is served as a `StrategyEntry`: its parameters' model (a
`StrategyParams` subclass, beside the strategy: every parameter's name, type,
default, unit and bounds), its factory ``factory(settings, params)`` and its
cost model ``cost(settings, params)``.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, Generic, TypeVar

from pydantic import BaseModel, ConfigDict, field_validator, model_validator

from focustrack_client.models import MAX_ABS_UM
from focustrack_core.domain import (
    Acquisition,
    FocusFlag,
    FocusMap,
    Measurement,
    Outcome,
    Purpose,
    SlideSettings,
    ZRange,
    ZRangePolicy,
)
from focustrack_estimator.sigma_scale import SigmaScale

_EDGES = frozenset({FocusFlag.EDGE_LOW, FocusFlag.EDGE_HIGH})

#: Heights a stack may reach, +/- um: the API's bound on every height. A z-range the
#: policy would put beyond it is moved (and if need be narrowed) inside it, so that what
#: the estimator asks for can always be measured and posted back.
Z_LIMIT_UM = MAX_ABS_UM

#: Most retries a strategy may make on one tile: a scan must end, and each retry is a stack.
MAX_RETRIES = 50


def bounded(z: ZRange, limit_um: float = Z_LIMIT_UM) -> ZRange:
    """`z` moved inside [-limit_um, limit_um], with fewer frames if it is wider than that."""
    n_frames = min(z.n_frames, int(2 * limit_um // z.step_um) + 1)
    span_um = (n_frames - 1) * z.step_um
    low_um = min(max(z.low_um, -limit_um), limit_um - span_um)
    if (low_um, n_frames) == (z.low_um, z.n_frames):
        return z
    return ZRange(low_um, z.step_um, n_frames)


class PeakSearch:
    """The search for one tile's focus peak: the stacks that found none, and the next to take.

    After a stack without a peak:
    - an edge peak continues past that edge (`ZRangePolicy.beyond`); two stacks
      that each saw one flank (an EDGE_HIGH stack below an EDGE_LOW one)
      bracket the peak, and the next stack spans what lies between them and
      the frames they share;
    - a flat curve gets the widest stack once, centred where the last one was;
      a flat curve in a widest stack ends the search;
    - an empty field (nothing in view) ends the search at once;
    - so does a failure after `max_retries` retries: a scan must always end.
    A strategy that gives a tile up images it where it predicted its focus.
    """

    def __init__(self, policy: ZRangePolicy, max_retries: int) -> None:
        if not 0 <= max_retries <= MAX_RETRIES:
            raise ValueError(f"max_retries must be in 0..{MAX_RETRIES}, got {max_retries}")
        self.policy = policy
        self.max_retries = max_retries
        self.misses: list[tuple[ZRange, FocusFlag]] = []

    def __bool__(self) -> bool:
        """True once a stack of this tile has found no peak."""
        return bool(self.misses)

    @property
    def stacks(self) -> list[ZRange]:
        """The peakless stacks of this tile, in the order they were taken."""
        return [stack for stack, _ in self.misses]

    def clear(self) -> None:
        """Start the search of a new tile."""
        self.misses = []

    def failed(self, stack: ZRange, measurement: Measurement) -> bool:
        """Note that `stack` found no peak; True: take another (`next_range`); False: give up."""
        edges = measurement.flags & _EDGES
        flag = next(iter(edges)) if len(edges) == 1 else FocusFlag.FLAT
        self.misses.append((stack, flag))
        if FocusFlag.EMPTY in measurement.flags:
            return False
        if flag is FocusFlag.FLAT and stack.n_frames >= self.policy.max_frames:
            return False
        return len(self.misses) <= self.max_retries

    def next_range(self) -> ZRange:
        """The stack to take after the peakless ones."""
        above_um = max(
            (z.high_um for z, f in self.misses if f is FocusFlag.EDGE_HIGH), default=-math.inf
        )
        below_um = min(
            (z.low_um for z, f in self.misses if f is FocusFlag.EDGE_LOW), default=math.inf
        )
        if math.isfinite(above_um) and math.isfinite(below_um):
            half_width_um = abs(below_um - above_um) / 2.0 + self.policy.z_step_um
            centre_um = (above_um + below_um) / 2.0
            return self.policy.around(centre_um, half_width_um / self.policy.k_sigma)
        return self.policy.beyond(*self.misses[-1])


@dataclass(frozen=True)
class Cost:
    """What one slide of a strategy is projected to cost: its peak memory (bytes, the slide's
    whole life: state, transients, history) and its compute per tile (seconds at
    `NOMINAL_FLOPS_PER_S`). Estimates for the budget (`focustrack_estimator.budget.Budget`),
    checked against measurement by tests/test_estimator_budget.py."""

    peak_bytes: int
    seconds_per_tile: float

    def __add__(self, other: Cost) -> Cost:
        return Cost(
            self.peak_bytes + other.peak_bytes, self.seconds_per_tile + other.seconds_per_tile
        )


#: Magnitudes a strategy parameter may have (zero aside): beyond, its products with other
#: quantities under- or overflow a float (1e-300 squared is 0), and it is no physical
#: noise, length or sigma anyway (the smallest default is 1e-10).
PARAM_MAGNITUDES = (1e-30, 1e30)


def _null_is_the_default(schema: dict[str, Any]) -> None:
    """Say in a parameters model's JSON schema that each parameter takes null (its default)."""
    for parameter in schema.get("properties", {}).values():
        if isinstance(parameter.get("type"), str):
            parameter["type"] = [parameter["type"], "null"]


class StrategyParams(BaseModel):
    """A strategy's parameters: each one's name, type, default, unit (in its name or its
    description) and bounds. Every strategy has its own model, beside it.

    Values are taken as JSON gives them: an int where a float is expected, a list of
    numbers where a tuple is (a bank's grid), never a bool where a number is; None asks
    for the default; an unknown name is an error. Every number (and every element of a
    tuple) is 0 or of a magnitude within `PARAM_MAGNITUDES`. Not frozen: restoring a
    snapshot writes a strategy's attributes back, its options among them (`snapshot`).
    """

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        json_schema_extra=_null_is_the_default,
    )

    @model_validator(mode="before")
    @classmethod
    def _none_is_the_default(cls, data: Any) -> Any:
        if isinstance(data, Mapping):
            return {k: v for k, v in data.items() if v is not None or k not in cls.model_fields}
        return data

    @field_validator("*")
    @classmethod
    def _physical(cls, value: Any) -> Any:
        low, high = PARAM_MAGNITUDES
        for number in value if isinstance(value, tuple) else (value,):
            real = isinstance(number, float | int) and not isinstance(number, bool)
            if real and number != 0 and not low <= abs(number) <= high:
                raise ValueError(
                    f"not a physical value (magnitudes from {low:g} to {high:g}, or 0, are): "
                    f"{number!r}"
                )
        return value


P = TypeVar("P", bound=StrategyParams)

#: A strategy's cost model: called with the slide's settings and its parameters, as its
#: factory is.
CostModel = Callable[[SlideSettings, P], Cost]

#: Floating-point operations per second the time estimates assume: numpy on one loaded
#: core of the 2-core machine (its dense kernels run at 1-3 GFLOP/s there).
NOMINAL_FLOPS_PER_S = 1e9

#: Bytes every strategy holds per tile whatever it is: the focus map's seven float layers,
#: the serpentine's flags and innovations, and the service's history of each acquisition
#: (Python objects: about 1.1 kB each, measured with tracemalloc).
BYTES_PER_TILE = 1_500


def tile_cost(settings: SlideSettings) -> Cost:
    """The memory every strategy needs per tile (`BYTES_PER_TILE`); strategies add their own."""
    return Cost(settings.grid.n_tiles * BYTES_PER_TILE, 0.0)


class Strategy(ABC):
    """A scan strategy: a plan (`_plan`) and what it learns from each measurement (`_take`).

    Subclasses set `name`, take their parameters (their `StrategyParams` model)
    after the settings, and implement `_plan` and `_take`; this base class keeps the
    pending acquisition and its sequence number, so asking twice for the next
    acquisition returns the same one and a measurement is only taken for it.
    """

    name: str

    def __init__(self, settings: SlideSettings) -> None:
        self.settings = settings
        self.grid = settings.grid
        # The estimates, and each tile's predicted P(its kept frame lies outside the depth
        # of field) (`FocusMap.out_of_focus_risk`, NaN where the strategy states none).
        self.map = FocusMap.empty(settings.grid)
        self.n_recorded = 0
        self._pending: Acquisition | None = None
        self.sigma_scale = SigmaScale()  # the slide's scale on measured sigmas (adaptive R)

    def next_acquisition(self) -> Acquisition | None:
        """The next acquisition to make, or None when every tile has been imaged."""
        if self._pending is None:
            self._pending = self._plan()
        return self._pending

    def record(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        """Take the measurement made for `acquisition`, which must be the pending one."""
        pending = self.next_acquisition()
        if pending is None:
            raise ValueError("the scan is complete: no acquisition is pending")
        if acquisition != pending:
            raise ValueError(
                f"measurement is for acquisition {acquisition.index} at tile "
                f"({acquisition.row}, {acquisition.col}), but the pending one is "
                f"{pending.index} at ({pending.row}, {pending.col})"
            )
        outcome = self._take(pending, self.sigma_scale.scaled(measurement))
        self.sigma_scale.learn(measurement, outcome)
        self._pending = None
        self.n_recorded += 1
        return outcome

    def focus_map(self) -> FocusMap:
        """The estimates so far (the final map once `next_acquisition` returns None)."""
        return self.map

    @property
    def stated_risk(self) -> float | None:
        """The share of tiles allowed out of focus, where the strategy takes one (else None)."""
        return None

    @property
    def measurement_sigma_um(self) -> float:
        """The sigma a measurement is expected to have now, um (the configured noise)."""
        return self.settings.noise_sigma_um

    def _acquisition(
        self, row: int, col: int, z: ZRange, purpose: Purpose, *, measure: bool, **prediction
    ) -> Acquisition:
        """A new acquisition, numbered in sequence, its z-range `bounded`; for `_plan`."""
        return Acquisition(self.n_recorded, row, col, bounded(z), purpose, measure, **prediction)

    @abstractmethod
    def _plan(self) -> Acquisition | None:
        """Decide the next acquisition (None when the scan is complete)."""

    @abstractmethod
    def _take(self, acquisition: Acquisition, measurement: Measurement) -> Outcome:
        """Learn from the measurement of the pending acquisition; update `self.map`."""


@dataclass(frozen=True)
class StrategyEntry(Generic[P]):
    """A served strategy: its parameters' model, its factory and its cost model, each
    called with the slide's settings and the parameters validated by that model."""

    params: type[P]
    factory: Callable[[SlideSettings, P], Strategy]
    cost: CostModel[P]
