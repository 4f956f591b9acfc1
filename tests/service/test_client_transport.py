"""sdh2svc.client's telemetry and transport against small stand-in servers (no service): how
the telemetry ends when the service closes it, restarts, dies or answers no handshake; that
closing a client disconnects its telemetry; that tasks may share one stream; that its errors
pickle. What a lab script meets when the service goes away under it."""

from __future__ import annotations

import asyncio
import copy
import inspect
import json
import pickle
import re
import socket
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any, cast

import httpx
import pytest
from websockets.asyncio.server import ServerConnection, serve

import sdh2svc.client as client_module
from sdh2svc.client import AsyncClient, Client, NotFound, TooSlow, Unreachable

Handler = Callable[[ServerConnection], Any]


class Stand:
    """A WebSocket server on a free port whose every connection ``handler`` serves; counts
    the connections it has and has had."""

    def __init__(self, handler: Handler) -> None:
        self.handler, self.open, self.total = handler, 0, 0
        self.url = ""

    async def __call__(self, ws: ServerConnection) -> None:
        self.open += 1
        self.total += 1
        try:
            await self.handler(ws)
        finally:
            self.open -= 1


async def ticking(ws: ServerConnection) -> None:
    """A service's telemetry: hello, then a status every 20 ms."""
    await ws.send(json.dumps({"type": "hello"}))
    while True:
        await asyncio.sleep(0.02)
        await ws.send(json.dumps({"type": "status"}))


async def restarting(ws: ServerConnection) -> None:
    """hello, then the close a service sends as it shuts down (uvicorn: 1012)."""
    await ws.send(json.dumps({"type": "hello"}))
    await ws.close(1012, "service restart")


async def dying(ws: ServerConnection) -> None:
    """hello, then the connection cut without a close frame (the service killed)."""
    await ws.send(json.dumps({"type": "hello"}))
    await asyncio.sleep(0.05)
    ws.transport.abort()


async def cutting_off(ws: ServerConnection) -> None:
    """hello, then the close a service sends a client that took no message in time."""
    await ws.send(json.dumps({"type": "hello"}))
    await ws.close(1008, "too slow: took no message for 2 s (37 dropped)")


@pytest.fixture
async def stand(request: pytest.FixtureRequest) -> AsyncIterator[Stand]:
    st = Stand(request.param)
    async with serve(st, "127.0.0.1", 0) as server:
        port = next(iter(server.sockets)).getsockname()[1]
        st.url = f"http://127.0.0.1:{port}"
        yield st


async def _drain(tm: Any) -> list[str]:
    return [m["type"] async for m in tm]


def _sync_drain(url: str) -> list[str]:
    with Client(url, timeout=5.0) as c:
        return [m["type"] for m in c.telemetry()]


@pytest.mark.parametrize("stand", [restarting], indirect=True)
async def test_a_service_that_shuts_down_ends_the_telemetry(stand: Stand) -> None:
    """1012 ("service restart") is the service closing the socket: the iteration ends, it
    does not raise websockets' ConnectionClosedError."""
    async with AsyncClient(stand.url, timeout=5.0) as c:
        assert await _drain(c.telemetry()) == ["hello"]
    assert await asyncio.to_thread(_sync_drain, stand.url) == ["hello"]


@pytest.mark.parametrize("stand", [dying], indirect=True)
async def test_a_service_that_dies_is_unreachable(stand: Stand) -> None:
    async with AsyncClient(stand.url, timeout=5.0) as c:
        with pytest.raises(Unreachable, match="the telemetry was cut off"):
            await _drain(c.telemetry())
    with pytest.raises(Unreachable, match="the telemetry was cut off"):
        await asyncio.to_thread(_sync_drain, stand.url)


@pytest.mark.parametrize("stand", [cutting_off], indirect=True)
async def test_a_client_cut_off_for_reading_slowly_is_told_so(stand: Stand) -> None:
    """Not "the service is unreachable" (it is well), nor a normal end: TooSlow, with the
    service's reason (still an Unreachable, for scripts that catch that)."""
    why = "this client read too slow: took no message for 2 s (37 dropped)"
    async with AsyncClient(stand.url, timeout=5.0) as c:
        with pytest.raises(TooSlow, match=re.escape(why)):
            await _drain(c.telemetry())
    with pytest.raises(TooSlow, match=re.escape(why)):
        await asyncio.to_thread(_sync_drain, stand.url)
    assert issubclass(TooSlow, Unreachable)


