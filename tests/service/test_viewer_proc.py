"""The 3-D view in a child process (sdh2svc.service.viewer_proc): real processes, real viser."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import pickle
import signal
import socket
import subprocess
import sys
import textwrap
import time
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import msgspec.msgpack
import pytest
import viser
import zstandard
from viser import _messages
from websockets.asyncio.client import ClientConnection, connect
from websockets.typing import Subprotocol

from sdh2svc.config import Settings
from sdh2svc.service import viewer
from sdh2svc.service.viewer import camera_message
from sdh2svc.service.viewer_proc import KINDS, ViewerError, ViewerProcess

POSE = [90.0, -20.0, 30.0, -90.0, 0.0, -20.0, 30.0]
SAMPLE = {
    "iteration": 7, "phi2": -20.0, "phi3": 30.0, "phi4": -20.0, "phi5": 30.0,
    "Ay": -8.0, "Az": 140.0, "By": 74.0, "Bz": 140.0, "omega_A": 90.0, "omega_B": 115.0,
}  # fmt: skip
ROOT = Path(__file__).resolve().parents[2]


class Recorder:
    """An on_command that records what reached it (and on which loop), refusing some kinds."""

    def __init__(self, refuse: tuple[str, ...] = ()) -> None:
        self.calls: list[tuple[str, dict[str, Any]]] = []
        self.loops: set[asyncio.AbstractEventLoop] = set()
        self.refuse = refuse

    async def __call__(self, kind: str, args: dict[str, Any]) -> None:
        self.loops.add(asyncio.get_running_loop())
        self.calls.append((kind, args))
        if kind in self.refuse:
            raise RuntimeError("a run is already running")


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

    async def send_gui(self, uuid: str, value: Any) -> None:
        """What the viser client sends when a button is clicked or a slider moved."""
        msg = _messages.GuiUpdateMessage(uuid, {"value": value})
        await self.ws.send(msgspec.msgpack.encode(msg.as_serializable_dict()))


def decode(frame: bytes) -> list[dict[str, Any]]:
    """viser's wire format: sizes, zstd-compressed msgpack, then raw buffers (not needed)."""
    size, packed = int.from_bytes(frame[:8], "little"), int.from_bytes(frame[8:16], "little")
    inner = zstandard.ZstdDecompressor().decompress(frame[16 : 16 + packed], max_output_size=size)
    return list(msgspec.msgpack.decode(inner)["messages"])


@contextlib.asynccontextmanager
async def browser(url: str) -> AsyncIterator[Browser]:
    proto = [Subprotocol(f"viser-v{viser.__version__}")]
    async with connect(url.replace("http://", "ws://"), subprotocols=proto,
                       max_size=2**26) as ws:  # fmt: skip
        await ws.send(camera_message())
        b = Browser(ws)
        reader = asyncio.create_task(b.read())
        try:
            yield b
        finally:
            reader.cancel()


@contextlib.asynccontextmanager
async def running(cfg: Settings, **kwargs: Any) -> AsyncIterator[ViewerProcess]:
    v = ViewerProcess(cfg, port=0, **kwargs)
    await v.start()
    try:
        yield v
    finally:
        await v.stop()


