"""The simulated world in fast (virtual-clock) mode: the physics alone, then a whole run.

1. Physics alone: a scripted rolling motion stands in for the controller. Finger 2 follows the
   thesis's route (Δφ, k·Δφ) and Finger 1 mirrors it, one joint command and one tactile frame per
   iteration at 30 Hz of simulated time, for a 3-stroke run's worth of iterations.
2. A whole 3-stroke run of the egg (``sdh2svc run --sim --object egg --fast``) through all the
   bytes: emulators, paced Unix-socket lines, drivers, controller, recorder. Time spent inside the
   simulated world (every call into it: contact physics, the tactile sensor model and the lazy
   stepping's bookkeeping) is measured separately: the simulated seconds over that time are the
   world's own speed inside the run, and the share of the rest shows what bounds the whole run.

The target (≥ 50× real time in fast mode) is the simulated world's: part 1 and part 2's "world
alone" figure. The whole run's speed is printed next to it, not held to it.
"""

from __future__ import annotations

import asyncio
import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from bench.common import percentile
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, hand_model
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import get_object
from sdh2svc.sim.physics import ContactPhysics
from sdh2svc.sim.sdh2 import Sdh2Emulator
from sdh2svc.sim.sensor import TactileSensorModel

ITERATIONS = 540  # ≈ 3 strokes of 2 × 90 iterations, as in the thesis's runs
FRAME_PERIOD_S = 1 / 30
TARGET = 50.0  # × real time, for the simulated world (issue 4)


def run_object(name: str) -> dict[str, float]:
    cfg = load_config(use_env=False)
    w = PhysicsWorld(hand_model(cfg), cfg.sim, get_object(name))
    ctx = cfg.model_context()
    q = [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0]
    t = 0.0
    w.move_joints(t, q, [True] * 7)
    sens, thr = [0.5] * 6, [0] * 6
    while True:  # grasp
        t += FRAME_PERIOD_S
        f = w.tactile_frame(t, sens, thr)
        c1, c2 = ctx.contact(f[84:162].reshape(13, 6)), ctx.contact(f[408:486].reshape(13, 6))
        if (c1.force + c2.force) / 2 >= 2.0 or q[1] > 40:  # the controller's F at Fd
            break
        q[1] += 0.05
        q[2] -= 0.05
        q[5] += 0.05
        q[6] -= 0.05
        w.move_joints(t, q, [True] * 7)
    step_us, frame_us = [], []
    direction = 1.0
    t_wall = time.perf_counter()
    for i in range(ITERATIONS):
        if i % 90 == 0:
            direction = -direction
        q[5] -= 0.25 * direction
        q[6] += 0.5 * direction
        q[1] += 0.25 * direction
        q[2] -= 0.5 * direction
        t += FRAME_PERIOD_S
        t0 = time.perf_counter_ns()
        w.move_joints(t, q, [True] * 7)
        t1 = time.perf_counter_ns()
        w.tactile_frame(t, sens, thr)
        t2 = time.perf_counter_ns()
        step_us.append((t1 - t0) / 1000)
        frame_us.append((t2 - t1) / 1000)
    wall = time.perf_counter() - t_wall
    sim_s = ITERATIONS * FRAME_PERIOD_S
    return {
        "held": float(w.truth().held), "wall_s": wall, "sim_s": sim_s, "speed": sim_s / wall,
        "step_median_us": statistics.median(step_us), "step_p99_us": percentile(step_us, 99),
        "frame_median_us": statistics.median(frame_us),
    }  # fmt: skip


