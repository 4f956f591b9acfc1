"""Byte-level transports for the device emulators: a pty, a TCP port, or memory.

An emulator is a sans-I/O :class:`Device`: it is handed bytes and asked for whole packets, always
with the event loop's time, so it runs unchanged on a virtual clock. An endpoint owns the I/O and
the timing around it:

* the line is modelled as one full-duplex UART at ``baud`` (10 bits per byte, 8N1). Device→host:
  a packet's bytes are released in small chunks as they fall due, and the device is asked for the
  next packet only when the line is idle, so packets never interleave and streams are
  line-limited. With ``whole_packets=True`` (fast mode) each packet is released in one piece at
  the moment its last byte has left the UART: the same line time and rate, only its first bytes do
  not reach the host early (a cable pulled mid-packet still delivers the bytes already sent).
  Host→device: each piece the host writes reaches the device when its last byte has crossed the
  line (after the pieces before it), so a command costs its line time before the firmware sees it;
* a line forgets: the device's output goes nowhere while no host has the port open (TCP: no
  client; pty: nobody has the slave open, seen through inotify), and a host that opens it finds
  no stale bytes;
* faults from :class:`~sdh2svc.sim.faults.FaultConfig` corrupt, drop or cut device→host bytes,
  keep the device deaf and mute while it "boots", and :meth:`Endpoint.disconnect` pulls the cable;
* the host reaches it through an ordinary pyserial URL (:attr:`Endpoint.url`): a pty slave path or
  ``socket://127.0.0.1:PORT``.

Timing uses only ``loop.time()``, ``loop.call_at`` and ``asyncio.sleep``. Host-side behaviour this
relies on is in ``docs/protocols.md`` PART 4 (transports, items 8, 11, 13).
"""

from __future__ import annotations

import asyncio
import contextlib
import ctypes
import errno
import logging
import math
import os
import socket
import struct
import termios
from abc import ABC, abstractmethod
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from types import TracebackType
from typing import Literal, Protocol, Self, runtime_checkable

from sdh2svc.protocol.line import BAUD as DEFAULT_BAUD
from sdh2svc.protocol.line import BITS_PER_BYTE
from sdh2svc.sim.faults import FaultConfig, FaultedPacket, FaultInjector, FaultKind

__all__ = [
    "BITS_PER_BYTE",
    "DEFAULT_BAUD",
    "Device",
    "Endpoint",
    "FaultConfig",
    "FaultKind",
    "LinkPacer",
    "LinkStats",
    "MemoryEndpoint",
    "PtyEndpoint",
    "TcpEndpoint",
    "make_raw",
    "serve_device",
]

logger = logging.getLogger(__name__)

_READ_SIZE = 65_536


@runtime_checkable
class Device(Protocol):
    """A byte-level device emulator, driven by an endpoint; ``now`` is the loop clock in s."""

    def connected(self, now: float) -> None:
        """A host connected (TCP accept; pty: a program opened it), after any boot delay."""

    def disconnected(self, now: float) -> None:
        """The host went away (TCP close; pty: the last program closed it; the endpoint stops)."""

    def receive(self, data: bytes, now: float) -> None:
        """Bytes from the host, in whatever pieces they arrived."""

    def next_packet(self, now: float) -> bytes | None:
        """Called only when the line is idle: the next whole packet to send, or None."""

    def next_wakeup(self, now: float) -> float | None:
        """When next_packet may have something without new input (None: only after input)."""


@dataclass(slots=True)
class LinkStats:
    """Counters of one endpoint; ``faults`` is keyed by :class:`FaultKind`."""

    bytes_tx: int = 0  # device→host bytes handed to the host's transport
    bytes_rx: int = 0  # host→device bytes handed to the device
    packets_tx: int = 0  # packets taken from the device (including cut or lost ones)
    connections: int = 0  # times the device was told connected()
    faults: Counter[str] = field(default_factory=Counter)


