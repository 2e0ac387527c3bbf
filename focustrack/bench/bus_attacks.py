"""Attacks on the Zenoh bus, from a peer that holds no key: `focustrack bench chaos` runs them.

- **Replay** (`ResultReplay`): record the genuine focus results of one scan of a slide
  (payload and tag, as the focus service put them), then, during a later scan of the
  same slide after its focus moved, re-publish each the moment the stack of the same
  tile and sequence starts (its first frame), before the focus service can answer.
  The tag is genuine, so only a binding of the result to its acquisition stops it.
- **Forgery** (`FrameForger`): on the first frame of every stack, publish a stack of
  frames of its own on the same frames key (same slide, tile, sequence, z and shape;
  another clock, so the focus service takes it for a stack of its own): a sharp
  pattern whose contrast peaks at the frame farthest from the true focus (given to the
  forger by the bench, so that a measurement made from it stands out). The focus
  service scores it and tags its result like any other.
- **Memory** (`big_frames`, `incomplete_stacks`, `repeated_frames_request`): frames
  declared at 1 GiB sent part by part and never finished, stacks of 32 MiB frames that
  never get their other frames, and one FramesRequest naming the same frame 2,000
  times. The bench reads each service's peak memory around each.

`taken(log_path, sent, tolerance_um)` counts the measurements of a scan's log that
took one of the values sent; `ResultReplay.accepted` those that took a replayed result.
"""

from __future__ import annotations

import json
import multiprocessing
import threading
import time
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from focustrack_core.v1 import focus_pb2, instrument_pb2
from focustrack_core.wire import codec, keys, rpc
from focustrack_core.wire.session import open_session

#: (row, col, sequence) of a stack, as a scan's log names its measurements.
StackKey = tuple[int, int, int]

#: A slide name of the memory attacks' own: their frames name no tile a scan waits for.
ATTACK_SLIDE = "bus-attack"

#: The forged frames' contrast falls to 1/e this far from their sharp plane, um (about
#: the depth of field of the simulated 0.85 NA objective).
FORGED_FOCUS_WIDTH_UM = 1.0

#: A measurement this close to a forged stack's sharp plane came from the forged frames,
#: um: the plane is a frame step (0.5 um in a scan's stacks) or more from the true focus,
#: and the focus service measures genuine stacks to about 0.03 um.
FORGED_TOLERANCE_UM = 0.2

_RESULT_ENCODING = rpc.protobuf_encoding(focus_pb2.FocusResult)

#: Seconds an attacker's process may take to answer the bench (its start-up included).
PEER_TIMEOUT_S = 60.0


def _frame_start(sample: zenoh.Sample) -> instrument_pb2.ZFrameHeader | None:
    """The header of `sample` if it starts a frame (a whole frame, or its first part)."""
    attachment = sample.attachment
    try:
        header = codec.zframe_header(None if attachment is None else attachment.to_bytes())
    except ValueError:
        return None
    return header if header.part_offset == 0 else None


def _first_frame(sample: zenoh.Sample) -> instrument_pb2.ZFrameHeader | None:
    """The header of `sample` if it starts the first frame of a stack."""
    header = _frame_start(sample)
    return header if header is not None and header.index == 0 else None


def _put(
    session: zenoh.Session,
    key_expr: str,
    payload: bytes | bytearray,
    encoding: zenoh.Encoding,
    attachment: bytes | None,
) -> None:
    """A put that waits for room (Zenoh's default, DROP, loses what a busy link cannot take)."""
    session.put(
        key_expr,
        payload,
        encoding=encoding,
        congestion_control=zenoh.CongestionControl.BLOCK,
        attachment=attachment,
    )


