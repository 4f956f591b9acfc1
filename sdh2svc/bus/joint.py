"""Asyncio driver of the SDH2 joint-controller line (protocols.md PART 2, PART 4).

:class:`JointLink` owns one line (a device path or any pyserial URL: a pty, ``socket://``, …) and
speaks to it through the sans-I/O codec :mod:`sdh2svc.protocol.sdh` only. What it adds is the
I/O policy of SCHUNK's SDHLibrary, plus what a service needs around it:

* Connect handshake (§2.3, §2.8): ``" \\r\\n"``, discard 100 ms of input, ``ver`` with a 1 s
  timeout, then ``vlim``, ``alim`` and ``con`` — and then, our addition, :meth:`JointLink.hold`'s
  sequence: the firmware keeps its last velocity or move forever (§2.4), so on every connect and
  reconnect the link first stops whatever the previous host (or a dead process) left running;
  a ``selgrip``/``grip`` move, which ``stop`` does not end, is ended by ``con=0``, or by
  powering its axes off (:meth:`JointLink._end_grips`).
* One command in flight at a time, each with a timeout. Replies are correlated by keyword (ASCII)
  or command code (binary). An ``E<n>`` line or a non-zero binary status raises
  :class:`FirmwareError`, after up to ``retries`` retries for axis commands (as SDHLibrary does).
  Garbage, a mismatched reply or a timeout cause a resync (:data:`RESYNC` blank lines, drain until
  the line is quiet, parser reset) and a retry — but first, if anything since the last hold could
  have started motion, a ``stop`` (our addition: a bad line must not let the hand move on while
  the retries take their time). :attr:`JointLink.stats` counts all of it. Our additions: a
  first attempt's reply must begin within :data:`REPLY_START_S` (or three of the line's recent
  round trips), a message must not stop for :data:`BYTE_GAP_S`, so a lost or broken reply is
  retried at once rather than after its timeout; and a reply to an exchange given up, arriving
  during a later one, is skipped there (``_Conn.owed``).
* ASCII by default; ``binary=True`` sends the 11 commands SDHLibrary-CPP sends in binary (§2.6),
  with CRC on serial lines and without over ``socket://`` (PART 4 item 1; ``binary_crc``).
* Targets outside the joint limits are refused with ``ValueError`` before any byte is written.
* :meth:`JointLink.emergency_stop` is SCHUNK's e-stop (power off, read actual, write it back as
  targets, §2.4) with precedence: commands queued behind it fail with :class:`EmergencyStopped`,
  the attempt in flight finishes first, and the command it belongs to (a hold's too) gives way
  before its next attempt, resync or retry's stop. Our addition: the stop *latches* — until
  :meth:`release`, commands that could move the hand (any set form except power-off, and
  ``m``) are refused with :class:`EmergencyStopped`, because ``m`` re-enables unpowered axes
  (PART 4 item 5); and a power-off the hand did not confirm (a silent line) is sent again,
  before anything else, as soon as the line answers.
* A line that fell silent and answers again may have a hand behind it that was switched off and
  on (or another hand, behind an adapter that stayed plugged in): once the command sequence
  that got the answer has run (an e-stop's whole sequence, say), the link drops that connection
  and reconnects at once, so the handshake identifies and holds the hand anew (our addition;
  a link opened with ``reconnect=False`` goes on on the same connection instead).
* Reconnect: when the port is lost (exception or EOF) the link reopens it with back-off
  (:func:`sdh2svc.bus.reconnect.reconnect`: 0.5, 1, 2, 4, 5, 5 … s) and reruns the handshake;
  meanwhile commands raise :class:`LinkLost`. :class:`LinkEvent` values (the type both links
  share) go to an optional callback and to :meth:`JointLink.subscribe` queues.
* The newest actual angles (:attr:`JointLink.reading`, with their arrival time) come from every
  ``pos``/``tpap`` answer; :meth:`JointLink.start_polling` keeps them fresh, so a control loop
  takes them (:meth:`JointLink.take_reading`) without a round trip. While it takes them in a
  rhythm, one ``pos`` is answered just before each iteration is due and none goes out between an
  iteration's start and its target command (:mod:`sdh2svc.bus.polling`); otherwise a ``pos``
  follows every other command and, with nothing else sent, goes out every ``idle_s``. A poll
  waits its turn like any command (never ahead of one queued first); an e-stop still goes first.

Angles are degrees, velocities deg/s, accelerations deg/s² at this edge (as on the wire).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import re
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from functools import partial
from numbers import Real
from types import TracebackType
from typing import Final, Self, TypeAlias

import serial

from sdh2svc.bus.link import PushReader, close_streams, is_socket_url, open_streams
from sdh2svc.bus.polling import PollPlan
from sdh2svc.bus.reconnect import (
    Backoff,
    LinkEvent,
    LinkEventKind,
    RepeatedFailures,
    failure_after,
    reconnect,
)
from sdh2svc.model.hand import HAND_VELOCITY_LIMIT_DEG_S
from sdh2svc.protocol.dsa import PREAMBLE as DSACON_PREAMBLE
from sdh2svc.protocol.sdh import (
    ASCII_COMMANDS,
    BINARY_COMMANDS,
    COMMAND_SINCE,
    NUM_AXES,
    RESYNC,
    ArgForm,
    AxisState,
    BinaryCommand,
    BinaryReply,
    DebugLine,
    ErrorLine,
    Garbage,
    Reply,
    ReplyEvent,
    ReplyParser,
    SdhError,
    encode_ascii,
    encode_binary_request,
    encode_blank,
    firmware_release,
)

__all__ = [
    "DEFAULT_LIMITS",
    "ControllerMode",
    "EmergencyStopped",
    "FirmwareError",
    "JointLink",
    "JointLinkError",
    "JointReading",
    "JointStats",
    "LinkEvent",
    "LinkEventKind",
    "LinkLost",
]

logger = logging.getLogger(__name__)

Vec: TypeAlias = tuple[float, ...]
Limits: TypeAlias = Sequence[tuple[float, float]]

DEFAULT_LIMITS: Final[tuple[tuple[float, float], ...]] = ((0.0, 90.0),) + ((-90.0, 90.0),) * 6
"""Joint ranges in degrees, axis 0 first (§2.2)."""

CONNECT_DRAIN_S: Final = 0.1  # §2.3: discard whatever arrives within 100 ms of the blank line
VER_TIMEOUT_S: Final = 1.0  # §2.3: no `ver` reply within 1 s means "SDH not connected"
BACKOFF: Final = Backoff(initial_s=0.5, max_s=5.0)  # before each attempt to reopen the line
POLL_IDLE_S: Final = 0.05  # polling with no command to follow: the angles are read this often
# A message that stops for this long is broken off (a flipped length byte, a lost line end): the
# SDH2 sends a reply in one burst (≤ 6 ms at 115200 baud), a USB adapter in 16 ms packets
BYTE_GAP_S: Final = 0.1
# A reply not begun by then is lost (a command the line spoilt on its way, a reply lost whole),
# and the command's retry goes at once, with the whole timeout, instead of one second of joint
# angles growing old under a control loop: every command but `ref` answers at once (§2.4), its
# first byte due within a few ms plus a USB adapter's 16 ms latency twice. A line slower than
# that (a serial server on a network) stretches it: RTT_MARGIN × its slowest recent round trip
REPLY_START_S: Final = 0.1
RTT_MARGIN: Final = 3.0
STALL_GRACE_S: Final = 0.05  # a lost reply's wait once more, past a stall of this process
RTTS_KEPT: Final = 16
_ANSWERS_LATE: Final = frozenset({"ref"})  # answers when its moves end (SDHLibrary waits 10 s)
OWED_KEPT: Final = 4  # replies still owed to given-up exchanges that are remembered
HEARD_KEPT: Final = 256  # a connection's first bytes kept, to tell another device by them
_NUM_TEMPS: Final = 9  # 7 motors, FPGA, PCB (§2.2)
_VERSION: Final = re.compile(r"\d+(\.\d+){1,4}")  # the firmware's, as ver answers it
BINARY_SINCE: Final = (0, 0, 2, 15)  # the first firmware with the binary frames (protocols §2.6)
# What SDHLibrary-CPP takes on firmware older than `vlim`, `con` and `alim`
# (protocol.sdh.COMMAND_SINCE): its fixed limits (the velocities: model.hand's) and the pose
# controller (sdh/sdh.cpp: GetAxisLimitVelocity, GetAxisLimitAcceleration, GetController)
OLD_VELOCITY_LIMITS: Final = HAND_VELOCITY_LIMIT_DEG_S
OLD_ACCELERATION_LIMITS: Final = (5000.0, 400.0, 1500.0, 400.0, 1500.0, 400.0, 1500.0)
_WARNINGS: Final = frozenset({LinkEventKind.ERROR, LinkEventKind.RECONNECT_FAILED})
_TARGET_COMMANDS: Final = frozenset({"p", "tpap"})  # set forms are limit-checked
# The firmware could not read a command this link encoded from its table: the line spoilt it on
# the way (a flipped bit, a lost byte), so it is retried as a spoilt reply is
_SPOILT_ON_THE_LINE: Final = frozenset({
    SdhError.CHECKSUM_ERROR, SdhError.NOT_ENOUGH_PARAMS, SdhError.NO_PARAMS_EXPECTED,
    SdhError.CMD_UNKNOWN, SdhError.CMD_FORMAT_ERROR, SdhError.MAX_COMMANDLINE_EXCEEDED,
    SdhError.CRC_ERROR,
})  # fmt: skip


# -- errors, events, statistics -----------------------------------------------------------------


class JointLinkError(Exception):
    """Anything that keeps a joint-controller command from succeeding."""


class FirmwareError(JointLinkError):
    """The firmware answered ``E<n>`` or a binary reply with non-zero status (§2.5)."""

    def __init__(self, code: int, command: str = "") -> None:
        self.code = code
        self.error = SdhError(code) if 0 <= code <= max(SdhError) else None
        self.name = self.error.name if self.error is not None else f"E{code}"
        self.command = command
        super().__init__(f"{command or 'command'}: firmware error {code} ({self.name})")


class HandRefused(JointLinkError):
    """The hand answered, but is not the one this host can drive (``accept`` said why)."""

    def __init__(self, problems: Sequence[str]) -> None:
        super().__init__("; ".join(problems))
        self.problems = list(problems)


class LinkLost(JointLinkError):
    """The port is gone (or closed); a reconnect may be under way."""


class AnsweredAgain(LinkLost):
    """A silent line answered again: the connection is dropped, so that the reconnect's
    handshake identifies the hand anew (it may have been switched off and on meanwhile)."""


class EmergencyStopped(JointLinkError):
    """Refused or cancelled because of an emergency stop (call ``release()`` to resume)."""


class ControllerMode(IntEnum):
    """Values of ``con`` (§2.4)."""

    POSE = 0
    VELOCITY = 1
    VELOCITY_ACCELERATION = 2


@dataclass(slots=True)
class JointStats:
    """Counters since construction (handshakes included)."""

    commands: int = 0  # transactions started
    timeouts: int = 0  # attempts without a reply in time
    errors: int = 0  # firmware errors (E<n>, non-zero binary status)
    garbled: int = 0  # attempts spoilt by garbage or a reply to something else
    retries: int = 0
    resyncs: int = 0
    failures: int = 0  # commands that raised after their retries
    link_losses: int = 0
    reconnects: int = 0
    motion_stops: int = 0  # `stop`s sent before a retry because the hand might be moving
    rtt_count: int = 0
    rtt_min_s: float = math.inf
    rtt_max_s: float = 0.0
    rtt_last_s: float = math.nan

    def record_rtt(self, seconds: float) -> None:
        self.rtt_count += 1
        self.rtt_min_s = min(self.rtt_min_s, seconds)
        self.rtt_max_s = max(self.rtt_max_s, seconds)
        self.rtt_last_s = seconds


@dataclass(frozen=True, slots=True)
class JointReading:
    """Actual joint angles (deg, wire axis order) and the loop time their answer arrived."""

    angles: Vec
    at: float

    def age(self, now: float | None = None) -> float:
        """Seconds since arrival."""
        return (asyncio.get_running_loop().time() if now is None else now) - self.at


class _Garbled(Exception):
    """An attempt's reply was unusable; resync and retry."""


