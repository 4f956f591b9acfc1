"""One rule for "this machine": the service's exposure check, the client's and health's
proxy bypass (sdh2svc.hosts)."""

from __future__ import annotations

import pytest

from sdh2svc.hosts import (
    accepted_hosts,
    is_host,
    is_loopback,
    origin_key,
    origin_text,
    split_host,
)


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("localhost", True), ("LOCALHOST", True), ("127.0.0.1", True), ("127.8.9.10", True),
        ("::1", True), ("[::1]", True),
        ("0.0.0.0", False), ("::", False), ("192.168.1.42", False), ("labpc", False),
        ("foo.localhost", False), ("localhost.example.org", False), ("", False), (None, False),
    ],
)  # fmt: skip
def test_loopback_is_localhost_or_a_loopback_address(host: str | None, loopback: bool) -> None:
    assert is_loopback(host) is loopback


def test_the_service_and_the_client_ask_the_same_rule() -> None:
    from sdh2svc import client
    from sdh2svc.service import server

    assert client.is_loopback is server.is_loopback is is_loopback


@pytest.mark.parametrize(
    ("origin", "key"),
    [
        ("http://LocalHost:8000", ("http", "localhost", 8000)),
        ("http://localhost", ("http", "localhost", 80)),
        ("https://ops.example/", ("https", "ops.example", 443)),
        ("wss://ops.example", ("wss", "ops.example", 443)),
        ("http://[::1]:8000", ("http", "[::1]", 8000)),
        ("http://[0:0::1]", ("http", "[::1]", 80)),
        ("chrome-extension://abcdef", ("chrome-extension", "abcdef", None)),
        ("null", None), ("", None), ("localhost:8000", None), ("http://", None),
        ("http://a/b", None), ("http://a//", None), ("http://user@a", None), ("http://a?x", None),
        ("http://a:0", None), ("http://a:65536", None), ("http://a:x", None), ("http://[::1", None),
        ("http://[zz]", None), ("1http://a", None), ("ht tp://a", None),
    ],
)  # fmt: skip
def test_an_origin_as_compared(origin: str, key: tuple[str, str, int | None] | None) -> None:
    assert origin_key(origin) == key
    if key is not None:
        assert origin_key(origin_text(key)) == key


@pytest.mark.parametrize(
    ("value", "expected"),
    [("LocalHost:8000", ("localhost", 8000)), ("[::1]:80", ("[::1]", 80)),
     ("[::1]", ("[::1]", None)), ("::1", ("[::1]", None)), ("lab-pc", ("lab-pc", None)),
     ("a:b", ("", None)), ("a:123456", ("", None)), ("a:0", ("", None)), ("[::1", ("", None)),
     ("[::1]x", ("", None)), ("a/b", ("", None)), ("u@a", ("", None)), ("", ("", None))],
)  # fmt: skip
def test_a_host_as_compared(value: str, expected: tuple[str, int | None]) -> None:
    assert split_host(value) == expected
    assert is_host(value) is bool(expected[0])


def test_the_guard_the_view_and_the_configuration_spell_hosts_and_origins_alike() -> None:
    from sdh2svc import config
    from sdh2svc.service import guard, viewer

    assert guard.split_host is split_host
    assert guard.accepted_hosts is viewer.accepted_hosts is accepted_hosts
    assert guard.origin_key is viewer.origin_key is config.origin_key is origin_key
    assert config.is_host is is_host
