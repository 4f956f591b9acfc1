"""Read an MCAP file back with `mcap`'s reader, validating every message against its schema.

JSON channels against their JSON schema (jsonschema); protobuf channels (the Foxglove schemas)
decoded with the FileDescriptorSet their schema record carries, with no unknown field allowed.
"""

from __future__ import annotations

import io
import json
from dataclasses import dataclass, field
from typing import Any

import jsonschema
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from google.protobuf.json_format import MessageToDict
from google.protobuf.message import Message
from mcap.reader import make_reader


@dataclass
class Recording:
    """Decoded messages per topic (with log times), the schemas, metadata and attachments."""

    messages: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    log_times: dict[str, list[int]] = field(default_factory=dict)
    schemas: dict[str, tuple[str, str]] = field(default_factory=dict)  # topic → (name, encoding)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, tuple[str, bytes]] = field(default_factory=dict)


def _proto_class(name: str, data: bytes) -> type[Message]:
    fds = descriptor_pb2.FileDescriptorSet.FromString(data)
    pool = descriptor_pool.DescriptorPool()
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def _no_unknown_fields(msg: Message) -> None:
    from google.protobuf.unknown_fields import UnknownFieldSet

    assert len(UnknownFieldSet(msg)) == 0, f"unknown fields in {type(msg).__name__}"
    for fd, value in msg.ListFields():
        if fd.message_type is None:
            continue
        for v in value if fd.is_repeated else [value]:
            _no_unknown_fields(v)


def read(raw: bytes) -> Recording:
    out = Recording()
    reader = make_reader(io.BytesIO(raw))
    validators: dict[int, Any] = {}
    for schema, channel, message in reader.iter_messages():
        assert schema is not None, f"{channel.topic} has no schema"
        out.schemas[channel.topic] = (schema.name, schema.encoding)
        if schema.id not in validators:
            if schema.encoding == "jsonschema":
                doc = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(doc)
                validators[schema.id] = jsonschema.Draft202012Validator(doc)
            else:
                assert schema.encoding == "protobuf" and channel.message_encoding == "protobuf"
                validators[schema.id] = _proto_class(schema.name, schema.data)
        v = validators[schema.id]
        if schema.encoding == "jsonschema":
            assert channel.message_encoding == "json"
            obj = json.loads(message.data)
            v.validate(obj)
        else:
            msg = v.FromString(message.data)
            _no_unknown_fields(msg)
            obj = MessageToDict(msg, preserving_proto_field_name=True)
            obj["_raw"] = msg
        out.messages.setdefault(channel.topic, []).append(obj)
        out.log_times.setdefault(channel.topic, []).append(message.log_time)
    for m in reader.iter_metadata():
        out.metadata[m.name] = dict(m.metadata)
    for a in reader.iter_attachments():
        out.attachments[a.name] = (a.media_type, bytes(a.data))
    return out