class PeerProcess:
    """An attacker (`kind(session, *args)`, e.g. `ResultReplay`) on a session of its own
    to `endpoint`, in a process of its own, as a context manager.

    A peer on another host takes frames and puts its messages without waiting for the
    bench's scheduler, which shares this interpreter (and its lock): here, one in the
    same process saw a stack's first frame after the focus service had scored all of
    it. `call(name, *args)` runs the attacker's method `name` there (or reads its
    attribute) and gives back what it returns.
    """

    def __init__(self, endpoint: str, kind: type, *args: object) -> None:
        context = multiprocessing.get_context("spawn")  # no copy of this process's threads
        self._connection, child = context.Pipe()
        self._process = context.Process(
            target=_serve_peer, args=(child, endpoint, kind, args), name=kind.__name__
        )
        self._process.start()
        self._answer()  # its session is open and it listens

    def _answer(self) -> Any:
        if not self._connection.poll(PEER_TIMEOUT_S):
            raise RuntimeError(f"the {self._process.name} peer did not answer")
        status, value = self._connection.recv()
        if status != "ok":
            raise RuntimeError(f"the {self._process.name} peer failed: {value}")
        return value

    def call(self, name: str, *args: object) -> Any:
        self._connection.send((name, args))
        return self._answer()

    def __enter__(self) -> PeerProcess:
        return self

    def __exit__(self, *_: object) -> None:
        if self._process.is_alive():
            self._connection.send(None)
            self._process.join(PEER_TIMEOUT_S)
        if self._process.is_alive():
            self._process.kill()
            self._process.join()


def _serve_peer(
    connection: Connection, endpoint: str, kind: type, args: tuple[object, ...]
) -> None:
    """The attacker's process: its session, then `PeerProcess.call`s until told to end."""
    try:
        with open_session(connect=[endpoint]) as session:
            peer = kind(session, *args)
            connection.send(("ok", None))
            while (request := connection.recv()) is not None:
                name, call_args = request
                try:
                    value = getattr(peer, name)
                    connection.send(("ok", value(*call_args) if callable(value) else value))
                except Exception as error:  # said to the bench, which raises it
                    connection.send(("error", f"{type(error).__name__}: {error}"))
            peer.close()
    except Exception as error:  # the session did not open: the bench raises it
        connection.send(("error", f"{type(error).__name__}: {error}"))


def taken(log_path: Path, sent: dict[StackKey, float], tolerance_um: float) -> int:
    """Measurements in a scan's log (`scan_log.jsonl`) of a stack in `sent` whose z is
    within `tolerance_um` of the z sent for it."""
    count = 0
    for line in log_path.read_text().splitlines():
        entry = json.loads(line)
        if entry["event"] != "measured" or entry["z_um"] is None:
            continue
        z_um = sent.get((entry["row"], entry["col"], entry["sequence"]))
        count += z_um is not None and abs(entry["z_um"] - z_um) <= tolerance_um
    return count


