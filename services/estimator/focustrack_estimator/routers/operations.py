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
    """`degraded` while the store is (its disk full, its checkpoints failing): reads go on."""
    status = "ok" if slides.store.problem() is None else "degraded"
    return api.Health(status=status, slides=await slides.count())


@router.get("/metrics", response_class=PlainTextResponse)
async def metrics_text(metrics: MetricsDep) -> PlainTextResponse:
    """Prometheus text exposition: requests, latencies, filter time, slides, measurements."""
    text = await asyncio.to_thread(metrics.render)
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")
