"""A client of the Foxglove WebSocket protocol (foxglove.websocket.v1, now named foxglove.sdk.v1)
over ``websockets``, for the tests: what each advertised channel carries, decoded against the
schema it was advertised with."""

from __future__ import annotations

import base64
import json
from typing import Any

import jsonschema
from mcap_check import _no_unknown_fields, _proto_class
from websockets.asyncio.client import ClientConnection

# The protocol's names: foxglove-sdk ≥ 0.30 answers to the newer one only; a client offers both.
SUBPROTOCOLS = ["foxglove.websocket.v1", "foxglove.sdk.v1"]
MESSAGE_DATA, FETCH_ASSET_RESPONSE = 0x01, 0x04  # binary opcodes (server → client)


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


async def recv_json(ws: ClientConnection, op: str) -> dict[str, Any]:
    """The next text message of operation ``op`` (others skipped)."""
    while True:
        m = await ws.recv()
        if isinstance(m, str) and (obj := json.loads(m))["op"] == op:
            return obj  # type: ignore[no-any-return]
