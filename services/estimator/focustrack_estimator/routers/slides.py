"""Slides: create, list, read and delete them (under /v1)."""

from __future__ import annotations

from fastapi import APIRouter, Response

from focustrack_client import models as api
from focustrack_estimator.dependencies import SlideId, SlidesDep
from focustrack_estimator.event_store import SlideRecord

router = APIRouter(prefix="/v1", tags=["slides"])


def _slide_out(record: SlideRecord) -> api.Slide:
    return api.Slide(
        id=record.id,
        config=api.SlideCreate.model_validate(record.config),
        n_acquisitions=record.n_events,
        n_accepted=record.n_accepted,
        done=record.done,
        created_unix_s=record.created_s,
        updated_unix_s=record.updated_s,
    )


@router.post("/slides", status_code=201)
async def create_slide(config: api.SlideCreate, slides: SlidesDep) -> api.Slide:
    """Create a slide scan; its strategy is built (and its parameters checked) at once."""
    slide_id = await slides.create(config)
    return _slide_out(await slides.record(slide_id))


@router.get("/slides")
async def list_slides(slides: SlidesDep) -> list[api.Slide]:
    """Every slide with its configuration and progress, oldest first."""
    return [_slide_out(record) for record in await slides.records()]


@router.get("/slides/{slide_id}")
async def get_slide(slide_id: SlideId, slides: SlidesDep) -> api.Slide:
    return _slide_out(await slides.record(slide_id))


@router.delete("/slides/{slide_id}", status_code=204)
async def delete_slide(slide_id: SlideId, slides: SlidesDep) -> Response:
    await slides.delete(slide_id)
    return Response(status_code=204)
