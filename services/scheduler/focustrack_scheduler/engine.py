"""The engine: executes a scan plan's steps against the real services.

Each step of `plan.py` is carried out here, with the service's timeout and
retries with exponential back-off (tenacity) for as long as the policy's outage
allows, and a `ServiceUnavailableError` naming the service, its key expression or
URL, when one stays gone longer than that:

- instrument (Zenoh queries): a query without an answer (the instrument or the
  router is gone) or answered BUSY (its queue is full) is sent again, with pauses
  doubling from `backoff_initial_s` to `backoff_max_s`, for up to
  `RetryPolicy.instrument_outage_s` (60 s: a router or instrument restart); any
  other refusal (an Error reply) is not retried, it is a bug in the request;
- the frames a tile keeps (its image, or its planes) are fetched from the instrument
  by a query once the tile's focus is known (`InstrumentClient.frames`), retried as
  any instrument query; the scheduler does not receive the other frames;
- focus results: each acquisition is asked for under a fresh nonce, and only a result
  with that nonce (and its sequence, tile and frames) is taken, once (`clients.Inbox`);
  waited for `focus_timeout_s`, or until the scan's link to the bus went down and has
  been back for a grace (`session.LinkWatch`: Zenoh keeps nothing for a link that is
  gone, so a result in flight then is lost); either goes back to the plan, which
  acquires the stack again (under a new nonce);
- phase stacks (`AcquirePhase`, with ``--phase``): acquired as any stack, their result
  taken the same way and waited for `phase_timeout_s` from the acquisition (the whole of
  it: a phase takes seconds to compute, so one on its way may still come after the bus is
  back); the scan goes on without the last `phase_in_flight` results (it images the next
  tile while the phase service reconstructs), and awaits every one still to come before
  it ends (a scan that stops keeps those tiles without phase); a result that does not
  come, or one that reports an error, leaves the tile without phase (logged), never stops
  the scan; an instrument that takes a phase stack as a focus stack (it predates the
  field) is not waited for; with no phase service's liveliness token on the bus one is
  awaited `phase_timeout_s` (once: while none came, the next stacks are not acquired),
  and once the phase services alive at a stack's request have all gone and another is
  there (`session.TokenWatch`), the result went with them: the stack is acquired again,
  once, for the one there now;
- estimator (HTTP): connection errors and 5xx answers are retried the same way
  for up to `estimator_outage_s` (a restarted estimator rebuilds its slides from
  its log, and a measurement posted twice is recorded once); a 4xx is a refusal
  and stops the scan with the estimator's own `detail`.

The engine also keeps the scan's record (`record.ScanRecord`), the progress bar,
the wall-time split, the scan's metrics and each tile's trace (`telemetry`).
"""

from __future__ import annotations

import contextlib
import logging
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

import httpx
import numpy as np

from focustrack_client import EstimatorClient, EstimatorError
from focustrack_core.domain import Acquisition, Measurement, Outcome
from focustrack_core.logs import worth_logging
from focustrack_core.rest import to_api, to_domain
from focustrack_core.v1 import instrument_pb2
from focustrack_core.wire import keys, rpc
from focustrack_core.wire.session import LinkWatch, TokenWatch
from focustrack_core.wire.trust import new_nonce
from focustrack_scheduler.clients import (
    InstrumentClient,
    PhaseReceived,
    SlideListener,
    acquire_request,
    phase_request,
)
from focustrack_scheduler.in_focus import InFocusScore
from focustrack_scheduler.laser import read_laser
from focustrack_scheduler.outputs import WALL_STATE_KEY, OutputFolderError, WallTimes
from focustrack_scheduler.plan import (
    MIN_PHASE_REACH_DOF,
    Acquire,
    AcquirePhase,
    AskNext,
    AwaitFocus,
    CompareFrame,
    CreateOrResumeSlide,
    DescribeSlide,
    FocusUnavailableError,
    Frame,
    KeepPlanes,
    KeepTile,
    MatchTile,
    PhaseStacks,
    Plan,
    PostMeasurement,
    ReadLaser,
    Retake,
    SlideGeometry,
    TilesWithoutPhase,
    execute,
    prior_upload,
)
from focustrack_scheduler.realign import FirstPassImages, LateralPlacement, Realign
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy, estimator_retryable, instrument_retryable
from focustrack_scheduler.telemetry import ScanMetrics, TileSpans

log = logging.getLogger(__name__)

T = TypeVar("T")


