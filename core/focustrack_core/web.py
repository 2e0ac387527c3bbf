"""The FastAPI edge the stack services share (extra `web`): one app with the house's body
limits, 422 shape and Prometheus metrics at ``/metrics``, the bearer-token check of ``/v1``
(before the body is read), a query and a form of the route's own fields, each once, an
upload read within a limit, and the ``/healthz`` of a service that is on Zenoh too
(`with_bus_health`).

`serving` holds what needs no web framework (plain ASGI); this module is for the
services built on FastAPI (the focus and phase services), which import it.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

from fastapi import Depends, FastAPI, HTTPException, Request, UploadFile, params
from fastapi.dependencies.models import Dependant
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse, PlainTextResponse
from fastapi.routing import APIRoute
from fastapi.security import HTTPBearer
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from focustrack_core.http_metrics import CONTENT_TYPE, HttpMetrics
from focustrack_core.serving import (
    BearerGate,
    BodyLimit,
    ConcurrencyLimit,
    RequestTimer,
    Scope,
    SlowBodyTimeout,
    cut,
    quoted_errors,
)
from focustrack_core.tracing import TraceRequests

_bearer = HTTPBearer(auto_error=False, description="Required when the service has a token")


def check_least(limits: object, least: Mapping[str, int]) -> None:
    """ValueError naming the first of `limits`' fields (a service's request limits) below
    its `least`: a limit that admits no request is a configuration error, not a service
    that answers nothing."""
    for name, floor in least.items():
        if (value := getattr(limits, name)) < floor:
            raise ValueError(f"{name} must be at least {floor}, got {value}")


def bearer_scheme(token: str | None) -> Callable[..., Any]:
    """The dependency that shows a route's bearer token in the OpenAPI document when the
    service has one (`token`; None: no token, the document asks for none). It checks
    nothing: `guarded_app`'s `BearerGate` refuses a request without the token before its
    body is read, which a dependency, run after the body is parsed, cannot."""
    return _open if token is None else _bearer


async def _open() -> None:
    """The dependency of a service without a token: every request passes."""


def route_of(app: FastAPI) -> Callable[[Scope], str | None]:
    """For `RequestTimer`: the template of the route a request was addressed to (method
    and path), for a request the middleware refused before routing."""

    def template(scope: Scope) -> str | None:
        for route in app.router.routes:
            if isinstance(route, APIRoute) and route.matches(scope)[0] is Match.FULL:
                return route.path
        return None

    return template


def guarded_app(
    title: str,
    description: str,
    max_upload_bytes: int,
    body_timeout_s: float,
    metrics: HttpMetrics,
    token: str | None = None,
    max_concurrent: int | None = None,
    bounded_prefix: str = "/v1",
) -> FastAPI:
    """A FastAPI app that refuses a request under ``/v1`` without `token` as its bearer
    token (401, before its body is read; None: open), one under `bounded_prefix` beyond
    `max_concurrent` under way there (503 with Retry-After, before its body is read; None:
    no bound), a body over `max_upload_bytes` (413) or slower than `body_timeout_s` to
    arrive (408), answers invalid requests with the quoted 422, counts and times every
    request into `metrics`, served at ``GET /metrics`` (Prometheus text, no token: as
    ``/healthz``), and serves each in a span of the caller's trace (`TraceRequests`). Its
    routes declare the token with `bearer_scheme`."""
    app = FastAPI(
        title=title,
        version="1",
        description=description,
        dependencies=[Depends(query_as_declared)],
    )
    app.add_middleware(BodyLimit, max_bytes=max_upload_bytes, error_body=lambda d: {"detail": d})
    timeout = f"the request body did not arrive within {body_timeout_s:g} s"
    app.add_middleware(SlowBodyTimeout, timeout_s=body_timeout_s, error_body={"detail": timeout})
    if max_concurrent is not None:
        app.add_middleware(
            ConcurrencyLimit,
            max_concurrent=max_concurrent,
            error_body=lambda d: {"detail": d},
            prefix=bounded_prefix,
        )
    if token is not None:  # outside the bound: a request without the token takes no place
        app.add_middleware(BearerGate, token=token, error_body=lambda d: {"detail": d})
    # outermost: it counts the 401s, 413s and 408s too
    app.add_middleware(RequestTimer, observe=metrics.observe_request, route_of=route_of(app))
    app.add_middleware(TraceRequests)  # each request in a span, the caller's its parent

    @app.exception_handler(RequestValidationError)
    async def _invalid(_: Request, error: RequestValidationError) -> JSONResponse:
        return JSONResponse({"detail": quoted_errors(error.errors())}, status_code=422)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(_: Request, error: StarletteHTTPException) -> JSONResponse:
        # A form the multipart parser refuses is a 400 of its own words: a text field over
        # its 1 MB part limit (a million heights in z_um) is an oversized request (413, as
        # documented); its other refusals (a broken boundary, too many fields) are input
        # that cannot be read (422), as every other.
        if error.status_code == 400:
            oversized = str(error.detail).startswith("Part exceeded maximum size")
            detail = f"the form cannot be read: {error.detail}"
            if oversized:
                detail += " (a form field other than the stack's file is short text)"
            return JSONResponse({"detail": detail}, status_code=413 if oversized else 422)
        detail = cut(error.detail) if isinstance(error.detail, str) else error.detail
        return JSONResponse({"detail": detail}, error.status_code, headers=error.headers)

    @app.get("/metrics", response_class=PlainTextResponse, include_in_schema=False)
    async def _metrics() -> PlainTextResponse:
        return PlainTextResponse(metrics.render(), media_type=CONTENT_TYPE)

    return app


async def form_as_declared(request: Request) -> None:
    """A dependency that refuses (415) a body that is no form (a JSON body was a 422 listing
    every field as missing; a form without its file is the 422 that names it), and (422) a
    form with a field its route does not take (a misspelt ``photons_per_count`` would
    silently be its default) or with a field given twice (which of two stacks was meant
    is not for us to guess)."""
    media_type = request.headers.get("content-type", "").partition(";")[0].strip().lower()
    if media_type not in ("multipart/form-data", "application/x-www-form-urlencoded"):
        raise HTTPException(
            415,
            f"the body is {media_type or 'of no media type'}; this route takes "
            "multipart/form-data: the stack as a file field and the others as form fields "
            "(curl -F stack=@stack.npy -F 'z_um=[...]')",
        )
    form = await request.form()  # parsed already for the route's own fields: read again
    route: APIRoute = request.scope["route"]
    declared = {param.alias for param in route.dependant.body_params}
    unknown = sorted(set(form) - declared)
    if unknown:
        raise HTTPException(
            422,
            f"unknown form field {', '.join(unknown)}; this route takes "
            f"{', '.join(sorted(declared))}",
        )
    repeated = sorted({name for name in form if len(form.getlist(name)) > 1})
    if repeated:
        raise HTTPException(
            422, f"form field {', '.join(repeated)} given more than once; send each field once"
        )
    files = {param.alias for param in route.dependant.body_params if _is_file(param)}
    for name in sorted(files & set(form)):
        if isinstance(form[name], str):  # FastAPI's words: "Expected UploadFile, received: str"
            raise HTTPException(
                422, f"form field {name} must be a file (curl -F {name}=@FILE), not text"
            )


def _is_file(param: Any) -> bool:
    """Whether the body parameter `param` (a route's `ModelField`) takes an uploaded file."""
    return isinstance(param.field_info, params.File)


def _declared_query(dependant: Dependant) -> set[str]:
    """The query parameters a route (its dependant and theirs, recursively) takes, by name."""
    names = {param.alias for param in dependant.query_params}
    for sub in dependant.dependencies:
        names |= _declared_query(sub)
    return names


async def query_as_declared(request: Request) -> None:
    """A dependency that refuses (422, as any invalid request: each app's own shape) a query
    parameter its route does not take (``?fromat=png`` answered JSON, ``?limt=10`` a page
    of the default size) or one given twice (``?format=png&format=npy`` answered the last:
    which was meant is not for us to guess), as the JSON bodies refuse an unknown field."""
    route = request.scope.get("route")
    if not isinstance(route, APIRoute) or not request.query_params:
        return
    declared = _declared_query(route.dependant)
    takes = ", ".join(sorted(declared)) or "none"
    problems = [
        {
            "loc": ("query", name),
            "msg": f"unknown query parameter; this route takes {takes}",
            "type": "extra_forbidden",
        }
        for name in sorted(set(request.query_params) - declared)
    ] + [
        {"loc": ("query", name), "msg": "given more than once; give it once", "type": "value_error"}
        for name in sorted(set(request.query_params) & declared)
        if len(request.query_params.getlist(name)) > 1
    ]
    if problems:
        raise RequestValidationError(problems)


async def read_upload(upload: UploadFile, limit_bytes: int) -> bytes:
    """The bytes of `upload`, at most `limit_bytes` of them: 413 for a larger file, refused
    from its declared size where it has one, else after reading one byte past the limit."""
    if upload.size is not None and upload.size > limit_bytes:
        raise HTTPException(413, f"stack of {upload.size} bytes exceeds {limit_bytes}")
    data = await upload.read(limit_bytes + 1)
    if len(data) > limit_bytes:
        raise HTTPException(413, f"stack exceeds the limit of {limit_bytes} bytes")
    return data


def with_bus_health(app: FastAPI, bus_health: Callable[[], dict[str, str]]) -> FastAPI:
    """`app` whose ``/healthz`` also reports the Zenoh session (``status`` degraded while it
    is not open or has no router). The REST app knows nothing of Zenoh; its shell adds it."""
    routes = app.router.routes
    rest = next(r for r in routes if isinstance(r, APIRoute) and r.path == "/healthz")
    where = routes.index(rest)
    routes.remove(rest)

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        return rest.endpoint() | bus_health()

    # In the place of the one it replaces: FastAPI prepares each route the first time a
    # request is matched against it, in order, so the first probe prepares no other.
    routes.insert(where, routes.pop())
    return app
