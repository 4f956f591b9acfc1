"""Which frames the DSACON32m is asked for, when and why: the tactile line's policy (sans-I/O).

Six tactile pads share one 115200-baud line (11 520 bytes/s). Every frame carries all six
matrices (the protocol has no per-matrix request), so the line has to carry the highest rate any
subscriber asked for. :mod:`sdh2svc.bus.tactile` does the I/O; everything it decides is here, as
numbers in and numbers out.

``R`` = the highest ``rate_hz`` of the open subscriptions. Measured, then refined continuously
(:class:`LineEstimates`):

* ``S``: wire size of a frame (EWMA over received frames; RLE makes it grow with contact, from
  79 bytes for an empty hand to 985 for a busy one, §1.10; initial guess 175 bytes);
* ``P`` = min(controller cap 30 fps, baud/10/S, 1.05 × the rate last measured over a whole
  2 s window in push mode): what push mode can deliver;
* ``Q`` = 1 / (EWMA of the pull cycle, request written → frame parsed): what pull can deliver
  (initial guess from S, the 10-byte ACK and 5 ms of turnaround).

Modes (:func:`choose_mode`):

* **idle** when nobody subscribes: acquisition off, the line is silent.
* **push** (one "rate > 0, acq on"; the controller streams) when ``R ≥ 0.9·P`` — the subscriber
  needs about every frame the controller or the line can produce, and pull's per-frame round trip
  would only lose rate — or when ``R > 0.8·Q``, i.e. pull cannot keep up with a 20 % margin
  (large frames under heavy contact). Once in push it stays while ``R ≥ 0.75·P``: frame sizes
  change with contact and would otherwise make the mode flap. The framerate field is ceil(R)
  (:func:`push_framerate`; documented firmware streams at its maximum for any value > 0; firmware
  that honours the value then streams at R).
* **pull** otherwise: "rate 0, acq on" re-sent every 1/R s on an anchored schedule
  (:func:`next_pull`: a late cycle starts at once instead of shifting every later one, so the mean
  rate stays R). It costs the line R·(S + 10) bytes/s instead of P·S, keeps it quiet for
  configuration commands, and every frame is sampled on request, so it is at most one ACK + one
  frame time old on arrival.

Examples (rolling): distal pads at 30 Hz and the other pads at 2 Hz → R = 30 ≥ 0.9·30 → push,
about 30 fps: ~25 % line utilisation with the emulator's two sliding blobs (~95-byte frames),
45-50 % at ~175-byte frames. Only the 2 Hz watch → pull at 2 Hz, about 2 %. Under heavy
contact (S ≈ 985 bytes) push gives at most P ≈ 11.7 fps and a 10 Hz request goes to push too
(pull would manage only ≈ 10.9 Hz).

The choice is re-evaluated whenever a subscription opens or closes and every
:data:`REPLAN_S`. The line is given up for a new connection (:func:`line_verdict`) after a run of
errors with no good packet for a while, or when nothing good arrives well beyond the expected
frame gap (SDHLibrary's updater, §1.7).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass
from enum import StrEnum
from typing import Final

from sdh2svc.protocol.line import BITS_PER_BYTE

__all__ = [
    "ACK_BYTES",
    "PUSH_CAP_FPS",
    "RATE_WINDOW_S",
    "REPLAN_S",
    "LineEstimates",
    "Mode",
    "RateMeter",
    "choose_mode",
    "line_verdict",
    "next_pull",
    "push_framerate",
]

PUSH_CAP_FPS: Final = 30.0  # "highest possible rate (for now: 30 FPS)", §1.6
ACK_BYTES: Final = 10  # 0x03 ACK packet: 8 framing bytes + error u16
RATE_WINDOW_S: Final = 2.0  # rates are measured over this window
REPLAN_S: Final = 0.5  # the mode is chosen again at least this often
_INITIAL_FRAME_BYTES: Final = 175.0  # RLE restarted per row, §1.10: a middle-of-the-road guess
_TURNAROUND_S: Final = 0.005  # host + controller reaction time assumed before the first pull
_EWMA: Final = 0.2
_ENTER_PUSH: Final = 0.9
_STAY_PUSH: Final = 0.75
_PULL_MARGIN: Final = 0.8
_PUSH_HEADROOM: Final = 1.05  # push may deliver a little more than last measured


class Mode(StrEnum):
    IDLE = "idle"
    PULL = "pull"
    PUSH = "push"


def choose_mode(required_hz: float, *, push_fps: float, pull_max_hz: float, current: Mode) -> Mode:
    """The acquisition mode for ``required_hz`` (the policy in the module docstring)."""
    if required_hz <= 0.0:
        return Mode.IDLE
    if required_hz > _PULL_MARGIN * pull_max_hz:
        return Mode.PUSH
    threshold = _STAY_PUSH if current is Mode.PUSH else _ENTER_PUSH
    return Mode.PUSH if required_hz >= threshold * push_fps else Mode.PULL


def push_framerate(required_hz: float) -> int:
    """The framerate field of the push request: ceil(R) within the field's u16."""
    return max(1, min(0xFFFF, math.ceil(required_hz)))


