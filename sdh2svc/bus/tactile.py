"""asyncio driver of the DSACON32m tactile-controller line (protocols.md PART 1, PART 4).

Six tactile pads share one 115200-baud RS-232 line (11 520 bytes/s). :class:`TactileBus` opens
it the way SDHLibrary does (§1.6, PART 4 items 8-9), then owns the line: one reader task parses
every byte with :mod:`sdh2svc.protocol.dsa`, one scheduler task decides what the controller is
asked to send, and a supervisor reconnects after a lost port or a run of errors (§1.7).

Subscribers (:meth:`TactileBus.subscribe`) declare the matrices and the rate they need. Every
frame carries all six matrices (the protocol has no per-matrix request), so the line has to carry
the highest rate any subscriber asked for, and each subscription holds only the newest frame.

Which frames the controller is asked for, when and why (idle, push or pull, at what rate) is
decided in :mod:`sdh2svc.bus.acquisition`, sans-I/O; the choice is re-evaluated whenever a
subscription opens or closes and every 0.5 s. ``bus.stats`` reports the mode, frames/s, bytes/s,
line utilisation = bytes/s × 10 / baud, and the estimates.

Faults: the parser never raises; bad CRCs, oversized headers and undecodable frames are dropped
and counted, a read timeout flushes the parser, commands are retried. The line is reopened (with
back-off, :func:`~sdh2svc.bus.reconnect.reconnect`, rerunning the open sequence and the acquisition
mode) when the port is lost, after more than ``max_error_streak`` errors in a row with no good
packet for ``min_dead_s``, or when nothing good arrives for ``stall_s`` beyond the expected frame
gap. Events (:class:`~sdh2svc.bus.reconnect.LinkEvent`, the type both links share: ``connected``,
``lost``, ``reconnected``, ``crc_error``, …) go to every subscription's queue and to listeners.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import deque
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Final, Self, TypeVar

import numpy as np
import numpy.typing as npt
import serial

from sdh2svc.bus.acquisition import (
    RATE_WINDOW_S,
    REPLAN_S,
    LineEstimates,
    Mode,
    RateMeter,
    choose_mode,
    line_verdict,
    next_pull,
    push_framerate,
)
from sdh2svc.bus.link import close_streams, open_streams
from sdh2svc.bus.reconnect import (
    LINE_DOWN,
    LINE_UP,
    Backoff,
    LinkEvent,
    LinkEventKind,
    RepeatedFailures,
    failure_after,
    reconnect,
)
from sdh2svc.protocol import dsa
from sdh2svc.protocol.line import BAUD

__all__ = [
    "FrameTimeout",
    "LinkEvent",
    "LinkEventKind",
    "Mode",
    "Subscription",
    "SubscriptionClosed",
    "TactileBus",
    "TactileCommandError",
    "TactileConnectionError",
    "TactileError",
    "TactileFrame",
    "TactileOptions",
    "TactileStats",
    "TactileTimeoutError",
]

logger = logging.getLogger(__name__)
_T = TypeVar("_T")
_A = TypeVar("_A")

_STOP = dsa.configure_acquisition(acquire=False, framerate=0)


class TactileError(Exception):
    """Base of the driver's errors."""


class TactileConnectionError(TactileError):
    """The line is down (or went down while a command waited)."""


class HandUnlike(TactileError):
    """The controller reports other matrices than those expected (``TactileOptions.expect``)."""


class TactileTimeoutError(TactileError, TimeoutError):
    """A command got no reply after all its tries."""


class TactileCommandError(TactileError):
    """The controller answered a command with a non-zero error code."""

    def __init__(self, command: str, code: int) -> None:
        try:
            name = dsa.DsaError(code).name
        except ValueError:  # a code the protocol does not define (`in` raises on 3.11)
            name = str(code)
        super().__init__(f"{command}: controller error {name}")
        self.code = code


class FrameTimeout(TactileError, TimeoutError):
    """No new frame within the subscriber's limit."""


class _Garbled(TactileError):
    """The reply being waited for arrived broken (bad CRC, or cut off): send the command again."""


class SubscriptionClosed(TactileError):
    """The subscription (or its bus) was closed."""


