"""The simulator with a phase specimen behind the real shell, over Zenoh on loopback:
phase stacks and their headers, the refusal of a reference plane beyond the travel, and
the true phase (evaluation only)."""

from __future__ import annotations

import threading
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from focustrack_core.v1 import common_pb2, instrument_pb2
from focustrack_core.wire import keys, rpc, session
from focustrack_instrument_sim import service
from focustrack_instrument_sim.simulated import SimulatedInstrument, microscope_from_options
from focustrack_instrument_sim.simulator_options import SimulatorOptions

SIZE = 128
OPTIONS = SimulatorOptions(seed=3, rows=2, cols=3, width=SIZE, height=SIZE, specimen="phase-blood")


@pytest.fixture(scope="module")
def client() -> Iterator[zenoh.Session]:
    """The simulator (phase-blood, truth served) in this process as "sim", and a client."""
    endpoint = session.loopback_endpoint()
    instrument = SimulatedInstrument(microscope_from_options(OPTIONS))
    with (
        session.open_session(listen=[endpoint]) as instrument_side,
        session.open_session(connect=[endpoint]) as client,
    ):
        shell = service.InstrumentService(instrument, instrument_side, "sim", serve_truth=True)
        shell.start()
        thread = threading.Thread(target=shell.serve)
        thread.start()
        try:
            yield client
        finally:
            shell.stop.set()
            thread.join()
            shell.close()
            instrument.close()


def _acquire(client: zenoh.Session, **fields) -> instrument_pb2.AcquireReply:
    request = instrument_pb2.AcquireRequest(
        **{"slide": "slide-0", "row": 1, "col": 2, "z_low_um": -2.0, "z_step_um": 1.0,
           "n_frames": 5, **fields}
    )  # fmt: skip
    return rpc.call(client, keys.acquire_key("sim"), request, instrument_pb2.AcquireReply)


def test_a_phase_stack_echoes_its_purpose_and_reference_and_says_how_it_was_imaged(
    client: zenoh.Session,
) -> None:
    phase = instrument_pb2.ACQUISITION_PURPOSE_PHASE
    header = _acquire(client, purpose=phase, reference_z_um=-0.5, sequence=5).header
    assert (header.purpose, header.reference_z_um, header.sequence) == (phase, -0.5, 5)
    assert (header.wavelength_um, header.condenser_na, header.objective_na) == (0.532, 0.2, 0.85)
    assert (header.photons_per_count, header.dark_counts) == (5.0, 100.0)
    assert header.channel_order == "RGB" and list(header.shape) == [5, SIZE, SIZE, 3]
    # a focus stack of the same specimen is imaged alike, and says so too
    focus = _acquire(client, sequence=6).header
    assert focus.purpose == instrument_pb2.ACQUISITION_PURPOSE_FOCUS
    assert (focus.wavelength_um, focus.condenser_na, focus.photons_per_count) == (0.532, 0.2, 5.0)


@pytest.mark.parametrize(
    ("fields", "code", "field"),
    [
        ({"purpose": 1, "reference_z_um": 500.0}, common_pb2.ERROR_CODE_Z_OUT_OF_RANGE,
         "reference_z_um"),
        ({"purpose": 1, "reference_z_um": float("inf")}, common_pb2.ERROR_CODE_MALFORMED_REQUEST,
         "reference_z_um"),
        ({"purpose": 7}, common_pb2.ERROR_CODE_MALFORMED_REQUEST, "purpose"),
    ],
)  # fmt: skip
def test_a_phase_request_the_instrument_cannot_take_is_refused(
    client: zenoh.Session, fields: dict, code: int, field: str
) -> None:
    with pytest.raises(rpc.RemoteError) as refused:
        _acquire(client, **fields)
    assert (refused.value.error.code, refused.value.error.field) == (code, field)


def _phase_truth(
    client: zenoh.Session, key_expr: str
) -> tuple[instrument_pb2.PhaseTruth, np.ndarray]:
    """The reply to a phase-truth query: its header and pixels; RemoteError on an error."""
    (reply,) = list(client.get(key_expr, timeout=10))
    if reply.err is not None:
        raise rpc.RemoteError(rpc.error_of(reply.err))
    assert reply.ok is not None and reply.ok.attachment is not None
    header = instrument_pb2.PhaseTruth.FromString(reply.ok.attachment.to_bytes())
    pixels = np.frombuffer(reply.ok.payload.to_bytes(), dtype=np.dtype(header.dtype))
    return header, pixels.reshape(tuple(header.shape))


def test_the_true_phase_of_a_tile_is_served_apart(client: zenoh.Session) -> None:
    key_expr = keys.phase_truth_key("sim", "slide-0", 1, 2)
    assert key_expr.startswith("focustrack/v1/eval/")
    header, phase_rad = _phase_truth(client, key_expr)
    assert (header.instrument, header.slide, header.row, header.col) == ("sim", "slide-0", 1, 2)
    assert list(header.shape) == [SIZE, SIZE] and header.dtype == "<f4"
    scope = microscope_from_options(OPTIONS)  # the same slide, in this process
    expected = scope.true_phase("slide-0", 1, 2)
    scope.close()
    np.testing.assert_array_equal(phase_rad, expected.phase_rad)
    assert header.pixel_size_um == pytest.approx(expected.pixel_size_um)
    slide_truth = rpc.call(client, keys.truth_key("sim", "slide-0"),
                           instrument_pb2.AcquireRequest(), instrument_pb2.SlideTruth)  # fmt: skip
    assert header.focus_z_um == pytest.approx(slide_truth.best_focus_um[1 * 3 + 2])
    assert 0.5 < phase_rad.max() < 3.0  # red cells, in radians


@pytest.mark.parametrize(
    ("slide", "row", "col", "code"),
    [
        ("slide-7", 0, 0, common_pb2.ERROR_CODE_UNKNOWN_SLIDE),
        ("slide-0", 2, 0, common_pb2.ERROR_CODE_TILE_OUTSIDE_SLIDE),
        ("slide-0", 0, 3, common_pb2.ERROR_CODE_TILE_OUTSIDE_SLIDE),
    ],
)
def test_the_true_phase_of_a_tile_that_is_not_there_is_an_error(
    client: zenoh.Session, slide: str, row: int, col: int, code: int
) -> None:
    with pytest.raises(rpc.RemoteError) as refused:
        _phase_truth(client, keys.phase_truth_key("sim", slide, row, col))
    assert refused.value.error.code == code


def test_a_tile_key_that_names_no_tile_is_malformed(client: zenoh.Session) -> None:
    with pytest.raises(rpc.RemoteError) as refused:
        _phase_truth(client, "focustrack/v1/eval/phase/sim/slide-0/one/2")
    assert refused.value.error.code == common_pb2.ERROR_CODE_MALFORMED_REQUEST


def test_without_serve_truth_there_is_no_true_phase_on_the_bus() -> None:
    endpoint = session.loopback_endpoint()
    instrument = SimulatedInstrument(microscope_from_options(OPTIONS))
    with (
        session.open_session(listen=[endpoint]) as instrument_side,
        session.open_session(connect=[endpoint]) as client,
    ):
        shell = service.InstrumentService(instrument, instrument_side, "sim")
        shell.start()
        try:
            assert shell.phase_truth is None
            replies = list(client.get(keys.phase_truth_key("sim", "slide-0", 0, 0), timeout=1))
            assert [reply.ok for reply in replies if reply.ok is not None] == []
        finally:
            shell.close()
            instrument.close()
