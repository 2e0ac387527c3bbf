"""A slide's log records: the domain's acquisitions, measurements and outcomes as JSON objects.

What goes into the store (`event_store.Event`) and comes back on a restart. The
records are the contract with logs written by earlier versions: a field added
to a domain type must read from older records too (as `planes_um` does).
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

from focustrack_core.domain import Acquisition, FocusFlag, Measurement, Outcome, Purpose, ZRange
from focustrack_estimator.event_store import Event


@dataclasses.dataclass(frozen=True)
class Logged:
    """One recorded acquisition, in memory: the tile asked for, what was sent, what it did."""

    acquisition: Acquisition
    measurement: Measurement
    outcome: Outcome


def acquisition_record(acquisition: Acquisition) -> dict[str, Any]:
    return dataclasses.asdict(acquisition)


def acquisition_of(record: dict[str, Any]) -> Acquisition:
    return Acquisition(
        **{**record, "z": ZRange(**record["z"]), "purpose": Purpose(record["purpose"])}
    )


def measurement_record(measurement: Measurement) -> dict[str, Any]:
    return {
        "z_um": measurement.z_um,
        "sigma_um": measurement.sigma_um,
        "flags": sorted(measurement.flags),
    }


def measurement_of(record: dict[str, Any]) -> Measurement:
    return Measurement(
        record["z_um"], record["sigma_um"], frozenset(FocusFlag(f) for f in record["flags"])
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
