"""The joint link never leaves motion running that no live loop commands.

The emulator keeps a velocity or a move going until another command arrives, whether a host is
connected or not — as the firmware does (protocols.md §2.4, PART 4). These tests prove that the
driver stops it: on every connect and reconnect, and before retrying a spoilt exchange.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from sdh2svc.bus.joint import (
    ControllerMode,
    EmergencyStopped,
    JointLink,
    JointLinkError,
    LinkEvent,
    LinkEventKind,
)
from sdh2svc.protocol.sdh import AxisState
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.endpoint import FaultConfig, UnixEndpoint, serve_device
from sdh2svc.sim.sdh2 import Sdh2Emulator
from sdh2svc.sim.world import ScriptedWorld

SHAPES = [(14, 6), (13, 6)] * 3
CLOSING = (0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # axis 1 closing at 10 °/s


@pytest.fixture(params=["pty", "tcp"])
async def served(request: pytest.FixtureRequest) -> AsyncIterator[tuple[Sdh2Emulator, str, object]]:
    dev = Sdh2Emulator(ScriptedWorld(SHAPES))
    async with serve_device(dev, request.param) as ep:
        yield dev, ep.url, ep


async def _abandon_a_velocity(url: str) -> None:
    """A host that starts a velocity and dies without a word (its port simply closes)."""
    host = await JointLink.open(url, reconnect=False)
    await host.set_controller(ControllerMode.VELOCITY)
    await host.tvav(CLOSING)
    await host.close()


async def test_a_velocity_left_by_a_dead_host_is_stopped_on_connect(served) -> None:
    dev, url, _ = served
    await _abandon_a_velocity(url)
    assert dev.moving  # the firmware keeps it: nobody stopped it
    async with await JointLink.open(url) as link:
        assert not dev.moving
        held = await link.get_actual()
        assert link.controller is ControllerMode.POSE
        assert dev.target_deg == pytest.approx(held)
        await asyncio.sleep(0.2)
        assert await link.get_actual() == pytest.approx(held, abs=1e-6)  # still


async def test_a_reconnect_stops_what_ran_while_the_line_was_down() -> None:
    dev = Sdh2Emulator(ScriptedWorld(SHAPES))
    async with serve_device(dev, "tcp") as ep, await JointLink.open(ep.url) as link:
        events = link.subscribe()
        await link.set_controller(ControllerMode.VELOCITY)
        await link.tvav(CLOSING)
        ep.disconnect(0.5)  # the cable is cut while the finger closes
        while (await events.get()).kind is not LinkEventKind.LOST:
            pass
        assert dev.moving  # nothing reaches the hand while the line is down
        while (await events.get()).kind is not LinkEventKind.RECONNECTED:
            pass
        assert not dev.moving
        held = await link.get_actual()
        await asyncio.sleep(0.2)
        assert await link.get_actual() == pytest.approx(held, abs=1e-6)


async def test_a_spoilt_reply_during_a_move_stops_the_move_before_the_retry(served) -> None:
    dev, url, _ = served
    async with await JointLink.open(url, timeout_s=0.3) as link:
        await link.set_targets((0.0, 80.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        await link.move()  # a long move: ≈ 2 s at the default 40 °/s
        assert dev.moving
        real = dev.next_packet
        spoilt = []

        def garble_once(now: float) -> bytes | None:
            packet = real(now)
            if packet is not None and not spoilt:
                spoilt.append(packet)
                return b"POS=garbage\r\n"
            return packet

        dev.next_packet = garble_once  # type: ignore[method-assign]
        actual = await link.get_actual()  # spoilt, then retried
        assert spoilt and link.stats.garbled == 1 and link.stats.retries == 1
        assert link.stats.motion_stops == 1
        assert not dev.moving
        assert actual[1] < 60.0


async def test_a_target_echoed_wrong_is_set_again_not_moved_to(served) -> None:
    """ASCII has no checksum: a digit flipped on the way to the hand sets another target, which
    the next `m` would drive the finger to in one move. The set command's echo must be what was
    sent, or the exchange is spoilt and sent again (a mutation audit made the check always pass
    and every other test passed)."""
    dev, url, _ = served
    async with await JointLink.open(url, timeout_s=0.3) as link:
        real = dev.next_packet
        flipped: list[bytes] = []

        def flip_the_echo(now: float) -> bytes | None:
            packet = real(now)
            if packet is not None and packet.startswith(b"P=") and not flipped:
                flipped.append(packet)
                return b"P=12.500" + packet[packet.index(b",") :]  # as if 2.5 became 12.5
            return packet

        dev.next_packet = flip_the_echo  # type: ignore[method-assign]
        garbled = link.stats.garbled
        echoed = await link.set_targets((0.0, 2.5, 0.0, 0.0, 0.0, 0.0, 0.0))
        assert flipped and link.stats.garbled == garbled + 1  # taken as spoilt, and sent again
        assert echoed == pytest.approx((0.0, 2.5, 0.0, 0.0, 0.0, 0.0, 0.0))
        assert dev.target_deg == pytest.approx((0.0, 2.5, 0.0, 0.0, 0.0, 0.0, 0.0))


# -- on a fast-mode line (a Unix socket, virtual clock), what the hand received and when --------


class _Heard(Sdh2Emulator):
    """Logs every piece of bytes it receives, with the loop time."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.heard: list[tuple[float, bytes]] = []

    def receive(self, data: bytes, now: float) -> None:
        self.heard.append((now, bytes(data)))
        super().receive(data, now)

    def since(self, t0: float) -> list[bytes]:
        return [d for t, d in self.heard if t >= t0]

    def first(self, data: bytes, t0: float) -> float | None:
        return next((t for t, d in self.heard if t >= t0 and data in d), None)


