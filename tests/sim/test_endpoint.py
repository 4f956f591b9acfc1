"""Transports under the device emulators: real ptys, real TCP on 127.0.0.1, and a virtual clock.

Wall-clock assertions are lower bounds only (bytes can't beat the line rate); exact timing is
checked on a virtual-clock event loop, which runs the same endpoint code without waiting.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import os
import random
import re
import socket
import struct
import termios
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
import serial
import serial_asyncio

from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.endpoint import (
    BITS_PER_BYTE,
    DEFAULT_BAUD,
    Device,
    Endpoint,
    FaultConfig,
    FaultKind,
    LinkPacer,
    MemoryEndpoint,
    PtyEndpoint,
    TcpEndpoint,
    serve_device,
)
from sdh2svc.sim.faults import FaultInjector, bernoulli_positions

BYTE_TIME = BITS_PER_BYTE / DEFAULT_BAUD
FRAME_RE = re.compile(rb"F(\d{8}) ([a-z]+)\n")
ECHO_RE = re.compile(rb"(\d+):(ping\d*)\n")


class ToyDevice:
    """Line-command test device.

    ``stream SIZE PERIOD_MS`` streams numbered frames (period 0: as fast as the line allows),
    ``stop`` ends the stream, ``blob N`` / ``zeros N`` / ``burst K L`` queue test packets, and any
    other line is echoed as ``SEQ:line``; SEQ persists across connections.
    """

    def __init__(self, greeting: bytes = b"") -> None:
        self.inbox = bytearray()
        self.outbox: deque[bytes] = deque([greeting] if greeting else [])
        self.seq = 0
        self.frame_size = 0
        self.period_s = 0.0
        self.next_frame_at = math.inf
        self.frames = 0
        self.events: list[tuple[str, float]] = []

    def connected(self, now: float) -> None:
        self.events.append(("connected", now))

    def disconnected(self, now: float) -> None:
        self.events.append(("disconnected", now))
        self.frame_size = 0  # the host that wanted the stream is gone

    def receive(self, data: bytes, now: float) -> None:
        self.inbox += data
        while (end := self.inbox.find(b"\n")) >= 0:
            line = bytes(self.inbox[:end]).rstrip(b"\r")
            del self.inbox[: end + 1]
            self._command(line, now)

    def next_packet(self, now: float) -> bytes | None:
        if self.outbox:
            return self.outbox.popleft()
        if self.frame_size and now >= self.next_frame_at:
            self.next_frame_at = max(self.next_frame_at + self.period_s, now)
            return self._frame()
        return None

    def next_wakeup(self, now: float) -> float | None:
        return self.next_frame_at if self.frame_size else None

    def _command(self, line: bytes, now: float) -> None:
        word, *args = line.split(b" ") if line else [b""]
        nums = [int(a) for a in args if a.isdigit()]
        if word == b"stream":
            self.frame_size, self.period_s, self.next_frame_at = nums[0], nums[1] / 1000, now
        elif word == b"stop":
            self.frame_size = 0
            self.outbox.append(b"stopped\n")
        elif word == b"blob":
            self.outbox.append(b"B" * (nums[0] - 1) + b"\n")
        elif word == b"zeros":
            self.outbox.append(bytes(nums[0]))
        elif word == b"burst":
            count, size = nums
            self.outbox.extend(b"<%05d" % i + b"x" * (size - 7) + b">" for i in range(count))
        else:
            self.seq += 1
            self.outbox.append(b"%d:%s\n" % (self.seq, line))

    def _frame(self) -> bytes:
        self.frames += 1
        fill = b"abcdefghijklmnopqrstuvwxyz"[self.frames % 26 : self.frames % 26 + 1]
        return b"F%08d " % self.frames + fill * (self.frame_size - 11) + b"\n"


# -- host side helpers -------------------------------------------------------------------------

Host = tuple[asyncio.StreamReader, asyncio.StreamWriter]


@contextlib.asynccontextmanager
async def host(url: str) -> AsyncIterator[Host]:
    """A pyserial-asyncio host on ``url``, closed (fds released) on exit."""
    reader, writer = await serial_asyncio.open_serial_connection(url=url, baudrate=DEFAULT_BAUD)
    try:
        yield reader, writer
    finally:
        writer.close()
        with contextlib.suppress(serial.SerialException, ConnectionError):
            await writer.wait_closed()


async def ask(conn: Host, line: bytes, timeout: float = 5.0) -> bytes:
    reader, writer = conn
    writer.write(line + b"\r\n")
    return await asyncio.wait_for(reader.readline(), timeout)


async def until_line(reader: asyncio.StreamReader, pattern: re.Pattern[bytes]) -> bytes:
    """Skip stale or unrelated lines until one matches."""
    async with asyncio.timeout(5.0):
        while not pattern.fullmatch(line := await reader.readline()):
            pass
    return line


async def at_eof(reader: asyncio.StreamReader, timeout: float = 5.0) -> bool:
    try:
        data = await asyncio.wait_for(reader.read(4096), timeout)
    except serial.SerialException:
        return True  # pyserial's way of saying the socket closed
    return data == b""


async def eventually(cond: Callable[[], bool], timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not cond():
            await asyncio.sleep(0.01)


def open_fds() -> set[str]:
    return set(os.listdir("/proc/self/fd"))


def make(kind: str, device: Device, **kwargs: Any) -> Endpoint:
    return serve_device(device, "pty" if kind == "pty" else "tcp", **kwargs)


KINDS = pytest.mark.parametrize("kind", ["pty", "tcp"])


# -- pure parts --------------------------------------------------------------------------------


def test_toy_device_satisfies_protocol() -> None:
    assert isinstance(ToyDevice(), Device)


def test_pacer_releases_bytes_as_they_leave_the_uart() -> None:
    pacer = LinkPacer(DEFAULT_BAUD, tick_s=0.001)
    pacer.begin(10.0, 100)
    assert pacer.due(10.0) == 0
    assert pacer.due(10.0 + 11 * BYTE_TIME) == 11
    assert pacer.due(11.0) == 100
    assert pacer.wake_at(10.0, 0) == pytest.approx(10.001)  # a tick, not every byte
    assert pacer.wake_at(10.0085, 97) == pytest.approx(10.0 + 100 * BYTE_TIME)  # end, not later
    end = pacer.free_at
    assert end == pytest.approx(10.0 + 100 * BYTE_TIME)
    pacer.begin(end + 0.0005, 10)  # a late wake-up after back-to-back packets: no drift
    assert pacer.free_at == pytest.approx(end + 10 * BYTE_TIME)
    pacer.begin(20.0, 10)  # after an idle line: starts now, never earlier
    assert pacer.due(20.0) == 0
    unpaced = LinkPacer(None)
    unpaced.begin(0.0, 50)
    assert unpaced.due(0.0) == 50


def test_fault_config_validates() -> None:
    assert FaultConfig() == FaultConfig(0.0, 0.0, 0.0, 0.0)
    with pytest.raises(ValueError):
        FaultConfig(bit_error_rate=1.5)
    with pytest.raises(ValueError):
        FaultConfig(boot_delay_s=-1.0)


def test_fault_injection_is_deterministic_per_seed() -> None:
    cfg = FaultConfig(bit_error_rate=0.01, drop_byte_rate=0.01, truncate_packet_rate=0.2, seed=7)
    packets = [bytes(200)] * 50

    def run(config: FaultConfig) -> list[tuple[bytes, frozenset[int]]]:
        inj = FaultInjector(config)
        return [(p.data, p.dropped) for p in map(inj.apply_tx, packets)]

    assert run(cfg) == run(cfg)
    assert run(cfg) != run(FaultConfig(bit_error_rate=0.01, seed=8))
    assert list(bernoulli_positions(random.Random(1), 10, 1.0)) == list(range(10))
    clean = FaultInjector(FaultConfig(bit_error_rate=0.5))
    assert clean.apply_rx(b"host bytes") == b"host bytes"  # host→device only with the flag
    noisy = FaultInjector(FaultConfig(bit_error_rate=0.5, host_to_device=True))
    assert noisy.apply_rx(b"host bytes") != b"host bytes"
    assert noisy.counts[FaultKind.RX_BIT_ERROR] > 0


# -- virtual clock: same code, exact timing ----------------------------------------------------


def run_virtual(main: Callable[[], Awaitable[None]]) -> None:
    """Run on the product's fast-mode loop (sdh2svc.sim.clock)."""
    run_fast(main())


