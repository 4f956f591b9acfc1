"""JointLink against the SDH2 emulator over a real pty and real TCP (no mocks).

Timing assertions are lower bounds only: bytes cannot beat the emulated 115200-baud line, and a
move cannot finish before its duration.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import re
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import pytest

from sdh2svc.bus.joint import (
    DEFAULT_LIMITS,
    REPLY_START_S,
    ControllerMode,
    EmergencyStopped,
    FirmwareError,
    HandRefused,
    JointLink,
    JointLinkError,
    LinkEvent,
    LinkEventKind,
    LinkLost,
)
from sdh2svc.protocol import dsa
from sdh2svc.protocol.sdh import NUM_AXES, AxisState, SdhError
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.dsacon import DsaconEmulator, DsaconOptions
from sdh2svc.sim.endpoint import Endpoint, FaultConfig, FaultKind, UnixEndpoint, serve_device
from sdh2svc.sim.sdh2 import Sdh2Emulator, Sdh2Options
from sdh2svc.sim.world import ScriptedWorld

SHAPES = [(14, 6), (13, 6)] * 3
KINDS = ["pty", "tcp"]
POSE_A = (30.0, -40.0, 20.0, -50.0, 10.0, -40.0, 20.0)


@dataclass
class Rig:
    """An emulator served on one endpoint; :meth:`open` tracks links for teardown."""

    dev: Sdh2Emulator
    ep: Endpoint
    links: list[JointLink] = field(default_factory=list)

    async def open(self, **kwargs: Any) -> JointLink:
        link = await JointLink.open(self.ep.url, **kwargs)
        self.links.append(link)
        return link


@contextlib.asynccontextmanager
async def _rig(kind: str, faults: FaultConfig | None = None) -> AsyncIterator[Rig]:
    dev = Sdh2Emulator(ScriptedWorld(SHAPES))
    async with serve_device(dev, kind, faults=faults) as ep:
        rig = Rig(dev, ep)
        try:
            yield rig
        finally:
            for link in rig.links:
                await link.close()


@pytest.fixture(params=KINDS)
async def rig(request: pytest.FixtureRequest) -> AsyncIterator[Rig]:
    async with _rig(request.param) as r:
        yield r


@pytest.fixture
async def tcp_rig() -> AsyncIterator[Rig]:
    async with _rig("tcp") as r:
        yield r


def _close(a: tuple[float, ...], b: tuple[float, ...], tol: float = 2e-3) -> bool:
    return len(a) == len(b) and all(abs(x - y) <= tol for x, y in zip(a, b, strict=True))


async def _next_event(queue: asyncio.Queue[LinkEvent], kind: LinkEventKind) -> LinkEvent:
    async with asyncio.timeout(15):
        while (event := await queue.get()).kind is not kind:
            pass
    return event


# -- handshake --------------------------------------------------------------------------------


async def test_open_handshake(rig: Rig) -> None:
    seen: list[LinkEvent] = []
    loop = asyncio.get_running_loop()
    start = loop.time()
    link = await rig.open(on_event=seen.append)
    assert loop.time() - start >= 0.1  # the 100 ms drain after the blank line
    opts = rig.dev.options
    assert link.version == opts.version
    assert link.velocity_limits == opts.velocity_limit
    assert link.acceleration_limits == opts.acceleration_limit
    assert link.controller is ControllerMode.POSE
    assert link.connected
    assert rig.dev.stats.blank_lines >= 1
    # ver, vlim ×2, alim ×2 (read twice alike), con, then the hold: stop, pos, p (pose mode),
    # and state (nothing moves on after the stop)
    assert link.stats.commands == 10
    assert link.stats.rtt_count == 10 and link.stats.rtt_min_s > 0.0
    assert [e.kind for e in seen] == [LinkEventKind.CONNECTED]
    assert link.binary_crc is (rig.ep.url.startswith("socket://") is False)
    await link.close()
    await link.close()  # idempotent
    assert seen[-1].kind is LinkEventKind.CLOSED
    with pytest.raises(LinkLost):
        await link.get_actual()


async def test_open_silent_device_fails_clearly() -> None:
    dev = Sdh2Emulator(ScriptedWorld(SHAPES))
    async with serve_device(dev, "pty", faults=FaultConfig(boot_delay_s=30.0)) as ep:
        loop = asyncio.get_running_loop()
        start = loop.time()
        with pytest.raises(
            JointLinkError, match=re.escape(f"joint line {ep.url}: SDH not connected")
        ):
            await JointLink.open(ep.url)
        assert loop.time() - start >= 1.0  # the 1 s `ver` timeout


async def test_firmware_without_binary_frames_is_spoken_to_in_ascii() -> None:
    """VER=0.0.1.0 was taken with binary frames asked for: its first binary command would have
    failed as line noise, retried as a spoilt reply. The link speaks ASCII to it instead."""
    dev = Sdh2Emulator(ScriptedWorld(SHAPES), options=Sdh2Options(version="0.0.1.0"))
    async with serve_device(dev, "tcp") as ep:
        link = await JointLink.open(ep.url, binary=True)
        try:
            assert (link.version, link.binary) == ("0.0.1.0", False)
            assert len(await link.get_actual()) == 7
        finally:
            await link.close()


def test_a_hand_refused_is_held_first() -> None:
    """A hand this host refuses (``accept``: its speeds) was left as the last program left it:
    an axis driving at 5 °/s drove on. Every handshake that reaches an SDH2 holds it."""
    from sdh2svc.config import load_config
    from sdh2svc.connect import Simulated, simulated_hand

    async def main() -> tuple[float, float]:
        async with simulated_hand(load_config(use_env=False), Simulated(fast=True)) as bench:
            sim, url = bench.sim, bench.sim.urls("sdh")[0]
            first = await JointLink.open(url)
            await first.power([True] * 7)
            await first.set_controller(ControllerMode.VELOCITY)
            await first.set_velocities([0, 5, 0, 0, 0, 0, 0])  # axis 1 driving at 5 °/s
            await first.close()
            with pytest.raises(HandRefused, match="too slow for us"):
                await JointLink.open(url, accept=lambda vlim: ["too slow for us"])
            held = sim.sdh.actual_deg[1]
            await asyncio.sleep(5.0)
            return held, sim.sdh.actual_deg[1]

    held, later = run_fast(main())
    assert later == pytest.approx(held, abs=0.01)


async def test_a_device_that_echoes_is_no_sdh2() -> None:
    """An echo took `ver` for the firmware's answer and failed a step later, at vlim, with a
    message that did not say why."""

    done = asyncio.Event()

    async def echo(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            while data := await reader.read(100):
                writer.write(data)
        finally:
            writer.close()
            done.set()

    async with await asyncio.start_server(echo, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        with pytest.raises(JointLinkError, match="'ver' is no SDH2's answer to ver"):
            await JointLink.open(f"socket://127.0.0.1:{port}")
        await done.wait()  # the link closed its end


async def test_open_missing_port() -> None:
    with pytest.raises(JointLinkError, match=r"^joint line /dev/does-not-exist-sdh2: cannot open"):
        await JointLink.open("/dev/does-not-exist-sdh2")


# -- round trips --------------------------------------------------------------------------------


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
async def test_round_trips(rig: Rig, binary: bool) -> None:
    link = await rig.open(binary=binary)
    dev = rig.dev
    binary_before = dev.stats.binary
    assert await link.get_actual() == dev.actual_deg
    assert await link.set_targets(POSE_A) == POSE_A
    assert dev.target_deg == POSE_A
    assert await link.get_targets() == POSE_A
    assert await link.tpap((0.0,) * NUM_AXES) == dev.actual_deg  # tpap answers actual angles
    assert dev.target_deg == (0.0,) * NUM_AXES
    assert await link.get_state() == (AxisState.DISABLED,) * NUM_AXES
    on = (True, False, True, True, False, True, True)
    assert await link.power(on) == on
    assert dev.powered == on
    assert await link.get_power() == on
    states = await link.get_state()
    assert [s is AxisState.IDLE for s in states] == list(on)
    assert await link.tvav((0.0,) * NUM_AXES) == (0.0,) * NUM_AXES
    assert await link.get_velocity() == (0.0,) * NUM_AXES
    assert len(await link.temperatures()) == 9
    sent_binary = dev.stats.binary - binary_before
    assert sent_binary == (10 if binary else 0)  # every vector command above but temp
    assert link.stats.errors == link.stats.retries == link.stats.timeouts == 0


async def test_move_until_idle(rig: Rig) -> None:
    link = await rig.open()
    loop = asyncio.get_running_loop()
    assert await link.set_velocities((60.0,) * NUM_AXES) == (60.0,) * NUM_AXES
    await link.set_targets(POSE_A)
    duration = await link.move()
    started = loop.time()
    assert duration > 0.5  # 50° at ≤ 60 °/s
    assert AxisState.POSITIONING in await link.get_state()  # PART 4 item 6
    states = await link.wait_idle(poll_s=0.02)
    assert loop.time() - started >= duration - 0.05
    assert states == (AxisState.IDLE,) * NUM_AXES
    assert _close(await link.get_actual(), POSE_A)


async def test_stop_halts_move(rig: Rig) -> None:
    link = await rig.open()
    await link.set_targets(POSE_A)
    await link.move()
    await asyncio.sleep(0.2)
    await link.stop()
    assert AxisState.POSITIONING not in await link.get_state()
    halted = await link.get_actual()
    await asyncio.sleep(0.1)
    assert await link.get_actual() == halted
    assert not _close(halted, POSE_A)


async def test_cancelled_command_leaves_the_line_usable(rig: Rig) -> None:
    link = await rig.open()
    task = asyncio.create_task(link.get_actual())
    await asyncio.sleep(0)  # on the line, reply not yet in
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert await link.get_targets() == (0.0,) * NUM_AXES  # not the late POS reply
    assert link.stats.resyncs == 1 and link.stats.garbled == 0


# -- limits -------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("axis", "angle"), [(0, -1.0), (0, 90.5), (3, 91.0), (6, -120.0), (2, math.nan)]
)
async def test_out_of_limit_target_rejected_before_writing(
    rig: Rig, axis: int, angle: float
) -> None:
    link = await rig.open()
    await link.set_targets(POSE_A)
    rx, commands = rig.ep.stats.bytes_rx, rig.dev.stats.commands
    bad = list(POSE_A)
    bad[axis] = angle
    with pytest.raises(ValueError, match=f"axis {axis}"):
        await link.set_targets(bad)
    with pytest.raises(ValueError, match=f"axis {axis}"):
        await link.tpap(bad)
    with pytest.raises(ValueError, match=f"axis {axis}"):
        await link.command("p", bad)  # the low-level path checks too
    with pytest.raises(ValueError, match=f"axis {axis}"):
        await link.command("p", angle, axis=axis)
    await asyncio.sleep(0.02)
    assert (rig.ep.stats.bytes_rx, rig.dev.stats.commands) == (rx, commands)
    assert rig.dev.target_deg == POSE_A


async def test_custom_limits(rig: Rig) -> None:
    limits = list(DEFAULT_LIMITS)
    limits[1] = (-30.0, 30.0)
    link = await rig.open(limits=limits)
    with pytest.raises(ValueError, match="axis 1"):
        await link.set_targets((0.0, 35.0, 0.0, 0.0, 0.0, 0.0, 0.0))
    assert await link.set_targets((0.0, 30.0, 0.0, 0.0, 0.0, 0.0, 0.0))


async def test_an_axis_far_outside_narrowed_limits_is_named_when_the_line_is_refused(
    tcp_rig: Rig,
) -> None:
    """A reading more than 2° past the limits is refused as a spoilt reply (ASCII has no
    checksum); where an axis really stands there — the limits narrowed since, a finger moved
    unpowered — the line's failure names it and says what to do, not only the raw reading."""
    assert tcp_rig.dev.actual_deg[1] == pytest.approx(0.0)
    limits = list(DEFAULT_LIMITS)
    limits[1] = (10.0, 30.0)
    with pytest.raises(JointLinkError) as refused:
        await tcp_rig.open(limits=limits, reconnect=False, timeout_s=0.2, retries=1)
    said = str(refused.value)
    assert "axis 1 reads 0°, outside its limits 10…30° by more than 2°" in said, said
    assert "move it within its limits with the hand off, or widen `limits`" in said
    assert "axis 0" not in said and "axis 2" not in said  # only the axis that is outside


