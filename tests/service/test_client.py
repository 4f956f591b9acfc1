"""One real ``sdh2svc serve --sim`` with a token and the live Foxglove view: sdh2svc.client's
every call once and its refusals; one one-cycle run watched by the client's telemetry and by a
client of the Foxglove WebSocket protocol (over ``websockets``) subscribed to every channel, then
read back."""

from __future__ import annotations

import asyncio
import csv
import functools
import io
import json
import re
import socket
import struct
from collections.abc import AsyncIterator, Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
from foxglove_ws import FETCH_ASSET_RESPONSE, MESSAGE_DATA, SUBPROTOCOLS, Decoder, recv_json
from websockets.asyncio.client import ClientConnection, connect

from sdh2svc.client import (
    ApiError,
    AsyncClient,
    AsyncTelemetry,
    Client,
    Conflict,
    InvalidRequest,
    NotFound,
    SamplePage,
    Unauthorized,
    Unreachable,
    _raise_for,
)
from sdh2svc.service.foxglove_live import URDF_URI
from sdh2svc.service.foxglove_mcap import PAD_NAMES, pad_topic
from tests.live_service import LiveService, start_run, start_service
from tests.service.conftest import LONG_RUNS, PATIENT

TOKEN = "s3cret"
RUN_TIMEOUT_S = 120.0
TOPICS = {"/samples", "/tf", "/scene", "/events", *(pad_topic(p) for p in PAD_NAMES)}


@dataclass
class Cycle:
    """A run on the egg (one cycle asked, stopped once it rolls), watched by the client's
    telemetry and in Foxglove."""

    run_id: int
    hello: dict[str, Any]
    first_sample: dict[str, Any]  # of the run, from the client's telemetry
    end: dict[str, Any]  # wait_run's answer
    foxglove: dict[str, list[Any]]  # topic → the messages received, decoded
    urdf: bytes  # the URDF asset, fetched from the Foxglove server


@pytest.fixture(scope="module")
def cycle(lab: tuple[LiveService, int]) -> Cycle:
    """One run for the two watchers, stopped once they have seen it roll."""
    return asyncio.run(_watch_a_cycle(*lab))


async def _watch_a_cycle(svc: LiveService, port: int) -> Cycle:
    async with AsyncClient(svc.url, token=TOKEN) as c:
        # the watchers close once they have seen enough: an unread socket takes seconds to
        # close behind what the service queued for it
        async with (
            connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws,  # type: ignore[arg-type]
            c.telemetry(tactile=False) as tm,
        ):
            assert ws.subprotocol in SUBPROTOCOLS
            info = await asyncio.wait_for(recv_json(ws, "serverInfo"), 10.0)
            assert info["name"] == "sdh2svc"
            channels = (await asyncio.wait_for(recv_json(ws, "advertise"), 10.0))["channels"]
            assert {c["topic"] for c in channels} == TOPICS
            subs = {i: c["id"] for i, c in enumerate(channels)}  # subscription id → channel id
            await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
                {"id": i, "channelId": ch} for i, ch in subs.items()]}))  # fmt: skip
            await ws.send(json.dumps({"op": "fetchAsset", "uri": URDF_URI, "requestId": 7}))

            hello = await anext(tm)
            run_id = (await start_run(c, {"cycles": 1}, "egg"))["run_id"]
            async with asyncio.timeout(RUN_TIMEOUT_S):
                first, (got, urdf) = await asyncio.gather(
                    _first_sample(tm, run_id), _every_channel(ws, Decoder(channels), subs)
                )
        with pytest.raises(Conflict):  # one run at a time
            await c.start_run()
        # the watchers have what they need: once it has a few samples to page through, the run
        # stops (and releases) rather than roll its stroke; a run's completion is the fast-mode
        # tests' and the stalled-client test's
        await c.wait_status(_rolled(ITERATIONS), timeout=RUN_TIMEOUT_S)
        await c.stop_run()
        end = await c.wait_run(run_id, timeout=RUN_TIMEOUT_S)
    return Cycle(run_id, hello, first, end, got, urdf)


