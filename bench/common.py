"""Small helpers shared by the benchmark sections."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def percentile(values: list[float], q: float) -> float:
    """q-th percentile (0…100) by nearest rank on the sorted values."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def time_calls(fn: Callable[[], object], n: int, warmup: int = 200) -> list[float]:
    """Wall time of each of ``n`` calls of ``fn``, in microseconds."""
    for _ in range(warmup):
        fn()
    out = []
    for _ in range(n):
        t0 = time.perf_counter_ns()
        fn()
        out.append((time.perf_counter_ns() - t0) / 1000.0)
    return out


def summary_us(samples: list[float]) -> str:
    return (
        f"median {statistics.median(samples):8.1f} µs   p99 {percentile(samples, 99):8.1f} µs   "
        f"(n = {len(samples)})"
    )