# -- firmware errors ------------------------------------------------------------------------


async def test_unknown_command_raises_firmware_error(rig: Rig) -> None:
    link = await rig.open()
    with pytest.raises(FirmwareError) as info:
        await link.command("frobnicate")
    assert info.value.code == SdhError.CMD_UNKNOWN
    assert info.value.name == "CMD_UNKNOWN"
    assert (link.stats.errors, link.stats.retries) == (1, 0)  # not an axis command: no retry
    assert _close(await link.get_actual(), rig.dev.actual_deg)  # the line is still in step


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
async def test_axis_command_error_is_retried(rig: Rig, binary: bool) -> None:
    link = await rig.open(binary=binary)
    with pytest.raises(FirmwareError) as info:
        await link.set_velocities((-10.0,) * NUM_AXES)  # pose mode takes 0…vlim only
    assert info.value.code == SdhError.RANGE_ERROR
    assert link.stats.errors == 1 + link.retries
    assert link.stats.retries == link.retries
    assert link.stats.resyncs == link.retries
    assert await link.get_velocities() == (40.0,) * NUM_AXES


# -- emergency stop -------------------------------------------------------------------------


async def test_emergency_stop_mid_motion(rig: Rig) -> None:
    link = await rig.open()
    events = link.subscribe()
    await link.set_targets(POSE_A)
    duration = await link.move()
    await asyncio.sleep(duration / 3)
    in_flight = asyncio.create_task(link.get_actual())
    queued: list[asyncio.Task[Any]] = [
        asyncio.create_task(link.set_targets((0.0,) * NUM_AXES)),
        asyncio.create_task(link.get_state()),
    ]
    await asyncio.sleep(0)  # the first is on the line, the others wait their turn
    held = await link.emergency_stop()
    assert len(await in_flight) == NUM_AXES
    for task in queued:
        with pytest.raises(EmergencyStopped):
            await task
    assert (await _next_event(events, LinkEventKind.EMERGENCY_STOP)).url == link.url
    assert not _close(held, POSE_A)  # stopped on the way
    assert await link.get_state() == (AxisState.DISABLED,) * NUM_AXES
    first = await link.get_actual()
    await asyncio.sleep(0.2)
    assert await link.get_actual() == first  # the axes stay where they stopped
    assert _close(await link.get_targets(), first)
    assert _close(rig.dev.target_deg, rig.dev.actual_deg)
    # Latched: nothing may start motion until release().
    for attempt in (link.move, lambda: link.set_targets(POSE_A)):
        with pytest.raises(EmergencyStopped):
            await attempt()
    assert link.estopped
    assert await link.release() == (True,) * NUM_AXES
    assert not link.estopped
    await link.set_targets(POSE_A)
    await link.move()
    await link.wait_idle()
    assert _close(await link.get_actual(), POSE_A)