@contextlib.asynccontextmanager
async def _fast_line(tmp_path: Path, dev: Sdh2Emulator) -> AsyncIterator[tuple[UnixEndpoint, str]]:
    async with UnixEndpoint(dev, str(tmp_path / "sdh.sock"), whole_packets=True) as ep:
        yield ep, ep.url


@contextlib.asynccontextmanager
async def _heard_link(tmp_path: Path) -> AsyncIterator[tuple[_Heard, UnixEndpoint, JointLink]]:
    """A hand that logs what it hears on a fast-mode line, and a link open on it that retries
    (1 s per attempt, 3 retries)."""
    dev = _Heard(ScriptedWorld(SHAPES))
    async with (
        _fast_line(tmp_path, dev) as (ep, url),
        await JointLink.open(url, timeout_s=1.0, retries=3) as link,
    ):
        yield dev, ep, link


POWER_OFF = b"power=0,0,0,0,0,0,0"


async def _abandon_a_grip(url: str, velocity_deg_s: float = 5.0) -> None:
    """A host (SCHUNK's demo, a script) pre-shapes for a grasp, starts a slow grip and dies."""
    host = await JointLink.open(url, reconnect=False)
    await host.command("selgrip", 1)
    await host.wait_idle()
    await host.command("grip", (1.0, velocity_deg_s))
    await host.close()


def test_a_grip_left_running_by_another_program_ends_on_connect(tmp_path: Path) -> None:
    """`stop` does not end a selgrip/grip move (protocols.md §2.4): the handshake finds the axes
    still positioning after its stop, and ends the move (`con=0`)."""

    async def main() -> None:
        dev = Sdh2Emulator(ScriptedWorld(SHAPES))
        async with _fast_line(tmp_path, dev) as (_, url):
            await _abandon_a_grip(url)
            await asyncio.sleep(0.2)
            assert dev.moving  # closing, with no host at all
            async with await JointLink.open(url) as link:
                assert not dev.moving
                held = await link.get_actual()
                await asyncio.sleep(3.0)  # the grip had ≥ 10 s to go at 5 °/s
                assert await link.get_actual() == pytest.approx(held, abs=1e-6)
                assert all(s is AxisState.IDLE for s in await link.get_state())
                assert all(dev.powered[1:])  # ended, not switched off

    run_fast(main())


