"""`focustrack serve phase`: the phase service on Zenoh and over REST, in one process.

Zenoh (`bus.py`): the frames of stacks taken for phase (``ZStackHeader.purpose`` phase)
in, a PhaseResult per stack out on ``focustrack/v1/phase/{slide}/{row}/{col}``; with
``--frame-key-file`` only frames tagged by the instrument are read, with
``--result-key-file`` every result is tagged (`focustrack_core.wire.trust`). The session is
opened in the background and tried again until the router answers, so the REST API comes
up at once (``/healthz`` says ``degraded`` until the session is open and linked).
REST: the FastAPI app of `app.py`, served by uvicorn on --host/--port.

Its options come from flags, ``FOCUSTRACK_PHASE_<OPTION>`` or ``--settings FILE``
(`PhaseServiceSettings`). Without a token the API is open: off loopback the service
refuses to start without one unless --insecure is given.
"""

from __future__ import annotations

import logging
import os
import sys
import time
from dataclasses import fields
from typing import ClassVar

from pydantic import Field
from pydantic_settings import SettingsConfigDict

from focustrack_core.serving import (
    ListenError,
    http_url,
    listening_socket,
    refuse_open_network,
    serve_until_stopped,
)
from focustrack_core.settings import command_main
from focustrack_core.web import with_bus_health
from focustrack_core.wire import keys
from focustrack_core.wire.frame_worker import ZFRAME_SUBSCRIPTION, FrameReaderSettings, WorkerBus
from focustrack_core.wire.session import DEFAULT_ENDPOINT
from focustrack_phase.acekf import MAX_WAVELENGTH_UM
from focustrack_phase.app import LEAST_LIMITS, PhaseLimits, create_app
from focustrack_phase.bus import PhaseOptics, PhaseStacks, ZenohPhaseWorker

log = logging.getLogger(__name__)


class PhaseServiceSettings(FrameReaderSettings):
    """The phase service's options: flags, ``FOCUSTRACK_PHASE_<OPTION>`` or a settings file.

    The limits' defaults are the REST app's `PhaseLimits`, which `limits` gives back (and
    checks), and which bound the stacks taken on Zenoh too; the filter's defaults are
    `AcekfOptions`', which each REST request may change.
    """

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_PHASE_")
    default_connect: ClassVar[tuple[str, ...]] = (DEFAULT_ENDPOINT,)

    host: str = Field("127.0.0.1", description="HTTP address")
    port: int = Field(8300, ge=0, le=65535, description="HTTP port")
    token: str | None = Field(None, description="require this bearer token on /v1 (unset: no auth)")
    insecure: bool = Field(
        False,
        description="serve REST without a token on a non-loopback address (refused otherwise)",
    )
    # the REST API's limits (`PhaseLimits`)
    max_upload_bytes: int = Field(
        PhaseLimits.max_upload_bytes,
        ge=LEAST_LIMITS["max_upload_bytes"],
        description="largest request body, bytes (413)",
    )
    max_decoded_bytes: int = Field(
        PhaseLimits.max_decoded_bytes,
        ge=LEAST_LIMITS["max_decoded_bytes"],
        description="largest decoded stack, bytes, read from its header (413)",
    )
    max_frames: int = Field(
        PhaseLimits.max_frames,
        ge=LEAST_LIMITS["max_frames"],
        description="most frames of a stack (413)",
    )
    max_pixels: int = Field(
        PhaseLimits.max_pixels,
        ge=LEAST_LIMITS["max_pixels"],
        description="most pixels of one frame, height x width (413)",
    )
    body_timeout_s: float = Field(
        PhaseLimits.body_timeout_s,
        gt=0,
        description="seconds a request body may take to arrive (408)",
    )
    max_concurrent: int = Field(
        PhaseLimits.max_concurrent,
        ge=LEAST_LIMITS["max_concurrent"],
        description="stacks reconstructed over REST at once; one more is answered 503 with "
        "Retry-After before its body is read (each holds up to its upload, the stack "
        "decoded and the filter's arrays: this bounds the memory)",
    )
    # Zenoh: phase stacks in, phase results out (`bus.py`)
    wavelength_um: float = Field(
        PhaseOptics.wavelength_um,
        gt=0,
        le=MAX_WAVELENGTH_UM,
        description="illumination wavelength, um, for stacks whose header gives none (an "
        "instrument that predates the field)",
    )

    fft_workers: int = Field(
        1,
        ge=1,
        le=os.cpu_count() or 1,
        description="threads of each of the filter's FFTs, at most the machine's cores: 1 runs "
        "them on OpenCV's DFT (one thread), more on scipy.fft's pocketfft threads, which can "
        "pay only on a machine with more than two cores to spare (on two, it is slower than "
        "OpenCV on one)",
    )

    def limits(self) -> PhaseLimits:
        """What one REST request may ask."""
        return PhaseLimits(
            **{limit.name: getattr(self, limit.name) for limit in fields(PhaseLimits)}
        )


def run(settings: PhaseServiceSettings) -> int:
    refusal = refuse_open_network("phase", settings.host, settings.token, settings.insecure)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    limits = settings.limits()  # the options' bounds are the limits' own
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    try:
        signer, frame_signer = settings.signers()
        settings.check_listen()  # a Zenoh port in use: one line, not a wait for ever
        # bound before the bus and the log say where it is: a port in use is one line
        listening = listening_socket(settings.host, settings.port, "phase")
    except (ValueError, ListenError) as error:
        log.error("%s", error)
        return 2
    optics = PhaseOptics(settings.wavelength_um)
    bus = WorkerBus(
        settings,
        lambda session: ZenohPhaseWorker(
            session,
            PhaseStacks(
                limits,
                settings.open_frames_bytes,
                settings.open_frame_timeout_s,
                frame_signer=frame_signer,
            ),
            optics,
            signer=signer,
            fft_workers=settings.fft_workers,
        ),
    )
    log.info(
        "phase service: zenoh %s (%s) -> %s/phase/... (results %s), %s (auth %s)",
        ZFRAME_SUBSCRIPTION,
        "any frames" if frame_signer is None else "tagged frames only",
        keys.PREFIX,
        "tagged" if signer is not None else "untagged",
        http_url(settings.host, listening.getsockname()[1], "/v1/phase/stack"),  # --port 0: chosen
        "on" if settings.token else "off",
    )
    started_s = time.perf_counter()
    try:
        app = with_bus_health(
            create_app(limits, settings.token or None, settings.fft_workers), bus.health
        )
        serve_until_stopped(app, listening, log_level="info")
    finally:
        bus.close()
        log.info(
            "published %d phase results in %.0f s; dropped %d untagged frame samples",
            sum(worker.n_published for worker in bus.workers),
            time.perf_counter() - started_s,
            sum(worker.stacks.n_untagged for worker in bus.workers),
        )
    return 0


#: The command's settings model (`focustrack serve phase` parses it and calls `run`).
Settings = PhaseServiceSettings

#: The `focustrack-phase` console script (and `python -m focustrack_phase`).
main = command_main(
    "focustrack-phase", "the phase service (Zenoh and REST)", PhaseServiceSettings, run
)