class _Signal:
    """:class:`asyncio.Event` for the one task that waits on it (an endpoint's transmitter):
    the same set/clear/wait semantics, without the Event's loop check and list of waiters on
    every wait (fast mode waits tens of thousands of times a run)."""

    __slots__ = ("_value", "_waiter")

    def __init__(self) -> None:
        self._value = False
        self._waiter: asyncio.Future[bool] | None = None

    def is_set(self) -> bool:
        return self._value

    def set(self) -> None:
        if not self._value:
            self._value = True
            waiter = self._waiter
            if waiter is not None and not waiter.done():
                waiter.set_result(True)

    def clear(self) -> None:
        self._value = False

    async def wait(self) -> bool:
        if self._value:
            return True
        waiter = asyncio.get_running_loop().create_future()
        self._waiter = waiter
        try:
            await waiter
            return True
        finally:
            self._waiter = None


class LinkPacer:
    """The transmit clock of one serial line (sans-I/O).

    Byte ``i`` of a packet started at ``t0`` has fully left the UART at ``t0 + (i + 1) *
    byte_time``. A packet that follows the previous one within ``max_catchup_s`` starts where that
    one ended, so back-to-back packets keep the exact line rate despite late wake-ups; after a
    longer idle gap the line starts at ``now`` (never earlier, so bytes never beat the line rate).

    Chunks are released every ``tick_s``; with ``whole_packets`` a packet is one chunk, released
    when its last byte is due.
    """

    def __init__(
        self,
        baud: int | None = DEFAULT_BAUD,
        *,
        tick_s: float = 0.001,
        max_catchup_s: float = 0.002,
        whole_packets: bool = False,
    ) -> None:
        if baud is not None and baud <= 0:
            raise ValueError("baud must be positive or None")
        self.byte_time = 0.0 if baud is None else BITS_PER_BYTE / baud
        self.tick_s = tick_s
        self.whole_packets = whole_packets
        self.max_catchup_s = max_catchup_s
        self._t0 = -math.inf
        self._size = 0
        self.free_at = -math.inf  # when the line went (or goes) idle

    def begin(self, now: float, size: int, ready: float = -math.inf) -> None:
        """Start a packet of ``size`` bytes that the device had ready at ``ready`` (if known);
        the line must be idle."""
        # Never before the line is free nor before the packet was ready; from there if that
        # was recent (a late wake-up), else now.
        start = max(self.free_at, ready)
        self._t0 = start if now - start <= self.max_catchup_s else now
        self._size = size
        self.free_at = self._t0 + size * self.byte_time

    def due(self, now: float) -> int:
        """How many bytes of the current packet have left the UART by ``now``."""
        if self.byte_time == 0.0:
            return self._size
        done = math.floor((now - self._t0) / self.byte_time + 1e-6)  # 1e-6: float noise only
        return max(0, min(self._size, done))

    def wake_at(self, now: float, sent: int) -> float:
        """When to release the next chunk: one tick on, but not before a byte is due and not
        after the packet's last byte is (with ``whole_packets``: when the last byte is)."""
        if self.whole_packets:
            return self.free_at
        next_byte = self._t0 + (sent + 1) * self.byte_time
        return min(max(now + self.tick_s, next_byte), self.free_at)

    def abort(self, now: float) -> None:
        """The rest of the packet is never sent: the line is idle from ``now``."""
        self.free_at = min(self.free_at, now)


