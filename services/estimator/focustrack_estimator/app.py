"""The estimator's REST API: FastAPI routers over `slides.Slides`, under /v1.

`create_app(settings)` builds the application: its store, its live slides, its
metrics, the optional bearer-token check (off unless a token is configured),
the request body limit and timeout, and the mapping of domain errors to HTTP
statuses (404 unknown slide, 409 not the pending acquisition or a conflicting
re-post, 422 invalid input or a slide over the cost budget, 413 oversized body,
408 a body too slow to arrive), each with a `detail` naming the problem (and
quoting at most 200 characters of any input).
"""

from __future__ import annotations

import asyncio
import gc
import json
import secrets
import time
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from dataclasses import asdict, dataclass
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Depends, FastAPI, HTTPException, Path, Query, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from focustrack_client import models as api
from focustrack_core.domain import FocusMap
from focustrack_core.geometry import ScanGrid
from focustrack_core.maps import (
    MAP_LAYERS,
    layer_json,
    map_csv,
    map_layers,
    map_npy,
)
from focustrack_core.rest import to_api
from focustrack_core.serving import BodyLimit, SlowBodyTimeout, cut
from focustrack_estimator import registry
from focustrack_estimator.errors import SlideError
from focustrack_estimator.lean import RiskSummary, summarise_risk
from focustrack_estimator.metrics import EstimatorMetrics
from focustrack_estimator.params import StrategyInfo, publish_params, strategy_infos
from focustrack_estimator.slides import (
    Budget,
    GridLimits,
    Slide,
    Slides,
    diagnose,
    map_png,
)
from focustrack_estimator.store import SlideRecord, Store


@dataclass(frozen=True)
class Settings:
    """How the service runs: its SQLite file, its bearer token (None: no auth), its body limit
    and body timeout, the largest grid a slide may have, each slide's cost budget and the
    live slides' (`slides.Budget`), and how often a slide's state is snapshotted."""

    store_path: str
    token: str | None = None
    max_body_bytes: int = 64 * 1024
    max_grid_side: int = GridLimits.max_side
    max_grid_tiles: int = GridLimits.max_tiles
    snapshot_every: int = 200  # measurements between a slide's snapshots
    body_timeout_s: float = 30.0  # a request body must arrive whole within this
    max_slide_bytes: int = Budget.max_slide_bytes
    max_tile_s: float = Budget.max_tile_s
    max_live_slides: int = Budget.max_live_slides
    max_live_bytes: int = Budget.max_live_bytes
    catalogue: registry.Catalogue = registry.SERVED  # the strategies served


#: Worker threads for strategy work and SQLite (a request waiting for its commit holds one).
WORKER_THREADS = 64

SlideId = Annotated[str, Path(min_length=1, max_length=64, description="The id POST returned")]
_ERRORS: dict[int | str, dict[str, Any]] = {
    status: {"model": api.Error, "description": text}
    for status, text in (
        (401, "Missing or wrong bearer token"),
        (404, "Unknown slide"),
        (409, "Not the pending acquisition, a conflicting re-post, or a finished scan"),
        (413, "Request body too large"),
    )
}
_MAP_MEDIA = {
    "csv": "text/csv",
    "npy": "application/octet-stream",
    "png": "image/png",
}

#: The error code of an HTTP status the service answers without a more specific one.
_CODE_OF_STATUS = {
    401: api.ErrorCode.UNAUTHORIZED,
    404: api.ErrorCode.NOT_FOUND,
    405: api.ErrorCode.NOT_FOUND,
    409: api.ErrorCode.CONFLICT,
    413: api.ErrorCode.PAYLOAD_TOO_LARGE,
    422: api.ErrorCode.INVALID_REQUEST,
}


def error_response(
    status: int,
    code: api.ErrorCode | None,
    detail: object,
    headers: dict[str, str] | None = None,
) -> JSONResponse:
    """An error reply in the one shape of `api.Error`: a `code` for programs, a `detail`
    (long inputs quoted in it are cut: `focustrack_core.serving.cut`)."""
    if code is None:
        default = api.ErrorCode.INTERNAL if status >= 500 else api.ErrorCode.INVALID_REQUEST
        code = _CODE_OF_STATUS.get(status, default)
    return JSONResponse({"code": code, "detail": _cut_quotes(detail)}, status, headers=headers)