@dataclass(frozen=True, slots=True)
class _Lost:
    """Queue sentinel: the connection died."""

    exc: BaseException


# -- one request ----------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Request:
    keyword: str  # lower case
    data: bytes  # exactly what goes on the line
    axis: int | None
    binary: BinaryCommand | None
    retry_on_error: bool  # axis commands: SDHLibrary retries after E<n>
    moves: bool  # refused while an emergency stop is latched
    n_values: int | None  # reply value count, when known
    check: Callable[[Vec], bool] | None = None  # plausibility of the reply values
    from_table: bool = False  # encoded from the command table: the firmware can read it

    @property
    def label(self) -> str:
        return self.keyword if self.axis is None else f"{self.keyword}({self.axis})"


def _as_values(values: float | Sequence[float] | None) -> Vec | None:
    if values is None:
        return None
    if isinstance(values, (float, Real)):
        return (float(values),)
    return tuple(float(v) for v in values)


def _may_move(keyword: str, values: Vec | None) -> bool:
    if keyword == "m":
        return True
    if values is None:
        return False
    return not (keyword == "power" and not any(values))  # powering off is always allowed


def _is_flags(allowed: frozenset[int]) -> Callable[[Vec], bool]:
    return lambda vals: all(v in allowed for v in vals)


_ECHOED: Final = frozenset({"p", "v", "a", "con", "power", "vp"})  # `kw=x` answers `KW=x`
_ACTUAL_ANGLES: Final = frozenset({"pos", "tpap"})
_READ_MARGIN_DEG: Final = 2.0  # plausibility margin of an actual-angle reading
_ECHO_TOL: Final = 0.01  # the wire carries 3 decimals


def _echoes(sent: Vec) -> Callable[[Vec], bool]:
    """The firmware took what we sent: a set command's echo (a flipped digit on the way to the
    hand would otherwise set a wrong target, and the next `m` would go there)."""
    return lambda got: (
        len(got) == len(sent)
        and all(abs(g - v) <= _ECHO_TOL for g, v in zip(got, sent, strict=True))
    )


_REPLY_CHECKS: Final[dict[str, Callable[[Vec], bool]]] = {
    "power": _is_flags(frozenset({0, 1})),
    "state": _is_flags(frozenset(int(s) for s in AxisState)),
    "con": _is_flags(frozenset(int(m) for m in ControllerMode)),
}


# -- one open port --------------------------------------------------------------------------------


