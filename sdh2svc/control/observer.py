"""What watches a run from beside it: one interface for its samples, events and frames.

The runner reports to one :class:`RunObserver`: the recorded run, which records and hands on to
one more (the service's telemetry, a campaign's truth probe). An event's serialised form
(``kind``'s value, ``detail`` as a JSON object) is what the store, the WebSocket and the
dashboard read.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any, Protocol

from sdh2svc.bus.tactile import TactileFrame
from sdh2svc.control.sample import Sample


class EventKind(StrEnum):
    """What happened in a run (the ``detail`` each carries in brackets)."""

    START = "start"  # {params}
    PHASE = "phase"  # {phase}
    PARAMS = "params"  # {params}: new parameters took effect
    GRASPED = "grasped"  # {F, wedge_deg}
    REVERSAL = "reversal"  # {reason, stroke, half_strokes}
    FAULT = "fault"  # {fault, message}
    ESTOP = "estop"  # {}
    END = "end"  # {status, message}
    RECOGNITION_FAILED = "recognition_failed"  # {message}: the rolling goes on without it
    # the hand's own, outside a run: the service opening the hand (control.motion)
    OPEN = "open"  # {}
    OPENED = "opened"  # {completed, message?}


@dataclass(frozen=True, slots=True)
class Event:
    """One event of a run, ``t`` seconds after it started, at ``iteration``."""

    t: float
    iteration: int
    kind: EventKind
    detail: dict[str, Any]


class RunObserver(Protocol):
    """Receives everything worth recording of a run, as it happens (never blocking it)."""

    def sample(self, sample: Sample) -> None:
        """Every rolling iteration's record."""

    def event(self, event: Event) -> None:
        """Every event (phase, grasped, reversal, fault, end, …)."""

    def frame(self, t: float, iteration: int, frame: TactileFrame) -> None:
        """The tactile frame of every rolling iteration, ``t`` s after the run started."""


class BaseObserver:
    """Ignores everything: subclass it and override only what you watch."""

    def sample(self, sample: Sample) -> None:
        pass

    def event(self, event: Event) -> None:
        pass

    def frame(self, t: float, iteration: int, frame: TactileFrame) -> None:
        pass
