"""For every test of the workspace: no FOCUSTRACK_* variable of the developer's shell, and
the slow test files first.

Each service reads its settings from the environment (`FOCUSTRACK_<SERVICE>_<OPTION>`);
a token or a port left set in a shell would otherwise change what a test's service,
or the service it spawns, does. A test that needs one sets it itself (monkeypatch).
"""

from __future__ import annotations

import os

import pytest


def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Files with a slow test first, each file's tests in their own order.

    With `--dist loadfile` a worker takes a whole file at a time, in collection order once
    xdist's own reordering (by number of tests, most first) is off (`--no-loadscope-reorder`
    in the Makefile). That reordering puts the end-to-end files, a few long tests each,
    last: one of them started at the end keeps its worker busy while the others have
    nothing left to do. Started first, they leave the many short files to even out the end.
    """
    slow_files = {item.path for item in items if item.get_closest_marker("slow")}
    items.sort(key=lambda item: item.path not in slow_files)


@pytest.fixture(autouse=True)
def _no_focustrack_environment(monkeypatch: pytest.MonkeyPatch) -> None:
    for name in [name for name in os.environ if name.startswith("FOCUSTRACK_")]:
        monkeypatch.delenv(name)