def test_virtual_clock_packet_goes_out_in_line_rate_chunks() -> None:
    chunks: list[tuple[float, int]] = []

    async def main() -> None:
        dev = ToyDevice()
        ep = MemoryEndpoint(dev, on_output=lambda data, now: chunks.append((now, len(data))))
        async with ep:
            ep.write(b"blob 1000\n")
            # the device hears the request once its 10 bytes have crossed the line
            t0 = asyncio.get_running_loop().time() + 10 * BYTE_TIME
            await asyncio.sleep(1.0)
        assert ep.output == b"B" * 999 + b"\n"
        sent = 0
        for t, n in chunks:
            sent += n
            assert sent <= (t - t0) / BYTE_TIME + 1e-6  # never ahead of the line
            assert n <= 13  # ~1 ms worth, not the whole packet
        assert len(chunks) >= 80
        assert chunks[-1][0] == pytest.approx(t0 + 1000 * BYTE_TIME)  # and never behind it

    run_virtual(main)


@pytest.mark.parametrize(("period_ms", "expected"), [(0, 10.0 / (100 * BYTE_TIME)), (50, 200)])
def test_virtual_clock_stream_is_line_limited_or_periodic(period_ms: int, expected: float) -> None:
    async def main() -> None:
        dev = ToyDevice()
        async with MemoryEndpoint(dev) as ep:
            ep.write(b"stream 100 %d\n" % period_ms)
            await asyncio.sleep(10.0)
            frames = len(FRAME_RE.findall(ep.output))
        assert abs(frames - expected) <= 1.5

    run_virtual(main)


