"""paced(): act on wake-ups, at most once per period, never on a timer of its own (virtual time)."""

from __future__ import annotations

import asyncio
import itertools
from collections.abc import Callable

import pytest

from sdh2svc.service.pacing import paced
from sdh2svc.sim.clock import run_fast


def _acts(wakes: list[float], period: float, until: float, did: Callable[[int], bool]) -> list:
    """The virtual times at which ``paced`` acted, for wake-ups at ``wakes``."""

    async def main() -> list[float]:
        loop = asyncio.get_running_loop()
        t0, wake, acts = loop.time(), asyncio.Event(), []

        async def act() -> bool:
            acts.append(round(loop.time() - t0, 6))
            return did(len(acts))

        task = asyncio.create_task(paced(wake, period, act))
        for t in wakes:
            await asyncio.sleep(max(0.0, t - (loop.time() - t0)))
            wake.set()
        await asyncio.sleep(until - (loop.time() - t0))
        task.cancel()
        return acts

    return run_fast(main())


def test_a_burst_is_merged_to_at_most_one_act_per_period() -> None:
    acts = _acts([i * 0.01 for i in range(100)], 0.1, 1.2, lambda _: True)
    assert 10 <= len(acts) <= 12  # a wake-up every 10 ms for a second, 0.1 s period
    assert min(b - a for a, b in itertools.pairwise(acts)) >= 0.09 - 1e-9  # 0.9 periods
    assert acts[-1] >= 0.99  # the last wake-up (at 0.99) is acted on, not lost


def test_a_lone_early_wake_up_is_acted_on_a_period_later() -> None:
    # at 0 it acts; at 0.02 it is too soon: it waits until 0.09 for another wake-up, then one
    # more period (no wake-up of its own inside an iteration), and acts at 0.19
    assert _acts([0.0, 0.02], 0.1, 1.0, lambda _: True) == [0.0, pytest.approx(0.19)]


def test_a_wake_up_that_did_nothing_starts_no_period() -> None:
    # the first act does nothing (e.g. nobody watches): the next wake-up is acted on at once
    assert _acts([0.0, 0.01], 0.1, 1.0, lambda n: n > 1) == [0.0, 0.01]
