"""`focustrack scan`: scan one slide through the instrument, focus and estimator services.

    focustrack scan --estimator http://127.0.0.1:8100 --connect tcp/127.0.0.1:7447 \\
        --instrument sim --slide slide-0 --strategy kf-wiener0 --out out/scan

Run again on the same `--out` folder, it resumes the slide where the estimator's
state says it is (after a crash, a kill or Ctrl-C) instead of starting over.
Exit status: 0 when the scan is complete, 1 when a service is gone or refused
the scan (the message names it), 2 for bad arguments.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import logging
import os
import signal
import sys
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import httpx
import numpy as np
import zenoh
from pydantic import ValidationError

from focustrack_client import EstimatorClient, EstimatorError
from focustrack_core import tracing
from focustrack_core.http_metrics import metrics_server
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.serving import ListenError
from focustrack_core.settings import command_main, make_writable_folder
from focustrack_core.wire import rpc
from focustrack_core.wire.session import open_config, zenoh_message
from focustrack_core.wire.trust import ResultSigner, signer_of
from focustrack_scheduler.clients import InstrumentClient, SlideListener, truth_empty
from focustrack_scheduler.engine import (
    Engine,
    ScanProgress,
    ScanRefusedError,
    ServiceUnavailableError,
)
from focustrack_scheduler.finished import FinishedScan, OutputWriter, write_outputs
from focustrack_scheduler.live import LiveScan
from focustrack_scheduler.outputs import LOCK_FILE, MosaicFormat, OutputFolderError
from focustrack_scheduler.plan import FocusUnavailableError, ScanRequest, SlideGeometry, scan_plan
from focustrack_scheduler.record import ScanRecord
from focustrack_scheduler.retry import RetryPolicy
from focustrack_scheduler.settings import ScanOptions, ScanSettings
from focustrack_scheduler.telemetry import ScanMetrics
from focustrack_scheduler.writers import DEFAULT_WRITERS

if TYPE_CHECKING:
    from focustrack_scheduler.live_view import LiveServer

log = logging.getLogger(__name__)

#: What stops a scan, reported in one line rather than a traceback.
SCAN_ERRORS = (
    ServiceUnavailableError,
    ScanRefusedError,
    FocusUnavailableError,
    OutputFolderError,
    zenoh.ZError,
)

_DEFAULTS = ScanOptions.defaults()


@dataclass(frozen=True)
class ScanJob:
    """One scan: what to scan, where the estimator is, where the outputs go and which."""

    request: ScanRequest
    estimator_url: str
    out_dir: Path
    retry: RetryPolicy = field(default_factory=RetryPolicy)
    token: str | None = None
    progress: bool = not _DEFAULTS.no_progress
    label: str = "scan"
    mosaic_format: MosaicFormat = _DEFAULTS.mosaic_format
    writers: Sequence[OutputWriter] = DEFAULT_WRITERS  # the outputs written at the end
    live: LiveServer | None = None  # the live web view that shows this scan, if any
    trust: ResultSigner | None = None  # focus results count only with this key's tag
    metrics: ScanMetrics = field(default_factory=ScanMetrics)  # the live view serves them


@contextlib.contextmanager
def _holding(out_dir: Path) -> Iterator[None]:
    """The output folder for this process alone while the block runs: a second scan into it
    is refused (ScanRefusedError, naming the process that holds it), where the two used to
    write into one log, one mosaic and one state. An advisory lock, which the system
    releases when the process ends, however it ends."""
    out_dir.mkdir(parents=True, exist_ok=True)
    with (out_dir / LOCK_FILE).open("a+") as lock:
        try:
            fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            lock.seek(0)
            holder = lock.read().strip() or "another process"
            raise ScanRefusedError(
                f"{out_dir} is in use by another scan ({holder}): wait for it to end, or use "
                "another output folder"
            ) from None
        lock.truncate(0)
        lock.write(f"process {os.getpid()}\n")
        lock.flush()
        yield  # the lock goes with the file's closing


def _check_output_folder(out_dir: Path) -> None:
    """ValueError naming --out unless `out_dir` is, or is now made, a folder this process
    can write into (a file there, or a folder it cannot write, used to wait for the bus
    first and fail after it)."""
    try:
        make_writable_folder(out_dir)
    except ValueError as error:
        raise ValueError(f"--out {out_dir} cannot be the output folder: {error}") from None


def _slide_settings(request: ScanRequest) -> dict[str, Any]:
    """What the scan's estimator slide is made with, beyond its strategy, as JSON keeps it:
    the strategy's parameters, the start and the z-stack policy."""
    policy = request.policy
    settings = {
        "params": dict(request.params),
        "start_z_um": request.start_z_um,
        "start_sigma_um": request.start_sigma_um,
        "noise_sigma_um": request.noise_sigma_um,
        "z_range": {
            "k_sigma": policy.k_sigma,
            "z_step_um": policy.z_step_um,
            "min_frames": policy.min_frames,
            "max_frames": policy.max_frames,
        },
    }
    return dict(json.loads(json.dumps(settings)))