def test_virtual_clock_boot_delay_mutes_device() -> None:
    async def main() -> None:
        dev = ToyDevice(greeting=b"hello\n")
        ep = MemoryEndpoint(dev, faults=FaultConfig(boot_delay_s=8.0))
        async with ep:
            t0 = asyncio.get_running_loop().time()
            ep.write(b"early\n")
            await asyncio.sleep(7.9)
            assert ep.output == b"" and dev.events == []
            await asyncio.sleep(0.2)
            ep.write(b"ping\n")
            await asyncio.sleep(0.1)
        assert ep.output == b"hello\n1:ping\n"  # "early" was never heard
        assert dev.events[0] == ("connected", pytest.approx(t0 + 8.0))
        assert ep.stats.faults[FaultKind.MUTED_RX_BYTE] == len(b"early\n")

    run_virtual(main)


# -- real transports ---------------------------------------------------------------------------


@KINDS
async def test_pyserial_host_round_trips(kind: str) -> None:
    dev = ToyDevice()
    async with make(kind, dev) as ep:
        assert ep.url.startswith("/dev/" if kind == "pty" else "socket://127.0.0.1:")
        async with host(ep.url) as conn:
            assert await ask(conn, b"ping") == b"1:ping\n"
            assert await ask(conn, b"ping2") == b"2:ping2\n"
        assert ep.stats.bytes_rx == len(b"ping\r\nping2\r\n")
        assert ep.stats.bytes_tx == len(b"1:ping\n2:ping2\n")
        assert ep.stats.packets_tx == 2
    assert dev.events[0][0] == "connected"


