"""Connecting to a hand, real or simulated: the one seam between the drivers and what uses them.

A real hand is two serial URLs (:class:`Real`). A simulated one (:class:`Simulated`) is an object
and a clock: the simulated hand is started in this process and the drivers reach it through the
same URL mechanism a real hand has (TCP; Unix sockets in fast mode, on the virtual clock). Either
way :func:`connect_hand` yields a :class:`Hand` with both open links; in simulation only, it also
carries a :class:`Bench` — what a lab has beside the hand: put the object back, its true outline,
the truth. Nothing above asks "is it simulated?" again; it asks whether there is a bench.

Opening and closing in order is written here once: the simulated hand, then the joint line, then
the tactile bus; closed the other way round.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import tempfile
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sdh2svc.bus.joint import HandRefused, JointLink
from sdh2svc.bus.link import check_url
from sdh2svc.bus.tactile import HandUnlike, TactileBus, TactileOptions
from sdh2svc.config import ConfigError, Settings
from sdh2svc.model.hand import matrix_pads
from sdh2svc.sim.hand import HandModel, ObjectNow, Truth
from sdh2svc.sim.lab import SimulatedHand, start_simulated_hand
from sdh2svc.sim.objects import Outline, Shape
from sdh2svc.sim.physics import ContactTruth
from sdh2svc.sim.press import Press


@dataclass(frozen=True, slots=True)
class Real:
    """A real hand: its DSACON32m (tactile) and SDH2 (joints) lines, device paths or URLs.
    ``patient``: the lines are opened in the background until the hand answers (a service that
    starts before its hand is on), not refused at once."""

    dsa_url: str
    sdh_url: str
    patient: bool = False


@dataclass(frozen=True, slots=True)
class Simulated:
    """A simulated hand in this process.

    ``obj`` defaults to the configuration's ``sim.object``. ``fast``: Unix sockets in a
    temporary folder, for the virtual clock (:func:`sdh2svc.sim.clock.run_fast`); else TCP on
    ``sim.links.host`` (ports: 0 = free ones, None = the configuration's) and, with ``pty``,
    ptys. ``replace_after_s`` > 0 starts a lab assistant that puts a let-go object back (real
    time only); None takes ``sim.replace_after_s``.
    """

    obj: Shape | None = None
    fast: bool = False
    tcp: bool = True
    pty: bool = False
    dsa_port: int | None = 0
    sdh_port: int | None = 0
    replace_after_s: float | None = 0.0


Where = Real | Simulated


def real_hand(
    cfg: Settings, dsa_url: str | None = None, sdh_url: str | None = None, *,
    patient: bool = False,
) -> Real:  # fmt: skip
    """The real hand at the given lines, else at the configuration's ``links``."""
    return Real(dsa_url or cfg.links.dsa_url, sdh_url or cfg.links.sdh_url, patient)


def hand_model(cfg: Settings) -> HandModel:
    """The model's sections of the configuration that the simulation copies."""
    return HandModel(cfg.hand, cfg.axes, cfg.tactile)


class Bench:
    """The simulated hand's surroundings, as a lab has them: the object between the fingertips
    (put it back, or another), its true outline, the truth, and a person's finger to press a
    pad with. A real hand has none."""

    def __init__(self, sim: SimulatedHand) -> None:
        self.sim = sim  # the emulators, for tests that look at the devices themselves

    @property
    def obj(self) -> Shape:
        return self.sim.world.obj

    @property
    def outline(self) -> Outline:
        return self.sim.world.outline

    def place(
        self, obj: Shape | None = None, *, height_mm: float | None = None,
        angle_deg: float | None = None,
    ) -> None:  # fmt: skip
        """Put ``obj`` (default: the same object) between the fingertips, in the fixture."""
        self.sim.world.place(obj or self.obj, height_mm=height_mm, angle_deg=angle_deg)

    def press(self, press: Press, after_s: float = 0.0) -> None:
        """Press a pad ``after_s`` from now, on the simulated hand's clock (the running event
        loop's: virtual in fast mode); ValueError if the press is off the pad."""
        self.sim.world.press(press, asyncio.get_running_loop().time() + after_s)

    def release(self) -> int:
        """Lift every press that is on now; returns how many."""
        return self.sim.world.release(asyncio.get_running_loop().time())

    def truth(self) -> Truth:
        """What really happens now (steps the physics up to the joints' actual pose)."""
        return self.sim.world.truth()

    def object_pose(self) -> tuple[float, float, float]:
        """The object's pose (y, z mm; ψ rad) without stepping anything: reading it mid-run
        leaves the run exactly as it would have been unobserved."""
        return self.sim.world.object_pose()

    def contacts_now(self) -> tuple[ContactTruth, ...]:
        """The true contacts as last stepped; like :meth:`object_pose`, steps nothing."""
        return self.sim.world.contacts_now()

    def object_now(self) -> ObjectNow:
        """The object's pose and state as last stepped; like :meth:`object_pose`, steps nothing
        (a run recorded with its truth stays bit for bit the run without)."""
        return self.sim.world.object_now()


@dataclass(frozen=True, slots=True)
class Hand:
    """An open hand: both links, where they lead, and — in simulation only — the bench."""

    joints: JointLink
    tactile: TactileBus
    dsa_url: str
    sdh_url: str
    bench: Bench | None
    fast: bool = False  # simulated on the virtual clock

    @property
    def real(self) -> bool:
        """A real hand (whose e-stop latch on disk applies), not a simulated one."""
        return self.bench is None

    def describe(self) -> dict[str, Any]:
        """The hand as a run's record names it: where, and which firmware answered."""
        info = self.tactile.controller_info
        return {"sim": not self.real, "fast": self.fast, "dsa_url": self.dsa_url,
                "sdh_url": self.sdh_url, "sdh_firmware": self.joints.version,
                "dsacon_firmware": info.sw_version if info else None,
                "dsacon_serial": info.serial_no if info else None}  # fmt: skip


@contextlib.asynccontextmanager
async def simulated_hand(cfg: Settings, spec: Simulated) -> AsyncIterator[Bench]:
    """The simulated hand alone, served on its endpoints (``bench.sim.urls``), stopped at the
    end: for a driver elsewhere (``sdh2svc sim``, a service in another process)."""
    with contextlib.ExitStack() as stack:
        unix_dir = None
        if spec.fast:
            unix_dir = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix="sdh2svc-")))
        sim = await start_simulated_hand(
            hand_model(cfg), cfg.sim, obj=spec.obj, pty=spec.pty, tcp=spec.tcp, unix_dir=unix_dir,
            dsa_port=spec.dsa_port, sdh_port=spec.sdh_port, replace_after_s=spec.replace_after_s,
        )  # fmt: skip
        try:
            yield Bench(sim)
        finally:
            await sim.stop()