class ResultReplay:
    """Records a slide's focus results (`record`), then replays them (`replay`).

    Keeps the last result of each (row, col, sequence). A replayed result is put as the
    stack's first frame comes, and again and again from its last frame until just after
    the genuine result for it (`FLOOD_PERIOD_S`, `FLOOD_AFTER_S`), so that it is the
    latest one whenever the scheduler looks. `replayed` maps each stack it replayed a
    result for to that result's scores (`accepted` finds them in a log).
    """

    #: Seconds between copies of a replayed result while the genuine one is due.
    FLOOD_PERIOD_S = 3e-4
    #: Copies go on this long after the genuine result came, s.
    FLOOD_AFTER_S = 3e-3
    #: And stop this long after the stack's last frame in any case, s.
    FLOOD_MAX_S = 1.0

    def __init__(self, session: zenoh.Session, slide: str) -> None:
        self.session, self.slide = session, slide
        self.captured: dict[StackKey, tuple[str, bytes, bytes | None, list[float]]] = {}
        self.replayed: dict[StackKey, list[float]] = {}
        self.n_replayed = 0  # stacks it replayed a result for
        self._lock = threading.Lock()
        self._subscribers: list[zenoh.Subscriber[None]] = []
        self._replaying = False
        self._answered: set[tuple[str, int, float]] = set()  # stacks (key, sequence, clock)
        self._genuine: dict[StackKey, threading.Event] = {}  # set when its result came

    def record(self) -> None:
        """Record every focus result of the slide from now on (until `stop`)."""
        self.stop()
        self._subscribers = [
            self.session.declare_subscriber(keys.focus_pattern(self.slide), self._on_result)
        ]

    def replay(self) -> None:
        """Re-publish the recorded results from now on (until `stop`)."""
        self.stop()
        self._replaying = True
        self._subscribers = [
            self.session.declare_subscriber(keys.zframe_pattern(self.slide), self._on_frame),
            self.session.declare_subscriber(keys.focus_pattern(self.slide), self._on_result),
        ]

    def stop(self) -> None:
        for subscriber in self._subscribers:
            subscriber.undeclare()
        self._subscribers, self._replaying = [], False
        for genuine in self._genuine.values():
            genuine.set()  # floods end

    close = stop  # the end of it: what `PeerProcess` calls on every attacker

    @property
    def n_captured(self) -> int:
        """Results recorded (the last of each stack)."""
        with self._lock:
            return len(self.captured)

    def _on_result(self, sample: zenoh.Sample) -> None:
        payload = codec.payload_bytes(sample.payload)
        try:
            result = focus_pb2.FocusResult.FromString(payload)
        except Exception:  # a DecodeError: not a result to replay
            return
        stack = (result.row, result.col, result.sequence)
        with self._lock:
            if not self._replaying:
                tag = None if sample.attachment is None else sample.attachment.to_bytes()
                self.captured[stack] = (str(sample.key_expr), payload, tag, list(result.scores))
                return
            found, genuine = self.captured.get(stack), self._genuine.get(stack)
        if found is not None and genuine is not None and found[1] != payload:
            genuine.set()  # the genuine result: the flood goes on a little longer, then ends

    def _on_frame(self, sample: zenoh.Sample) -> None:
        header = _frame_start(sample)
        if header is None:
            return
        stack = header.stack
        key = (stack.row, stack.col, stack.sequence)
        stack_id = (str(sample.key_expr), stack.sequence, stack.clock_s)
        with self._lock:
            found = self.captured.get(key)
            if found is None:
                return
            if header.index == 0 and stack_id not in self._answered:
                self._answered.add(stack_id)
                self.n_replayed += 1
                self.replayed[key] = found[3]
                self._genuine[key] = threading.Event()
                first = True
            elif header.index == stack.shape[0] - 1 and key in self._genuine:
                first = False
            else:
                return
        if first:
            _put(self.session, found[0], found[1], _RESULT_ENCODING, found[2])
        else:
            genuine = self._genuine[key]
            threading.Thread(target=self._flood, args=(found, genuine), daemon=True).start()

    def _flood(
        self, found: tuple[str, bytes, bytes | None, list[float]], genuine: threading.Event
    ) -> None:
        """Put `found` every FLOOD_PERIOD_S until FLOOD_AFTER_S after `genuine` is set."""
        key_expr, payload, tag, _ = found
        end_s = time.monotonic() + self.FLOOD_MAX_S
        came = False
        while time.monotonic() < end_s:
            _put(self.session, key_expr, payload, _RESULT_ENCODING, tag)
            if not came and genuine.is_set():
                came, end_s = True, min(end_s, time.monotonic() + self.FLOOD_AFTER_S)
            time.sleep(self.FLOOD_PERIOD_S)

    def accepted(self, log_path: Path) -> int:
        """Measurements in a scan's log (`scan_log.jsonl`) that took a replayed result: their
        curve is its scores to the last digit (the slide's new images score otherwise),
        which finds flat results, without a best z, as well."""
        with self._lock:
            replayed = dict(self.replayed)
        count = 0
        for line in log_path.read_text().splitlines():
            entry = json.loads(line)
            if entry["event"] != "measured" or not entry.get("curve_scores"):
                continue
            scores = replayed.get((entry["row"], entry["col"], entry["sequence"]))
            count += scores == entry["curve_scores"]
        return count


