"""`sdh2svc sim`: both simulated controllers served for any driver, over ptys and TCP."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import serial_asyncio

from sdh2svc import connect
from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus
from sdh2svc.cli import main
from sdh2svc.config import load_config
from sdh2svc.connect import Real, hand_model
from sdh2svc.protocol import dsa, sdh
from sdh2svc.service.headless import run_once
from sdh2svc.sim import lab
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.lab import LabAssistant, start_simulated_hand


async def _dsa_info(url: str) -> dsa.ControllerInfo:
    reader, writer = await serial_asyncio.open_serial_connection(url=url, baudrate=115200)
    try:
        parser = dsa.PacketParser()
        writer.write(dsa.query_controller_info())
        while True:
            for ev in parser.feed(await asyncio.wait_for(reader.read(256), 5.0)):
                if (
                    isinstance(ev, dsa.Packet)
                    and ev.id == dsa.PacketId.QUERY_CONTROLLER_CONFIGURATION
                ):
                    return dsa.ControllerInfo.decode(ev.payload)
    finally:
        writer.close()


async def _sdh_version(url: str) -> str:
    reader, writer = await serial_asyncio.open_serial_connection(url=url, baudrate=115200)
    try:
        parser = sdh.ReplyParser()
        writer.write(sdh.encode_ascii("ver"))
        while True:
            for ev in parser.feed(await asyncio.wait_for(reader.read(256), 5.0)):
                if isinstance(ev, sdh.Reply) and ev.keyword == "VER":
                    return ev.text
    finally:
        writer.close()


def test_sim_serves_both_devices_on_pty_and_tcp() -> None:
    proc = subprocess.Popen(
        [sys.executable, "-m", "sdh2svc", "sim", "--json", "--dsa-port", "0", "--sdh-port", "0",
         "--object", "rubber"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        assert proc.stdout is not None
        info = json.loads(proc.stdout.readline())
        assert info["object"] == "rubber"
        for kind in ("dsa", "sdh"):
            assert any(u.startswith("/dev/pts/") for u in info[kind])
            assert any(u.startswith("socket://127.0.0.1:") for u in info[kind])

        async def check() -> None:
            for url in info["dsa"]:
                ci = await _dsa_info(url)
                assert ci.sw_version >= 0x1000
            for url in info["sdh"]:
                assert await _sdh_version(url) == "0.0.3.3"
            # and our own drivers, over the pty and over TCP
            for dsa_url, sdh_url in zip(info["dsa"], info["sdh"], strict=True):
                async with await TactileBus.open(dsa_url) as bus:
                    assert bus.nb_cells == 486
                    sub = bus.subscribe({1, 5}, 30.0)
                    first = await sub.next_frame(timeout=5.0)
                    second = await sub.next_frame(timeout=5.0)
                    assert second.seq > first.seq
                async with await JointLink.open(sdh_url) as link:
                    assert link.version == "0.0.3.3"
                    assert len(await link.get_actual()) == 7

        asyncio.run(check())
    finally:
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    assert proc.returncode == 0, err
    assert "Traceback" not in err


def test_sim_rejects_an_unknown_object() -> None:
    r = subprocess.run([sys.executable, "-m", "sdh2svc", "sim", "--object", "banana"],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 2 and "presets" in r.stderr


def test_sim_puts_the_object_back_between_runs(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two runs, one after the other, against one simulated hand with the lab assistant that
    `sdh2svc sim` starts: after the first lets the egg go, the assistant puts it back (logged),
    and the second grasps it again. In fast mode (virtual clock) through the same drivers and
    bytes; the option's way from the command line to the assistant is checked below."""
    db = json.dumps(str(tmp_path / "runs.sqlite"))
    cfg = load_config(overrides=[f"storage.db_path={db}", "sim.object='egg'", "rolling.cycles=1",
                                 "safety.force_ceiling_factor=4.0"], use_env=False)  # fmt: skip

    def put_back() -> list[str]:
        return [m for m in caplog.messages if "put back between the fingertips" in m]

    async def main() -> list[dict[str, Any]]:
        hand = await start_simulated_hand(hand_model(cfg), cfg.sim, unix_dir=tmp_path)
        # fast mode starts no assistant of its own: this is the one `sdh2svc sim` starts
        assistant = asyncio.create_task(LabAssistant(hand.world, 0.5).run())
        summaries = []
        try:
            real = Real(hand.urls("dsa")[0], hand.urls("sdh")[0])  # to the drivers, a real hand
            for n in (1, 2):
                summaries.append(await run_once(cfg, real))
                async with asyncio.timeout(20.0):  # virtual seconds
                    while len(put_back()) < n:
                        await asyncio.sleep(0.1)
                assert hand.world.truth().in_fixture, f"after run {n}"
        finally:
            assistant.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await assistant
            await hand.stop()
        return summaries

    with caplog.at_level(logging.INFO, logger="sdh2svc.sim.lab"):
        summaries = run_fast(main())
    for n, summary in enumerate(summaries, 1):
        assert summary["status"] == "completed", (n, summary)
        assert summary["iterations"] > 0
    assert len(put_back()) == 2, caplog.messages