ITERATIONS = 10  # the watched run's before it stops: test_run_observed_and_read_back pages them


def _rolled(n: int) -> Callable[[dict[str, Any]], bool]:
    """The run has rolled ``n`` iterations; an AssertionError naming how it ended if it ended
    first (not a wait for what will never come)."""

    def ok(st: dict[str, Any]) -> bool:
        run = st.get("run") or {}
        assert run.get("status") in (None, "running"), f"the run ended first: {run}"
        return bool(run.get("iteration", 0) >= n)

    return ok


async def _first_sample(tm: AsyncTelemetry, run_id: int) -> dict[str, Any]:
    async for msg in tm:
        if msg["type"] == "sample" and msg["run_id"] == run_id:
            return msg["sample"]  # type: ignore[no-any-return]
    raise AssertionError("the telemetry ended before the run's first sample")


async def _every_channel(
    ws: ClientConnection, decode: Decoder, subs: dict[int, int]
) -> tuple[dict[str, list[Any]], bytes]:
    """Every channel's messages, until each has brought one (the scene its contacts and the
    object), and the URDF asset."""
    got: dict[str, list[Any]] = {}
    urdf = b""
    scene_ids: set[str] = set()
    while set(got) != TOPICS or not urdf or not {"contacts", "object"} <= scene_ids:
        m = await ws.recv()
        if isinstance(m, str):
            continue
        if m[0] == FETCH_ASSET_RESPONSE:
            request_id, status, n = struct.unpack_from("<IBI", m, 1)
            assert (request_id, status) == (7, 0), m[10 : 10 + n]
            urdf = bytes(m[10 + n :])
            continue
        assert m[0] == MESSAGE_DATA
        sub, _log_time = struct.unpack_from("<IQ", m, 1)
        topic, msg = decode(subs[sub], m[13:])
        got.setdefault(topic, []).append(msg)
        if topic == "/scene":
            scene_ids.update(e.id for e in msg.entities)
    return got, urdf


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[LiveService, int]]:
    """The service and its live Foxglove view's port (the tests leave it idle)."""
    port = _free_port()
    extra = (*LONG_RUNS, *PATIENT, "--set", f"service.foxglove_port={port}")
    s = start_service(tmp_path_factory.mktemp("lab"), viewer=False, extra=extra, token=TOKEN)
    try:
        assert s.announced["foxglove_url"] == f"ws://127.0.0.1:{port}", s.announced
        yield s, port
    finally:
        assert s.stop() == 0, "".join(s.log)


@pytest.fixture
def svc(lab: tuple[LiveService, int]) -> LiveService:
    return lab[0]


def test_an_error_without_the_service_body() -> None:
    """A proxy's or a crashed worker's answer still raises, with what it said."""
    request = httpx.Request("GET", "http://127.0.0.1:1/api/status")
    with pytest.raises(ApiError) as raised:
        _raise_for(httpx.Response(502, text="Bad Gateway", request=request))
    assert type(raised.value) is ApiError and raised.value.status == 502
    assert raised.value.details == ["Bad Gateway"] and "502" in str(raised.value)
    body = {"error": "no run 7 (GET /api/runs lists them)", "details": []}
    with pytest.raises(NotFound, match="no run 7"):
        _raise_for(httpx.Response(404, json=body, request=request))


def test_a_service_that_does_not_answer_is_unreachable() -> None:
    url = f"http://127.0.0.1:{_free_port()}"  # nothing listens there
    with Client(url) as c, pytest.raises(Unreachable, match=re.escape(f"GET {url}/api/status")):
        c.status()
    with pytest.raises(Unreachable, match=re.escape(f"ws://127.0.0.1:{url.rsplit(':', 1)[1]}")):
        next(Client(url).telemetry())


async def test_a_bad_telemetry_query_is_an_invalid_request(svc: LiveService) -> None:
    async with AsyncClient(svc.url, token=TOKEN) as c:
        with pytest.raises(InvalidRequest) as bad:
            async with c.telemetry(decimate=0):
                pass
    assert bad.value.status == 422 and bad.value.details == [
        "query.decimate = '0': Input should be greater than or equal to 1"
    ]


