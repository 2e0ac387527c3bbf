"""`focustrack serve focus`: the focus service on Zenoh and over REST, in one process.

Zenoh: subscribes to ``focustrack/v1/zstack/**`` and publishes a FocusResult on
``focustrack/v1/focus/{slide}/{row}/{col}`` for every stack; a stack that cannot
be read gets a FocusResult whose `error` says why (code BAD_STACK). Stacks are
taken from a bounded FIFO by one worker thread, so a burst waits (back pressure
to the publisher) instead of piling up without bound.
REST: the FastAPI app of `app.py`, served by uvicorn on --host/--port.
"""

from __future__ import annotations

import argparse
import logging
import threading
import time
from dataclasses import replace

import numpy as np
import uvicorn
import zenoh

from focustrack_core.config import command_main
from focustrack_core.v1 import common_pb2, focus_pb2, instrument_pb2
from focustrack_core.wire import keys
from focustrack_core.wire.codec import decode_zstack
from focustrack_core.wire.rpc import protobuf_encoding
from focustrack_core.wire.session import DEFAULT_ENDPOINT, add_zenoh_arguments, session_from_args
from focustrack_focus.app import create_app
from focustrack_focus.metrics import DEFAULT_METRIC, METRICS
from focustrack_focus.peak import PeakMode, PeakSettings
from focustrack_focus.pipeline import FocusResult, FocusSettings, focus_stack
from focustrack_focus.preprocess import GREEN, Preprocess, lowpass_sigma_for_optics

log = logging.getLogger(__name__)

ZSTACK_SUBSCRIPTION = f"{keys.PREFIX}/zstack/**"
FOCUS_RESULT_ENCODING = protobuf_encoding(focus_pb2.FocusResult)
QUEUE_STACKS = 8  # stacks waiting for the worker before the publisher is held back


def settings_for(
    header: instrument_pb2.ZStackHeader, base: FocusSettings, na: float | None
) -> FocusSettings:
    """`base` adapted to one stack: its green channel, and (with `na`) a low-pass matched to
    its pixel size (thesis A-1-1)."""
    preprocess = base.preprocess
    order = header.channel_order.upper()
    if "G" in order:
        preprocess = replace(preprocess, channel=order.index("G"))
    if na is not None and header.pixel_size_um > 0:
        sigma_px = lowpass_sigma_for_optics(header.pixel_size_um, na)
        preprocess = replace(preprocess, lowpass_sigma_px=sigma_px)
    return replace(base, preprocess=preprocess)


def result_message(
    tile: keys.TileKey,
    header: instrument_pb2.ZStackHeader | None,
    result: FocusResult | None = None,
    error: str = "",
) -> focus_pb2.FocusResult:
    """The wire FocusResult of a stack: its result, or an error saying why there is none."""
    message = focus_pb2.FocusResult(slide=tile.slide, row=tile.row, col=tile.col)
    if header is not None:
        message.sequence = header.sequence
        message.instrument = header.instrument
    if result is not None:
        message.metric = result.metric
        message.z_um.extend(result.z_um.tolist())
        message.scores.extend(result.scores.tolist())
        if result.best_z_um is not None:
            message.best_z_um = result.best_z_um
        if result.sigma_um is not None:
            message.sigma_um = result.sigma_um
        if result.runner_up_z_um is not None:
            message.runner_up_z_um = result.runner_up_z_um
        if result.chosen_probability is not None:
            message.chosen_probability = result.chosen_probability
        message.flags.extend(sorted(flag.proto for flag in result.flags))
        message.compute_time_s = result.compute_time_s
    if error:
        message.error.CopyFrom(
            common_pb2.Error(code=common_pb2.ERROR_CODE_BAD_STACK, message=error)
        )
    return message


def analyse_sample(
    key: str, payload: bytes, attachment: bytes | None, base: FocusSettings, na: float | None
) -> focus_pb2.FocusResult:
    """The FocusResult for one z-stack sample (ValueError only when its key names no tile)."""
    tile = keys.parse_zstack_key(key)
    header = None
    try:
        header, pixels = decode_zstack(payload, attachment)
        frames = pixels[..., 0] if pixels.shape[-1] == 1 else pixels
        z_um = np.asarray(header.z_um, dtype=float)
        result = focus_stack(frames, z_um, settings_for(header, base, na))
    except Exception as error:  # a bad stack is answered with an error, never a crash
        log.warning("stack on %s: %s", key, error)
        return result_message(tile, header, error=f"{type(error).__name__}: {error}")
    return result_message(tile, header, result)


