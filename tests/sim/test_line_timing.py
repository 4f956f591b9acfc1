"""The simulated controllers' timing as the real ones': line time both ways, the SDH2 firmware's
processing time (the vendor's loop rates), motion that goes on without a host, and a pty that
forgets what nobody read."""

from __future__ import annotations

import asyncio
import contextlib
import os
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import TypeVar

import pytest
import serial_asyncio

import sdh2svc.bus  # noqa: F401  (registers unix:// with pyserial)
from bench.links import vendor_loop  # the benchmark's loop, measured here on virtual time
from sdh2svc.bus.joint import JointLink
from sdh2svc.config import load_config
from sdh2svc.connect import hand_model
from sdh2svc.protocol import dsa, sdh
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.dsacon import DsaconEmulator
from sdh2svc.sim.endpoint import BITS_PER_BYTE, DEFAULT_BAUD, MemoryEndpoint, PtyEndpoint
from sdh2svc.sim.lab import SimulatedHand, start_simulated_hand
from sdh2svc.sim.sdh2 import PUBLISHED_LOOP_HZ, Sdh2Emulator, Sdh2Options
from sdh2svc.sim.world import ScriptedWorld

BYTE_TIME = BITS_PER_BYTE / DEFAULT_BAUD
SHAPES = [(14, 6), (13, 6)] * 3
T = TypeVar("T")


@contextlib.asynccontextmanager
async def fast_hand(tmp_path: Path) -> AsyncIterator[SimulatedHand]:
    """The simulated hand as the configuration has it, on Unix sockets (the virtual clock)."""
    cfg = load_config(use_env=False)
    hand = await start_simulated_hand(hand_model(cfg), cfg.sim, unix_dir=tmp_path)
    try:
        yield hand
    finally:
        await hand.stop()


def fast(tmp_path: Path, body: Callable[[SimulatedHand], Awaitable[T]]) -> T:
    async def main() -> T:
        async with fast_hand(tmp_path) as hand:
            return await body(hand)

    return run_fast(main())


def sdh2_replies(latency: float, *writes: bytes, wait_s: float = 0.1) -> list[tuple[float, bytes]]:
    """The SDH2 emulator (``latency`` s to process an ASCII command) sent ``writes`` at once on
    the virtual clock: its replies, each with when it was out, from the writes on."""
    chunks: list[tuple[float, bytes]] = []

    async def main() -> float:
        emu = Sdh2Emulator(ScriptedWorld(SHAPES), options=Sdh2Options(ascii_latency_s=latency))
        ep = MemoryEndpoint(emu, whole_packets=True, on_output=lambda d, t: chunks.append((t, d)))
        async with ep:
            await asyncio.sleep(0.1)
            t0 = asyncio.get_running_loop().time()
            for data in writes:
                ep.write(data)
            await asyncio.sleep(wait_s)
        return t0

    t0 = run_fast(main())
    return [(t - t0, data) for t, data in chunks]


def test_host_bytes_take_their_line_time_and_the_firmware_its_processing_time() -> None:
    """`pos`: 5 bytes in, the processing time, 47 bytes out; a second command sent at once
    waits until the firmware is done with the first."""
    latency = 0.006  # longer than a reply's line time, so the second waits for the firmware
    (t1, r1), (t2, r2) = sdh2_replies(latency, b"pos\r\n", b"pos\r\n")
    assert r1 == r2 and len(r1) == 47
    assert t1 == pytest.approx(5 * BYTE_TIME + latency + 47 * BYTE_TIME, abs=1e-9)
    # the second command was in after 10 bytes; its processing began when the first's ended
    assert t2 == pytest.approx(5 * BYTE_TIME + 2 * latency + 47 * BYTE_TIME, abs=1e-9)


def test_line_noise_takes_the_firmware_no_time() -> None:
    """100 stray bytes that frame nothing before `pos`: they take their line time and get no
    answer, but no processing time — a burst of noise must not hold every later reply back by a
    command's time per byte (1000 bytes were 5 s; 200 kB left the SDH2 deaf for 15 minutes)."""
    latency = 0.0049
    ((t1, r1),) = sdh2_replies(latency, b"\xff" * 100 + b"\r\npos\r\n", wait_s=1.0)
    # (the noise's line, ended by the CR LF, is a blank line: no answer, a command's time)
    assert r1.startswith(b"POS=")
    assert t1 == pytest.approx(107 * BYTE_TIME + 2 * latency + len(r1) * BYTE_TIME, abs=1e-9)


