"""The service's gate: which requests reach the app at all (docs/api.md, *Who may command it*).

A pure ASGI middleware, so that it sees WebSocket handshakes as well as HTTP requests, and refuses
before the app reads a byte of a body:

* **Host** (only without a token): the ``Host`` header must name this service — a loopback name
  (``localhost``, ``127.0.0.1``, ``[::1]``, any port), ``service.host``, or one of
  ``service.allowed_hosts`` — else 400. A page of another site that makes its own name resolve
  to 127.0.0.1 (DNS rebinding) still sends its own name here.
* **Body size**, whatever the token: more than ``service.max_body_kb`` is refused with 413, from
  ``Content-Length`` at once, or by counting the chunks of a body sent without one.
* **Origin** (only without a token), on mutating requests and the WebSocket handshake: when a
  browser sends one, it must be the service's own (same scheme, host and port as the request's
  ``Host``) or one of ``service.allowed_origins``, else 403. Scripts and curl send none.
* **Content type**, whatever the token: a mutating request (POST, PUT, PATCH, DELETE) must say
  ``Content-Type: application/json`` (its body may be empty), else 415. A web page can send
  ``text/plain`` anywhere without asking; JSON it cannot without the browser's CORS preflight,
  which this service never grants.

* **Framing**: every answer forbids other sites' pages to frame it (``frame-ancestors 'self'``,
  ``X-Frame-Options``): a page that framed the dashboard, its own Origin being the service's,
  could have a click on it drive the hand (clickjacking).
* **HEAD** is answered as its GET, without the body (the routes answer GET only; monitors and
  ``curl -I`` ask with HEAD), after the same rules.

``POST /api/estop`` is exempt from the Origin and content-type rules (and, in the app, from the
token): stopping the hand must always work, from anything. The Host and size rules still apply.
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any

from sdh2svc.config import clip
from sdh2svc.hosts import (
    LOOPBACK_NAMES,
    Origin,
    accepted_hosts,
    origin_key,
    origin_text,
    split_host,
)

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

MUTATING = frozenset({"POST", "PUT", "PATCH", "DELETE"})
# A body over the limit but within this is read and dropped before the 413, so that its sender
# gets the answer; a larger one is answered at once (and the connection closed).
DRAIN_MAX_BYTES = 16 * 2**20
ESTOP_PATH = "/api/estop"


class Guard:
    """The middleware: ``Guard(app, token=…, host=…, allowed_hosts=…, allowed_origins=…,
    max_body_kb=…)`` (``app.add_middleware(Guard, …)``)."""

    def __init__(
        self,
        app: ASGIApp,
        *,
        token: str,
        host: str,
        allowed_hosts: tuple[str, ...] = (),
        allowed_origins: tuple[str, ...] = (),
        max_body_kb: int = 1024,
    ) -> None:
        self.app = app
        self.token = token
        self.max_body = max_body_kb * 1024
        self.max_body_kb = max_body_kb
        # names allowed with any port; "name:port" entries allow that port only
        names, exact = accepted_hosts(host, allowed_hosts)
        self.host_names, self.host_exact = set(names), set(exact)
        self.origins: set[Origin] = {k for o in allowed_origins if (k := origin_key(o))}
        self._allowed_text = ", ".join(dict.fromkeys([*LOOPBACK_NAMES, host, *allowed_hosts]))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        kind = scope["type"]
        if kind == "http":
            await self._http(scope, receive, send)
        elif kind == "websocket":
            await self._websocket(scope, receive, send)
        else:
            await self.app(scope, receive, send)

    # --- the rules --------------------------------------------------------------------------------

    def _host_refusal(self, headers: dict[str, list[str]]) -> tuple[int, str, list[str]] | None:
        if self.token:
            return None
        hosts = headers.get("host", [])
        if len(hosts) != 1:
            return 400, "send exactly one Host header", []
        name, port = split_host(hosts[0])
        if name in self.host_names or (name, port) in self.host_exact:
            return None
        return (400, f"this service does not answer to the host name {clip(hosts[0])!r}",
                [f"allowed (any port): {self._allowed_text}; add a name to "
                 "service.allowed_hosts, or set service.token"])  # fmt: skip

    def _origin_refusal(
        self, scope: Scope, headers: dict[str, list[str]]
    ) -> tuple[int, str, list[str]] | None:
        if self.token or "origin" not in headers:
            return None
        origins = headers["origin"]
        scheme = "https" if scope.get("scheme") in ("https", "wss") else "http"
        own = origin_key(f"{scheme}://{headers['host'][0]}") if "host" in headers else None
        if len(origins) == 1:
            key = origin_key(origins[0])
            if key is not None and (key == own or key in self.origins):
                return None
        listed = ", ".join(sorted(map(origin_text, self.origins))) or "none"
        return (403, f"cross-origin request refused: Origin {clip(origins[0])!r} is not this "
                "service's", [f"allowed: {own and origin_text(own)} and service.allowed_origins "
                              f"({listed})"])  # fmt: skip

    def _type_refusal(self, headers: dict[str, list[str]]) -> tuple[int, str, list[str]] | None:
        types = headers.get("content-type", [])
        media = types[0].split(";", 1)[0].strip().lower() if len(types) == 1 else ""
        if media == "application/json":
            return None
        got = clip(types[0]) if len(types) == 1 else ("none" if not types else "several")
        return (415, "send requests that change something as JSON: "
                "'Content-Type: application/json' (the body may be empty)",
                [f"Content-Type: {got}"])  # fmt: skip

    def _too_large(self) -> tuple[int, str, list[str]]:
        return (413, f"request body too large: at most {self.max_body_kb} kB "
                "(service.max_body_kb)", [])  # fmt: skip

    # --- HTTP -------------------------------------------------------------------------------------

    async def _http(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = _headers(scope)
        method = scope.get("method", "GET")
        send = _unframeable(send)
        if method == "HEAD":
            scope, send = {**scope, "method": "GET"}, _without_body(send)
        # (with a trailing slash too: a client that writes one must stop the hand all the same)
        estop = method == "POST" and scope.get("path", "").rstrip("/") == ESTOP_PATH
        refusal = self._host_refusal(headers)
        lengths = headers.get("content-length", [])
        if refusal is None:
            if len(lengths) > 1 or (lengths and not lengths[0].strip().isdigit()):
                refusal = 400, "send one valid Content-Length", []
            elif lengths and int(lengths[0]) > self.max_body:
                refusal = self._too_large()
        if refusal is None and method in MUTATING and not estop:
            refusal = self._origin_refusal(scope, headers) or self._type_refusal(headers)
        if refusal is not None:
            too_large = refusal[0] == 413
            # Read (and drop) the body before answering: a server that closes with unread input
            # makes the kernel reset the connection, and the client may lose the answer itself
            # (a 413 came back as "connection reset" one time in five). A body declared beyond
            # DRAIN_MAX_BYTES is answered at once: reading it would be the attack.
            declared = int(lengths[0]) if lengths and lengths[0].strip().isdigit() else 0
            if not too_large:
                await _drain(receive, self.max_body)
            elif declared <= DRAIN_MAX_BYTES:
                await _drain(receive, DRAIN_MAX_BYTES)
            await _send_error(send, *refusal, close=too_large)
            return
        # the body, counted as it comes: a body without Content-Length (chunked) never grows
        # past the limit in memory
        chunks: list[bytes] = []
        size = 0
        while True:
            message = await receive()
            if message["type"] != "http.request":  # the client went away
                return
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body:
                if message.get("more_body", False):  # the rest read and dropped (see above)
                    await _drain(receive, DRAIN_MAX_BYTES)
                await _send_error(send, *self._too_large())
                return
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        body = b"".join(chunks)
        del chunks
        replayed = False

        async def replay() -> Message:
            nonlocal replayed
            if not replayed:
                replayed = True
                return {"type": "http.request", "body": body, "more_body": False}
            return await receive()

        await self.app(scope, replay, send)

    # --- WebSocket --------------------------------------------------------------------------------

    async def _websocket(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = _headers(scope)
        refusal = self._host_refusal(headers) or self._origin_refusal(scope, headers)
        if refusal is None:
            await self.app(scope, receive, send)
            return
        message = await receive()  # websocket.connect
        if message["type"] != "websocket.connect":
            return
        if "websocket.http.response" in scope.get("extensions", {}):
            status, text, details = refusal
            body = _error_body(text, details)
            await send({"type": "websocket.http.response.start", "status": status,
                        "headers": [(b"content-type", b"application/json"),
                                    (b"content-length", str(len(body)).encode())]})  # fmt: skip
            await send({"type": "websocket.http.response.body", "body": body})
        else:
            await send({"type": "websocket.close", "code": 1008})


FRAME_HEADERS = ((b"content-security-policy", b"frame-ancestors 'self'"),
                 (b"x-frame-options", b"SAMEORIGIN"))  # fmt: skip


def _unframeable(send: Send) -> Send:
    """``send`` whose answer forbids framing by other sites' pages (:data:`FRAME_HEADERS`)."""

    async def framed(message: Message) -> None:
        if message["type"] == "http.response.start":
            message = {**message, "headers": [*message.get("headers", []), *FRAME_HEADERS]}
        await send(message)

    return framed


