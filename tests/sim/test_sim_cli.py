"""`sdh2svc sim`: both simulated controllers served for any driver, over ptys and TCP."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys

import serial_asyncio

from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus
from sdh2svc.protocol import dsa, sdh


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
