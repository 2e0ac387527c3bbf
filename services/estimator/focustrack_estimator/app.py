"""The estimator's REST API: a FastAPI app over `slides.Slides`, its routes under /v1.

`create_app(store, settings)` builds the application over a store it is given
(whoever opened the store closes it): its live slides, its metrics, the optional
bearer-token check (off unless a token is configured), the request body limits (a
prior map's its own) and timeout, and the error replies (`handlers`). The routes are in
`routers`, what they depend on in `dependencies`.
"""

from __future__ import annotations

import asyncio
import copy
import gc
import math
import re
import threading
from collections.abc import AsyncIterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import asynccontextmanager
from typing import TYPE_CHECKING, Any

from fastapi import Depends, FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from focustrack_client import models as api
from focustrack_core.serving import BearerGate, BodyLimit, RequestTimer, SlowBodyTimeout
from focustrack_core.tracing import TraceRequests
from focustrack_core.web import bearer_scheme, route_of
from focustrack_estimator import handlers
from focustrack_estimator.budget import Budget, GridLimits
from focustrack_estimator.event_store import EventStore, StoreUnavailableError
from focustrack_estimator.metrics import EstimatorMetrics
from focustrack_estimator.prior import max_prior_bytes
from focustrack_estimator.routers import maps, operations, scan, slides, strategies
from focustrack_estimator.settings import EstimatorSettings
from focustrack_estimator.slides import Slides, load_strategies, strategies_loaded

if TYPE_CHECKING:
    from focustrack_estimator.registry import Catalogue

#: Worker threads for strategy work and the store (a request waiting for its commit holds one).
WORKER_THREADS = 64

#: Seconds after the service starts serving that its strategies load in the background.
STRATEGIES_DELAY_S = 0.3


#: The one route whose body is a file, not JSON: a prior map (`prior`), under a limit of its own.
_PRIOR_ROUTE = re.compile(r"/v1/slides/[^/]+/prior")


class _BodyLimits:
    """ASGI middleware: a PUT of a prior map may be as large as the largest grid's map and
    its sigmas (`max_prior_bytes`); every other request body `max_bytes` (the settings')."""

    def __init__(self, app: ASGIApp, *, max_bytes: int, max_prior_bytes: int) -> None:
        def error_body(detail: str) -> dict[str, str]:
            return {"code": api.ErrorCode.PAYLOAD_TOO_LARGE, "detail": detail}

        self.default = BodyLimit(app, max_bytes=max_bytes, error_body=error_body)
        self.prior = BodyLimit(app, max_bytes=max_prior_bytes, error_body=error_body)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        prior = scope["type"] == "http" and scope["method"] == "PUT"
        limit = self.prior if prior and _PRIOR_ROUTE.fullmatch(scope["path"]) else self.default
        await limit(scope, receive, send)


def create_app(
    store: EventStore, settings: EstimatorSettings, catalogue: Catalogue | None = None
) -> FastAPI:
    """The estimator service over `store`, as `settings` say; `catalogue`: the strategies
    served (None: the estimator's own, imported once the service serves)."""

    def slides_in_store() -> float:
        if store.problem() is not None:
            return math.nan  # not known; asking would wait for the store's timeout
        try:
            return store.count_slides()
        except StoreUnavailableError:
            return math.nan

    metrics = EstimatorMetrics(
        slides_in_store,
        lambda: live.n_live,
        strategies_loaded,
        lambda: store.problem() is not None,
    )
    live = Slides(
        store,
        limits=GridLimits.of(settings),
        budget=Budget.of(settings),
        snapshot_every=settings.snapshot_every,
        timer=metrics.filter.observe,
        catalogue=catalogue,
        discarded=metrics.snapshots_discarded.inc,
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
        # The strategies (scipy, filterpy: most of the start-up before) load beside the
        # serving, a moment after it starts: /healthz answers at once (their import would
        # share the interpreter with the first probe), and the first slide seldom waits
        # for them (a request that needs them before loads them itself).
        loader = threading.Timer(STRATEGIES_DELAY_S, load_strategies)
        loader.name, loader.daemon = "estimator-strategies", True
        loader.start()
        yield
        loader.cancel()
        # At shutdown every live slide's state is snapshotted, so the next start replays
        # nothing (after a kill -9 it replays the events since the last periodic snapshot).
        await asyncio.to_thread(live.save_snapshots)
        # The store is not closed here: in-process clients (TestClient) run the lifespan
        # once per session; whoever opened it closes it (`service.run`).

    app = FastAPI(
        title="focustrack estimator",
        version="1",
        summary="Each slide's focus estimator: the next tile and z-range, and what a "
        "measurement taught it",
        lifespan=lifespan,
    )
    app.state.settings, app.state.slides, app.state.metrics = settings, live, metrics
    # The token is checked by `BearerGate`, before a body is read; the routes only declare it
    # (OpenAPI), and only when there is one (a dependency costs a little per request).
    # /healthz first: FastAPI prepares a route when a request is first matched against it,
    # in order, so the health probe right after start does not wait for the others'.
    app.include_router(operations.router)
    token = [Depends(bearer_scheme(settings.token))] if settings.token else []
    for router in (slides.router, scan.router, maps.router, strategies.router):
        app.include_router(router, dependencies=token, responses=handlers.ERROR_RESPONSES)
    app.add_middleware(
        _BodyLimits,
        max_bytes=settings.max_body_bytes,
        max_prior_bytes=max_prior_bytes(settings.max_grid_tiles),
    )
    timeout = f"the request body did not arrive within {settings.body_timeout_s:g} s"
    app.add_middleware(
        SlowBodyTimeout,
        timeout_s=settings.body_timeout_s,
        error_body={"code": api.ErrorCode.INVALID_REQUEST, "detail": timeout},
    )
    if settings.token:
        app.add_middleware(
            BearerGate,
            token=settings.token,
            error_body=lambda d: {"code": api.ErrorCode.UNAUTHORIZED, "detail": d},
        )
    # outermost: it counts the 401s and 413s too
    app.add_middleware(RequestTimer, observe=metrics.observe_request, route_of=route_of(app))
    app.add_middleware(TraceRequests)  # each request in a span, the caller's its parent
    handlers.install(app)
    _publish_params_on_first_ask(app, live)
    return app


def _publish_params_on_first_ask(app: FastAPI, live: Slides) -> None:
    """Each served strategy's parameters model goes into the OpenAPI document the first
    time it is asked for once the strategies are loaded (`params.publish_params`; they load
    a moment after the service starts): until then the document is without them, rather
    than the event loop waiting for their import."""
    build = app.openapi  # FastAPI's: built once, then kept
    published: dict[str, Any] | None = None

    def openapi() -> dict[str, Any]:
        nonlocal published
        if published is None and strategies_loaded():
            from focustrack_estimator.params import publish_params

            document = copy.deepcopy(build())  # a failure leaves FastAPI's document whole
            publish_params(document, live.catalogue())
            published = document
        return build() if published is None else published

    app.openapi = openapi  # type: ignore[method-assign]