def test_sim_replace_after_reaches_the_lab_assistant(monkeypatch: pytest.MonkeyPatch) -> None:
    """`sdh2svc sim --replace-after S` configures the assistant, which the real-time hand
    starts (the one the test above exercises)."""
    seen: list[float] = []

    async def fake_start(model: Any, sim: Any, **kwargs: Any) -> Any:
        after = kwargs["replace_after_s"]
        seen.append(sim.replace_after_s if after is None else after)
        raise OSError("stop here")

    monkeypatch.setattr(connect, "start_simulated_hand", fake_start)
    assert main(["sim", "--no-pty", "--replace-after", "0.5"]) == 4  # "cannot serve" after it
    assert seen == [0.5]
    monkeypatch.undo()

    class Recording(LabAssistant):
        def __init__(self, world: Any, after_s: float, poll_s: float = 0.1) -> None:
            seen.append(after_s)
            super().__init__(world, after_s, poll_s)

    monkeypatch.setattr(lab, "LabAssistant", Recording)

    async def real_time() -> None:
        cfg = load_config(overrides=["sim.replace_after_s=1.5"], use_env=False)
        hand = await lab.start_simulated_hand(
            hand_model(cfg), cfg.sim, pty=False, tcp=True, dsa_port=0, sdh_port=0
        )
        await hand.stop()

    asyncio.run(real_time())
    assert seen == [0.5, 1.5]


def _ver(port: int) -> bytes:
    """The SDH2's answer to `ver` on ``port`` (b"": none within 3 s)."""
    import socket

    with socket.create_connection(("127.0.0.1", port), timeout=3.0) as s:
        s.sendall(b"ver\r\n")
        got = b""
        with contextlib.suppress(TimeoutError):
            while b"\n" not in got:
                if not (more := s.recv(256)):
                    break
                got += more
    return got


def test_a_sim_in_the_background_of_its_terminal_keeps_serving() -> None:
    """`sdh2svc sim &` from a terminal: its first read of the terminal used to stop the whole
    process (SIGTTIN) after it had printed its URLs, and every driver met a silent line. Here a
    session with a pseudo-terminal starts the sim as a background job of it (a process group of
    its own, not the terminal's foreground one)."""
    import os
    import pty
    import select
    import time

    argv = [sys.executable, "-m", "sdh2svc", "sim", "--no-pty", "--sdh-port", "0",
            "--dsa-port", "0"]  # fmt: skip
    pid, fd = pty.fork()
    if pid == 0:  # the session's leader: the terminal's foreground group is its own
        job = os.fork()
        if job == 0:
            os.setpgid(0, 0)  # a background job: `&`
            os.execv(sys.executable, argv)
        os.write(1, f"job {job}\n".encode())
        os.waitpid(job, 0)
        os._exit(0)
    job = port = None
    try:
        seen = b""
        deadline = time.monotonic() + 30
        while port is None and (left := deadline - time.monotonic()) > 0:
            if select.select([fd], [], [], left)[0]:
                seen += os.read(fd, 1024)
            job = int(m.group(1)) if (m := re.search(rb"job (\d+)", seen)) else None
            url = re.search(rb"SDH2 \(joints\): +socket://127\.0\.0\.1:(\d+)", seen)
            port = int(url.group(1)) if url else None
        assert job is not None and port is not None, seen
        answer = b""
        while not answer and time.monotonic() < deadline:
            with contextlib.suppress(OSError):
                answer = _ver(port)
            time.sleep(0.2)
        assert answer.startswith(b"VER="), answer
        with open(f"/proc/{job}/stat") as stat:  # not stopped: running or sleeping
            assert stat.read().rsplit(")", 1)[1].split()[0] in "RS"
    finally:
        for group in (job, pid):  # (a stopped job would not take a SIGTERM)
            if group is not None:
                with contextlib.suppress(ProcessLookupError, PermissionError):
                    os.killpg(group, signal.SIGKILL)
        os.waitpid(pid, 0)
        os.close(fd)