class Endpoint(ABC):
    """Serves one :class:`Device`: pacing, faults, boot silence and connection bookkeeping.

    Subclasses provide the byte pipe (the abstract hooks) and call ``_on_rx`` with host bytes and
    ``_set_host`` on (dis)connection. An exception raised by the device is logged at once and
    re-raised by :meth:`stop`, so emulator bugs fail the test that caused them.
    """

    def __init__(
        self,
        device: Device,
        *,
        baud: int | None = DEFAULT_BAUD,
        faults: FaultConfig | None = None,
        whole_packets: bool = False,
    ) -> None:
        self.device = device
        self.faults = faults or FaultConfig()
        self.stats = LinkStats()
        self._injector = FaultInjector(self.faults, self.stats.faults)
        self._pacer = LinkPacer(baud, whole_packets=whole_packets)
        self._tx: FaultedPacket | None = None  # the packet on the line, if any
        self._tx_sent = 0  # how many of its bytes have been released
        self._tx_link = -1  # the host connection it is for
        self._loop: asyncio.AbstractEventLoop | None = None
        self._task: asyncio.Task[None] | None = None
        self._changed = _Signal()  # any state change the transmitter may be waiting for
        self._state: Literal["new", "running", "stopped"] = "new"
        self._booted = False
        self._boot_end = 0.0
        self._unplugged_until = -math.inf
        self._device_connected = False
        self._link_id = 0  # bumped whenever the host side changes; in-flight packets die with it
        self._device_error: Exception | None = None  # first exception from device.receive()
        self._rx_free_at = -math.inf  # when the host→device line is idle again
        self._poked_at = math.inf  # first change the transmitter was told of since it looked
        self._ready_at = -math.inf  # the earliest the next packet can have been ready

    # -- public API --------------------------------------------------------------------------

    @property
    @abstractmethod
    def url(self) -> str:
        """What a pyserial host opens (``serial_for_url``)."""

    @property
    def running(self) -> bool:
        return self._state == "running"

    async def start(self) -> None:
        """Open the transport and start serving (boot silence starts now)."""
        if self._state != "new":
            raise RuntimeError("an endpoint can be started once")
        self._loop = asyncio.get_running_loop()
        await self._open()
        self._state = "running"
        now = self._loop.time()
        self._boot_end = now + self.faults.boot_delay_s
        if self.faults.boot_delay_s <= 0.0:
            self._finish_boot(now)
        self._task = self._loop.create_task(self._run(), name=f"{type(self).__name__}-tx")
        self._task.add_done_callback(_log_crash)

    async def stop(self) -> None:
        """Stop serving and release every fd; idempotent. Re-raises a device exception that
        ended the transmitter."""
        if self._state != "running":
            self._state = "stopped"
            return
        self._state = "stopped"
        task, self._task = self._task, None
        try:
            if task is not None:
                task.cancel()
                await asyncio.wait([task])
        finally:
            await self._close()
            self._tell_disconnected()
        crash = None if task is None or task.cancelled() else task.exception()
        if (crash := crash or self._device_error) is not None:
            raise crash

    def set_faults(self, faults: FaultConfig) -> None:
        """From now on, inject these faults (e.g. a line that turns bad mid-run)."""
        self.faults = faults
        self._injector = FaultInjector(faults, self.stats.faults)

    def disconnect(self, duration_s: float) -> None:
        """Pull the cable for ``duration_s``: nothing gets through in either direction."""
        if not self.running:
            raise RuntimeError("endpoint is not running")
        self.stats.faults[FaultKind.DISCONNECT] += 1
        if self._pacer.whole_packets and self._tx_link == self._link_id and self._sink_ready():
            self._release_due(self._now())  # what left the UART before the cable came out
        self._unplugged_until = max(self._unplugged_until, self._now() + duration_s)
        self._unplug()
        self._poke()

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.stop()

    # -- subclass hooks ----------------------------------------------------------------------

    @abstractmethod
    async def _open(self) -> None: ...

    @abstractmethod
    async def _close(self) -> None:
        """Release every fd; when this returns they are closed."""

    @abstractmethod
    def _host_present(self) -> bool:
        """Whether anyone could be listening (TCP: a client is connected)."""

    @abstractmethod
    def _sink_ready(self) -> bool:
        """Whether the transport takes more bytes now (False applies backpressure)."""

    @abstractmethod
    def _sink_write(self, data: bytes) -> None: ...

    @abstractmethod
    def _unplug(self) -> None:
        """React to :meth:`disconnect`, after which bytes stop flowing both ways by themselves."""

    # -- shared machinery --------------------------------------------------------------------

    def _require_loop(self) -> asyncio.AbstractEventLoop:
        assert self._loop is not None, "endpoint not started"
        return self._loop

    def _now(self) -> float:
        loop = self._loop
        assert loop is not None, "endpoint not started"
        return loop.time()

    def _unplugged(self, now: float) -> bool:
        return now < self._unplugged_until

    def _poke(self) -> None:
        self._poked_at = min(self._poked_at, self._now())
        self._changed.set()

    def _finish_boot(self, now: float) -> None:
        self._booted = True
        if self._host_present():
            self._tell_connected(now)

    def _tell_connected(self, now: float) -> None:
        if self._booted and not self._device_connected:
            self._device_connected = True
            self.stats.connections += 1
            self.device.connected(now)

    def _tell_disconnected(self) -> None:
        if self._device_connected:
            self._device_connected = False
            self.device.disconnected(self._now())

    def _set_host(self, present: bool) -> None:
        """The host side changed: tell the device and abandon any packet in flight."""
        self._link_id += 1
        self._tell_disconnected()
        if present:
            self._tell_connected(self._now())
        self._poke()

    def _on_rx(self, data: bytes) -> None:
        """Bytes from the host: dropped while deaf, else faulted and handed to the device once
        they have crossed the line (their line time after the line is free)."""
        now = self._now()
        if not self._booted or self._unplugged(now):
            self.stats.faults[FaultKind.MUTED_RX_BYTE] += len(data)
            return
        data = self._injector.apply_rx(data)
        if not data:
            return
        arrive = max(now, self._rx_free_at) + len(data) * self._pacer.byte_time
        self._rx_free_at = arrive
        if arrive <= now:
            self._deliver(data)
        else:  # strictly later than the piece before, so pieces arrive in order
            self._require_loop().call_at(arrive, self._deliver, data)

    def _deliver(self, data: bytes) -> None:
        """Bytes that have crossed the line. A host that closed the port meanwhile still sent
        them (a serial port drains its output on close: SDHLibrary's last word, a power-off, is
        written just before it closes)."""
        if self._state != "running":
            return
        if self._unplugged(self._now()):  # the cable came out while they were on the way
            self.stats.faults[FaultKind.MUTED_RX_BYTE] += len(data)
            return
        self.stats.bytes_rx += len(data)
        now = self._now()
        try:
            self.device.receive(data, now)
            if not self._device_connected:  # the host has gone: what it asked for goes nowhere
                self.device.disconnected(now)
        except Exception as exc:  # keep serving; the transport callback is no place to raise
            logger.exception("device.receive() failed")
            self._device_error = self._device_error or exc
        self._poke()

    async def _run(self) -> None:
        """The transmitter: boot, then pull packets whenever the line is idle and pace them."""
        while not self._booted:
            await asyncio.sleep(self._boot_end - self._now())
            if self._now() >= self._boot_end:
                self._finish_boot(self._now())
        while True:
            self._changed.clear()  # before polling, so input arriving later wakes us
            self._poked_at = math.inf
            now = self._now()
            listening = self._host_present()
            packet = self.device.next_packet(now) if listening else None
            if packet is not None:
                await self._transmit(packet, self._ready_at)
                self._ready_at = -math.inf  # the next one may have been ready all along
                continue
            wakeup = self.device.next_wakeup(now) if listening else None
            if wakeup is not None and wakeup <= now:
                wakeup = now + self._pacer.tick_s  # "due now" yet nothing to send: don't spin
            await self._wait_change(wakeup)

    async def _wait_change(self, deadline: float | None) -> None:
        """Sleep until something changes or ``deadline``; note when that was (the next packet
        cannot have been ready earlier, so a late wake-up does not move it earlier still)."""
        loop = self._require_loop()
        timer = None if deadline is None else loop.call_at(deadline, self._changed.set)
        try:
            await self._changed.wait()
        finally:
            if timer is not None:
                timer.cancel()
        self._ready_at = min(self._poked_at, math.inf if deadline is None else deadline)

    async def _transmit(self, packet: bytes, ready: float) -> None:
        out = self._injector.apply_tx(packet)
        self.stats.packets_tx += 1
        link = self._link_id
        self._pacer.begin(self._now(), len(out), ready)
        self._tx, self._tx_sent, self._tx_link = out, 0, link
        waited, size = False, len(out)
        try:
            while self._tx_sent < size:
                await self._until_writable(link)
                now = self._now()
                if link != self._link_id:
                    self._pacer.abort(now)
                    return
                self._release_due(now)
                if self._tx_sent < size:
                    await asyncio.sleep(self._pacer.wake_at(now, self._tx_sent) - now)
                    waited = True
        finally:
            self._tx = None
        if not waited:  # let the host run between packets (a paced packet has waited its line
            await asyncio.sleep(0)  # time, and the host cannot answer within the same instant)

    def _release_due(self, now: float) -> None:
        """Hand the host the bytes of the packet on the line that have left the UART by now."""
        out, sent = self._tx, self._tx_sent
        if out is None:
            return
        due = self._pacer.due(now)
        if due > sent:
            self._tx_sent = due
            self._emit(out, sent, due, now)

    async def _until_writable(self, link: int) -> None:
        while link == self._link_id and not (self._unplugged(self._now()) or self._sink_ready()):
            self._changed.clear()
            await self._changed.wait()

    def _emit(self, out: FaultedPacket, start: int, stop: int, now: float) -> None:
        data = out.slice(start, stop)
        if not data:
            return
        if self._unplugged(now):
            self.stats.faults[FaultKind.UNPLUGGED_TX_BYTE] += len(data)
            return
        self.stats.bytes_tx += len(data)
        self._sink_write(data)