async def test_emergency_stop_binary_precedence_over_a_burst(rig: Rig) -> None:
    link = await rig.open(binary=True)
    await link.set_targets(POSE_A)
    await link.move()
    burst = [asyncio.create_task(link.get_actual()) for _ in range(20)]
    await asyncio.sleep(0)
    await link.emergency_stop()
    results = await asyncio.gather(*burst, return_exceptions=True)
    assert isinstance(results[0], tuple)  # the one in flight finished
    assert all(isinstance(r, EmergencyStopped) for r in results[1:])
    assert rig.dev.powered == (False,) * NUM_AXES
    assert _close(rig.dev.target_deg, rig.dev.actual_deg)


# -- faults ---------------------------------------------------------------------------------


async def _hammer(link: JointLink, rng: random.Random, n: int) -> tuple[float, ...]:
    """n mixed commands; returns the last targets written."""
    targets = (0.0,) * NUM_AXES
    ops: list[Callable[[], Awaitable[object]]] = [
        link.get_actual,
        link.get_state,
        link.get_power,
        link.get_targets,
    ]
    for i in range(n):
        if i % 3 == 0:
            targets = tuple(round(rng.uniform(lo, hi), 1) for lo, hi in DEFAULT_LIMITS)
            await (link.tpap(targets) if i % 2 else link.set_targets(targets))
        else:
            await rng.choice(ops)()
    return targets


