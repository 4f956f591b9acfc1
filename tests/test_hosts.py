"""One rule for "this machine": the service's exposure check, the client's and health's
proxy bypass (sdh2svc.hosts)."""

from __future__ import annotations

import pytest

from sdh2svc.hosts import is_loopback


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