def _check_same_scan(record: ScanRecord, job: ScanJob) -> str | None:
    """The estimator slide id to resume, if `out_dir` holds an earlier run of this scan.

    A run on the folder of another scan is refused, and so is one with other slide
    settings: the estimator's slide keeps those it was made with, while the folder would
    say the new ones. Settings a folder predates are not compared."""
    state = record.state.read()
    if state is not None and "estimator" not in state:  # each scan's first save names it
        raise ScanRefusedError(
            f"{record.state.path} is no scan's (it names no estimator, as a scan's does), "
            "and a scan would write into it: use another output folder"
        )
    if state is None or state.get("slide_id") is None:
        return None  # nor did an earlier run that failed before its slide was made
    wanted = {
        "estimator": job.estimator_url.rstrip("/"),  # http://host:8100/ is http://host:8100
        "instrument": job.request.instrument,
        "slide": job.request.slide,
        "strategy": job.request.strategy,
    }
    saved = {**state, "estimator": str(state.get("estimator", "")).rstrip("/")}
    different = {name: saved.get(name) for name in wanted if saved.get(name) != wanted[name]}
    if different:
        raise ScanRefusedError(
            f"{record.out_dir} holds another scan ({different}, not "
            f"{ {name: wanted[name] for name in different} }): use another output folder"
        )
    settings = _slide_settings(job.request)
    changed = {
        name: state[name] for name in settings if state.get(name, settings[name]) != settings[name]
    }
    if changed:
        raise ScanRefusedError(
            f"{record.out_dir} holds a scan whose slide was made with {changed}, not "
            f"{ {name: settings[name] for name in changed} }; its estimator slide keeps "
            "them: resume it with them, or use another output folder"
        )
    return state.get("slide_id")


def _record_scan(record: ScanRecord, job: ScanJob) -> None:
    """Say in the folder's state which scan it holds (what `_check_same_scan` compares)."""
    record.state.save(
        estimator=job.estimator_url,
        instrument=job.request.instrument,
        slide=job.request.slide,
        strategy=job.request.strategy,
        **_slide_settings(job.request),
    )


def run_scan(session: zenoh.Session, job: ScanJob) -> dict[str, Any]:
    """Scan (or resume) the slide, write the job's outputs, and return the report."""
    with _holding(job.out_dir):
        return _scan_held(session, job)


