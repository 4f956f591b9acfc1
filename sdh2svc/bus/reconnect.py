"""What both links share about their line's life: one event type, one reconnect with back-off.

A link reports what happens on its line as :class:`LinkEvent` values (the kinds of both lines in
one :class:`LinkEventKind`), and reopens a lost line with :func:`reconnect`: exponential back-off
from ``initial_s`` to ``max_s``, every failed attempt reported, never giving up (the hand needs
its lines).
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import TypeVar

__all__ = ["Backoff", "LinkEvent", "LinkEventKind", "RepeatedFailures", "reconnect"]

T = TypeVar("T")


class LinkEventKind(StrEnum):
    # a line's life (both links)
    CONNECTED = "connected"
    LOST = "lost"
    RECONNECT_FAILED = "reconnect_failed"
    RECONNECTED = "reconnected"
    CLOSED = "closed"
    # the joint line
    ERROR = "error"  # a command failed after its retries
    EMERGENCY_STOP = "emergency_stop"
    RELEASED = "released"
    # the tactile line
    CRC_ERROR = "crc_error"
    OVERSIZED = "oversized"
    BAD_FRAME = "bad_frame"
    RESYNC = "resync"
    TIMEOUT = "timeout"
    MODE = "mode"  # the acquisition mode changed (detail: the new one)


# A line's life as the log and the status tell it: why it went down (and stays down), and back up
LINE_DOWN = frozenset({LinkEventKind.LOST, LinkEventKind.RECONNECT_FAILED})
LINE_UP = frozenset({LinkEventKind.CONNECTED, LinkEventKind.RECONNECTED})


@dataclass(frozen=True, slots=True)
class LinkEvent:
    kind: LinkEventKind
    url: str
    time: float  # loop time
    detail: str = ""


@dataclass(frozen=True, slots=True)
class Backoff:
    """Delays before the attempts to reopen a line: doubling from ``initial_s`` up to ``max_s``."""

    initial_s: float
    max_s: float

    def delays(self) -> Iterator[float]:
        delay = self.initial_s
        while True:
            yield delay
            delay = min(2.0 * delay, self.max_s)


REPEAT_SAID_S = 600.0  # a line failing to reopen the same way is said again at most this often


class RepeatedFailures:
    """Which of a line's failed reopenings are worth a warning: the first of a spell, one whose
    reason changed, and one every :data:`REPEAT_SAID_S` (saying how many came between); the
    rest are logged at DEBUG. With the hand switched off, the two lines failing every 4–5 s wrote
    ≈ 27 warnings a minute, the same two, while the status said the lines were down."""

    def __init__(self) -> None:
        self._reason: str | None = None
        self._said_at = -math.inf
        self._unsaid = 0

    def note(self, kind: LinkEventKind, detail: str, now: float) -> tuple[bool, str]:
        """For an event of ``kind`` at loop time ``now``: whether to log it quietly, and what
        to add to its line."""
        if kind in LINE_UP:
            self._reason, self._said_at, self._unsaid = None, -math.inf, 0
        if kind is not LinkEventKind.RECONNECT_FAILED:
            return False, ""
        if detail == self._reason and now - self._said_at < REPEAT_SAID_S:
            self._unsaid += 1
            return True, ""
        alike = detail == self._reason and self._unsaid
        more = f" (and {self._unsaid} times alike since)" if alike else ""
        self._reason, self._said_at, self._unsaid = detail, now, 0
        return False, more

    def level(self, kind: LinkEventKind, detail: str, now: float, warn: bool) -> tuple[int, str]:
        """The logging level of an event (WARNING if ``warn``, else INFO; DEBUG when
        :meth:`note` quiets it) and what to add to its line."""
        quiet, more = self.note(kind, detail, now)
        return (logging.DEBUG if quiet else logging.WARNING if warn else logging.INFO), more


def failure_after(kind: LinkEventKind, detail: str, failure: str | None) -> str | None:
    """Why a line is down once an event of ``kind`` happened (``failure``: why it was): a loss
    or failed reconnect says why, its coming up clears it, anything else leaves it."""
    if kind in LINE_DOWN:
        return detail
    return None if kind in LINE_UP else failure


async def reconnect(
    connect: Callable[[], Awaitable[T]],
    backoff: Backoff,
    failed: Callable[[Exception], None],
    *,
    at_once: bool = False,
) -> T:
    """``connect()`` after each back-off delay (``at_once``: the first attempt without one, as
    a line opened in the background) until it succeeds; ``failed(exc)`` for every attempt that
    raised (whatever went wrong, the next attempt follows)."""
    for i, delay in enumerate(backoff.delays()):
        if not (at_once and i == 0):
            await asyncio.sleep(delay)
        try:
            return await connect()
        except Exception as exc:
            failed(exc)
    raise AssertionError("back-off delays never end")
