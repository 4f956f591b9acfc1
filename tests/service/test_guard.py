"""The request guard (sdh2svc.service.guard) in process: the rules, one by one, on a bare ASGI app
that records what reaches it (tests/service/test_hardening.py tries them on a live service)."""

from __future__ import annotations

import json
from typing import Any

from sdh2svc.service.guard import Guard


class Recorder:
    """An ASGI app that reads the whole body and answers 200 with its length."""

    def __init__(self) -> None:
        self.calls: list[dict[str, Any]] = []

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] == "websocket":
            self.calls.append({"path": scope["path"]})
            await send({"type": "websocket.accept"})
            return
        body = b""
        while True:
            m = await receive()
            body += m.get("body", b"")
            if not m.get("more_body"):
                break
        self.calls.append({"path": scope["path"], "body": body})
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": str(len(body)).encode()})


def guard(app: Recorder, **kw: Any) -> Guard:
    opts: dict[str, Any] = {"token": "", "host": "127.0.0.1", "max_body_kb": 1}
    return Guard(app, **{**opts, **kw})


async def call(
    g: Guard,
    method: str = "GET",
    path: str = "/api/status",
    headers: dict[str, str] | None = None,
    chunks: tuple[bytes, ...] = (b"",),
) -> tuple[int, dict[str, Any] | bytes, int]:
    """One HTTP request: (status, JSON error or raw body, how many body chunks were read)."""
    hdrs = {"host": "127.0.0.1:8000", **(headers or {})}
    scope = {"type": "http", "method": method, "path": path, "scheme": "http",
             "headers": [(k.lower().encode(), v.encode()) for k, v in hdrs.items()]}  # fmt: skip
    pending = [{"type": "http.request", "body": c, "more_body": i < len(chunks) - 1}
               for i, c in enumerate(chunks)]  # fmt: skip
    read = 0
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        nonlocal read
        if pending:
            read += 1
            return pending.pop(0)
        return {"type": "http.disconnect"}

    async def send(m: dict[str, Any]) -> None:
        sent.append(m)

    await g(scope, receive, send)
    status = sent[0]["status"]
    body = b"".join(m.get("body", b"") for m in sent[1:])
    ctype = dict(sent[0]["headers"]).get(b"content-type")
    return status, json.loads(body) if ctype == b"application/json" else body, read


JSON = {"content-type": "application/json"}


async def test_host_allow_list_without_a_token() -> None:
    app = Recorder()
    g = guard(app, host="127.0.0.1", allowed_hosts=("lab-pc.local", "proxy:8443"))
    for host in ("127.0.0.1:8000", "localhost", "LOCALHOST:1", "[::1]:8000", "lab-pc.local:9",
                 "proxy:8443"):  # fmt: skip
        assert (await call(g, headers={"host": host}))[0] == 200, host
    for host in ("evil.example", "evil.example:8000", "127.0.0.1.evil.example", "proxy:8000",
                 "localhost.", "x" * 500):  # fmt: skip
        status, body, _ = await call(g, headers={"host": host})
        assert status == 400, host
        assert "host name" in body["error"] and len(body["error"]) < 200  # type: ignore[index]
    assert len(app.calls) == 6
    # with a token: the token protects, any Host passes
    assert (await call(guard(Recorder(), token="t"), headers={"host": "evil.example"}))[0] == 200


async def test_an_error_body_is_limited_as_the_apps() -> None:
    """However long the configuration's lists, a refusal's lines are as long as the app's
    errors may be (``error_content``, one rule for both)."""
    names = tuple(f"lab-pc-{i:03d}.example.org" for i in range(200))
    g = guard(Recorder(), allowed_hosts=names, allowed_origins=tuple(f"http://{n}" for n in names))
    status, body, _ = await call(g, headers={"host": "evil.example"})
    assert status == 400
    assert body["details"] and all(len(d) <= 401 for d in body["details"])  # type: ignore[index]
    assert "lab-pc-000.example.org" in body["details"][0]  # type: ignore[index]
    status, body, _ = await call(g, "POST", "/api/runs", {"origin": "http://evil.example", **JSON})
    assert status == 403
    assert all(len(d) <= 401 for d in body["details"])  # type: ignore[index]