def _scan_held(session: zenoh.Session, job: ScanJob) -> dict[str, Any]:
    """`run_scan`'s work, once the output folder is this process's."""
    record = ScanRecord(job.out_dir)
    estimator = EstimatorClient(job.estimator_url, job.token, job.retry.estimator_timeout_s)
    listener = SlideListener(
        session,
        job.request.slide,
        job.trust,
        phase=job.request.phase is not None,
        on_rejected=job.metrics.faults.labels("result_rejected").inc,
    )
    if job.live is not None:
        job.live.metrics = job.metrics
    try:
        resume_id = _check_same_scan(record, job)
        record.mosaic.check()  # before a stack is taken, not at the first tile kept
        request = replace(job.request, resume_slide_id=resume_id)
        _record_scan(record, job)
        instrument = InstrumentClient(session, request.instrument, job.retry.instrument_timeout_s)
        truth: dict[str, np.ndarray | None] = {"um": None, "empty": None}

        def start(geometry: SlideGeometry) -> ScanProgress | None:
            try:  # evaluation only: the plan never sees it
                truth["um"] = instrument.truth_um(request.slide)
                truth["empty"] = truth_empty(instrument.slide_truth(request.slide))
            except rpc.RemoteError as error:
                log.warning("no truth from the instrument (%s): no in-focus figures", error)
            if job.live is not None:  # in focus by the truth, else by the focus service
                live = LiveScan.follow(
                    record,
                    geometry.grid,
                    job.label,
                    dof_um=geometry.dof_um,
                    truth_um=truth["um"],
                    empty_glass=truth["empty"],
                )
                job.live.show(live)
            if not job.progress:
                return None
            return ScanProgress(
                geometry.grid.n_tiles, truth["um"], geometry.dof_um, label=job.label
            )

        engine = Engine(
            instrument,
            listener,
            estimator,
            record,
            job.retry,
            estimator_url=job.estimator_url,
            on_geometry=start,
            realign=request.realign,
            metrics=job.metrics,
        )
        slide_id = engine.run(scan_plan(request))
        assert engine.geometry is not None  # the plan's first step described the slide
        focus_map = focus_map_of_npy(
            engine.estimator_call("the map", lambda: estimator.focus_map_file(slide_id, "npy"))
        )
        geometry = engine.geometry
        if job.live is not None and job.live.scan is not None:
            job.live.scan.finish()
        finished = FinishedScan.of(
            record,
            geometry.grid,
            focus_map,
            truth["um"],
            geometry.dof_um,
            engine.scan_wall,
            job.mosaic_format,
            focus_results_rejected=listener.n_rejected,
        )
        write_outputs(finished, job.writers)
        return dict(finished.report)
    finally:
        listener.close()
        estimator.close()
        record.close()


#: How long the scan asks the estimator for its strategies before the bus (s): a check, not
#: the scan's own wait for an estimator that is still starting (the engine's, later).
STRATEGY_CHECK_TIMEOUT_S = 3.0


def check_strategy(settings: ScanSettings) -> None:
    """ValueError for a strategy, or a parameter of it, that the estimator does not serve.

    Asked before the bus, which may take up to `--bus-timeout-s` to open: a misspelt
    `--strategy` was refused only once the router answered. An estimator that does not
    answer yet (or an older one without `GET /v1/strategies`) is no refusal: the scan
    meets it later, with its own waits and errors.
    """
    try:
        with EstimatorClient(
            settings.estimator,
            settings.token or None,
            timeout_s=STRATEGY_CHECK_TIMEOUT_S,
            retry_pauses_s=(),
        ) as estimator:
            served = {info.name: info for info in estimator.strategies()}
    except (httpx.HTTPError, EstimatorError, ValidationError):  # the last: a reply unread
        return
    info = served.get(settings.strategy)
    if info is None:
        raise ValueError(
            f"the estimator at {settings.estimator} serves no strategy "
            f"{settings.strategy!r}; it serves {', '.join(sorted(served))}"
        )
    unknown = sorted(set(settings.params) - set(info.defaults))
    if unknown:
        raise ValueError(
            f"{settings.strategy} has no parameter {', '.join(map(repr, unknown))}; "
            f"its parameters: {', '.join(sorted(info.defaults)) or 'none'}"
        )


def _waiting_for_the_bus(settings: ScanSettings) -> None:
    connect, _ = settings.endpoints()
    print(
        f"focustrack scan: no Zenoh router answers at {', '.join(connect) or 'its endpoints'} "
        f"yet; trying for {settings.bus_timeout_s:g} s (--bus-timeout-s; Ctrl-C stops)",
        file=sys.stderr,
        flush=True,
    )


def _said(error: Exception) -> str:
    """What went wrong, in words: Zenoh's without the path of its Rust source."""
    return zenoh_message(error) if isinstance(error, zenoh.ZError) else str(error)


class _Terminated(KeyboardInterrupt):
    """SIGTERM (`docker stop`, a job scheduler's end): the scan stops as at Ctrl-C."""


def _terminate(*_: object) -> None:
    raise _Terminated


def run(settings: ScanSettings) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        return _run(settings)
    finally:
        signal.signal(signal.SIGTERM, previous)


