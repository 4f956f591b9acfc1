"""The live Foxglove view of ``sdh2svc serve --sim``: a client speaking the Foxglove WebSocket
protocol (foxglove.websocket.v1, now named foxglove.sdk.v1) over ``websockets`` subscribes to
every channel during a one-stroke run and decodes what each one receives against the schema it
was advertised with."""

from __future__ import annotations

import asyncio
import base64
import json
import math
import socket
import struct
import time
from collections.abc import Iterator
from typing import Any

import httpx
import jsonschema
import numpy as np
import pytest
from foxglove import messages as fm
from mcap_check import _no_unknown_fields, _proto_class
from websockets.asyncio.client import ClientConnection, connect

from sdh2svc.config import load_config
from sdh2svc.control.observer import EventKind
from sdh2svc.service import foxglove_live
from sdh2svc.service.foxglove_live import URDF_URI, FoxgloveLive, FoxgloveStartError
from sdh2svc.service.foxglove_mcap import PAD_NAMES, pad_topic
from sdh2svc.service.telemetry import Event, Pose, SampleMsg, Sim, Tactile
from tests.live_service import LiveService, start_service
from tests.service.test_telemetry import a_sample

TIMEOUT_S = 120.0
# The protocol's names: foxglove-sdk ≥ 0.30 answers to the newer one only; a client offers both.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA, FETCH_ASSET_RESPONSE = 0x01, 0x04  # binary opcodes (server → client)
TOPICS = {"/samples", "/tf", "/scene", "/events", *(pad_topic(p) for p in PAD_NAMES)}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port: int = s.getsockname()[1]
        return port


@pytest.fixture(scope="module")
def fox(
    tmp_path_factory: pytest.TempPathFactory, long_runs: tuple[str, ...]
) -> Iterator[tuple[LiveService, int]]:
    port = _free_port()
    extra = (*long_runs, "--set", f"service.foxglove_port={port}")
    s = start_service(tmp_path_factory.mktemp("fox"), viewer=False, extra=extra)
    try:
        yield s, port
    finally:
        assert s.stop() == 0, "".join(s.log)


class Decoder:
    """Each advertised channel's decoder: JSON checked against its JSON schema, protobuf parsed
    with the FileDescriptorSet it was advertised with (no unknown fields)."""

    def __init__(self, channels: list[dict[str, Any]]) -> None:
        self.topics = {c["id"]: c["topic"] for c in channels}
        self._decode = {c["id"]: self._decoder(c) for c in channels}

    @staticmethod
    def _decoder(c: dict[str, Any]) -> Any:
        if c["encoding"] == "json":
            assert c["schemaEncoding"] == "jsonschema"
            doc = json.loads(c["schema"])
            jsonschema.Draft202012Validator.check_schema(doc)
            validator = jsonschema.Draft202012Validator(doc)

            def json_message(data: bytes) -> Any:
                obj = json.loads(data)
                validator.validate(obj)
                return obj

            return json_message
        assert c["encoding"] == "protobuf" and c["schemaEncoding"] == "protobuf"
        cls = _proto_class(c["schemaName"], base64.b64decode(c["schema"]))

        def proto_message(data: bytes) -> Any:
            msg = cls.FromString(data)
            _no_unknown_fields(msg)
            return msg

        return proto_message

    def __call__(self, channel_id: int, data: bytes) -> tuple[str, Any]:
        return self.topics[channel_id], self._decode[channel_id](data)


async def _recv_json(ws: ClientConnection, op: str) -> dict[str, Any]:
    while True:
        m = await ws.recv()
        if isinstance(m, str) and (obj := json.loads(m))["op"] == op:
            return obj  # type: ignore[no-any-return]


