"""The vectorised RLE encoder against a literal one, on both sides of its 4096-texel lookup."""

from __future__ import annotations

import numpy as np
import pytest

from sdh2svc.protocol import dsa


def _literal(values: list[int], breaks: set[int]) -> bytes:
    """Greedy runs of at most 15, restarted at a new value or a break (protocols.md §1.5)."""
    words: list[int] = []
    count = 0
    for i, v in enumerate(values):
        if count and (v != values[i - 1] or count == 15 or i in breaks):
            words.append(count << 12 | values[i - 1])
            count = 0
        count += 1
    if count:
        words.append(count << 12 | values[-1])
    return b"".join(w.to_bytes(2, "little") for w in words)


@pytest.mark.parametrize("n", [1, 2, 15, 16, 31, 486, 4095, 4096, 4097, 5000])
def test_rle_encode_matches_the_literal_runs(n: int) -> None:
    rng = np.random.default_rng(n)
    for _ in range(5):
        # long zero runs, short runs of repeats and lone values, as a loaded pad gives
        values = rng.integers(0, 4, n) * (rng.random(n) < 0.3) * rng.integers(1, 1366)
        breaks = sorted({int(b) for b in rng.integers(0, n + 1, int(rng.integers(0, 6)))})
        want = _literal([int(v) for v in values], set(breaks))
        assert dsa.rle_encode(values, breaks=breaks) == want
        assert np.array_equal(dsa.rle_decode(want, n), values)
