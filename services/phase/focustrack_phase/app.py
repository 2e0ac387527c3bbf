"""The phase service over REST (FastAPI): a through-focus stack in, phase and amplitude out.

- ``POST /v1/phase/stack``: multipart, ``stack`` (a multi-page TIFF or a .npy array of
  raw counts, frames first: (n, H, W), n >= 2), ``z_um`` (each frame's height relative
  to the plane to reconstruct, um: a JSON list or comma-separated numbers),
  ``wavelength_um``, ``pixel_um``; optional ``photons_per_count`` (1) and the filter's
  settings ``q0``, ``p0``, ``update``, ``condenser_na``, ``amplitude_floor``,
  ``prior_length_um``, ``background`` (`AcekfOptions`). ``?format=npy`` (the default)
  answers a float32 .npy of shape (2, H, W): the phase (rad) and the amplitude (relative
  to the stack's mean) at z = 0, its header ``X-Background-Share`` the share of the image
  taken as glass (zero phase); ``?format=png`` a picture of the phase with a colour bar in
  radians.
- ``GET /healthz``. OpenAPI docs at ``/docs``.

Bad input is a 4xx whose detail names the problem, as the focus service's: 413 for an
oversized body or a stack that would decode to more than the limits (read from the
file's header), 415 for a file that is neither TIFF nor .npy or a body that is no
form, 408 for a body that arrives too slowly, 401 without the token (when one is set),
503 with Retry-After while `PhaseLimits.max_concurrent` stacks are under way, 422 for
the rest, naming the field. The reconstruction (and the picture) run on a
worker thread, so ``/healthz`` answers while a stack is being reconstructed.
"""

from __future__ import annotations

import enum
import io
import math
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np
from fastapi import Depends, FastAPI, File, Form, HTTPException, Query, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response

from focustrack_core.http_metrics import HttpMetrics
from focustrack_core.stacks import TooLargeError, UnsupportedFileError, decode_stack, parse_z_list
from focustrack_core.web import (
    bearer_scheme,
    check_least,
    form_as_declared,
    guarded_app,
    read_upload,
)
from focustrack_phase.acekf import (
    MAX_AMPLITUDE_FLOOR,
    MAX_PRIOR_LENGTH_UM,
    MAX_Q0,
    MIN_Q0,
    AcekfOptions,
    Background,
    FieldEstimate,
    Update,
    reconstruct,
)

#: The .npy answer's header with the share of the image taken as empty glass, whose phase
#: is zero (`FieldEstimate.background_share`; absent with ``background=none``).
BACKGROUND_SHARE_HEADER = "X-Background-Share"
#: The picture's height over its width at most (and its width over its height): a frame
#: beyond, a strip of 20000 x 2 pixels say, is drawn stretched to this, not on a canvas
#: of millions of pixels (which took minutes, then crashed matplotlib).
MAX_PICTURE_ASPECT = 4.0


#: The least each limit of `PhaseLimits` may be: what the smallest stack the filter takes
#: needs (2 frames of 2x2 bytes, sent with its form), so that a limit below admits nothing.
LEAST_LIMITS = {
    "max_upload_bytes": 4096,
    "max_decoded_bytes": 8,
    "max_frames": 2,
    "max_pixels": 4,
    "max_concurrent": 1,
}


@dataclass(frozen=True)
class PhaseLimits:
    """What one request may ask of the service (its settings; each a flag of the command).

    max_upload_bytes: the whole request body; max_decoded_bytes: the pixels a stack
    decodes to, read from its header before decoding; max_frames: of a stack (the time
    of a reconstruction grows with them); max_pixels: of one frame, height x width (the
    filter holds about ten arrays of that size); body_timeout_s: how long a body may
    take to arrive; max_concurrent: the reconstructions under way at once (one more is
    a 503, before its body is read): each may hold its upload, its decoded stack and the
    filter's arrays, so these bound the service's memory.
    """

    max_upload_bytes: int = 256 << 20
    max_decoded_bytes: int = 512 << 20
    max_frames: int = 201
    max_pixels: int = 2048 * 2048
    body_timeout_s: float = 60.0
    max_concurrent: int = 2

    def __post_init__(self) -> None:
        check_least(self, LEAST_LIMITS)
        if not self.body_timeout_s > 0:
            raise ValueError(f"the body timeout must be positive, got {self.body_timeout_s} s")