def test_joint_loop_runs_at_the_real_hands_rates(tmp_path: Path) -> None:
    async def body(hand: SimulatedHand) -> dict[str, float]:
        url = hand.urls("sdh")[0]
        rates = {}
        for name in ("binary", "ascii"):
            # binary_crc: the RS-232 form (5/33-byte requests, 34-byte replies) the figure is for
            binary = name == "binary"
            link = await JointLink.open(url, binary=binary, binary_crc=binary or None)
            try:
                rates[name] = await vendor_loop(link, 60)
            finally:
                await link.close()
        return rates

    rates = fast(tmp_path, body)
    for name, hz in rates.items():
        assert hz == pytest.approx(PUBLISHED_LOOP_HZ[name], rel=0.15), name


async def raw_sdh(url: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    return await serial_asyncio.open_serial_connection(url=url, baudrate=DEFAULT_BAUD)


async def ask(conn: tuple[asyncio.StreamReader, asyncio.StreamWriter], line: bytes) -> bytes:
    conn[1].write(line + b"\r\n")
    return await asyncio.wait_for(conn[0].readline(), 2.0)


@pytest.mark.parametrize("mode", ["move", "velocity"])
def test_motion_goes_on_after_the_host_disconnects(tmp_path: Path, mode: str) -> None:
    """A host starts a move (or a velocity) and closes the port at once, as SDHLibrary does
    after its last command: the command still crosses the line, and the motion carries on, the
    world stepping on the controller's own clock; the next host finds the joints on their way."""

    async def body(hand: SimulatedHand) -> None:
        url = hand.urls("sdh")[0]
        conn = await raw_sdh(url)
        if mode == "move":
            await ask(conn, b"p=0,-40,40,-40,40,-40,40")
            conn[1].write(b"m\r\n")
        else:
            await ask(conn, b"con=1")
            conn[1].write(b"v=0,-10,10,0,0,0,0\r\n")
        conn[1].close()
        await asyncio.sleep(0.15)  # the host is gone: nobody asks the controller anything
        assert not hand.endpoints["sdh"][0]._host_present()
        seen = []
        for _ in range(3):
            seen.append(hand.sdh.actual_deg[1])
            await asyncio.sleep(0.3)
        assert seen[0] > seen[1] > seen[2]  # axis 1 goes on towards -40 (or at -10 deg/s)
        before = hand.sdh.actual_deg[1]
        conn = await raw_sdh(url)
        pos = sdh.ReplyParser().feed(await ask(conn, b"pos"))[0]
        assert isinstance(pos, sdh.Reply)
        assert before >= pos.values[1] >= hand.sdh.actual_deg[1]  # on its way: no jump
        conn[1].close()

    fast(tmp_path, body)


async def test_a_reopened_pty_holds_no_stale_bytes() -> None:
    """A host starts a push stream, stops reading, and goes without a stop: what it left unread
    is forgotten, and the next host's stop is answered by the first bytes it reads."""
    emu = DsaconEmulator(ScriptedWorld(SHAPES))
    async with PtyEndpoint(emu) as ep:
        reader, writer = await serial_asyncio.open_serial_connection(url=ep.url)
        writer.write(dsa.configure_acquisition(acquire=True, framerate=30))
        await asyncio.wait_for(reader.read(1), 2.0)  # the stream runs
        sent = ep.stats.bytes_tx
        await eventually(lambda: ep.stats.bytes_tx > sent + 500)  # unread frames pile up
        writer.close()
        await eventually(lambda: not ep.host_open)
        assert not emu.streaming
        fd = os.open(ep.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            assert read_now(fd) == b""  # nothing stale
            os.write(fd, dsa.configure_acquisition(acquire=False, framerate=0))
            got = b""
            async with asyncio.timeout(2.0):
                while len(got) < 10:
                    got += read_now(fd)
                    await asyncio.sleep(0.005)
        finally:
            os.close(fd)
    ack = dsa.PacketParser().feed(got)[0]
    assert isinstance(ack, dsa.Packet) and ack.id == dsa.PacketId.CONFIGURE_DATA_ACQUISITION


def read_now(fd: int) -> bytes:
    """What the slave holds now (the last host left VMIN = 0: an empty read returns b"")."""
    try:
        return os.read(fd, 4096)
    except BlockingIOError:
        return b""


async def eventually(cond: Callable[[], bool], timeout: float = 5.0) -> None:
    async with asyncio.timeout(timeout):
        while not cond():
            await asyncio.sleep(0.01)
