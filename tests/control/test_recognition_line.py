"""The recognition's line window: its extremes kept in monotonic queues are the window's own
``max`` and ``min``, signed zeros and ties included."""

from __future__ import annotations

import math
import random
from collections import deque

from sdh2svc.control.recognition import _Extremes, _Line


def test_extremes_are_the_windows_max_and_min() -> None:
    rng = random.Random(11)
    for n in (1, 2, 3, 20, 120):
        ext, window = _Extremes(n), deque[float](maxlen=n)
        for i in range(600):
            if i == 300:
                ext.clear()
                window.clear()
            v = rng.choice([0.0, -0.0, 1.0, -1.0, rng.uniform(-5, 5), round(rng.uniform(-3, 3))])
            ext.add(v)
            window.append(v)
            want = max(window) - min(window)
            assert math.copysign(1.0, ext.span()) == math.copysign(1.0, want)
            assert ext.span() == want


def test_line_fit_travel_and_turn() -> None:
    rng = random.Random(12)
    line = _Line(20)
    xs, ys = deque[float](maxlen=20), deque[float](maxlen=20)
    for _ in range(200):
        x, y = rng.uniform(0, 40), rng.uniform(-1, 1)
        line.add(x, y)
        xs.append(x)
        ys.append(y)
        _, travel, turn, _ = line.fit()
        assert travel == max(xs) - min(xs)
        assert turn == math.degrees(max(ys) - min(ys))
