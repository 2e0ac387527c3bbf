"""The focus service over REST (FastAPI): a z-stack or a focus curve in, a focus result out.

- ``POST /v1/focus/stack``: multipart, ``stack`` (a multi-page TIFF or a .npy
  array, frames first: (n, H, W) or (n, H, W, C)) and ``z_um`` (the z of each
  frame in um: a JSON list or comma-separated numbers); optional ``metric``,
  ``mode``, ``channel``, ``lowpass_sigma_px``.
- ``POST /v1/focus/curve``: JSON ``{"z_um": [...], "scores": [...]}`` (optional
  ``metric`` label, ``mode`` and ``prior``: ``{"z_um": m, "sigma_um": s}``, the
  estimator's belief before this stack), for lab software that computes its own
  scores. ``best_z_um``/``sigma_um`` are always the curve's own measurement; with
  a prior the reply adds ``posterior_z_um``/``posterior_sigma_um`` (both combined).
- ``GET /healthz``. OpenAPI docs at ``/docs``.

Bad input is a 4xx whose detail names the problem: 413 for an oversized
upload, 415 for a file that is neither TIFF nor .npy, 422 for the rest.
"""

from __future__ import annotations

import io
import json
from dataclasses import replace
from typing import Annotated, Any

import numpy as np
import tifffile
from fastapi import FastAPI, File, Form, HTTPException, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field, model_validator

from focustrack_focus.metrics import DEFAULT_METRIC, METRICS
from focustrack_focus.peak import PeakMode, Prior
from focustrack_focus.pipeline import FocusSettings, focus_from_curve, focus_stack

#: Default upload limit: 41 frames of 2048x2048x3 uint16 is about 1 GB; 1 GiB.
MAX_UPLOAD_BYTES = 1 << 30
_NPY_MAGIC = b"\x93NUMPY"
_TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


class PriorModel(BaseModel):
    """The estimator's belief about the focus before this stack (um)."""

    model_config = ConfigDict(extra="forbid")

    z_um: float = Field(allow_inf_nan=False)
    sigma_um: float = Field(gt=0, allow_inf_nan=False)


class CurveRequest(BaseModel):
    """A focus curve: the z (um) of each frame and its score."""

    model_config = ConfigDict(extra="forbid")

    z_um: list[Annotated[float, Field(allow_inf_nan=False)]] = Field(min_length=3)
    scores: list[Annotated[float, Field(allow_inf_nan=False)]] = Field(min_length=3)
    metric: str = Field(DEFAULT_METRIC, description="label of the metric that made the scores")
    mode: PeakMode = PeakMode.MAX
    prior: PriorModel | None = Field(
        None, description="the estimator's prior; weighs peaks, adds the posterior"
    )

    @model_validator(mode="after")
    def _same_length(self) -> CurveRequest:
        if len(self.z_um) != len(self.scores):
            raise ValueError(
                f"{len(self.z_um)} z values but {len(self.scores)} scores: one score per z needed"
            )
        return self


class FocusResponse(BaseModel):
    """The focus of a stack or curve (the JSON of `FocusResult`)."""

    z_um: list[float]
    scores: list[float]
    best_z_um: float | None
    sigma_um: float | None
    flags: list[str]
    metric: str
    compute_time_s: float
    runner_up_z_um: float | None = Field(None, description="z of the next most likely peak")
    chosen_probability: float | None = Field(
        None, description="probability that best_z_um's peak is the focus (peak choice)"
    )
    posterior_z_um: float | None = Field(None, description="prior and measurement combined")
    posterior_sigma_um: float | None = None


def parse_z_list(text: str) -> np.ndarray:
    """z values from a form field: a JSON list or comma-separated numbers; ValueError if not."""
    text = text.strip()
    try:
        values = (
            json.loads(text)
            if text.startswith("[")
            else [float(part) for part in text.split(",") if part.strip()]
        )
        z = np.asarray(values, dtype=np.float64)
    except (ValueError, TypeError) as error:
        raise ValueError(f"z_um must be a JSON list or comma-separated numbers: {error}") from None
    if z.ndim != 1:
        raise ValueError(f"z_um must be a flat list of numbers, got shape {z.shape}")
    return z