def next_pull(due: float, period_s: float, now: float) -> float:
    """When the pull cycle after one due at ``due`` is due: anchored, or at once if late."""
    return max(due + period_s, now)


def line_verdict(
    *,
    error_streak: int,
    max_error_streak: int,
    quiet_s: float,
    min_dead_s: float,
    stall_s: float,
    expected_gap_s: float | None,
) -> str | None:
    """Why the line should be given up, or None. ``quiet_s``: time without a good packet;
    ``expected_gap_s``: the frame gap expected now (None when idle: silence is normal)."""
    if error_streak > max_error_streak and quiet_s >= min_dead_s:
        return f"{error_streak} errors in a row"
    if expected_gap_s is not None and quiet_s >= stall_s + expected_gap_s:
        return f"no good packet for {quiet_s:.2f} s"
    return None


@dataclass(slots=True)
class LineEstimates:
    """What the line can deliver, refined from every frame and pull cycle (``S``, ``P``, ``Q``)."""

    baud: int
    push_cap_fps: float = PUSH_CAP_FPS
    frame_bytes: float = _INITIAL_FRAME_BYTES  # S, EWMA of a frame's wire size
    pull_cycle_s: float | None = None  # EWMA of a clean pull cycle
    push_achieved: float | None = None  # frames/s measured over a whole window in push

    def frame(self, wire_bytes: int) -> None:
        self.frame_bytes += _EWMA * (wire_bytes - self.frame_bytes)

    def pull_cycle(self, seconds: float) -> None:
        prev = self.pull_cycle_s
        self.pull_cycle_s = seconds if prev is None else prev + _EWMA * (seconds - prev)

    def push_fps(self) -> float:
        """``P``: what push mode can deliver."""
        line_fps = self.baud / BITS_PER_BYTE / self.frame_bytes
        achieved = math.inf if self.push_achieved is None else _PUSH_HEADROOM * self.push_achieved
        return min(self.push_cap_fps, line_fps, achieved)

    def pull_max_hz(self) -> float:
        """``Q``: what pull mode can deliver."""
        if self.pull_cycle_s is None:
            byte_s = BITS_PER_BYTE / self.baud
            return 1.0 / ((self.frame_bytes + ACK_BYTES) * byte_s + _TURNAROUND_S)
        return 1.0 / self.pull_cycle_s

    def line_utilisation_pct(self, bytes_per_s: float) -> float:
        return 100.0 * bytes_per_s * BITS_PER_BYTE / self.baud


class RateMeter:
    """Sum of amounts over the last ``window`` seconds (or since ``start``), as a rate."""

    def __init__(self, start: float, window: float = RATE_WINDOW_S) -> None:
        self.window = window
        self._start = start
        self._items: deque[tuple[float, int]] = deque()
        self._sum = 0

    def add(self, t: float, amount: int) -> None:
        self._items.append((t, amount))
        self._sum += amount
        self._prune(t)  # (read only at a run's end, it held every read of the run)

    def _prune(self, now: float) -> None:
        while self._items and self._items[0][0] < now - self.window:
            self._sum -= self._items.popleft()[1]

    def rate(self, now: float) -> float:
        self._prune(now)
        span = min(self.window, now - self._start)
        return self._sum / span if span > 0.0 else 0.0