def _cut_quotes(detail: object) -> object:
    """`detail` with every string in it (messages, locations: a key may be 1 MB) cut short."""
    if isinstance(detail, str):
        return cut(detail)
    if isinstance(detail, list | tuple):
        return [_cut_quotes(item) for item in detail]
    if isinstance(detail, dict):
        return {key: _cut_quotes(value) for key, value in detail.items()}
    return detail


_bearer = HTTPBearer(auto_error=False, description="Required when the service has a token")


# Dependencies are coroutines: FastAPI runs plain functions in its thread pool, a thread
# hop per dependency per request (it tripled the latency of /next).
async def _require_token(
    request: Request,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> None:
    token: str = request.app.state.settings.token
    if credentials is None or not secrets.compare_digest(
        credentials.credentials.encode(), token.encode()
    ):
        raise HTTPException(
            401, "missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"}
        )


async def _slides(request: Request) -> Slides:
    return request.app.state.slides


async def _metrics(request: Request) -> EstimatorMetrics:
    return request.app.state.metrics


SlidesDep = Annotated[Slides, Depends(_slides)]
MetricsDep = Annotated[EstimatorMetrics, Depends(_metrics)]

v1 = APIRouter(prefix="/v1", responses=_ERRORS)


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


async def _record(slides: Slides, slide_id: str) -> SlideRecord:
    record = await asyncio.to_thread(slides.store.slide, slide_id)
    if record is None:
        raise HTTPException(404, f"no slide {slide_id!r}")
    return record


@v1.post("/slides", status_code=201, tags=["slides"])
async def create_slide(config: api.SlideCreate, slides: SlidesDep) -> api.Slide:
    """Create a slide scan; its strategy is built (and its parameters checked) at once."""
    slide_id = await slides.create(config)
    return _slide_out(await _record(slides, slide_id))


@v1.get("/strategies", tags=["strategies"])
async def list_strategies(slides: SlidesDep) -> list[StrategyInfo]:
    """The strategies served, each with its parameters: their JSON schema (types, units,
    bounds, defaults) and their defaults."""
    return strategy_infos(slides.catalogue)


@v1.get("/slides", tags=["slides"])
async def list_slides(slides: SlidesDep) -> list[api.Slide]:
    """Every slide with its configuration and progress, oldest first."""
    return [_slide_out(record) for record in await asyncio.to_thread(slides.store.slides)]


@v1.get("/slides/{slide_id}", tags=["slides"])
async def get_slide(slide_id: SlideId, slides: SlidesDep) -> api.Slide:
    return _slide_out(await _record(slides, slide_id))


@v1.delete("/slides/{slide_id}", status_code=204, tags=["slides"])
async def delete_slide(slide_id: SlideId, slides: SlidesDep) -> Response:
    await slides.delete(slide_id)
    return Response(status_code=204)


@v1.get("/slides/{slide_id}/next", tags=["scan"])
async def next_acquisition(slide_id: SlideId, slides: SlidesDep) -> api.Next:
    """The next tile to image and the z-range to acquire there (the same until measured)."""
    return await slides.run(slide_id, lambda slide: to_api.next_step(slide.next(), slide.grid))


@v1.post("/slides/{slide_id}/measurements", tags=["scan"])
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


def _map_json(focus_map: FocusMap, grid: ScanGrid) -> str:
    """The JSON of `api.FocusMapOut`, written directly: validating and serialising 280 000
    floats through the model took seconds for a 200x200 slide (a test checks it validates)."""
    layers = map_layers(focus_map)
    fields = {"rows": str(grid.rows), "cols": str(grid.cols)}
    for name in api.FocusMapOut.model_fields.keys() - fields.keys():
        missing = getattr(focus_map, name) is None
        fields[name] = "null" if missing else layer_json(layers[name])
    ordered = (f"{json.dumps(name)}:{fields[name]}" for name in api.FocusMapOut.model_fields)
    return "{" + ",".join(ordered) + "}"


