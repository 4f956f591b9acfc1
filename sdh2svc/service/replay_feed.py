"""The 3-D view following the dashboard's replay: a recorded iteration as the telemetry messages a
live one makes (:mod:`sdh2svc.service.telemetry`'s own types), and what keeps the live ones back
while it is shown.

A view (:class:`~sdh2svc.service.viewer.Viewer` or its process) takes every hub message through
:meth:`ReplayFeed.live`. While a recorded iteration is shown (:meth:`ReplayFeed.show`, from
``PUT /api/viewer/replay``) the live messages of the kinds a replay replaces wait, the latest of
each, and the status goes on with a ``replay`` entry saying what is shown; :meth:`ReplayFeed.end`
(``DELETE /api/viewer/replay``, or :data:`REPLAY_TTL_S` without a new iteration: a closed
dashboard) puts the latest live ones back.
"""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from sdh2svc.config import Settings
from sdh2svc.control.sample import Sample
from sdh2svc.model.hand import AxisMap, matrix_shapes
from sdh2svc.service.store import RunStore, recorded_settings
from sdh2svc.service.telemetry import (
    AnyMessage,
    Message,
    Pose,
    SampleMsg,
    Sim,
    Status,
    Tactile,
    frame_matrices,
    kind_of,
    recorded_truth,
    to_json,
)

REPLAY_KINDS = frozenset({"sample", "tactile", "pose", "sim"})  # what a replay replaces
REPLAY_TTL_S = 60.0  # no new iteration for this long: the dashboard is gone, the view goes live


@dataclass(frozen=True, slots=True)
class Recorded:
    """One recorded iteration as the view gets it."""

    run_id: int
    iteration: int
    t: float  # s since the run started
    messages: tuple[Message, ...]

    def where(self) -> dict[str, Any]:
        return {"run_id": self.run_id, "iteration": self.iteration, "t": self.t}


def recorded_iteration(store: RunStore, cfg: Settings, run_id: int, it: int) -> Recorded | None:
    """Iteration ``it`` of run ``run_id`` as its pose, a sample (with what the view draws of it),
    its tactile frame and, when recorded (simulation), the object's truth as a ``sim`` message; a
    run without it gets an empty ``sim``, which hides the live object's outline. None when the run
    has no sample of that iteration.

    The pose: a sample carries φ2…φ5 only; φ1 and the thumb are the run's pre-shape (a run holds
    them there, as the MCAP export draws them), not the live hand's, which may be anywhere (at
    rest, φ1 = 0: the fingers would close across the plane the contacts are drawn in)."""
    row = store.sample_at(run_id, it)
    if row is None:
        return None
    view_axes = cfg.axes  # the view reads a pose's angles in its own wiring's order
    cfg = recorded_settings(store.run(run_id) or {}, cfg)  # its pads' shapes, its hand
    sample = Sample(**row)
    msgs: list[Message] = [
        Pose(_held_pose(sample, cfg, view_axes)),
        SampleMsg(run_id, sample).with_view(cfg.hand, live=False),
    ]
    texels = store.frame_at(run_id, it, sample.t)
    if texels is not None:
        shapes = matrix_shapes(cfg.tactile, cfg.axes)
        mats = frame_matrices(np.frombuffer(texels, "<u2"), shapes)
        msgs.append(Tactile(it, sample.t, mats))
    truth, outline = store.truth_at(run_id, it), store.outline(run_id)
    msgs.append(Sim(recorded_truth(outline, truth) if truth and outline else {}))
    return Recorded(run_id, it, sample.t, tuple(msgs))


def _held_pose(sample: Sample, cfg: Settings, view_axes: AxisMap) -> tuple[float, ...]:
    """The hand's angles at ``sample`` (one per wire axis of ``view_axes``): φ2…φ5 the sample's,
    φ1 and the thumb the pre-shape of ``cfg``, the configuration the run was recorded with."""
    pre, ax = cfg.run.preshape_deg, cfg.axes
    angles = [0.0] * len(pre)
    for name in ("phi1", "thumb_proximal", "thumb_distal"):
        angles[getattr(view_axes, name)] = float(pre[getattr(ax, name)])
    for name in ("phi2", "phi3", "phi4", "phi5"):
        v = getattr(sample, name)
        angles[getattr(view_axes, name)] = float(v if v is not None else pre[getattr(ax, name)])
    return tuple(angles)


class ReplayFeed:
    """Between the hub and a view's store of latest messages (``put``); see the module doc.

    :meth:`live` runs for every hub message: a dictionary store at most."""

    def __init__(self, put: Callable[[AnyMessage], None], ttl_s: float = REPLAY_TTL_S) -> None:
        self._put = put
        self.ttl_s = ttl_s
        self.showing: Recorded | None = None
        self._live: dict[str, AnyMessage] = {}  # kind → the latest live message of REPLAY_KINDS
        self._status: AnyMessage | None = None
        self._timer: asyncio.TimerHandle | None = None

    def live(self, msg: AnyMessage) -> None:
        kind = kind_of(msg)
        if kind in REPLAY_KINDS:
            self._live[kind] = msg
            if self.showing is not None:
                return
        elif kind in ("status", "hello"):
            self._status = msg
            if self.showing is not None:
                msg = self._tagged(msg)
        self._put(msg)

    def show(self, rec: Recorded) -> None:
        """Show ``rec`` instead of the live state, until :meth:`end` or ``ttl_s`` without a
        newer one (call on the event loop)."""
        self.showing = rec
        for m in rec.messages:
            self._put(m)
        if self._status is not None:
            self._put(self._tagged(self._status))
        if self._timer is not None:
            self._timer.cancel()
        self._timer = asyncio.get_running_loop().call_later(self.ttl_s, self.end)

    def end(self) -> None:
        """Live again: the latest live messages, as if they had just come."""
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None
        if self.showing is None:
            return
        self.showing = None
        for m in self._live.values():
            self._put(m)
        if self._status is not None:
            self._put(self._status)

    def _tagged(self, msg: AnyMessage) -> Status:
        status = dict(to_json(msg).get("status") or {})
        status["replay"] = self.showing.where() if self.showing is not None else None
        return Status(status)