async def test_origin_checked_on_mutating_requests_without_a_token() -> None:
    app = Recorder()
    g = guard(app, allowed_origins=("http://dash.example:9000",))
    own = {"origin": "http://127.0.0.1:8000", **JSON}
    assert (await call(g, "POST", "/api/runs", own))[0] == 200
    assert (await call(g, "POST", "/api/runs", JSON))[0] == 200  # no Origin: curl, a script
    ok = {"origin": "http://DASH.example:9000", **JSON}
    assert (await call(g, "PATCH", "/api/params", ok))[0] == 200
    for origin in ("http://evil.example", "null", "http://127.0.0.1:8001", "https://127.0.0.1:8000",
                   "http://dash.example"):  # fmt: skip
        status, body, _ = await call(g, "POST", "/api/runs", {"origin": origin, **JSON})
        assert status == 403, origin
        assert body["error"].startswith("cross-origin request refused")  # type: ignore[index]
    # reads are not checked (the browser keeps the answer from the page anyway)
    assert (await call(g, "GET", "/api/status", {"origin": "http://evil.example"}))[0] == 200
    # the default port is the same origin as none
    g80 = guard(Recorder())
    assert (await call(g80, "POST", "/x", {"host": "localhost", "origin": "http://localhost:80",
                                           **JSON}))[0] == 200  # fmt: skip
    # with a token, Origin is not the guard's business
    assert (await call(guard(Recorder(), token="t"), "POST", "/api/runs",
                       {"origin": "http://evil.example", **JSON}))[0] == 200  # fmt: skip


async def test_json_content_type_on_mutating_requests_whatever_the_token() -> None:
    for token in ("", "t"):
        app = Recorder()
        g = guard(app, token=token)
        for method in ("POST", "PUT", "PATCH", "DELETE"):
            for headers in ({}, {"content-type": "text/plain"},
                            {"content-type": "application/x-www-form-urlencoded"},
                            {"content-type": "multipart/form-data; boundary=x"}):  # fmt: skip
                status, body, _ = await call(g, method, "/api/runs", headers)
                assert status == 415, (method, headers)
                assert "application/json" in body["error"]  # type: ignore[index]
        assert not app.calls
        assert (await call(g, "POST", "/api/runs/stop", JSON))[0] == 200  # empty body: fine
        cs = {"content-type": "Application/JSON; charset=utf-8"}
        assert (await call(g, "POST", "/api/runs", cs, (b"{}",)))[0] == 200
        assert (await call(g, "GET", "/api/status"))[0] == 200  # reads need none


async def test_estop_is_exempt_from_origin_and_content_type_but_not_host() -> None:
    app = Recorder()
    g = guard(app)
    foreign = {"origin": "http://evil.example", "content-type": "text/plain"}
    assert (await call(g, "POST", "/api/estop", foreign))[0] == 200
    assert (await call(g, "POST", "/api/estop"))[0] == 200
    assert (await call(g, "POST", "/api/estop/release", foreign))[0] == 403
    assert (await call(g, "POST", "/api/estop/release"))[0] == 415
    assert (await call(g, "POST", "/api/estop", {"host": "evil.example"}))[0] == 400
    assert (await call(g, "POST", "/api/estop", {"content-length": "5000"}))[0] == 413
    assert (await call(g, "POST", "/api/estop/", foreign))[0] == 200  # a trailing slash too
    assert [c["path"] for c in app.calls] == ["/api/estop", "/api/estop", "/api/estop/"]