@pytest.mark.parametrize(
    ("kind", "binary"),
    [("pty", False), ("pty", True), ("tcp", False)],
    ids=["pty-ascii", "pty-binary", "tcp-ascii"],
)
async def test_bit_errors_are_retried(kind: str, binary: bool) -> None:
    faults = FaultConfig(bit_error_rate=1e-3, seed=7)
    async with _rig(kind, faults) as rig:
        link = await rig.open(binary=binary, timeout_s=0.25, retries=8)
        targets = await _hammer(link, random.Random(1), 240)
        stats = link.stats
        assert rig.ep.stats.faults[FaultKind.BIT_ERROR] > 0
        assert stats.garbled + stats.timeouts > 0
        assert stats.retries >= stats.garbled + stats.timeouts - stats.failures
        assert stats.resyncs > 0 and stats.failures == 0
        assert _close(rig.dev.target_deg, targets, 1e-4)  # host→device is clean
        assert len(await link.get_actual()) == NUM_AXES


@contextlib.asynccontextmanager
async def _whole_packets(
    tmp_path: Path, dev: Sdh2Emulator, **open_kw: Any
) -> AsyncIterator[tuple[Endpoint, JointLink]]:
    """``dev`` on a Unix socket that delivers whole packets (fast mode), and a link open on it."""
    async with UnixEndpoint(dev, str(tmp_path / "sdh.sock"), whole_packets=True) as ep:
        link = await JointLink.open(ep.url, **open_kw)
        try:
            yield ep, link
        finally:
            await link.close()


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_a_reply_broken_off_is_retried_at_once_not_after_its_timeout(
    tmp_path: Path, binary: bool
) -> None:
    """A reply cut short (a flipped length byte, a lost line end) leaves the parser waiting for
    bytes that never come: after BYTE_GAP_S of nothing more the link resyncs and retries, not
    after the reply's timeout (1 s), so a control loop's joint angles do not age by a second.
    A reply cut before its first byte (lost whole) is given up after REPLY_START_S."""

    async def main() -> None:
        dev = Sdh2Emulator(ScriptedWorld(SHAPES))
        async with _whole_packets(tmp_path, dev, binary=binary, timeout_s=1.0, retries=5) as (
            ep,
            link,
        ):
            ep.set_faults(FaultConfig(truncate_packet_rate=0.2, seed=3))
            loop = asyncio.get_running_loop()
            slow = 0
            for _ in range(300):
                t0 = loop.time()
                assert len(await link.get_actual()) == NUM_AXES
                slow += loop.time() - t0 >= REPLY_START_S + 0.3
            cut = ep.stats.faults[FaultKind.TRUNCATE_PACKET]
            stats = link.stats
            assert cut >= 40 and stats.failures == 0, (cut, stats)
            assert stats.garbled >= cut * 3 // 4, (cut, stats)  # found, retried
            assert 1 <= stats.timeouts <= cut // 8, (cut, stats)  # cut at byte 0
            assert slow == 0, (slow, cut, stats)  # none waited for its reply's timeout

    run_fast(main())


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_a_reply_lost_whole_is_given_up_once_it_has_not_begun_in_time(
    tmp_path: Path, binary: bool
) -> None:
    """Not one byte of a reply by REPLY_START_S (every command but `ref` answers at once): the
    reply is lost (a command spoilt on its way, a reply lost whole), and the retry goes then, not
    after the reply's timeout (1 s) — a control loop's joint angles age by a fraction of it."""

    async def main() -> None:
        dev = Sdh2Emulator(ScriptedWorld(SHAPES))
        async with _whole_packets(tmp_path, dev, binary=binary, timeout_s=1.0, retries=3) as (
            ep,
            link,
        ):
            loop = asyncio.get_running_loop()
            ep.set_faults(FaultConfig(drop_byte_rate=1.0))  # every reply lost
            t0 = loop.time()
            read = asyncio.ensure_future(link.get_actual())
            await asyncio.sleep(REPLY_START_S / 2)
            ep.set_faults(FaultConfig())  # the line good again before the retry
            assert len(await read) == NUM_AXES
            took = loop.time() - t0
            assert link.stats.timeouts == 1 and link.stats.failures == 0, link.stats
            assert REPLY_START_S <= took < REPLY_START_S + 0.2, took

    run_fast(main())


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_a_slow_line_stretches_how_soon_a_reply_must_begin(tmp_path: Path, binary: bool) -> None:
    """A line whose replies all take longer than REPLY_START_S (a serial server on a network, a
    slow converter) is not a line losing every reply: the deadline follows its round trips."""

    async def main() -> None:
        slow = Sdh2Options(ascii_latency_s=0.2, binary_latency_s=0.2)
        dev = Sdh2Emulator(ScriptedWorld(SHAPES), options=slow)
        async with _whole_packets(tmp_path, dev, binary=binary, timeout_s=1.0, retries=3) as (
            _,
            link,
        ):
            for _ in range(20):
                assert len(await link.get_actual()) == NUM_AXES
                await link.move()
            assert link.stats.timeouts == link.stats.retries == 0, link.stats
            assert link.stats.rtt_min_s > REPLY_START_S, link.stats

    run_fast(main())


