"""One interface for what watches a run (control.observer)."""

from __future__ import annotations

import json

from sdh2svc.control.observer import Event, EventKind

# what the store, the WebSocket and the dashboard read: the kinds' strings never change
KINDS = ["start", "phase", "params", "grasped", "reversal", "fault", "estop", "end"]
KINDS += ["recognition_failed"]
KINDS += ["open", "opened"]  # the hand's own, outside a run


def test_event_kinds_serialise_as_their_strings() -> None:
    assert [k.value for k in EventKind] == KINDS
    e = Event(1.5, 3, EventKind.PHASE, {"phase": "rolling"})
    wire = {"t": e.t, "iteration": e.iteration, "kind": e.kind, "detail": e.detail}
    assert json.dumps(wire) == (
        '{"t": 1.5, "iteration": 3, "kind": "phase", "detail": {"phase": "rolling"}}'
    )
    assert e.kind == "phase" and str(e.kind) == "phase"
