"""What a scan has learnt: its focus maps, and the diagnostics of its filter (under /v1)."""

from __future__ import annotations

import asyncio
from dataclasses import asdict
from typing import TYPE_CHECKING, Annotated

from fastapi import APIRouter, Depends, Query, Response

from focustrack_client import models as api
from focustrack_core.maps import MAP_LAYERS
from focustrack_core.web import query_as_declared
from focustrack_estimator.dependencies import SlideId, SlidesDep
from focustrack_estimator.maps_out import FILE_MEDIA, MapFormat, render_map

if TYPE_CHECKING:
    from focustrack_estimator.diagnose import SlideDiagnostics

router = APIRouter(prefix="/v1", tags=["maps"])


@router.get(
    "/slides/{slide_id}/map",
    dependencies=[Depends(query_as_declared)],
    response_model=api.FocusMapOut,
    responses={
        200: {
            "content": {media: {} for media in FILE_MEDIA.values()},
            "description": "JSON (default); CSV, one line per tile; .npy, a structured array "
            f"with fields {', '.join(MAP_LAYERS)}; PNG, a heat map of the posterior and its sigma",
        }
    },
)
async def get_map(
    slide_id: SlideId,
    slides: SlidesDep,
    map_format: Annotated[MapFormat, Query(alias="format")] = "json",
) -> Response:
    """The prior, posterior and smoothed focus maps with their sigma (um)."""
    focus_map, grid = await slides.run(slide_id, lambda slide: (slide.focus_map(), slide.grid))
    content, media_type = await asyncio.to_thread(
        render_map, focus_map, grid, map_format, f"slide {slide_id}"
    )
    return Response(content, media_type=media_type)


@router.get("/slides/{slide_id}/diagnostics")
async def get_diagnostics(slide_id: SlideId, slides: SlidesDep) -> api.Diagnostics:
    """Counts and innovation statistics (mean, NIS, whiteness) of the scan so far."""
    return _diagnostics_out(await slides.run(slide_id, lambda slide: slide.diagnose()))


def _diagnostics_out(result: SlideDiagnostics) -> api.Diagnostics:
    stats, risk = result.innovations, result.risk
    return api.Diagnostics(
        n_acquisitions=result.n_acquisitions,
        n_measured=result.n_measured,
        n_accepted=result.n_accepted,
        n_rejected=result.n_rejected,
        innovations_note=result.innovations_note,
        sigma_scale=result.sigma_scale,
        innovations=None
        if stats is None
        else api.InnovationStats(
            n=stats.n,
            mean_innovation_um=stats.mean_um,
            mean_z=stats.mean_z,
            mean_nis=stats.mean_nis,
            nis_low=stats.nis_interval[0],
            nis_high=stats.nis_interval[1],
            autocorrelation=stats.autocorrelation.tolist(),
            autocorrelation_bound=stats.autocorrelation_bound,
            ljung_box_q=stats.ljung_box_q,
            ljung_box_p=stats.ljung_box_p,
            zero_mean=stats.zero_mean,
            consistent=stats.consistent,
            white=stats.white,
        ),
        risk=None if risk is None else api.RiskStats(**asdict(risk)),
    )
