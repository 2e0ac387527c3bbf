"""Fixtures of the core's tests: Zenoh sessions linked on loopback."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
import zenoh

from focustrack_core.wire import session


@pytest.fixture
def pair() -> Iterator[tuple[zenoh.Session, zenoh.Session, zenoh.Session]]:
    """A listening peer and two clients connected to it, on a free loopback port."""
    endpoint = session.loopback_endpoint()
    with (
        session.open_session(listen=[endpoint]) as hub,
        session.open_session(connect=[endpoint]) as one,
        session.open_session(connect=[endpoint]) as two,
    ):
        yield hub, one, two
