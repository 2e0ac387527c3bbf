"""`LinkWatch` on real sessions: a client's router closed and opened again on the same
loopback port (a router restart), the watch begun before or during the outage; and
`AliveTokens` and `TokenWatch`: focus services' liveliness tokens coming and going."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from focustrack_core.testing import within
from focustrack_core.wire import keys
from focustrack_core.wire.session import (
    AliveTokens,
    LinkWatch,
    TokenWatch,
    loopback_endpoint,
    open_session,
)

GRACE_S = 0.3


def never_within(condition: Callable[[], bool], duration_s: float) -> bool:
    """Whether `condition` stays false for `duration_s`, asked every 50 ms."""
    return not within(condition, duration_s)


@pytest.mark.timeout(60)
def test_a_router_restart_is_seen_once_the_link_has_been_back_for_the_grace() -> None:
    endpoint = loopback_endpoint()
    router = open_session(listen=[endpoint], mode="router")
    with open_session(connect=[endpoint]) as client:
        assert within(lambda: bool(client.info.routers_zid()))
        watch, unbroken = LinkWatch(client, GRACE_S), LinkWatch(client, GRACE_S)
        assert never_within(unbroken.lost, 2 * GRACE_S)  # nothing happened: nothing lost
        router.close()
        assert never_within(watch.lost, 2 * GRACE_S)  # down: nothing to do but wait
        router = open_session(listen=[endpoint], mode="router")
        try:
            assert within(watch.lost)  # back: what was in flight is lost
            started = LinkWatch(client, GRACE_S)  # begun on the new link, which holds
            assert never_within(started.lost, 2 * GRACE_S)
        finally:
            router.close()
        assert within(lambda: not client.info.routers_zid())
        assert watch.lost()  # once lost, lost: down again changes nothing


@pytest.mark.timeout(60)
def test_a_watch_begun_while_the_router_is_down_counts_the_link_as_down() -> None:
    endpoint = loopback_endpoint()
    router = open_session(listen=[endpoint], mode="router")
    with open_session(connect=[endpoint]) as client:
        assert within(lambda: bool(client.info.routers_zid()))
        router.close()
        assert within(lambda: not client.info.routers_zid())
        watch = LinkWatch(client, GRACE_S)
        assert never_within(watch.lost, 2 * GRACE_S)
        with open_session(listen=[endpoint], mode="router"):
            assert within(watch.lost)


@pytest.mark.timeout(60)
def test_focus_services_that_all_went_are_seen_once_another_is_there() -> None:
    endpoint = loopback_endpoint()
    with (
        open_session(listen=[endpoint], mode="router"),
        open_session(connect=[endpoint]) as scheduler,
    ):
        tokens = AliveTokens(scheduler, keys.alive_pattern("focus", "slide-0"))
        first, also, other = (open_session(connect=[endpoint]) for _ in range(3))
        every_slide = keys.alive_key("focus", "*", str(first.info.zid()))
        this_slide = keys.alive_key("focus", "slide-0", "also")
        held = [  # a dropped token goes
            first.liveliness().declare_token(every_slide),
            also.liveliness().declare_token(this_slide),
            other.liveliness().declare_token(keys.alive_key("focus", "scanner-2-*", "x")),
        ]
        try:
            # another scanner's service is not watched
            assert within(lambda: tokens.alive() == {every_slide, this_slide})
            watch = TokenWatch(tokens)
            other.close()
            first.close()  # gone, but the other one of this slide may still publish
            assert within(lambda: tokens.alive() == {this_slide})
            assert never_within(watch.lost, 0.5)
            also.close()
            assert within(lambda: not tokens.alive())
            assert never_within(watch.lost, 0.5)  # all gone, and none to take the stack again
            missed = TokenWatch(tokens)  # a stack asked for with no service there
            with open_session(connect=[endpoint]) as second:
                held.append(
                    second.liveliness().declare_token(keys.alive_key("focus", "slide-0", "second"))
                )
                assert within(watch.lost) and missed.lost()
                assert not TokenWatch(tokens).lost()  # begun with the second alive
                late = AliveTokens(scheduler, keys.alive_pattern("focus", "slide-0"))
                assert within(lambda: late.alive() == tokens.alive() != frozenset())
                late.close()
            assert watch.lost()  # once lost, lost
        finally:
            tokens.close()
            for service in (first, also, other):
                service.close()
