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
from types import SimpleNamespace
from typing import Any

import pytest
from viser_client import PROTOCOL, browser, ws_url
from websockets.asyncio.client import connect
from websockets.exceptions import InvalidStatus
from websockets.typing import Origin

from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Simulated
from sdh2svc.service import viewer, viewer_proc
from sdh2svc.service.app import close_services, open_services
from sdh2svc.service.replay_feed import Recorded
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


@contextlib.asynccontextmanager
async def running(cfg: Settings, **kwargs: Any) -> AsyncIterator[ViewerProcess]:
    v = ViewerProcess(cfg, port=0, **kwargs)
    await v.start()
    try:
        yield v
    finally:
        await v.stop()


async def wait_for(pred: Any, timeout: float = 30.0) -> None:
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


@pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux's scheduling policies")
async def test_the_view_never_takes_the_services_core_on_waking(cfg: Settings) -> None:
    """The child is a batch task (it does not preempt the service when the service's telemetry
    wakes it) with a normal share of the CPU (its panel's e-stop answers on a busy machine)."""
    v = ViewerProcess(cfg, port=0)
    await v.start()
    try:
        assert v.pid is not None
        assert os.sched_getscheduler(v.pid) == os.SCHED_BATCH
        assert os.getpriority(os.PRIO_PROCESS, v.pid) == os.getpriority(os.PRIO_PROCESS, 0)
        assert os.sched_getscheduler(0) == os.SCHED_OTHER  # the service's own is untouched
    finally:
        await v.stop()


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
        rolling = {"auth_required": False, "estopped": False, "hand": {"opening": False},
                   "run": {"id": 1, "state": "rolling"}}  # fmt: skip
        v.handle({"type": "status", "status": rolling})  # Stop: a run to stop
        await wait_for(lambda: any("rolling" in t for t in b.panel()))

        await b.send_gui(stop, True)  # refused by the parent: the note shows in the child's panel
        await wait_for(lambda: any("stop: a run is already running" in t for t in b.panel()))
        await b.send_gui(k, 3.5)
        await wait_for(lambda: len(commands.calls) == 2)
        assert commands.calls == [("stop", {}), ("params", {"k": 3.5})]
        assert commands.loops == {asyncio.get_running_loop()}  # run on the parent's loop


def test_the_panels_authority_is_the_viewers() -> None:
    assert viewer_proc.ALWAYS_ALLOWED == viewer.ALWAYS_ALLOWED
    assert viewer_proc.NEEDS_TOKEN == viewer.NEEDS_TOKEN


async def test_read_only_view_only_stops(cfg: Settings, caplog: pytest.LogCaptureFixture) -> None:
    """With a token: the controls are disabled but E-STOP; clicks on them, sent over viser's
    websocket as a hostile page's script would (viser does not check ``disabled``), are refused
    in the child's panel (not even sent to the parent) and nothing reaches on_command; E-STOP
    does."""
    caplog.set_level(logging.WARNING, logger="sdh2svc.service")
    commands = Recorder()
    async with running(cfg, on_command=commands, read_only=True) as v, browser(v.url or "") as b:
        await wait_for(lambda: v.watched)
        await wait_for(lambda: any(m["type"] == "GuiSliderMessage" for m in b.messages))
        shown = {m["props"]["label"]: m["props"] for m in b.messages
                 if m["type"] in ("GuiButtonMessage", "GuiSliderMessage")}  # fmt: skip
        assert {label for label, p in shown.items() if not p["disabled"]} == {"E-STOP"}
        assert shown["Open hand"]["hint"] == shown["k"]["hint"] == viewer.NEEDS_TOKEN
        # and the panel says so (a disabled control's hint never shows in viser's client)
        await wait_for(lambda: any("Read-only view" in t for t in b.panel()))

        await b.send_gui(b.gui_uuid("GuiButtonMessage", "Grasp & roll"), True)
        await wait_for(lambda: any("start: needs the API token" in t for t in b.panel()))
        await b.send_gui(b.gui_uuid("GuiButtonMessage", "Open hand"), True)
        await wait_for(lambda: any("open: needs the API token" in t for t in b.panel()))
        await b.send_gui(b.gui_uuid("GuiSliderMessage", "k"), 3.5)
        await wait_for(lambda: any("params: needs the API token" in t for t in b.panel()))
        assert commands.calls == []
        await b.send_gui(b.gui_uuid("GuiButtonMessage", "E-STOP"), True)
        await wait_for(lambda: len(commands.calls) == 1)
        assert commands.calls == [("estop", {})]
    said = [r.getMessage() for r in caplog.records]
    assert sum("refused in the panel" in m for m in said) == 3  # the child's log, through ours
    assert not any("(read-only view)" in m for m in said)  # the parent had nothing to refuse


