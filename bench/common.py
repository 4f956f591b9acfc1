"""Small helpers shared by the benchmark sections."""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable


def percentile(values: list[float], q: float) -> float:
    """q-th percentile (0…100) by nearest rank on the sorted values."""
    s = sorted(values)
    return s[min(len(s) - 1, max(0, round(q / 100 * (len(s) - 1))))]


def p99_ratio_interval(
    base: list[list[float]], loaded: list[list[float]], n: int = 2000, seed: int = 0
) -> tuple[float, float]:
    """A 95 % interval of p99(loaded) / p99(base), each pooled over its runs' values, by a
    two-level bootstrap: runs drawn with replacement, then each drawn run's values. A p99 of a
    few hundred values is its few worst ones, and one run's preemptions on a shared machine
    move them: drawing the runs says how much (iterations alone would say far too little)."""
    import numpy as np

    rng = np.random.default_rng(seed)

    def p99(runs: list[np.ndarray]) -> float:
        picked = [runs[i] for i in rng.integers(len(runs), size=len(runs))]
        pooled = np.concatenate([r[rng.integers(len(r), size=len(r))] for r in picked])
        return percentile(pooled.tolist(), 99)

    b = [np.asarray(r, dtype=float) for r in base if r]
    lo = [np.asarray(r, dtype=float) for r in loaded if r]
    ratios = sorted(p99(lo) / p99(b) for _ in range(n))
    return ratios[round(0.025 * (n - 1))], ratios[round(0.975 * (n - 1))]


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