class PhaseFormat(enum.StrEnum):
    """What `POST /v1/phase/stack` answers."""

    NPY = "npy"  # float32 (2, H, W): phase (rad), amplitude
    PNG = "png"  # the phase, with a colour bar in radians


def field_npy(estimate: FieldEstimate) -> bytes:
    """A .npy file of float32 (2, H, W): the phase (rad) and the amplitude (relative)."""
    buffer = io.BytesIO()
    np.save(buffer, np.stack([estimate.phase_rad, estimate.amplitude]).astype(np.float32))
    return buffer.getvalue()


def phase_png(phase_rad: np.ndarray) -> bytes:
    """A PNG of `phase_rad` (H, W), on a cyclic colour map over [-pi, pi] with a colour bar
    labelled in radians; square pixels unless H / W is beyond `MAX_PICTURE_ASPECT`."""
    # matplotlib takes about a second to import: the first picture pays it, not start-up.
    # A Figure of its own (no pyplot) is safe on the worker threads.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    height, width = phase_rad.shape
    aspect = min(max(height / width, 1.0 / MAX_PICTURE_ASPECT), MAX_PICTURE_ASPECT)
    figure = Figure(figsize=(6.0, 5.0 * aspect + 0.5), dpi=100)
    FigureCanvasAgg(figure)
    axes = figure.add_subplot()
    image = axes.imshow(
        phase_rad,
        cmap="twilight",
        vmin=-math.pi,
        vmax=math.pi,
        aspect="equal" if aspect == height / width else "auto",
    )
    axes.set_axis_off()
    bar = figure.colorbar(image, ax=axes, ticks=[-math.pi, -math.pi / 2, 0, math.pi / 2, math.pi])
    bar.ax.set_yticklabels(["-π", "-π/2", "0", "π/2", "π"])
    bar.set_label("phase (rad)")
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", bbox_inches="tight")
    return buffer.getvalue()


def checked_stack(frames: np.ndarray, z_um: np.ndarray, limits: PhaseLimits) -> np.ndarray:
    """`frames` once it is a stack the service takes: (n >= 2, H, W), one z per frame, within
    `limits.max_pixels`; ValueError naming what is wrong (the maths checks the rest,
    `acekf.validate_stack`)."""
    if frames.ndim != 3:
        raise ValueError(
            f"stack must be frames of one channel, (frames, height, width); got shape "
            f"{frames.shape}"
        )
    if frames.shape[0] < 2:
        raise ValueError(f"stack must hold at least 2 frames; got {frames.shape[0]}")
    pixels = frames.shape[1] * frames.shape[2]
    if pixels > limits.max_pixels:
        raise TooLargeError(
            f"stack frames of {frames.shape[1]}x{frames.shape[2]} = {pixels} pixels; the limit "
            f"is {limits.max_pixels}"
        )
    if z_um.size != frames.shape[0]:
        raise ValueError(
            f"z_um must list one height per frame: {frames.shape[0]} frames, got {z_um.size}"
        )
    return frames


#: The form's numbers: finite, and > 0 where the maths needs it (422 names the field).
Positive = Annotated[float, Form(gt=0, allow_inf_nan=False)]


