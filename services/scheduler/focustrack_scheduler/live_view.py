"""The live web view of a scan: a page, its state as JSON, and its updates as server-sent events.

    GET /                      the page (focus map, sigma, images per tile, flags, the
                               latest through-focus curve; hover a tile for its numbers)
    GET /live/state?since=N    the tiles changed after version N (`LiveScan.changes`)
    GET /live/events           server-sent events: `update`, the same JSON, whenever the
                               scan moves on (at most `MAX_UPDATES_PER_S` a second; the
                               first one holds every tile)

The scheduler serves it while it scans (`focustrack scan --live-port`, and the demo);
`LiveServer` runs uvicorn on a thread of its own and shows one `LiveScan` at a time.
"""

from __future__ import annotations

import argparse
import asyncio
import json
from collections.abc import AsyncIterator
from importlib.resources import files
from typing import Any

from fastapi import FastAPI, HTTPException, Query
from fastapi.responses import HTMLResponse, StreamingResponse

from focustrack_core.serving import BackgroundServer
from focustrack_scheduler.live import LiveScan

#: Updates sent per second at most: a fast scan's changes are batched, not one event each.
MAX_UPDATES_PER_S = 5.0
#: Seconds between keep-alive comments on an idle event stream.
KEEPALIVE_S = 15.0


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
            previous.finish()  # wakes the streams waiting on it

    def stop(self) -> None:
        if self.scan is not None:
            self.scan.finish()
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

    @app.get("/live/state")
    def state(since: int = Query(0, ge=0)) -> dict[str, Any]:
        return current().changes(since)

    @app.get("/live/events")
    async def events() -> StreamingResponse:
        return StreamingResponse(_stream(server), media_type="text/event-stream")

    return app


async def _stream(server: LiveServer) -> AsyncIterator[str]:
    """Every change of the shown scan as an `update` event; all tiles again after a swap."""
    scan: LiveScan | None = None
    version = 0
    while True:
        if server.scan is not scan:
            scan, version = server.scan, 0
        if scan is None:
            await asyncio.sleep(0.2)
            continue
        if scan.version > version or version == 0:
            update = scan.changes(version)
            version = update["version"]
            yield f"event: update\ndata: {json.dumps(update)}\n\n"
            await asyncio.sleep(1.0 / MAX_UPDATES_PER_S)
            continue
        newer = await asyncio.to_thread(scan.wait, version, KEEPALIVE_S)
        if newer == version:
            yield ": keep-alive\n\n"
