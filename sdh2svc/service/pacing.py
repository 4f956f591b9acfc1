"""Act on wake-ups or deliveries at most a given number of times a second (the 3-D view's
frames, the live Foxglove view's 3-D channels)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable

# acts at least this many periods apart: deliveries at the period's own rate, with some jitter,
# are each acted on rather than every other one
SLACK = 0.9


async def paced(wake: asyncio.Event, period: float, act: Callable[[], Awaitable[bool]]) -> None:
    """Call ``act`` when ``wake`` is set, at most about once per ``period`` seconds, for ever.

    "About": acts are at least :data:`SLACK` periods apart.

    Telemetry is delivered in the control loop's quiet time, after an iteration, so acting on
    delivery never falls inside an iteration: a wake-up too soon after the last act is merged
    into the next, acted on at the next wake-up (or one period later if none comes), never on
    a timer of its own. ``act`` returns whether it did something (only then the period runs)."""
    loop = asyncio.get_running_loop()
    last = -math.inf
    while True:
        await wake.wait()
        while (early := last + SLACK * period - loop.time()) > 0:
            wake.clear()
            try:
                async with asyncio.timeout(early + period):
                    await wake.wait()
            except TimeoutError:
                break
        wake.clear()
        if await act():
            last = loop.time()


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
