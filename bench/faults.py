"""Faults next to the hand: bit errors on the joint line, the e-stop's latency, cables cut and
the service killed during the grasp — what the fault figures of docs/benchmarks.md come from.

* Bit errors (fast mode, virtual clock): from the grasp on, the joint line's replies carry bit
  errors at a rate; per rate, how many 1-stroke egg runs complete, how they end otherwise, and
  the highest F any frame showed, against the ceiling. The same for other faults of the joint
  line: replies cut short, and bit errors both ways (the commands too).
* E-stop: ``POST /api/estop`` on a real service (``sdh2svc serve --sim``) during the rolling —
  the answer comes once the hand has taken the power-off and the hold.
* Cables cut and ``kill -9`` (real time): the simulated hand in this process, the service as
  its own process reaching the joint line through a cable that is cut; how far the fingers went
  in the 2 s after the cut or the kill, and after the link (or the service) came back.
"""

from __future__ import annotations

import asyncio
import dataclasses
import signal
import statistics
import tempfile
import time
from collections import Counter
from pathlib import Path
from typing import Any

from sdh2svc.client import AsyncClient, StatusCheck, run_state
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, connect_hand, simulated_hand
from sdh2svc.control.observer import BaseObserver, Event, EventKind
from sdh2svc.control.runner import Runner
from sdh2svc.sim.cable import Cable
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.faults import FaultConfig
from sdh2svc.sim.lab import SimulatedHand
from tests.live_service import LiveService, start_service

RATES = (0.0, 1e-4, 3e-4, 1e-3, 3e-3)
SEEDS = range(1, 9)
# other faults of the joint line, from the grasp on: (what, the fault), on OTHER_SEEDS each
OTHER = (
    ("replies cut short at 1 % of packets", FaultConfig(truncate_packet_rate=0.01)),
    ("bit errors both ways (the commands too) at 3e-5",
     FaultConfig(bit_error_rate=3e-5, host_to_device=True)),
    ("bit errors both ways (the commands too) at 1e-4",
     FaultConfig(bit_error_rate=1e-4, host_to_device=True)),
)  # fmt: skip
OTHER_SEEDS = range(1, 5)
WATCH_S = 2.0
FINGERS = (1, 2, 3, 4, 5, 6)


async def _noisy_run(tmp: Path, faults: FaultConfig, seed: int) -> tuple[str, float]:
    cfg = load_config(overrides=[f"storage.db_path='{tmp / 'b.sqlite'}'", f"sim.seed={seed}",
                                 "rolling.cycles=1"], use_env=False)  # fmt: skip
    ctx, axes = cfg.model_context(), cfg.axes
    peak = 0.0

    def watch(frame: Any) -> None:
        nonlocal peak
        c1 = ctx.contact(frame.matrices[axes.finger1_distal_matrix])
        c2 = ctx.contact(frame.matrices[axes.finger2_distal_matrix])
        peak = max(peak, (c1.force + c2.force) / 2)  # the controller's F

    async with connect_hand(cfg, Simulated(fast=True)) as hand:
        assert hand.bench is not None
        sim = hand.bench.sim

        class OnGrasping(BaseObserver):
            def event(self, e: Event) -> None:
                if e.kind is EventKind.PHASE and e.detail["phase"] == "grasping":
                    sim.endpoints["sdh"][0].set_faults(dataclasses.replace(faults, seed=seed))

        hand.tactile.add_frame_listener(watch)
        result = await Runner(cfg.control(), hand.joints, hand.tactile, observer=OnGrasping()).run()
    how = result.status if result.status != "faulted" else result.message.split(":")[0]
    return how, peak / (cfg.safety.force_ceiling_factor * cfg.rolling.grasp_force)


def _bit_errors() -> None:
    print("  bit errors in the joint line's replies from the grasp on (egg, 1 stroke, "
          f"{len(SEEDS)} seeds each, fast mode):")  # fmt: skip
    for ber in RATES:
        _noisy_runs(f"BER {ber:7.0e}", FaultConfig(bit_error_rate=ber), SEEDS)
    print(f"  other faults of the joint line from the grasp on ({len(OTHER_SEEDS)} seeds each):")
    for what, faults in OTHER:
        _noisy_runs(what, faults, OTHER_SEEDS)


