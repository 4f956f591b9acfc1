"""The simulated hand as a lab would plug it in: both controllers served on ptys and TCP ports.

One :class:`~sdh2svc.sim.hand.PhysicsWorld` stands behind a DSACON32m emulator and an SDH2
joint-controller emulator; each emulator is served on a pty and on a TCP port (or a Unix socket in
fast mode). A device has one host at a time, so when it is served on several endpoints the one
whose host spoke last owns its replies (:class:`SharedDevice`).

Between runs a :class:`LabAssistant` puts the object back between the fingertips once it has
been released or dropped and no pad has touched it for a while — what a person in the lab does
before the next run — so that a driver can run again and again against one simulated hand.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import sys
from dataclasses import dataclass, field
from pathlib import Path

from sdh2svc.model.hand import matrix_pads
from sdh2svc.sim.dsacon import DsaconEmulator, DsaconOptions
from sdh2svc.sim.endpoint import Device, Endpoint, PtyEndpoint, TcpEndpoint, UnixEndpoint
from sdh2svc.sim.faults import FaultConfig
from sdh2svc.sim.hand import HandModel, PhysicsWorld
from sdh2svc.sim.objects import Shape
from sdh2svc.sim.sdh2 import Sdh2Emulator, Sdh2Options
from sdh2svc.sim.simconfig import SimConfig

log = logging.getLogger(__name__)


class LabAssistant:
    """Puts the object back between the fingertips (in the fixture, as at the start) once it
    is neither held nor in the fixture — released or dropped — and no pad has touched it for
    ``after_s``. Only the world's public ground truth and placement are used."""

    def __init__(self, world: PhysicsWorld, after_s: float, poll_s: float = 0.1) -> None:
        self.world, self.after_s, self.poll_s = world, after_s, poll_s
        self._loose_since: float | None = None

    def check(self, now: float) -> bool:
        """One look at the hand at time ``now`` (s); True if the object was put back."""
        t = self.world.truth()
        if t.held or t.in_fixture or t.contacts:
            self._loose_since = None
            return False
        if self._loose_since is None:
            self._loose_since = now
        if now - self._loose_since < self.after_s:
            return False
        self.world.place(self.world.obj)
        self._loose_since = None
        _say(f"the {t.object} was let go (released or dropped) and untouched for "
             f"{self.after_s:g} s: put back between the fingertips")  # fmt: skip
        return True

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(self.poll_s)
            self.check(loop.time())


def _say(message: str) -> None:
    """To the log when logging is set up (the service), else a line on stderr (`sdh2svc sim`)."""
    if logging.getLogger().hasHandlers():
        log.info("%s", message)
    else:
        print(f"sdh2svc sim: {message}", file=sys.stderr, flush=True)


class ServoClock:
    """The joint controller's own clock: steps its servo, and with it the world, whenever a
    motion needs it, whether or not a host is connected — a move or a velocity goes on after the
    host has gone, as the firmware's does.

    With ``lazy`` (a virtual clock: fast mode) it wakes for no tick: the emulator and the world
    catch up with it whenever they are read (:meth:`Sdh2Emulator.attach_lazy_clock`), stepping
    the same ticks at the same times. The ticks are the servo's physics and nobody sees one
    before something reads the hand, so the run is the same; what goes is an event-loop wake-up
    per 5 ms tick."""

    def __init__(self, sdh: Sdh2Emulator, world: PhysicsWorld | None = None, *,
                 lazy: bool = False) -> None:  # fmt: skip
        self.sdh = sdh
        self.lazy = lazy
        self._wakeup: asyncio.Future[None] | None = None
        if lazy:
            if world is None:
                raise ValueError("a lazy servo clock needs the world, to catch up when it is read")
            sdh.attach_lazy_clock(asyncio.get_running_loop().time)
            world.before_read = sdh.observe
        else:
            sdh.attach_clock(self.wake)

    def start(self) -> asyncio.Task[None]:
        task = asyncio.create_task(self.run(), name="sdh2-servo-clock")
        task.add_done_callback(_log_crash)
        return task

    def wake(self) -> None:
        """A command started a motion (or brought its next step forward): look again."""
        if self._wakeup is not None and not self._wakeup.done():
            self._wakeup.set_result(None)

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            due = self.sdh.step(loop.time())
            if self.lazy:
                return  # powered on; the rest is caught up when read
            self._wakeup = fut = loop.create_future()
            timer = None if due is None else loop.call_at(due, _resolve, fut)
            try:
                await fut
            finally:
                self._wakeup = None
                if timer is not None:
                    timer.cancel()


def _resolve(fut: asyncio.Future[None]) -> None:
    if not fut.done():
        fut.set_result(None)


def _log_crash(task: asyncio.Task[None]) -> None:
    if not task.cancelled() and (exc := task.exception()) is not None:
        log.error("the servo clock crashed", exc_info=exc)


class SharedDevice:
    """One device behind several endpoints: :meth:`port` gives each endpoint its own view."""

    def __init__(self, device: Device) -> None:
        self.device = device
        self.owner: _Port | None = None

    def port(self) -> _Port:
        return _Port(self)


