"""Act on wake-ups at most a given number of times a second (the 3-D view's frames)."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable


async def paced(wake: asyncio.Event, period: float, act: Callable[[], Awaitable[bool]]) -> None:
    """Call ``act`` when ``wake`` is set, at most about once per ``period`` seconds, for ever.

    "About": acts are at least 0.9 periods apart, so that wake-ups coming at the period's own
    rate, with some jitter, are each acted on rather than every other one.

    Telemetry is delivered in the control loop's quiet time, after an iteration, so acting on
    delivery never falls inside an iteration: a wake-up too soon after the last act is merged
    into the next, acted on at the next wake-up (or one period later if none comes), never on
    a timer of its own. ``act`` returns whether it did something (only then the period runs)."""
    loop = asyncio.get_running_loop()
    last = -math.inf
    while True:
        await wake.wait()
        while (early := last + 0.9 * period - loop.time()) > 0:
            wake.clear()
            try:
                async with asyncio.timeout(early + period):
                    await wake.wait()
            except TimeoutError:
                break
        wake.clear()
        if await act():
            last = loop.time()