class _Conn:
    """An open port: a reader task feeding the reply parser into an event queue."""

    def __init__(
        self,
        reader: asyncio.StreamReader,
        writer: asyncio.StreamWriter,
        parser: ReplyParser,
        on_lost: Callable[[_Conn, BaseException], None],
    ) -> None:
        self.writer = writer
        self.parser = parser
        self.events: asyncio.Queue[ReplyEvent | _Lost] = asyncio.Queue()
        self.rx_bytes = 0
        self.heard = bytearray()
        self._gap: asyncio.TimerHandle | None = None  # the rest of a message is due by then
        self.on_bytes: Callable[[], object] | None = None  # called once, at the next bytes
        self.dirty = False  # the line may hold leftovers of an unfinished exchange
        # the replies still owed to exchanges given up (timed out, spoilt): one that comes late,
        # during a later exchange, is skipped there, not taken for that one's reply spoilt
        self.owed: deque[str | BinaryCommand] = deque(maxlen=OWED_KEPT)
        self.lost: BaseException | None = None
        self._closing = False
        self._reader = reader
        self._on_lost = on_lost
        self._task: asyncio.Task[None] | None = None
        if isinstance(reader, PushReader):  # replies parsed as they arrive, no task between
            reader.push_to(self._received, self._ended)
        else:
            self._task = asyncio.get_running_loop().create_task(self._pump(), name="sdh-joint-rx")

    def _received(self, data: bytes) -> None:
        if self._closing:
            return
        try:
            self._feed(data)
        except Exception as exc:  # as the reading task would: the connection ends
            self.die(exc)

    def _feed(self, data: bytes) -> None:
        if self.rx_bytes < HEARD_KEPT:  # the first bytes, to tell what answers (_handshake)
            self.heard += data[: HEARD_KEPT - self.rx_bytes]
        self.rx_bytes += len(data)
        if self.on_bytes is not None:
            began, self.on_bytes = self.on_bytes, None
            began()
        for event in self.parser.feed(data):
            self.events.put_nowait(event)
        if self._gap is not None or self.parser.buffered:
            self._watch_gap()

    def _watch_gap(self) -> None:
        """A message left unfinished must go on within :data:`BYTE_GAP_S`, else it is broken off
        and reported as garbage at once: the command's retry need not wait for its reply's
        timeout (a second of joint angles growing old under a control loop)."""
        if self._gap is not None:
            self._gap.cancel()
            self._gap = None
        if self.parser.buffered:
            self._gap = asyncio.get_running_loop().call_later(BYTE_GAP_S, self._broken_off)

    def _broken_off(self) -> None:
        self._gap = None
        held = self.parser.flush()
        if held and self.lost is None and not self._closing:
            why = f"a message broken off after {len(held)} bytes (then {BYTE_GAP_S:g} s of nothing)"
            self.events.put_nowait(Garbage(held, why))

    def _ended(self, exc: BaseException | None) -> None:
        if not self._closing:
            self.die(exc if exc is not None else ConnectionResetError("end of stream"))

    async def _pump(self) -> None:
        try:
            while True:
                data = await self._reader.read(4096)
                if not data:
                    raise ConnectionResetError("end of stream")
                self._feed(data)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # serial/socket errors end the connection
            self.die(exc)

    def die(self, exc: BaseException) -> None:
        """The connection ends (its port is closed by the owner's ``on_lost``)."""
        if self.lost is None:
            self.lost = exc
            self.events.put_nowait(_Lost(exc))
            self._on_lost(self, exc)

    async def send(self, data: bytes) -> None:
        if self.lost is not None:
            raise LinkLost(f"joint line lost: {self.lost}")
        try:
            self.writer.write(data)
            await self.writer.drain()
        except (OSError, serial.SerialException, RuntimeError) as exc:
            self.die(exc)
            raise LinkLost(f"joint line lost: write failed: {exc}") from exc

    def discard(self) -> None:
        """Forget received events and any partial message (keeps a loss visible)."""
        self.parser.reset()
        while not self.events.empty():
            self.events.get_nowait()
        if self.lost is not None:
            self.events.put_nowait(_Lost(self.lost))

    async def drain_quiet(self, quiet_s: float, max_s: float) -> None:
        """Wait until nothing arrived for ``quiet_s`` (at most ``max_s``), then discard."""
        loop = asyncio.get_running_loop()
        deadline = loop.time() + max_s
        while True:
            seen = self.rx_bytes
            await asyncio.sleep(quiet_s)
            if self.rx_bytes == seen or loop.time() >= deadline or self.lost is not None:
                break
        self.discard()

    async def close(self) -> None:
        if self._closing:  # closed (or closing) already
            return
        self._closing = True  # nothing received from now on counts (as a cancelled reader)
        if self._gap is not None:
            self._gap.cancel()
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task
        if self.lost is None:
            self.lost = LinkLost("closed")
            self.events.put_nowait(_Lost(self.lost))
        await close_streams(self.writer)


# -- one command at a time, e-stop first ---------------------------------------------------------


class _Turnstile:
    """A FIFO mutex whose urgent waiters jump the queue and can fail the ordinary ones."""

    def __init__(self) -> None:
        self._held = False
        self._waiters: deque[tuple[bool, asyncio.Future[None]]] = deque()

    async def acquire(self, *, urgent: bool = False) -> None:
        if not self._held and not self._waiters:
            self._held = True
            return
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        entry = (urgent, fut)
        if urgent:
            # Behind earlier urgent waiters, ahead of every ordinary one.
            pos = sum(1 for u, _ in self._waiters if u)
            self._waiters.insert(pos, entry)
        else:
            self._waiters.append(entry)
        try:
            await fut
        except asyncio.CancelledError:
            if fut.done() and not fut.cancelled() and fut.exception() is None:
                self.release()  # granted just as we were cancelled: pass it on
            elif entry in self._waiters:
                self._waiters.remove(entry)
            raise

    def release(self) -> None:
        while self._waiters:
            _, fut = self._waiters.popleft()
            if not fut.done():
                fut.set_result(None)
                return
        self._held = False

    def fail_waiting(self, make_exc: Callable[[], BaseException], *, urgent_too: bool) -> None:
        """Fail the waiters that have not got their turn yet."""
        keep: deque[tuple[bool, asyncio.Future[None]]] = deque()
        for urgent, fut in self._waiters:
            if urgent and not urgent_too:
                keep.append((urgent, fut))
            elif not fut.done():
                fut.set_exception(make_exc())
        self._waiters = keep


# -- the driver -----------------------------------------------------------------------------------


