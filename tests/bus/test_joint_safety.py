"""The joint link never leaves motion running that no live loop commands.

The emulator keeps a velocity or a move going until another command arrives, whether a host is
connected or not — as the firmware does (protocols.md §2.4, PART 4). These tests prove that the
driver stops it: on every connect and reconnect, and before retrying a spoilt exchange.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator

import pytest

from sdh2svc.bus.joint import ControllerMode, JointLink, LinkEventKind
from sdh2svc.sim.endpoint import serve_device
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