@dataclass(frozen=True, slots=True)
class TactileOptions:
    """Timing and policy knobs; the defaults follow SDHLibrary where it has a value."""

    baud: int = BAUD
    open_tries: int = 3  # stop + ACK tries through the 8 s boot (PART 4 item 8)
    open_timeout_s: float = 3.0
    flush_first_s: float = 1.0  # silence before the first byte ends the open flush (item 9)
    flush_gap_s: float = 0.02  # ...and between later bytes (1 ms in SDHLibrary; pty/TCP jitter)
    read_timeout_s: float = 0.1  # a silent line for this long flushes a partial packet
    command_timeout_s: float = 0.5  # a reply waits behind one frame at most (≤ 86 ms)
    command_tries: int = 3
    open_query_tries: int = 8  # infos are 12-60 bytes: a noisy line garbles many (retries are fast)
    frame_timeout_s: float = 0.5  # pull: frame after its ACK; subscribers: beyond 1/rate
    max_error_streak: int = 8  # "> 8 in a row" as SDHLibrary's updater
    min_dead_s: float = 0.5  # ...and no good packet for this long
    stall_s: float = 1.5  # nothing good beyond the expected frame gap → reconnect
    silent_s: float = 0.25  # ...→ silent meanwhile: shown down, runs refused (before a run's
    #                         stale-frame fault at 0.3 s, so a run faulted by it is not restarted)
    reconnect: bool = True
    backoff_initial_s: float = 0.25
    backoff_max_s: float = 4.0
    push_cap_fps: float = 30.0  # "highest possible rate (for now: 30 FPS)", §1.6
    rle: bool = True
    events_maxlen: int = 256
    # the matrices the controller must report, in wire order: (name, rows, cols) each; a
    # controller that reports others is refused at every open (empty: any)
    expect: tuple[tuple[str, int, int], ...] = ()
    # the texel pitch the configuration computes with (mm): a controller reporting another is
    # said at open, not refused (what the device reports is unconfirmed, protocols.md §1.4.3)
    pitch_mm: float | None = None


PITCH_TOLERANCE_MM: Final = 0.05  # a reported texel pitch within this of the configured one


def _pitch_unlike(mats: Sequence[dsa.MatrixInfo], pitch_mm: float) -> str:
    """The matrices whose reported texel size is not the configured pitch ("": none)."""
    odd = [f"matrix {i}: {m.texel_width:g} × {m.texel_height:g} mm"
           for i, m in enumerate(mats)
           if max(abs(m.texel_width - pitch_mm), abs(m.texel_height - pitch_mm))
           > PITCH_TOLERANCE_MM]  # fmt: skip
    return "; ".join(odd)


def _unlike(mats: Sequence[dsa.MatrixInfo], expect: Sequence[tuple[str, int, int]]) -> str:
    """How the controller's matrices differ from those expected ("": they do not)."""
    if len(mats) != len(expect):
        return (f"the controller reports {len(mats)} tactile matrices, the configuration "
                f"expects {len(expect)}")  # fmt: skip
    return "; ".join(
        f"matrix {i} ({name}) is {m.cells_y} × {m.cells_x} cells on the controller, "
        f"{rows} × {cols} in the configuration"
        for i, (m, (name, rows, cols)) in enumerate(zip(mats, expect, strict=True))
        if m.shape != (rows, cols)
    )


@dataclass(frozen=True, slots=True, eq=False)
class TactileFrame:
    """One decoded frame as delivered: CRC-checked and expanded to exactly nb_cells texels."""

    seq: int  # bus-wide counter of delivered frames (strictly increasing)
    timestamp_ms: int  # controller clock
    texels: npt.NDArray[np.uint16]  # flat, read-only, wire order
    matrices: tuple[npt.NDArray[np.uint16], ...]  # (cells_y, cells_x) views per matrix
    arrival: float  # loop time when its last byte was parsed
    wire_bytes: int

    def age(self, now: float | None = None) -> float:
        """Seconds since arrival."""
        t = asyncio.get_running_loop().time() if now is None else now
        return t - self.arrival


_OPENED = "port open, no answer yet from the DSACON32m (it answers ≈ 8 s after power-on)"


def _opened(failure: str) -> str:
    """Why a line that was down is not up yet once its port opened: the open sequence waits for
    the controller (through its boot), and the last failure, a refused or missing port, is past."""
    before = failure.removeprefix(f"{_OPENED}; before: ")
    return f"{_OPENED}; before: {before}"


@dataclass(frozen=True, slots=True)
class TactileStats:
    mode: Mode
    required_hz: float
    frames: int
    frames_per_s: float
    bytes_per_s: float
    line_utilisation_pct: float
    frame_age_ms: float  # age of the newest frame (from arrival); inf before the first
    frame_bytes: float  # EWMA of the wire size of a frame
    push_fps_estimate: float
    pull_max_hz: float
    crc_errors: int
    oversized: int
    bad_frames: int
    garbage_bytes: int
    resyncs: int
    timeouts: int
    unexpected_replies: int  # late replies to commands that had already timed out
    reconnects: int
    connected: bool
    silent: bool  # connected, but a stream runs and no good packet came (TactileBus.silent)


