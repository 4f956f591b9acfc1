"""The joint angles read continuously: the pure poll plan, and the link's poller on a virtual clock.

The link tests run the SDH2 emulator behind a Unix socket on fast mode's virtual clock, so every
time below is line time, exact: a command that went out at once went out at the same instant.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TypeVar

import pytest

from sdh2svc.bus.joint import EmergencyStopped, JointLink, JointReading
from sdh2svc.bus.polling import PollPlan
from sdh2svc.protocol.sdh import NUM_AXES
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.endpoint import UnixEndpoint
from sdh2svc.sim.sdh2 import Sdh2Emulator, Sdh2Options
from sdh2svc.sim.world import ScriptedWorld

T = TypeVar("T")
PERIOD = 1 / 30  # a control loop on 30 frames/s
POSE = (10.0, -20.0, 15.0, -25.0, 5.0, -20.0, 10.0)


# -- the plan (pure) -----------------------------------------------------------------------------


def _rhythm(plan: PollPlan, beats: int, t0: float = 0.0, rtt: float = 0.005) -> float:
    """``beats`` beats one period apart, each followed by its command; returns the last one."""
    t = t0
    for i in range(beats):
        t = t0 + i * PERIOD
        plan.beat(t)
        plan.command()
    plan.polled(t - rtt - plan.guard_s, t - plan.guard_s)  # answered just before the beat
    return t


def test_no_rhythm_no_plan() -> None:
    plan = PollPlan()
    assert plan.start_at(0.0) is None
    plan.beat(0.0)
    plan.command()
    assert plan.start_at(0.001) is None  # one beat is no rhythm yet


def test_the_poll_is_answered_a_margin_before_the_next_beat() -> None:
    plan = PollPlan()
    last = _rhythm(plan, 5)
    assert plan.margin_s == pytest.approx(plan.guard_s)  # a steady rhythm: no jitter
    latest = last + PERIOD - plan.guard_s - 0.005
    assert plan.start_at(last + 0.001) == pytest.approx(latest)  # as late as possible
    assert plan.start_at(latest) == pytest.approx(latest)
    plan.polled(latest, latest + 0.005)
    # Read in its slot: the next poll after the next beat, or once that is overdue.
    assert plan.start_at(latest + 0.006) == pytest.approx(last + PERIOD * (1 + plan.late))
    assert plan.start_at(last + PERIOD * (1 + plan.late) + 1e-6) is None  # the loop stopped


def test_a_missed_slot_waits_for_the_next_unless_a_beat_went_without() -> None:
    plan = PollPlan()
    last = _rhythm(plan, 5)
    due = last + PERIOD
    after_beat = due + plan.late * PERIOD
    assert plan.start_at(due - 0.006) == pytest.approx(after_beat)  # missed: not across the beat
    plan.beat(due)  # this beat takes the angles read before the last one
    plan.command()
    late = due + PERIOD - plan.guard_s - 0.005 + 0.001  # this slot missed too
    assert plan.start_at(late) == late  # a second beat must not go without


def test_a_beat_without_a_slot_is_read_right_after_its_command() -> None:
    plan = PollPlan()
    last = _rhythm(plan, 5, rtt=0.040)  # a round trip longer than the period
    assert plan.start_at(last + 0.001) == last + 0.001  # fresh angles first
    plan.polled(last + 0.001, last + 0.041)
    assert plan.start_at(last + 0.042) is None  # beat overdue: the caller's own terms


def test_no_poll_between_a_beat_and_its_command() -> None:
    plan = PollPlan()
    _rhythm(plan, 5)
    plan.beat(10.0)  # after a pause: no rhythm, but the command is on its way
    assert plan.start_at(10.001) == pytest.approx(10.0 + plan.hold_s)
    plan.command()
    assert plan.start_at(10.001) is None


def test_a_jittery_rhythm_widens_the_margin() -> None:
    plan = PollPlan()
    for i in range(20):
        plan.beat(i * PERIOD + (0.004 if i % 2 else 0.0))  # frames of alternating size
        plan.command()
    assert plan.margin_s > plan.guard_s + 0.004


def test_a_long_pause_starts_a_new_rhythm() -> None:
    plan = PollPlan()
    _rhythm(plan, 5)
    plan.beat(5.0)
    assert plan.period_s is None and plan.jitter_s == 0.0


# -- the link's poller (virtual clock) ------------------------------------------------------------


@asynccontextmanager
async def _link(
    tmp_path: Path, options: Sdh2Options | None = None
) -> AsyncIterator[tuple[JointLink, Sdh2Emulator]]:
    """The link on the emulator; with ``options`` (a timing) in binary, as the service."""
    dev = Sdh2Emulator(ScriptedWorld([(14, 6), (13, 6)] * 3), options=options)
    async with UnixEndpoint(dev, str(tmp_path / "sdh.sock"), whole_packets=True) as ep:
        link = await JointLink.open(ep.url, binary=options is not None)
        try:
            yield link, dev
        finally:
            await link.close()


def _fast(
    tmp_path: Path,
    body: Callable[[JointLink, Sdh2Emulator], Awaitable[T]],
    options: Sdh2Options | None = None,
) -> T:
    async def main() -> T:
        async with _link(tmp_path, options) as (link, dev):
            return await body(link, dev)

    return run_fast(main())


@dataclass(frozen=True)
class Beat:
    """One iteration of a 30 Hz control loop: when it took the angles, when they were read,
    when its command went on the line, and how many exchanges it took to command and move."""

    t: float
    read_at: float
    sent: float
    exchanges: int


def _control_loop(beats: int) -> Callable[[JointLink, Sdh2Emulator], Awaitable[list[Beat]]]:
    """A control loop at 30 Hz: take the angles, command the targets and move, ``beats`` times."""

    async def loop_30hz(link: JointLink, _: Sdh2Emulator) -> list[Beat]:
        loop = asyncio.get_running_loop()
        await link.set_velocities((40.0,) * NUM_AXES)
        link.start_polling()
        out = []
        t = loop.time()
        for _ in range(beats):
            t += PERIOD
            await asyncio.sleep(t - loop.time())
            reading = link.take_reading()
            assert reading is not None
            before = link.stats.commands
            sent = await link.send_targets(POSE)
            await link.move()
            out.append(Beat(t, reading.at, sent, link.stats.commands - before))
        return out

    return loop_30hz


def test_a_control_loop_commands_at_once_on_fresh_angles(tmp_path: Path) -> None:
    beats = [(b.t, b.read_at, b.sent) for b in _fast(tmp_path, _control_loop(60))[10:]]
    assert all(sent == t for t, _, sent in beats)  # no poll in the way: the command left at once
    ages = [t - at for t, at, _ in beats]
    assert max(ages) <= 0.004  # answered just before the beat (the plan's 2 ms guard)
    assert len({at for _, at, _ in beats}) == len(beats)  # a new reading every beat


@pytest.mark.parametrize("firmware_s", [0.00207, 0.003, 0.004])
def test_no_poll_between_a_command_and_its_move_at_the_real_hand_s_timing(
    tmp_path: Path, firmware_s: float
) -> None:
    """At the real hand's line timing (the firmware's time per binary frame as config/sim.toml
    says, and a little slower: those figures are approximate) a ``p`` takes 8–10 ms. Once it
    took longer than a quarter period, the poll planned before the beat for a quarter period
    after it fired during the ``p`` and went on the line before the loop's ``m``: the ``m``
    came a whole poll late, the next poll after it late too, at times still on the line when
    the next beat's command came (bench service: sense→command p99 ×2). A beat now makes the
    poller plan again."""

    timing = Sdh2Options(ascii_latency_s=0.0049, binary_latency_s=firmware_s)
    run = _fast(tmp_path, _control_loop(90), timing)[10:]  # once the rhythm is learnt
    beats = [(b.t, b.sent, b.exchanges) for b in run]  # p, m and any poll between
    assert [n for _, _, n in beats] == [2] * len(beats)  # p and m only: no poll in between
    assert all(sent == t for t, sent, _ in beats)  # and none in the way of the command


def test_the_poller_keeps_the_newest_angles(tmp_path: Path) -> None:
    async def follow(link: JointLink, dev: Sdh2Emulator) -> tuple[JointReading, float, tuple]:
        loop = asyncio.get_running_loop()
        link.start_polling(idle_s=0.05)
        await link.set_velocities((40.0,) * NUM_AXES)
        await link.set_targets(POSE)
        await link.move()
        await asyncio.sleep(2.0)  # the move is over by now
        reading = link.reading
        assert reading is not None
        return reading, loop.time(), dev.actual_deg

    reading, now, actual = _fast(tmp_path, follow)
    assert reading.angles == pytest.approx(actual, abs=1e-3)
    assert now - reading.at <= 0.05 + 0.01  # one idle period and a round trip at most


def test_commands_wait_at_most_one_poll(tmp_path: Path) -> None:
    async def busy(link: JointLink, _: Sdh2Emulator) -> tuple[list[float], float, int]:
        loop = asyncio.get_running_loop()
        link.start_polling(idle_s=0.001)  # the line nearly always busy with polls
        before = link.reading
        waits = []
        for i in range(30):
            await asyncio.sleep(0.0007 * (i % 7))
            t0 = loop.time()
            await link.get_state()
            waits.append(loop.time() - t0)
        assert link.reading is not before
        return waits, link.stats.rtt_max_s, link.stats.commands

    waits, rtt_max, _ = _fast(tmp_path, busy)
    assert max(waits) <= 2 * rtt_max + 1e-9  # the poll on the line, then its own exchange


def test_the_emergency_stop_goes_first_and_polling_goes_on(tmp_path: Path) -> None:
    async def estop(link: JointLink, dev: Sdh2Emulator) -> tuple[float, float, int]:
        loop = asyncio.get_running_loop()
        link.start_polling(idle_s=0.001)
        await asyncio.sleep(0.05)
        queued = asyncio.create_task(link.get_state())
        await asyncio.sleep(0)
        t0 = loop.time()
        await link.emergency_stop()
        took = loop.time() - t0
        with pytest.raises(EmergencyStopped):
            await queued
        assert dev.powered == (False,) * NUM_AXES
        stopped_at = loop.time()
        await asyncio.sleep(0.05)
        assert link.reading is not None and link.reading.at > stopped_at  # still reading
        return took, link.stats.rtt_max_s, link.stats.failures

    took, rtt_max, failures = _fast(tmp_path, estop)
    assert took <= 4 * rtt_max  # at most the poll on the line, then power, pos, p
    assert failures == 0