async def test_a_handshake_that_is_no_handshake_is_unreachable() -> None:
    """A port that accepts and closes at once (a service dying, a proxy), and a URL without
    a scheme: Unreachable, as the REST calls raise, not websockets' own exceptions."""

    async def hang_up(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        writer.close()

    server = await asyncio.start_server(hang_up, "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]
    async with server:
        async with AsyncClient(f"http://127.0.0.1:{port}", timeout=5.0) as c:
            with pytest.raises(Unreachable):
                await c.telemetry().__anext__()
        with pytest.raises(Unreachable):
            await asyncio.to_thread(_sync_drain, f"http://127.0.0.1:{port}")
    with pytest.raises(Unreachable):
        next(Client("127.0.0.1:1").telemetry())


@pytest.mark.parametrize("stand", [ticking], indirect=True)
async def test_closing_a_client_disconnects_its_telemetry(stand: Stand) -> None:
    c = AsyncClient(stand.url, timeout=5.0)
    tm = c.telemetry()  # used as a plain async iterator: no `async with` to close it
    assert (await tm.__anext__())["type"] == "hello"
    assert stand.open == 1
    await c.aclose()
    with pytest.raises(StopAsyncIteration):
        await tm.__anext__()
    await _until(lambda: stand.open == 0)

    def sync_side() -> None:
        with Client(stand.url, timeout=5.0) as s:
            g = s.telemetry()
            assert next(g)["type"] == "hello"
        # leaving `with` closed the socket: the generator ends
        assert [m["type"] for m in g][-1:] in ([], ["status"])

    await asyncio.to_thread(sync_side)
    await _until(lambda: stand.open == 0)


@pytest.mark.parametrize("stand", [ticking], indirect=True)
async def test_tasks_share_one_telemetry_stream(stand: Stand) -> None:
    """Each message to one task, over one connection (two tasks once opened two, one of them
    beyond aclose's reach, then failed in websockets' ConcurrencyError)."""
    async with AsyncClient(stand.url, timeout=5.0) as c:
        tm = c.telemetry()

        async def some() -> list[str]:
            return [(await tm.__anext__())["type"] for _ in range(5)]

        got = await asyncio.gather(some(), some(), some())
        assert sorted(t for g in got for t in g) == ["hello", *["status"] * 14]
        assert stand.total == 1
        await tm.aclose()
    await _until(lambda: stand.open == 0)


async def _until(ok: Callable[[], bool]) -> None:
    async with asyncio.timeout(10):
        while not ok():
            await asyncio.sleep(0.01)


def test_an_api_error_pickles_and_copies_whole() -> None:
    """An error raised in a worker process reaches its parent (it is pickled)."""
    e = NotFound(404, "no run 7", ["run_id: 7"], "GET", "http://h/api/runs/7")
    for back in (pickle.loads(pickle.dumps(e)), copy.copy(e)):
        assert type(back) is NotFound and str(back) == str(e)
        got = (back.status, back.error, back.details, back.url)
        assert got == (404, "no run 7", ["run_id: 7"], e.url)


def test_the_exceptions_a_script_catches_are_exported() -> None:
    assert {"Unreachable", "ApiError", "InvalidRequest", "TelemetryMessage"} <= set(
        client_module.__all__
    )
    assert all(hasattr(client_module, name) for name in client_module.__all__)


def _undocumented(obj: object) -> bool:
    return not (getattr(obj, "__doc__", None) or "").strip()  # its own, not inherited


def test_every_public_method_and_function_of_the_client_says_what_it_does() -> None:
    """A lab script's author reads ``help(Client.stop_run)``: each public function, and each
    public method of each public class (:class:`Client`, :class:`AsyncClient`, the telemetry
    streams, …), has a docstring."""
    missing = []
    for name in client_module.__all__:
        obj = getattr(client_module, name)
        if inspect.isfunction(obj) and _undocumented(obj):
            missing.append(name)
        if not inspect.isclass(obj) or obj.__module__ != client_module.__name__:
            continue
        for attr, value in vars(obj).items():
            if attr.startswith("_"):
                continue
            if isinstance(value, (staticmethod, classmethod)):
                value = value.__func__
            if (inspect.isfunction(value) or isinstance(value, property)) and _undocumented(value):
                missing.append(f"{name}.{attr}")
    assert not missing, f"no docstring: {', '.join(missing)}"
    # the classes a script uses are among those checked
    checked = {"Client", "AsyncClient", "Telemetry", "AsyncTelemetry"}
    assert checked <= set(client_module.__all__)


def test_the_telemetry_url_keeps_the_scheme_whatever_its_case() -> None:
    assert client_module._ws_url("HTTP://h:1", 1, True, None).startswith("ws://h:1/ws/")
    assert client_module._ws_url("Https://h", 1, True, None).startswith("wss://h/ws/")


def test_a_telemetry_option_of_0_reaches_the_service() -> None:
    """max_queue=0 was dropped from the URL (the service's default used without a word)."""
    url = client_module._ws_url("http://h:1", 1, True, 0)
    assert url.endswith("&max_queue=0")  # the service's 422 for it: tests/service/test_client.py


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("http://127.0.0.1:8000/", "http://127.0.0.1:8000"),
        ("127.0.0.1:8000", "http://127.0.0.1:8000"),
        ("localhost:8000", "http://localhost:8000"),
        (" HTTPS://lab.example/hand/ ", "https://lab.example/hand"),
        ("[::1]:8000", "http://[::1]:8000"),
    ],
)
def test_a_url_without_its_scheme_is_http(given: str, expected: str) -> None:
    """``Client("localhost:8000")`` used to be Unreachable ("unsupported protocol
    'localhost://'"), as if no service ran there."""
    with Client(given) as c:
        assert c.url == expected
    assert client_module.service_url(given) == expected  # AsyncClient's too