@v1.get(
    "/slides/{slide_id}/map",
    tags=["maps"],
    response_model=api.FocusMapOut,
    responses={
        200: {
            "content": {media: {} for media in _MAP_MEDIA.values()},
            "description": "JSON (default); CSV, one line per tile; .npy, a structured array "
            f"with fields {', '.join(MAP_LAYERS)}; PNG, a heat map of the posterior and its sigma",
        }
    },
)
async def get_map(
    slide_id: SlideId,
    slides: SlidesDep,
    map_format: Annotated[Literal["json", "csv", "npy", "png"], Query(alias="format")] = "json",
) -> Response:
    """The prior, posterior and smoothed focus maps with their sigma (um)."""
    focus_map, grid = await slides.run(slide_id, lambda slide: (slide.focus_map(), slide.grid))
    content: str | bytes
    if map_format == "json":
        content = await asyncio.to_thread(_map_json, focus_map, grid)
        return Response(content, media_type="application/json")
    if map_format == "csv":
        content = await asyncio.to_thread(map_csv, focus_map, grid)
    elif map_format == "npy":
        content = await asyncio.to_thread(map_npy, focus_map)
    else:
        content = await asyncio.to_thread(map_png, focus_map, f"slide {slide_id}")
    return Response(content, media_type=_MAP_MEDIA[map_format])


@v1.get("/slides/{slide_id}/diagnostics", tags=["maps"])
async def get_diagnostics(slide_id: SlideId, slides: SlidesDep) -> api.Diagnostics:
    """Counts and innovation statistics (mean, NIS, whiteness) of the scan so far."""
    result, risk = await slides.run(slide_id, lambda slide: (diagnose(slide.history), _risk(slide)))
    stats = result.innovations
    return api.Diagnostics(
        n_acquisitions=result.n_acquisitions,
        n_measured=result.n_measured,
        n_accepted=result.n_accepted,
        n_rejected=result.n_rejected,
        innovations_note=result.innovations_note,
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


def _risk(slide: Slide) -> RiskSummary | None:
    strategy = slide.strategy
    risk_map = strategy.focus_map().out_of_focus_risk
    if risk_map is None:
        return None
    return summarise_risk(
        risk_map, strategy.stated_risk, strategy.settings.dof_um, strategy.measurement_sigma_um
    )


ops = APIRouter(tags=["operations"])


@ops.get("/healthz")
async def healthz(slides: SlidesDep) -> api.Health:
    return api.Health(status="ok", slides=await asyncio.to_thread(slides.store.count_slides))


@ops.get("/metrics", response_class=PlainTextResponse)
async def metrics_text(metrics: MetricsDep) -> PlainTextResponse:
    """Prometheus text exposition: requests, latencies, filter time, slides, measurements."""
    text = await asyncio.to_thread(metrics.render)
    return PlainTextResponse(text, media_type="text/plain; version=0.0.4")


class _RequestMetrics:
    """ASGI middleware: count and time every request by method, route template and status."""

    def __init__(self, app: ASGIApp, metrics: EstimatorMetrics) -> None:
        self.app, self.metrics = app, metrics

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        start_s = time.perf_counter()
        status = 500

        async def send_status(message: Message) -> None:
            nonlocal status
            if message["type"] == "http.response.start":
                status = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_status)
        finally:
            route = getattr(scope.get("route"), "path", "unmatched")  # the template, not the id
            self.metrics.requests.inc(method=scope["method"], route=route, status=str(status))
            self.metrics.latency.observe(time.perf_counter() - start_s, route=route)


def _allowed_methods(app: FastAPI, scope: Scope) -> list[str]:
    """Every method some route of the app serves at the request's path."""
    return sorted(
        {
            method
            for route in app.routes
            if isinstance(route, APIRoute) and route.matches(scope)[0] is not Match.NONE
            for method in route.methods or ()
        }
    )