class Subscription:
    """A subscriber's view: the newest frame only (a slot + an event), and the bus events."""

    def __init__(self, bus: TactileBus, matrices: frozenset[int], rate_hz: float) -> None:
        self.bus = bus
        self.matrices = matrices
        self.rate_hz = rate_hz
        self.events: asyncio.Queue[LinkEvent] = asyncio.Queue(bus.options.events_maxlen)
        self._slot: TactileFrame | None = None
        self._last_seq = -1
        self._ready = asyncio.Event()
        self._closed = False

    @property
    def latest(self) -> TactileFrame | None:
        """The newest frame delivered to this subscription (taken or not)."""
        return self._slot

    async def next_frame(self, timeout: float | None = None) -> TactileFrame:
        """The newest frame, newer than the last one returned; never the same one twice.

        Raises :class:`FrameTimeout` if none arrives within ``timeout`` (default: the bus's
        ``frame_timeout_s`` beyond this subscription's period).
        """
        if timeout is None:
            timeout = self.bus.options.frame_timeout_s + 1.0 / self.rate_hz
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout
        while True:
            frame = self._slot
            if frame is not None and frame.seq > self._last_seq:
                self._last_seq = frame.seq
                return frame
            if self._closed:
                raise SubscriptionClosed("subscription closed")
            self._ready.clear()
            try:
                async with asyncio.timeout_at(deadline):
                    await self._ready.wait()
            except TimeoutError:
                raise FrameTimeout(f"no tactile frame for {timeout:.3f} s") from None

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self._ready.set()
            self.bus._unsubscribe(self)

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _offer(self, frame: TactileFrame) -> None:
        self._slot = frame
        self._ready.set()

    def _event(self, event: LinkEvent) -> None:
        if self.events.full():  # drop the oldest: recent events matter more
            self.events.get_nowait()
        self.events.put_nowait(event)


