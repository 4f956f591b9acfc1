"""TactileBus against the DSACON32m emulator over real ptys and TCP sockets (no mocks).

The world records every frame the emulator samples, keyed by the timestamp it sends, so a test
can check that the driver delivered exactly those frames: none lost on a clean line, none
corrupted on a noisy one. Timing assertions in real time are lower bounds only; the long
push test runs on the virtual clock of fast mode (over a Unix socket), where they are exact.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import re
from collections.abc import AsyncIterator, Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from sdh2svc.bus.tactile import (
    FrameTimeout,
    LinkEvent,
    LinkEventKind,
    Mode,
    Subscription,
    TactileBus,
    TactileCommandError,
    TactileConnectionError,
    TactileError,
    TactileFrame,
    TactileOptions,
    TactileStats,
)
from sdh2svc.protocol import dsa
from sdh2svc.sim.cable import Cable
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.dsacon import DsaconEmulator, DsaconOptions
from sdh2svc.sim.endpoint import Endpoint, FaultConfig, PtyEndpoint, TcpEndpoint, UnixEndpoint
from sdh2svc.sim.sdh2 import Sdh2Emulator
from sdh2svc.sim.world import Pattern, ScriptedWorld

SHAPES = [(14, 6), (13, 6)] * 3
NB_CELLS = 486
DISTAL = {1, 5}
OTHERS = {0, 2, 3, 4}
PERIOD_MS = 33  # 30 fps, by the controller's ms clock (floored)


class RecordingWorld(ScriptedWorld):
    """ScriptedWorld that remembers what each sampled frame held, and when."""

    def __init__(self, pattern: Pattern | None = None) -> None:
        super().__init__(SHAPES, pattern)
        self.sampled: list[tuple[float, np.ndarray]] = []

    def tactile_frame(
        self, now: float, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        out = super().tactile_frame(now, sensitivity, threshold)
        self.sampled.append((now, out.copy()))
        return out


@dataclass
class Rig:
    emu: DsaconEmulator
    world: RecordingWorld
    endpoint: Endpoint
    bus: TactileBus
    frames: list[TactileFrame] = field(default_factory=list)

    def emitted(self) -> dict[int, np.ndarray]:
        """Every frame the emulator sampled, by the timestamp it carries."""
        return {self.emu.clock_ms(t): texels for t, texels in self.world.sampled}

    def emitted_stamps(self) -> list[int]:
        return [self.emu.clock_ms(t) for t, _ in self.world.sampled]

    async def collect(self, n: int) -> None:
        """Wait until the frame listener has seen ``n`` frames in all."""
        while len(self.frames) < n:
            await asyncio.sleep(0.05)


@contextlib.asynccontextmanager
async def rig(
    kind: str,
    faults: FaultConfig | None = None,
    options: TactileOptions | None = None,
    emulator: DsaconOptions | None = None,
    pattern: Pattern | None = None,
    unix_path: Path | None = None,
) -> AsyncIterator[Rig]:
    """The emulator on a ``kind`` endpoint: "pty", "tcp", or "unix" (at ``unix_path``; the
    transport of fast mode, whose virtual clock needs the kernel to deliver at once)."""
    world = RecordingWorld(pattern)
    emu = DsaconEmulator(world, options=emulator or DsaconOptions())
    endpoint: Endpoint
    if kind == "pty":
        endpoint = PtyEndpoint(emu, faults=faults)
    elif kind == "unix":
        assert unix_path is not None
        endpoint = UnixEndpoint(emu, str(unix_path), faults=faults)
    else:
        endpoint = TcpEndpoint(emu, faults=faults)
    async with endpoint:
        bus = await TactileBus.open(endpoint.url, options)
        r = Rig(emu, world, endpoint, bus)
        bus.add_frame_listener(r.frames.append)
        try:
            yield r
        finally:
            await bus.close()


def assert_plausible(r: Rig, frames: Sequence[TactileFrame]) -> None:
    """Each delivered frame is exactly one the emulator sampled (so never a corrupted one)."""
    emitted = r.emitted()
    for f in frames:
        assert f.texels.shape == (NB_CELLS,)
        assert f.timestamp_ms in emitted, f"frame {f.timestamp_ms} was never sent"
        np.testing.assert_array_equal(f.texels, emitted[f.timestamp_ms])
        assert [m.shape for m in f.matrices] == SHAPES


async def until(predicate: Callable[[], bool], timeout: float = 10.0) -> None:
    async with asyncio.timeout(timeout):
        while not predicate():
            await asyncio.sleep(0.01)


async def next_event(sub: Subscription, kind: LinkEventKind, timeout: float) -> LinkEvent:
    async with asyncio.timeout(timeout):
        while (event := await sub.events.get()).kind is not kind:
            pass
    return event


async def test_a_line_that_never_answers_is_named_when_the_open_fails() -> None:
    """A lab plugs in two lines: the error says which one (here a TCP port that accepts and
    never answers, as a converter with nothing behind it)."""
    peers: list[asyncio.StreamWriter] = []

    async def mute(_: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        peers.append(w)

    server = await asyncio.start_server(mute, "127.0.0.1", 0)
    url = f"socket://127.0.0.1:{server.sockets[0].getsockname()[1]}"
    quick = TactileOptions(open_tries=1, open_timeout_s=0.05, command_timeout_s=0.05,
                           open_query_tries=1)  # fmt: skip
    try:
        with pytest.raises(TactileError, match=re.escape(f"tactile line {url}: no reply")):
            await TactileBus.open(url, quick)
    finally:
        for w in peers:
            w.close()
        server.close()


def test_command_error_names_known_and_unknown_codes() -> None:
    assert str(TactileCommandError("x", 0x10)).endswith(dsa.DsaError(0x10).name)
    assert str(TactileCommandError("x", 999)) == "x: controller error 999"


@pytest.mark.parametrize("kind", ["pty", "tcp"])
async def test_open_sequence_then_pull_at_a_low_rate(kind: str) -> None:
    async with rig(kind) as r:
        bus = r.bus
        assert bus.connected and bus.mode is Mode.IDLE
        assert bus.controller_info is not None and bus.controller_info.sw_version >= 0x1000
        assert bus.sensor_info is not None and bus.sensor_info.nb_matrices == 6
        assert [m.shape for m in bus.matrix_infos] == SHAPES
        assert bus.nb_cells == NB_CELLS
        assert not r.frames  # nothing is acquired before someone subscribes

        with bus.subscribe(OTHERS, rate_hz=5.0) as sub:
            first = await sub.next_frame()
            assert bus.mode is Mode.PULL
            await asyncio.sleep(1.5)
            stats = bus.stats
        stamps = [f.timestamp_ms for f in r.frames]
        assert len(stamps) >= 4  # ~8 expected
        # requested every 200 ms on an anchored schedule (a late pull starts at once, the next
        # keeps its time), never ahead of it: by more than a latency's jitter, never sooner
        # than k periods after the first (a loaded machine delays pulls, never hastens them)
        assert all(s - stamps[0] >= k * 200 - 100 for k, s in enumerate(stamps)), stamps
        assert stats.mode is Mode.PULL and stats.required_hz == 5.0
        assert 0.0 < stats.line_utilisation_pct < 10.0  # ~5 × 100 bytes of 11 520 per second
        assert first.seq == 1 and first.age() >= 0.0
        assert_plausible(r, r.frames)

        await until(lambda: bus.mode is Mode.IDLE)  # the last subscriber left: acquisition stops
        assert not r.emu.streaming
        await bus.close()
        await bus.close()  # idempotent
        assert not bus.connected


async def test_open_retries_the_stop_through_the_boot() -> None:
    # Deaf and mute for 0.8 s, then ESC[5n noise: the third stop (at 1.0 s) is answered.
    options = TactileOptions(open_timeout_s=0.5)
    async with rig("pty", options=options, emulator=DsaconOptions(boot_s=0.8)) as r:
        assert r.bus.nb_cells == NB_CELLS and r.bus.stats.timeouts >= 1
        with r.bus.subscribe(DISTAL, rate_hz=10.0) as sub:
            assert_plausible(r, [await sub.next_frame()])


async def test_heavy_contact_frames_move_a_10_hz_request_to_push() -> None:
    rng = np.random.default_rng(1)

    def busy(now: float) -> np.ndarray:  # no two neighbours equal: 985-byte RLE frames
        return rng.integers(100, 4000, NB_CELLS).astype(np.float64)

    async with rig("pty", pattern=busy) as r:
        bus = r.bus
        with bus.subscribe(DISTAL, rate_hz=10.0):
            await until(lambda: bus.mode is Mode.PUSH)  # pull cannot sustain 10 Hz any more
            await until(lambda: len(r.frames) >= 20)
            stats = bus.stats
        assert stats.frame_bytes > 900 and stats.push_fps_estimate < 12.5
        assert stats.pull_max_hz < 12.5
        with bus.subscribe(OTHERS, rate_hz=4.0):
            await until(lambda: bus.mode is Mode.PULL)
        assert_plausible(r, r.frames)


def test_push_delivers_1000_frames_without_loss(tmp_path: Path) -> None:
    """33 s of push streaming at 30 fps, every frame delivered, none twice, none lost.

    On the virtual clock (fast mode, sdh2svc.sim.clock): the emulator's frame period, the
    line's pacing at 115200 baud, the subscriber's frame timeout and the bus's 2 s rate windows
    all run on ``loop.time()``, which only moves when nothing is in flight. The same driver code
    and bytes as in real time, but a busy machine can no longer stretch a frame gap past the
    subscriber's timeout or thin the measured rate; so the figures below are exact, not bounds.
    (A pty needs real time; the real-time paths are covered by the other tests here.)
    """

    async def stream() -> tuple[Rig, list[TactileFrame], Mode, TactileStats, float]:
        async with rig("unix", unix_path=tmp_path / "dsa.sock") as r:
            loop = asyncio.get_running_loop()
            fast = r.bus.subscribe(DISTAL, rate_hz=30.0)
            slow = r.bus.subscribe(OTHERS, rate_hz=2.0)
            t0 = loop.time()
            got: list[TactileFrame] = []
            while len(r.frames) < 1000:
                got.append(await fast.next_frame())
            mode, stats, elapsed = r.bus.mode, r.bus.stats, loop.time() - t0
            fast.close()
            slow.close()
        return r, got, mode, stats, elapsed

    r, got, mode, stats, elapsed = run_fast(stream())
    assert mode is Mode.PUSH
    stamps = [f.timestamp_ms for f in r.frames]
    assert min(np.diff(stamps)) >= PERIOD_MS
    # No loss: the delivered frames are exactly the emitted ones, in order, without a gap.
    emitted = r.emitted_stamps()
    start = emitted.index(stamps[0])
    assert emitted[start : start + len(stamps)] == stamps
    assert_plausible(r, r.frames)
    assert [f.seq for f in r.frames] == list(range(1, len(r.frames) + 1))
    # The subscriber never saw a frame twice, always a newer one, and (reading as fast as the
    # frames come) every one of them.
    assert [f.seq for f in got] == [f.seq for f in r.frames]
    assert stats.crc_errors == stats.bad_frames == stats.garbage_bytes == stats.reconnects == 0
    assert stats.timeouts == 0
    # 1000 frames at the controller's 30 fps cap: 999 frame periods of line time (plus the
    # start of the stream), and 30 frames/s measured
    assert 999 / 30.0 <= elapsed < 999 / 30.0 + 0.5
    assert stats.frames_per_s == pytest.approx(30.0, abs=0.5)
    assert 10.0 < stats.line_utilisation_pct < 100.0
    assert 79 <= stats.frame_bytes <= 985


async def test_a_slow_subscriber_always_gets_the_newest_frame() -> None:
    async with rig("tcp") as r:
        fast = r.bus.subscribe(DISTAL, rate_hz=30.0)  # drives push; never read
        slow = r.bus.subscribe(OTHERS, rate_hz=2.0)
        seen: list[TactileFrame] = []
        for _ in range(5):
            await asyncio.sleep(0.3)
            frame = await slow.next_frame()
            assert frame is r.frames[-1]  # the latest delivered, not a queued stale one
            seen.append(frame)
        assert r.bus.mode is Mode.PUSH
        seqs = [f.seq for f in seen]
        assert min(np.diff(seqs)) >= 2  # stale frames were skipped, not queued
        again = await slow.next_frame()  # never the same frame twice: waits for a new one
        assert again.seq > seen[-1].seq
        assert fast.latest is not None and fast.latest.seq >= again.seq
        with pytest.raises(FrameTimeout):
            await slow.next_frame(timeout=0.0)


async def test_sensitivity_and_threshold_while_streaming() -> None:
    async with rig("pty") as r:
        bus = r.bus
        sub = bus.subscribe(DISTAL, rate_hz=30.0)
        await r.collect(5)
        before, commands = len(r.frames), 0
        while len(r.frames) < before + 10:  # commands back to back while frames stream on
            value = 0.5 + 0.01 * (commands % 40)
            await bus.set_sensitivity(1, value)
            assert (await bus.get_sensitivity(1)).cur_sens == pytest.approx(value)
            commands += 1
        await bus.set_threshold(5, 1000)
        assert await bus.get_threshold(5) == 1000
        await bus.set_sensitivity(3, 0.6, persistent=True)  # no reply: not waited for
        assert (await bus.get_sensitivity(3)).cur_sens == pytest.approx(0.6)
        assert r.emu.threshold[5] == 1000 and r.emu.sensitivity[3] == pytest.approx(0.6)
        assert commands >= 2
        mark = len(r.frames)
        await r.collect(mark + 10)
        assert bus.mode is Mode.PUSH and bus.stats.timeouts == 0
        distal5 = np.concatenate([f.matrices[5].ravel() for f in r.frames[mark:]])
        assert np.all((distal5 == 0) | (distal5 >= 1000))  # the threshold acts on the frames
        stamps = [f.timestamp_ms for f in r.frames]
        emitted = r.emitted_stamps()
        assert emitted[emitted.index(stamps[0]) :][: len(stamps)] == stamps  # none lost
        assert_plausible(r, r.frames)
        sub.close()


async def test_noisy_line_drops_bad_frames_and_keeps_delivering() -> None:
    faults = FaultConfig(bit_error_rate=1e-3, truncate_packet_rate=0.05, seed=7)
    async with rig("pty", faults=faults) as r:
        bus = r.bus
        with bus.subscribe(DISTAL | OTHERS, rate_hz=30.0) as sub:
            pushed = [await sub.next_frame(timeout=2.0) for _ in range(40)]
            assert bus.mode is Mode.PUSH
        with bus.subscribe(OTHERS, rate_hz=5.0) as sub:  # pull: lost frames are re-requested
            pulled = [await sub.next_frame(timeout=2.0) for _ in range(5)]
            assert bus.mode is Mode.PULL
        stats = bus.stats
        kinds = {e.kind for e in bus.history}
    assert pulled[0].seq > pushed[-1].seq
    assert stats.crc_errors > 0 and stats.garbage_bytes > 0 and stats.resyncs > 0
    assert LinkEventKind.CRC_ERROR in kinds and LinkEventKind.RESYNC in kinds
    assert_plausible(r, r.frames)  # CRC-checked: nothing corrupted got through
    assert len(r.frames) < len(r.world.sampled)  # frames were lost to the noise, and skipped


async def test_pty_line_going_silent_is_detected_and_reopened() -> None:
    options = TactileOptions(stall_s=0.5, open_timeout_s=0.5)
    async with rig("pty", options=options) as r:
        sub = r.bus.subscribe(DISTAL, rate_hz=30.0)
        before = await sub.next_frame()
        r.endpoint.disconnect(1.0)  # a pty cannot tell: the bytes just stop
        lost = await next_event(sub, LinkEventKind.LOST, timeout=5.0)
        assert "no good packet" in lost.detail
        await next_event(sub, LinkEventKind.RECONNECTED, timeout=20.0)
        after = await sub.next_frame(timeout=2.0)
        assert after.timestamp_ms > before.timestamp_ms + 1000
        assert r.bus.mode is Mode.PUSH and r.bus.stats.reconnects == 1
        assert_plausible(r, r.frames)
        sub.close()


async def test_tcp_disconnect_times_out_waiters_then_reconnects() -> None:
    async with rig("tcp") as r:
        sub = r.bus.subscribe(DISTAL, rate_hz=30.0)
        before = await sub.next_frame()
        r.endpoint.disconnect(1.5)
        with pytest.raises(FrameTimeout):
            while True:
                await sub.next_frame()  # default limit: frame_timeout_s beyond 1/rate
        await next_event(sub, LinkEventKind.LOST, timeout=5.0)
        await next_event(sub, LinkEventKind.RECONNECTED, timeout=20.0)
        after = await sub.next_frame(timeout=2.0)
        assert after.timestamp_ms > before.timestamp_ms + 1500
        assert r.bus.mode is Mode.PUSH and r.bus.connected
        stats = r.bus.stats
        assert stats.reconnects >= 1
        assert_plausible(r, r.frames)
        sub.close()


def test_a_held_line_is_silent_while_a_stream_runs_then_reconnects(tmp_path: Path) -> None:
    """A line that stops carrying bytes with its port open: silent once ``silent_s`` beyond
    the frame gap has passed without a good packet (not before), lost at ``stall_s``, and
    neither once it carries again; idle, the line owes nothing and is never silent."""
    options = TactileOptions()

    async def main() -> list[tuple[float, bool, bool]]:
        loop = asyncio.get_running_loop()
        emu = DsaconEmulator(RecordingWorld(), options=DsaconOptions())
        async with UnixEndpoint(emu, str(tmp_path / "dsa.sock")) as endpoint:
            cable = Cable.unix(endpoint.url, str(tmp_path / "cable.sock"))
            await cable.plug()
            bus = await TactileBus.open(cable.url, options)
            try:
                idle_quiet = loop.time()
                await asyncio.sleep(2 * options.stall_s)  # idle: no stream, nothing owed
                assert bus.mode is Mode.IDLE and bus.connected and not bus.silent
                assert loop.time() - idle_quiet >= 2 * options.stall_s
                sub = bus.subscribe(DISTAL, rate_hz=30.0)
                await sub.next_frame()
                await sub.next_frame()
                last = sub.latest
                assert last is not None and not bus.silent
                cable.hold()
                seen = []
                while bus.connected:
                    seen.append((loop.time() - last.arrival, bus.silent, bus.connected))
                    assert bus.stats.silent is bus.silent  # status shows it
                    await asyncio.sleep(0.01)
                cable.resume()
                await until(lambda: bus.connected, timeout=30.0)
                await sub.next_frame(timeout=2.0)
                assert not bus.silent
                sub.close()
                return seen
            finally:
                await bus.close()
                await cable.close()

    seen = run_fast(main())
    gap = 1 / 30.0
    quiet_then = [quiet for quiet, silent, _ in seen if silent]
    assert quiet_then, "the held line never counted as silent"
    assert min(quiet_then) >= options.silent_s  # not on one late frame
    assert min(quiet_then) <= options.silent_s + gap + 0.02  # but at once after
    assert all(silent for quiet, silent, _ in seen if quiet >= options.silent_s + gap + 0.02)
    assert max(quiet for quiet, _, _ in seen) <= options.stall_s + gap + 0.2  # then lost


async def test_a_failed_waiter_nobody_awaits_is_not_logged_as_never_retrieved() -> None:
    """A pull's ACK is not always awaited (its frame answers it): failed as the line was lost,
    asyncio logged "Future exception was never retrieved" at ERROR, which reads as a crash in
    the service's journal after a hand's power cycle."""
    loop = asyncio.get_running_loop()
    logged: list[dict[str, object]] = []
    loop.set_exception_handler(lambda _loop, context: logged.append(context))
    bus = TactileBus("socket://127.0.0.1:1")
    pid = dsa.PacketId.CONFIGURE_DATA_ACQUISITION
    awaited: asyncio.Future[bytes] = loop.create_future()
    waiting = asyncio.ensure_future(awaited)
    await asyncio.sleep(0)
    bus._waiter = (pid, awaited)
    bus._fail_waiter(TactileConnectionError("connection closed"))
    with pytest.raises(TactileConnectionError):  # a task awaiting its reply still gets it
        await waiting
    bus._waiter = (pid, loop.create_future())
    bus._fail_waiter(TactileConnectionError("no good packet for 1.72 s"))
    bus._waiter = None  # the failed future dropped, never awaited
    gc.collect()
    assert logged == []


def test_a_tactile_line_opened_on_the_joint_controller_says_the_lines_may_be_swapped(
    tmp_path: Path,
) -> None:
    """Pointed at the SDH2, the open sequence's commands are answered with bytes, never a
    DSACON32m packet; the error says so and that the lines may be swapped."""

    async def main() -> None:
        sdh = Sdh2Emulator(ScriptedWorld(SHAPES))
        async with UnixEndpoint(sdh, str(tmp_path / "sdh.sock")) as ep:
            with pytest.raises(TactileError, match=r"none of them a DSACON32m packet.*swapped"):
                await TactileBus.open(ep.url, TactileOptions(reconnect=False))

    run_fast(main())


def test_a_booting_controller_s_open_port_is_not_called_refused(tmp_path: Path) -> None:
    """Found by stress-testing: the status kept "cannot open: … Connection refused" through the
    DSACON32m's 8 s boot, while the port was open and the open sequence waited for its answer."""

    async def main() -> tuple[str | None, str | None, bool]:
        path = tmp_path / "dsa.sock"
        bus = await TactileBus.open(f"unix://{path}", TactileOptions(), patient=True)
        try:
            await until(lambda: bus.failure is not None and "cannot open" in bus.failure)
            refused = bus.failure
            emu = DsaconEmulator(ScriptedWorld(SHAPES), options=DsaconOptions(boot_s=8.0))
            async with UnixEndpoint(emu, str(path)):
                await until(lambda: bus.failure is not None and "port open" in bus.failure)
                booting = bus.failure
                await until(lambda: bus.connected, timeout=30.0)
                return refused, booting, bus.failure is None
        finally:
            await bus.close()

    refused, booting, cleared = run_fast(main())
    assert refused is not None and refused.startswith("cannot open")
    assert booting is not None and booting.startswith("port open, no answer yet")
    assert booting.endswith(f"before: {refused}")  # said once, not nested attempt after attempt
    assert cleared
