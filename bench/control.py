"""The closed loop: the rolling step's compute time, and whole runs through the drivers and
bytes — in real time (sense→command latency, iterations vs frames per second) and in fast mode
(simulated seconds per wall second for a 3-stroke run)."""

from __future__ import annotations

import asyncio
import math
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import percentile, summary_us, time_calls
from sdh2svc.config import load_config
from sdh2svc.control.rolling import RollState, step
from sdh2svc.model.kinematics import HandPose
from sdh2svc.service.headless import run_once
from sdh2svc.sim.clock import run_fast


def _frame(S: float) -> np.ndarray:
    m = np.zeros((13, 6), dtype=np.uint16)
    j = int(S // 3.4)
    w = S / 3.4 - j
    m[j, 1:5], m[j + 1, 1:5] = round(1500 * (1 - w)), round(1500 * w)
    return m


def run() -> dict[str, float]:
    cfg = load_config(use_env=False)
    ctx = cfg.model_context()
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))
    f1, f2 = _frame(20.0), _frame(22.0)
    samples = time_calls(lambda: step(RollState(), pose, f1, f2, cfg.rolling, ctx), 5000)
    print("closed loop")
    print(f"  control step (pure)  {summary_us(samples)}")
    out: dict[str, float] = {"step_median_us": float(np.median(samples)),
                             "step_p99_us": percentile(samples, 99)}  # fmt: skip
    with tempfile.TemporaryDirectory() as tmp:
        db = f"storage.db_path='{Path(tmp) / 'bench.sqlite'}'"
        rt = load_config(overrides=[db, "rolling.cycles=1", "sim.object='egg'"], use_env=False)
        t0 = time.perf_counter()
        s = asyncio.run(run_once(rt, sim=True))
        wall = time.perf_counter() - t0
        lat = s["latency_ms"]
        its, skipped = s["iterations"], s["frames_skipped"]
        print(f"  real time at {rt.sim.links.baud} baud, egg, 1 stroke: {s['status']}, {its} "
              f"iterations in {wall:.1f} s wall")  # fmt: skip
        print(f"  iterations/s {s['loop_hz']:.1f} vs frames/s {s['frames']['frames_per_s']:.1f} "
              f"delivered: {its / (its + skipped):.2f} iterations per fresh frame while rolling, "
              f"{skipped} skipped (target: 1.00, 0 skipped)")  # fmt: skip
        print(f"  sense→command (frame complete → targets written): p50 {lat['p50']:.1f} ms, "
              f"p99 {lat['p99']:.1f} ms (includes the `pos` and `p` round trips)")  # fmt: skip
        out["iterations_per_frame"] = its / (its + skipped)
        out["frames_skipped"] = skipped
        out["latency_p99_ms"] = lat["p99"]
        fast = load_config(overrides=[db, "rolling.cycles=3", "sim.object='egg'"], use_env=False)
        t0 = time.perf_counter()
        s = run_fast(run_once(fast, sim=True, fast=True))
        wall = time.perf_counter() - t0
        ratio = s["iterations"] / s["loop_hz"] / wall if s["loop_hz"] else float("nan")
        print(f"  fast mode, egg, 3 strokes: {s['status']}, {s['iterations']} iterations, "
              f"rolling phase {s['iterations'] / s['loop_hz']:.1f} simulated s in {wall:.1f} s "
              f"wall for the whole run, grasp included → {ratio:.1f}× real time (the world's "
              "own speed, target 50×: python -m bench sim)")  # fmt: skip
        out["fast_ratio"] = ratio
    return out