class UnsupportedFileError(ValueError):
    """The upload is neither a TIFF nor a .npy file (HTTP 415)."""


def decode_stack(data: bytes) -> np.ndarray:
    """A z-stack from the bytes of a .npy or (multi-page) TIFF file; ValueError if it is not."""
    if data.startswith(_NPY_MAGIC):
        try:
            return np.load(io.BytesIO(data), allow_pickle=False)
        except ValueError as error:
            raise ValueError(f"the .npy file cannot be read: {error}") from None
    if data[:4] in _TIFF_MAGICS:
        try:
            return tifffile.imread(io.BytesIO(data))
        except Exception as error:  # tifffile raises many types on a broken file
            raise ValueError(f"the TIFF file cannot be read: {error}") from None
    raise UnsupportedFileError(
        "the stack must be a multi-page TIFF or a .npy file (unknown file signature)"
    )


def create_app(
    settings: FocusSettings | None = None, max_upload_bytes: int = MAX_UPLOAD_BYTES
) -> FastAPI:
    """The REST app; `settings` are the defaults that request fields override."""
    base = settings or FocusSettings()
    app = FastAPI(
        title="focustrack focus service",
        version="1",
        description="Best focus (with an uncertainty and flags) from a z-stack or a focus curve.",
    )

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, error: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes each bad input, and a NaN there cannot be
        # written as JSON (a 500): give where and what is wrong, without the input.
        detail = [
            {"loc": list(item["loc"]), "msg": item["msg"], "type": item["type"]}
            for item in error.errors()
        ]
        return JSONResponse({"detail": detail}, status_code=422)

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return {"status": "ok", "metrics": list(METRICS), "default_metric": base.metric}

    @app.post("/v1/focus/curve", response_model=FocusResponse)
    def focus_curve(request: CurveRequest) -> dict[str, Any]:
        chosen = replace(base, peak=replace(base.peak, mode=request.mode))
        prior = None if request.prior is None else Prior(request.prior.z_um, request.prior.sigma_um)
        try:
            result = focus_from_curve(
                np.array(request.z_um), np.array(request.scores), chosen, prior=prior
            )
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
        return result.to_json() | {"metric": request.metric}

    @app.post("/v1/focus/stack", response_model=FocusResponse)
    async def focus_stack_endpoint(
        stack: Annotated[UploadFile, File(description="multi-page TIFF or .npy, frames first")],
        z_um: Annotated[str, Form(description="z of each frame, um: JSON list or a,b,c")],
        metric: Annotated[str, Form()] = base.metric,
        mode: Annotated[PeakMode, Form()] = base.peak.mode,
        channel: Annotated[int | None, Form(ge=0)] = base.preprocess.channel,
        lowpass_sigma_px: Annotated[float, Form(ge=0, le=64)] = base.preprocess.lowpass_sigma_px,
    ) -> dict[str, Any]:
        if stack.size is not None and stack.size > max_upload_bytes:
            raise HTTPException(413, f"stack of {stack.size} bytes exceeds {max_upload_bytes}")
        data = await stack.read(max_upload_bytes + 1)
        if len(data) > max_upload_bytes:
            raise HTTPException(413, f"stack exceeds the limit of {max_upload_bytes} bytes")
        try:
            z = parse_z_list(z_um)
            if metric not in METRICS:
                raise ValueError(f"unknown focus metric {metric!r}; known: {', '.join(METRICS)}")
            chosen = FocusSettings(
                preprocess=replace(
                    base.preprocess, channel=channel, lowpass_sigma_px=lowpass_sigma_px
                ),
                metric=metric,
                peak=replace(base.peak, mode=mode),
            )
            frames = decode_stack(data)
            if frames.ndim == 2:
                raise ValueError(f"the stack holds a single {frames.shape} frame; need >= 3")
            result = await run_in_threadpool(focus_stack, frames, z, chosen)
        except UnsupportedFileError as error:
            raise HTTPException(415, str(error)) from None
        except ValueError as error:
            raise HTTPException(422, str(error)) from None
        return result.to_json()

    return app
