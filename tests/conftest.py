"""Servers for the system tests: the focus REST app on a real uvicorn server, in a thread.

Helper modules of this folder (`compose_runner`) are importable by its tests: pytest
imports test files by path (``--import-mode=importlib``), not this folder.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterator
from contextlib import ExitStack
from pathlib import Path

import pytest
from fastapi import FastAPI

sys.path.insert(0, str(Path(__file__).parent))

from focustrack_core.serving import BackgroundServer


@pytest.fixture
def serve() -> Iterator[Callable[[FastAPI], str]]:
    """Serve ASGI apps on loopback for the test: `url = serve(app)`; stopped after it."""
    with ExitStack() as servers:
        yield lambda app: servers.enter_context(BackgroundServer(app)).url.rstrip("/")
