"""What both links share about their line's life: one event type, one reconnect with back-off.

A link reports what happens on its line as :class:`LinkEvent` values (the kinds of both lines in
one :class:`LinkEventKind`), and reopens a lost line with :func:`reconnect`: exponential back-off
from ``initial_s`` to ``max_s``, every failed attempt reported, never giving up (the hand needs
its lines).
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass
from enum import StrEnum
from typing import TypeVar

__all__ = ["Backoff", "LinkEvent", "LinkEventKind", "reconnect"]

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