async def test_pty_slave_is_raw_and_8bit_clean() -> None:
    payload = bytes(b for b in range(256) if b != 0x0A)  # incl. \r, XON/XOFF, ^C, bit 7 set
    async with PtyEndpoint(ToyDevice(), baud=None) as ep:
        # Open the slave without configuring it: only the endpoint's raw mode applies.
        fd = os.open(ep.path, os.O_RDWR | os.O_NOCTTY | os.O_NONBLOCK)
        try:
            iflag, oflag, cflag, lflag, *_ = termios.tcgetattr(fd)
            assert not iflag & (termios.ISTRIP | termios.ICRNL | termios.INLCR | termios.IXON)
            assert not oflag & termios.OPOST
            assert not lflag & (termios.ECHO | termios.ICANON | termios.ISIG)
            assert cflag & termios.CSIZE == termios.CS8
            os.write(fd, payload + b"\n")
            got = bytearray()
            async with asyncio.timeout(5.0):
                while len(got) < len(payload) + 3:
                    with contextlib.suppress(BlockingIOError):
                        got += os.read(fd, 4096)
                    await asyncio.sleep(0.005)
        finally:
            os.close(fd)
    assert bytes(got) == b"1:" + payload + b"\n"


@KINDS
async def test_pacing_never_beats_the_line_rate(kind: str) -> None:
    size = 3000
    async with make(kind, ToyDevice()) as ep, host(ep.url) as (reader, writer):
        loop = asyncio.get_running_loop()
        t_request = loop.time()
        writer.write(b"blob %d\n" % size)
        reply = await asyncio.wait_for(reader.readline(), 10.0)
        elapsed = loop.time() - t_request
    assert len(reply) == size
    assert elapsed >= 0.95 * size * BYTE_TIME


async def test_stream_is_line_limited_and_never_interleaved() -> None:
    frame_size = 200
    lines: list[bytes] = []
    async with make("pty", ToyDevice()) as ep, host(ep.url) as (reader, writer):
        loop = asyncio.get_running_loop()
        t_request = t_last_frame = loop.time()

        async def read_line() -> None:
            nonlocal t_last_frame
            lines.append(await asyncio.wait_for(reader.readline(), 5.0))
            if lines[-1].startswith(b"F"):
                t_last_frame = loop.time()

        writer.write(b"stream %d 0\n" % frame_size)
        for i in range(6):
            writer.write(b"ping%d\n" % i)  # replies must land between frames
            deadline = loop.time() + 0.1
            while loop.time() < deadline:
                await read_line()
        writer.write(b"stop\n")
        while lines[-1] != b"stopped\n":
            await read_line()
    frames = [m for line in lines if (m := FRAME_RE.fullmatch(line))]
    echoes = [m.group(2) for line in lines if (m := ECHO_RE.fullmatch(line))]
    assert len(frames) + len(echoes) + 1 == len(lines)  # every line whole: nothing interleaved
    assert all(len(m.group(0)) == frame_size and len(set(m.group(2))) == 1 for m in frames)
    assert [int(m.group(1)) for m in frames] == list(range(1, len(frames) + 1))
    assert echoes == [b"ping%d" % i for i in range(6)]
    # All frames had fully arrived by t_last_frame; the line can't have carried more since the
    # request (echoes shared the line, which only loosens the bound).
    assert len(frames) >= 3
    assert len(frames) <= (t_last_frame - t_request) / (frame_size * BYTE_TIME) + 1


async def test_bit_error_rate_flips_about_the_expected_bits() -> None:
    size, ber = 100_000, 1e-3
    faults = FaultConfig(bit_error_rate=ber, seed=1)
    async with PtyEndpoint(ToyDevice(), baud=None, faults=faults) as ep:
        async with host(ep.url) as conn:
            conn[1].write(b"zeros %d\n" % size)
            data = await asyncio.wait_for(conn[0].readexactly(size), 10.0)
        flipped = sum(bin(b).count("1") for b in data)
        assert flipped == ep.stats.faults[FaultKind.BIT_ERROR]
    expected = 8 * size * ber  # 800, sigma ~28
    assert 0.8 * expected <= flipped <= 1.2 * expected


