"""Operations: the health probe and the Prometheus metrics (outside /v1, no token)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from focustrack_client import models as api
from focustrack_estimator.dependencies import MetricsDep, SlidesDep

router = APIRouter(tags=["operations"])


@router.get("/healthz")
async def healthz(slides: SlidesDep) -> api.Health:
    return api.Health(status="ok", slides=await slides.count())


@router.get("/metrics", response_class=PlainTextResponse)
async def metrics_text(metrics: MetricsDep) -> PlainTextResponse:
    """Prometheus text exposition: requests, latencies, filter time, slides, measurements."""
    text = await asyncio.to_thread(metrics.render)
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")