class _NoiseBeforeStop(Sdh2Emulator):
    """Once armed, the next `stop` is answered by a noise burst on the line at once, its own
    reply only after the firmware's processing time (30 ms: after the host's resync has drained
    the line for 20 ms quiet)."""

    armed = False

    def receive(self, data: bytes, now: float) -> None:
        super().receive(data, now)
        if self.armed and b"stop" in data:
            self.armed = False
            self._outbox.append(b"#\x01noise\r\n")


def test_a_late_reply_to_an_exchange_given_up_is_skipped_not_taken_for_garbage(
    tmp_path: Path,
) -> None:
    """A reply that comes after its exchange was given up (spoilt by noise before it, its first
    byte late) arrives during the next exchange: it is skipped there, not taken for that
    exchange's reply spoilt — which resynced again, and the `stop` sent before each retry left
    every later reply one exchange behind until the command failed (seen: `p: bad reply (ASCII
    reply STOP to binary p)` under host→device bit errors)."""

    async def main() -> None:
        dev = _NoiseBeforeStop(ScriptedWorld(SHAPES), options=Sdh2Options(ascii_latency_s=0.0049))
        async with _whole_packets(tmp_path, dev, binary=True, timeout_s=1.0, retries=3) as (
            ep,
            link,
        ):
            await link.move()  # the hand may be moving: a retry sends `stop` first
            # one `pos` lost whole; its retry's `stop` spoilt by noise, its reply late
            ep.set_faults(FaultConfig(drop_byte_rate=1.0))
            dev.armed = True
            read = asyncio.ensure_future(link.get_actual())
            await asyncio.sleep(REPLY_START_S / 2)
            ep.set_faults(FaultConfig())
            assert len(await read) == NUM_AXES
            for _ in range(10):
                assert len(await link.get_actual()) == NUM_AXES
                await link.move()
            st = link.stats
            assert not dev.armed and st.motion_stops == 1, st
            assert st.failures == 0 and st.garbled == 0, st

    run_fast(main())