class _GripOutlivesCon(Sdh2Emulator):
    """A firmware whose `con=0` does not end a grip either (what the real one does is not in
    our sources)."""

    def _set_controller(self, con: int) -> None:
        move, in_move = self._move, list(self._ax.in_move)
        super()._set_controller(con)
        if move is not None and not move.stoppable:
            self._move, self._ax.in_move[:] = move, in_move


def test_a_grip_that_neither_stop_nor_con_ends_is_powered_off_on_connect(tmp_path: Path) -> None:
    async def main() -> None:
        dev = _GripOutlivesCon(ScriptedWorld(SHAPES))
        async with _fast_line(tmp_path, dev) as (_, url):
            await _abandon_a_grip(url)
            await asyncio.sleep(0.2)
            seen: list[LinkEvent] = []
            async with await JointLink.open(url, on_event=seen.append) as link:
                assert not any(dev.powered) and not dev.moving
                held = await link.get_actual()
                await asyncio.sleep(3.0)
                assert await link.get_actual() == pytest.approx(held, abs=1e-6)
                assert any(e.kind is LinkEventKind.ERROR and "powered off" in e.detail
                           for e in seen), seen  # fmt: skip

    run_fast(main())


@pytest.mark.parametrize("during", ["hold", "get_actual"])
def test_an_estop_goes_before_the_retries_of_a_hold_on_a_bad_line(
    tmp_path: Path, during: str
) -> None:
    """Every reply cut short: a hold (a run's halt after a fault, a stopped *Open hand*) retries
    each of its commands. The e-stop's power-off goes after the attempt in flight, not after
    the hold's every retry (1.7 s before: the hold's commands did not give way)."""

    async def main() -> None:
        async with _heard_link(tmp_path) as (dev, ep, link):
            loop = asyncio.get_running_loop()
            await link.set_targets((0.0, 30.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            await link.move()  # the hand may be moving: each retry sends `stop` first
            ep.set_faults(FaultConfig(truncate_packet_rate=1.0))
            busy = asyncio.ensure_future(getattr(link, during)())
            await asyncio.sleep(0.01)
            t0 = loop.time()
            estop = asyncio.ensure_future(link.emergency_stop())
            with pytest.raises(EmergencyStopped):
                await busy
            ep.set_faults(FaultConfig())
            with contextlib.suppress(JointLinkError):
                await estop
            sent = dev.first(POWER_OFF, t0)
            assert sent is not None and sent - t0 < 0.3, sent and sent - t0
            assert not any(dev.powered)

    run_fast(main())


@pytest.mark.parametrize("line", ["needs a resync", "retrying"])
def test_no_move_goes_on_the_line_after_the_estop(tmp_path: Path, line: str) -> None:
    """A move that passed the latch's check before the e-stop came, then waited on the line (a
    resync first, or a retry's `stop`), is abandoned: no `m` after the e-stop (`m` also powers
    the axes on), and the power-off does not wait for it."""

    async def main() -> None:
        async with _heard_link(tmp_path) as (dev, ep, link):
            loop = asyncio.get_running_loop()
            await link.set_targets((0.0, 10.0, 0.0, 0.0, 0.0, 0.0, 0.0))
            if line == "needs a resync":  # an exchange its caller gave up mid-reply
                read = asyncio.ensure_future(link.get_actual())
                await asyncio.sleep(0.0005)
                read.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await read
                move = asyncio.ensure_future(link.move())
                await asyncio.sleep(0.005)  # in the resync's drain
            else:  # the `m`'s reply lost whole: its retry's `stop` is out
                await link.move()
                await link.set_targets((0.0, 20.0, 0.0, 0.0, 0.0, 0.0, 0.0))
                ep.set_faults(FaultConfig(drop_byte_rate=1.0))
                move = asyncio.ensure_future(link.move())
                await asyncio.sleep(0.15)
                ep.set_faults(FaultConfig())
            t0 = loop.time()
            held = await link.emergency_stop()
            with pytest.raises(EmergencyStopped):
                await move
            assert b"m\r\n" not in dev.since(t0), dev.since(t0)
            sent = dev.first(POWER_OFF, t0)
            assert sent is not None and sent - t0 < 0.1, sent - t0 if sent else None
            assert dev.target_deg == pytest.approx(held)

    run_fast(main())
