"""For every test of the workspace: no FOCUSTRACK_* variable of the developer's shell, and
one HTTP client.

Each service reads its settings from the environment (`FOCUSTRACK_<SERVICE>_<OPTION>`);
a token or a port left set in a shell would otherwise change what a test's service,
or the service it spawns, does. A test that needs one sets it itself (monkeypatch).
"""

from __future__ import annotations

import os
from collections.abc import Iterator

import httpx
import pytest


@pytest.fixture(scope="session")
def http() -> Iterator[httpx.Client]:
    """The client a test asks the services' HTTP APIs with (full URLs; httpx's defaults).

    One for all of a worker's tests: `httpx.get` and the like make a client per call, and
    a client costs about 50 ms of CPU to make (its TLS context: the CA bundle read and
    parsed), which polls and scans of hundreds of requests added up to minutes of the
    suite's CPU. It keeps no connection open between requests, as `httpx.get` did not:
    the tests kill and restart the servers they ask, behind port forwards and balancers
    that may hold a dead server's connection open.
    """
    with httpx.Client(limits=httpx.Limits(max_keepalive_connections=0)) as client:
        yield client


@pytest.fixture(autouse=True)
def _no_focustrack_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [name for name in os.environ if name.startswith("FOCUSTRACK_")]:
        monkeypatch.delenv(name)
