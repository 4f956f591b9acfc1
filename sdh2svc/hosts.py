"""Which hosts are this machine's: one rule for the service's refusal to listen beyond it
without a token, and for the client's and ``sdh2svc health``'s asking it directly (never
through the proxy of ``http_proxy``)."""

from __future__ import annotations

import ipaddress


def is_loopback(host: str | None) -> bool:
    """Whether ``host`` (an address to listen on, or a URL's host name) is this machine's
    loopback: ``localhost`` (in any case) or a loopback address (IPv6 with or without its
    brackets). Any other name is taken to be reachable from elsewhere."""
    if not host:
        return False
    if host.lower() == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.removeprefix("[").removesuffix("]")).is_loopback
    except ValueError:
        return False
