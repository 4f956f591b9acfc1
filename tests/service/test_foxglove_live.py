"""The live Foxglove view of ``sdh2svc serve --sim``: a client speaking the Foxglove WebSocket
protocol (foxglove.websocket.v1, now named foxglove.sdk.v1) over ``websockets`` subscribes to
every channel during a one-stroke run and decodes what each one receives against the schema it
was advertised with."""

from __future__ import annotations

import asyncio
import base64
import json
import socket
import struct
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import jsonschema
import pytest
from mcap_check import _no_unknown_fields, _proto_class
from websockets.asyncio.client import ClientConnection, connect

from sdh2svc.service.foxglove_live import URDF_URI
from sdh2svc.service.foxglove_mcap import PAD_NAMES, pad_topic
from tests.live_service import LiveService, start_service

TIMEOUT_S = 120.0
# The protocol's names: foxglove-sdk ≥ 0.30 answers to the newer one only; a client offers both.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA, FETCH_ASSET_RESPONSE = 0x01, 0x04  # binary opcodes (server → client)
TOPICS = {"/samples", "/tf", "/contacts", "/events", *(pad_topic(p) for p in PAD_NAMES)}


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
        async with httpx.AsyncClient(base_url=svc.url, headers=svc.headers()) as c:
            r = await c.post("/api/runs", json={"object": "egg", "params": {"cycles": 1}})
            assert r.status_code == 201, r.text
            deadline = time.monotonic() + TIMEOUT_S
            while set(got) != TOPICS or not urdf:
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
            await c.post("/api/runs/stop")  # the module's service idle for the next test

    assert urdf.startswith(b"<?xml") and b"<robot" in urdf
    sample = got["/samples"][0]
    assert sample["iteration"] >= 1 and "phi2" in sample
    assert any(t.child_frame_id for t in got["/tf"][0].transforms)
    assert got["/contacts"][-1].entities[0].frame_id == "frame0"
    assert any(log.name for log in got["/events"])
    for pad in PAD_NAMES:
        grid = got[pad_topic(pad)][0]
        assert grid.frame_id == f"{pad}_pad" and grid.column_count > 0
        assert len(grid.data) == grid.row_stride * (len(grid.data) // grid.row_stride) > 0


async def test_off_by_default(tmp_path: Path) -> None:
    from sdh2svc.config import load_config

    assert load_config(use_env=False).service.foxglove_port == 0