async def test_every_channel_live_during_a_run(fox: tuple[LiveService, int]) -> None:
    svc, port = fox
    async with connect(f"ws://127.0.0.1:{port}", subprotocols=SUBPROTOCOLS) as ws:  # type: ignore[arg-type]
        assert ws.subprotocol in SUBPROTOCOLS
        info = await asyncio.wait_for(_recv_json(ws, "serverInfo"), 10.0)
        assert info["name"] == "sdh2svc"
        channels = (await asyncio.wait_for(_recv_json(ws, "advertise"), 10.0))["channels"]
        assert {c["topic"] for c in channels} == TOPICS
        decode = Decoder(channels)
        subs = {i: c["id"] for i, c in enumerate(channels)}  # subscription id → channel id
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [
            {"id": i, "channelId": ch} for i, ch in subs.items()]}))  # fmt: skip
        await ws.send(json.dumps({"op": "fetchAsset", "uri": URDF_URI, "requestId": 7}))

        got: dict[str, list[Any]] = {}
        urdf = b""
        scene_ids: set[str] = set()
        async with httpx.AsyncClient(base_url=svc.url, headers=svc.headers()) as c:
            r = await c.post("/api/runs", json={"object": "egg", "params": {"cycles": 1}})
            assert r.status_code == 201, r.text
            deadline = time.monotonic() + TIMEOUT_S
            while set(got) != TOPICS or not urdf or not {"contacts", "object"} <= scene_ids:
                m = await asyncio.wait_for(ws.recv(), deadline - time.monotonic())
                if isinstance(m, str):
                    continue
                if m[0] == FETCH_ASSET_RESPONSE:
                    request_id, status, n = struct.unpack_from("<IBI", m, 1)
                    assert (request_id, status) == (7, 0), m[10 : 10 + n]
                    urdf = m[10 + n :]
                    continue
                assert m[0] == MESSAGE_DATA
                sub, _log_time = struct.unpack_from("<IQ", m, 1)
                topic, msg = decode(subs[sub], m[13:])
                got.setdefault(topic, []).append(msg)
                if topic == "/scene":
                    scene_ids.update(e.id for e in msg.entities)
            await c.post("/api/runs/stop")  # the module's service idle for the next test

    assert urdf.startswith(b"<?xml") and b"<robot" in urdf
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


def test_off_by_default() -> None:
    assert load_config(use_env=False).service.foxglove_port == 0


# --- the listener's policy, in process (no client: the channels and the builders are fakes) ---


class FakeChannel:
    def __init__(self, subscribed: bool = True) -> None:
        self.subscribed = subscribed
        self.logged: list[tuple[Any, int | None]] = []

    def has_sinks(self) -> bool:
        return self.subscribed

    def log(self, msg: Any, *, log_time: int | None = None) -> None:
        self.logged.append((msg, log_time))


class FakeHand:
    """Counts what is built (the builders themselves: test_foxglove_mcap.py)."""

    def __init__(self) -> None:
        self.built: list[str] = []

    def transforms(self, s: Any, ns: int) -> str:
        self.built.append("tf")
        return "tf"

    def pose_transforms(self, angles: Any, ns: int) -> str:
        self.built.append("pose")
        return "pose"

    def scene(self, s: Any, ns: int, alpha: float, truth: Any = None) -> tuple[str, float]:
        self.built.append("scene" if truth is None else "object")
        return ("scene", alpha)

    def pad_grids(self, mats: Any, ns: int) -> dict[str, str]:
        self.built.append("grids")
        return {p: p for p in PAD_NAMES}


class Clock:
    now = 100.0

    def monotonic(self) -> float:
        return self.now

    def time_ns(self) -> int:
        return round(self.now * 1e9)


@pytest.fixture
def live(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[FoxgloveLive, FakeHand, Clock]]:
    clock = Clock()
    monkeypatch.setattr(foxglove_live, "time", clock)
    fox = FoxgloveLive(load_config(use_env=False), host="127.0.0.1", port=0, max_hz=10.0)
    fox.start()
    assert fox.port > 0 and fox.url == f"ws://127.0.0.1:{fox.port}"
    hand = FakeHand()
    fox._hand = hand  # type: ignore[assignment]
    try:
        yield fox, hand, clock
    finally:
        fox.stop()


