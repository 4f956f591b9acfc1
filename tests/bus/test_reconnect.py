"""The links' shared reconnect: back-off delays, every failure reported, never giving up."""

from __future__ import annotations

import asyncio
import itertools

import pytest

from sdh2svc.bus.joint import BACKOFF
from sdh2svc.bus.reconnect import (
    REPEAT_SAID_S,
    Backoff,
    LinkEventKind,
    RepeatedFailures,
    reconnect,
)
from sdh2svc.bus.tactile import TactileOptions
from sdh2svc.sim.clock import run_fast


def _first(backoff: Backoff, n: int) -> list[float]:
    return list(itertools.islice(backoff.delays(), n))


def test_each_links_backoff() -> None:
    assert _first(BACKOFF, 7) == [0.5, 1.0, 2.0, 4.0, 5.0, 5.0, 5.0]
    o = TactileOptions()
    assert _first(Backoff(o.backoff_initial_s, o.backoff_max_s), 6) == [0.25, 0.5, 1, 2, 4, 4]


def test_reconnect_retries_after_each_delay_until_it_succeeds() -> None:
    attempts: list[float] = []
    failures: list[str] = []

    async def main() -> tuple[str, float]:
        loop = asyncio.get_running_loop()

        async def connect() -> str:
            attempts.append(loop.time())
            if len(attempts) < 4:
                raise OSError(f"no way in ({len(attempts)})")
            return "line"

        t0 = loop.time()
        line = await reconnect(connect, Backoff(0.5, 5.0), lambda e: failures.append(str(e)))
        return line, loop.time() - t0

    line, took = run_fast(main())
    assert line == "line"
    assert took == pytest.approx(0.5 + 1.0 + 2.0 + 4.0)
    assert failures == ["no way in (1)", "no way in (2)", "no way in (3)"]


def test_a_line_failing_alike_is_warned_of_once_in_a_while() -> None:
    """The hand switched off: both lines failed to reopen every 4–5 s, each failure a warning
    (≈ 27 a minute in the journal, the same two). The first of a spell, a changed reason, and
    one every REPEAT_SAID_S (with how many came between) are warnings; the rest are quiet."""
    failed, up = LinkEventKind.RECONNECT_FAILED, LinkEventKind.RECONNECTED
    refused = "cannot open: [Errno 111] Connection refused"
    repeats = RepeatedFailures()
    said = [repeats.note(failed, refused, t) for t in (0.0, 5.0, 10.0)]
    assert said == [(False, ""), (True, ""), (True, "")]
    assert repeats.note(LinkEventKind.LOST, "read failed", 12.0) == (False, "")  # not quieted
    assert repeats.note(failed, "cannot open: no such device", 15.0) == (False, "")  # new reason
    assert repeats.note(failed, refused, 20.0) == (False, "")
    assert repeats.note(failed, refused, 25.0) == (True, "")
    again = repeats.note(failed, refused, 20.0 + REPEAT_SAID_S)
    assert again == (False, " (and 1 times alike since)")
    assert repeats.note(up, "", 700.0) == (False, "")  # back up: the next spell is said again
    assert repeats.note(failed, refused, 701.0) == (False, "")