class ServiceUnavailableError(RuntimeError):
    """A service did not answer within its timeout and retries."""


class ScanRefusedError(RuntimeError):
    """A service refused a request of the scan (the message says which and why)."""


class ScanProgress:
    """A progress bar: tiles imaged, images, simulated time and the running in-focus rate.

    The in-focus rate needs the truth (evaluation only), so it is shown when there is one.
    """

    def __init__(
        self, total_tiles: int, truth_um: np.ndarray | None, dof_um: float, *, label: str
    ) -> None:
        from tqdm import tqdm  # only a scan that shows its progress needs it

        self.score = None if truth_um is None else InFocusScore(truth_um, dof_um)
        self.bar = tqdm(total=total_tiles, desc=label, unit="tile")

    def update(self, record: ScanRecord) -> None:
        tally = record.tally
        postfix = {"images": tally.n_images, "sim": f"{tally.scan_time_s:.0f}s"}
        if self.score is not None and tally.kept:
            in_focus = self.score.tiles(tally.kept, tally.planes) / len(tally.kept)
            postfix["in focus"] = f"{in_focus:.0%}"
        self.bar.set_postfix(postfix, refresh=False)
        # `update` redraws at most every `mininterval`, so a log file is not flooded.
        self.bar.update(len(tally.kept) - self.bar.n)

    def close(self) -> None:
        self.bar.close()


@dataclass(frozen=True)
class PendingPhase:
    """A phase stack acquired whose result the scan has yet to take.

    n_frames, scan_time_s: its images and the instrument's (simulated) seconds for them.
    services: the phase services alive at its request (the result goes with them).
    deadline_s: `time.monotonic()` after which its result is awaited no longer.
    attempt: 1, or 2 for a stack taken again because its result went with its service.
    """

    step: AcquirePhase
    n_frames: int
    scan_time_s: float
    services: TokenWatch
    deadline_s: float
    attempt: int


