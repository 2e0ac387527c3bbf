"""Serving HTTP: off loopback a service refuses to start without a token unless --insecure."""

from __future__ import annotations

from focustrack_core.serving import http_url, is_loopback, refuse_open_network


def test_loopback_is_told_apart_from_the_network() -> None:
    assert all(map(is_loopback, ["127.0.0.1", "127.0.0.2", "::1", "localhost"]))
    assert not any(map(is_loopback, ["0.0.0.0", "::", "192.168.1.10", "estimator"]))
    assert refuse_open_network("focus", "127.0.0.1", None, insecure=False) is None
    assert refuse_open_network("focus", "0.0.0.0", "secret", insecure=False) is None
    assert refuse_open_network("focus", "0.0.0.0", None, insecure=True) is None
    message = refuse_open_network("focus", "0.0.0.0", None, insecure=False)
    assert message and "FOCUSTRACK_FOCUS_TOKEN" in message and "--insecure" in message


def test_a_url_brackets_an_ipv6_host() -> None:
    """`--host ::1` printed http://::1:8100, which no client takes."""
    assert http_url("::1", 8100) == "http://[::1]:8100"
    assert http_url("127.0.0.1", 8100, "/metrics") == "http://127.0.0.1:8100/metrics"
    assert http_url("localhost", 80, "/") == "http://localhost:80/"
