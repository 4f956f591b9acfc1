"""Pre-shape, release and *Open hand* moves (control/motion.py) on the simulated hand, through
the real driver and bytes, on the virtual clock: as fast as ≤ 1° increments let a finger stop,
and still within one increment of where they were when their loop stops."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

from sdh2svc.control.motion import move_in_increments, move_to_preshape
from tests.control.test_runner import cfg_with, fast, rig

FINGERS = (1, 2, 3, 4, 5, 6)
EPS = 1e-4  # the binary protocol's float32 angles


def test_a_move_runs_as_fast_as_its_increments_allow_and_stops_with_its_loop(
    tmp_path: Path,
) -> None:
    straight = [0.0, 0.0, 0.0, -90.0, 0.0, 0.0, 0.0]
    cfg = cfg_with(tmp_path, f"sim.start_deg={straight}")
    lo, hi = cfg.limits.min_deg, cfg.limits.max_deg

    async def main() -> tuple[float, tuple[float, ...], tuple[float, ...], tuple[float, ...]]:
        async with rig(cfg, tmp_path) as (_sim, runner):
            joints, loop = runner.joints, asyncio.get_running_loop()
            t0 = loop.time()
            shaped = await move_to_preshape(joints, cfg.run, (lo, hi), cfg.safety)
            took = loop.time() - t0
            # back towards straight, and the loop stops a second into the move
            back = asyncio.create_task(move_in_increments(
                joints, straight, velocity_deg_s=cfg.run.preshape_velocity_deg_s, lo=lo,
                hi=hi, max_step_deg=cfg.safety.max_step_deg))  # fmt: skip
            await asyncio.sleep(1.0)
            back.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await back
            stopped = await joints.get_actual()
            await asyncio.sleep(3.0)
            return took, shaped, stopped, await joints.get_actual()

    took, shaped, stopped, after = fast(main)
    assert max(abs(a - g) for a, g in zip(shaped, cfg.run.preshape_deg, strict=True)) < 0.1
    # axis 0 turns 90°: about 5 s at the 15–20°/s that one-degree increments allow (at a
    # proximal axis's 400°/s², a finger that must stop within 1° moves at ≤ 22°/s); a pause
    # added between increments, or increments that no longer wait for the fingers, show here
    assert 4.0 < took < 6.5, took
    assert max(abs(stopped[i] - shaped[i]) for i in FINGERS) > 10.0  # it was under way …
    # … and went on at most the one increment it had been given
    assert max(abs(after[i] - stopped[i]) for i in FINGERS) <= cfg.safety.max_step_deg + EPS
