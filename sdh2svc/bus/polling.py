"""When to read the joint angles between a control loop's commands (sans-I/O).

The joint line carries one exchange at a time. A ``pos`` poll on the line when the control loop
wants to command would hold the command back by a whole reply (≈ 5 ms at 115200 baud), and a poll
right after the command leaves the angles a whole period old when the next iteration takes them.
A control loop takes the angles in a rhythm (once per tactile frame, :meth:`PollPlan.beat`), so
the poll goes as late as it can: it is to be answered a margin before the next beat is due — the
beats' own jitter (frames grow with contact) a few times over, at least ``guard_s`` — and the
iteration finds angles about that margin old. After a beat the loop's command follows, so no
poll starts before it (for at most ``hold_s``), and the caller plans again at every beat: a poll
timed, before the beat, for a quarter period after it would otherwise go on the line between a
slow command (a binary ``p`` on the real hand: 8–10 ms) and its move. A poll that misses its
slot (its timer fired late on a busy machine) waits for the next one, and the iteration takes
angles a period older; but a rhythm with no slot at all (a slow round trip) and a second beat in
a row without a reading get their poll at once: fresh angles come before a clean line. Without
a rhythm (no loop running, or a beat overdue beyond ``late``) :meth:`PollPlan.start_at` says
None and the caller polls on its own terms (after every command, and every so often).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

_EWMA: Final = 0.2


def _ewma(prev: float | None, x: float) -> float:
    return x if prev is None else prev + _EWMA * (x - prev)


@dataclass(slots=True)
class PollPlan:
    """The control loop's rhythm and the polls' round trip, as measured (seconds)."""

    guard_s: float = 0.002  # a poll is answered at least this long before the next beat is due
    jitter_factor: float = 3.0  # …and this many mean deviations of the beat from its period
    hold_s: float = 0.02  # after a beat: no poll for this long unless the command comes first
    max_period_s: float = 0.5  # beats further apart than this are no rhythm
    late: float = 0.25  # a beat overdue by this fraction of the period ends the rhythm
    period_s: float | None = None  # EWMA of the intervals between beats
    jitter_s: float = 0.0  # EWMA of |interval - period|
    rtt_s: float | None = None  # EWMA of the polls' round trips
    last_beat: float | None = None
    last_answer: float = -math.inf  # when the last poll was answered
    held_until: float | None = None  # a command is on its way: no poll before it

    def beat(self, now: float) -> None:
        """A control loop took the angles at ``now``; its command follows."""
        if self.last_beat is not None:
            gap = now - self.last_beat
            if 0.0 < gap <= self.max_period_s:
                if self.period_s is not None:
                    self.jitter_s = _ewma(self.jitter_s, abs(gap - self.period_s))
                self.period_s = _ewma(self.period_s, gap)
            elif gap > self.max_period_s:
                self.period_s, self.jitter_s = None, 0.0  # a new rhythm starts from scratch
        self.last_beat = now
        self.held_until = now + self.hold_s

    def command(self) -> None:
        """The loop's command went on the line: polls may go again."""
        self.held_until = None

    def polled(self, started: float, answered: float) -> None:
        """A poll went out at ``started`` and was answered at ``answered``."""
        self.rtt_s = _ewma(self.rtt_s, answered - started)
        self.last_answer = answered

    @property
    def margin_s(self) -> float:
        """How long before the next beat is due a poll is to be answered."""
        return self.guard_s + self.jitter_factor * self.jitter_s

    def start_at(self, now: float) -> float | None:
        """When the next poll should start: ``now`` or later; None when there is no rhythm."""
        if self.held_until is not None and now < self.held_until:
            return self.held_until
        if self.period_s is None or self.rtt_s is None or self.last_beat is None:
            return None
        due = self.last_beat + self.period_s
        if now > due + self.late * self.period_s:
            return None  # the loop stopped (or skipped a beat): no rhythm to keep
        latest = due - self.margin_s - self.rtt_s  # the last start answered in time
        if now <= latest:
            return latest  # read as late as possible
        if self.last_answer < self.last_beat and (
            latest <= self.last_beat  # no slot at all
            or self.last_answer < self.last_beat - self.period_s  # the last beat went without
            or now + self.rtt_s <= due - self.guard_s  # still in time, if only just
        ):
            return now
        return due + self.late * self.period_s  # the next poll after the beat