class JointLink:
    """Driver of the SDH2 joint-controller line; see the module docstring.

    Build with ``await JointLink.open(url, …)`` (or the constructor, then :meth:`connect`);
    use as an async context manager to close it.
    """

    def __init__(
        self,
        url: str,
        *,
        binary: bool = False,
        binary_crc: bool | None = None,
        timeout_s: float = 1.0,
        retries: int = 3,
        limits: Limits | None = None,
        reconnect: bool = True,
        on_event: Callable[[LinkEvent], None] | None = None,
        resync_quiet_s: float = 0.02,
        resync_max_s: float = 0.5,
        accept: Callable[[Vec], Sequence[str]] | None = None,
    ) -> None:
        """``accept``: told the hand's velocity limits at every handshake; the problems it
        returns refuse the hand (:class:`HandRefused`) once the handshake has held it."""
        if timeout_s <= 0 or retries < 0:
            raise ValueError("timeout_s must be > 0 and retries >= 0")
        self.url = url
        self._accept = accept
        self.binary = binary
        self.binary_crc = not is_socket_url(url) if binary_crc is None else binary_crc
        self.timeout_s = timeout_s
        self.retries = retries
        self.limits = _check_limits(DEFAULT_LIMITS if limits is None else limits)
        self.stats = JointStats()
        self.version = ""
        self.velocity_limits: Vec = ()
        self.failure: str | None = None  # why the line went down, until it is back up
        self._repeats = RepeatedFailures()  # its failed reopenings, logged quietly when alike
        self.acceleration_limits: Vec = ()
        self.controller: ControllerMode | None = None
        self._reconnect = reconnect
        self._on_event = on_event
        self._subscribers: list[asyncio.Queue[LinkEvent]] = []
        self._quiet_s = resync_quiet_s
        self._resync_max_s = resync_max_s
        self._conn: _Conn | None = None
        self._gate = _Turnstile()
        self._closed = False
        self._estopped = False
        self._latches = 0  # e-stops latched so far (a release names the last one it saw)
        self._releasing = False  # a release is out (estopped until the hand takes it)
        self._estop_pending = 0
        # a latched e-stop whose power-off the hand has not confirmed (a silent line, a line
        # down): sent again before anything else once the line answers (_transact, _handshake)
        self._power_off_owed = False
        self.reading: JointReading | None = None  # the newest actual angles (pos, tpap)
        self._rtts: deque[float] = deque(maxlen=RTTS_KEPT)  # recent round trips (_reply_start_s)
        self._may_be_moving = False  # a command that can start motion went out since the last hold
        self._poller: asyncio.Task[None] | None = None
        self._polling = False
        self._poll_idle_s = POLL_IDLE_S
        self._poll_wanted = False  # a command went out since the last poll
        self._poll_wake = asyncio.Event()  # a command went out (the plan may have changed)
        self._last_poll = -math.inf
        self.poll_plan = PollPlan()
        self._reconnect_task: asyncio.Task[None] | None = None
        self._background: set[asyncio.Task[None]] = set()
        self._sent_at = math.nan  # loop time the last request went on the line
        self._silent = False  # the port is open, but the line gave no byte back (_transact)
        self._answered_again: _Conn | None = None  # a silent line answered: to be dropped
        self._dropped: _Conn | None = None  # a lost connection the reconnect is to close
        self._bare: dict[tuple[str, bool, bool], _Request] = {}  # requests without values

    # -- lifecycle ------------------------------------------------------------------------------

    @classmethod
    async def open(
        cls,
        url: str,
        *,
        binary: bool = False,
        binary_crc: bool | None = None,
        timeout_s: float = 1.0,
        retries: int = 3,
        limits: Limits | None = None,
        reconnect: bool = True,
        on_event: Callable[[LinkEvent], None] | None = None,
        accept: Callable[[Vec], Sequence[str]] | None = None,
        patient: bool = False,
    ) -> Self:
        """Open ``url`` and run the handshake; raises :class:`JointLinkError` on failure — or,
        ``patient``, connect in the background as a lost line reconnects (now, then after each
        back-off delay, every failure reported) until the hand answers: a service that starts
        before its hand is on."""
        link = cls(
            url,
            binary=binary,
            binary_crc=binary_crc,
            timeout_s=timeout_s,
            retries=retries,
            limits=limits,
            reconnect=reconnect,
            on_event=on_event,
            accept=accept,
        )
        if patient:
            link._reconnect_task = asyncio.get_running_loop().create_task(
                link._first_connection(), name="sdh-joint-connect"
            )
        else:
            await link.connect()
        return link

    async def _first_connection(self) -> None:
        self._conn = await reconnect(self._reconnect_once, BACKOFF, self._reconnect_failed,
                                     at_once=True)  # fmt: skip
        self._reconnect_task = None
        self._emit(LinkEventKind.CONNECTED, f"firmware {self.version}")

    async def connect(self) -> None:
        """Open the port and run the handshake (first connection)."""
        if self._closed:
            raise LinkLost("link closed")
        if self._conn is not None:
            return
        if self._reconnect_task is not None:  # opened patiently: that connection, not a second
            await asyncio.shield(self._reconnect_task)
            return
        try:
            self._conn = await self._connect_once()
        except JointLinkError as e:  # which line it was (a lab plugs in two)
            if type(e) is not JointLinkError or str(e).startswith("joint line"):
                raise
            raise JointLinkError(f"joint line {self.url}: {e}") from e
        self._emit(LinkEventKind.CONNECTED, f"firmware {self.version}")

    async def close(self, *, power_off: bool = False) -> None:
        """Optionally power all axes off, then close the port; idempotent."""
        if self._closed:
            return
        if power_off and self._conn is not None:
            with contextlib.suppress(JointLinkError):
                await self._call(self._request("power", (0,) * NUM_AXES))
        self._closed = True
        self._polling = False
        self._gate.fail_waiting(lambda: LinkLost("link closed"), urgent_too=True)
        for task in (self._reconnect_task, self._poller):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._reconnect_task = self._poller = None
        conn, self._conn = self._conn, None
        if conn is not None:
            await conn.close()
        dropped, self._dropped = self._dropped, None
        if dropped is not None:  # lost just now: the reconnect was cancelled before closing it
            await dropped.close()
        if self._background:
            await asyncio.gather(*self._background, return_exceptions=True)
        self._emit(LinkEventKind.CLOSED)

    async def __aenter__(self) -> Self:
        await self.connect()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    @property
    def connected(self) -> bool:
        return self._conn is not None and self._conn.lost is None

    @property
    def silent(self) -> bool:
        """The port is open but the line has stopped answering: not a byte back through two
        attempts in a row of the last command (see :meth:`_transact`); False once it answers."""
        return self._silent and self.connected

    @property
    def estopped(self) -> bool:
        """Whether an emergency stop is latched (see :meth:`release`): also while a release is
        out, until the hand has taken it."""
        return self._estopped or self._releasing

    @property
    def power_off_confirmed(self) -> bool:
        """False while the hand owes an e-stop's power-off: not yet confirmed by a reply (a
        silent or down line, a latch taken from disk before the line answered)."""
        return not self._power_off_owed

    # -- events ---------------------------------------------------------------------------------

    def subscribe(self) -> asyncio.Queue[LinkEvent]:
        """A queue that receives every later :class:`LinkEvent`."""
        queue: asyncio.Queue[LinkEvent] = asyncio.Queue()
        self._subscribers.append(queue)
        return queue

    def _emit(self, kind: LinkEventKind, detail: str = "") -> None:
        event = LinkEvent(kind, self.url, asyncio.get_running_loop().time(), detail)
        self.failure = failure_after(kind, detail, self.failure)
        level, more = self._repeats.level(kind, detail, event.time, kind in _WARNINGS)
        logger.log(level, "%s %s %s%s", self.url, kind, detail, more)
        for queue in self._subscribers:
            queue.put_nowait(event)
        if self._on_event is not None:
            try:
                self._on_event(event)
            except Exception:  # a faulty observer must not break the link
                logger.exception("event callback failed")

    # -- low-level command --------------------------------------------------------------------

    async def command(
        self,
        keyword: str,
        values: float | Sequence[float] | None = None,
        *,
        axis: int | None = None,
        timeout_s: float | None = None,
    ) -> Reply:
        """Send one command (ASCII, or binary for the 11 of §2.6 when ``binary``) and return
        its reply; binary replies come back as a :class:`Reply` with ``text=""``.

        Encoding errors and targets (``p``, ``tpap``) outside the joint limits raise
        ``ValueError`` before anything is written.
        """
        if keyword.lower() in _TARGET_COMMANDS and values is not None:
            self._check_target_form(values, axis)
        return await self._call(self._request(keyword, values, axis), timeout_s)

    def _check_target_form(self, values: float | Sequence[float], axis: int | None) -> None:
        vals = _as_values(values) or ()
        if axis is None:
            self.check_targets(vals)
        elif 0 <= axis < NUM_AXES and len(vals) == 1:
            self._check_angle(axis, vals[0])

    def _request(
        self, keyword: str, values: float | Sequence[float] | None = None, axis: int | None = None
    ) -> _Request:
        if values is None and axis is None:  # `pos`, `m`, …: the same request every time
            key = (keyword, self.binary, self.binary_crc)
            req = self._bare.get(key)
            if req is None:
                req = self._bare[key] = self._new_request(keyword)
            return req
        return self._new_request(keyword, values, axis)

    def _new_request(
        self, keyword: str, values: float | Sequence[float] | None = None, axis: int | None = None
    ) -> _Request:
        kw = keyword.lower()
        vals = _as_values(values)
        spec = ASCII_COMMANDS.get(kw)
        code = BINARY_COMMANDS.get(kw) if self.binary and axis is None else None
        if code is not None and vals is not None and len(vals) != NUM_AXES:
            code = None  # binary frames carry exactly 7 values
        if code is not None:
            data = encode_binary_request(code, vals, with_crc=self.binary_crc)
        else:
            data = encode_ascii(keyword, vals, axis=axis)
        n_values = None if spec is None else spec.reply_values
        if spec is not None and axis is not None and spec.form is ArgForm.VECTOR:
            n_values = 1
        axis_cmd = spec is not None and spec.form in (ArgForm.VECTOR, ArgForm.AXIS_ONLY)
        check = _REPLY_CHECKS.get(kw)
        if kw in _ECHOED and vals is not None:
            check = _echoes(vals)
        elif kw in _ACTUAL_ANGLES:
            check = self._plausible_actual
        return _Request(kw, data, axis, code, axis_cmd, _may_move(kw, vals), n_values,
                        check, spec is not None or code is not None)  # fmt: skip

    def _plausible_actual(self, values: Vec) -> bool:
        """Actual angles a hand can have: within the limits (± a margin) and no further from the
        last reading than the axes can travel since. ASCII replies carry no checksum, and a
        flipped digit would make a 12.5° finger read 92.5° — whose ±1° target is 80° away."""
        if len(values) != NUM_AXES or not all(math.isfinite(v) for v in values):
            return False
        if self._past_limits(values):
            return False
        last = self.reading
        if last is None or not self.velocity_limits:
            return True
        dt = last.age()
        vlim = self.velocity_limits
        return all(abs(v - w) <= vmax * dt + _READ_MARGIN_DEG
                   for v, w, vmax in zip(values, last.angles, vlim, strict=True))  # fmt: skip

    async def _call(self, req: _Request, timeout_s: float | None = None) -> Reply:
        return (await self._call_sent(req, timeout_s))[0]

    async def _call_sent(
        self, req: _Request, timeout_s: float | None = None
    ) -> tuple[Reply, float]:
        """The reply, and the loop time its (last) request was written to the line."""
        self._check_usable(req)
        await self._gate.acquire()
        try:
            self._check_usable(req)
            conn = self._require_conn()
            reply = await self._transact(conn, req, timeout_s=timeout_s or self.timeout_s,
                                         retries=self.retries)  # fmt: skip
            if req.keyword == "p":
                self.poll_plan.command()
            return reply, self._sent_at
        finally:
            self._let_go()
            if req.keyword not in _ACTUAL_ANGLES:  # those answer the angles themselves
                self._poll_wanted = True
                self._poll_wake.set()

    def _let_go(self) -> None:
        """Release the turnstile. A connection whose silent line answered again is dropped now,
        once its holder's whole sequence (an e-stop's power, pos and p) has run on it: the
        reconnect's handshake identifies and holds the hand anew (it may have been switched
        off and on, or be another hand behind the same adapter)."""
        conn, self._answered_again = self._answered_again, None
        if conn is not None and conn is self._conn:
            conn.die(AnsweredAgain("the line answers again after being silent: the hand is "
                                   "identified anew"))  # fmt: skip
        self._gate.release()

    def _check_usable(self, req: _Request) -> None:
        if self._closed:
            raise LinkLost("link closed")
        if self._estopped and req.moves:
            raise EmergencyStopped(f"{req.label} refused: emergency stop latched")

    def _require_conn(self) -> _Conn:
        conn = self._conn
        if conn is None or conn.lost is not None:
            raise LinkLost(f"joint line lost: no connection to {self.url}")
        return conn

    async def _transact(
        self,
        conn: _Conn,
        req: _Request,
        *,
        timeout_s: float,
        retries: int,
        urgent: bool = False,
        stops_only: bool = False,
    ) -> Reply:
        """One command with SDHLibrary's retry policy; the caller holds the turnstile.

        Unless ``urgent`` (the handshake, the e-stop itself), it gives way to an e-stop waiting
        for the line before each attempt, and to a latch come since it began unless it
        ``stops_only`` (a hold): a line that needed a resync, or a retry's stop, first, must
        not send a move after the e-stop, nor hold the e-stop's power-off back.

        Retries help a line that answers wrongly (a flipped bit, a lost byte); a line that stays
        silent — not one byte back — through two attempts in a row does not answer any more
        (a hung controller, a stalled converter, its port still open): the command fails then,
        and the link counts as :attr:`silent` until something answers again (one attempt only
        meanwhile). Otherwise a silent line would hold a run through every retry — 20 s —
        before it could fault, while the fingers wait."""
        self.stats.commands += 1
        failure: JointLinkError | None = None
        silent_before = self._silent  # the line was silent already: one silent attempt ends it
        for attempt in range(retries + 1):
            if attempt:
                self._give_way(req, urgent, stops_only)
                self.stats.retries += 1
            resynced = conn.dirty
            if resynced:
                await self._resync(conn)
            if attempt and self._may_be_moving:
                self._give_way(req, urgent, stops_only)
                await self._stop_motion(conn, timeout_s)
            self._give_way(req, urgent, stops_only)
            rx = conn.rx_bytes
            # only a first attempt on a line in step must begin its reply early (and tells the
            # line's round trip): a resync's blank lines may hold the next reply back (the
            # firmware works through them), and a line is silent, or an answer given up for
            # good, only after a whole timeout
            in_step = attempt == 0 and not resynced
            early = (in_step and retries > 0 and bool(self._rtts)
                     and req.keyword not in _ANSWERS_LATE)  # fmt: skip
            start_s = min(timeout_s, self._reply_start_s()) if early else timeout_s
            try:
                reply = await self._attempt(conn, req, timeout_s, start_s=start_s,
                                            typical=in_step)  # fmt: skip
            except FirmwareError as exc:
                self.stats.errors += 1
                spoilt = req.from_table and exc.error in _SPOILT_ON_THE_LINE
                if not (req.retry_on_error or spoilt):
                    raise
                failure, conn.dirty = exc, True  # SDHLibrary resyncs before retrying
            except _Garbled as exc:
                self.stats.garbled += 1
                failure = JointLinkError(f"{req.label}: bad reply ({exc})")
            except TimeoutError:
                self.stats.timeouts += 1
                silent = conn.rx_bytes == rx
                if silent and start_s < timeout_s:
                    failure = JointLinkError(f"{req.label}: no reply begun within "
                                             f"{start_s:.3g} s")  # fmt: skip
                else:
                    failure = JointLinkError(f"{req.label}: no reply within {timeout_s} s")
                if silent and silent_before:
                    self._silent = True
                    failure = JointLinkError(f"{req.label}: no reply within {timeout_s} s, "
                                             "twice in a row: the line is silent")  # fmt: skip
                    break
                silent_before = silent
            else:
                was_silent, self._silent = self._silent, False
                self._may_be_moving = self._may_be_moving or req.moves
                if self._power_off_owed and not self._estop_pending and req.keyword != "power":
                    await self._pay_power_off(conn, timeout_s)
                if was_silent and self._reconnect:  # dropped once its holder's sequence ran
                    self._answered_again = conn
                return reply
        assert failure is not None
        self.stats.failures += 1
        self._emit(LinkEventKind.ERROR, str(failure))
        raise failure

    def _give_way(self, req: _Request, urgent: bool, stops_only: bool) -> None:
        """Before an attempt goes on the line (see :meth:`_transact`)."""
        if urgent:
            return
        if self._estop_pending:
            raise EmergencyStopped(f"{req.label} abandoned for an emergency stop")
        if self._estopped and req.moves and not stops_only:
            raise EmergencyStopped(f"{req.label} refused: emergency stop latched")

    async def _pay_power_off(self, conn: _Conn, timeout_s: float) -> None:
        """The latched e-stop's power-off, owed since the line stopped answering: the line
        answers again. A failure leaves it owed (the next answer tries again)."""
        try:
            await self._attempt(conn, self._request("power", (0,) * NUM_AXES), timeout_s)
        except (JointLinkError, _Garbled, TimeoutError) as exc:
            self._emit(LinkEventKind.ERROR, f"the e-stop's power-off, sent again: {exc}")
            return
        self._power_off_owed = False
        self._emit(LinkEventKind.EMERGENCY_STOP, "powered off once the line answered again")

    async def _attempt(
        self,
        conn: _Conn,
        req: _Request,
        timeout_s: float,
        *,
        start_s: float | None = None,
        typical: bool = False,
    ) -> Reply:
        """One exchange; its reply must begin within ``start_s`` (default: ``timeout_s``);
        ``typical``: its round trip is the line's own (no resync's backlog before it)."""
        conn.discard()  # late replies of earlier exchanges
        loop = asyncio.get_running_loop()
        start = loop.time()
        conn.dirty = True  # until the reply is in (also if the caller cancels us)
        await conn.send(req.data)
        self._sent_at = sent = loop.time()
        began = timeout_s if start_s is None else min(start_s, timeout_s)
        try:
            reply = await self._reply_begun(conn, req, sent + began, sent + timeout_s)
        except BaseException:
            if conn.dirty:  # its reply may still come
                conn.owed.append(req.binary or req.keyword)
            raise
        conn.dirty = False
        rtt = loop.time() - start
        self.stats.record_rtt(rtt)
        if typical:
            self._rtts.append(rtt)
        return reply

    async def _reply_begun(
        self, conn: _Conn, req: _Request, begin_by: float, end_by: float
    ) -> Reply:
        """:meth:`_reply`, and past a first byte not come by ``begin_by``, STALL_GRACE_S more:
        this process may have stood still (a loaded machine: its own loop and an in-process
        device alike) while the reply was due; it counts as lost only once the loop has run
        that much longer without a byte of it."""
        rx = conn.rx_bytes
        try:
            return await self._reply(conn, req, begin_by, end_by)
        except TimeoutError:
            if begin_by >= end_by or conn.rx_bytes != rx:
                raise  # the whole timeout: it never began, or began and did not end
            grace = min(end_by, asyncio.get_running_loop().time() + STALL_GRACE_S)
            return await self._reply(conn, req, grace, end_by)

    async def _reply(self, conn: _Conn, req: _Request, begin_by: float, end_by: float) -> Reply:
        """The reply to ``req``: its first byte by ``begin_by``, all of it by ``end_by``."""
        try:
            async with asyncio.timeout_at(begin_by) as within:
                if begin_by < end_by:
                    conn.on_bytes = partial(_extend, within, end_by)
                while (reply := self._match(req, await conn.events.get(), conn)) is None:
                    pass
        finally:
            conn.on_bytes = None  # (a Timeout left cannot be rescheduled)
        return reply

    def _reply_start_s(self) -> float:
        """How soon a reply must begin (:data:`REPLY_START_S`, or longer on a slow line)."""
        return max(REPLY_START_S, RTT_MARGIN * max(self._rtts))

    def _match(self, req: _Request, event: ReplyEvent | _Lost, conn: _Conn) -> Reply | None:
        """The reply for ``req``, None to keep waiting; raises for anything else."""
        match event:
            case _Lost(exc):
                raise LinkLost(f"joint line lost: {exc} (no reply to {req.label!r})")
            case DebugLine():
                return None  # §2.3: hosts skip '@' lines
            case Garbage(reason=reason):
                raise _Garbled(reason)
            case ErrorLine(code=code):
                conn.dirty = False  # a clean answer: the line is in step
                raise FirmwareError(code, req.label)
            case BinaryReply():
                return self._match_binary(req, event, conn)
            case Reply():
                return self._match_ascii(req, event, conn)
        raise _Garbled(f"unexpected event {event!r}")

    def _match_binary(self, req: _Request, event: BinaryReply, conn: _Conn) -> Reply | None:
        if event.cmd != req.binary:
            if _late(conn, event.cmd):
                return None
            raise _Garbled(f"binary reply {event.cmd.name} to {req.label}")
        if not event.ok:
            conn.dirty = False
            raise FirmwareError(event.status, req.label)
        return self._checked(req, Reply(req.keyword.upper(), None, event.values, ""))

    def _match_ascii(self, req: _Request, event: Reply, conn: _Conn) -> Reply | None:
        ours = req.binary is None and event.keyword == req.keyword.upper()
        if not ours and _late(conn, event.keyword.lower()):
            return None
        if req.binary is not None:
            raise _Garbled(f"ASCII reply {event.keyword} to binary {req.label}")
        free_text = req.n_values is None and event.keyword == ""  # e.g. the [U] `stop` reply
        if not free_text and (event.keyword != req.keyword.upper() or event.axis != req.axis):
            raise _Garbled(f"reply {event.keyword or event.text!r} to {req.label}")
        return self._checked(req, event)

    def _checked(self, req: _Request, reply: Reply) -> Reply:
        if req.n_values is not None and len(reply.values) != req.n_values:
            raise _Garbled(f"{req.label}: {len(reply.values)} values, expected {req.n_values}")
        if req.check is not None and not req.check(reply.values):
            beyond = self._beyond_limits(reply.values) if req.keyword in _ACTUAL_ANGLES else ""
            raise _Garbled(f"{req.label}: implausible values {reply.values}{beyond}")
        return reply

    def _past_limits(self, values: Vec) -> list[str]:
        """The axes an actual-angle reading puts past their limits by more than the read
        margin, each said with its reading and limits (a non-finite value is no reading)."""
        m = _READ_MARGIN_DEG
        return [f"axis {axis} reads {v:g}°, outside its limits {lo:g}…{hi:g}°"
                for axis, (v, (lo, hi)) in enumerate(zip(values, self.limits, strict=False))
                if math.isfinite(v) and not lo - m <= v <= hi + m]  # fmt: skip

    def _beyond_limits(self, values: Vec) -> str:
        """Which axes an actual-angle reading puts past their limits, and what to do if one
        really stands there ("" if none does): the reading is refused as a spoilt reply either
        way (ASCII carries no checksum), and a line refused at every try would otherwise leave
        a lab checking its cables."""
        past = self._past_limits(values)
        if not past:
            return ""
        return (f" ({'; '.join(past)} by more than {_READ_MARGIN_DEG:g}°: if it stands there — "
                "moved unpowered, or the limits narrowed since — move it within its limits "
                "with the hand off, or widen `limits`)")  # fmt: skip

    async def _urgent(self, conn: _Conn, req: _Request) -> Reply:
        """A transaction that must not give way to an emergency stop (handshake, the stop)."""
        return await self._transact(conn, req, timeout_s=self.timeout_s, retries=self.retries,
                                    urgent=True)  # fmt: skip

    async def _resync(self, conn: _Conn) -> None:
        """Bring both parsers back to a message boundary (:data:`RESYNC`) and drain."""
        self.stats.resyncs += 1
        await conn.send(RESYNC)
        await conn.drain_quiet(self._quiet_s, self._resync_max_s)
        conn.dirty = False

    async def _stop_motion(self, conn: _Conn, timeout_s: float) -> None:
        """Before retrying a failed exchange: `stop` (and zero velocities in a velocity
        controller), one attempt each, errors ignored — the hand must not move on while the
        line is bad, and a stop that got through works even if its reply did not."""
        self.stats.motion_stops += 1
        for req in self._stop_requests():
            try:
                await self._attempt(conn, req, timeout_s)
            except (JointLinkError, _Garbled, TimeoutError):
                await self._resync(conn)

    def _stop_requests(self) -> list[_Request]:
        """What stops every axis in the current controller: zero target velocities (a velocity
        controller), then `stop` (an `m` move)."""
        stop = [self._request("stop")]
        if self.controller is ControllerMode.POSE:
            return stop
        return [self._request("v", (0.0,) * NUM_AXES), *stop]

    async def _hold_on(self, conn: _Conn, *, urgent: bool) -> Vec:
        """Stop every axis where it is (:meth:`_stop_requests`), pose controller, actual angles
        as targets (so a later `m` does not jump). Not ``urgent`` (a hold of ours), it gives way
        to an e-stop, whose power-off stops the hand and whose own sequence holds it."""

        async def call(req: _Request) -> Reply:
            return await self._transact(conn, req, timeout_s=self.timeout_s,
                                        retries=self.retries, urgent=urgent,
                                        stops_only=True)  # fmt: skip

        for req in self._stop_requests():
            await call(req)
        if self.controller is not ControllerMode.POSE:
            await call(self._request("con", int(ControllerMode.POSE)))
            self.controller = ControllerMode.POSE
        actual = self._took_actual((await call(self._request("pos"))).values)
        held = self.clip_to_limits(actual)
        await call(self._request("p", held))
        self._may_be_moving = False
        return held

    async def _end_grips(self, conn: _Conn) -> None:
        """A ``selgrip``/``grip`` move a previous program left running: ``stop`` does not end
        one (§2.4). ``con=0`` ends any move in the simulator (on the firmware: not in our
        sources); an axis still positioning after it is powered off, which ends a move on any
        firmware."""
        if not await self._positioning(conn):
            return
        logger.warning("%s: axes still moving after `stop` (a selgrip/grip left running by "
                       "another program?): switching to the pose controller", self.url)  # fmt: skip
        if self._has_con:
            await self._urgent(conn, self._request("con", int(ControllerMode.POSE)))
        self.controller = ControllerMode.POSE
        await self._hold_on(conn, urgent=True)  # `con=` may reset the targets
        if moving := await self._positioning(conn):
            await self._urgent(conn, self._request("power", (0,) * NUM_AXES))
            self._emit(LinkEventKind.ERROR, f"axes {moving} moved on after `stop` and `con=0` "
                       "(a grip left running by another program?): powered off (a run "
                       "powers them on again)")  # fmt: skip

    async def _positioning(self, conn: _Conn) -> list[int]:
        """The axes the controller says are moving (``state``: positioning or speed mode)."""
        states = (await self._urgent(conn, self._request("state"))).values
        busy = (AxisState.POSITIONING, AxisState.SPEED_MODE)
        return [axis for axis, v in enumerate(states) if int(v) in busy]

    # -- connecting -----------------------------------------------------------------------------

    async def _connect_once(self) -> _Conn:
        try:
            reader, writer = await open_streams(self.url)
        except (OSError, serial.SerialException, ValueError) as exc:
            raise JointLinkError(f"cannot open: {exc}") from exc
        parser = ReplyParser(crc=self.binary_crc, binary=self.binary)
        conn = _Conn(reader, writer, parser, self._conn_lost)
        self._silent = False  # a new connection is given its retries
        try:
            await self._handshake(conn)
        except BaseException:
            await conn.close()
            raise
        return conn

    async def _handshake(self, conn: _Conn) -> None:
        await conn.send(encode_blank())  # ends any half-received line (§2.3)
        await asyncio.sleep(CONNECT_DRAIN_S)
        conn.discard()
        try:
            ver = await self._transact(conn, self._request("ver"), timeout_s=VER_TIMEOUT_S,
                                       retries=0, urgent=True)  # fmt: skip
        except JointLinkError as exc:
            if DSACON_PREAMBLE in conn.heard:
                raise JointLinkError(f"SDH not connected: {exc}; what came back is a DSACON32m's "
                                     "packets: this is the tactile line (are the two lines "
                                     "swapped?)") from exc  # fmt: skip
            raise JointLinkError(f"SDH not connected: {exc}") from exc
        version = self._identified(ver)
        release = firmware_release(version)
        # Older firmware lacks these commands; SDHLibrary-CPP (sdh.cpp) sends none of them
        # then and takes fixed limits and the pose controller instead
        vlim = (await self._agreed(conn, "vlim") if release >= COMMAND_SINCE["vlim"]
                else OLD_VELOCITY_LIMITS)  # fmt: skip
        alim = (await self._agreed(conn, "alim") if release >= COMMAND_SINCE["alim"]
                else OLD_ACCELERATION_LIMITS)  # fmt: skip
        con = (int((await self._urgent(conn, self._request("con"))).values[0])
               if release >= COMMAND_SINCE["con"] else int(ControllerMode.POSE))  # fmt: skip
        if self.version and version != self.version:  # another hand behind the same port?
            logger.warning("%s: firmware %s, was %s", self.url, version, self.version)
        self.version = version
        self.velocity_limits, self.acceleration_limits = vlim, alim
        self.controller = ControllerMode(con)
        if self._estopped:  # a latched e-stop holds on a new connection too (the controller
            # may have been reset, or powered on by hand, while the line was down)
            await self._urgent(conn, self._request("power", (0,) * NUM_AXES))
            self._power_off_owed = False
        # Whatever the last host left running (a velocity, a move), it stops now: the firmware
        # keeps its last command forever, and no loop of ours commands it yet. (A hand this
        # host then refuses is held all the same.)
        await self._hold_on(conn, urgent=True)
        await self._end_grips(conn)
        if self._accept is not None and (problems := self._accept(vlim)):
            raise HandRefused(problems)

    @property
    def _has_con(self) -> bool:
        """Whether the firmware knows ``con`` (an unknown version: assumed to)."""
        return not self.version or firmware_release(self.version) >= COMMAND_SINCE["con"]

    def _identified(self, ver: Reply) -> str:
        """The firmware's version from its answer to ``ver``: an SDH2 says ``VER=x.x.x.x``; any
        other line (a device that echoes, another controller) is not one, and is sent nothing
        more. Firmware older than the binary frames is spoken to in ASCII."""
        text = ver.text.strip()
        if ver.keyword != "VER" or not _VERSION.fullmatch(text):
            said = f"{ver.keyword}={ver.text}" if ver.keyword else ver.text
            raise JointLinkError(f"SDH not connected: {said!r} is no SDH2's answer to ver "
                                 "(VER=x.x.x.x): another device on this port, or one that "
                                 "echoes?")  # fmt: skip
        if self.binary and firmware_release(text) < BINARY_SINCE:
            logger.warning("%s firmware %s does not speak the binary frames (from 0.0.2.15 "
                           "on): this line speaks ASCII", self.url, text)  # fmt: skip
            self.binary = False
        return text

    async def _agreed(self, conn: _Conn, keyword: str, tries: int = 4) -> Vec:
        """Values read twice alike: the limits every later command is checked against must not
        carry a flipped digit (ASCII replies have no checksum)."""
        last = (await self._urgent(conn, self._request(keyword))).values
        for _ in range(tries):
            again = (await self._urgent(conn, self._request(keyword))).values
            if again == last:
                return again
            last = again
        raise JointLinkError(f"{keyword}: no two readings agree (a noisy line?)")

    def _conn_lost(self, conn: _Conn, exc: BaseException) -> None:
        if conn is not self._conn or self._closed:
            return  # a handshake's own connection, or closing: the caller sees it
        self._conn = None
        self.stats.link_losses += 1
        self._emit(LinkEventKind.LOST, str(exc))
        if self._reconnect:
            self._dropped = conn  # closed by the reconnect, or by close() if it comes first
            self._reconnect_task = asyncio.get_running_loop().create_task(
                self._reconnect_loop(conn, at_once=isinstance(exc, AnsweredAgain)),
                name="sdh-joint-reconnect",
            )
        else:
            task = asyncio.get_running_loop().create_task(conn.close())
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _reconnect_loop(self, old: _Conn, *, at_once: bool = False) -> None:
        await old.close()
        self._dropped = None
        self._conn = await reconnect(self._reconnect_once, BACKOFF, self._reconnect_failed,
                                     at_once=at_once)  # fmt: skip
        self._reconnect_task = None
        self.stats.reconnects += 1
        self._emit(LinkEventKind.RECONNECTED, f"firmware {self.version}")

    def _reconnect_failed(self, exc: Exception) -> None:
        self._emit(LinkEventKind.RECONNECT_FAILED, str(exc))

    async def _reconnect_once(self) -> _Conn:
        conn = await self._connect_once()
        if conn.lost is not None:
            await conn.close()
            raise LinkLost(f"lost right after the handshake: {conn.lost}")
        return conn

    # -- limits ---------------------------------------------------------------------------------

    def check_targets(self, angles: Sequence[float]) -> Vec:
        """The 7 angles as floats; ``ValueError`` naming the first axis outside its limits."""
        vals = tuple(float(a) for a in angles)
        if len(vals) != NUM_AXES:
            raise ValueError(f"targets: {NUM_AXES} values needed, got {len(vals)}")
        for axis, angle in enumerate(vals):
            self._check_angle(axis, angle)
        return vals

    def _check_angle(self, axis: int, angle: float) -> None:
        lo, hi = self.limits[axis]
        if not lo <= angle <= hi:  # also refuses NaN
            raise ValueError(f"axis {axis}: target {angle}° outside [{lo}, {hi}]°")

    def clip_to_limits(self, angles: Sequence[float]) -> Vec:
        return tuple(min(max(a, lo), hi) for a, (lo, hi) in zip(angles, self.limits, strict=True))

    def _check_velocities(self, velocities: Sequence[float]) -> Vec:
        vals = _seven_values(velocities, "velocities")
        for axis, v in enumerate(vals):
            vmax = self.velocity_limits[axis] if self.velocity_limits else math.inf
            if not abs(v) <= vmax:
                raise ValueError(f"axis {axis}: velocity {v} deg/s beyond ±{vmax}")
        return vals

    # -- typed commands -------------------------------------------------------------------------

    async def _vector(self, keyword: str, values: Sequence[float] | None = None) -> Vec:
        return (await self._call(self._request(keyword, values))).values

    async def get_actual(self) -> Vec:
        """Actual joint angles (``pos``), deg."""
        return self._took_actual(await self._vector("pos"))

    def _took_actual(self, actual: Vec) -> Vec:
        self.reading = JointReading(actual, asyncio.get_running_loop().time())
        return actual

    def take_reading(self) -> JointReading | None:
        """:attr:`reading`, for a control loop whose command follows: no poll goes out first."""
        self.poll_plan.beat(asyncio.get_running_loop().time())
        # the poller plans again: its timer, set before this beat, may fall before the command
        # and its move are through (a ``p`` longer than the plan's quarter period of lateness)
        self._poll_wake.set()
        return self.reading

    @property
    def last_actual(self) -> Vec | None:
        """The newest actual angles, for displays (no line time)."""
        return None if self.reading is None else self.reading.angles

    async def get_targets(self) -> Vec:
        """Target angles (``p``), deg."""
        return await self._vector("p")

    async def set_targets(self, angles: Sequence[float]) -> Vec:
        """Set target angles (``p=…``) after the limit check; returns the echoed targets."""
        return await self._vector("p", self.check_targets(angles))

    async def send_targets(self, angles: Sequence[float]) -> float:
        """:meth:`set_targets` for a control loop: returns, once the firmware took them, the
        loop time the targets were written to the line (where sense→command ends)."""
        return (await self._call_sent(self._request("p", self.check_targets(angles))))[1]

    async def move(self) -> float:
        """Start the coordinated move to the targets (``m``); returns its duration in s."""
        return (await self._call(self._request("m"))).values[0]

    async def stop(self) -> None:
        """Stop an ``m`` move (``stop``)."""
        await self._call(self._request("stop"))

    async def get_state(self) -> tuple[AxisState, ...]:
        return tuple(AxisState(int(v)) for v in await self._vector("state"))

    async def wait_idle(self, poll_s: float = 0.02) -> tuple[AxisState, ...]:
        """Poll ``state`` until no axis is positioning or in speed mode (SDHLibrary's WaitAxis)."""
        busy = (AxisState.POSITIONING, AxisState.SPEED_MODE)
        while True:
            states = await self.get_state()
            if not any(s in busy for s in states):
                return states
            await asyncio.sleep(poll_s)

    async def set_velocities(self, velocities: Sequence[float]) -> Vec:
        """Target velocities (``v=…``), deg/s, checked against ``vlim``."""
        return await self._vector("v", self._check_velocities(velocities))

    async def get_velocities(self) -> Vec:
        """Target velocities (``v``), deg/s."""
        return await self._vector("v")

    async def set_accelerations(self, accelerations: Sequence[float]) -> Vec:
        """Target accelerations (``a=…``), deg/s²."""
        return await self._vector("a", _seven_values(accelerations, "accelerations"))

    async def set_controller(self, mode: ControllerMode | int) -> ControllerMode:
        mode = ControllerMode(mode)
        if not self._has_con:  # firmware before 0.0.2.6: the pose controller, fixed (COMMAND_SINCE)
            if mode is not ControllerMode.POSE:
                raise JointLinkError(f"firmware {self.version} has only the pose controller")
            self.controller = ControllerMode.POSE
            return self.controller
        reply = await self._call(self._request("con", int(mode)))
        self.controller = ControllerMode(int(reply.values[0]))
        return self.controller

    async def power(self, on: Sequence[bool]) -> tuple[bool, ...]:
        """Enable/disable the axis controllers; returns the echoed flags."""
        if len(on) != NUM_AXES:
            raise ValueError(f"power needs {NUM_AXES} flags")
        return _flags(await self._vector("power", [1.0 if f else 0.0 for f in on]))

    async def get_power(self) -> tuple[bool, ...]:
        return _flags(await self._vector("power"))

    async def tpap(self, targets: Sequence[float]) -> Vec:
        """Set target angles (limit-checked) and read the actual ones in one round trip."""
        return self._took_actual(await self._vector("tpap", self.check_targets(targets)))

    async def tvav(self, velocities: Sequence[float]) -> Vec:
        """Set target velocities and read the actual velocities in one round trip."""
        return await self._vector("tvav", self._check_velocities(velocities))

    async def get_velocity(self) -> Vec:
        """Actual angular velocities (``vel``), deg/s."""
        return await self._vector("vel")

    async def temperatures(self) -> Vec:
        """9 temperatures (°C): 7 motors, FPGA, PCB."""
        temps = await self._vector("temp")
        if len(temps) != _NUM_TEMPS:
            raise JointLinkError(f"temp: {len(temps)} values")
        return temps

    async def hold(self) -> Vec:
        """Stop every axis where it is and switch to the pose controller; returns the held
        angles. Allowed while an emergency stop is latched (it only stops); gives way to an
        e-stop waiting for the line (:class:`EmergencyStopped`: its power-off stops the hand)."""
        await self._gate.acquire()
        try:
            if self._closed:
                raise LinkLost("link closed")
            return await self._hold_on(self._require_conn(), urgent=False)
        finally:
            self._let_go()

    # -- polling the actual angles ----------------------------------------------------------------

    def start_polling(self, idle_s: float = POLL_IDLE_S) -> None:
        """Keep :attr:`reading` fresh (module docstring) until :meth:`stop_polling`."""
        if idle_s <= 0:
            raise ValueError("idle_s must be > 0")
        if self._closed:
            raise LinkLost("link closed")
        self._polling, self._poll_idle_s = True, idle_s
        self._poll_wanted = True  # a first reading at once
        self._poll_wake.set()
        if self._poller is None or self._poller.done():
            self._poller = asyncio.get_running_loop().create_task(
                self._poll_loop(), name="sdh-joint-poll"
            )

    def stop_polling(self) -> None:
        """No more polls once the one on the line (if any) is answered."""
        self._polling = False
        self._poll_wake.set()

    def _next_poll(self, now: float) -> float:
        at = self.poll_plan.start_at(now)
        if at is not None:
            return at
        return now if self._poll_wanted else self._last_poll + self._poll_idle_s

    async def _poll_loop(self) -> None:
        loop = asyncio.get_running_loop()
        while self._polling and not self._closed:
            now = loop.time()
            if (at := self._next_poll(now)) > now:
                self._poll_wake.clear()
                try:
                    async with asyncio.timeout(at - now):
                        await self._poll_wake.wait()
                    continue  # a command went out: plan again
                except TimeoutError:
                    pass  # its time (a timer fires a little late: no second look at the plan)
            try:
                await self._poll()
            except EmergencyStopped:
                pass  # the stop went first; read again after it
            except JointLinkError:  # line down or failing: the reading ages, its users see it
                await asyncio.sleep(self._poll_idle_s)

    async def _poll(self) -> None:
        loop = asyncio.get_running_loop()
        await self._gate.acquire()
        try:
            self._poll_wanted = False  # this reading follows every command so far
            self._last_poll = start = loop.time()
            if self._closed:
                raise LinkLost("link closed")
            conn, req = self._require_conn(), self._request("pos")
            reply = await self._transact(conn, req, timeout_s=self.timeout_s, retries=self.retries)
            self._took_actual(reply.values)
            self.poll_plan.polled(start, loop.time())
        finally:
            self._let_go()

    # -- emergency stop -------------------------------------------------------------------------

    def latch(self) -> None:
        """Latch an emergency stop without a word to the hand (e.g. one found latched on disk
        while the line is down): motion commands are refused and the hand is powered off as soon
        as the line answers (the next connect, or the next reply on this one)."""
        self._estopped = self._power_off_owed = True
        self._latches += 1

    async def emergency_stop(self) -> Vec:
        """SCHUNK's e-stop with precedence; returns the angles written as targets.

        Queued commands fail with :class:`EmergencyStopped`; the attempt in flight finishes (or
        times out) first, and the rest of its command (a resync, a retry and the stop before it; a
        hold's later commands) is abandoned with :class:`EmergencyStopped`. A failed power-off still
        reads and holds the position, then raises. The stop stays latched until :meth:`release`,
        also if it raised (e.g. :class:`LinkLost` while reconnecting: the latch then keeps motion
        commands off the new connection; nothing is sent to it by itself).
        """
        if self._closed:
            raise LinkLost("link closed")
        # counted again after a caller's own latch(): a release decided between the two must
        # not power the hand on while this stop is still on its way to it
        self.latch()
        self._estop_pending += 1
        try:
            self._gate.fail_waiting(
                lambda: EmergencyStopped("cancelled by an emergency stop"), urgent_too=False
            )
            await self._gate.acquire(urgent=True)
            try:
                held = await self._estop_sequence(self._require_conn())
            finally:
                self._let_go()
        finally:
            self._estop_pending -= 1
        self._emit(LinkEventKind.EMERGENCY_STOP, f"holding {held}")
        return held

    async def _estop_sequence(self, conn: _Conn) -> Vec:
        first_error: JointLinkError | None = None
        try:
            await self._urgent(conn, self._request("power", (0,) * NUM_AXES))
            self._power_off_owed = False
        except JointLinkError as exc:
            first_error = exc  # still hold the hand where it is
        actual = self._took_actual((await self._urgent(conn, self._request("pos"))).values)
        held = self.clip_to_limits(actual)
        await self._urgent(conn, self._request("p", held))
        if first_error is not None:
            raise first_error
        return held

    @property
    def latches(self) -> int:
        """How many e-stops this link has latched: what a release decided on (see
        :meth:`release`)."""
        return self._latches

    async def release(self, seen: int | None = None) -> tuple[bool, ...]:
        """Clear a latched emergency stop and power all axes on again, holding them where they
        are: the targets are first set to the actual angles (fingers that sagged, or were moved
        by hand, while unpowered would otherwise be driven back to the targets the e-stop
        wrote). :attr:`estopped` stays true until the hand has answered (the link lets these
        commands through meanwhile).

        ``seen``: :attr:`latches` when the caller decided to release. An e-stop latched since
        (pressed while the caller was busy, e.g. deleting its record) is not released:
        :class:`EmergencyStopped`, the latch as it is. An e-stop that comes during the release
        itself refuses its power-on, or powers the hand off after it."""
        if seen is not None and seen != self._latches:
            raise EmergencyStopped("an emergency stop came during the release: it stays latched")
        self._releasing, self._estopped, self._power_off_owed = True, False, False
        try:
            await self.set_targets(self.clip_to_limits(await self.get_actual()))
            flags = await self.power([True] * NUM_AXES)
        except BaseException:
            # not released until the hand took it; and, latched, the hand is to be powered off
            # (the power-on may have reached it, its answer not)
            self._estopped = self._power_off_owed = True
            raise
        finally:
            self._releasing = False
        self._emit(LinkEventKind.RELEASED)
        return flags


