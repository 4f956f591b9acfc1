"""`sdh2svc sim`: both simulated controllers served for any driver, over ptys and TCP."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

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


def test_sim_puts_the_object_back_between_runs(tmp_path: Path) -> None:
    """Two real runs, one after the other, against one `sdh2svc sim` over TCP: after the first
    lets the egg go, the lab assistant puts it back (logged), and the second grasps it again."""
    sim = subprocess.Popen(
        [sys.executable, "-m", "sdh2svc", "sim", "--json", "--no-pty", "--dsa-port", "0",
         "--sdh-port", "0", "--object", "egg", "--replace-after", "0.5"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    err: list[str] = []
    reader = threading.Thread(target=lambda: err.extend(sim.stderr), daemon=True)  # type: ignore[arg-type]
    reader.start()
    try:
        assert sim.stdout is not None
        info = json.loads(sim.stdout.readline())
        run = [sys.executable, "-m", "sdh2svc", "run", "--dsa", info["dsa"][0], "--sdh",
               info["sdh"][0], "--cycles", "1", "--json",
               # the egg's force peaks may reach the default 3 × Fd in real time (tests/service)
               "--set", "safety.force_ceiling_factor=4.0",
               "--set", f"storage.db_path={json.dumps(str(tmp_path / 'runs.sqlite'))}"]  # fmt: skip
        for n in (1, 2):
            r = subprocess.run(run, capture_output=True, text=True, timeout=180, cwd=tmp_path)
            summary = json.loads(r.stdout)
            assert summary["status"] == "completed", (n, summary, r.stderr)
            assert summary["iterations"] > 0
            deadline = time.monotonic() + 20.0
            while not any("put back" in line for line in err[n - 1 :]):
                assert time.monotonic() < deadline, f"run {n}: the egg was not put back: {err}"
                time.sleep(0.05)
    finally:
        sim.send_signal(signal.SIGINT)
        sim.wait(timeout=20)
        reader.join(5.0)
        for stream in (sim.stdout, sim.stderr):
            stream.close()  # type: ignore[union-attr]
    assert sim.returncode == 0, err
    assert sum("put back between the fingertips" in line for line in err) == 2, err
    assert not any("Traceback" in line for line in err)
