"""`focustrack scan`: scan one slide through the instrument, focus and estimator services.

    focustrack scan --estimator http://127.0.0.1:8100 --connect tcp/127.0.0.1:7447 \\
        --instrument sim --slide slide-0 --strategy kf-wiener0 --out out/scan

Run again on the same `--out` folder, it resumes the slide where the estimator's
state says it is (after a crash, a kill or Ctrl-C) instead of starting over.
Exit status: 0 when the scan is complete, 1 when a service is gone or refused
the scan (the message names it), 2 for bad arguments.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from focustrack_client import EstimatorClient
from focustrack_core.config import command_main
from focustrack_core.maps import focus_map_of_npy
from focustrack_core.rest.to_domain import default_policy
from focustrack_core.wire import rpc
from focustrack_core.wire.session import DEFAULT_ENDPOINT, add_zenoh_arguments, config_from_args
from focustrack_core.wire.trust import ResultSigner, signer_of
from focustrack_scheduler.clients import InstrumentClient, SlideListener
from focustrack_scheduler.engine import (
    Engine,
    RetryPolicy,
    ScanProgress,
    ScanRefusedError,
    ServiceUnavailableError,
)
from focustrack_scheduler.live import LiveScan
from focustrack_scheduler.live_view import LiveServer, port_number
from focustrack_scheduler.outputs import MosaicFormat, ScanRecord, write_outputs
from focustrack_scheduler.plan import (
    FocusUnavailableError,
    ScanRequest,
    SlideGeometry,
    scan_plan,
)

log = logging.getLogger(__name__)

#: The best Kalman strategy we have, the demo's headline. kf-2d has the lowest prior MAE at
#: the simulator's focus noise (0.146 um against 0.284 for kf-wiener0 and 0.254 for kf-mmae,
#: 8 standard 10x10 maps, `focustrack bench accuracy --noise-um 0.1 --dof-um 0.89`) and at
#: the thesis' 1.5 um noise (0.461 against 0.612 for kf-mmae, 16 maps of 20x20).
BEST_KALMAN = "kf-2d"

DEFAULT_ESTIMATOR = "http://127.0.0.1:8100"
TOKEN_ENV = "FOCUSTRACK_ESTIMATOR_TOKEN"

#: What stops a scan, reported in one line rather than a traceback.
SCAN_ERRORS = (
    ServiceUnavailableError,
    ScanRefusedError,
    FocusUnavailableError,
    zenoh.ZError,
)


@dataclass(frozen=True)
class ScanJob:
    """One scan: what to scan, where the estimator is, where the outputs go."""

    request: ScanRequest
    estimator_url: str
    out_dir: Path
    retry: RetryPolicy = field(default_factory=RetryPolicy)
    token: str | None = None
    progress: bool = True
    label: str = "scan"
    mosaic_format: MosaicFormat = MosaicFormat.OME_ZARR
    live: LiveServer | None = None  # the live web view that shows this scan, if any
    trust: ResultSigner | None = None  # focus results count only with this key's tag


def _check_same_scan(record: ScanRecord, job: ScanJob) -> str | None:
    """The estimator slide id to resume, if `out_dir` holds an earlier run of this scan."""
    state = record.state
    if state is None:
        return None
    wanted = {
        "estimator": job.estimator_url,
        "instrument": job.request.instrument,
        "slide": job.request.slide,
        "strategy": job.request.strategy,
    }
    different = {name: state.get(name) for name in wanted if state.get(name) != wanted[name]}
    if different:
        raise ScanRefusedError(
            f"{record.out_dir} holds another scan ({different}, not "
            f"{ {name: wanted[name] for name in different} }): use another output folder"
        )
    return state.get("slide_id")


def run_scan(session: zenoh.Session, job: ScanJob) -> dict[str, Any]:
    """Scan (or resume) the slide, write the outputs, and return the report."""
    record = ScanRecord(job.out_dir)
    estimator = EstimatorClient(job.estimator_url, job.token, job.retry.estimator_timeout_s)
    listener = SlideListener(session, job.request.slide, job.trust)
    try:
        resume_id = _check_same_scan(record, job)
        request = replace(job.request, resume_slide_id=resume_id)
        record.save_state(
            estimator=job.estimator_url,
            instrument=request.instrument,
            slide=request.slide,
            strategy=request.strategy,
            params=dict(request.params),
        )
        instrument = InstrumentClient(session, request.instrument, job.retry.instrument_timeout_s)
        truth: dict[str, np.ndarray | None] = {"um": None}

        def start(geometry: SlideGeometry) -> ScanProgress:
            if job.live is not None:
                job.live.show(LiveScan.follow(record, geometry.grid, job.label))
            try:  # evaluation only: the plan never sees it
                truth["um"] = instrument.truth_um(request.slide)
            except rpc.RemoteError as error:
                log.warning("no truth from the instrument (%s): no in-focus figures", error)
            return ScanProgress(
                geometry.grid.n_tiles,
                truth["um"],
                geometry.dof_um,
                label=job.label,
                enabled=job.progress,
            )

        engine = Engine(
            instrument,
            listener,
            estimator,
            record,
            job.retry,
            estimator_url=job.estimator_url,
            on_geometry=start,
        )
        slide_id = engine.run(scan_plan(request))
        assert engine.geometry is not None  # the plan's first step described the slide
        focus_map = focus_map_of_npy(
            engine.estimator_call("the map", lambda: estimator.focus_map_file(slide_id, "npy"))
        )
        geometry = engine.geometry
        if job.live is not None and job.live.scan is not None:
            job.live.scan.finish()
        return write_outputs(
            record,
            geometry.grid,
            focus_map,
            truth["um"],
            geometry.dof_um,
            engine.wall,
            job.mosaic_format,
            focus_results_rejected=listener.n_rejected,
        )
    finally:
        listener.close()
        estimator.close()
        record.close()


def _params(items: list[str] | None) -> dict[str, Any]:
    """`NAME=VALUE` strings as parameters; values are read as JSON where they parse."""
    params: dict[str, Any] = {}
    for item in items or []:
        name, equals, text = item.partition("=")
        if not (name and equals):
            raise ValueError(f"--param takes NAME=VALUE, got {item!r}")
        try:
            params[name] = json.loads(text)
        except json.JSONDecodeError:
            params[name] = text
    return params


def add_scan_options(parser: argparse.ArgumentParser) -> None:
    """The options a scan shares with `focustrack demo`: prior, z-range policy, retries."""
    prior = parser.add_argument_group("what is known before the first tile")
    prior.add_argument("--start-z-um", type=float, default=0.0, help="start height (0)")
    prior.add_argument("--start-sigma-um", type=float, default=10.0, help="its std (10)")
    prior.add_argument(
        "--noise-sigma-um",
        type=float,
        default=0.1,
        help="std of a best-focus measurement without its own sigma (0.1)",
    )
    policy = parser.add_argument_group("z-stacks")
    defaults = default_policy()
    policy.add_argument("--k-sigma", type=float, default=defaults.k_sigma)
    policy.add_argument("--z-step-um", type=float, default=defaults.z_step_um)
    policy.add_argument("--min-frames", type=int, default=defaults.min_frames)
    policy.add_argument("--max-frames", type=int, default=defaults.max_frames)
    retry = parser.add_argument_group("timeouts and retries")
    default_retry = RetryPolicy()
    retry.add_argument(
        "--instrument-timeout-s", type=float, default=default_retry.instrument_timeout_s
    )
    retry.add_argument(
        "--instrument-outage-s",
        type=float,
        default=default_retry.instrument_outage_s,
        help="how long to keep retrying an instrument (or router) that does not answer or "
        "is busy, with pauses doubling up to 5 s",
    )
    retry.add_argument("--focus-timeout-s", type=float, default=default_retry.focus_timeout_s)
    retry.add_argument(
        "--focus-attempts",
        type=int,
        default=ScanRequest.focus_attempts,
        help="acquisitions of a stack without result (%(default)s: with --focus-timeout-s, "
        "rides out a focus service restart of a minute)",
    )
    retry.add_argument(
        "--estimator-outage-s",
        type=float,
        default=default_retry.estimator_outage_s,
        help="how long to keep retrying an estimator that does not answer",
    )
    parser.add_argument(
        "--mosaic-format",
        type=MosaicFormat,
        choices=list(MosaicFormat),
        default=MosaicFormat.OME_ZARR,
        help="file of the mosaic: mosaic.ome.zarr (ome-zarr, the default) or mosaic.ome.tif",
    )
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument(
        "--result-key-file",
        type=Path,
        metavar="FILE",
        help="the focus service's shared key: accept only focus results tagged with it "
        "(docs/security.md; default: any result on the bus)",
    )


def request_from_args(
    args: argparse.Namespace, instrument: str, slide: str, strategy: str
) -> ScanRequest:
    """The ScanRequest of the shared options (ValueError on a bad one)."""
    return ScanRequest(
        instrument=instrument,
        slide=slide,
        strategy=strategy,
        params=_params(getattr(args, "param", None)),
        start_z_um=args.start_z_um,
        start_sigma_um=args.start_sigma_um,
        noise_sigma_um=args.noise_sigma_um,
        policy=default_policy(
            k_sigma=args.k_sigma,
            z_step_um=args.z_step_um,
            min_frames=args.min_frames,
            max_frames=args.max_frames,
        ),
        focus_attempts=args.focus_attempts,
    )


def retry_from_args(args: argparse.Namespace) -> RetryPolicy:
    return RetryPolicy(
        instrument_timeout_s=args.instrument_timeout_s,
        instrument_outage_s=args.instrument_outage_s,
        focus_timeout_s=args.focus_timeout_s,
        estimator_outage_s=args.estimator_outage_s,
    )


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--estimator", default=DEFAULT_ESTIMATOR, help=f"estimator URL ({DEFAULT_ESTIMATOR})"
    )
    parser.add_argument(
        "--token",
        default=os.environ.get(TOKEN_ENV),
        help=f"estimator bearer token (default ${TOKEN_ENV})",
    )
    add_zenoh_arguments(parser, default_connect=[DEFAULT_ENDPOINT])
    parser.add_argument("--instrument", default="sim", help="instrument name (sim)")
    parser.add_argument("--slide", default="slide-0", help="slide name (slide-0)")
    parser.add_argument("--strategy", default=BEST_KALMAN, help=f"strategy ({BEST_KALMAN})")
    parser.add_argument(
        "--param", action="append", metavar="NAME=VALUE", help="a strategy parameter (repeat)"
    )
    parser.add_argument(
        "--out", type=Path, default=Path("out/scan"), help="output folder (out/scan)"
    )
    parser.add_argument(
        "--live-port",
        type=port_number,
        help="serve the live web view of the scan on this port of 127.0.0.1 (0: any free one)",
    )
    add_scan_options(parser)


def run(args: argparse.Namespace) -> int:
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(name)s: %(message)s")
    try:
        job = ScanJob(
            request=request_from_args(args, args.instrument, args.slide, args.strategy),
            estimator_url=args.estimator,
            out_dir=args.out,
            retry=retry_from_args(args),
            token=args.token or None,
            progress=not args.no_progress,
            label=args.strategy,
            mosaic_format=args.mosaic_format,
            trust=signer_of(args.result_key_file),
        )
        config = config_from_args(args)  # a Zenoh config file it cannot use: exit 2
    except ValueError as error:
        print(f"focustrack scan: error: {error}", file=sys.stderr)
        return 2
    try:
        with zenoh.open(config) as session, live_server(args.live_port) as live:
            if live is not None:
                print(f"live view at {live.url}", flush=True)
            report = run_scan(session, replace(job, live=live))
    except SCAN_ERRORS as error:
        print(f"focustrack scan: error: {error}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"focustrack scan: interrupted; the same --out {args.out} resumes", file=sys.stderr)
        return 130
    print(summary_line(report))
    print(f"outputs in {args.out}")
    return 0


@contextlib.contextmanager
def live_server(port: int | None) -> Iterator[LiveServer | None]:
    """The live web view on 127.0.0.1:`port` while the block runs (None: no view)."""
    if port is None:
        yield None
        return
    with LiveServer(port=port) as server:
        yield server


def summary_line(report: dict[str, Any]) -> str:
    """One line: the strategy's images per tile, scan time, in-focus fraction and MAE."""

    def number(value: float | None, form: str) -> str:
        return "n/a" if value is None else format(value, form)

    return (
        f"{report['strategy']}: {report['tiles_imaged']} tiles, "
        f"{report['images_per_tile']:.2f} images/tile, "
        f"simulated scan time {report['scan_time_s']:.1f} s, "
        f"in focus {number(report['in_focus_fraction'], '.1%')}, "
        f"MAE {number(report['mae_um'], '.3f')} um"
    )


#: Every option's environment variable is this prefix and its name (focustrack_core.config).
ENV_PREFIX = "FOCUSTRACK_SCAN_"

#: The `focustrack-scheduler` console script (and `python -m focustrack_scheduler`).
main = command_main(
    "focustrack-scheduler", "scan one slide through the services", add_arguments, run, ENV_PREFIX
)