class _Port:
    """An endpoint's view of a :class:`SharedDevice` (implements Device)."""

    def __init__(self, shared: SharedDevice) -> None:
        self.shared = shared

    def _claim(self, now: float) -> None:
        sh = self.shared
        if sh.owner is not self:
            if sh.owner is not None:
                sh.device.disconnected(now)
            sh.owner = self
            sh.device.connected(now)

    def connected(self, now: float) -> None:
        if self.shared.owner is None:
            self._claim(now)

    def disconnected(self, now: float) -> None:
        if self.shared.owner is self:
            self.shared.device.disconnected(now)
            self.shared.owner = None

    def receive(self, data: bytes, now: float) -> None:
        self._claim(now)
        self.shared.device.receive(data, now)

    def next_packet(self, now: float) -> bytes | None:
        return self.shared.device.next_packet(now) if self.shared.owner is self else None

    def next_wakeup(self, now: float) -> float | None:
        return self.shared.device.next_wakeup(now) if self.shared.owner is self else None


@dataclass
class SimulatedHand:
    """The running simulated hand: its world, both emulators and their endpoints."""

    world: PhysicsWorld
    dsa: DsaconEmulator
    sdh: Sdh2Emulator
    endpoints: dict[str, list[Endpoint]] = field(default_factory=dict)
    _assistant: asyncio.Task[None] | None = None  # the LabAssistant's polling task
    _clock: asyncio.Task[None] | None = None  # the joint controller's servo clock

    def urls(self, device: str) -> list[str]:
        return [ep.url for ep in self.endpoints.get(device, [])]

    async def stop(self) -> None:
        for task in (self._assistant, self._clock):
            if task is not None:
                task.cancel()
                with contextlib.suppress(asyncio.CancelledError):
                    await task
        self._assistant = self._clock = None
        for eps in self.endpoints.values():
            for ep in eps:
                with contextlib.suppress(Exception):
                    await ep.stop()


async def start_simulated_hand(
    model: HandModel,
    sim: SimConfig,
    *,
    obj: Shape | None = None,
    pty: bool | None = None,
    tcp: bool = True,
    unix_dir: Path | None = None,
    dsa_port: int | None = None,
    sdh_port: int | None = None,
    replace_after_s: float | None = None,
) -> SimulatedHand:
    """Build the world and both emulators and start their endpoints.

    ``unix_dir`` serves each device on a Unix socket in that folder instead of TCP and ptys (fast
    mode). Ports default to ``sim.links``; 0 picks free ones.
    ``replace_after_s`` (default: ``sim.replace_after_s``; 0: never) starts the
    :class:`LabAssistant` on the real-time event loop; in fast mode, whose clock is virtual, it
    is off.
    """
    links = sim.links
    world = PhysicsWorld(model, sim, obj)
    if sim.slow_axes:  # a fault set on purpose, or left in a configuration by mistake
        drags = "; ".join(f"axis {a} moves at most {v:g}°/s" for a, v in sim.slow_axes)
        log.warning("the simulated hand drags (sim.slow_axes): %s", drags)
    masks = [layout.valid() for _, layout in matrix_pads(model.axes, model.tactile)]
    dsa = DsaconEmulator(world, options=DsaconOptions(boot_s=links.dsa_boot_s), static_masks=masks)
    latency = Sdh2Options(ascii_latency_s=links.sdh_ascii_latency_ms / 1000,
                          binary_latency_s=links.sdh_binary_latency_ms / 1000)  # fmt: skip
    sdh = Sdh2Emulator(world, options=latency)
    hand = SimulatedHand(world, dsa, sdh)
    hand._clock = ServoClock(sdh, world, lazy=unix_dir is not None).start()
    faults = FaultConfig(bit_error_rate=links.bit_error_rate, seed=sim.seed)
    ports = {
        "dsa": links.dsa_tcp_port if dsa_port is None else dsa_port,
        "sdh": links.sdh_tcp_port if sdh_port is None else sdh_port,
    }
    try:
        for name, device in (("dsa", dsa), ("sdh", sdh)):
            shared = SharedDevice(device)
            eps: list[Endpoint] = []
            if unix_dir is not None:
                # fast mode: whole packets as their last byte is due (see endpoint.py)
                eps.append(UnixEndpoint(shared.port(), str(unix_dir / f"{name}.sock"),
                                        baud=links.baud, faults=faults,
                                        whole_packets=True))  # fmt: skip
            else:
                if pty if pty is not None else links.pty:
                    eps.append(PtyEndpoint(shared.port(), baud=links.baud, faults=faults))
                if tcp:
                    eps.append(TcpEndpoint(shared.port(), host=links.host, port=ports[name],
                                           baud=links.baud, faults=faults))  # fmt: skip
            hand.endpoints[name] = eps
            for ep in eps:
                await ep.start()
    except BaseException:
        await hand.stop()
        raise
    after = sim.replace_after_s if replace_after_s is None else replace_after_s
    if after > 0 and unix_dir is None:
        assistant = LabAssistant(world, after)
        hand._assistant = asyncio.create_task(assistant.run(), name="lab-assistant")
    return hand
