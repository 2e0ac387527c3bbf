"""The scan's laser readings: an acquisition of purpose `laser` is a query to the instrument's
reflection autofocus (`focustrack/v1/instrument/{name}/laser`), not a z-stack.

The estimator's `kf-2d-laser` asks for one before each tile's own acquisition; the plan
(`plan.scan_plan`) yields `plan.ReadLaser`, the engine queries the instrument
(`read_laser`) and the reading goes back to the estimator as the acquisition's
measurement: the coverslip's height (um) with the sensor's sigma. No frame is taken,
so nothing is kept.
"""

from __future__ import annotations

from focustrack_core.domain import Acquisition, Measurement
from focustrack_core.rest import to_api
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_scheduler.clients import InstrumentClient


def read_laser(
    instrument: InstrumentClient, slide: str, acquisition: Acquisition
) -> tuple[Measurement, float]:
    """Query the instrument's laser over `acquisition`'s tile: the reading (z um, sigma um)
    and the seconds it took (the move and the reading); RemoteError when it refuses or has
    no laser. A reading that is no height (not finite, beyond the API's bounds) is no
    reading (the strategy's images decide); its sigma is taken within the API's bounds
    (0: the laser's own sigma, the strategy's setting)."""
    reading = rpc.call(
        instrument.session,
        keys.laser_key(instrument.name),
        instrument_pb2.LaserRequest(slide=slide, row=acquisition.row, col=acquisition.col),
        instrument_pb2.LaserReading,
        instrument.timeout_s,
    )
    if not to_api.is_height(reading.z_um):  # posted as it is, it would end the scan
        return Measurement(z_um=None), reading.timing.total_s
    sigma_um = to_api.sigma_within_bounds(reading.sigma_um)
    return Measurement(z_um=reading.z_um, sigma_um=sigma_um), reading.timing.total_s
