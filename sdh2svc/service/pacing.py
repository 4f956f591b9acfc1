"""Act on wake-ups or deliveries at most a given number of times a second (the 3-D view's
frames, the live Foxglove view's 3-D channels).

:func:`paced` keeps "at most" on average, with a budget (a token bucket): each period earns
one act, up to :data:`BURST` saved, and acts are at least :data:`MIN_GAP` periods apart. A
fixed least gap alone (the former rule: 0.9 periods) halved the rate of deliveries that come at
about the period's own rate: the control loop's iterations at 29 Hz under a 30 Hz cap, a few ms
of jitter each, put one delivery in three or so inside the gap, and each of those waited for the
next — the 3-D view drew at ~16 Hz. With the budget, a delivery late by a few ms leaves its
credit to the next one, early by as much.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

BURST = 1.5  # acts a period's budget may hold (≥ 1): what a late delivery leaves to the next
MIN_GAP = 0.5  # acts at least this many periods apart, whatever was saved


class _Budget:
    """Whether an act is due at ``now``, and when it will be (times in seconds)."""

    def __init__(self, period: float) -> None:
        self.period = period
        self._tokens = BURST
        self._at = -math.inf  # when the tokens were counted
        self._last = -math.inf  # the last act

    def _tokens_at(self, now: float) -> float:
        if self._at == -math.inf:
            return BURST
        return min(BURST, self._tokens + (now - self._at) / self.period)

    def wait(self, now: float) -> float:
        """Seconds until an act is allowed (≤ 0: now)."""
        short = max(0.0, 1.0 - self._tokens_at(now)) * self.period
        return max(short, self._last + MIN_GAP * self.period - now)

    def spend(self, now: float) -> None:
        self._tokens, self._at, self._last = self._tokens_at(now) - 1.0, now, now


async def paced(wake: asyncio.Event, period: float, act: Callable[[], Awaitable[bool]]) -> None:
    """Call ``act`` when ``wake`` is set, at most once per ``period`` seconds on average (see the
    module doc), for ever.

    Telemetry is delivered in the control loop's quiet time, after an iteration, so acting on
    delivery never falls inside an iteration: a wake-up before the budget allows is merged into
    the next, acted on at the next wake-up (or one period after it would have been allowed, if
    none comes), never on a timer of its own. ``act`` returns whether it did something (only
    then is the budget spent)."""
    loop = asyncio.get_running_loop()
    budget = _Budget(period)
    while True:
        await wake.wait()
        while (early := budget.wait(loop.time())) > 0:
            wake.clear()
            try:
                async with asyncio.timeout(early + period):
                    await wake.wait()
            except TimeoutError:
                break
        wake.clear()
        if await act():
            budget.spend(loop.time())


# Throttle's least gap (it drops what it does not act on, so it keeps the former rule; its
# deliveries' jitter is the hub's, not an iteration's)
SLACK = 0.9


class Throttle:
    """The synchronous kind, for deliveries acted on at once: :meth:`due` at most about once per
    ``period_s`` (at least :data:`SLACK` periods apart); a delivery not acted on is dropped."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._last = -math.inf

    def due(self, now: float) -> bool:
        """Whether acting at ``now`` keeps the pace (it then counts as acted on)."""
        if now - self._last < SLACK * self.period_s:
            return False
        self._last = now
        return True
