"""`focustrack serve phase`: the phase service over REST (the FastAPI app of `app.py`).

Its options come from flags, ``FOCUSTRACK_PHASE_<OPTION>`` or ``--settings FILE``
(`PhaseServiceSettings`). Without a token the API is open: off loopback the service
refuses to start without one unless --insecure is given.
"""

from __future__ import annotations

import logging
import sys
from dataclasses import fields

import uvicorn
from pydantic import Field
from pydantic_settings import SettingsConfigDict

from focustrack_core.serving import refuse_open_network
from focustrack_core.settings import ServiceSettings, command_main
from focustrack_phase.app import PhaseLimits, create_app

log = logging.getLogger(__name__)


class PhaseServiceSettings(ServiceSettings):
    """The phase service's options: flags, ``FOCUSTRACK_PHASE_<OPTION>`` or a settings file.

    The limits' defaults are the REST app's `PhaseLimits`, which `limits` gives back (and
    checks); the filter's defaults are `AcekfOptions`', which each request may change.
    """

    model_config = SettingsConfigDict(env_prefix="FOCUSTRACK_PHASE_")

    host: str = Field("127.0.0.1", description="HTTP address")
    port: int = Field(8300, ge=0, le=65535, description="HTTP port")
    token: str | None = Field(None, description="require this bearer token on /v1 (unset: no auth)")
    insecure: bool = Field(
        False,
        description="serve REST without a token on a non-loopback address (refused otherwise)",
    )
    # the REST API's limits (`PhaseLimits`)
    max_upload_bytes: int = Field(
        PhaseLimits.max_upload_bytes, description="largest request body, bytes (413)"
    )
    max_decoded_bytes: int = Field(
        PhaseLimits.max_decoded_bytes,
        description="largest decoded stack, bytes, read from its header (413)",
    )
    max_frames: int = Field(PhaseLimits.max_frames, description="most frames of a stack (413)")
    max_pixels: int = Field(
        PhaseLimits.max_pixels, description="most pixels of one frame, height x width (413)"
    )
    body_timeout_s: float = Field(
        PhaseLimits.body_timeout_s, description="seconds a request body may take to arrive (408)"
    )

    def limits(self) -> PhaseLimits:
        """What one REST request may ask (ValueError if a limit admits nothing)."""
        return PhaseLimits(
            **{limit.name: getattr(self, limit.name) for limit in fields(PhaseLimits)}
        )


def run(settings: PhaseServiceSettings) -> int:
    refusal = refuse_open_network("phase", settings.host, settings.token, settings.insecure)
    if refusal:
        print(refusal, file=sys.stderr)
        return 2
    try:
        limits = settings.limits()
    except ValueError as error:
        print(f"phase service not started: {error}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    log.info(
        "phase service: http://%s:%d/v1/phase/stack (auth %s)",
        settings.host,
        settings.port,
        "on" if settings.token else "off",
    )
    app = create_app(limits, settings.token or None)
    uvicorn.run(app, host=settings.host, port=settings.port, log_level="info")
    return 0


#: The command's settings model (`focustrack serve phase` parses it and calls `run`).
Settings = PhaseServiceSettings

#: The `focustrack-phase` console script (and `python -m focustrack_phase`).
main = command_main("focustrack-phase", "the phase service (REST)", PhaseServiceSettings, run)