class ZenohFocusWorker:
    """Subscribes to z-stacks and publishes their focus results, on its own thread."""

    def __init__(self, session: zenoh.Session, settings: FocusSettings, na: float | None = None):
        self.session = session
        self.settings = settings
        self.na = na
        self.n_published = 0
        self._subscriber = session.declare_subscriber(
            ZSTACK_SUBSCRIPTION, zenoh.handlers.FifoChannel(QUEUE_STACKS)
        )
        self._thread = threading.Thread(target=self._serve, name="focus-zenoh", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        for sample in self._subscriber:  # ends when the subscriber is undeclared
            key = str(sample.key_expr)
            attachment = None if sample.attachment is None else sample.attachment.to_bytes()
            try:
                message = analyse_sample(
                    key, sample.payload.to_bytes(), attachment, self.settings, self.na
                )
            except ValueError as error:  # the key names no tile: nowhere to answer
                log.warning("ignored sample on %s: %s", key, error)
                continue
            self.session.put(
                keys.focus_key(message.slide, message.row, message.col),
                message.SerializeToString(),
                encoding=FOCUS_RESULT_ENCODING,
                congestion_control=zenoh.CongestionControl.BLOCK,
            )
            self.n_published += 1

    def close(self, timeout_s: float = 5.0) -> None:
        self._subscriber.undeclare()
        self._thread.join(timeout_s)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--host", default="127.0.0.1", help="HTTP address (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=8002, help="HTTP port (default 8002)")
    add_zenoh_arguments(parser, default_connect=[DEFAULT_ENDPOINT])
    parser.add_argument("--metric", choices=list(METRICS), default=DEFAULT_METRIC)
    parser.add_argument(
        "--focus-mode",
        choices=[mode.value for mode in PeakMode],
        default="max",
        help="max: stained specimens; valley: unstained, phase-like ones",
    )
    parser.add_argument(
        "--lowpass-sigma-px",
        type=float,
        default=None,
        help="Gaussian low-pass sigma, px (default: matched to each stack's "
        "pixel size and --na; 2 px where a stack gives no pixel size)",
    )
    parser.add_argument("--na", type=float, default=0.85, help="numerical aperture (0.85)")
    parser.add_argument(
        "--min-structure-snr",
        type=float,
        default=FocusSettings.min_structure_snr,
        help="a stack whose through-focus change stands fewer noise spreads than this above "
        "its pixel noise is flat (default %(default)g; --min-structure-snr=-inf: never)",
    )


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    preprocess = Preprocess(channel=GREEN)
    if args.lowpass_sigma_px is not None:
        preprocess = replace(preprocess, lowpass_sigma_px=args.lowpass_sigma_px)
    settings = FocusSettings(
        preprocess,
        args.metric,
        PeakSettings(mode=PeakMode(args.focus_mode)),
        min_structure_snr=args.min_structure_snr,
    )
    na = None if args.lowpass_sigma_px is not None else args.na
    session = session_from_args(args)
    worker = ZenohFocusWorker(session, settings, na)
    log.info(
        "focus service: zenoh %s -> %s/focus/..., http://%s:%d (metric %s)",
        ZSTACK_SUBSCRIPTION,
        keys.PREFIX,
        args.host,
        args.port,
        args.metric,
    )
    started = time.perf_counter()
    try:
        uvicorn.run(create_app(settings), host=args.host, port=args.port, log_level="info")
    finally:
        worker.close()
        session.close()
        log.info(
            "published %d results in %.0f s", worker.n_published, time.perf_counter() - started
        )
    return 0


#: Every option's environment variable is this prefix and its name (focustrack_core.config).
ENV_PREFIX = "FOCUSTRACK_FOCUS_"

#: The `focustrack-focus` console script (and `python -m focustrack_focus`).
main = command_main(
    "focustrack-focus", "the focus service (Zenoh and REST)", add_arguments, run, ENV_PREFIX
)
