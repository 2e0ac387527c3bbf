"""Operations: the health probe and the Prometheus metrics (outside /v1, no token)."""

from __future__ import annotations

import asyncio

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse

from focustrack_client import models as api
from focustrack_estimator.dependencies import MetricsDep, SlidesDep
from focustrack_estimator.event_store import StoreUnavailableError

router = APIRouter(tags=["operations"])


@router.get("/healthz")
async def healthz(slides: SlidesDep) -> api.Health:
    """`degraded` while the store is (its disk full, its checkpoints failing, its database
    unreachable), saying why; the store is not asked again while it is known to fail (the
    probe answers at once, and the store's own watch says when it is back)."""
    problem, n_slides = slides.store.problem(), None
    if problem is None:
        try:
            n_slides = await slides.count()
        except StoreUnavailableError as error:
            problem = str(error)
    status = "ok" if problem is None else "degraded"
    return api.Health(status=status, slides=n_slides, problem=problem)


@router.get("/metrics", response_class=PlainTextResponse)
async def metrics_text(metrics: MetricsDep) -> PlainTextResponse:
    """Prometheus text exposition: requests, latencies, filter time, slides, measurements."""
    text = await asyncio.to_thread(metrics.render)
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")