def _extend(within: asyncio.Timeout, when: float) -> None:
    """A reply's deadline moved on as its first byte came; not once it has fired (its waiter is
    being cancelled: a Timeout that fired cannot be rescheduled)."""
    if not within.expired():
        within.reschedule(when)


def _late(conn: _Conn, reply_to: str | BinaryCommand) -> bool:
    """Whether a reply that is not the awaited one answers an exchange given up earlier (taken
    off what is owed: it came)."""
    if reply_to in conn.owed:
        conn.owed.remove(reply_to)
        return True
    return False


def _seven_values(values: Sequence[float], what: str) -> Vec:
    vals = tuple(float(v) for v in values)
    if len(vals) != NUM_AXES:
        raise ValueError(f"{what}: {NUM_AXES} values needed, got {len(vals)}")
    if not all(math.isfinite(v) for v in vals):
        raise ValueError(f"{what}: non-finite value in {vals}")
    return vals


def _flags(values: Vec) -> tuple[bool, ...]:
    return tuple(v != 0.0 for v in values)


def _check_limits(limits: Limits) -> tuple[tuple[float, float], ...]:
    out = tuple((float(lo), float(hi)) for lo, hi in limits)
    if len(out) != NUM_AXES or any(not lo <= hi for lo, hi in out):
        raise ValueError(f"limits need {NUM_AXES} (low, high) pairs with low <= high")
    return out
