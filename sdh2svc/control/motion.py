"""Moves that stop when their loop stops: every command leaves the hand at most one increment.

The SDH2 firmware has no watchdog: a velocity or a move, once commanded, goes on until it ends
or another command arrives, whether or not the host that sent it still lives (protocols.md §2.4).
So a long move is never commanded at once. :func:`move_in_increments` re-targets the fingers at
most ``max_step_deg`` ahead of where they actually are, round trip after round trip; if the loop
stops — its process killed, its line cut, its task cancelled — the fingers stop within that one
increment (≤ 1°, :class:`~sdh2svc.control.safety.SafetyConfig`).
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Callable, Sequence

from sdh2svc.bus.joint import ControllerMode, JointLink, JointLinkError
from sdh2svc.control.safety import RunConfig, SafetyConfig, clamp_targets
from sdh2svc.protocol.sdh import AxisState

MOVE_PERIOD_S = 0.01  # pause between increments: the line stays free for others (≈ 40 Hz loop)
PROGRESS_DEG = 0.05  # the largest gap to the goal shrank by this: progress
STALL_S = 2.0  # no progress for this long: blocked (an obstacle, an axis that does not move)
STATE_POLL_S = 0.02  # the last increment's state polls (SDHLibrary's WaitAxis)
BUSY = (AxisState.POSITIONING, AxisState.SPEED_MODE)

Check = Callable[[], None]  # raises to abort the move (e.g. a force above the ceiling)


class MoveBlocked(JointLinkError):
    """The fingers stopped short of the goal (something in the way, or an axis not moving)."""


async def move_in_increments(
    joints: JointLink,
    goal: Sequence[float],
    *,
    velocity_deg_s: float,
    lo: Sequence[float],
    hi: Sequence[float],
    max_step_deg: float,
    check: Check | None = None,
) -> tuple[float, ...]:
    """Move to ``goal`` (7 wire-axis angles, deg, clamped to [lo, hi]) in increments of at most
    ``max_step_deg`` ahead of the actual angles; returns the final actual angles.

    ``check`` runs before every increment, and while the firmware finishes the last one, and
    aborts the move by raising (the hand is then held where it is by the caller). Raises
    :class:`MoveBlocked` when the fingers stop making progress for :data:`STALL_S`, or the
    last increment outlasts its own duration by as much.
    """
    if not all(math.isfinite(g) for g in goal):
        raise ValueError(f"a goal angle is no finite number: {list(goal)}")
    goal = tuple(min(b, max(a, g)) for g, a, b in zip(goal, lo, hi, strict=True))
    await joints.set_controller(ControllerMode.POSE)
    await joints.set_velocities([velocity_deg_s] * len(goal))
    if joints.acceleration_limits:
        await joints.set_accelerations(joints.acceleration_limits)
    loop = asyncio.get_running_loop()
    best, last_progress = float("inf"), loop.time()
    while True:
        actual = await joints.get_actual()
        if check is not None:
            check()
        targets = clamp_targets(goal, actual, lo, hi, max_step_deg)
        await joints.set_targets(targets)
        duration_s = await joints.move()
        if targets == goal:  # the last increment: the firmware finishes it, watched as the rest
            await _finish(joints, duration_s, check)
            return await joints.get_actual()
        gap = max(abs(g - a) for g, a in zip(goal, actual, strict=True))
        if gap < best - PROGRESS_DEG:
            best, last_progress = gap, loop.time()
        elif loop.time() - last_progress > STALL_S:
            raise MoveBlocked(f"the fingers stopped {gap:.1f}° short of the pose")
        await asyncio.sleep(MOVE_PERIOD_S)


async def _finish(joints: JointLink, duration_s: float, check: Check | None) -> None:
    """Wait for the firmware to end the last increment (``duration_s``: ``m``'s answer), the
    check going on meanwhile; an axis still busy :data:`STALL_S` after that is blocked."""
    loop = asyncio.get_running_loop()
    wait_s = (duration_s if 0.0 < duration_s < math.inf else 0.0) + STALL_S  # (NaN: 0)
    deadline = loop.time() + wait_s
    while any(s in BUSY for s in await joints.get_state()):
        if check is not None:
            check()
        if loop.time() > deadline:
            raise MoveBlocked(f"the fingers did not end the pose's last increment "
                              f"{wait_s:.1f} s after it began")  # fmt: skip
        await asyncio.sleep(STATE_POLL_S)


async def move_to_preshape(
    joints: JointLink,
    run: RunConfig,
    limits: tuple[Sequence[float], Sequence[float]],
    safety: SafetyConfig,
    check: Check | None = None,
) -> tuple[float, ...]:
    """Open the coupled fingers to ``run.preshape_deg`` at the pre-shape speed (a run's
    pre-shape and release, the service's Open hand); ``limits`` are (min_deg, max_deg)."""
    lo, hi = limits
    return await move_in_increments(
        joints,
        run.preshape_deg,
        velocity_deg_s=run.preshape_velocity_deg_s,
        lo=lo,
        hi=hi,
        max_step_deg=safety.max_step_deg,
        check=check,
    )
