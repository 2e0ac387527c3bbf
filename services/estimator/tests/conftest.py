"""Fixtures of the estimator's tests: an app in process over a store of its own.

Helper modules of this folder (`estimator_in_process`, `remote_strategy`) are importable by
its tests: pytest imports test files by path (``--import-mode=importlib``), not this folder.
"""

from __future__ import annotations

import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi import FastAPI

sys.path.insert(0, str(Path(__file__).parent))

from estimator_in_process import estimator
from postgres_server import PostgresServer, postgres_server


@pytest.fixture
def app(tmp_path: Path) -> Iterator[FastAPI]:
    """The estimator's app on default settings, over a new store."""
    with estimator(tmp_path / "estimator.sqlite") as app:
        yield app


@pytest.fixture(scope="session")
def postgres() -> Iterator[PostgresServer]:
    """A real PostgreSQL server on loopback for this pytest worker (skips where there is none
    and it cannot be installed); each test takes a database of its own (`new_database`)."""
    with postgres_server() as server:
        yield server
