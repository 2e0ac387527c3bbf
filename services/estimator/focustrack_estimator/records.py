"""A slide's log records: the domain's acquisitions, measurements and outcomes as JSON objects.

What goes into the store (`event_store.Event`) and comes back on a restart. The
records are the contract with logs written by earlier versions: a field added
to a domain type must read from older records too (as `planes_um` does). A record
read back is checked (`checked_logged_of`): one that does not decode, or holds what
the API would not have accepted, is a corrupt log.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from pydantic import ValidationError

from focustrack_client import models as api
from focustrack_client.models import MAX_ABS_UM, MIN_SIGMA_UM
from focustrack_core.domain import Acquisition, FocusFlag, Measurement, Outcome, Purpose, ZRange
from focustrack_core.geometry import ScanGrid
from focustrack_estimator.event_store import CorruptLogError, Event, SlideRecord


@dataclasses.dataclass(frozen=True)
class Logged:
    """One recorded acquisition, in memory: the tile asked for, what was sent, what it did."""

    acquisition: Acquisition
    measurement: Measurement
    outcome: Outcome


def config_of(record: SlideRecord, params: dict[str, Any] | None = None) -> api.SlideCreate:
    """The slide's stored configuration (its parameters replaced by `params` where given);
    CorruptLogError if this version refuses it (another version's, or a damaged one)."""
    config = record.config if params is None else {**record.config, "params": params}
    try:
        return api.SlideCreate.model_validate(config)
    except ValidationError as error:
        problems = "; ".join(
            f"{'.'.join(map(str, e['loc'])) or 'the whole'}: {e['msg']}"
            for e in error.errors(include_url=False)
        )
        raise CorruptLogError(record.id, None, problems) from None


def acquisition_record(acquisition: Acquisition) -> dict[str, Any]:
    return dataclasses.asdict(acquisition)


def acquisition_of(record: dict[str, Any]) -> Acquisition:
    return Acquisition(
        **{**record, "z": ZRange(**record["z"]), "purpose": Purpose(record["purpose"])}
    )


def measurement_record(measurement: Measurement) -> dict[str, Any]:
    record: dict[str, Any] = {
        "z_um": measurement.z_um,
        "sigma_um": measurement.sigma_um,
        "flags": sorted(measurement.flags),
    }
    # the choice between peaks, where the focus service gave it (else as recorded before)
    for key in ("runner_up_z_um", "chosen_probability"):
        if (value := getattr(measurement, key)) is not None:
            record[key] = value
    if measurement.frame_out_of_focus:  # else as recorded before the first-frame check
        record["frame_out_of_focus"] = True
    return record


def measurement_of(record: dict[str, Any]) -> Measurement:
    # records written before the runner-up was kept have neither key: they replay as before
    return Measurement(
        record["z_um"],
        record["sigma_um"],
        frozenset(FocusFlag(f) for f in record["flags"]),
        record.get("runner_up_z_um"),
        record.get("chosen_probability"),
        bool(record.get("frame_out_of_focus", False)),
    )


def outcome_record(outcome: Outcome) -> dict[str, Any]:
    record = dataclasses.asdict(outcome)
    # as logged before tiles kept several frames: the logs of those scans still replay
    planes_um = record.pop("planes_um")
    return {**record, "planes_um": list(planes_um)} if planes_um else record


def outcome_of(record: dict[str, Any]) -> Outcome:
    return Outcome(**{**record, "planes_um": tuple(record.get("planes_um", ()))})


def event_of(logged: Logged) -> Event:
    """The log event of a recorded acquisition (its sequence is the acquisition's index)."""
    return Event(
        logged.acquisition.index,
        acquisition_record(logged.acquisition),
        measurement_record(logged.measurement),
        outcome_record(logged.outcome),
    )


def logged_of(event: Event) -> Logged:
    return Logged(
        acquisition_of(event.acquisition),
        measurement_of(event.measurement),
        outcome_of(event.outcome),
    )


def checked_logged_of(slide_id: str, event: Event, sequence: int, grid: ScanGrid) -> Logged:
    """The recorded acquisition of `event`, read back as the slide's record `sequence` on
    `grid`; CorruptLogError if the record fails its own checks: it does not decode, it is
    not at its place in the log, its tile is off the grid or not its outcome's, or its
    measurement is one the API refuses (a height beyond +/-MAX_ABS_UM, a sigma out of range).
    """
    try:
        logged = logged_of(event)
        problem = _problem(logged, event.sequence, sequence, grid)
    except (KeyError, TypeError, ValueError, AttributeError) as error:
        problem = f"{type(error).__name__}: {error}"
    if problem is not None:
        raise CorruptLogError(slide_id, sequence, problem)
    return logged


def _problem(logged: Logged, stored_as: int, sequence: int, grid: ScanGrid) -> str | None:
    """What is wrong with a record read back as record `sequence` (None: nothing)."""
    acquisition, outcome = logged.acquisition, logged.outcome
    tile = (acquisition.row, acquisition.col)
    z_um, sigma_um = logged.measurement.z_um, logged.measurement.sigma_um
    if not stored_as == acquisition.index == sequence:
        return f"it is stored as record {stored_as}, of acquisition {acquisition.index}"
    if not (all(isinstance(i, int) for i in tile) and grid.contains(*tile)):
        return f"tile {tile} is off the {grid.rows}x{grid.cols} grid"
    if (outcome.row, outcome.col) != tile:
        return f"its outcome is of tile ({outcome.row}, {outcome.col}), not {tile}"
    if z_um is not None and not abs(z_um) <= MAX_ABS_UM:
        return f"measured height {z_um} um is beyond +/-{MAX_ABS_UM:g} um"
    if sigma_um is not None and not MIN_SIGMA_UM <= sigma_um <= MAX_ABS_UM:
        return f"measurement sigma {sigma_um} um is out of {MIN_SIGMA_UM:g}..{MAX_ABS_UM:g} um"
    return None


#: Replayed and logged numbers that differ by at most this (relative, and absolute in um)
#: are the same result computed with other round-off (another numpy, BLAS or CPU).
REPLAY_TOLERANCE = 1e-6


def same_up_to_round_off(replayed: Any, logged: Any) -> bool:
    """Whether two records (JSON-like) are equal except for floats within `REPLAY_TOLERANCE`.

    Integers, flags, strings and None must match exactly: a tile, a frame count or
    an acceptance that changed is a different outcome, not round-off.
    """
    if isinstance(replayed, dict) and isinstance(logged, dict):
        return replayed.keys() == logged.keys() and all(
            same_up_to_round_off(replayed[k], logged[k]) for k in replayed
        )
    if isinstance(replayed, float) and isinstance(logged, float):
        return math.isclose(replayed, logged, rel_tol=REPLAY_TOLERANCE, abs_tol=REPLAY_TOLERANCE)
    return type(replayed) is type(logged) and replayed == logged