async def test_closing_the_client_disconnects_telemetry_the_program_dropped(
    svc: LiveService,
) -> None:
    """A stream read once and dropped (``async for … break``, then forgotten) still has its
    connection: closing its client closes it. A stream that ended is forgotten by its client."""
    import gc

    c = AsyncClient(svc.url, token=TOKEN)
    connections = []
    for _ in range(3):
        tm = c.telemetry(tactile=False)
        async for _msg in tm:
            break
        connections.append(tm._ws)  # (the connection only: the stream itself is dropped)
        del tm
    gc.collect()
    assert all(ws is not None and ws.state.name == "OPEN" for ws in connections)
    await c.aclose()
    assert all(ws is not None and ws.state.name == "CLOSED" for ws in connections)
    async with AsyncClient(svc.url, token=TOKEN) as c2:
        async with c2.telemetry(tactile=False) as tm2:
            async for _msg in tm2:
                break
        assert not c2._telemetry  # closed: no longer held


def test_calls_and_refusals(svc: LiveService) -> None:
    with Client(svc.url, token=TOKEN) as c:
        assert c.viewer() == {"url": None}
        st = c.status()
        assert st["sim"] is True and st["auth_required"] is True
        assert c.params()["k"] == 2.0
        assert "k" in c.params_schema()["properties"]
        assert c.config()["service"]["token"] == "***"
        assert c.sim_object()["presets"]
        assert c.set_sim_object(name="egg")["object"]["name"] == "egg"

        assert c.patch_params({"k": 3.0})["k"] == 3.0
        with pytest.raises(InvalidRequest) as bad:
            c.patch_params({"k": 0.5})
        assert bad.value.status == 422 and bad.value.error == "invalid rolling parameters"
        assert any(d.startswith("k = 0.5") for d in bad.value.details)
        assert c.patch_params({"k": 2.0})["k"] == 2.0

        with pytest.raises(Conflict) as none:
            c.stop_run()
        assert none.value.status == 409 and none.value.error == "no run is running"
        with pytest.raises(NotFound) as missing:
            c.run(9999)
        assert missing.value.status == 404 and "no run 9999" in str(missing.value)

        assert c.estop()["estopped"] is True
        with pytest.raises(Conflict):
            c.start_run()
        assert c.release_estop() == {"estopped": False}

        # every route of docs/api.md has its call
        press = c.press(3, 10.0, 12.0, 2.0, duration_s=0.5)
        assert (press["pad"], press["radius_mm"], press["duration_s"]) == (3, 3.0, 0.5)
        assert c.release_press()["released"] >= 0
        with pytest.raises(InvalidRequest):
            c.press(3, 10.0, 12.0, 60.0)  # above 50 N
        for call in (lambda: c.truth(9999), lambda: c.frames(9999, to=5),
                     lambda: c.samples(9999, limit=100, outline=True)):  # fmt: skip
            with pytest.raises(NotFound):
                call()
        for replay in (lambda: c.show_replay(1, 0), c.end_replay):
            with pytest.raises(Conflict, match="3-D view is off"):  # none in this service
                replay()
        with pytest.raises(InvalidRequest):  # max_queue=0 reaches the service: its 422
            next(c.telemetry(max_queue=0))

    with Client(svc.url) as anonymous:  # reading needs no token; commanding does
        assert anonymous.status()["estopped"] is False
        patch = functools.partial(anonymous.patch_params, {"k": 3.0})
        for command in (patch, anonymous.start_run, anonymous.release_estop, anonymous.open_hand):
            with pytest.raises(Unauthorized) as refused:
                command()
            assert refused.value.status == 401 and "bearer token" in refused.value.error
        assert anonymous.estop()["estopped"] is True  # stopping always works
    with Client(svc.url, token=TOKEN) as c:
        c.release_estop()


