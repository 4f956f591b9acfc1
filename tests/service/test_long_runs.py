"""What a run of thousands of strokes costs as it goes (rolling.cycles up to 10 000): what it
keeps per iteration, and the work at its end kept off the event loop."""

from __future__ import annotations

import asyncio
import threading
import tracemalloc
from pathlib import Path
from typing import Any

from test_sim_press import service
from test_storage_faults import JSON

from sdh2svc.config import load_config
from sdh2svc.connect import Simulated
from sdh2svc.control.runner import RunResult


def test_a_run_keeps_three_doubles_an_iteration_for_its_summary() -> None:
    """F, σ and the latency of every iteration are kept for the summary's statistics: as
    Python floats in lists, 96 bytes an iteration (≈ 0.4 GB over a 10 000-stroke run)."""
    result = RunResult("running")
    n = 100_000
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for i in range(n):
            result.forces.append(1.0 + i * 1e-6)
            result.sigmas.append(2.0 + i * 1e-6)
            result.latencies_ms.append(3.0 + i * 1e-6)
        per_iteration = (tracemalloc.get_traced_memory()[0] - before) / n
    finally:
        tracemalloc.stop()
    assert per_iteration < 3 * 8 * 1.2, per_iteration  # (a list's growth slack: ≤ 12 %)
    summary = result.summary()
    assert summary["force"]["min"] == 1.0 and summary["force"]["max"] == 1.0 + (n - 1) * 1e-6


def test_a_runs_summary_is_made_off_the_event_loop(tmp_path: Path, monkeypatch: Any) -> None:
    """The summary sorts every latency and takes the force's deviation exactly: 0.4 s at
    440 000 iterations, ≈ 4 s at 4 million, during which the service answered nothing (an
    e-stop's request included). It is made in a thread (on the virtual clock, where work sent
    to a thread runs inline, the loop is all there is)."""
    made_in: list[bool] = []
    summary = RunResult.summary

    def watched(self: RunResult) -> dict[str, Any]:
        made_in.append(threading.current_thread() is threading.main_thread())
        return summary(self)

    monkeypatch.setattr(RunResult, "summary", watched)
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            assert (await c.post("/api/runs", json={})).status_code == 201
            assert (await c.post("/api/runs/stop", headers=JSON)).status_code == 202
            while services.station.running:
                await asyncio.sleep(0.01)

    asyncio.run(main())
    assert made_in == [False]  # once, not on the event loop's thread