def _chans(fox: FoxgloveLive, subscribed: bool) -> dict[str, FakeChannel]:
    ch = {n: FakeChannel(subscribed) for n in ("_samples", "_tf", "_scene", "_events")}
    for name, c in ch.items():
        setattr(fox, name, c)
    fox._pads = {p: FakeChannel(subscribed) for p in PAD_NAMES}  # type: ignore[misc]
    return ch


def _tactile(seq: int) -> Tactile:
    return Tactile(seq, 0.0, tuple(np.zeros((2, 3), np.uint16) for _ in PAD_NAMES))


def test_nothing_is_built_for_a_channel_nobody_reads(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    fox, hand, _ = live
    ch = _chans(fox, subscribed=False)
    fox.handle(SampleMsg(1, a_sample()))
    fox.handle(_tactile(1))
    fox.handle(Pose((0.0,) * 7))
    fox.handle(Event(1, 0.0, 0, EventKind.PHASE, {"phase": "grasping"}))
    assert hand.built == [] and not any(c.logged for c in ch.values())


def test_3d_channels_at_most_max_hz_samples_and_events_all(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    fox, hand, clock = live
    ch = _chans(fox, subscribed=True)
    for i in range(5):  # 5 samples and frames within 0.1 s (max_hz = 10): the 3-D ones once
        clock.now += 0.02
        fox.handle(SampleMsg(1, a_sample(iteration=i + 1)))
        fox.handle(_tactile(i))
    assert [json.loads(m)["iteration"] for m, _ in ch["_samples"].logged] == [1, 2, 3, 4, 5]
    assert hand.built == ["tf", "scene", "grids"]
    assert all(len(c.logged) == 1 for c in fox._pads.values())  # type: ignore[attr-defined]
    clock.now += 0.1  # a period later: the next sample and frame are drawn
    fox.handle(SampleMsg(1, a_sample(iteration=6)))
    fox.handle(_tactile(6))
    assert hand.built == ["tf", "scene", "grids", "tf", "scene", "grids"]
    # log times: the clock at delivery
    assert ch["_samples"].logged[-1][1] == clock.time_ns()


def test_the_cones_take_the_runs_alpha(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    fox, _, _ = live
    ch = _chans(fox, subscribed=True)
    fox.handle(Event(1, 0.0, 0, EventKind.START, {"params": {"alpha_deg": 30.0}}))
    fox.handle(SampleMsg(1, a_sample()))
    assert ch["_scene"].logged[-1][0] == ("scene", pytest.approx(math.radians(30.0)))
    assert [type(m) for m, _ in ch["_events"].logged] == [fm.Log]


def test_the_object_and_the_contacts_end(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    """The truth's object at each ``sim`` message; a run's end deletes its contacts."""
    fox, hand, _ = live
    ch = _chans(fox, subscribed=True)
    fox.handle(Sim({"outline": [[0.0, 100.0], [10.0, 110.0]]}))
    fox.handle(Sim({"outline": [[0.0, 100.0], [10.0, 110.0]]}))
    assert hand.built == ["object", "object"]
    fox.handle(Event(1, 9.0, 300, EventKind.END, {"status": "completed", "message": ""}))
    update = _proto_class("foxglove.SceneUpdate", fm.SceneUpdate.get_schema().data)
    (deletion,) = update.FromString(ch["_scene"].logged[-1][0].encode()).deletions
    assert deletion.id == "contacts" and deletion.type == 0  # MATCHING_ID, not ALL


def test_stopped_it_ignores_messages(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    fox, hand, _ = live
    _chans(fox, subscribed=True)
    fox.stop()
    fox.handle(SampleMsg(1, a_sample()))
    assert hand.built == []


def test_a_taken_port_is_a_start_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        fox = FoxgloveLive(load_config(use_env=False), host="127.0.0.1",
                           port=s.getsockname()[1], max_hz=10.0)  # fmt: skip
        with pytest.raises(FoxgloveStartError, match=r"in use.*service\.foxglove_port"):
            fox.start()
