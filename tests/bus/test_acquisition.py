"""The tactile line's acquisition policy: pure functions of rates, sizes and times."""

from __future__ import annotations

import pytest

from sdh2svc.bus.acquisition import (
    ACK_BYTES,
    LineEstimates,
    Mode,
    RateMeter,
    choose_mode,
    line_verdict,
    next_pull,
    push_framerate,
)
from sdh2svc.protocol.line import BAUD


def test_scheduling_policy() -> None:
    def mode(
        required: float, push: float = 30.0, pull: float = 100.0, cur: Mode = Mode.IDLE
    ) -> Mode:
        return choose_mode(required, push_fps=push, pull_max_hz=pull, current=cur)

    assert mode(0.0) is Mode.IDLE
    assert mode(30.0) is Mode.PUSH  # rolling: distal pads at the controller's cap
    assert mode(2.0) is Mode.PULL  # collision watch only
    assert mode(20.0) is Mode.PULL  # pull sustains it with less line time
    assert mode(24.0, cur=Mode.PUSH) is Mode.PUSH  # hysteresis: stays in push
    assert mode(20.0, cur=Mode.PUSH) is Mode.PULL
    # Heavy contact: 985-byte frames cap push at ~11.7 fps and pull at ~10.9 Hz.
    assert mode(10.0, push=11.7, pull=10.9) is Mode.PUSH
    assert mode(5.0, push=11.7, pull=10.9) is Mode.PULL


def test_push_framerate_is_ceil_r_within_u16() -> None:
    assert push_framerate(30.0) == 30
    assert push_framerate(2.1) == 3
    assert push_framerate(0.2) == 1
    assert push_framerate(1e6) == 0xFFFF


def test_pull_schedule_is_anchored_and_catches_up() -> None:
    assert next_pull(1.0, 0.5, now=1.2) == 1.5  # on time: the anchored schedule
    assert next_pull(1.0, 0.5, now=1.7) == 1.7  # late: at once, the next ones stay anchored


def test_estimates_of_push_and_pull() -> None:
    line = LineEstimates(BAUD)
    assert line.push_fps() == 30.0  # 175-byte guess: the controller's cap binds
    line.frame_bytes = 985.0  # heavy contact
    assert line.push_fps() == pytest.approx(BAUD / 10 / 985)  # ≈ 11.7 fps
    assert line.pull_max_hz() == pytest.approx(1 / ((985 + ACK_BYTES) * 10 / BAUD + 0.005))
    line.pull_cycle(0.1)
    line.pull_cycle(0.2)
    assert line.pull_max_hz() == pytest.approx(1 / 0.12)  # EWMA 0.2 of the measured cycles
    line.push_achieved = 8.0
    assert line.push_fps() == pytest.approx(8.4)  # a little more than last measured
    for _ in range(50):
        line.frame(95)
    assert line.frame_bytes == pytest.approx(95, abs=1)
    assert line.line_utilisation_pct(BAUD / 10 / 2) == pytest.approx(50.0)


def test_line_verdict() -> None:
    ok = {"max_error_streak": 8, "min_dead_s": 0.5, "stall_s": 1.5}
    assert line_verdict(error_streak=9, quiet_s=0.4, expected_gap_s=None, **ok) is None
    assert line_verdict(error_streak=9, quiet_s=0.5, expected_gap_s=None, **ok) is not None
    assert line_verdict(error_streak=0, quiet_s=1.0, expected_gap_s=None, **ok) is None  # idle
    assert line_verdict(error_streak=0, quiet_s=1.5, expected_gap_s=0.1, **ok) is None
    assert "no good packet" in (
        line_verdict(error_streak=0, quiet_s=1.6, expected_gap_s=0.1, **ok) or ""
    )


def test_rate_meter_over_its_window() -> None:
    meter = RateMeter(start=0.0, window=2.0)
    rates = {}
    for i in range(30):  # 100 bytes every 0.1 s: 1000 bytes/s
        meter.add(i * 0.1, 100)
        rates[i] = meter.rate(i * 0.1 + 0.05)
    assert rates[9] == pytest.approx(1000 / 0.95)  # since start, not yet a whole window
    assert rates[29] == pytest.approx(20 * 100 / 2.0)  # the last 2 s only


def test_rate_meter_keeps_only_its_window_whoever_reads_it() -> None:
    """The tactile line's byte meter is read only by the status: a headless run read it once,
    at its end, and it held every read of the run until then (≈ 80 bytes an iteration: 0.35
    GB over a 10 000-stroke run). It drops what leaves its window as it goes."""
    meter = RateMeter(start=0.0, window=1.0)
    for i in range(100_000):  # 100 reads a second for 1000 s, never asked for the rate
        meter.add(i * 0.01, 10)
    assert len(meter._items) <= 101
    assert meter.rate(999.99) == pytest.approx(1000.0, rel=0.02)