@pytest.mark.parametrize("binary", [False, True], ids=["ascii", "binary"])
def test_a_command_the_line_spoilt_on_its_way_is_sent_again(tmp_path: Path, binary: bool) -> None:
    """The firmware answers E13 / E14 to a command a flipped bit made unreadable: one encoded
    from the command table was spoilt on the line, and is retried as a spoilt reply is, not
    raised as the firmware's refusal (runs faulted on `m: firmware error 13`)."""

    async def main() -> None:
        dev = Sdh2Emulator(ScriptedWorld(SHAPES))
        async with _whole_packets(tmp_path, dev, binary=binary, timeout_s=0.2, retries=5) as (
            ep,
            link,
        ):
            ep.set_faults(FaultConfig(bit_error_rate=1e-3, host_to_device=True, seed=5))
            for _ in range(400):  # `m`: no axis command, not retried after an error before
                await link.move()
            assert ep.stats.faults[FaultKind.RX_BIT_ERROR] > 0
            assert link.stats.errors > 0 and link.stats.failures == 0, link.stats

    run_fast(main())


async def test_pty_unplugged_times_out_then_recovers() -> None:
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=1)
        rig.ep.disconnect(0.6)
        with pytest.raises(JointLinkError, match="no reply") as info:
            await link.get_actual()
        assert not isinstance(info.value, LinkLost)  # a serial line can't tell
        assert link.stats.timeouts == 2
        await asyncio.sleep(0.6)
        assert len(await link.get_actual()) == NUM_AXES


async def test_a_silent_line_fails_after_two_silent_attempts_not_every_retry() -> None:
    """Not a byte back through two attempts in a row: the command fails then (the retries
    are for a line that answers wrongly), and the link is silent — one attempt per command —
    until the line answers again."""
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=3)
        rig.ep.disconnect(3.0)  # (the two calls below take about 0.3 s)
        with pytest.raises(JointLinkError, match="twice in a row: the line is silent"):
            await link.get_actual()
        assert link.stats.timeouts == 2 and link.silent and link.connected
        with pytest.raises(JointLinkError, match="the line is silent"):
            await link.get_actual()
        assert link.stats.timeouts == 3  # one attempt while silent
        assert len(await _answered(link)) == NUM_AXES  # the line answers again: so does the link
        assert not link.silent


async def _answered(link: JointLink) -> tuple[float, ...]:
    """The actual angles, once a command is answered (a silent line coming back)."""
    async with asyncio.timeout(30):
        while True:
            with contextlib.suppress(JointLinkError):
                return await link.get_actual()
            await asyncio.sleep(0.1)


async def test_a_silent_line_that_answers_again_is_identified_anew() -> None:
    """A hand switched off and on behind an adapter that stayed plugged in: its line falls
    silent, then answers again. The link drops that connection and reconnects at once, so the
    handshake reads the firmware anew and holds the hand; a hand it no longer accepts is not
    driven (the link stays down, each attempt saying why)."""
    refuse: list[str] = []
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=1, accept=lambda vlim: refuse)
        events = link.subscribe()
        await link.set_targets(POSE_A)  # (not moved to: `m` never sent)
        assert rig.dev.target_deg != pytest.approx(await link.get_actual(), abs=1.0)
        rig.ep.disconnect(1.0)
        with pytest.raises(JointLinkError, match="the line is silent"):
            await link.get_actual()
        rig.dev.options = replace(rig.dev.options, version="0.0.3.4")  # the hand that came back
        await _answered(link)
        lost = await _next_event(events, LinkEventKind.LOST)
        assert "answers again after being silent" in lost.detail
        back = await _next_event(events, LinkEventKind.RECONNECTED)
        assert link.version == "0.0.3.4" and "0.0.3.4" in back.detail
        assert rig.dev.target_deg == pytest.approx(await link.get_actual(), abs=1e-3)  # held

        refuse.append("not the hand this host was set up for")
        rig.ep.disconnect(1.0)
        with pytest.raises(JointLinkError, match="the line is silent"):
            await link.get_actual()
        await _answered(link)
        failed = await _next_event(events, LinkEventKind.RECONNECT_FAILED)
        assert "not the hand this host was set up for" in failed.detail
        assert not link.connected


