"""One interface for what watches a run (control.observer)."""

from __future__ import annotations

import json
from typing import Any

from sdh2svc.control.observer import BaseObserver, Event, EventKind, Observers

# what the store, the WebSocket and the dashboard read: the kinds' strings never change
KINDS = ["start", "phase", "params", "grasped", "reversal", "fault", "estop", "end"]
KINDS += ["open", "opened"]  # the hand's own, outside a run


def test_event_kinds_serialise_as_their_strings() -> None:
    assert [k.value for k in EventKind] == KINDS
    e = Event(1.5, 3, EventKind.PHASE, {"phase": "rolling"})
    wire = {"t": e.t, "iteration": e.iteration, "kind": e.kind, "detail": e.detail}
    assert json.dumps(wire) == (
        '{"t": 1.5, "iteration": 3, "kind": "phase", "detail": {"phase": "rolling"}}'
    )
    assert e.kind == "phase" and str(e.kind) == "phase"


class Log(BaseObserver):
    def __init__(self, name: str, log: list[Any]) -> None:
        self.name, self.log = name, log

    def event(self, event: Event) -> None:
        self.log.append((self.name, event.kind))

    def frame(self, t: float, frame: Any) -> None:
        self.log.append((self.name, t))


def test_observers_tell_each_in_order() -> None:
    log: list[Any] = []
    both = Observers(Log("a", log), Log("b", log))
    both.event(Event(0.0, 0, EventKind.START, {}))
    both.frame(0.5, None)
    both.sample(None)  # type: ignore[arg-type]  # BaseObserver ignores it
    assert log == [("a", "start"), ("b", "start"), ("a", 0.5), ("b", 0.5)]
