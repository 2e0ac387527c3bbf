"""For every test of the workspace: no FOCUSTRACK_* variable of the developer's shell.

Each service reads its settings from the environment (`FOCUSTRACK_<SERVICE>_<OPTION>`);
a token or a port left set in a shell would otherwise change what a test's service,
or the service it spawns, does. A test that needs one sets it itself (monkeypatch).
"""

from __future__ import annotations

import os

import pytest


@pytest.fixture(autouse=True)
def _no_focustrack_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [name for name in os.environ if name.startswith("FOCUSTRACK_")]:
        monkeypatch.delenv(name)
