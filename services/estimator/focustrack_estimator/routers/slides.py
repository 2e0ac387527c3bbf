"""Slides: create, list (a page at a time), read and delete them, and upload a prior map
(under /v1)."""

from __future__ import annotations

import logging
from typing import Annotated
from urllib.parse import urlencode

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response

from focustrack_client import models as api
from focustrack_core.web import query_as_declared
from focustrack_estimator.dependencies import (
    JSON_BODY_RESPONSES,
    SlideId,
    SlidesDep,
    json_body,
    media_type,
)
from focustrack_estimator.event_store import CorruptLogError, SlideRecord
from focustrack_estimator.paging import decode_cursor, encode_cursor
from focustrack_estimator.prior import PRIOR_MEDIA_TYPE
from focustrack_estimator.records import config_of

router = APIRouter(prefix="/v1", tags=["slides"])
log = logging.getLogger(__name__)

#: The OpenAPI schema of a body that is a file.
_FILE = {"type": "string", "format": "binary"}

#: The headers of a page of the slide listing that is not the last (OpenAPI).
_PAGE_HEADERS = {
    "Link": {
        "description": 'The next page, RFC 8288: `</v1/slides?limit=L&cursor=C>; rel="next"`; '
        "absent on the last page",
        "schema": {"type": "string"},
    },
    api.NEXT_CURSOR_HEADER: {
        "description": "The next page's `cursor`, opaque; absent on the last page",
        "schema": {"type": "string"},
    },
    api.UNREADABLE_SLIDES_HEADER: {
        "description": "Slides of this page left out: this version cannot read their stored "
        "configuration (each one's own requests answer 409 `slide_log_corrupt`)",
        "schema": {"type": "string"},
    },
}


def _slide_out(record: SlideRecord) -> api.Slide:
    return api.Slide(
        id=record.id,
        config=config_of(record),
        n_acquisitions=record.n_events,
        n_accepted=record.n_accepted,
        done=record.done,
        created_unix_s=record.created_s,
        updated_unix_s=record.updated_s,
    )


def _summary(record: SlideRecord) -> api.SlideSummary:
    """The slide without its list parameters of more than `api.MAX_LISTED_VALUES` values."""
    params: dict[str, api.ParamValue] = record.config.get("params", {})
    omitted = [
        name
        for name, value in params.items()
        if isinstance(value, list) and len(value) > api.MAX_LISTED_VALUES
    ]
    kept = {name: value for name, value in params.items() if name not in omitted}
    return api.SlideSummary(
        id=record.id,
        config=config_of(record, kept),
        n_acquisitions=record.n_events,
        n_accepted=record.n_accepted,
        done=record.done,
        created_unix_s=record.created_s,
        updated_unix_s=record.updated_s,
        omitted_params=omitted,
    )


@router.post(
    "/slides",
    status_code=201,
    dependencies=[Depends(json_body)],
    responses=JSON_BODY_RESPONSES,
)
async def create_slide(config: api.SlideCreate, slides: SlidesDep) -> api.Slide:
    """Create a slide scan; its strategy is built (and its parameters checked) at once."""
    slide_id = await slides.create(config)
    return _slide_out(await slides.record(slide_id))


@router.get(
    "/slides",
    dependencies=[Depends(query_as_declared)],
    responses={
        200: {
            "description": "The page's slides; the next page's URL and cursor in headers",
            "headers": _PAGE_HEADERS,
        }
    },
)
async def list_slides(
    request: Request,
    response: Response,
    slides: SlidesDep,
    limit: Annotated[
        int, Query(ge=1, le=api.MAX_PAGE_SLIDES, description="Most slides on the page")
    ] = api.DEFAULT_PAGE_SLIDES,
    cursor: Annotated[
        str | None,
        Query(max_length=512, description="The previous page's `next_cursor`; none: the first"),
    ] = None,
) -> list[api.SlideSummary]:
    """A page of slides, oldest first: each one's configuration without large arrays (a
    prior map: `omitted_params` names them) and its progress. Unless it is the last page,
    the `Link` header (rel="next") has the next page's URL and `X-Next-Cursor` its cursor."""
    after = None if cursor is None else decode_cursor(cursor)
    records = await slides.page(after, limit + 1)  # one more: is there a next page?
    page = records[:limit]
    if len(records) > limit:
        next_cursor = encode_cursor(page[-1].created_s, page[-1].id)
        query = urlencode({"limit": limit, "cursor": next_cursor})
        response.headers["Link"] = f'<{request.url.path}?{query}>; rel="next"'
        response.headers[api.NEXT_CURSOR_HEADER] = next_cursor
    summaries, unreadable = [], []
    for record in page:
        try:
            summaries.append(_summary(record))
        except CorruptLogError as error:  # that slide's own requests say so (409); not the page's
            log.error("%s", error)
            unreadable.append(record.id)
    if unreadable:
        response.headers[api.UNREADABLE_SLIDES_HEADER] = ", ".join(unreadable)
    return summaries


@router.get("/slides/{slide_id}")
async def get_slide(slide_id: SlideId, slides: SlidesDep) -> api.Slide:
    return _slide_out(await slides.record(slide_id))


@router.put(
    "/slides/{slide_id}/prior",
    status_code=204,
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {PRIOR_MEDIA_TYPE: {"schema": _FILE}},
        }
    },
    responses={
        415: {"model": api.Error, "description": "Not an .npy file's media type"},
        422: {"model": api.Error, "description": "Not an .npy of the slide's grid, or bad values"},
    },
)
async def put_prior(slide_id: SlideId, request: Request, slides: SlidesDep) -> Response:
    """The slide's prior map (kf-rescan), before its first acquisition: an .npy file of
    float64 or float32 heights, um, of shape (rows, cols), or (2, rows, cols) with their
    sigmas. It replaces the `prior_map_um` (and `prior_map_sigma_um`) parameters."""
    media = media_type(request)
    if media != PRIOR_MEDIA_TYPE:
        raise HTTPException(
            415,
            f"the prior map is an .npy file sent as {PRIOR_MEDIA_TYPE}; "
            f"got {media or 'no Content-Type'}",
        )
    await slides.set_prior(slide_id, await request.body())
    return Response(status_code=204)


@router.delete("/slides/{slide_id}", status_code=204)
async def delete_slide(slide_id: SlideId, slides: SlidesDep) -> Response:
    await slides.delete(slide_id)
    return Response(status_code=204)