async def test_an_estop_the_silent_line_answers_completes_before_the_hand_is_identified_anew() -> (
    None
):
    """The line answers again during an e-stop: its whole sequence (power off, read, hold) runs
    on that connection and reports the hand reached; only then is the line dropped, and the
    reconnect powers the (latched) hand off and holds it again. A link that does not reconnect
    goes on on the same connection."""
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=1)
        events = link.subscribe()
        await link.power([True] * NUM_AXES)
        rig.ep.disconnect(1.0)
        with pytest.raises(JointLinkError, match="the line is silent"):
            await link.get_actual()
        await asyncio.sleep(1.2)  # the line answers again
        held = await link.emergency_stop()  # not LinkLost half-way
        assert len(held) == NUM_AXES and link.power_off_confirmed
        assert not any(rig.dev.powered)
        await _next_event(events, LinkEventKind.RECONNECTED)
        assert link.estopped and not any(rig.dev.powered)
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=1, reconnect=False)
        rig.ep.disconnect(1.0)
        with pytest.raises(JointLinkError, match="the line is silent"):
            await link.get_actual()
        await _answered(link)
        assert len(await link.get_actual()) == NUM_AXES and link.connected


async def test_a_release_the_hand_has_not_taken_shows_latched() -> None:
    """While the release's power command is out (a silent line), the link says e-stopped: the
    status showed it released for the seconds the release took to fail."""
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.2, retries=1)
        await link.emergency_stop()
        rig.ep.disconnect(2.0)  # silent while the release is out
        release = asyncio.create_task(link.release())
        seen = []
        while not release.done():
            seen.append(link.estopped)
            await asyncio.sleep(0.01)
        with pytest.raises(JointLinkError):
            await release
        assert seen and all(seen) and link.estopped


async def test_a_release_does_not_release_an_estop_latched_since_its_caller_decided() -> None:
    """A release names the e-stops it saw (:attr:`JointLink.latches`): one latched since (an
    e-stop pressed while the caller deleted its record) stays latched, the hand off."""
    async with _rig("pty") as rig:
        link = await rig.open()
        await link.emergency_stop()
        seen = link.latches
        await link.emergency_stop()  # pressed again while the release was on its way
        with pytest.raises(EmergencyStopped, match="came during the release"):
            await link.release(seen)
        assert link.estopped and not any(rig.dev.powered)
        link.latch()  # one latched without a word to the hand counts too
        with pytest.raises(EmergencyStopped):
            await link.release(seen + 1)
        await link.release(link.latches)
        assert not link.estopped and all(rig.dev.powered)
        # a caller's latch() and the stop it then sends count as two: a release decided
        # between them would power the hand on under a stop still on its way
        link.latch()
        seen = link.latches
        await link.emergency_stop()
        with pytest.raises(EmergencyStopped):
            await link.release(seen)
        assert link.estopped and not any(rig.dev.powered)


async def test_a_release_holds_the_fingers_where_they_sagged_while_unpowered() -> None:
    """Unpowered, fingers sag (or a hand moves them); powered on again, the firmware drives to
    its targets — those the e-stop wrote. The release writes the actual angles first."""
    world = ScriptedWorld(SHAPES)
    dev = Sdh2Emulator(world)
    async with serve_device(dev, "pty") as ep:
        link = await JointLink.open(ep.url)
        try:
            held = await link.emergency_stop()
            assert not any(dev.powered)
            world._angles = tuple(a - 3.0 if i in (1, 2) else a  # (a test's hand on the world)
                                  for i, a in enumerate(world._angles))  # fmt: skip
            await link.release()
            assert all(dev.powered)
            sagged = await link.get_actual()
            assert not _close(sagged, held, 1.0)
            assert _close(dev.target_deg, sagged, 1e-3)
            await asyncio.sleep(0.5)
            assert _close(await link.get_actual(), sagged, 1e-3)  # nothing moved
        finally:
            await link.close()