def _noisy_runs(what: str, faults: FaultConfig, seeds: range) -> None:
    ends: Counter[str] = Counter()
    peaks = []
    for seed in seeds:
        with tempfile.TemporaryDirectory() as tmp:
            how, peak = run_fast(_noisy_run(Path(tmp), faults, seed))
        ends[how] += 1
        peaks.append(peak)
    done = ends.pop("completed", 0)
    other = ", ".join(f"{n} {k}" for k, n in ends.most_common()) or "none"
    print(f"    {what}: {done}/{len(seeds)} completed (others: {other}); "
          f"highest F / ceiling {max(peaks):.2f} (must stay ≤ 1)")  # fmt: skip


async def _estop_latency(tmp: Path, trials: int = 5) -> None:
    svc = await asyncio.to_thread(start_service, tmp, viewer=False)
    times = []
    try:
        async with svc.client() as client:
            for _ in range(trials):
                await client.start_run()
                await _wait(client, run_state("rolling"))
                t0 = time.perf_counter()
                answer = await client.estop()
                times.append((time.perf_counter() - t0) * 1000)
                assert answer["hand_reached"], answer
                await client.release_estop()
                await _wait(client, lambda st: not st["run"] or st["run"]["state"] == "e-stopped")
    finally:
        await asyncio.to_thread(svc.stop)
    print(f"  e-stop during the rolling (REST answer = hand powered off and held), {trials} "
          f"trials: median {statistics.median(times):.0f} ms, max {max(times):.0f} ms")  # fmt: skip


async def _wait(client: AsyncClient, ok: StatusCheck, timeout_s: float = 90.0) -> dict[str, Any]:
    return await client.wait_status(ok, timeout=timeout_s)


def _angles(sim: SimulatedHand) -> tuple[float, ...]:
    sim.sdh.next_wakeup(asyncio.get_running_loop().time())
    return sim.sdh.actual_deg


def _travel(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    return max(abs(a[i] - b[i]) for i in FINGERS)


async def _cut_or_kill(tmp: Path, kill: bool) -> tuple[float, float]:
    """The fingers' travel in WATCH_S after the fault, and after the link/service is back."""
    async with simulated_hand(load_config(use_env=False), Simulated()) as bench:
        return await _watch_cut_or_kill(tmp, kill, bench.sim)


async def _watch_cut_or_kill(tmp: Path, kill: bool, sim: SimulatedHand) -> tuple[float, float]:
    host, port = sim.urls("sdh")[0].removeprefix("socket://").rsplit(":", 1)
    cable = Cable(host, int(port))
    await cable.plug()
    extra = ["--dsa", sim.urls("dsa")[0], "--sdh", cable.url]
    serve = lambda: start_service(tmp, viewer=False, sim=False, extra=extra)  # noqa: E731
    svc: LiveService = await asyncio.to_thread(serve)
    try:
        async with svc.client() as client:
            await client.start_run()
            await _wait(client, run_state("grasping"))
        start = _angles(sim)
        while _travel(_angles(sim), start) < 0.3:
            await asyncio.sleep(0.02)
        if kill:
            await asyncio.to_thread(svc.stop, signal.SIGKILL)
        else:
            await cable.cut()
        at = _angles(sim)
        await asyncio.sleep(WATCH_S)
        during = _travel(_angles(sim), at)
        if kill:
            svc = await asyncio.to_thread(serve)
        else:
            await cable.plug()
        async with svc.client() as client:
            await _wait(client, lambda st: st["hand"]["connected"]["joints"])
        await asyncio.sleep(WATCH_S / 2)
        return during, _travel(_angles(sim), at)
    finally:
        await asyncio.to_thread(svc.stop)
        await cable.close()


def run() -> None:
    print("faults")
    _bit_errors()
    with tempfile.TemporaryDirectory() as tmp:
        asyncio.run(_estop_latency(Path(tmp)))
    for kill in (False, True):
        what = "service killed (-9) and restarted" if kill else "joint cable cut and plugged back"
        moved = []
        for _ in range(3):
            with tempfile.TemporaryDirectory() as tmp:
                moved.append(asyncio.run(_cut_or_kill(Path(tmp), kill)))
        print(f"  {what} during the grasp, 3 times: the fingers went at most "
              f"{max(m[0] for m in moved):.2f}° in {WATCH_S:g} s after it, "
              f"{max(m[1] for m in moved):.2f}° until after it was back "
              f"(one increment: ≤ 1°; the velocity grasp went on at 3 °/s)")  # fmt: skip