def _run(settings: ScanSettings) -> int:
    try:
        job = ScanJob(
            request=settings.scan_request(),
            estimator_url=settings.estimator,
            out_dir=settings.out,
            retry=settings.retry(),
            token=settings.token or None,
            progress=not settings.no_progress,
            label=settings.strategy,
            mosaic_format=settings.mosaic_format,
            trust=signer_of(settings.result_key_file),
        )
        # a Zenoh config file or endpoint it cannot use: exit 2
        config = settings.zenoh(settings.bus_timeout_s)
        _check_output_folder(settings.out)  # before the bus, which may take a while
        check_strategy(settings)  # as much
    except (ValueError, zenoh.ZError) as error:
        print(f"focustrack scan: error: {_said(error)}", file=sys.stderr)
        return 2
    if ignored := settings.ignored_phase_options():
        print(
            f"focustrack scan: note: {', '.join(ignored)} change nothing without --phase",
            file=sys.stderr,
        )
    tracing.configure("focustrack-scheduler", settings.otlp_endpoint)
    try:
        with (
            open_config(config, lambda: _waiting_for_the_bus(settings)) as session,
            live_server(settings.live_port, settings.live_host) as live,
            metrics_server(job.metrics.registry, settings.metrics_host, settings.metrics_port),
        ):
            if live is not None:
                print(f"live view at {live.url}", flush=True)
            report = run_scan(session, replace(job, live=live))
    except SCAN_ERRORS as error:
        print(f"focustrack scan: error: {_said(error)}", file=sys.stderr)
        return 1
    except ValidationError as error:  # a --param the slide's model refuses (NaN, 1e400)
        print(f"focustrack scan: error: {error}", file=sys.stderr)
        return 2
    except ListenError as error:  # --live-port or --metrics-port taken
        print(f"focustrack scan: error: {error}", file=sys.stderr)
        return 2
    except OSError as error:  # the outputs' folder or a file in it (a file, unwritable)
        print(f"focustrack scan: error: cannot write the outputs: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt as stop:  # Ctrl-C, or SIGTERM (`_Terminated`)
        print(
            f"focustrack scan: interrupted; the same --out {settings.out} resumes", file=sys.stderr
        )
        return 143 if isinstance(stop, _Terminated) else 130
    print(summary_line(report))
    print(f"outputs in {settings.out}")
    return 0


@contextlib.contextmanager
def live_server(port: int | None, host: str = "127.0.0.1") -> Iterator[LiveServer | None]:
    """The live web view on `host`:`port` while the block runs (None: no view)."""
    if port is None:
        yield None
        return
    from focustrack_scheduler.live_view import LiveServer  # FastAPI: only when it is asked for

    with LiveServer(host=host, port=port) as server:
        yield server


def summary_line(report: dict[str, Any]) -> str:
    """One line: the strategy's images per tile, scan time, in-focus fraction and MAE, the
    tiles with phase (where phase was asked for; a warning for those without), and the
    tiles whose focus was not found, where there are some."""

    def number(value: float | None, form: str) -> str:
        return "n/a" if value is None else format(value, form)

    line = (
        f"{report['strategy']}: {report['tiles_imaged']} tiles, "
        f"{report['images_per_tile']:.2f} images/tile, "
        f"simulated scan time {report['scan_time_s']:.1f} s, "
        f"in focus {number(report['in_focus_fraction'], '.1%')}, "
        f"MAE {number(report['mae_um'], '.3f')} um"
    )
    if report["tiles_phase_asked"]:
        line += (
            f", phase on {report['tiles_with_phase']} of {report['rows'] * report['cols']} tiles"
        )
        if (missing := report["tiles_phase_asked"] - report["tiles_with_phase"]) > 0:
            line += f"; WARNING: no phase on {missing} tiles (the scan's log says why)"
    if report["tiles_without_focus"]:
        flags = ", ".join(f"{flag} {n}" for flag, n in report["tiles_flagged"].items())
        line += (
            f"; WARNING: no focus found on {report['tiles_without_focus']} of "
            f"{report['rows'] * report['cols']} tiles (flags: {flags})"
        )
    return line


#: The command's settings (`focustrack scan` runs them: focustrack/cli.py).
Settings = ScanSettings

#: The `focustrack-scheduler` console script (and `python -m focustrack_scheduler`).
main = command_main("focustrack-scheduler", "scan one slide through the services", Settings, run)
