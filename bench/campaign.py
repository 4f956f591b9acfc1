"""Campaign throughput: the smoke suite (3 strokes per case, fast mode, the full byte path) on 1
and on 2 worker processes — runs per hour per core, and the parallel efficiency from 1 to 2
workers (target ≥ 0.85; the machine is shared, so run it when nothing else does)."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import run_campaign


def _wall(workers: int) -> tuple[float, int]:
    suite = load_suite("smoke")
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        run_campaign(suite, Path(tmp) / "out", workers=workers, progress=False)
        return time.perf_counter() - t0, len(suite.cases)


def run() -> None:
    print("campaign (smoke suite)")
    t1, n = _wall(1)
    t2, _ = _wall(2)
    print(f"  1 worker : {n} cases in {t1:.1f} s = {3600 * n / t1:.0f} runs per hour per core")
    print(f"  2 workers: {n} cases in {t2:.1f} s = {3600 * n / t2 / 2:.0f} runs per hour per core")
    print(f"  parallel efficiency 1 → 2 workers: {t1 / t2 / 2:.2f} (target ≥ 0.85)")
