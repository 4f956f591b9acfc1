"""Pre-shape, release and *Open hand* moves (control/motion.py) on the simulated hand, through
the real driver and bytes, on the virtual clock: as fast as ≤ 1° increments let a finger stop,
and still within one increment of where they were when their loop stops."""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Sequence
from pathlib import Path
from typing import cast

import pytest

from sdh2svc.bus.joint import JointLink
from sdh2svc.control.motion import (
    STALL_S,
    Check,
    MoveBlocked,
    move_in_increments,
    move_to_preshape,
)
from sdh2svc.protocol.sdh import AxisState
from tests.control.test_runner import cfg_with, fast, rig

FINGERS = (1, 2, 3, 4, 5, 6)
EPS = 1e-4  # the binary protocol's float32 angles


def test_a_move_runs_as_fast_as_its_increments_allow_and_stops_with_its_loop(
    tmp_path: Path,
) -> None:
    straight = [0.0, 0.0, 0.0, -90.0, 0.0, 0.0, 0.0]
    cfg = cfg_with(tmp_path, f"sim.start_deg={straight}")
    lo, hi = cfg.limits.min_deg, cfg.limits.max_deg

    async def main() -> tuple[float, tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        async with rig(cfg, tmp_path) as (_sim, runner):
            joints, loop = runner.joints, asyncio.get_running_loop()
            t0 = loop.time()
            shaped = await move_to_preshape(joints, cfg.run, (lo, hi), cfg.safety)
            took = loop.time() - t0
            # back towards straight, and the loop stops a second into the move
            back = asyncio.create_task(move_in_increments(
                joints, straight, velocity_deg_s=cfg.run.preshape_velocity_deg_s, lo=lo,
                hi=hi, max_step_deg=cfg.safety.max_step_deg))  # fmt: skip
            await asyncio.sleep(1.0)
            back.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await back
            stopped = await joints.get_actual()
            await asyncio.sleep(3.0)
            return took, shaped, stopped, await joints.get_actual()

    took, shaped, stopped, after = fast(main)
    assert max(abs(a - g) for a, g in zip(shaped, cfg.run.preshape_deg, strict=True)) < 0.1
    # axis 0 turns 90°: about 5 s at the 15–20°/s that one-degree increments allow (at a
    # proximal axis's 400°/s², a finger that must stop within 1° moves at ≤ 22°/s); a pause
    # added between increments, or increments that no longer wait for the fingers, show here
    assert 4.0 < took < 6.5, took
    assert max(abs(stopped[i] - shaped[i]) for i in FINGERS) > 10.0  # it was under way …
    # … and went on at most the one increment it had been given
    assert max(abs(after[i] - stopped[i]) for i in FINGERS) <= cfg.safety.max_step_deg + EPS


class _Busy:
    """A joint link whose axes stay busy for ``busy_polls`` state polls after each move (forever
    if None): an axis the firmware keeps positioning, against something it cannot push away.
    Its fingers are already within one increment of the goal, so the first move is the last."""

    acceleration_limits: tuple[float, ...] = ()

    def __init__(self, goal: Sequence[float], busy_polls: int | None = None) -> None:
        self.actual = tuple(g - 0.5 for g in goal)
        self.busy_polls, self.polls, self.moves = busy_polls, 0, 0

    async def set_controller(self, _mode: object) -> None: ...
    async def set_velocities(self, _v: Sequence[float]) -> None: ...
    async def set_targets(self, _t: Sequence[float]) -> None: ...

    async def get_actual(self) -> tuple[float, ...]:
        return self.actual

    async def move(self) -> float:
        self.moves, self.polls = self.moves + 1, 0
        return 0.1  # s, as the firmware answers ``m``

    async def get_state(self) -> tuple[AxisState, ...]:
        await asyncio.sleep(0.004)  # a round trip
        self.polls += 1
        done = self.busy_polls is not None and self.polls > self.busy_polls
        return (AxisState.IDLE if done else AxisState.POSITIONING,) * 7

    async def wait_idle(self, poll_s: float = 0.02) -> tuple[AxisState, ...]:
        while AxisState.POSITIONING in (states := await self.get_state()):
            await asyncio.sleep(poll_s)
        return states


GOAL = (0.0, 10.0, 20.0, -30.0, 40.0, 10.0, 20.0)


async def _move(link: _Busy, check: Check | None = None) -> tuple[float, ...]:
    return await move_in_increments(cast(JointLink, link), GOAL, velocity_deg_s=20.0,
                                    lo=[-90.0] * 7, hi=[90.0] * 7, max_step_deg=1.0,
                                    check=check)  # fmt: skip


def test_a_last_increment_that_never_ends_is_a_blocked_move() -> None:
    """The last ≤ 1° is left to the firmware; an axis it keeps positioning (something in the
    way) ends the move as blocked once the increment has outlasted its own duration by
    STALL_S — it does not wait for ever."""

    async def main() -> float:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(MoveBlocked, match="did not end the pose's last increment"):
            await asyncio.wait_for(_move(_Busy(GOAL)), 60.0)
        return loop.time() - t0

    took = fast(main)
    assert STALL_S + 0.1 <= took < STALL_S + 0.2, took


def test_the_check_runs_while_the_last_increment_ends() -> None:
    """A force ceiling (the check) is watched while the firmware ends the last increment too,
    not only before each increment: it aborts the move there."""

    class Ceiling(Exception):
        pass

    link = _Busy(GOAL, busy_polls=10)

    def check() -> None:
        if link.moves:  # after the (last) increment was sent
            raise Ceiling

    async def main() -> None:
        await _move(link, check)

    with pytest.raises(Ceiling):
        fast(main)
    assert link.moves == 1 and link.polls == 1  # the first poll's check stopped it


def test_a_last_increment_that_ends_returns_the_actual_angles() -> None:
    link = _Busy(GOAL, busy_polls=3)

    async def main() -> tuple[float, ...]:
        return await _move(link)

    assert fast(main) == link.actual
    assert link.moves == 1 and link.polls == 4


class _Stuck(_Busy):
    """Fingers that do not move at all, 20° from the goal (an obstacle, a person's hand)."""

    def __init__(self, goal: Sequence[float]) -> None:
        super().__init__(goal)
        self.actual = tuple(g - 20.0 for g in goal)


def test_fingers_that_make_no_progress_end_the_move_after_stall_s() -> None:
    """Each increment is one step ahead of the actual angles: fingers that do not follow are
    pushed one step on for STALL_S, then the move ends as blocked — not ten times as long (a
    mutation audit stretched STALL_S tenfold and every other test passed)."""

    async def main() -> float:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(MoveBlocked, match=r"the fingers stopped 20\.0° short of the pose"):
            await asyncio.wait_for(_move(_Stuck(GOAL)), 60.0)
        return loop.time() - t0

    took = fast(main)
    assert STALL_S <= took < STALL_S + 0.5, took


@pytest.mark.parametrize("duration", [float("nan"), float("inf"), -1.0])
def test_a_nonsensical_move_duration_still_ends_a_blocked_last_increment(duration: float) -> None:
    """`m` answered with a NaN, infinite or negative duration: taken as none, so an axis the
    firmware keeps positioning still ends the move STALL_S later (with the duration as it came,
    the deadline never passed: a mutation audit)."""

    class Odd(_Busy):
        async def move(self) -> float:
            await super().move()
            return duration

    async def main() -> float:
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(MoveBlocked, match="did not end the pose's last increment"):
            await asyncio.wait_for(_move(Odd(GOAL)), 60.0)
        return loop.time() - t0

    took = fast(main)
    assert STALL_S <= took < STALL_S + 0.2, took
