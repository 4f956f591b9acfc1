"""Host names and origins, one spelling for every part that compares them: the service's
refusal to listen beyond this machine without a token, the client's and ``sdh2svc health``'s
asking it directly (never through the proxy of ``http_proxy``), the guard's Host and Origin
rules, the 3-D view's Origin check and framing, and the configuration's check of
``service.allowed_hosts`` and ``service.allowed_origins``."""

from __future__ import annotations

import ipaddress

#: The loopback names a Host header may say, in :func:`split_host`'s spelling.
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "[::1]")
_DEFAULT_PORTS = {"http": 80, "ws": 80, "https": 443, "wss": 443}

#: An origin as compared: (scheme, host as :func:`split_host` spells it, port or None).
Origin = tuple[str, str, int | None]


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


def split_host(value: str) -> tuple[str, int | None]:
    """``"Example.org:8000"`` → ``("example.org", 8000)``; IPv6 in brackets: ``"[::1]"``.

    A bare IPv6 address (as in ``service.host = "::1"``) comes back bracketed and compressed;
    anything a Host header cannot say (a scheme, a path, a user, a malformed port or address)
    gives ``("", None)``, which matches nothing.
    """
    value = value.strip().lower()
    if not value or any(c in value for c in "/?#@ \t"):
        return "", None
    if value.startswith("["):
        inner, close, rest = value[1:].partition("]")
        name = _v6(inner) if close else ""
        if not rest or not name:
            return name, None
        port_text = rest[1:] if rest.startswith(":") else "x"
    elif value.count(":") > 1:  # a bare IPv6 address
        return _v6(value), None
    else:
        name, sep, port_text = value.partition(":")
        if not sep:
            return name, None
    if not name or not port_text.isdigit() or not 0 < int(port_text) <= 65535:
        return "", None
    return name, int(port_text)


def _v6(text: str) -> str:
    try:
        return f"[{ipaddress.IPv6Address(text).compressed}]"
    except ValueError:
        return ""


def is_host(text: str) -> bool:
    """Whether ``text`` is what a Host header can say: ``name`` or ``name:port``, an IPv6
    address in brackets (with a port or not) or bare."""
    return bool(split_host(text)[0])


def accepted_hosts(
    host: str, allowed_hosts: tuple[str, ...]
) -> tuple[tuple[str, ...], tuple[tuple[str, int], ...]]:
    """The names this service answers to with any port (loopback, ``host``, the
    ``allowed_hosts`` entries without a port) and the (name, port) entries with one, in
    :func:`split_host`'s spelling, in order, each once; entries that can match nothing left out."""
    names, exact = list(LOOPBACK_NAMES), list[tuple[str, int]]()
    for entry in (host, *allowed_hosts):
        name, port = split_host(entry)
        if name and port is None:
            names.append(name)
        elif name and port is not None:
            exact.append((name, port))
    return tuple(dict.fromkeys(names)), tuple(dict.fromkeys(exact))


def origin_key(origin: str) -> Origin | None:
    """``scheme://host[:port]`` (a browser's Origin header, a configured origin; one ``/`` at
    its end allowed) as compared: lower case, the scheme's default port filled in for http(s)
    and ws(s); None for anything else (``null``, a path, a user, no scheme)."""
    scheme, sep, rest = origin.strip().lower().partition("://")
    if not sep or not scheme.isascii() or not scheme[:1].isalpha():
        return None
    if not all(c.isalnum() or c in "+-." for c in scheme):
        return None
    name, port = split_host(rest.removesuffix("/"))
    if not name:
        return None
    return scheme, name, port if port is not None else _DEFAULT_PORTS.get(scheme)


def origin_text(key: Origin) -> str:
    """An origin as a browser would write it: the scheme's default port left out."""
    scheme, name, port = key
    default = port is None or _DEFAULT_PORTS.get(scheme) == port
    return f"{scheme}://{name}" + ("" if default else f":{port}")
