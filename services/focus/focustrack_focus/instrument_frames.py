"""Each instrument's frame size, from its info reply: the bound on a frame a peer sends.

The focus service refuses a frame larger than its instrument's frames before it takes
the frame's buffer (`service.FrameAnalyser.frame_bytes_of`).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

import zenoh
from google.protobuf.message import DecodeError

from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc

log = logging.getLogger(__name__)

INSTRUMENTS = 16  # instruments whose frame size is kept (the most recent)
INFO_TIMEOUT_S = 5.0  # an instrument's info query; it is asked again after as long
INFO_QUERIES = 4  # info queries under way at once, at most


def info_frame_bytes(info: instrument_pb2.InstrumentInfo) -> int:
    """Bytes of one frame of the instrument that `info` describes: height x width x
    channels (one per letter of its channel order, at least one), each sample in the
    fewest of 1, 2, 4 or 8 bytes that hold its bit depth."""
    itemsize = next((size for size in (1, 2, 4) if info.bit_depth <= 8 * size), 8)
    return info.height * info.width * max(1, len(info.channel_order)) * itemsize


class InstrumentFrameSizes:
    """Each instrument's frame size, bytes (`info_frame_bytes`), from its info reply
    (``focustrack/v1/instrument/{name}/info``), for `FrameAnalyser.frame_bytes_of`.

    The first frame that names an instrument starts its info query in the background
    (never holding the frames up); until it answers, its size is not known (None), and
    it is asked again `timeout_s` after the last time. At most INFO_QUERIES queries are
    under way and INSTRUMENTS sizes kept, so made-up names cannot grow either.
    """

    def __init__(self, session: zenoh.Session, timeout_s: float = INFO_TIMEOUT_S) -> None:
        self.session = session
        self.timeout_s = timeout_s
        self._sizes: OrderedDict[str, int] = OrderedDict()
        self._asked: OrderedDict[str, float] = OrderedDict()  # when each was last asked, s
        self._lock = threading.Lock()

    def __call__(self, instrument: str) -> int | None:
        """The frame size of `instrument`, bytes, once it has answered; else None."""
        with self._lock:
            if instrument in self._sizes:
                return self._sizes[instrument]
            now_s = time.monotonic()
            asked_s = self._asked.get(instrument)
            under_way = sum(now_s - s < self.timeout_s for s in self._asked.values())
            if (asked_s is not None and now_s - asked_s < self.timeout_s) or (
                under_way >= INFO_QUERIES
            ):
                return None
            self._asked.pop(instrument, None)
            self._asked[instrument] = now_s
            while len(self._asked) > INSTRUMENTS:
                self._asked.popitem(last=False)
        threading.Thread(target=self._ask, args=(instrument,), daemon=True).start()
        return None

    def _ask(self, instrument: str) -> None:
        try:
            info = rpc.call(
                self.session,
                keys.info_key(instrument),
                instrument_pb2.AcquireRequest(),
                instrument_pb2.InstrumentInfo,
                self.timeout_s,
            )
        except (ValueError, DecodeError, rpc.RemoteError) as error:  # a bad name or reply; none
            log.info("instrument %r's frame size is not known: %s", instrument, error)
            return
        size = info_frame_bytes(info)
        if size == 0:  # an info without a frame format: nothing to bound by
            return
        log.info("instrument %r takes frames of %d bytes", instrument, size)
        with self._lock:
            self._sizes[instrument] = size
            while len(self._sizes) > INSTRUMENTS:
                self._sizes.popitem(last=False)