async def test_read_only_parent_runs_only_the_estop(cfg: Settings) -> None:
    """The parent does not take the child's word for it: read-only, a command other than the
    e-stop from the child (say, one whose panel check failed) is answered refused, not run."""
    commands = Recorder()
    v = ViewerProcess(cfg, on_command=commands, read_only=True)
    replies: list[tuple[Any, ...]] = []
    v._chan = SimpleNamespace(send=replies.append)  # type: ignore[assignment]
    for ident, kind in enumerate(("start", "stop", "release", "open", "params", "estop")):
        await v._command(ident, kind, {"k": 3.5} if kind == "params" else {})
    assert commands.calls == [("estop", {})]
    assert replies == [("result", i, viewer.NEEDS_TOKEN) for i in range(5)] + [("result", 5, None)]


async def test_websocket_refuses_other_sites(cfg: Settings) -> None:
    """A page of another site cannot open the view's websocket (403); the view's own can."""
    async with running(cfg) as v:
        assert v.url is not None
        port = int(v.url.rsplit(":", 1)[1])
        for origin in ("http://evil.example", f"http://evil.example:{port}", "null"):
            with pytest.raises(InvalidStatus) as refused:
                async with connect(ws_url(v.url), subprotocols=PROTOCOL, origin=Origin(origin)):
                    pass
            assert refused.value.response.status_code == 403
        async with browser(v.url, origin=f"http://127.0.0.1:{port}"):
            await wait_for(lambda: v.watched)


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


async def test_the_status_says_when_the_view_is_gone(tmp_path: Path) -> None:
    """A dead view's process left the dashboard's frame saying "Connecting…" for ever: the
    status now says the view is no longer served (the dashboard then shows its note)."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'",
                                 "service.viser_port=0"], use_env=False)  # fmt: skip
    services = await open_services(cfg, Simulated(), viewer=True)
    try:
        st = services.station
        assert st.status()["viewer"] is True and services.viewer.pid is not None
        os.kill(services.viewer.pid, signal.SIGKILL)
        await wait_for(lambda: st.status()["viewer"] is False)
        assert services.viewer_url is None
    finally:
        await close_services(services)
    without = await open_services(cfg, Simulated(), viewer=False)
    try:
        assert without.station.status()["viewer"] is None
    finally:
        await close_services(without)


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


async def test_a_replay_goes_to_the_child_as_its_latest_messages(cfg: Settings) -> None:
    """The parent's feed: a replayed iteration replaces the latest live messages it forwards;
    live ones wait, and come back when the replay ends (no child needed to see it)."""
    vp = ViewerProcess(cfg, port=0)
    live_sample = {"type": "sample", "run_id": 1, "sample": {"iteration": 1}}
    vp.handle(live_sample)
    vp.handle({"type": "status", "status": {"run": None}})
    shown = {"type": "sample", "run_id": 2, "sample": {"iteration": 9}}
    vp.replay.show(Recorded(2, 9, 0.2, (shown,)))  # type: ignore[arg-type]
    assert vp._latest["sample"] is shown
    assert vp._latest["status"].status["replay"] == {"run_id": 2, "iteration": 9, "t": 0.2}
    newer = {"type": "sample", "run_id": 1, "sample": {"iteration": 2}}
    vp.handle(newer)
    assert vp._latest["sample"] is shown
    vp.replay.end()
    assert vp._latest["sample"] is newer
    assert vp._latest["status"] == {"type": "status", "status": {"run": None}}