def _without_body(send: Send) -> Send:
    """``send`` for a HEAD request: the GET's status and headers (its length too), no body."""

    async def headless(message: Message) -> None:
        if message["type"] == "http.response.body":
            message = {**message, "body": b""}
        await send(message)

    return headless


def _headers(scope: Scope) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for key, value in scope.get("headers", []):
        out.setdefault(key.decode("latin-1").lower(), []).append(value.decode("latin-1"))
    return out


async def _drain(receive: Receive, limit: int) -> None:
    """Receive a request's body and drop it, up to ``limit`` bytes."""
    size = 0
    while size <= limit:
        message = await receive()
        if message["type"] != "http.request" or not message.get("more_body", False):
            return
        size += len(message.get("body", b""))


async def _send_error(
    send: Send, status: int, message: str, details: list[str], *, close: bool = True
) -> None:
    """The JSON error; ``close``: the connection ends after it (a body too large to read)."""
    body = _error_body(message, details)
    headers = [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())]
    if close:
        headers.append((b"connection", b"close"))
    await send({"type": "http.response.start", "status": status, "headers": headers})
    await send({"type": "http.response.body", "body": body})


MESSAGE_CHARS = 400  # an error's sentence, and each of its detail lines, at most
DETAIL_LINES = 50


def error_content(message: str, details: list[str]) -> dict[str, Any]:
    """Every error's body, the guard's and the app's (``api.errors``): the last guard against
    echoing a long value back (what builds the message clips what it quotes)."""
    lines = [clip(d, MESSAGE_CHARS) for d in details][:DETAIL_LINES]
    return {"error": clip(message, MESSAGE_CHARS), "details": lines}


def _error_body(message: str, details: list[str]) -> bytes:
    """The error body, encoded as the app's own (Starlette's JSONResponse: compact, UTF-8)."""
    return json.dumps(error_content(message, details), ensure_ascii=False,
                      separators=(",", ":")).encode()  # fmt: skip