@pytest.mark.parametrize("fault", ["drop", "truncate"])
async def test_dropped_and_truncated_bytes_are_counted_and_missing(fault: str) -> None:
    count, size = 400, 50
    faults = (
        FaultConfig(drop_byte_rate=0.01, seed=3)
        if fault == "drop"
        else FaultConfig(truncate_packet_rate=0.2, seed=3)
    )
    dev = ToyDevice()
    async with TcpEndpoint(dev, baud=None, faults=faults) as ep, host(ep.url) as (reader, writer):
        writer.write(b"burst %d %d\n" % (count, size))
        await eventually(lambda: ep.stats.packets_tx == count)  # every fault decided by now
        lost = ep.stats.faults[FaultKind.DROP_BYTE] + ep.stats.faults[FaultKind.TRUNCATED_BYTES]
        data = await asyncio.wait_for(reader.readexactly(count * size - lost), 10.0)
        assert ep.stats.bytes_tx == len(data)
    intact = len(re.findall(rb"<\d{5}x{%d}>" % (size - 7), data))
    if fault == "drop":
        drops = ep.stats.faults[FaultKind.DROP_BYTE]
        assert 0.6 * count * size * 0.01 <= drops <= 1.4 * count * size * 0.01
        assert intact <= count - 1
    else:
        cut = ep.stats.faults[FaultKind.TRUNCATE_PACKET]
        assert 0.6 * count * 0.2 <= cut <= 1.4 * count * 0.2
        assert intact == count - cut  # a cut packet never reaches its closing ">"


async def test_tcp_disconnect_then_reconnect_keeps_device_state() -> None:
    dev = ToyDevice()
    async with TcpEndpoint(dev) as ep:
        async with host(ep.url) as conn:
            assert await ask(conn, b"ping") == b"1:ping\n"
            ep.disconnect(0.4)
            assert await at_eof(conn[0])
        async with host(ep.url) as refused:  # inside the window: accepted and dropped at once
            assert await at_eof(refused[0])
        await asyncio.sleep(0.5)
        async with host(ep.url) as conn:
            assert await ask(conn, b"ping") == b"2:ping\n"  # same device, state kept
        await eventually(lambda: len(dev.events) == 4)
    assert [e for e, _ in dev.events] == ["connected", "disconnected"] * 2
    assert ep.stats.faults[FaultKind.DISCONNECT] == 1
    assert ep.stats.connections == 2


async def test_tcp_new_connection_replaces_the_old_one() -> None:
    dev = ToyDevice()
    async with TcpEndpoint(dev) as ep, host(ep.url) as first:
        assert await ask(first, b"ping") == b"1:ping\n"
        async with host(ep.url) as second:
            assert await at_eof(first[0])
            assert await ask(second, b"ping") == b"2:ping\n"
    assert [e for e, _ in dev.events] == ["connected", "disconnected", "connected", "disconnected"]


async def test_pty_disconnect_drops_bytes_both_ways() -> None:
    dev = ToyDevice()
    async with PtyEndpoint(dev) as ep, host(ep.url) as (reader, writer):
        writer.write(b"stream 100 0\n")
        await until_line(reader, FRAME_RE)
        ep.disconnect(0.3)
        writer.write(b"lost\n")  # the device never hears this
        await asyncio.sleep(0.4)
        writer.write(b"stop\nping\n")
        assert await until_line(reader, ECHO_RE) == b"1:ping\n"
    assert ep.stats.faults[FaultKind.UNPLUGGED_TX_BYTE] > 0  # the stream ran on into the void
    assert ep.stats.faults[FaultKind.MUTED_RX_BYTE] == len(b"lost\n")
    assert [e for e, _ in dev.events] == ["connected", "disconnected"]  # a serial line can't tell


