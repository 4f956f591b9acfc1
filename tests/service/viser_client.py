"""A scripted viser client for the 3-D view's tests: what a browser sends and receives, in
viser's wire format (zstd-compressed msgpack)."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from typing import Any

import msgspec.msgpack
import viser
import zstandard
from viser import _messages
from websockets.asyncio.client import ClientConnection, connect
from websockets.typing import Origin, Subprotocol

PROTOCOL = [Subprotocol(f"viser-v{viser.__version__}")]


def camera_message() -> bytes:
    """What a browser sends once it shows the scene: its camera (viser counts a client as
    connected, and the view draws for it, from then on). viser's private message type: a
    scripted client's business, not the service's."""
    msg = _messages.ViewerCameraMessage(
        wxyz=(1.0, 0.0, 0.0, 0.0), position=(0.3, 0.0, 0.2), fov=1.0, near=0.01, far=100.0,
        image_height=720, image_width=1280, look_at=(0.0, 0.0, 0.0), up_direction=(0.0, 0.0, 1.0),
    )  # fmt: skip
    return msgspec.msgpack.encode(msg.as_serializable_dict())


class Browser:
    """A viser websocket client: what a browser showing the view receives, decoded."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.messages: list[dict[str, Any]] = []

    async def read(self) -> None:
        with contextlib.suppress(Exception):
            async for frame in self.ws:
                assert isinstance(frame, bytes)
                self.messages += decode(frame)

    def sent(self, kind: str, name: str) -> list[dict[str, Any]]:
        """The messages of one type (e.g. SetPositionMessage) sent for a scene node, in order."""
        return [m for m in self.messages if m["type"] == kind and m.get("name") == name]

    def gui_uuid(self, kind: str, label: str) -> str:
        return next(
            m["uuid"] for m in self.messages if m["type"] == kind and m["props"]["label"] == label
        )

    def panel(self) -> list[str]:
        """The GUI updates received, as text (the markdown's content travels as "_markdown")."""
        return [str(m["updates"]) for m in self.messages if m["type"] == "GuiUpdateMessage"]

    async def send_gui(self, uuid: str, value: Any, **props: Any) -> None:
        """What the viser client sends when a button is clicked or a slider moved (whether or
        not the control is disabled: viser's client would not, a hostile page's script would);
        ``props``: more fields in the same update, as a hostile client could put there."""
        msg = _messages.GuiUpdateMessage(uuid, {"value": value, **props})
        await self.ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))


def decode(frame: bytes) -> list[dict[str, Any]]:
    """viser's wire format: sizes, zstd-compressed msgpack, then raw buffers (not needed)."""
    size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + packed], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


def ws_url(url: str) -> str:
    return url.replace("http://", "ws://")


@contextlib.asynccontextmanager
async def browser(url: str, origin: str | None = None) -> AsyncIterator[Browser]:
    """A browser on the view at ``url`` (an http:// URL), its page at ``origin`` if given."""
    async with connect(ws_url(url), subprotocols=PROTOCOL, max_size=2**26,
                       origin=Origin(origin) if origin else None) as ws:  # fmt: skip
        await ws.send(camera_message())
        b = Browser(ws)
        reader = asyncio.create_task(b.read())
        try:
            yield b
        finally:
            reader.cancel()
