"""Servers for the system tests: the focus REST app on a real uvicorn server, in a thread."""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import ExitStack

import pytest
from fastapi import FastAPI

from focustrack_core.serving import BackgroundServer


@pytest.fixture
def serve() -> Iterator[Callable[[FastAPI], str]]:
    """Serve ASGI apps on loopback for the test: `url = serve(app)`; stopped after it."""
    with ExitStack() as servers:
        yield lambda app: servers.enter_context(BackgroundServer(app)).url.rstrip("/")