@KINDS
async def test_boot_delay_keeps_device_deaf_and_mute(kind: str) -> None:
    boot = 0.4
    dev = ToyDevice(greeting=b"hello\n")
    ep = make(kind, dev, faults=FaultConfig(boot_delay_s=boot))
    loop = asyncio.get_running_loop()
    async with ep, host(ep.url) as (reader, writer):
        t_start = loop.time()  # start() began slightly earlier: a conservative origin
        writer.write(b"early\n")
        assert await asyncio.wait_for(reader.readline(), 5.0) == b"hello\n"
        assert loop.time() - t_start >= 0.95 * boot
        assert await ask((reader, writer), b"ping") == b"1:ping\n"  # "early" was never heard
    assert dev.events[0][1] - t_start >= 0.95 * boot


async def stalled(ep: Endpoint) -> int:
    """Wait until the line stops moving (nobody reads), then return bytes_tx."""
    last = -1
    async with asyncio.timeout(5.0):
        while last != ep.stats.bytes_tx:
            last = ep.stats.bytes_tx
            await asyncio.sleep(0.1)
    return last


@KINDS
async def test_host_not_reading_or_vanishing_does_not_hurt_the_endpoint(kind: str) -> None:
    dev = ToyDevice()
    async with make(kind, dev, baud=None) as ep:
        if isinstance(ep, TcpEndpoint):
            reader, writer = await asyncio.open_connection("127.0.0.1", ep.port)
            writer.write(b"stream 500 0\n")
            await reader.readexactly(5000)
            await stalled(ep)  # the host stops reading: TCP backpressure holds the line
            # ...then it is killed: connection reset while the server has data queued
            linger = struct.pack("ii", 1, 0)
            writer.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, linger)
            writer.close()
            with contextlib.suppress(ConnectionError):
                await writer.wait_closed()
        else:
            async with host(ep.url) as (reader, writer):
                writer.write(b"stream 500 0\n")
                await reader.readexactly(5000)
            await stalled(ep)  # nobody reads the pty: it fills up and the line stalls
        assert ep.running
        async with host(ep.url) as (reader, writer):
            writer.write(b"stop\nping\n")
            assert await until_line(reader, ECHO_RE) == b"1:ping\n"
    assert dev.frames > 10


class BrokenDevice(ToyDevice):
    def receive(self, data: bytes, now: float) -> None:
        if data.startswith(b"rx"):
            raise KeyError("receive bug")
        super().receive(data, now)

    def next_packet(self, now: float) -> bytes | None:
        if self.seq:
            raise ZeroDivisionError("next_packet bug")
        return super().next_packet(now)


@pytest.mark.parametrize(("command", "error"), [(b"rx\n", KeyError), (b"tx\n", ZeroDivisionError)])
async def test_device_bug_is_logged_and_raised_by_stop(
    command: bytes, error: type[Exception], caplog: pytest.LogCaptureFixture
) -> None:
    ep = MemoryEndpoint(BrokenDevice())
    await ep.start()
    ep.write(command)
    await asyncio.sleep(0.01)
    assert "failed" in caplog.text or "crashed" in caplog.text  # logged when it happened
    with pytest.raises(error):
        await ep.stop()
    await ep.stop()


@KINDS
async def test_stop_releases_every_fd_and_is_idempotent(kind: str) -> None:
    before = open_fds()
    ep = make(kind, ToyDevice())
    await ep.stop()  # before start: nothing to do
    ep = make(kind, ToyDevice())
    async with ep:
        async with host(ep.url) as conn:
            assert await ask(conn, b"ping") == b"1:ping\n"
        if kind == "tcp":
            async with host(ep.url) as conn:  # still connected when stop() comes
                assert await ask(conn, b"ping") == b"2:ping\n"
                host_fd = str(conn[1].transport.serial.fileno())  # type: ignore[attr-defined]
                await ep.stop()
                assert open_fds() == before | {host_fd}  # closed by now, not a step later
                assert await at_eof(conn[0])
    await ep.stop()
    assert not ep.running
    assert open_fds() == before
    with pytest.raises(RuntimeError):
        await ep.start()