class _Stopwatch:
    """Accumulates the wall time and the calls of the methods it wraps (on the class), per
    label; wrapped methods may nest (a label's time then includes the inner ones'), except
    those wrapped with ``pause``: their time is left out of every call around them (their
    own inner wrapped calls still count, each under its label)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}
        self.calls: dict[str, int] = {}
        self.step_us: list[float] = []  # each "physics" call's duration
        self._undo: list[Callable[[], None]] = []
        self._paused = 0.0  # total time spent in pausing calls so far

    def wrap(self, cls: type, name: str, label: str, *, pause: bool = False) -> None:
        orig = getattr(cls, name)
        method = f"{cls.__name__}.{name}"  # calls are also counted per method
        self.seconds.setdefault(label, 0.0)
        self.calls.setdefault(label, 0)
        self.calls.setdefault(method, 0)

        def timed(*args: Any, **kwargs: Any) -> Any:
            paused0 = self._paused
            t0 = time.perf_counter_ns()
            try:
                return orig(*args, **kwargs)
            finally:
                dt = (time.perf_counter_ns() - t0) / 1e9
                if pause:
                    self._paused = paused0 + dt
                else:
                    dt -= self._paused - paused0
                self.seconds[label] += dt
                self.calls[label] += 1
                self.calls[method] += 1
                if label == "physics":
                    self.step_us.append(dt * 1e6)

        setattr(cls, name, timed)
        self._undo.append(lambda: setattr(cls, name, orig))

    def restore(self) -> None:
        for undo in reversed(self._undo):
            undo()


def run_whole(name: str = "egg") -> dict[str, Any]:
    """One whole fast run through the bytes; returns the speed and where the time went."""
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    watch = _Stopwatch()
    for method in ("move_joints", "tactile_frame", "truth"):  # the whole world, seam to seam
        watch.wrap(PhysicsWorld, method, "world")
    watch.wrap(ContactPhysics, "step", "physics")
    # a lazy servo clock catches up (steps the joint emulator) when the world is read: the
    # emulator's work, not the world's (the world calls it makes count as the world's)
    watch.wrap(Sdh2Emulator, "observe", "servo catch-up", pause=True)
    watch.wrap(TactileSensorModel, "frame", "sensor")
    with tempfile.TemporaryDirectory(prefix="sdh2svc-bench-") as tmp:
        db = Path(tmp) / "runs.sqlite"
        cfg = load_config(overrides=[f"storage.db_path={db}"], use_env=False)

        async def main() -> tuple[dict[str, Any], float]:
            loop = asyncio.get_running_loop()
            t0 = loop.time()
            summary = await run_once(cfg, Simulated(obj=get_object(name), fast=True))
            return summary, loop.time() - t0

        t_wall = time.perf_counter()
        try:
            summary, sim_s = run_fast(main())
        finally:
            watch.restore()
        wall = time.perf_counter() - t_wall
    return {
        "status": summary["status"], "strokes": summary["strokes"], "sim_s": sim_s,
        "wall_s": wall, "speed": sim_s / wall, "seconds": watch.seconds, "calls": watch.calls,
        "step_us": watch.step_us,
    }  # fmt: skip


def run() -> dict[str, float]:
    print(f"simulated world, fast mode: {ITERATIONS} iterations at 30 Hz of simulated time")
    print("  1. physics alone (scripted rolling; one iteration = one joint command, 2 substeps,")
    print("     and one tactile frame)")
    out = {}
    for name in ("egg", "rubber", "cylinder"):
        r = run_object(name)
        out[name] = r["speed"]
        print(f"  {name:9s} {r['speed']:7.1f}× real time ({r['speed'] / TARGET:4.2f} of the "
              f"{TARGET:.0f}× target)  iteration median {r['step_median_us']:6.0f} µs p99 "
              f"{r['step_p99_us']:6.0f} µs   tactile frame {r['frame_median_us']:4.0f} µs   "
              f"held at the end: {bool(r['held'])}")  # fmt: skip
    w = run_whole("egg")
    out["whole_egg"] = w["speed"]
    sec, calls, wall, sim_s = w["seconds"], w["calls"], w["wall_s"], w["sim_s"]
    world_speed = sim_s / sec["world"]
    out["world_in_run"] = world_speed
    rest = wall - sec["world"]
    steps = w["step_us"]
    print(
        f"  2. whole 3-stroke egg run through all the bytes (--fast): {w['status']}, "
        f"{w['strokes']} strokes, {sim_s:.1f} s simulated in {wall:.2f} s wall"
    )
    print(f"     whole run    {w['speed']:7.1f}× real time")
    print(
        f"     world alone  {world_speed:7.1f}× real time ({world_speed / TARGET:4.2f} of the "
        f"{TARGET:.0f}× target): {sec['world']:.2f} s wall in its calls, of which physics "
        f"{sec['physics']:.2f} s, tactile sensor model {sec['sensor']:.2f} s"
    )
    ticks, frames = calls["PhysicsWorld.move_joints"], calls["sensor"]
    print(
        f"     physics steps: {calls['physics']} for {ticks} servo ticks and {frames} tactile "
        f"frames ({calls['physics'] / frames:.1f} per frame), "
        f"median {statistics.median(steps):5.0f} µs p99 {percentile(steps, 99):6.0f} µs"
    )
    print(
        f"     where the wall time went: simulated world {sec['world'] / wall:5.1%}, everything "
        f"else (emulators, lines, drivers, controller, recorder) {rest / wall:5.1%}"
    )
    if rest > 0:
        print(f"     bound without any world cost: {sim_s / rest:5.1f}× real time")
    print(f"  target: the simulated world ≥ {TARGET:.0f}× real time (1. and 2.'s world alone)")
    return out