async def test_run_observed_and_read_back(svc: LiveService, cycle: Cycle, tmp_path: Path) -> None:
    assert cycle.hello["status"]["sim"] is True
    assert cycle.first_sample["iteration"] >= 0
    # why it stopped, as its record keeps it (the message was empty)
    assert cycle.end["message"] == "through the API (POST /api/runs/stop)", cycle.end
    assert cycle.end["status"] == "stopped", cycle.end
    run_id = cycle.run_id
    async with AsyncClient(svc.url, token=TOKEN) as c:
        assert (await c.runs())[0]["id"] == run_id
        run = await c.run(run_id)
        assert run["status"] == "stopped" and run["iterations"] > 0
        assert run["summary"]["message"] == cycle.end["message"]
        # a run that has already ended: its end at once (not a wait for the next one's)
        assert (await c.wait_run(run_id, timeout=0.0)) == cycle.end
        with pytest.raises(NotFound, match="no run 999999"):
            await c.wait_run(999999, timeout=0.0)
        kinds = [e["kind"] for e in await c.events(run_id)]
        assert {"start", "grasped", "end"} <= set(kinds), kinds

        page = await c.samples(run_id, offset=1, limit=2)
        assert page["total"] == run["iterations"] and len(page["samples"]) == 2
        assert set(page) == set(SamplePage.__annotations__)  # the type says what comes
        every = [s async for s in c.iter_samples(run_id, page=100)]
        assert len(every) == page["total"] and every[1:3] == page["samples"]

        text = (await c.export_bytes(run_id, "csv")).decode()
        assert len(list(csv.DictReader(io.StringIO(text)))) == page["total"]
        path = await c.export(run_id, tmp_path / "run.mcap")
        assert path.read_bytes()[:5] == b"\x89MCAP"
        with pytest.raises(NotFound):
            await c.export_bytes(9999, "mcap")

        async with c.telemetry(tactile=False) as tm:  # Open hand: its events, then idle
            assert (await c.open_hand()) == {"state": "opening"}
            kinds = [m["kind"] async for m in _until_event(tm, "opened")]
            assert kinds[-2:] == ["open", "opened"]
        assert (await c.status())["hand"]["opening"] is False

    with Client(svc.url, token=TOKEN) as sync:  # the same from the blocking client
        csv_path = sync.export(run_id, tmp_path / "run.csv")
        assert csv_path.read_bytes().decode() == text
        assert list(sync.iter_samples(run_id, page=50)) == every
        messages = sync.telemetry(tactile=False)  # a plain iterator, closed by hand
        hello = next(messages)
        messages.close()
        assert hello["type"] == "hello" and "links" in hello["status"]
        assert list(messages) == []  # closed: the iteration is over
        # as AsyncClient's: a `with` block, which disconnects as it is left
        with sync.telemetry(tactile=False) as live:
            ws = live._ws
            assert ws is not None and ws.state.name == "OPEN"  # connected on entering
            for msg in live:
                assert msg["type"] == "hello"
                break
        assert ws.state.name == "CLOSED" and not sync._sockets


async def _until_event(tm: AsyncTelemetry, kind: str) -> AsyncIterator[dict[str, Any]]:
    """The events telemetry brings, up to the first of ``kind``."""
    async for msg in tm:
        if msg["type"] == "event":
            yield msg
            if msg["kind"] == kind:
                return


def test_every_foxglove_channel_live_during_a_run(cycle: Cycle) -> None:
    got = cycle.foxglove
    assert cycle.urdf.startswith(b"<?xml") and b"<robot" in cycle.urdf
    sample = got["/samples"][0]
    assert sample["iteration"] >= 1 and "phi2" in sample
    assert any(t.child_frame_id for t in got["/tf"][0].transforms)
    entities = {e.id: e for m in got["/scene"] for e in m.entities}
    assert entities["contacts"].frame_id == "frame0"
    assert {f"pads/{p}" for p in PAD_NAMES} <= set(entities)
    assert entities["object"].frame_id == "frame0" and len(entities["object"].lines[0].points) > 20
    assert any(log.name for log in got["/events"])
    for pad in PAD_NAMES:
        grid = got[pad_topic(pad)][0]
        assert grid.frame_id == f"{pad}_pad" and grid.column_count > 0
        assert len(grid.data) == grid.row_stride * (len(grid.data) // grid.row_stride) > 0
