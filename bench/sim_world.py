"""The simulated world alone: physics step + tactile frame, in fast (virtual-clock) mode.

A scripted rolling motion stands in for the controller: Finger 2 follows the thesis's route
(Δφ, k·Δφ) and Finger 1 mirrors it, one joint command and one tactile frame per iteration at
30 Hz of simulated time, for a 3-stroke run's worth of iterations.
"""

from __future__ import annotations

import statistics
import time

from bench.common import percentile
from sdh2svc.config import load_config
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import get_object

ITERATIONS = 540  # ≈ 3 strokes of 2 × 90 iterations, as in the thesis's runs
FRAME_PERIOD_S = 1 / 30


def run_object(name: str) -> dict[str, float]:
    cfg = load_config(use_env=False)
    w = PhysicsWorld(cfg, cfg.sim, get_object(name))
    ctx = cfg.model_context()
    q = [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0]
    t = 0.0
    w.move_joints(t, q, [True] * 7)
    sens, thr = [0.5] * 6, [0] * 6
    while True:  # grasp
        t += FRAME_PERIOD_S
        f = w.tactile_frame(t, sens, thr)
        c1, c2 = ctx.contact(f[84:162].reshape(13, 6)), ctx.contact(f[408:486].reshape(13, 6))
        if (c1.force_library + c2.force_library) / 2 >= 2.0 or q[1] > 40:
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


def run() -> dict[str, float]:
    print(f"simulated world, fast mode: {ITERATIONS} iterations at 30 Hz of simulated time")
    out = {}
    for name in ("egg", "rubber", "cylinder"):
        r = run_object(name)
        out[name] = r["speed"]
        print(f"  {name:9s} {r['speed']:7.1f}× real time  physics step median "
              f"{r['step_median_us']:7.0f} µs p99 {r['step_p99_us']:7.0f} µs   tactile frame "
              f"{r['frame_median_us']:5.0f} µs   held at the end: {bool(r['held'])}")  # fmt: skip
    print("  target: ≥ 50× real time (the byte path and drivers are not in this figure)")
    return out
