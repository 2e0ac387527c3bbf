"""A scan: the next acquisition, and the measurement made for it (under /v1)."""

from __future__ import annotations

from fastapi import APIRouter, Depends

from focustrack_client import models as api
from focustrack_core.rest import to_api
from focustrack_estimator.dependencies import (
    JSON_BODY_RESPONSES,
    MetricsDep,
    SlideId,
    SlidesDep,
    json_body,
)

router = APIRouter(prefix="/v1", tags=["scan"])


@router.get("/slides/{slide_id}/next")
async def next_acquisition(slide_id: SlideId, slides: SlidesDep) -> api.Next:
    """The next tile to image and the z-range to acquire there (the same until measured)."""
    return await slides.run(slide_id, lambda slide: to_api.next_step(slide.next(), slide.grid))


@router.post(
    "/slides/{slide_id}/measurements",
    dependencies=[Depends(json_body)],
    responses=JSON_BODY_RESPONSES,
)
async def post_measurement(
    slide_id: SlideId,
    measurement: api.MeasurementIn,
    slides: SlidesDep,
    metrics: MetricsDep,
) -> api.OutcomeOut:
    """The best focus measured for the pending acquisition; on disk before the reply.

    Re-posting the same measurement for an acquisition already recorded returns
    the same outcome; a different value for it is a 409.
    """
    logged, new = await slides.run(slide_id, lambda slide: slide.measure(measurement))
    if new and logged.acquisition.measure:
        metrics.measurements.inc()
        if not logged.outcome.accepted:
            metrics.rejections.inc()
    return to_api.outcome_out(measurement.sequence, logged.outcome)