@pytest.mark.parametrize("bad", ["ftp://127.0.0.1/", "http://127.0.0.1:99999", "http://", ":80"])
def test_a_url_that_cannot_be_a_service_is_refused_at_once(bad: str) -> None:
    with pytest.raises(ValueError, match=re.escape(repr(bad))):
        Client(bad)


@pytest.fixture
def mute_port() -> Iterator[int]:
    """A port that takes connections and never answers (a hung service)."""
    with socket.create_server(("127.0.0.1", 0)) as server:
        yield server.getsockname()[1]


def _limits(e: BaseException) -> dict[str, float]:
    """The timeouts the request that failed was sent with."""
    cause = e.__cause__
    assert isinstance(cause, httpx.TimeoutException), repr(cause)
    return cast(dict[str, float], cause.request.extensions["timeout"])


@pytest.fixture
def estop_limit(monkeypatch: pytest.MonkeyPatch) -> float:
    """The e-stop's own limit, shortened for the tests (waited for against a mute port)."""
    assert client_module._ESTOP.timeout == client_module.ESTOP_TIMEOUT_S  # the call uses it
    monkeypatch.setattr(client_module, "_ESTOP", replace(client_module._ESTOP, timeout=0.3))
    return 0.3


def test_an_estop_a_hung_service_does_not_answer_fails_within_its_own_limit(
    mute_port: int, estop_limit: float
) -> None:
    """A 30 s client learnt that its e-stop went unanswered after 30 s; the e-stop has its own
    limit (the other calls keep the client's), also in a client without a timeout."""
    with Client(f"127.0.0.1:{mute_port}", timeout=30.0) as c:
        with pytest.raises(Unreachable, match=r"POST .*/api/estop") as raised:
            c.estop()
        assert _limits(raised.value)["read"] == estop_limit
    with Client(f"127.0.0.1:{mute_port}", timeout=0.2) as c:  # a shorter client's own
        with pytest.raises(Unreachable) as raised:
            c.estop()
        assert _limits(raised.value)["read"] == 0.2
        with pytest.raises(Unreachable) as raised:
            c.status()
        assert _limits(raised.value)["read"] == 0.2
    with Client(f"127.0.0.1:{mute_port}", timeout=None) as c:  # type: ignore[arg-type]
        with pytest.raises(Unreachable) as raised:
            c.estop()
        assert _limits(raised.value)["read"] == estop_limit


async def test_the_async_estop_has_its_own_limit_too(mute_port: int, estop_limit: float) -> None:
    async with AsyncClient(f"127.0.0.1:{mute_port}", timeout=30.0) as c:
        with pytest.raises(Unreachable) as raised:
            await c.estop()
        assert _limits(raised.value)["read"] == estop_limit