async def test_body_limit_from_content_length_and_from_counted_chunks() -> None:
    app = Recorder()
    g = guard(app, max_body_kb=1)
    # Content-Length: refused before a single chunk is read
    status, body, read = await call(g, "PATCH", "/api/params",
                                    {**JSON, "content-length": str(300 * 2**20)})  # fmt: skip
    assert (status, read) == (413, 0)
    assert "at most 1 kB" in body["error"] and "service.max_body_kb" in body["error"]  # type: ignore[index]
    # no Content-Length (chunked): counted as it comes, refused at the chunk that crosses it
    chunks = (b"x" * 400,) * 10
    status, _, read = await call(g, "PATCH", "/api/params", JSON, chunks)
    # 1200 bytes > 1024 at the third: the rest is read and dropped (so that the sender gets
    # the 413 rather than a reset connection), never kept
    assert (status, read) == (413, 10)
    assert not app.calls
    # at the limit: the app gets the whole body
    status, got, _ = await call(g, "PATCH", "/api/params", JSON, (b"x" * 1000, b"y" * 24))
    assert status == 200 and got == b"1024"
    assert app.calls[-1]["body"] == b"x" * 1000 + b"y" * 24
    # before the token: a large body is never buffered to be answered 401
    tok = guard(Recorder(), token="t", max_body_kb=1)
    assert (await call(tok, "PATCH", "/api/params", JSON, chunks))[0] == 413
    assert (await call(g, "GET", "/api/status", {"content-length": "x"}))[0] == 400


async def websocket(g: Guard, headers: dict[str, str], extension: bool) -> list[dict[str, Any]]:
    hdrs = {"host": "127.0.0.1:8000", **headers}
    scope: dict[str, Any] = {
        "type": "websocket", "path": "/ws/telemetry", "scheme": "ws",
        "headers": [(k.encode(), v.encode()) for k, v in hdrs.items()],
        "extensions": {"websocket.http.response": {}} if extension else {},
    }  # fmt: skip
    sent: list[dict[str, Any]] = []
    msgs = [{"type": "websocket.connect"}]

    async def receive() -> dict[str, Any]:
        return msgs.pop(0) if msgs else {"type": "websocket.disconnect", "code": 1000}

    async def send(m: dict[str, Any]) -> None:
        sent.append(m)

    await g(scope, receive, send)
    return sent


async def test_websocket_handshake_checks_host_and_origin() -> None:
    app = Recorder()
    g = guard(app)
    ok = await websocket(g, {"origin": "http://127.0.0.1:8000"}, extension=True)
    assert ok == [{"type": "websocket.accept"}]
    assert (await websocket(g, {}, extension=True)) == [{"type": "websocket.accept"}]
    bad = await websocket(g, {"origin": "http://evil.example"}, extension=True)
    assert bad[0]["type"] == "websocket.http.response.start" and bad[0]["status"] == 403
    assert json.loads(bad[1]["body"])["error"].startswith("cross-origin")
    bad = await websocket(g, {"host": "evil.example"}, extension=True)
    assert bad[0]["status"] == 400
    # a server without the response extension: the handshake is closed (HTTP 403)
    bad = await websocket(g, {"origin": "http://evil.example"}, extension=False)
    assert bad == [{"type": "websocket.close", "code": 1008}]
    assert len(app.calls) == 2
    # with a token the WebSocket is open, as every read is
    tok = guard(Recorder(), token="t")
    assert (await websocket(tok, {"origin": "http://evil.example"}, extension=True))[0] == {
        "type": "websocket.accept"
    }


async def test_a_refused_small_body_is_read_first_and_the_connection_kept() -> None:
    """Closing with unread input makes the kernel reset the connection, and the client may lose
    the answer: a refused body within the limit is read (and dropped) before the answer, which
    keeps the connection; only a body over the limit ends it."""
    app = Recorder()
    g = guard(app)
    chunks = [{"type": "http.request", "body": b'{"a":', "more_body": True},
              {"type": "http.request", "body": b"1}", "more_body": False}]  # fmt: skip
    sent: list[dict[str, Any]] = []

    async def receive() -> dict[str, Any]:
        return chunks.pop(0) if chunks else {"type": "http.disconnect"}

    async def send(m: dict[str, Any]) -> None:
        sent.append(m)

    headers = [(b"host", b"127.0.0.1:8000"), (b"content-type", b"text/plain")]
    scope = {"type": "http", "method": "POST", "path": "/api/estop/release", "scheme": "http",
             "headers": headers}  # fmt: skip
    await g(scope, receive, send)
    assert sent[0]["status"] == 415 and not chunks and not app.calls
    assert (b"connection", b"close") not in sent[0]["headers"]
    status, _, _ = await call(g, "POST", "/api/runs", JSON, chunks=(b"x" * 2048,))
    assert status == 413