def _log_crash(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and (exc := task.exception()) is not None:
        logger.error("device transmitter crashed", exc_info=exc)


# -- pty ---------------------------------------------------------------------------------------


def make_raw(fd: int, baud: int | None = DEFAULT_BAUD) -> None:
    """Raw 8N1 like cfmakeraw(3): no echo, no CR/LF mapping, 8 bits kept (ISTRIP off)."""
    iflag, oflag, cflag, lflag, ispeed, _ospeed, cc = termios.tcgetattr(fd)
    iflag &= ~(
        termios.IGNBRK | termios.BRKINT | termios.PARMRK | termios.ISTRIP
        | termios.INLCR | termios.IGNCR | termios.ICRNL | termios.IXON | termios.IXOFF
    )  # fmt: skip
    oflag &= ~termios.OPOST
    lflag &= ~(termios.ECHO | termios.ECHONL | termios.ICANON | termios.ISIG | termios.IEXTEN)
    cflag &= ~(termios.CSIZE | termios.PARENB | termios.CSTOPB)
    cflag |= termios.CS8 | termios.CREAD | termios.CLOCAL
    speed = getattr(termios, f"B{baud}", ispeed) if baud else ispeed  # cosmetic on a pty
    cc[termios.VMIN], cc[termios.VTIME] = 1, 0
    termios.tcsetattr(fd, termios.TCSANOW, [iflag, oflag, cflag, lflag, speed, speed, cc])


class PtyEndpoint(Endpoint):
    """Serves the device on a fresh pty; the host opens :attr:`path`.

    The endpoint keeps its own slave fd open for its whole life, so master reads never fail with
    EIO between hosts and a host's HUPCL does not hang up the line. It watches the slave's device
    node (inotify: opens and last closes) to know whether a host has it open: the device is
    "connected" while one has, and otherwise its output goes nowhere and whatever the last host
    left unread is flushed, as on a serial port nobody reads — the next host finds no stale
    bytes. Where inotify is missing the device is connected from start to stop and unread output
    queues in the pty until it is full, after which the line stalls (backpressure).
    """

    def __init__(
        self, device: Device, *, baud: int | None = DEFAULT_BAUD, faults: FaultConfig | None = None
    ) -> None:
        super().__init__(device, baud=baud, faults=faults)
        self._baud = baud
        self._master = -1
        self._slave = -1
        self._path = ""
        self._pending = bytearray()  # written by the line, not yet taken by the pty
        self._writer_armed = False
        self._watch: _OpenWatch | None = None  # opens of the slave by hosts (None: can't tell)
        self._opens = 0

    @property
    def path(self) -> str:
        """The pty slave device, e.g. ``/dev/pts/5``."""
        return self._path

    @property
    def url(self) -> str:
        return self._path

    async def _open(self) -> None:
        master, slave = os.openpty()
        try:
            make_raw(slave, self._baud)
            os.set_blocking(master, False)
            self._path = os.ttyname(slave)
        except BaseException:
            os.close(master)
            os.close(slave)
            raise
        self._master, self._slave = master, slave
        self._watch = _OpenWatch.create(self._path)
        if self._watch is not None:
            self._require_loop().add_reader(self._watch.fd, self._on_watch)
        self._require_loop().add_reader(master, self._on_readable)

    async def _close(self) -> None:
        loop = self._require_loop()
        loop.remove_reader(self._master)
        if self._watch is not None:
            loop.remove_reader(self._watch.fd)
            self._watch.close()
            self._watch = None
        self._arm_writer(False)
        self._pending.clear()
        os.close(self._master)
        os.close(self._slave)
        self._master = self._slave = -1

    @property
    def host_open(self) -> bool:
        """Whether a host has the slave open (always True where that can't be seen)."""
        return self._watch is None or self._opens > 0

    def _host_present(self) -> bool:
        return self.host_open

    def _on_watch(self) -> None:
        """Opens and last closes of the slave: (dis)connect the device, forget unread bytes."""
        assert self._watch is not None
        for delta in self._watch.read():
            was = self._opens > 0
            self._opens = max(0, self._opens + delta)
            if (self._opens > 0) != was:
                self._forget()
                self._set_host(not was)

    def _forget(self) -> None:
        """Drop what the device sent that no host has read (a serial port keeps nothing)."""
        self._pending.clear()
        self._arm_writer(False)
        with contextlib.suppress(termios.error):
            termios.tcflush(self._slave, termios.TCIFLUSH)

    def _sink_ready(self) -> bool:
        return not self._pending

    def _unplug(self) -> None:
        """Nothing to do: a serial device can't tell its cable was pulled."""

    def _sink_write(self, data: bytes) -> None:
        self._pending += data
        self._flush()

    def _on_readable(self) -> None:
        if self._watch is not None:
            self._on_watch()  # a host that opened and wrote at once: connect it first
        try:
            data = os.read(self._master, _READ_SIZE)
        except (BlockingIOError, InterruptedError):
            return
        except OSError as exc:  # EIO would mean no slave fd is open; ours always is
            logger.debug("pty read failed: %s", exc)
            return
        if data:
            self._on_rx(data)

    def _flush(self) -> None:
        try:
            while self._pending:
                del self._pending[: os.write(self._master, self._pending)]
        except (BlockingIOError, InterruptedError):
            self._arm_writer(True)  # the pty is full: resume when it drains
            return
        except OSError as exc:  # e.g. EIO: the bytes are gone, as on a dead line
            logger.debug("pty write failed, %d bytes lost: %s", len(self._pending), exc)
            self._pending.clear()
        self._arm_writer(False)
        self._poke()

    def _arm_writer(self, on: bool) -> None:
        if on and not self._writer_armed:
            self._require_loop().add_writer(self._master, self._flush)
        elif not on and self._writer_armed:
            self._require_loop().remove_writer(self._master)
        self._writer_armed = on


class _OpenWatch:
    """Counts opens and last closes of a device node through Linux's inotify (ctypes: the
    standard library has no binding). :meth:`read` yields +1 per open, −1 per close."""

    _IN_CLOSE_WRITE, _IN_CLOSE_NOWRITE, _IN_OPEN, _IN_Q_OVERFLOW = 0x08, 0x10, 0x20, 0x4000
    _EVENT = struct.Struct("iIII")  # wd, mask, cookie, len (then len bytes of name)

    def __init__(self, fd: int) -> None:
        self.fd = fd

    @classmethod
    def create(cls, path: str) -> _OpenWatch | None:
        """A watch on ``path``, or None where inotify is unavailable."""
        try:
            libc = ctypes.CDLL(None, use_errno=True)
            fd = libc.inotify_init1(os.O_NONBLOCK | os.O_CLOEXEC)
        except (OSError, AttributeError):
            return None
        if fd < 0:
            return None
        mask = cls._IN_OPEN | cls._IN_CLOSE_WRITE | cls._IN_CLOSE_NOWRITE
        if libc.inotify_add_watch(fd, os.fsencode(path), mask) < 0:
            os.close(fd)
            return None
        return cls(fd)

    def read(self) -> list[int]:
        try:
            buf = os.read(self.fd, 4096)
        except (BlockingIOError, InterruptedError):
            return []
        out, pos = [], 0
        while pos + self._EVENT.size <= len(buf):
            _wd, mask, _cookie, size = self._EVENT.unpack_from(buf, pos)
            pos += self._EVENT.size + size
            if mask & self._IN_OPEN:
                out.append(1)
            if mask & (self._IN_CLOSE_WRITE | self._IN_CLOSE_NOWRITE):
                out.append(-1)
            if mask & self._IN_Q_OVERFLOW:
                logger.warning("pty open/close events lost; host presence may be wrong")
        return out

    def close(self) -> None:
        os.close(self.fd)


# -- TCP ---------------------------------------------------------------------------------------


class _TcpConnection(asyncio.Protocol):
    """One accepted host connection; forwards everything to its :class:`TcpEndpoint`."""

    def __init__(self, endpoint: TcpEndpoint) -> None:
        self.endpoint = endpoint
        self.transport: asyncio.Transport | None = None
        self.paused = False
        self.closed = endpoint._require_loop().create_future()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self.transport = transport
        self.endpoint._accepted(self)

    def data_received(self, data: bytes) -> None:
        self.endpoint._received(self, data)

    def connection_lost(self, exc: Exception | None) -> None:
        if not self.closed.done():
            self.closed.set_result(None)
        self.endpoint._lost(self)

    def pause_writing(self) -> None:
        self.paused = True

    def resume_writing(self) -> None:
        self.paused = False
        self.endpoint._poke()

    def setsockopt(self, option: int | None) -> None:
        """Set a boolean TCP option, if this platform has it."""
        sock = self.transport.get_extra_info("socket") if self.transport else None
        if option is not None and sock is not None:
            with contextlib.suppress(OSError):
                sock.setsockopt(socket.IPPROTO_TCP, option, 1)


class TcpEndpoint(Endpoint):
    """Serves the device on a TCP port; the host opens :attr:`url` (``socket://host:port``).

    One host at a time, sequentially, device state kept across connections. A new connection
    while one is open replaces it (the old one is aborted and the device sees disconnected() then
    connected()): a killed or hung host must not lock the next run out, and a real host never
    keeps two. During :meth:`disconnect` the client is aborted and new connections are accepted
    and closed at once, so the host sees the line go dead and cannot get back in.
    """

    _tcp = True  # TCP options apply (not on a Unix socket, where setting them only fails)

    def __init__(
        self,
        device: Device,
        *,
        host: str = "127.0.0.1",
        port: int = 0,
        baud: int | None = DEFAULT_BAUD,
        faults: FaultConfig | None = None,
        whole_packets: bool = False,
    ) -> None:
        super().__init__(device, baud=baud, faults=faults, whole_packets=whole_packets)
        self.host = host
        self._port = port
        self._server: asyncio.Server | None = None
        self._client: _TcpConnection | None = None
        self._conns: set[_TcpConnection] = set()

    @property
    def port(self) -> int:
        """The bound port (the ephemeral one when created with ``port=0``), after start()."""
        return self._port

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"socket://{host}:{self._port}"

    async def _open(self) -> None:
        loop = self._require_loop()
        self._server = await loop.create_server(lambda: _TcpConnection(self), self.host, self._port)
        if not self._server.sockets:  # asyncio skips an address whose socket() failed (EMFILE)
            self._server.close()
            raise OSError(errno.EMFILE, f"no socket for TCP port {self._port} (too many open "
                          "files?)")  # fmt: skip
        self._port = self._server.sockets[0].getsockname()[1]

    async def _close(self) -> None:
        assert self._server is not None
        self._server.close()
        self._client = None
        conns = list(self._conns)
        for conn in conns:
            if conn.transport is not None:
                conn.transport.abort()
        # abort() closes the socket one loop step later; wait so stop() really frees the fds.
        await asyncio.gather(*(c.closed for c in conns))
        await self._server.wait_closed()

    def _host_present(self) -> bool:
        return self._client is not None

    def _sink_ready(self) -> bool:
        return self._client is not None and not self._client.paused

    def _sink_write(self, data: bytes) -> None:
        assert self._client is not None and self._client.transport is not None
        if not self._client.transport.is_closing():
            self._client.transport.write(data)

    def _unplug(self) -> None:
        self._drop_client()

    def _drop_client(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            assert client.transport is not None
            client.transport.abort()
            self._set_host(False)

    def _accepted(self, conn: _TcpConnection) -> None:
        self._conns.add(conn)
        assert conn.transport is not None
        if not self.running or self._unplugged(self._now()):
            conn.transport.abort()  # refused: stopping, or the cable is out
            return
        if self._client is not None:  # said, not silent: a second program on the "line"
            logger.warning("%s: a new host connected; the one connected before is dropped (one "
                           "host at a time, as on a serial line)", self.url)  # fmt: skip
        self._drop_client()
        self._client = conn
        if self._tcp:
            conn.setsockopt(socket.TCP_NODELAY)
            conn.setsockopt(getattr(socket, "TCP_QUICKACK", None))
        self._set_host(True)

    def _received(self, conn: _TcpConnection, data: bytes) -> None:
        if conn is not self._client:
            return
        # Linux drops out of quick-ACK mode by itself; re-arm it so a host that sends a command
        # and its "\r\n" in two segments (Nagle on) is not held up by our delayed ACK.
        if self._tcp:
            conn.setsockopt(getattr(socket, "TCP_QUICKACK", None))
        self._on_rx(data)

    def _lost(self, conn: _TcpConnection) -> None:
        self._conns.discard(conn)
        if conn is self._client:
            self._client = None
            self._set_host(False)


class UnixEndpoint(TcpEndpoint):
    """Serves the device on a Unix-domain socket; the host opens :attr:`url` (``unix:///path``,
    see :mod:`sdh2svc.bus.urlhandlers`). The kernel delivers its bytes synchronously, so it is
    the transport of fast mode (virtual clock); otherwise it behaves as :class:`TcpEndpoint`."""

    _tcp = False

    def __init__(
        self,
        device: Device,
        path: str,
        *,
        baud: int | None = DEFAULT_BAUD,
        faults: FaultConfig | None = None,
        whole_packets: bool = False,
    ) -> None:
        super().__init__(device, baud=baud, faults=faults, whole_packets=whole_packets)
        self.path = path

    @property
    def url(self) -> str:
        return f"unix://{self.path}"

    async def _open(self) -> None:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)  # a stale socket file of an earlier run
        loop = self._require_loop()
        self._server = await loop.create_unix_server(lambda: _TcpConnection(self), self.path)

    async def _close(self) -> None:
        await super()._close()
        with contextlib.suppress(FileNotFoundError):
            os.unlink(self.path)


# -- memory ------------------------------------------------------------------------------------


class MemoryEndpoint(Endpoint):
    """An in-process host for emulator tests: :meth:`write` sends host bytes, device output
    collects in :attr:`output` (and goes to ``on_output(data, now)`` if given). Pacing and faults
    work as on a pty, so on a virtual-clock loop a test can check exact line timing."""

    def __init__(
        self,
        device: Device,
        *,
        baud: int | None = DEFAULT_BAUD,
        faults: FaultConfig | None = None,
        on_output: Callable[[bytes, float], None] | None = None,
        whole_packets: bool = False,
    ) -> None:
        super().__init__(device, baud=baud, faults=faults, whole_packets=whole_packets)
        self.output = bytearray()
        self._on_output = on_output

    @property
    def url(self) -> str:
        return "memory://"

    def write(self, data: bytes) -> None:
        """Host→device bytes (as if the host wrote them to the line now)."""
        self._on_rx(data)

    async def _open(self) -> None:
        pass

    async def _close(self) -> None:
        pass

    def _host_present(self) -> bool:
        return True

    def _sink_ready(self) -> bool:
        return True

    def _unplug(self) -> None:
        """Nothing to do: like a pty, the device can't tell."""

    def _sink_write(self, data: bytes) -> None:
        self.output += data
        if self._on_output is not None:
            self._on_output(data, self._now())


def serve_device(
    device: Device,
    kind: Literal["pty", "tcp", "memory"] = "pty",
    *,
    baud: int | None = DEFAULT_BAUD,
    faults: FaultConfig | None = None,
    host: str = "127.0.0.1",
    port: int = 0,
) -> Endpoint:
    """An unstarted endpoint of the given kind: ``async with serve_device(dev, "tcp") as ep``."""
    if kind == "pty":
        return PtyEndpoint(device, baud=baud, faults=faults)
    if kind == "tcp":
        return TcpEndpoint(device, host=host, port=port, baud=baud, faults=faults)
    if kind == "memory":
        return MemoryEndpoint(device, baud=baud, faults=faults)
    raise ValueError(f"unknown endpoint kind {kind!r}")