def _port(url: str) -> str:
    """What a line's URL opens: a device by its real path (a symlink is the device), a URL as
    written (its scheme in any case)."""
    url = url.strip()
    if "://" not in url:
        return os.path.realpath(url)
    scheme, _, rest = url.partition("://")
    return f"{scheme.lower()}://{rest}"


async def open_links(
    cfg: Settings, dsa_url: str, sdh_url: str, *, patient: bool = False
) -> tuple[JointLink, TactileBus]:
    """Both of the hand's lines, the joint controller first (its limits from the config); the
    hand as the configuration expects it — its speeds within the joints' velocity limits, its
    pads laid out as configured — or a ConfigError / TactileError saying how it differs.
    ``patient``: each line connects in the background until its controller answers (as a
    lost line reconnects; its link says why it is not up yet), and the same checks refuse a
    hand unlike the configuration at every connection."""
    try:
        for url in (dsa_url, sdh_url):
            check_url(url)
    except ValueError as e:
        raise ConfigError([str(e)]) from None
    if _port(dsa_url) == _port(sdh_url):
        same = f"the tactile and the joint line are both {sdh_url!r}"
        raise ConfigError([f"{same}: each controller has a line of its own (--dsa/--sdh, "
                           "links.dsa_url/sdh_url)"])  # fmt: skip
    lim = cfg.limits
    limits = list(zip(lim.min_deg, lim.max_deg, strict=True))
    try:
        joints = await JointLink.open(sdh_url, binary=cfg.links.binary, limits=limits,
                                      accept=cfg.run.speeds_outside, patient=patient)  # fmt: skip
    except HandRefused as e:  # a run or Open hand would command what the hand refuses
        raise ConfigError(e.problems) from None
    try:
        expect = tuple((pad, lay.rows, lay.cols) for pad, lay in matrix_pads(cfg.axes, cfg.tactile))
        options = TactileOptions(expect=expect, pitch_mm=cfg.tactile.texel_pitch_mm)
        tactile = await TactileBus.open(dsa_url, options, patient=patient)
    except HandUnlike as e:  # reached, but not the hand the configuration describes
        await joints.close()
        raise ConfigError([str(e)]) from None
    except BaseException:
        await joints.close()
        raise
    return joints, tactile


@contextlib.asynccontextmanager
async def connect_hand(cfg: Settings, where: Where) -> AsyncIterator[Hand]:
    """Open the hand — the simulated one first, if that — and both links; close them in order
    (the links, then the simulated hand)."""
    async with contextlib.AsyncExitStack() as stack:
        bench: Bench | None = None
        fast = isinstance(where, Simulated) and where.fast
        if isinstance(where, Simulated):
            bench = await stack.enter_async_context(simulated_hand(cfg, where))
            dsa_url, sdh_url = bench.sim.urls("dsa")[0], bench.sim.urls("sdh")[0]
        else:
            dsa_url, sdh_url = where.dsa_url, where.sdh_url
        patient = isinstance(where, Real) and where.patient
        joints, tactile = await open_links(cfg, dsa_url, sdh_url, patient=patient)
        stack.push_async_callback(_close_quietly, joints)
        stack.push_async_callback(_close_quietly, tactile)
        yield Hand(joints, tactile, dsa_url, sdh_url, bench, fast)


async def _close_quietly(link: JointLink | TactileBus) -> None:
    with contextlib.suppress(Exception):
        await link.close()