def create_app(settings: Settings) -> FastAPI:
    """The estimator service over the store at `settings.store_path`."""
    budget = Budget(  # checked before the store is opened: a bad setting touches no file
        settings.max_slide_bytes,
        settings.max_tile_s,
        settings.max_live_slides,
        settings.max_live_bytes,
    )
    store = Store(settings.store_path)
    metrics = EstimatorMetrics(store.count_slides, lambda: slides.n_live)
    slides = Slides(
        store,
        timer=metrics.filter.observe,
        snapshot_every=settings.snapshot_every,
        limits=GridLimits(settings.max_grid_side, settings.max_grid_tiles),
        budget=budget,
        catalogue=settings.catalogue,
    )

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        # Requests wait in worker threads for their group commit: allow many at once.
        executor = ThreadPoolExecutor(WORKER_THREADS, thread_name_prefix="estimator")
        asyncio.get_running_loop().set_default_executor(executor)
        # Everything loaded so far lives as long as the process: out of the collector's
        # sight, a full collection no longer stalls every request (150-200 ms at 100 slides).
        gc.collect()
        gc.freeze()
        yield
        # At shutdown every live slide's state is snapshotted, so the next start replays
        # nothing (after a kill -9 it replays the events since the last periodic snapshot).
        await asyncio.to_thread(slides.save_snapshots)
        # The store is not closed here: in-process clients (TestClient) run the lifespan
        # once per session; whoever created the app closes it (`service.run`).

    app = FastAPI(
        title="focustrack estimator",
        version="1",
        summary="Each slide's focus estimator: the next tile and z-range, and what a "
        "measurement taught it",
        lifespan=lifespan,
    )
    app.state.settings, app.state.slides, app.state.metrics = settings, slides, metrics
    # The token check is only installed when there is a token (it costs a dependency per request).
    app.include_router(v1, dependencies=[Depends(_require_token)] if settings.token else [])
    app.include_router(ops)
    publish_params(app.openapi(), settings.catalogue)  # the document is built once, kept
    app.add_middleware(
        BodyLimit,
        max_bytes=settings.max_body_bytes,
        error_body=lambda detail: {"code": api.ErrorCode.PAYLOAD_TOO_LARGE, "detail": detail},
    )
    timeout = f"the request body did not arrive within {settings.body_timeout_s:g} s"
    app.add_middleware(
        SlowBodyTimeout,
        timeout_s=settings.body_timeout_s,
        error_body={"code": api.ErrorCode.INVALID_REQUEST, "detail": timeout},
    )
    app.add_middleware(_RequestMetrics, metrics=metrics)  # outermost: it counts the 413s too

    @app.exception_handler(SlideError)
    async def slide_error(_: Request, error: SlideError) -> JSONResponse:
        if error.status == 422:  # the shape of FastAPI's own 422: one schema for clients
            detail = [{"loc": list(error.where), "msg": str(error), "type": "value_error"}]
            return error_response(error.status, error.code, detail)
        return error_response(error.status, error.code, str(error))

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, error: StarletteHTTPException) -> JSONResponse:
        headers = dict(error.headers or {})
        if error.status_code == 405:  # Starlette names the methods of one route; a path has more
            headers["Allow"] = ", ".join(_allowed_methods(app, request.scope))
        if error.status_code == 400:
            # FastAPI's answer to a body it cannot decode (not UTF-8): malformed input like
            # any other, so the documented 422 invalid_request rather than an undocumented 400
            detail = [{"loc": ["body"], "msg": error.detail, "type": "json_invalid"}]
            return error_response(422, api.ErrorCode.INVALID_REQUEST, detail, headers)
        return error_response(error.status_code, None, error.detail, headers)

    @app.exception_handler(RequestValidationError)
    async def invalid_request(_: Request, error: RequestValidationError) -> JSONResponse:
        # FastAPI's own handler echoes the input, which fails to render when it is NaN or
        # infinite (a 500 for the very values it rejects): say where and what, not the value.
        detail = [{"loc": e["loc"], "msg": e["msg"], "type": e["type"]} for e in error.errors()]
        return error_response(422, api.ErrorCode.INVALID_REQUEST, detail)

    return app