async def _cut_mid_export(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    """An export's answer that promises 100 000 bytes and is cut after 1000 (the service
    killed, the network gone)."""
    await reader.readuntil(b"\r\n\r\n")
    writer.write(b"HTTP/1.1 200 OK\r\nContent-Type: application/octet-stream\r\n"
                 b"Content-Length: 100000\r\n\r\n" + b"\x89MCAP0\r\n" + b"x" * 992)  # fmt: skip
    await writer.drain()
    writer.transport.abort()


async def test_an_export_cut_off_leaves_an_earlier_file_as_it_was_and_no_partial_one(
    tmp_path: Path,
) -> None:
    """A connection lost mid-export left a truncated file no reader opens, in place of a good
    export there before (the CLI's exports had the same; found by a CLI audit)."""
    server = await asyncio.start_server(_cut_mid_export, "127.0.0.1", 0)
    url = f"http://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    target = tmp_path / "run.mcap"
    target.write_bytes(b"the earlier export")
    try:
        async with AsyncClient(url) as c:
            with pytest.raises(Unreachable):
                await c.export(7, target)

        def blocking() -> None:
            with Client(url) as sync, pytest.raises(Unreachable):
                sync.export(7, target)

        await asyncio.to_thread(blocking)
    finally:
        server.close()
        await server.wait_closed()
    assert target.read_bytes() == b"the earlier export"
    assert [p.name for p in tmp_path.iterdir()] == ["run.mcap"]


def status_server(answer: dict[str, Any]) -> Iterator[int]:
    """An HTTP server on loopback that answers every GET (a proxied one too) with ``answer``."""
    import http.server
    import threading

    class Status(http.server.BaseHTTPRequestHandler):
        def do_GET(self) -> None:
            body = json.dumps(answer).encode()
            self.send_response(200)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(body)))
            self.end_headers()
            self.wfile.write(body)

        def log_message(self, *args: object) -> None:
            pass

    server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Status)
    threading.Thread(target=server.serve_forever, daemon=True).start()
    try:
        yield server.server_address[1]
    finally:
        server.shutdown()
        server.server_close()


@pytest.fixture
def lab_proxy(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """A lab PC's proxy settings, naming a proxy that answers every request it is given for
    itself (as a proxy answers for another host): {"via": "proxy"}."""
    for port in status_server({"via": "proxy"}):
        for name in ("http_proxy", "HTTP_PROXY", "all_proxy", "ALL_PROXY"):
            monkeypatch.setenv(name, f"http://127.0.0.1:{port}")
        for name in ("no_proxy", "NO_PROXY"):
            monkeypatch.delenv(name, raising=False)
        yield


@pytest.fixture
def status_port() -> Iterator[int]:
    yield from status_server({"state": "idle"})


@pytest.mark.parametrize("host", ["127.0.0.1", "localhost"])
async def test_a_service_on_this_machine_is_asked_directly_whatever_http_proxy_says(
    lab_proxy: None, status_port: int, host: str
) -> None:
    """httpx (and websockets) send even a loopback request through the proxy the environment
    names; a lab PC's or a container's proxy answers for another host or not at all."""
    url = f"http://{host}:{status_port}"

    def status() -> Any:
        with Client(url, timeout=5.0) as c:
            return c.status()

    assert await asyncio.to_thread(status) == {"state": "idle"}
    async with AsyncClient(url, timeout=5.0) as c:
        assert await c.status() == {"state": "idle"}


@pytest.mark.parametrize("stand", [restarting], indirect=True)
async def test_the_telemetry_of_a_service_on_this_machine_bypasses_the_proxy_too(
    lab_proxy: None, stand: Stand
) -> None:
    async with AsyncClient(stand.url, timeout=5.0) as c:
        assert await _drain(c.telemetry()) == ["hello"]
    assert await asyncio.to_thread(_sync_drain, stand.url) == ["hello"]


def test_a_service_elsewhere_still_goes_through_the_proxy(lab_proxy: None) -> None:
    """Only this machine's services are asked directly: a remote one keeps the lab's proxy
    (192.0.2.1 is an address for documentation: only the proxy answers for it)."""
    with Client("http://192.0.2.1:8000", timeout=5.0) as c:
        assert c.status() == {"via": "proxy"}