async def wait_for(pred: Any, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not pred():
        assert time.monotonic() < deadline, "condition not reached"
        await asyncio.sleep(0.01)


def alive(pid: int) -> bool:
    """The process exists and is not a zombie."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


# --- the parts ---------------------------------------------------------------------------------


def test_kinds_are_what_the_viewer_draws() -> None:
    assert set(KINDS) == set(viewer._PAYLOAD)


def test_settings_reach_the_child_exactly(cfg: Settings) -> None:
    """The child gets ``model_dump()`` through pickle and validates it again."""
    assert Settings.model_validate(pickle.loads(pickle.dumps(cfg.model_dump()))) == cfg


# --- a real child ------------------------------------------------------------------------------


async def test_serves_viser_on_a_free_port_and_stops(cfg: Settings) -> None:
    v = ViewerProcess(cfg, port=0)
    await v.start()
    pid = v.pid
    assert pid is not None and pid != os.getpid() and alive(pid)
    try:
        assert v.url is not None and v.url.startswith("http://127.0.0.1:")
        assert not v.url.endswith(":0")

        def get() -> tuple[int, bytes]:
            assert v.url is not None
            with urllib.request.urlopen(v.url, timeout=10) as r:
                return r.status, r.read()

        status, body = await asyncio.to_thread(get)
        assert status == 200 and b"<html" in body.lower()
    finally:
        await v.stop()
    assert not alive(pid)
    assert v.url is None and v.pid is None
    await v.stop()  # idempotent


async def test_forwards_latest_only_while_watched(cfg: Settings) -> None:
    async with running(cfg, max_hz=30.0) as v:
        v.handle({"type": "pose", "angles_deg": POSE})
        v.handle({"type": "sample", "run_id": 1, "sample": SAMPLE})
        v.handle({"type": "event", "kind": "reversal"})  # not drawn: not kept
        await asyncio.sleep(0.3)
        assert v.forwarded == 0 and not v.watched  # nobody watching: nothing sent

        async with browser(v.url or "") as b:
            await wait_for(lambda: v.watched)
            await wait_for(lambda: v.forwarded == 2)  # a new browser: all latest at once
            visible = "SetSceneNodeVisibilityMessage"
            await wait_for(lambda: any(m["visible"] for m in b.sent(visible, "/contacts/A")))

            moved = len(b.sent("SetPositionMessage", "/f1/distal"))
            for i in range(200):  # a burst: the latest is forwarded, not every message
                v.handle({"type": "sample", "sample": {**SAMPLE, "phi2": -i / 10}})
            await wait_for(lambda: len(b.sent("SetPositionMessage", "/f1/distal")) > moved)
            assert v.forwarded - 2 < 10

        await wait_for(lambda: not v.watched)
        before, seen = v.forwarded, len(b.messages)
        v.handle({"type": "sample", "sample": {**SAMPLE, "phi2": 5.0}})
        await asyncio.sleep(0.3)
        assert v.forwarded == before  # nobody watching again: nothing sent
        assert len(b.messages) == seen


async def test_gui_commands_reach_on_command_and_refusals_show(cfg: Settings) -> None:
    commands = Recorder(refuse=("stop",))
    async with running(cfg, on_command=commands) as v, browser(v.url or "") as b:
        await wait_for(lambda: v.watched)
        stop = b.gui_uuid("GuiButtonMessage", "Stop")
        k = b.gui_uuid("GuiSliderMessage", "k")

        def panel() -> list[str]:  # the markdown's content travels as "_markdown"
            return [str(m["updates"]) for m in b.messages if m["type"] == "GuiUpdateMessage"]

        await b.send_gui(stop, True)  # refused by the parent: the note shows in the child's panel
        await wait_for(lambda: any("stop: a run is already running" in t for t in panel()))
        await b.send_gui(k, 3.5)
        await wait_for(lambda: len(commands.calls) == 2)
        assert commands.calls == [("stop", {}), ("params", {"k": 3.5})]
        assert commands.loops == {asyncio.get_running_loop()}  # run on the parent's loop


async def test_port_in_use_is_a_clear_error(cfg: Settings) -> None:
    with socket.create_server(("127.0.0.1", 0)) as taken:
        port = taken.getsockname()[1]
        v = ViewerProcess(cfg, port=port)
        with pytest.raises(ViewerError, match=rf"127\.0\.0\.1:{port}: .*in use.*viser_port"):
            await v.start()
    assert v.pid is None and v.url is None


@pytest.mark.parametrize(
    ("sig", "level", "says"),
    [(signal.SIGKILL, logging.WARNING, "died"), (signal.SIGTERM, logging.INFO, "on SIGTERM")],
    ids=["killed", "terminated"],
)
async def test_survives_the_child_dying(
    cfg: Settings, caplog: pytest.LogCaptureFixture, sig: int, level: int, says: str
) -> None:
    """Killed: a warning, once; terminated (e.g. the process group): said, not warned of."""
    caplog.set_level(logging.INFO, logger="sdh2svc.service.viewer_proc")
    async with running(cfg) as v:
        assert v.pid is not None
        os.kill(v.pid, sig)
        await wait_for(lambda: v.url is None)
        v.handle({"type": "sample", "sample": SAMPLE})  # still just a store
        await asyncio.sleep(0.1)
    ours = [r for r in caplog.records if r.name == "sdh2svc.service.viewer_proc"]
    assert [(r.levelno, says in r.getMessage()) for r in ours] == [(level, True)]


def test_child_exits_when_the_parent_is_killed(tmp_path: Path) -> None:
    script = tmp_path / "parent.py"
    script.write_text(
        textwrap.dedent("""
        import asyncio
        from sdh2svc.config import default_config
        from sdh2svc.service.viewer_proc import ViewerProcess

        async def main():
            v = ViewerProcess(default_config(), port=0)
            await v.start()
            print(v.pid, flush=True)
            await asyncio.sleep(60)

        if __name__ == "__main__":
            asyncio.run(main())
    """)
    )
    with subprocess.Popen([sys.executable, str(script)], cwd=ROOT, stdout=subprocess.PIPE,
                          stderr=subprocess.DEVNULL, text=True) as parent:  # fmt: skip
        try:
            assert parent.stdout is not None
            child = int(parent.stdout.readline())
            assert alive(child)
        finally:
            parent.kill()
    deadline = time.monotonic() + 10.0
    while alive(child):
        assert time.monotonic() < deadline, "the view's process outlived its parent"
        time.sleep(0.05)