async def test_an_estop_the_line_lost_is_sent_again_once_it_answers() -> None:
    """A silent line (its port open) swallows the e-stop's power-off; the link owes it, and
    the first command the line answers again is followed by it."""
    async with _rig("pty") as rig:
        link = await rig.open(timeout_s=0.1, retries=1)
        await link.power([True] * NUM_AXES)
        rig.ep.disconnect(1.0)
        with pytest.raises(JointLinkError):
            await link.emergency_stop()
        assert link.estopped and all(rig.dev.powered)
        await _answered(link)
        assert not any(rig.dev.powered) and link.estopped


async def test_tcp_disconnect_reconnects(tcp_rig: Rig) -> None:
    seen: list[LinkEvent] = []
    link = await tcp_rig.open(on_event=seen.append)
    events = link.subscribe()
    loop = asyncio.get_running_loop()
    speeds = (50.0, 30.0, 60.0, 30.0, 60.0, 30.0, 60.0)
    await link.set_velocities(speeds)
    await link.set_targets(POSE_A)
    unplugged = loop.time()
    tcp_rig.ep.disconnect(1.0)
    with pytest.raises(LinkLost) as lost:
        await link.get_actual()  # in flight when the line drops, or after
    # said as a lab reads it (a run's fault message), not by the wire command: "pos: port lost"
    assert str(lost.value).startswith("joint line lost: "), lost.value
    await _next_event(events, LinkEventKind.LOST)
    assert not link.connected
    with pytest.raises(LinkLost) as lost:
        await link.get_state()
    assert str(lost.value).startswith("joint line lost: "), lost.value
    await _next_event(events, LinkEventKind.RECONNECTED)
    assert loop.time() - unplugged >= 1.0  # nobody gets in while the cable is out
    assert link.connected
    assert await link.get_velocities() == speeds  # device state survived
    # …but not a target nobody commands any more: the reconnect held the axes where they are
    assert await link.get_targets() == pytest.approx(await link.get_actual())
    assert (link.stats.link_losses, link.stats.reconnects) == (1, 1)
    kinds = [e.kind for e in seen]
    assert kinds[0] is LinkEventKind.CONNECTED
    lost, back = kinds.index(LinkEventKind.LOST), kinds.index(LinkEventKind.RECONNECTED)
    assert LinkEventKind.RECONNECT_FAILED in kinds[lost:back]  # +0.5 s found no way in


@pytest.mark.parametrize("crc", [True, False])
async def test_binary_crc_override(rig: Rig, crc: bool) -> None:
    link = await rig.open(binary=True, binary_crc=crc)
    assert link.binary_crc is crc
    before = rig.dev.stats.binary  # the connect's hold sent `pos` and `p` in binary
    assert await link.set_targets(POSE_A) == pytest.approx(POSE_A)
    assert rig.dev.stats.binary == before + 1


async def test_latched_estop_is_reasserted_after_a_reconnect(tcp_rig: Rig) -> None:
    link = await tcp_rig.open()
    events = link.subscribe()
    await link.emergency_stop()
    assert tcp_rig.dev.powered == (False,) * NUM_AXES
    tcp_rig.ep.disconnect(0.5)
    # while the line is down, someone powers the axes at the controller
    tcp_rig.dev._set_power((1,) * NUM_AXES, range(NUM_AXES))
    assert tcp_rig.dev.powered == (True,) * NUM_AXES
    await _next_event(events, LinkEventKind.RECONNECTED)
    assert link.estopped
    assert tcp_rig.dev.powered == (False,) * NUM_AXES


def test_a_joint_line_opened_on_the_tactile_controller_says_the_lines_may_be_swapped(
    tmp_path: Path,
) -> None:
    """Pointed at a DSACON32m that streams (a previous host left it so), the handshake's `ver`
    goes unanswered among its packets; the error says what answered and that the lines may be
    swapped."""

    async def main() -> None:
        options = DsaconOptions(stream_survives_disconnect=True)
        dsa_emu = DsaconEmulator(ScriptedWorld([(14, 6), (13, 6)] * 3), options=options)
        async with UnixEndpoint(dsa_emu, str(tmp_path / "dsa.sock")) as ep:
            reader, writer = await asyncio.open_unix_connection(str(tmp_path / "dsa.sock"))
            writer.write(dsa.configure_acquisition(acquire=True, framerate=30))  # another host
            await reader.read(1)
            writer.close()
            await writer.wait_closed()
            with pytest.raises(JointLinkError, match=r"DSACON32m's packets.*swapped"):
                await JointLink.open(ep.url, reconnect=False)

    run_fast(main())
