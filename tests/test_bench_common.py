"""The benchmarks' own statistics (bench/common.py)."""

from __future__ import annotations

import numpy as np

from bench.common import p99_ratio_interval


def _runs(scale: float, seed: int) -> list[list[float]]:
    rng = np.random.default_rng(seed)
    return [(scale * rng.lognormal(0.0, 0.3, 300)).tolist() for _ in range(3)]


def test_the_p99_ratios_interval_holds_the_truth() -> None:
    """Alike runs: an interval around 1; runs twice as slow: around 2, clear of 1."""
    low, high = p99_ratio_interval(_runs(1.0, 1), _runs(1.0, 2))
    assert low < 1.0 < high
    low, high = p99_ratio_interval(_runs(1.0, 1), _runs(2.0, 2))
    assert 1.3 < low < 2.0 < high < 3.0
    assert p99_ratio_interval(_runs(1.0, 1), _runs(2.0, 2)) == (low, high)  # seeded


def test_one_runs_spikes_widen_the_interval() -> None:
    """Ten iterations 10× late in one loaded run of three: the pooled p99 says +several-fold,
    the interval says a run made it (its low end near 1)."""
    base = _runs(1.0, 1)
    loaded = _runs(1.0, 2)
    loaded[0][:10] = [10.0 * x for x in loaded[0][:10]]
    low, high = p99_ratio_interval(base, loaded)
    assert low < 1.3 and high > 3.0