class Engine:
    """Runs a plan: each step against the instrument, the focus results or the estimator."""

    def __init__(
        self,
        instrument: InstrumentClient,
        listener: SlideListener,
        estimator: EstimatorClient,
        record: ScanRecord,
        policy: RetryPolicy | None = None,
        *,
        estimator_url: str = "",
        on_geometry: Callable[[SlideGeometry], ScanProgress | None] = lambda _: None,
        realign: Realign | None = None,
        metrics: ScanMetrics | None = None,
    ) -> None:
        self.instrument = instrument
        self.listener = listener
        self.estimator = estimator
        self.record = record
        self.policy = policy or RetryPolicy()
        self.estimator_url = estimator_url
        self.wall = WallTimes()
        saved = record.state.read() or {}  # a resumed scan's state, read once
        # The earlier runs of a resumed scan: the report's split is of the whole scan.
        self._wall_before = WallTimes.of_dict(saved.get(WALL_STATE_KEY))
        self.geometry: SlideGeometry | None = None
        self._on_geometry = on_geometry
        self._realign = realign
        #: the second pass's lateral offset (with `realign`), made once the grid is known
        self.placement: LateralPlacement | None = None
        self._kept: tuple[tuple[int, int, int, int], np.ndarray] | None = None  # the last image
        self._progress: ScanProgress | None = None
        self._slide = ""  # the slide being scanned (DescribeSlide)
        #: the acquisitions of the tile being scanned, by sequence: to take one again
        self._taken: dict[int, tuple[str, Acquisition]] = {}
        self._nonces: dict[int, bytes] = {}  # of each stack this engine took, by sequence
        #: the focus services of the latest acquisition (by index), watched from before its
        #: request (its last attempt): one that dies before its result is awaited counts too
        self._services: tuple[int, TokenWatch] | None = None
        self._tile_format_saved = "tile" in saved
        self._phase_cut_said = False  # the phase stacks' cut to the frame limit, said once
        self._n_without_phase = 0  # tiles whose phase stack brought no phase (logged)
        #: no phase service came within the phase timeout; none is waited for again
        self._no_phase_service = False
        #: phase stacks acquired whose results are still to come, oldest first
        self._pending_phase: deque[PendingPhase] = deque()
        self.metrics = metrics or ScanMetrics()
        self.metrics.follow(record.tally.kept)
        record.listeners.add(self.metrics.take)
        self._tiles = TileSpans(self.metrics)  # each tile's trace
        #: acquisition index -> its focus curve (z um, scores), until it is posted
        self._curves: dict[int, tuple[list[float], list[float]]] = {}
        self._handlers: dict[type, Callable[[Any], Any]] = {
            DescribeSlide: self._describe,
            CreateOrResumeSlide: self._create_or_resume,
            AskNext: self._ask_next,
            Acquire: self._acquire,
            AwaitFocus: self._await_focus,
            PostMeasurement: self._post,
            KeepTile: self._keep,
            KeepPlanes: self._keep_planes,
            AcquirePhase: self._acquire_phase,
            TilesWithoutPhase: self._tiles_without_phase,
            ReadLaser: self._read_laser,
            MatchTile: self._match_tile,
            CompareFrame: self._compare_frame,
            Retake: self._retake,
        }

    def run(self, plan: Plan) -> str:
        """Execute `plan` to the end; its return value (the estimator's slide id)."""
        started_s = time.perf_counter()
        self.metrics.running.set(1)
        try:
            slide_id = execute(plan, self._answer)
            self._take_pending_phase(in_flight=0)  # the last tiles' phase
            return slide_id
        except FocusUnavailableError as error:
            if self.listener.focus_services.alive():
                raise
            # What the focus services' liveliness tokens say: none reads this slide.
            raise FocusUnavailableError(
                f"{error} No focus service on the bus reads this slide: none holds a "
                f"liveliness token on {self.listener.focus_services.key_expr} (start "
                "`focustrack serve focus`, its --slides matching the slide)"
            ) from error
        finally:
            self._drop_pending_phase()
            self._tiles.close()
            self.metrics.running.set(0)
            self.wall.close(time.perf_counter() - started_s)
            with contextlib.suppress(OSError, OutputFolderError):  # the scan's own error first
                self.record.state.save(**{WALL_STATE_KEY: self.scan_wall.as_dict()})
            if self._progress is not None:
                self._progress.close()

    @property
    def scan_wall(self) -> WallTimes:
        """Where the whole scan's wall time went: this run's and every earlier run's of a
        scan resumed (`wall` is this run's alone)."""
        return self._wall_before.plus(self.wall)

    def _answer(self, step: Any) -> Any:
        with self._tiles.step(step, self._slide):
            return self._handlers[type(step)](step)

    # --- instrument -------------------------------------------------------------------

    def _instrument_call(self, what: str, key_expr: str, call: Callable[[], T]) -> T:
        """`call()`, sent again while nobody answers or the instrument is busy; any other
        Error reply is a refusal."""
        outage_s = self.policy.instrument_outage_s
        retrying = self.policy.retrying(
            outage_s, instrument_retryable, f"instrument: {what}", self._retried("instrument")
        )
        try:
            return retrying(call)
        except rpc.RemoteError as error:
            if not instrument_retryable(error):
                raise ScanRefusedError(f"instrument refused {what}: {error}") from error
            raise ServiceUnavailableError(
                f"instrument {self.instrument.name!r} did not answer {what} on {key_expr} "
                f"for {outage_s:.0f} s ({error}). Is `focustrack serve instrument "
                f"--name {self.instrument.name}` running on the same Zenoh network?"
            ) from error

    def _describe(self, step: DescribeSlide) -> SlideGeometry:
        key_expr = keys.info_key(step.instrument)
        try:
            geometry = self._instrument_call(
                "the info query", key_expr, lambda: self.instrument.geometry(step.slide)
            )
        except ValueError as error:
            raise ScanRefusedError(str(error)) from error
        if (max_frames := geometry.stage.max_frames) is not None and max_frames < 2:
            raise ScanRefusedError(
                f"instrument {step.instrument!r} takes at most {max_frames} frame a stack; "
                "a focus curve needs 2"
            )
        if step.phase is not None:
            self._check_phase_stacks(step.phase, geometry)
        self.geometry, self._slide = geometry, step.slide
        if self._realign is not None:
            try:
                first = FirstPassImages(self._realign.first_pass, geometry.grid)
            except ValueError as error:
                raise ScanRefusedError(f"--first-pass: {error}") from error
            offset = (self.record.state.read() or {}).get("lateral_offset_um")  # a resumed scan's
            known = (float(offset[0]), float(offset[1])) if offset else None
            self.placement = LateralPlacement(first, self._realign, known)
        self.metrics.tiles.set(geometry.grid.n_tiles)
        self._progress = self._on_geometry(geometry)
        if self._progress is not None:
            self._progress.update(self.record)
        return geometry

    def _acquire(self, step: Acquire) -> tuple[float, ...]:
        acquisition = step.acquisition
        tile = (acquisition.row, acquisition.col)
        if any((a.row, a.col) != tile for _, a in self._taken.values()):
            self._taken, self._nonces = {}, {}  # a new tile: the last's frames are not asked for
        self._taken[acquisition.index] = (step.slide, acquisition)
        if step.asked is not None and step.attempt == 1:
            z, asked = acquisition.z, step.asked
            log.warning(
                "acquisition %d of tile (%d, %d): the estimator asked for %d frames at z "
                "%.3f..%.3f um; the stage takes %d at %.3f..%.3f um (its travel and frame limit)",
                acquisition.index, acquisition.row, acquisition.col, asked.n_frames,
                asked.low_um, asked.high_um, z.n_frames, z.low_um, z.high_um,
            )  # fmt: skip
        return self._take(step.slide, acquisition)

    def _take(self, slide: str, acquisition: Acquisition) -> tuple[float, ...]:
        """Acquire `acquisition`'s stack of `slide`, under a fresh nonce whose focus result
        alone the listener takes from now on; the z (um) of its frames."""
        request = self._offset(acquire_request(slide, acquisition, new_nonce()))
        self._nonces[acquisition.index] = request.nonce
        # its result may come first
        self.listener.focus.expect(acquisition.index, (slide, acquisition, request.nonce))
        key_expr = keys.acquire_key(self.instrument.name)
        what = f"acquisition {acquisition.index} of tile ({acquisition.row}, {acquisition.col})"

        def send() -> instrument_pb2.AcquireReply:
            self._services = (acquisition.index, TokenWatch(self.listener.focus_services))
            return self.instrument.acquire(request)

        sent_s = time.time()
        reply = self._instrument_call(what, key_expr, send)
        replied_s = time.time()
        if reply.header.nonce != request.nonce:  # its frames, so its result, would not match
            raise ScanRefusedError(
                f"instrument {self.instrument.name!r} took {what} without its nonce: it "
                "predates acquisition nonces (update it), or is not the instrument asked"
            )
        # Every stack taken is real images and stage time, kept or not.
        self.record.acquired(acquisition, len(reply.header.z_um), reply.timing.total_s)
        self._show()
        # The instrument replies once its frames are published (timestamp_unix_s).
        published_s = min(max(reply.header.timestamp_unix_s, sent_s), replied_s)
        self.wall.rendering_s += published_s - sent_s
        self.wall.transport_s += replied_s - published_s
        return tuple(reply.header.z_um)

    def _read_laser(self, step: ReadLaser) -> Measurement:
        acquisition = step.acquisition
        what = f"the laser reading of tile ({acquisition.row}, {acquisition.col})"
        if self.geometry is not None and self.geometry.laser is False:
            # Its info says so: no use waiting out an outage for a queryable that is not there.
            raise ScanRefusedError(
                f"the strategy asks for {what}, and instrument {self.instrument.name!r} has "
                "no laser autofocus: start it with one (`focustrack serve instrument "
                "--laser`) or scan with a strategy that reads the camera only"
            )
        measurement, seconds = self._instrument_call(
            what,
            keys.laser_key(self.instrument.name),
            lambda: read_laser(self.instrument, step.slide, acquisition),
        )
        self.record.acquired(acquisition, 0, seconds)  # stage time, no image
        return measurement

    def _await_focus(self, step: AwaitFocus) -> Any:
        acquisition = step.acquisition
        started_s = time.perf_counter()
        # Zenoh keeps nothing for a link or a process that is gone: a result in flight
        # when the bus went down, or not yet published when its focus service died, will
        # not come, so the wait ends once the bus or a focus service is back.
        link = LinkWatch(self.instrument.session)
        watched = self._services
        service = (
            watched[1]
            if watched is not None and watched[0] == acquisition.index
            else TokenWatch(self.listener.focus_services)
        )
        ended: list[tuple[str, str]] = []  # the fault that ended the wait, and why

        def lost() -> bool:
            if link.lost():
                ended.append(("focus_lost", "(the bus went down and is back)"))
            elif service.lost():
                ended.append(("focus_service_lost", "(its focus service went, another is there)"))
            return bool(ended)

        received = self.listener.focus.wait(
            acquisition.index, self.policy.focus_timeout_s, lost=lost
        )
        waited_s = time.perf_counter() - started_s
        if received is None:
            timeout = ("focus_timeout", f"within {self.policy.focus_timeout_s:.0f} s")
            fault, why = ended[0] if ended else timeout
            self.metrics.faults.labels(fault).inc()
            log.warning(
                "no focus result for acquisition %d %s: %s",
                acquisition.index,
                why,
                "its look unknown" if step.look_only else "acquiring it again",
            )
            self.wall.waiting_s += waited_s
            return None
        self._curves[acquisition.index] = (
            list(received.z_um),
            list(received.scores),
        )
        compute_s = min(received.compute_time_s, waited_s)
        self.wall.focus_computation_s += compute_s
        self.wall.waiting_s += waited_s - compute_s
        return received

    def _fetch(
        self, row: int, col: int, sequence: int, indices: list[int]
    ) -> tuple[Any, list[np.ndarray]] | None:
        """The stack header and frames at `indices` of acquisition `sequence` of tile
        (row, col), from the instrument (its frames query, retried as any instrument call).

        A stack of this tile that the instrument no longer holds (it restarted, or its
        budget ran out) is taken again, once; so is one the instrument holds under another
        nonce than this engine's (another scan of the slide took a stack under the same
        sequence since). None (logged) when it is still gone, or was taken before this
        scheduler started (a resumed scan).
        """
        started_s = time.perf_counter()
        what = f"frames {indices} of acquisition {sequence}"
        key_expr = keys.frames_key(self.instrument.name)

        def fetch() -> tuple[Any, list[np.ndarray]] | None:
            try:
                found = self.instrument.frames(self._slide, row, col, sequence, indices)
            except rpc.RemoteError as error:
                if error.error.code == rpc.ErrorCode.ERROR_CODE_FRAMES_GONE:
                    return None
                raise
            ours = self._nonces.get(sequence)
            if ours is not None and found[0].nonce != ours:
                log.warning("%s: the instrument holds another stack under this sequence", what)
                return None
            return found

        found = self._instrument_call(what, key_expr, fetch)
        if found is None:
            self.metrics.faults.labels("frames_gone").inc()
        if found is None and sequence in self._taken:
            log.warning("%s: the instrument no longer holds them; taking the stack again", what)
            self.wall.transport_s += time.perf_counter() - started_s
            self._take(*self._taken[sequence])
            started_s = time.perf_counter()
            found = self._instrument_call(what, key_expr, fetch)
        self.wall.transport_s += time.perf_counter() - started_s
        if found is None:
            log.warning("tile (%d, %d): the instrument has no %s any more", row, col, what)
        return found

    def _keep(self, step: KeepTile) -> None:
        if self.geometry is None:  # described before any acquisition
            return
        found = self._fetch(step.row, step.col, step.sequence, [step.frame])
        if found is None:  # logged: no image kept
            return
        header, (pixels,) = found
        # Saved before the first tile is kept: what the mosaic is made of, for the OME-TIFF,
        # and the pixel size for the live view's thumbnails, which follow the `kept` entry.
        if not self._tile_format_saved:
            height, width, channels = pixels.shape
            self._tile_format_saved = True
            self.record.state.save(
                tile={
                    "height": height,
                    "width": width,
                    "channels": channels,
                    "pixel_size_um": header.pixel_size_um,
                }
            )
        self._kept = ((step.row, step.col, step.sequence, step.frame), pixels)
        self.record.keep(
            self.geometry.grid, step.row, step.col, step.z_um, pixels, header.bit_depth,
            stage_um=(header.stage_x_um, header.stage_y_um),
        )  # fmt: skip
        self._show()

    def _keep_planes(self, step: KeepPlanes) -> None:
        if self.geometry is None:  # described before any acquisition
            return
        by_stack: dict[int, list[Frame]] = {}
        for frame in step.planes:
            by_stack.setdefault(frame.sequence, []).append(frame)
        pixels: dict[Frame, np.ndarray] = {}
        bit_depth = 0
        for sequence, frames in by_stack.items():  # one query per stack
            indices = [frame.index for frame in frames]
            found = self._fetch(step.row, step.col, sequence, indices)
            if found is None:  # logged: no planes kept
                return
            header, fetched = found
            pixels.update(zip(frames, fetched, strict=True))
            bit_depth = header.bit_depth  # one camera: the same for every stack of a tile
        z_um = [frame.z_um for frame in step.planes]
        stacked = np.stack([pixels[frame] for frame in step.planes])
        self.record.keep_planes(self.geometry.grid, step.row, step.col, z_um, stacked, bit_depth)

    def _acquire_phase(self, step: AcquirePhase) -> None:
        if self.geometry is None:  # described before any acquisition
            return
        if step.asked is not None and step.asked.n_frames != step.z.n_frames:
            self._say_phase_cut(step.asked.n_frames, step.z.n_frames)
        started_s = time.perf_counter()
        try:
            self._take_phase(step)
        finally:
            self.wall.phase_s += time.perf_counter() - started_s
        self._take_pending_phase(self.policy.phase_in_flight)

    def _check_phase_stacks(self, phase: PhaseStacks, geometry: SlideGeometry) -> None:
        """Refuse phase stacks the stage cuts to fewer than the 2 frames a phase needs (a
        step longer than its z travel: every tile's stack was taken, and refused by the
        phase service); warn, once, of stacks too close to focus to show phase."""
        asked = phase.z_range(0.0, geometry.dof_um)
        if geometry.stage.fit(asked).n_frames < 2:  # the same on every tile, wherever centred
            stage = geometry.stage
            raise ScanRefusedError(
                f"phase stack frames {asked.step_um:g} um apart (--phase-step-um) fit in the "
                f"instrument's z travel ({stage.z_min_um:g} to {stage.z_max_um:g} um) only "
                "once; a phase stack needs 2 frames"
            )
        if phase.too_close_to_focus(geometry.dof_um):
            log.warning(
                "phase stacks of %d planes %g um apart reach less than %g of the objective's "
                "depth of field (%g um) either side of focus: too near focus to show the phase "
                "(the default step is half the depth of field)",
                asked.n_frames, asked.step_um, MIN_PHASE_REACH_DOF, geometry.dof_um,
            )  # fmt: skip

    def _say_phase_cut(self, asked_frames: int, taken_frames: int) -> None:
        """Warn, once a scan, that the phase stacks are cut to the stage's frame limit (it
        is the same for every tile; a stack moved inside the travel keeps its frames)."""
        if self._phase_cut_said:
            return
        self._phase_cut_said = True
        log.warning(
            "phase stacks of %d planes (--phase-planes) are cut to %d, the most the "
            "instrument's frame limit and z travel allow",
            asked_frames, taken_frames,
        )  # fmt: skip

    def _take_phase(self, step: AcquirePhase, attempt: int = 1) -> None:
        """Acquire the phase stack; its result is awaited later (`_take_pending_phase`).

        No phase service reading the slide (their liveliness tokens): one is waited for up
        to `phase_timeout_s` (one restarting comes back within seconds), and if none comes
        the stack is not acquired (no one would reconstruct it), nor is one waited for
        again until one is there."""
        assert self.geometry is not None
        phase_services = self.listener.phase_services
        assert phase_services is not None, "phase stacks need SlideListener(phase=True)"
        what = f"the phase stack of tile ({step.row}, {step.col})"
        waited_s = 0.0 if self._no_phase_service else self.policy.phase_timeout_s
        if waited_s and not phase_services.alive():  # said: a silent wait looks like a hang
            log.warning(
                "%s: no phase service on the bus; waiting up to %g s for one", what, waited_s
            )
        if not phase_services.wait_alive(waited_s):
            self._no_phase_service = True
            nobody = f"no phase service on the bus reads this slide (waited {waited_s:g} s)"
            self._keep_phase(step, n_frames=0, scan_time_s=0.0, received=None, error=nobody)
            return
        self._no_phase_service = False
        services = TokenWatch(phase_services)
        request = self._offset(phase_request(step, new_nonce()))
        self.listener.phase.expect(step.sequence, (step, request.nonce))  # it may come first
        key_expr = keys.acquire_key(self.instrument.name)
        reply = self._instrument_call(what, key_expr, lambda: self.instrument.acquire(request))
        if reply.header.nonce != request.nonce:
            raise ScanRefusedError(
                f"instrument {self.instrument.name!r} took {what} without its nonce: it "
                "predates acquisition nonces (update it), or is not the instrument asked"
            )
        n_frames = len(reply.header.z_um)
        if reply.header.purpose != instrument_pb2.ACQUISITION_PURPOSE_PHASE:
            self.listener.phase.forget(step.sequence)
            error = "the instrument took it as a focus stack (it predates phase stacks)"
            self._keep_phase(step, n_frames, reply.timing.total_s, None, error)
            return
        deadline_s = time.monotonic() + self.policy.phase_timeout_s
        self._pending_phase.append(
            PendingPhase(step, n_frames, reply.timing.total_s, services, deadline_s, attempt)
        )

    def _take_pending_phase(self, in_flight: int) -> None:
        """Keep the results of the phase stacks pending, oldest first, that have come, and
        wait for the oldest until no more than `in_flight` are left. A result's wait ends
        at its deadline, or once every phase service alive at its request has gone and
        another is there: the result went with its service, and the stack is taken again
        (once) for the one there now."""
        if not self._pending_phase:  # a scan without phase spends no time here
            return
        started_s = time.perf_counter()
        try:
            while self._pending_phase:
                pending = self._pending_phase[0]
                sequence = pending.step.sequence
                if len(self._pending_phase) <= in_flight and not (
                    self.listener.phase.ready(sequence)
                    or time.monotonic() >= pending.deadline_s
                    or pending.services.lost()
                ):
                    return
                self._pending_phase.popleft()
                remaining_s = max(pending.deadline_s - time.monotonic(), 0.0)
                received = self.listener.phase.wait(
                    sequence, remaining_s, lost=pending.services.lost
                )
                error = None
                if received is None and pending.services.lost():
                    self.metrics.faults.labels("phase_service_lost").inc()
                    if pending.attempt == 1:
                        log.info(
                            "tile (%d, %d): its phase service went; taking its phase stack again",
                            pending.step.row,
                            pending.step.col,
                        )
                        self._take_phase(pending.step, attempt=2)
                        continue
                    error = "its phase service went before it published the result"
                elif received is None:
                    error = f"no phase result within {self.policy.phase_timeout_s:g} s"
                elif received.field is None:
                    error = f"the phase service: {received.result.error.message}"
                self._keep_phase(
                    pending.step, pending.n_frames, pending.scan_time_s, received, error
                )
        finally:
            self.wall.phase_s += time.perf_counter() - started_s

    def _tiles_without_phase(self, _: TilesWithoutPhase) -> list[tuple[int, int, float]]:
        self._take_pending_phase(in_flight=0)  # a result still to come is not missing
        tally = self.record.tally
        empty = tally.tiles_found_empty()  # nothing in view: no phase to take (`scan_plan`)
        return [
            (row, col, z_um)
            for (row, col), z_um in tally.kept.items()
            if (row, col) not in tally.phase and (row, col) not in empty
        ]

    def _drop_pending_phase(self) -> None:
        """The tiles whose phase results were still to come when the scan stopped: kept
        without phase (say so), their results awaited no longer."""
        while self._pending_phase:
            pending = self._pending_phase.popleft()
            self.listener.phase.forget(pending.step.sequence)
            stopped = "the scan stopped before its phase result came"
            self._keep_phase(pending.step, pending.n_frames, pending.scan_time_s, None, stopped)

    def _keep_phase(
        self,
        step: AcquirePhase,
        n_frames: int,
        scan_time_s: float,
        received: PhaseReceived | None,
        error: str | None,
    ) -> None:
        """Record the phase of `step`'s tile (`received`), or `error`: why it has none."""
        assert self.geometry is not None
        if error is not None:
            self._n_without_phase += 1
            if worth_logging(self._n_without_phase):  # one a tile: thousands on a slide
                log.warning(
                    "tile (%d, %d) has no phase (%d tiles so far): %s",
                    step.row,
                    step.col,
                    self._n_without_phase,
                    error,
                )
        self.record.phase(
            self.geometry.grid,
            step.row,
            step.col,
            sequence=step.sequence,
            n_frames=n_frames,
            scan_time_s=scan_time_s,
            reference_z_um=step.reference_z_um,
            field=None if received is None else received.field,
            background_share=None
            if received is None or received.field is None
            else received.result.background_share,
            error=error,
        )

    def _offset(self, request: instrument_pb2.AcquireRequest) -> instrument_pb2.AcquireRequest:
        """`request` at the pass's lateral offset, where it is known."""
        if self.placement is not None and self.placement.offset_um is not None:
            request.stage_offset_x_um, request.stage_offset_y_um = self.placement.offset_um
        return request

    def _kept_pixels(self, image: KeepTile) -> np.ndarray | None:
        """The pixels `image` kept; None where its fetch failed."""
        if self._kept is None:
            return None
        which, pixels = self._kept
        return pixels if which == (image.row, image.col, image.sequence, image.frame) else None

    def _match_tile(self, step: MatchTile) -> list[tuple[int, int, float]]:
        if self.placement is None or self.placement.offset_um is not None:
            return []
        image = step.image
        if (pixels := self._kept_pixels(image)) is None:
            return []
        again = self.placement.observe(image.row, image.col, image.z_um, pixels)
        if self.placement.offset_um is not None:  # a resumed scan goes on at it
            self.record.state.save(lateral_offset_um=list(self.placement.offset_um))
        return again

    def _compare_frame(self, step: CompareFrame) -> float | None:
        image = step.image
        if self.placement is None or (pixels := self._kept_pixels(image)) is None:
            return None
        return self.placement.sharpness_ratio(image.row, image.col, pixels)

    def _retake(self, step: Retake) -> None:
        assert self.geometry is not None  # described before any acquisition
        request = instrument_pb2.AcquireRequest(
            slide=step.slide, row=step.row, col=step.col, z_low_um=step.z_um, n_frames=1,
            sequence=step.sequence, nonce=new_nonce(),
        )  # fmt: skip
        self._nonces[step.sequence] = request.nonce
        what = f"tile ({step.row}, {step.col}) again at the lateral offset"
        key_expr = keys.acquire_key(self.instrument.name)
        reply = self._instrument_call(
            what, key_expr, lambda: self.instrument.acquire(self._offset(request))
        )
        self.record.retaken(step.row, step.col, step.sequence, reply.timing.total_s)
        self._keep(KeepTile(step.row, step.col, step.sequence, 0, step.z_um))

    def _show(self) -> None:
        if self._progress is not None:
            self._progress.update(self.record)

    # --- estimator --------------------------------------------------------------------

    def estimator_call(self, what: str, call: Callable[[], T]) -> T:
        """`call()`, retried with back-off while the estimator is unreachable or failing."""
        started_s = time.perf_counter()
        outage_s = self.policy.estimator_outage_s
        try:
            retrying = self.policy.retrying(
                outage_s, estimator_retryable, f"estimator: {what}", self._retried("estimator")
            )
            return retrying(call)
        except EstimatorError as error:
            if error.status < 500:
                raise ScanRefusedError(f"estimator refused {what}: {error}") from error
            raise self._estimator_gone(what, str(error)) from error
        except httpx.TransportError as error:
            raise self._estimator_gone(what, f"{type(error).__name__}: {error}") from error
        finally:
            self.wall.estimation_s += time.perf_counter() - started_s

    def _retried(self, service: str) -> Callable[[], None]:
        return self.metrics.retries.labels(service).inc

    def _estimator_gone(self, what: str, problem: str) -> ServiceUnavailableError:
        return ServiceUnavailableError(
            f"estimator at {self.estimator_url or 'its URL'} did not answer {what} "
            f"for {self.policy.estimator_outage_s:.0f} s: {problem}"
        )

    def _create_or_resume(self, step: CreateOrResumeSlide) -> str:
        if (slide_id := step.slide_id) is not None:
            slide = self.estimator_call(f"slide {slide_id}", lambda: self.estimator.slide(slide_id))
            if slide.config.strategy != step.config.strategy:
                raise ScanRefusedError(
                    f"estimator slide {step.slide_id} is scanned with "
                    f"{slide.config.strategy!r}, not {step.config.strategy!r}"
                )
            log.info("resuming estimator slide %s", slide_id)
            return slide_id
        config, prior_npy = prior_upload(step.config)
        slide = self.estimator_call("the new slide", lambda: self.estimator.create_slide(config))
        if prior_npy is not None:  # before the state names the slide: a resumed scan has it
            self.estimator_call(
                f"the prior map of slide {slide.id}",
                lambda: self.estimator.put_prior(slide.id, prior_npy),
            )
        self.record.state.save(slide_id=slide.id)
        return slide.id

    def _ask_next(self, step: AskNext) -> Acquisition | None:
        return to_domain.acquisition(
            self.estimator_call("/next", lambda: self.estimator.next(step.slide_id))
        )

    def _post(self, step: PostMeasurement) -> Outcome:
        body = to_api.measurement_in(step.acquisition, step.measurement)
        reply = self.estimator_call(
            f"the measurement of acquisition {step.acquisition.index}",
            lambda: self.estimator.measure(step.slide_id, body),
        )
        outcome = to_domain.outcome(reply)
        curve = self._curves.pop(step.acquisition.index, None)
        self.record.measurement(step.acquisition, step.measurement, outcome, curve)
        return outcome
