"""A scan's laser readings against what the instrument's info says of its laser (real Zenoh
on loopback, the engine's own code, a stand-in for the instrument).

An instrument without a laser autofocus has no laser queryable, so a reading asked of it
found nobody to answer, and the engine retried it as an outage for a minute before the
scan failed on its first tile. The instrument's info now says whether it has one: an
instrument that says it has none refuses the scan at once; one that says nothing (older
than the field) is still retried as before.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import zenoh

from focustrack_client import EstimatorClient
from focustrack_client import models as api
from focustrack_core.domain import Acquisition, Measurement, Purpose, ZRange
from focustrack_core.rest import to_api
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_scheduler.clients import InstrumentClient, SlideListener
from focustrack_scheduler.engine import Engine, ScanRefusedError, ServiceUnavailableError
from focustrack_scheduler.plan import DescribeSlide, Plan, ReadLaser
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy

SLIDE = "s1"
READING = ReadLaser(SLIDE, Acquisition(0, 1, 2, ZRange(0.0, 1.0, 1), Purpose.LASER, True))


class Instrument:
    """Answers the info query (a 3x3 slide, `laser` as given: None leaves it unset) and, with
    a laser, laser readings of `reading` (z um, sigma um)."""

    def __init__(
        self, bus: zenoh.Session, laser: bool | None, reading: tuple[float, float] = (1.5, 0.2)
    ) -> None:
        self._laser, self._reading = laser, reading
        self._queryables = [rpc.declare_answering(bus, keys.info_key("sim"), self._info)]
        if laser:
            self._queryables.append(rpc.declare_answering(bus, keys.laser_key("sim"), self._read))

    def _info(self, query: zenoh.Query) -> instrument_pb2.InstrumentInfo:
        slide = instrument_pb2.SlideInfo(slide=SLIDE, rows=3, cols=3, pitch_um=100.0)
        info = instrument_pb2.InstrumentInfo(instrument="sim", slides=[slide])
        if self._laser is not None:
            info.laser = self._laser
        return info

    def _read(self, query: zenoh.Query) -> instrument_pb2.LaserReading:
        request = rpc.parse_request(query, instrument_pb2.LaserRequest)
        return instrument_pb2.LaserReading(
            instrument="sim", slide=request.slide, row=request.row, col=request.col,
            z_um=self._reading[0], sigma_um=self._reading[1],
            timing=instrument_pb2.Timing(total_s=0.01),
        )  # fmt: skip

    def close(self) -> None:
        for queryable in self._queryables:
            queryable.undeclare()


def read_one(
    sessions: tuple[zenoh.Session, zenoh.Session],
    out_dir: Path,
    laser: bool | None,
    outage_s: float,
    reading: tuple[float, float] = (1.5, 0.2),
) -> Measurement:
    """Describe the slide and read the laser over one tile (it reads `reading`), with an
    engine that retries a silent instrument for `outage_s`; the measurement to post."""
    stand_in, scheduler = sessions
    instrument = Instrument(stand_in, laser, reading)
    engine = Engine(
        InstrumentClient(scheduler, "sim", timeout_s=5),
        SlideListener(scheduler, SLIDE),
        EstimatorClient("http://127.0.0.1:9"),  # this plan asks no estimator
        ScanRecord(out_dir),
        RetryPolicy(instrument_outage_s=outage_s, backoff_initial_s=0.05),
    )
    readings: list[Measurement] = []

    def plan() -> Plan:
        yield DescribeSlide("sim", SLIDE)
        readings.append((yield READING))
        return "read"

    try:
        engine.run(plan())
    finally:
        engine.listener.close()
        engine.record.close()
        instrument.close()
    return readings[0]


@pytest.mark.timeout(30)
def test_an_instrument_that_says_it_has_no_laser_refuses_the_reading_at_once(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    """Refused before any retry: with an hour of outage allowed, a retry would time out."""
    with pytest.raises(ScanRefusedError, match="instrument 'sim' has no laser autofocus"):
        read_one(sessions, tmp_path, laser=False, outage_s=3600.0)


@pytest.mark.parametrize(
    ("reading", "posted"),
    [((1.5, 0.2), Measurement(1.5, 0.2)),
     ((1.5, 0.0), Measurement(1.5)),  # no sigma: the strategy's own for its laser
     ((1.5, 1e-6), Measurement(1.5, api.MIN_SIGMA_UM)),  # the API refused it: a traceback
     ((float("nan"), 0.2), Measurement(None))],  # no reading: the images decide
)  # fmt: skip
def test_an_instrument_with_a_laser_gives_its_reading_within_the_apis_bounds(
    sessions: tuple[zenoh.Session, zenoh.Session],
    tmp_path: Path,
    reading: tuple[float, float],
    posted: Measurement,
) -> None:
    measurement = read_one(sessions, tmp_path, laser=True, outage_s=10.0, reading=reading)
    assert measurement == posted
    to_api.measurement_in(READING.acquisition, measurement)  # the engine's post: valid


def test_an_instrument_that_does_not_say_is_retried_as_an_outage(
    sessions: tuple[zenoh.Session, zenoh.Session], tmp_path: Path
) -> None:
    """An instrument older than the field may have a laser that is restarting: the reading
    is retried for the outage allowed, then the scan says nobody answered."""
    with pytest.raises(ServiceUnavailableError, match="did not answer the laser reading"):
        read_one(sessions, tmp_path, laser=None, outage_s=0.5)
