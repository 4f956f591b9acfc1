"""The live telemetry in Foxglove: the recording's channels (foxglove_mcap.py) served over the
Foxglove WebSocket protocol by ``foxglove-sdk``, fed from the telemetry hub.

* ``/samples`` (JSON, the schema from Sample) — every iteration;
* ``/tf`` — the links at each forwarded sample's φ2…φ5, and between runs at the hand's actual
  angles (the ``pose`` messages);
* ``/scene`` — the links and the pads (with each sample, and between runs with the ``pose``
  messages), and A, B, AB and the friction cones (α of the run in force) of each forwarded
  sample; in simulation the object's true outline (the ``sim`` messages); the contacts are
  deleted when a run ends;
* ``/tactile/<finger>_<proximal|distal>`` — each forwarded tactile frame's pads as Grids;
* ``/events`` — every event, as Log lines.

The messages are built by the same functions as the file's. The hub calls :meth:`FoxgloveLive.
handle` on the event loop, so its cost is the control loop's: nothing is built for a channel no
client subscribes to, and the 3-D channels (``/tf``, ``/scene``, ``/tactile/*``) are forwarded
at most ``max_hz`` times a second, like the viser view (``service.viewer_max_hz``). Encoding and
sending are the SDK's (its own threads). Log times: the wall clock at delivery (a live view has
no other common clock).

The server is read-only (no client publishing, parameters or services); it serves one asset,
the URDF at :data:`URDF_URI`, for Foxglove's URDF layer.
"""

from __future__ import annotations

import json
import logging
import math
import time
from typing import Any

import foxglove
from foxglove import channels as fc

from sdh2svc.config import Settings
from sdh2svc.control.observer import EventKind
from sdh2svc.model.urdf import to_xml
from sdh2svc.service.foxglove_mcap import (
    EVENTS,
    PAD_NAMES,
    SAMPLE_SCHEMA,
    SAMPLES,
    SCENE,
    TF,
    HandFrames,
    clear_contacts,
    log_message,
    pad_topic,
    sample_json,
    sample_schema,
)
from sdh2svc.service.pacing import Throttle
from sdh2svc.service.telemetry import (
    AnyMessage,
    Event,
    Pose,
    SampleMsg,
    Sim,
    Tactile,
    live_outline,
)

__all__ = ["URDF_URI", "FoxgloveLive", "FoxgloveStartError"]

log = logging.getLogger(__name__)

URDF_URI = "package://sdh2svc/sdh2.urdf"  # what the URDF layer asks the server for


class FoxgloveStartError(RuntimeError):
    """The live view cannot listen (the message names the port and what to do)."""