def create_app(
    limits: PhaseLimits | None = None, token: str | None = None, fft_workers: int = 1
) -> FastAPI:
    """The REST app; `limits` what one request may ask, `token` the bearer token /v1
    requires (None: open), `fft_workers` the threads of each of the filter's FFTs."""
    limits = limits or PhaseLimits()
    defaults = AcekfOptions()

    token_scheme = bearer_scheme(token)
    app = guarded_app(
        "focustrack phase service",
        "Quantitative phase and amplitude from a through-focus stack (sparse ACEKF).",
        limits.max_upload_bytes,
        limits.body_timeout_s,
        HttpMetrics("focustrack_phase"),
        token,
        limits.max_concurrent,
    )

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return {"status": "ok"}

    @app.post(
        "/v1/phase/stack",
        dependencies=[Depends(token_scheme), Depends(form_as_declared)],
        response_class=Response,
        responses={
            200: {
                "content": {"application/octet-stream": {}, "image/png": {}},
                "description": "float32 .npy (2, H, W): phase (rad), amplitude; or a PNG",
            }
        },
    )
    async def phase_stack(
        stack: Annotated[UploadFile, File(description="multi-page TIFF or .npy, frames first")],
        z_um: Annotated[str, Form(description="each frame's z from the plane, um: JSON list")],
        wavelength_um: Positive,
        pixel_um: Positive,
        photons_per_count: Positive = 1.0,
        q0: Annotated[float, Form(ge=MIN_Q0, le=MAX_Q0, allow_inf_nan=False)] = defaults.q0,
        p0: Annotated[float, Form(ge=-MAX_Q0, le=MAX_Q0, allow_inf_nan=False)] = defaults.p0,
        update: Annotated[
            Update, Form(description="phase_frame (ours) or paper (eq. 33 as printed)")
        ] = defaults.update,
        condenser_na: Annotated[
            float, Form(ge=0, lt=1.5, allow_inf_nan=False, description="0: coherent light")
        ] = defaults.condenser_na,
        amplitude_floor: Annotated[
            float, Form(gt=0, le=MAX_AMPLITUDE_FLOOR, allow_inf_nan=False)
        ] = defaults.amplitude_floor,
        prior_length_um: Annotated[
            float,
            Form(
                ge=0,
                le=MAX_PRIOR_LENGTH_UM,
                allow_inf_nan=False,
                description="the prior's correlation length, um (0: white, the paper's)",
            ),
        ] = defaults.prior_length_um,
        background: Annotated[
            Background,
            Form(
                description="anchor (the lowest frequencies set so the empty background is "
                "zero) or none (the filter's own, as the paper)"
            ),
        ] = defaults.background,
        format: Annotated[PhaseFormat, Query(description="npy or png")] = PhaseFormat.NPY,
    ) -> Response:
        data = await read_upload(stack, limits.max_upload_bytes)
        try:
            z = parse_z_list(z_um)
            options = AcekfOptions(
                q0=q0,
                p0=p0,
                update=update,
                condenser_na=condenser_na,
                amplitude_floor=amplitude_floor,
                prior_length_um=prior_length_um,
                background=background,
            )
            frames = await run_in_threadpool(
                decode_stack, data, limits.max_frames, limits.max_decoded_bytes
            )
            estimate = await run_in_threadpool(
                reconstruct,
                checked_stack(frames, z, limits),
                z,
                wavelength_um,
                pixel_um,
                photons_per_count,
                options,
                fft_workers,
            )
        except UnsupportedFileError as error:
            raise HTTPException(415, str(error)) from None
        except TooLargeError as error:
            raise HTTPException(413, str(error)) from None
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
        if format is PhaseFormat.PNG:
            return Response(
                await run_in_threadpool(phase_png, estimate.phase_rad), media_type="image/png"
            )
        headers = {"Content-Disposition": 'attachment; filename="phase.npy"'}
        if estimate.background_share is not None:
            headers[BACKGROUND_SHARE_HEADER] = f"{estimate.background_share:.4f}"
        return Response(
            await run_in_threadpool(field_npy, estimate),
            media_type="application/octet-stream",
            headers=headers,
        )

    return app
