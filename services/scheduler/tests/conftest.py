"""Fixtures shared by the scheduler's tests."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from focustrack_core.wire import session


@pytest.fixture
def sessions() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    """(the stand-ins' session, the scheduler's), linked on loopback."""
    endpoint = session.loopback_endpoint()
    with (
        session.open_session(listen=[endpoint]) as bus,
        session.open_session(connect=[endpoint]) as scheduler,
    ):
        yield bus, scheduler