class FoxgloveLive:
    """A Foxglove WebSocket server on ``host:port``, a hub listener (:meth:`handle`)."""

    def __init__(self, cfg: Settings, *, host: str, port: int, max_hz: float) -> None:
        self.host, self.port = host, port
        self._hand = HandFrames.of(cfg, live_outline)  # the live views' one outline
        self._alpha = math.radians(cfg.rolling.alpha_deg)
        self._pace_3d = Throttle(1.0 / max_hz)  # /tf and /scene
        self._pace_pads = Throttle(1.0 / max_hz)
        self._urdf = to_xml(self._hand.desc).encode()
        ctx = foxglove.Context()  # this service's channels only (tests run several)
        schema = foxglove.Schema(
            name=SAMPLE_SCHEMA, encoding="jsonschema", data=json.dumps(sample_schema()).encode()
        )
        self._samples = foxglove.Channel(
            SAMPLES, schema=schema, message_encoding="json", context=ctx
        )
        self._tf = fc.FrameTransformsChannel(TF, context=ctx)
        self._scene = fc.SceneUpdateChannel(SCENE, context=ctx)
        self._events = fc.LogChannel(EVENTS, context=ctx)
        self._pads = {pad: fc.GridChannel(pad_topic(pad), context=ctx) for pad in PAD_NAMES}
        self._ctx = ctx
        self._server: Any = None  # a foxglove.WebSocketServer while serving

    def start(self) -> None:
        """Listen (:class:`FoxgloveStartError` when it cannot, e.g. the port is taken)."""
        # The SDK logs through Python's logging from its own threads, a line per bad message a
        # client sends: a client sending junk fast took the interpreter from the control loop
        # (runs faulted) and filled the log. Off (FOXGLOVE_LOG_LEVEL still overrides it); a
        # client's errors are answered to the client.
        foxglove.set_log_level(logging.CRITICAL)
        try:
            self._server = foxglove.start_server(
                name="sdh2svc", host=self.host, port=self.port, capabilities=[],
                asset_handler=self._asset, context=self._ctx,
            )  # fmt: skip
        except RuntimeError as e:  # the SDK's FoxgloveError, e.g. "Address already in use"
            raise FoxgloveStartError(
                f"cannot serve the live Foxglove view on {self.host}:{self.port}: {e}; set "
                "service.foxglove_port to a free port, or 0 (off)"
            ) from e
        self.port = self._server.port

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def stop(self) -> None:
        if self._server is not None:
            self._server.stop()
            self._server = None

    def _asset(self, uri: str) -> bytes | None:
        return self._urdf if uri == URDF_URI else None

    def handle(self, msg: AnyMessage) -> None:
        """A hub message → its channels (see the module's doc); must return quickly."""
        if self._server is None or isinstance(msg, dict):
            return
        if isinstance(msg, SampleMsg):
            self._sample(msg)
        elif isinstance(msg, Tactile):
            self._tactile(msg)
        elif isinstance(msg, Event):
            self._event(msg)
        elif isinstance(msg, Sim):
            if self._scene.has_sinks():  # at the service's pose_hz: not rate-limited here
                ns = time.time_ns()
                self._scene.log(self._hand.scene(None, ns, self._alpha, msg.truth), log_time=ns)
        elif isinstance(msg, Pose):
            self._pose(msg)

    def _pose(self, msg: Pose) -> None:
        """The hand at its actual angles, between runs too: the links and pads on /scene with
        them (a real hand has no ``sim`` messages to draw them)."""
        tf, scene = self._tf.has_sinks(), self._scene.has_sinks()
        if (tf or scene) and self._due_3d():
            ns = time.time_ns()
            if tf:
                self._tf.log(self._hand.pose_transforms(msg.angles_deg, ns), log_time=ns)
            if scene:
                self._scene.log(self._hand.scene(None, ns, self._alpha), log_time=ns)

    def _sample(self, msg: SampleMsg) -> None:
        s = msg.sample
        row = dict(zip(s.columns(), s.row(), strict=True))
        ns = time.time_ns()
        if self._samples.has_sinks():
            self._samples.log(sample_json(row), log_time=ns)
        tf, scene = self._tf.has_sinks(), self._scene.has_sinks()
        if (tf or scene) and self._due_3d():
            if tf:
                self._tf.log(self._hand.transforms(row, ns), log_time=ns)
            if scene:
                self._scene.log(self._hand.scene(row, ns, self._alpha), log_time=ns)

    def _event(self, msg: Event) -> None:
        if msg.kind in (EventKind.START, EventKind.PARAMS):  # the cones' α is the run's
            alpha = msg.detail.get("params", {}).get("alpha_deg")
            if isinstance(alpha, int | float):
                self._alpha = math.radians(alpha)
        if msg.kind is EventKind.END and self._scene.has_sinks():  # no contacts between runs
            ns = time.time_ns()
            self._scene.log(clear_contacts(ns), log_time=ns)
        if self._events.has_sinks():
            ns = time.time_ns()
            self._events.log(log_message(msg.json(), ns), log_time=ns)

    def _tactile(self, msg: Tactile) -> None:
        if not any(ch.has_sinks() for ch in self._pads.values()):
            return
        if not self._pace_pads.due(time.monotonic()):
            return
        ns = time.time_ns()
        for pad, grid in self._hand.pad_grids(msg.matrices, ns).items():
            if self._pads[pad].has_sinks():
                self._pads[pad].log(grid, log_time=ns)

    def _due_3d(self) -> bool:
        return self._pace_3d.due(time.monotonic())