def forged_stack(
    header: instrument_pb2.ZStackHeader, sharp_index: int, seed: int = 0
) -> np.ndarray:
    """Frames (frames, height, width, channels) of `header`'s shape and dtype: a coarse
    random pattern whose contrast peaks at frame `sharp_index` and falls off with z."""
    n, height, width, channels = header.shape
    dtype = np.dtype(header.dtype)
    top = float(2 ** (header.bit_depth or 8 * dtype.itemsize) - 1)
    rng = np.random.default_rng(seed)
    blocks = rng.choice([-1.0, 1.0], size=(-(-height // 8), -(-width // 8)))
    pattern = np.kron(blocks, np.ones((8, 8)))[:height, :width, None]
    z_um = np.asarray(header.z_um)
    contrast = np.exp(-(((z_um - z_um[sharp_index]) / FORGED_FOCUS_WIDTH_UM) ** 2))
    frames = np.empty((n, height, width, channels), dtype)
    for index in range(n):
        noise = rng.normal(0.0, 0.005 * top, (height, width, 1))
        frame = top * (0.5 + 0.35 * contrast[index] * pattern) + noise
        frames[index] = np.clip(frame, 0, top).astype(dtype)
    return frames


class FrameForger:
    """Publishes a forged stack for every stack of `slide` it sees start (module docstring).

    `truth_um` (rows, cols) is the slide's true focus, um: the sharp plane is the frame
    farthest from it, not counting the first and last frames where a stack has more than
    two (a peak at an end is flagged and not measured). `forged` maps each stack it
    forged to the z of that plane, um.
    """

    def __init__(self, session: zenoh.Session, slide: str, truth_um: np.ndarray) -> None:
        self.session, self.truth_um = session, truth_um
        self.forged: dict[StackKey, float] = {}
        self.n_forged = 0
        self._lock = threading.Lock()
        self._answered: set[tuple[str, int, float]] = set()  # genuine stacks, and its own
        self._subscriber = session.declare_subscriber(keys.zframe_pattern(slide), self._on_frame)

    def _on_frame(self, sample: zenoh.Sample) -> None:
        header = _first_frame(sample)
        if header is None:
            return
        key_expr = str(sample.key_expr)
        genuine = header.stack
        forged_header = instrument_pb2.ZStackHeader()
        forged_header.CopyFrom(genuine)
        forged_header.clock_s = genuine.clock_s + 1e-3  # a stack of its own to the focus service
        with self._lock:
            if (key_expr, genuine.sequence, genuine.clock_s) in self._answered:
                return  # a stack it answered already, or one of its own
            self._answered.add((key_expr, genuine.sequence, genuine.clock_s))
            self._answered.add((key_expr, forged_header.sequence, forged_header.clock_s))
        z_um = np.asarray(genuine.z_um)
        candidates = np.arange(1, z_um.size - 1) if z_um.size > 2 else np.arange(z_um.size)
        truth_um = float(self.truth_um[genuine.row, genuine.col])
        sharp = int(candidates[np.argmax(np.abs(z_um[candidates] - truth_um))])
        frames = forged_stack(forged_header, sharp, seed=genuine.sequence)
        for index, frame in enumerate(frames):
            attachment = codec.frame_header(forged_header, index, frame).SerializeToString()
            payload = codec.raw_payload(frame)
            _put(self.session, key_expr, payload, codec.ZFRAME_ENCODING, attachment)
        with self._lock:
            self.n_forged += 1
            self.forged[(genuine.row, genuine.col, genuine.sequence)] = float(z_um[sharp])

    def accepted(self, log_path: Path) -> int:
        """Measurements in a scan's log made of its frames: at their sharp plane."""
        with self._lock:
            forged = dict(self.forged)
        return taken(log_path, forged, FORGED_TOLERANCE_UM)

    def close(self) -> None:
        self._subscriber.undeclare()


@dataclass(frozen=True)
class MemoryAttackSizes:
    """How hard the memory attacks push (defaults: the issue's probe)."""

    big_frames: int = 8  # frames declared at `big_frame_bytes`, each left unfinished
    big_frame_bytes: int = 1 << 30
    big_frame_sent_bytes: int = 208 << 20  # sent of each, in parts: 8 x 208 MiB = 1.66 GB
    incomplete_stacks: int = 24  # stacks of 3 frames, of which only the first is sent
    incomplete_frame_bytes: int = 32 << 20
    repeated_index: int = 2000  # copies of one index in one FramesRequest


#: The sizes of the attacker's probe, which `focustrack bench chaos` sends by default.
ISSUE_SIZES = MemoryAttackSizes()

#: Megabytes, not gigabytes: for the tests and a quick look (`--attack-sizes small`).
SMALL_SIZES = MemoryAttackSizes(
    big_frames=2,
    big_frame_bytes=64 << 20,
    big_frame_sent_bytes=4 << 20,
    incomplete_stacks=3,
    incomplete_frame_bytes=1 << 20,
    repeated_index=50,
)

#: Each size preset by its name on the command line.
ATTACK_SIZES = {"issue": ISSUE_SIZES, "small": SMALL_SIZES}


def _attack_header(
    sequence: int, frame_bytes: int, n_frames: int = 3
) -> instrument_pb2.ZStackHeader:
    """A stack header of `n_frames` uint16 frames of `frame_bytes` each (one channel)."""
    width = 4096
    height = max(1, frame_bytes // (2 * width))
    return instrument_pb2.ZStackHeader(
        instrument="attacker",
        slide=ATTACK_SLIDE,
        sequence=sequence,
        z_um=[0.5 * index for index in range(n_frames)],
        dtype="<u2",
        shape=[n_frames, height, width, 1],
        bit_depth=16,
        clock_s=time.time(),
    )


def big_frames(session: zenoh.Session, sizes: MemoryAttackSizes) -> dict[str, int]:
    """Frames declared at `big_frame_bytes`, each sent in parts up to
    `big_frame_sent_bytes` and never finished (tile (0, i) of `ATTACK_SLIDE`); what went."""
    part = bytearray(codec.FRAME_PART_BYTES)
    n_parts = sizes.big_frame_bytes // len(part)
    sent_parts = min(n_parts - 1, sizes.big_frame_sent_bytes // len(part))
    for frame in range(sizes.big_frames):
        header = _attack_header(frame, sizes.big_frame_bytes)
        key_expr = keys.zframe_key(ATTACK_SLIDE, 0, frame)
        for index in range(sent_parts):
            attachment = instrument_pb2.ZFrameHeader(
                stack=header, index=0, parts=n_parts, part_offset=index * len(part)
            ).SerializeToString()
            _put(session, key_expr, part, codec.ZFRAME_ENCODING, attachment)
    return {
        "frames": sizes.big_frames,
        "declared_bytes": sizes.big_frame_bytes,
        "sent_bytes": sizes.big_frames * sent_parts * len(part),
    }


def incomplete_stacks(session: zenoh.Session, sizes: MemoryAttackSizes) -> dict[str, int]:
    """Stacks of 3 frames of `incomplete_frame_bytes` whose first frame alone is sent,
    whole (tile (1, i) of `ATTACK_SLIDE`); what went."""
    header = _attack_header(0, sizes.incomplete_frame_bytes)
    frame = bytearray(int(np.prod(header.shape[1:])) * 2)
    for stack in range(sizes.incomplete_stacks):
        header.sequence = stack
        attachment = instrument_pb2.ZFrameHeader(stack=header, index=0).SerializeToString()
        key_expr = keys.zframe_key(ATTACK_SLIDE, 1, stack)
        _put(session, key_expr, frame, codec.ZFRAME_ENCODING, attachment)
    return {"stacks": sizes.incomplete_stacks, "sent_bytes": sizes.incomplete_stacks * len(frame)}


def repeated_frames_request(
    session: zenoh.Session,
    instrument: str,
    slide: str,
    sizes: MemoryAttackSizes,
    timeout_s: float = 120.0,
) -> dict[str, int]:
    """Acquire a stack of 5 frames of tile (0, 0) of `slide`, then ask for its first frame
    `repeated_index` times in one FramesRequest; the replies and their bytes."""
    sequence = 1 << 40  # no scan's
    acquire = instrument_pb2.AcquireRequest(
        slide=slide, row=0, col=0, z_low_um=-1.0, z_step_um=0.5, n_frames=5, sequence=sequence
    )
    rpc.call(  # RemoteError if the instrument refuses it
        session, keys.acquire_key(instrument), acquire, instrument_pb2.AcquireReply, timeout_s
    )
    request = instrument_pb2.FramesRequest(
        slide=slide, row=0, col=0, sequence=sequence, indices=[0] * sizes.repeated_index
    )
    n_replies = n_bytes = 0
    for reply in session.get(
        keys.frames_key(instrument),
        payload=request.SerializeToString(),
        encoding=rpc.protobuf_encoding(instrument_pb2.FramesRequest),
        timeout=timeout_s,
        consolidation=zenoh.ConsolidationMode.NONE,
    ):
        if reply.ok is not None:  # counted and dropped: the attacker keeps nothing
            n_replies += 1
            n_bytes += len(reply.ok.payload)
    return {"indices": sizes.repeated_index, "replies": n_replies, "reply_bytes": n_bytes}
