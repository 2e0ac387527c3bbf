"""The live web view of a scan: a page, its state as JSON, and its updates as server-sent events.

    GET /                      the page (the tiles' thumbnails, focus map, sigma, the
                               in-focus share so far, images per tile, flags, the
                               latest through-focus curve; with phase, a layer of each
                               tile's phase spread in rad; hover a tile for its numbers)
    GET /live/state?since=N    the tiles changed after version N (`LiveScan.changes`)
    GET /live/events           server-sent events: `update`, the same JSON, whenever the
                               scan moves on (at most `MAX_UPDATES_PER_S` a second; the
                               first one holds every tile); `end` when the server stops,
                               after the last update, and the stream ends
    GET /live/thumbnails.png   a thumbnail of each kept tile at its stage position, one
                               PNG (`thumbnails.Thumbnails`; transparent: not yet kept),
                               encoded again only when a tile was kept since
    GET /metrics               the scan's Prometheus metrics (`telemetry.ScanMetrics`)

The scheduler serves it while it scans (`focustrack scan --live-port`, and the demo);
`LiveServer` runs uvicorn on a thread of its own and shows one `LiveScan` at a time.
A stream looks for changes on the event loop (`MAX_UPDATES_PER_S` times a second), not
in a waiting thread, so stopping ends every stream within one look and no thread is
left blocked: the scheduler exits at once with clients connected.
"""

from __future__ import annotations

import argparse
import asyncio
import json
from collections.abc import AsyncIterator
from importlib.resources import files
from typing import Any

from fastapi import FastAPI, HTTPException, Query
from fastapi.responses import HTMLResponse, PlainTextResponse, Response, StreamingResponse

from focustrack_core.http_metrics import CONTENT_TYPE, RegistryMetrics
from focustrack_core.serving import BackgroundServer
from focustrack_scheduler.live import LiveScan

#: Updates sent per second at most: a fast scan's changes are batched, not one event each.
MAX_UPDATES_PER_S = 5.0
#: Seconds between keep-alive comments on an idle event stream.
KEEPALIVE_S = 15.0
#: The last event of every stream: the server is stopping (the page stops reconnecting).
END_EVENT = "event: end\ndata: {}\n\n"


def port_number(text: str) -> int:
    """A TCP port for argparse: 0 (any free one) to 65535; anything else is a usage error."""
    try:
        port = int(text)
    except ValueError:
        port = -1
    if not 0 <= port <= 65535:
        raise argparse.ArgumentTypeError(f"a port is 0 (any free one) to 65535, not {text!r}")
    return port


class LiveServer:
    """The live view on http://host:port/, in a background thread (a context manager)."""

    def __init__(self, host: str = "127.0.0.1", port: int = 0) -> None:
        self.scan: LiveScan | None = None
        self.closing = False  # set by `stop`: every event stream sends its last update and ends
        self.metrics: RegistryMetrics | None = None  # the scan's, served at /metrics
        self.app = create_app(self)
        self._server = BackgroundServer(self.app, host, port, name="live-view")

    @property
    def url(self) -> str:
        return self._server.url

    def start(self, timeout_s: float = 30.0) -> LiveServer:
        self._server.start(timeout_s)
        return self

    def show(self, scan: LiveScan) -> None:
        """Show `scan` from now on (the page starts over with its tiles)."""
        previous, self.scan = self.scan, scan
        if previous is not None:
            previous.finish()  # a scan no longer shown is over, even one that failed

    def stop(self) -> None:
        """End every event stream (after the scan's last update), then the server."""
        if self.scan is not None:
            self.scan.finish()
        self.closing = True
        self._server.stop()

    def __enter__(self) -> LiveServer:
        return self.start()

    def __exit__(self, *_: object) -> None:
        self.stop()


def create_app(server: LiveServer) -> FastAPI:
    app = FastAPI(title="FocusTrack live view", docs_url=None, redoc_url=None)
    page = files("focustrack_scheduler").joinpath("live.html").read_text()

    def current() -> LiveScan:
        if server.scan is None:
            raise HTTPException(503, "no scan has started yet")
        return server.scan

    @app.get("/", response_class=HTMLResponse)
    def index() -> str:
        return page

    @app.get("/healthz")
    def healthz() -> dict[str, Any]:
        """The server answers; the scan it shows, if any."""
        return {"status": "ok", "scan": None if server.scan is None else server.scan.label}

    @app.get("/live/state")
    def state(since: int = Query(0, ge=0)) -> dict[str, Any]:
        return current().changes(since)

    @app.get("/live/events")
    async def events() -> StreamingResponse:
        return StreamingResponse(_stream(server), media_type="text/event-stream")

    @app.get("/live/thumbnails.png")
    def thumbnails() -> Response:
        png = current().thumbnails.png()
        return Response(png, media_type="image/png", headers={"Cache-Control": "no-store"})

    @app.get("/metrics", response_class=PlainTextResponse)
    def metrics() -> PlainTextResponse:
        text = "" if server.metrics is None else server.metrics.render()
        return PlainTextResponse(text, media_type=CONTENT_TYPE)

    return app


async def _stream(server: LiveServer) -> AsyncIterator[str]:
    """Every change of the shown scan as an `update` event; all tiles again after a swap.

    Ends with `END_EVENT` once the server is closing, after the scan's last update.
    """
    scan: LiveScan | None = None
    version: int | None = None  # of the last update sent; None: none yet for `scan`
    idle_s = 0.0
    period_s = 1.0 / MAX_UPDATES_PER_S
    while True:
        closing = server.closing  # read first: a stop's last change is then seen below
        if server.scan is not scan:
            scan, version = server.scan, None
        if scan is not None and (version is None or scan.version > version):
            update = scan.changes(version or 0)
            version = update["version"]
            yield f"event: update\ndata: {json.dumps(update)}\n\n"
            idle_s = 0.0
        elif idle_s >= KEEPALIVE_S:
            yield ": keep-alive\n\n"
            idle_s = 0.0
        if closing:
            yield END_EVENT
            return
        await asyncio.sleep(period_s)
        idle_s += period_s