class TactileBus:
    """The DSACON32m line: open sequence, acquisition scheduling, commands, reconnects."""

    def __init__(self, url: str, options: TactileOptions | None = None) -> None:
        self.url = url
        self.options = options or TactileOptions()
        self.controller_info: dsa.ControllerInfo | None = None
        self.sensor_info: dsa.SensorInfo | None = None
        self.matrix_infos: tuple[dsa.MatrixInfo, ...] = ()
        self._loop = asyncio.get_running_loop()
        self._parser = dsa.PacketParser()
        self._subs: set[Subscription] = set()
        self._listeners: list[Callable[[LinkEvent], None]] = []
        self._frame_listeners: list[Callable[[TactileFrame], None]] = []
        self.history: deque[LinkEvent] = deque(maxlen=self.options.events_maxlen)
        self.failure: str | None = None  # why the line went down, until it is back up
        self._repeats = RepeatedFailures()  # its failed reopenings, logged quietly when alike
        # connection state
        self._writer: asyncio.StreamWriter | None = None
        self._reader_task: asyncio.Task[None] | None = None
        self._sched_task: asyncio.Task[None] | None = None
        self._supervisor: asyncio.Task[None] | None = None
        self._lost = asyncio.Event()
        self._lost_reason = ""
        self._connected = asyncio.Event()
        self._opening = True
        self._discarding = False
        self._opening_rx = 0  # bytes received while opening…
        self._heard_dsacon = False  # …and whether any of them was a DSACON32m packet
        self._closed = False
        self._cmd_lock = asyncio.Lock()
        self._waiter: tuple[int, asyncio.Future[bytes]] | None = None
        self._rx_pulse = asyncio.Event()
        self._frame_pulse = asyncio.Event()
        self._replan = asyncio.Event()
        # measurements
        self._mode = Mode.IDLE
        self._active_since = 0.0
        self._last_good = 0.0
        self._last_rx = 0.0
        self._error_streak = 0
        self._line = LineEstimates(self.options.baud, self.options.push_cap_fps)
        self._byte_meter = RateMeter(self._loop.time())
        self._frame_meter = RateMeter(self._loop.time())
        self._last_frame: TactileFrame | None = None
        self._seq = 0
        self._bad_frames = 0
        self._timeouts = 0
        self._reconnects = 0
        self._unexpected = 0
        self._errors = 0  # every error event so far

    # -- public API --------------------------------------------------------------------------

    @classmethod
    async def open(
        cls, url: str, options: TactileOptions | None = None, *, patient: bool = False
    ) -> TactileBus:
        """Open ``url`` (device path or pyserial URL) and run the SDHLibrary open sequence — or,
        ``patient``, do so in the background as a lost line reconnects (now, then after each
        back-off delay, every failure reported) until the controller answers."""
        bus = cls(url, options)
        if patient:
            bus._supervisor = bus._loop.create_task(bus._first_connection(), name="tactile-connect")
            return bus
        try:
            await bus._establish()
        except TactileError as e:  # which line it was: a lab plugs in two
            kind = HandUnlike if isinstance(e, HandUnlike) else TactileError
            raise kind(f"tactile line {url}: {e}") from e
        bus._emit(LinkEventKind.CONNECTED, url)
        bus._supervisor = bus._loop.create_task(bus._supervise(), name="tactile-supervisor")
        return bus

    async def close(self) -> None:
        """Stop acquisition (errors ignored, as SDHLibrary) and close the port; idempotent."""
        if self._closed:
            return
        self._closed = True
        await _cancel(self._supervisor)
        await _cancel(self._sched_task)
        if self._writer is not None and not self._lost.is_set():
            with contextlib.suppress(TactileError):
                await self._request(_STOP, timeout=0.5, tries=1)
        await self._teardown()
        for sub in list(self._subs):
            sub.close()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def nb_cells(self) -> int:
        return sum(m.nb_cells for m in self.matrix_infos)

    @property
    def mode(self) -> Mode:
        return self._mode

    @property
    def connected(self) -> bool:
        return self._connected.is_set()

    @property
    def silent(self) -> bool:
        """The port is open but a stream runs and nothing good came for ``silent_s`` beyond its
        frame gap: a held or stalled line (the reconnect waits for ``stall_s``). Idle, the line
        owes nothing, so it is never silent then."""
        if not self.connected or self._opening or self._mode is Mode.IDLE:
            return False
        return self._quiet_s(self._loop.time()) >= self.options.silent_s + self._expected_gap()

    def subscribe(self, matrices: Iterable[int], rate_hz: float) -> Subscription:
        """Ask for ``matrices`` at ``rate_hz``; the scheduler adapts the line at once.

        Every frame carries all six matrices (``frame.matrices[m]``): the protocol cannot ask for
        fewer, so ``matrices`` only declares (and validates) what this subscriber reads.
        """
        mats = frozenset(matrices)
        n = len(self.matrix_infos) or len(self.options.expect)  # (expected: not open yet)
        if not mats or (n and not mats <= set(range(n))):
            raise ValueError(f"matrices must be a non-empty subset of 0…{n - 1}")
        if not rate_hz > 0.0:
            raise ValueError(f"rate_hz must be > 0, got {rate_hz!r}")
        if self._closed:
            raise TactileConnectionError("bus closed")
        sub = Subscription(self, mats, float(rate_hz))
        self._subs.add(sub)
        self._replan.set()
        return sub

    def add_listener(self, callback: Callable[[LinkEvent], None]) -> None:
        """Call ``callback`` for every bus event (synchronously, from the reader task)."""
        self._listeners.append(callback)

    def add_frame_listener(self, callback: Callable[[TactileFrame], None]) -> None:
        """Call ``callback`` for every delivered frame (recorders: they must see all of them)."""
        self._frame_listeners.append(callback)

    async def set_sensitivity(
        self, matrix: int, value: float, *, persistent: bool = False, all_matrices: bool = False
    ) -> None:
        """0x0F; persistent writes get no reply (firmware bug, PART 4 item 15): not awaited."""
        cmd = dsa.set_sensitivity(matrix, value, persistent=persistent, all_matrices=all_matrices)
        await self._write_command(cmd, "set_sensitivity", reply=not persistent)

    async def get_sensitivity(self, matrix: int) -> dsa.SensitivityInfo:
        return await self._query(dsa.get_sensitivity_info(matrix), dsa.SensitivityInfo.decode)

    async def set_threshold(
        self, matrix: int, value: int, *, persistent: bool = False, all_matrices: bool = False
    ) -> None:
        """0x13; persistent writes get no reply, as for sensitivity."""
        self._require_threshold()
        cmd = dsa.set_threshold(matrix, value, persistent=persistent, all_matrices=all_matrices)
        await self._write_command(cmd, "set_threshold", reply=not persistent)

    async def get_threshold(self, matrix: int) -> int:
        self._require_threshold()
        info = await self._query(dsa.get_threshold(matrix), dsa.ThresholdInfo.decode)
        return info.threshold

    @property
    def _streams_on_pull(self) -> bool:
        """The controller streams on a pull request (:func:`dsa.single_frame_bug`)."""
        ci = self.controller_info
        return ci is not None and dsa.single_frame_bug(ci.sw_version)

    def _require_threshold(self) -> None:
        """SDHLibrary refuses 0x13/0x14 below firmware R268 (:data:`dsa.THRESHOLD_SINCE`)."""
        ci = self.controller_info
        if ci is not None and ci.sw_version < dsa.THRESHOLD_SINCE:
            raise TactileError(f"DSACON32m firmware R{ci.sw_version} has no matrix threshold "
                               f"(R{dsa.THRESHOLD_SINCE} or later)")  # fmt: skip

    @property
    def stats(self) -> TactileStats:
        now = self._loop.time()
        p = self._parser
        bps = self._byte_meter.rate(now)
        last = self._last_frame
        return TactileStats(
            mode=self._mode,
            required_hz=self._required_hz(),
            frames=self._seq,
            frames_per_s=self._frame_meter.rate(now),
            bytes_per_s=bps,
            line_utilisation_pct=self._line.line_utilisation_pct(bps),
            frame_age_ms=math.inf if last is None else 1000.0 * (now - last.arrival),
            frame_bytes=self._line.frame_bytes,
            push_fps_estimate=self._line.push_fps(),
            pull_max_hz=self._line.pull_max_hz(),
            crc_errors=p.crc_errors,
            oversized=p.oversized,
            bad_frames=self._bad_frames,
            garbage_bytes=p.garbage_bytes,
            resyncs=p.resyncs,
            timeouts=self._timeouts,
            unexpected_replies=self._unexpected,
            reconnects=self._reconnects,
            connected=self.connected,
            silent=self.silent,
        )

    # -- connection lifecycle ----------------------------------------------------------------

    async def _establish(self) -> None:
        """Connect, start reading, run the open sequence, start the scheduler."""
        try:
            reader, writer = await open_streams(self.url, baudrate=self.options.baud)
        except (OSError, serial.SerialException, ValueError) as exc:  # no port, no such URL…
            raise TactileConnectionError(f"cannot open: {exc}") from exc
        if self.failure is not None:  # the port is open now: why it was down is no longer so
            self.failure = _opened(self.failure)
        self._writer = writer
        self._lost.clear()
        self._opening = True
        self._opening_rx, self._heard_dsacon = 0, False
        self._reader_task = self._loop.create_task(self._read_loop(reader), name="tactile-rx")
        self._reader_task.add_done_callback(self._task_done)
        try:
            await self._open_sequence()
        except TactileTimeoutError as exc:
            await self._teardown()
            if self._opening_rx and not self._heard_dsacon:  # answers, but not a DSACON32m's
                raise TactileTimeoutError(
                    f"{exc}; {self._opening_rx} bytes came back, none of them a DSACON32m "
                    "packet: another device on this port (the SDH2's joint line, if the two "
                    "lines are swapped?), or a line at another baud rate"
                ) from exc
            raise
        except BaseException:
            await self._teardown()
            raise
        self._opening = False
        self._connected.set()
        self._mode = Mode.IDLE
        self._sched_task = self._loop.create_task(self._schedule(), name="tactile-scheduler")
        self._sched_task.add_done_callback(self._task_done)

    async def _open_sequence(self) -> None:
        """Stop + ACK (through the boot), flush, then 0x01, 0x02, 0x0B per matrix (§1.6)."""
        o = self.options
        for _ in range(o.open_tries):
            with contextlib.suppress(TactileTimeoutError):
                await self._request(_STOP, timeout=o.open_timeout_s, tries=1)
                break
        # After the last failed try SDHLibrary carries on regardless (PART 4 item 8).
        await self._flush_input()
        n = o.open_query_tries
        ci = await self._query(dsa.query_controller_info(), dsa.ControllerInfo.decode, n)
        si = await self._query(dsa.query_sensor_info(), dsa.SensorInfo.decode, n)
        mats = tuple(
            [
                await self._query(dsa.query_matrix_info(m), dsa.MatrixInfo.decode, n)
                for m in range(si.nb_matrices)
            ]
        )
        if self.matrix_infos and [m.shape for m in mats] != [m.shape for m in self.matrix_infos]:
            raise TactileError("matrix geometry changed across a reconnect")
        if o.expect and (unlike := _unlike(mats, o.expect)):
            raise HandUnlike(unlike)
        if o.pitch_mm is not None and (odd := _pitch_unlike(mats, o.pitch_mm)):
            logger.warning("%s: the controller reports texels of another size than the "
                           "configuration's tactile.texel_pitch_mm = %g mm (%s): S, the contact "
                           "areas and the forces are computed with %g mm; set it to what the "
                           "pads are if the report is right", self.url, o.pitch_mm, odd,
                           o.pitch_mm)  # fmt: skip
        self.controller_info, self.sensor_info, self.matrix_infos = ci, si, mats

    async def _flush_input(self) -> None:
        """Discard input until ``flush_first_s`` of silence, or ``flush_gap_s`` after a byte."""
        o = self.options
        self._discarding = True
        self._parser.flush()  # stale partial packets are not errors
        try:
            deadline = self._loop.time() + o.flush_first_s
            while (remaining := deadline - self._loop.time()) > 0:
                self._rx_pulse.clear()
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(remaining):
                        await self._rx_pulse.wait()
                    deadline = self._last_rx + o.flush_gap_s
        finally:
            self._discarding = False

    async def _supervise(self) -> None:
        """Wait for a loss, tear down, reconnect with back-off; report each step."""
        o = self.options
        backoff = Backoff(o.backoff_initial_s, o.backoff_max_s)
        while True:
            await self._lost.wait()
            await self._teardown()
            self._emit(LinkEventKind.LOST, self._lost_reason)
            if not o.reconnect:
                return
            await reconnect(self._establish, backoff, self._reconnect_failed)
            self._reconnects += 1
            self._emit(LinkEventKind.RECONNECTED, self.url)

    async def _first_connection(self) -> None:
        o = self.options
        await reconnect(self._establish, Backoff(o.backoff_initial_s, o.backoff_max_s),
                        self._reconnect_failed, at_once=True)  # fmt: skip
        self._emit(LinkEventKind.CONNECTED, self.url)
        await self._supervise()

    def _reconnect_failed(self, exc: Exception) -> None:
        self._emit(LinkEventKind.RECONNECT_FAILED, str(exc) or type(exc).__name__)

    def _task_done(self, task: asyncio.Task[None]) -> None:
        """A crashed reader or scheduler is a bug: log it and start over on a new connection."""
        if not task.cancelled() and (exc := task.exception()) is not None:
            logger.error("%s crashed", task.get_name(), exc_info=exc)
            self._mark_lost(f"{task.get_name()} crashed: {exc!r}")

    def _mark_lost(self, reason: str) -> None:
        if not self._lost.is_set():
            self._lost_reason = reason
            self._lost.set()
            self._connected.clear()
            self._fail_waiter(TactileConnectionError(reason))

    async def _teardown(self) -> None:
        self._connected.clear()
        await _cancel(self._sched_task)
        await _cancel(self._reader_task)
        self._sched_task = self._reader_task = None
        self._fail_waiter(TactileConnectionError("connection closed"))
        writer, self._writer = self._writer, None
        if writer is not None:
            await close_streams(writer)
        self._set_mode(Mode.IDLE)

    # -- reading -----------------------------------------------------------------------------

    async def _read_loop(self, reader: asyncio.StreamReader) -> None:
        try:
            while True:
                try:
                    async with asyncio.timeout(self.options.read_timeout_s):
                        data = await reader.read(4096)
                except TimeoutError:
                    self._on_read_timeout()
                    continue
                if not data:
                    raise EOFError("end of stream")
                self._on_bytes(data)
        except (OSError, EOFError, serial.SerialException) as exc:
            self._mark_lost(f"read failed: {exc!r}")

    def _on_bytes(self, data: bytes) -> None:
        now = self._loop.time()
        self._last_rx = now
        self._rx_pulse.set()
        self._byte_meter.add(now, len(data))
        if not self._discarding:  # (what the flush discards may be boot noise: not counted)
            if self._opening:
                self._opening_rx += len(data)
            self._dispatch(self._parser.feed(data), now)
        self._check_health(now)

    def _on_read_timeout(self) -> None:
        """Silence: whatever partial packet is buffered will never complete."""
        now = self._loop.time()
        if self._parser.buffered:
            self._dispatch(self._parser.flush(), now)
            self._error(LinkEventKind.TIMEOUT, "partial packet abandoned", now)
            self._fail_waiter(_Garbled("reply cut off"))  # nothing else is coming: retry now
        self._check_health(now)

    def _dispatch(self, events: list[dsa.Event], now: float) -> None:
        for ev in events:
            if self._opening and isinstance(ev, dsa.Packet | dsa.BadCrc | dsa.Oversized):
                self._heard_dsacon = True  # a preamble: a DSACON32m speaks on this line
            match ev:
                case dsa.Packet(id=dsa.PacketId.FULL_FRAME):
                    self._on_frame(ev.payload, now)
                case dsa.Packet():
                    self._on_reply(ev)
                case dsa.BadCrc():
                    self._error(LinkEventKind.CRC_ERROR, f"id {ev.id:#04x} len {ev.length}", now)
                    if self._waiter is not None and self._waiter[0] == ev.id:
                        self._fail_waiter(_Garbled("reply failed its CRC"))
                case dsa.Oversized():
                    self._error(LinkEventKind.OVERSIZED, f"id {ev.id:#04x} len {ev.length}", now)
                case dsa.GarbageSkipped() if not self._opening:
                    self._emit(LinkEventKind.RESYNC, f"{ev.nbytes} bytes skipped", now)
                case _:  # boot noise, or garbage of a stale stream while opening
                    pass

    def _on_frame(self, payload: bytes, now: float) -> None:
        if self._opening:  # a stale push stream before our stop's ACK (§1.7): not ours
            return
        try:
            frame = dsa.decode_frame_payload(payload, self.nb_cells)
        except dsa.FrameError as exc:
            self._bad_frames += 1
            self._error(LinkEventKind.BAD_FRAME, str(exc), now)
            return
        self._good(now)
        size = len(payload) + 8
        self._line.frame(size)
        self._frame_meter.add(now, 1)
        self._seq += 1
        matrices = tuple(dsa.split_matrices(frame.texels, self.matrix_infos))
        tf = TactileFrame(self._seq, frame.timestamp_ms, frame.texels, matrices, now, size)
        self._last_frame = tf
        for callback in self._frame_listeners:
            _call(callback, tf)
        for sub in self._subs:
            sub._offer(tf)
        self._frame_pulse.set()

    def _on_reply(self, packet: dsa.Packet) -> None:
        self._good(self._loop.time())
        waiter = self._waiter
        if waiter is not None and waiter[0] == packet.id and not waiter[1].done():
            waiter[1].set_result(packet.payload)
        else:
            self._unexpected += 1  # e.g. a late reply to a command that timed out

    def _good(self, now: float) -> None:
        self._last_good = now
        self._error_streak = 0

    def _error(self, kind: LinkEventKind, detail: str, now: float) -> None:
        self._error_streak += 1
        self._errors += 1
        self._frame_pulse.set()  # a pull cycle waiting for its frame may have just lost it
        self._emit(kind, detail, now)

    def _check_health(self, now: float) -> None:
        """Reconnect on a run of errors or a stalled stream (SDHLibrary's updater, §1.7)."""
        if self._opening or self._lost.is_set():
            return
        o = self.options
        why = line_verdict(
            error_streak=self._error_streak,
            max_error_streak=o.max_error_streak,
            quiet_s=self._quiet_s(now),
            min_dead_s=o.min_dead_s,
            stall_s=o.stall_s,
            expected_gap_s=None if self._mode is Mode.IDLE else self._expected_gap(),
        )
        if why is not None:
            self._mark_lost(why)

    def _quiet_s(self, now: float) -> float:
        """How long nothing good has come since the present mode began."""
        return now - max(self._last_good, self._active_since)

    def _expected_gap(self) -> float:
        rate = self._line.push_fps() if self._mode is Mode.PUSH else self._required_hz()
        return 1.0 / rate if rate > 0 else 0.0

    # -- commands ----------------------------------------------------------------------------

    async def _write(self, data: bytes) -> None:
        writer = self._writer
        if writer is None or self._lost.is_set():
            raise TactileConnectionError("not connected")
        try:
            writer.write(data)
            await writer.drain()
        except (OSError, serial.SerialException) as exc:
            self._mark_lost(f"write failed: {exc!r}")
            raise TactileConnectionError(str(exc)) from exc

    async def _request(
        self, command: bytes, *, timeout: float | None = None, tries: int | None = None
    ) -> bytes:
        """Send ``command`` and return the payload of the reply with its ID; frames arriving
        meanwhile are still delivered. Retries on a timeout or a host-CRC error reply."""
        pid = command[3]
        timeout = self.options.command_timeout_s if timeout is None else timeout
        tries = self.options.command_tries if tries is None else tries
        async with self._cmd_lock:
            for _ in range(tries):
                future: asyncio.Future[bytes] = self._loop.create_future()
                self._waiter = (pid, future)
                try:
                    await self._write(command)
                    async with asyncio.timeout(timeout):
                        payload = await future
                except TimeoutError:
                    self._timeouts += 1
                    self._error(LinkEventKind.TIMEOUT, f"no reply to {pid:#04x}", self._loop.time())
                    continue
                except _Garbled:
                    continue  # counted as the CRC error / partial packet it was
                finally:
                    self._waiter = None
                if _error_code(payload) == dsa.DsaError.E_CHECKSUM_ERROR:
                    continue  # our command was garbled on the way: send it again
                return payload
        raise TactileTimeoutError(f"no reply to command {pid:#04x} after {tries} tries")

    async def _query(
        self, command: bytes, decode: Callable[[bytes], _T], tries: int | None = None
    ) -> _T:
        """A request whose reply is decoded; an error reply raises :class:`TactileError`."""
        payload = await self._request(command, tries=tries)
        code = _error_code(payload)
        if code != dsa.DsaError.E_SUCCESS:
            raise TactileCommandError(f"command {command[3]:#04x}", code)
        try:
            return decode(payload)
        except dsa.ProtocolError as exc:
            raise TactileError(f"reply to {command[3]:#04x}: {exc}") from exc

    async def _write_command(self, command: bytes, name: str, *, reply: bool) -> None:
        if not reply:
            async with self._cmd_lock:
                await self._write(command)
            return
        code = _error_code(await self._request(command))
        if code != dsa.DsaError.E_SUCCESS:
            raise TactileCommandError(name, code)

    def _fail_waiter(self, exc: Exception) -> None:
        if self._waiter is not None and not (waiter := self._waiter[1]).done():
            waiter.set_exception(exc)
            # marked as seen: a pull's ACK is not always awaited (its frame is the answer),
            # and asyncio would log the unawaited failure as "never retrieved", an ERROR
            waiter.exception()

    # -- scheduling --------------------------------------------------------------------------

    def _required_hz(self) -> float:
        return max((s.rate_hz for s in self._subs), default=0.0)

    def _measure_push(self) -> None:
        """What the stream really delivers, once a whole rate window lies inside push mode."""
        now = self._loop.time()
        if self._mode is Mode.PUSH and now - self._active_since >= RATE_WINDOW_S:
            self._line.push_achieved = self._frame_meter.rate(now)

    def _set_mode(self, mode: Mode) -> None:
        if mode is not self._mode:
            self._mode = mode
            self._active_since = self._loop.time()
            self._emit(LinkEventKind.MODE, mode.value)

    async def _schedule(self) -> None:
        """Per connection: pick the mode, then run pull cycles or watch the push stream."""
        due = self._loop.time()
        push_rate = 0
        while True:
            required = self._required_hz()
            want = choose_mode(
                required,
                push_fps=self._line.push_fps(),
                pull_max_hz=self._line.pull_max_hz(),
                current=self._mode,
            )
            try:
                if want is Mode.PUSH:
                    rate = push_framerate(required)
                    if self._mode is not Mode.PUSH or rate != push_rate:
                        await self._configure(acquire=True, framerate=rate)
                        push_rate = rate
                        self._set_mode(Mode.PUSH)
                    await self._wait_replan(REPLAN_S)
                    self._measure_push()
                elif want is Mode.PULL:
                    if self._mode is Mode.PUSH:
                        await self._configure(acquire=False, framerate=0)
                    self._set_mode(Mode.PULL)
                    due = await self._pull_cycle(due, 1.0 / required)
                else:
                    if self._mode is not Mode.IDLE:
                        await self._configure(acquire=False, framerate=0)
                        self._set_mode(Mode.IDLE)
                    await self._wait_replan(None)
            except TactileCommandError as exc:  # the controller refused: retry a little later
                logger.warning("tactile acquisition command refused: %s", exc)
                await self._wait_replan(REPLAN_S)
            except TactileTimeoutError:
                pass  # counted; the health check decides whether to reconnect
            except TactileConnectionError:
                return  # the supervisor tears this connection down and starts a new one

    async def _configure(self, *, acquire: bool, framerate: int) -> None:
        cmd = dsa.configure_acquisition(acquire=acquire, framerate=framerate, rle=self.options.rle)
        code = _error_code(await self._request(cmd))
        if code != dsa.DsaError.E_SUCCESS:
            raise TactileCommandError("configure acquisition", code)

    async def _pull_cycle(self, due: float, period: float) -> float:
        """Wait for ``due``, request one frame and wait for it; return the next due time.

        The command lock is held until the frame is in (other commands would be answered after
        it anyway). The frame itself proves the request arrived, so a lost ACK costs nothing.
        """
        if await self._wait_replan(due - self._loop.time()):
            return due  # subscriptions changed: re-plan before requesting
        cmd = dsa.configure_acquisition(acquire=True, framerate=0, rle=self.options.rle)
        seq, errors, t0 = self._seq, self._errors, self._loop.time()
        async with self._cmd_lock:
            ack: asyncio.Future[bytes] = self._loop.create_future()
            self._waiter = (dsa.PacketId.CONFIGURE_DATA_ACQUISITION, ack)
            try:
                await self._write(cmd)
                o = self.options
                await self._await_frame(
                    seq, errors, ack, t0 + o.command_timeout_s + o.frame_timeout_s
                )
            finally:
                self._waiter = None
        if self._streams_on_pull:  # old firmware streams instead: stop it, as SDHLibrary does
            await self._configure(acquire=False, framerate=0)
        code = _ack_code(ack)
        now = self._loop.time()
        if code == dsa.DsaError.E_CHECKSUM_ERROR:
            return now  # the request was garbled on its way: send it again
        if code not in (None, dsa.DsaError.E_SUCCESS):
            raise TactileCommandError("pull request", code)
        if self._seq == seq:
            if self._errors == errors:  # plain silence, not a garbled frame
                self._timeouts += 1
                self._error(LinkEventKind.TIMEOUT, "no frame for a pull request", now)
            return now
        if code is not None and self._errors == errors:  # clean cycles measure the line
            self._line.pull_cycle(now - t0)
        return next_pull(due, period, now)

    async def _await_frame(
        self, seq: int, errors: int, ack: asyncio.Future[bytes], deadline: float
    ) -> None:
        """Until a frame newer than ``seq`` arrives, evidently came broken, or ``deadline``."""
        quiet = self.options.read_timeout_s
        while self._seq == seq:
            now = self._loop.time()
            remaining = deadline - now
            if self._errors != errors:
                # Something came broken. If the ACK was good, or the line has gone quiet, it was
                # our frame: nothing more is coming.
                if _ack_code(ack) is not None or now - self._last_rx >= quiet:
                    return
                remaining = min(remaining, self._last_rx + quiet - now)
            if remaining <= 0:
                return
            self._frame_pulse.clear()
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(remaining):
                    await self._frame_pulse.wait()

    async def _wait_replan(self, timeout: float | None) -> bool:
        """Sleep up to ``timeout`` (None: forever); True if subscriptions changed meanwhile."""
        if self._replan.is_set():
            self._replan.clear()
            return True
        if timeout is not None and timeout <= 0:
            return False
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout):
                await self._replan.wait()
        changed = self._replan.is_set()
        self._replan.clear()
        return changed

    def _unsubscribe(self, sub: Subscription) -> None:
        self._subs.discard(sub)
        self._replan.set()

    # -- events ------------------------------------------------------------------------------

    def _emit(self, kind: LinkEventKind, detail: str = "", now: float | None = None) -> None:
        event = LinkEvent(kind, self.url, self._loop.time() if now is None else now, detail)
        self.history.append(event)
        self.failure = failure_after(kind, detail, self.failure)
        if kind in LINE_DOWN or kind in LINE_UP:  # the line's life, logged as the joint line's
            level, more = self._repeats.level(kind, detail, event.time, kind in LINE_DOWN)
            logger.log(level, "tactile line %s %s %s%s", self.url, kind, detail, more)
        for sub in self._subs:
            sub._event(event)
        for callback in self._listeners:
            _call(callback, event)


def _call(callback: Callable[[_A], None], arg: _A) -> None:
    """Run a listener; its bugs are logged, never allowed to stop the reader."""
    try:
        callback(arg)
    except Exception:
        logger.exception("tactile listener %r failed", callback)


def _ack_code(ack: asyncio.Future[bytes]) -> int | None:
    """The error code of a received ACK; None if it never came or came garbled."""
    if not ack.done() or ack.cancelled() or ack.exception() is not None:
        return None
    return _error_code(ack.result())


def _error_code(payload: bytes) -> int:
    """The leading u16 error code of a reply (every reply starts with one, §1.3)."""
    return int.from_bytes(payload[:2], "little") if len(payload) >= 2 else dsa.DsaError.E_CMD_FAILED


async def _cancel(task: asyncio.Task[None] | None) -> None:
    """Cancel ``task`` and wait for it to finish (without swallowing our own cancellation)."""
    if task is None or task is asyncio.current_task():
        return
    task.cancel()
    await asyncio.wait([task])
