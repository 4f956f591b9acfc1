"""The live Foxglove view's listener in process: what it builds, when, and for whom. (A client of
the Foxglove WebSocket protocol receiving every channel during a run of a live service:
test_client.py, which shares that service.)"""

from __future__ import annotations

import json
import logging
import math
import socket
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from foxglove import messages as fm
from foxglove_ws import SUBPROTOCOLS
from mcap_check import _proto_class
from websockets.sync.client import connect

from sdh2svc.config import load_config
from sdh2svc.control.observer import EventKind
from sdh2svc.service import foxglove_live
from sdh2svc.service.foxglove_live import FoxgloveLive, FoxgloveStartError
from sdh2svc.service.foxglove_mcap import PAD_NAMES
from sdh2svc.service.telemetry import Event, Pose, SampleMsg, Sim, Tactile
from tests.service.test_telemetry import a_sample


def test_off_by_default() -> None:
    assert load_config(use_env=False).service.foxglove_port == 0


# --- the listener's policy, in process (no client: the channels and the builders are fakes) ---


class FakeChannel:
    def __init__(self, subscribed: bool = True) -> None:
        self.subscribed = subscribed
        self.logged: list[tuple[Any, int | None]] = []

    def has_sinks(self) -> bool:
        return self.subscribed

    def log(self, msg: Any, *, log_time: int | None = None) -> None:
        self.logged.append((msg, log_time))


class FakeHand:
    """Counts what is built (the builders themselves: test_foxglove_mcap.py)."""

    def __init__(self) -> None:
        self.built: list[str] = []

    def transforms(self, s: Any, ns: int) -> str:
        self.built.append("tf")
        return "tf"

    def pose_transforms(self, angles: Any, ns: int) -> str:
        self.built.append("pose")
        return "pose"

    def scene(self, s: Any, ns: int, alpha: float, truth: Any = None) -> tuple[str, float]:
        self.built.append("scene" if truth is None else "object")
        return ("scene", alpha)

    def pad_grids(self, mats: Any, ns: int) -> dict[str, str]:
        self.built.append("grids")
        return {p: p for p in PAD_NAMES}


class Clock:
    now = 100.0

    def monotonic(self) -> float:
        return self.now

    def time_ns(self) -> int:
        return round(self.now * 1e9)


@pytest.fixture
def live(monkeypatch: pytest.MonkeyPatch) -> Iterator[tuple[FoxgloveLive, FakeHand, Clock]]:
    clock = Clock()
    monkeypatch.setattr(foxglove_live, "time", clock)
    fox = FoxgloveLive(load_config(use_env=False), host="127.0.0.1", port=0, max_hz=10.0)
    fox.start()
    assert fox.port > 0 and fox.url == f"ws://127.0.0.1:{fox.port}"
    hand = FakeHand()
    fox._hand = hand  # type: ignore[assignment]
    try:
        yield fox, hand, clock
    finally:
        fox.stop()


def _chans(fox: FoxgloveLive, subscribed: bool) -> dict[str, FakeChannel]:
    ch = {n: FakeChannel(subscribed) for n in ("_samples", "_tf", "_scene", "_events")}
    for name, c in ch.items():
        setattr(fox, name, c)
    fox._pads = {p: FakeChannel(subscribed) for p in PAD_NAMES}  # type: ignore[misc]
    return ch


def _tactile(seq: int) -> Tactile:
    return Tactile(seq, 0.0, tuple(np.zeros((2, 3), np.uint16) for _ in PAD_NAMES))


def test_nothing_is_built_for_a_channel_nobody_reads(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    fox, hand, _ = live
    ch = _chans(fox, subscribed=False)
    fox.handle(SampleMsg(1, a_sample()))
    fox.handle(_tactile(1))
    fox.handle(Pose((0.0,) * 7))
    fox.handle(Event(1, 0.0, 0, EventKind.PHASE, {"phase": "grasping"}))
    assert hand.built == [] and not any(c.logged for c in ch.values())


def test_3d_channels_at_most_max_hz_samples_and_events_all(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    fox, hand, clock = live
    ch = _chans(fox, subscribed=True)
    for i in range(5):  # 5 samples and frames within 0.1 s (max_hz = 10): the 3-D ones once
        clock.now += 0.02
        fox.handle(SampleMsg(1, a_sample(iteration=i + 1)))
        fox.handle(_tactile(i))
    assert [json.loads(m)["iteration"] for m, _ in ch["_samples"].logged] == [1, 2, 3, 4, 5]
    assert hand.built == ["tf", "scene", "grids"]
    assert all(len(c.logged) == 1 for c in fox._pads.values())  # type: ignore[attr-defined]
    clock.now += 0.1  # a period later: the next sample and frame are drawn
    fox.handle(SampleMsg(1, a_sample(iteration=6)))
    fox.handle(_tactile(6))
    assert hand.built == ["tf", "scene", "grids", "tf", "scene", "grids"]
    # log times: the clock at delivery
    assert ch["_samples"].logged[-1][1] == clock.time_ns()


def test_between_runs_the_pose_draws_the_hand_on_tf_and_scene(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    """A real hand sends no ``sim`` messages: between runs its links and pads reach /scene
    with the pose, at the 3-D channels' rate; each only for a channel someone reads."""
    fox, hand, clock = live
    ch = _chans(fox, subscribed=True)
    for _ in range(3):  # within one period (max_hz = 10): drawn once
        clock.now += 0.02
        fox.handle(Pose((0.0,) * 7))
    assert hand.built == ["pose", "scene"]
    assert len(ch["_tf"].logged) == len(ch["_scene"].logged) == 1
    ch["_tf"].subscribed = False
    clock.now += 0.1
    fox.handle(Pose((0.0,) * 7))
    assert hand.built == ["pose", "scene", "scene"]


def test_deliveries_at_max_hz_with_jitter_are_all_forwarded(
    live: tuple[FoxgloveLive, FakeHand, Clock],
) -> None:
    """Frames at the 3-D channels' own rate, some a little early: none dropped (every other
    one was, whose follower then went out a period late: 19 Hz of 30)."""
    fox, hand, clock = live
    _chans(fox, subscribed=True)
    for i in range(20):
        clock.now += 0.1 + (0.006 if i % 2 else -0.006)  # max_hz = 10
        fox.handle(SampleMsg(1, a_sample(iteration=i + 1)))
        fox.handle(_tactile(i))
    assert hand.built.count("tf") == hand.built.count("grids") == 20


def test_a_client_sending_junk_is_not_logged(caplog: pytest.LogCaptureFixture) -> None:
    """The SDK would log a line per bad message from its own threads: a client flooding junk
    took the interpreter from the control loop (runs faulted) and filled the log."""
    fox = FoxgloveLive(load_config(use_env=False), host="127.0.0.1", port=0, max_hz=10.0)
    fox.start()
    try:
        with caplog.at_level(logging.DEBUG), \
                connect(fox.url, subprotocols=SUBPROTOCOLS) as ws:  # type: ignore[arg-type]  # fmt: skip
            for _ in range(50):
                ws.send("{x")
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 999}]}))
            while "Unknown channel" not in str(ws.recv(timeout=10)):
                pass  # the client is told (a status message per bad message)
    finally:
        fox.stop()
    assert [r for r in caplog.records if r.name.startswith("foxglove")] == []


def test_the_cones_take_the_runs_alpha(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    fox, _, _ = live
    ch = _chans(fox, subscribed=True)
    fox.handle(Event(1, 0.0, 0, EventKind.START, {"params": {"alpha_deg": 30.0}}))
    fox.handle(SampleMsg(1, a_sample()))
    assert ch["_scene"].logged[-1][0] == ("scene", pytest.approx(math.radians(30.0)))
    assert [type(m) for m, _ in ch["_events"].logged] == [fm.Log]


def test_the_object_and_the_contacts_end(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    """The truth's object at each ``sim`` message; a run's end deletes its contacts."""
    fox, hand, _ = live
    ch = _chans(fox, subscribed=True)
    fox.handle(Sim({"outline": [[0.0, 100.0], [10.0, 110.0]]}))
    fox.handle(Sim({"outline": [[0.0, 100.0], [10.0, 110.0]]}))
    assert hand.built == ["object", "object"]
    fox.handle(Event(1, 9.0, 300, EventKind.END, {"status": "completed", "message": ""}))
    update = _proto_class("foxglove.SceneUpdate", fm.SceneUpdate.get_schema().data)
    (deletion,) = update.FromString(ch["_scene"].logged[-1][0].encode()).deletions
    assert deletion.id == "contacts" and deletion.type == 0  # MATCHING_ID, not ALL


def test_stopped_it_ignores_messages(live: tuple[FoxgloveLive, FakeHand, Clock]) -> None:
    fox, hand, _ = live
    _chans(fox, subscribed=True)
    fox.stop()
    fox.handle(SampleMsg(1, a_sample()))
    assert hand.built == []


def test_a_taken_port_is_a_start_error() -> None:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        fox = FoxgloveLive(load_config(use_env=False), host="127.0.0.1",
                           port=s.getsockname()[1], max_hz=10.0)  # fmt: skip
        with pytest.raises(FoxgloveStartError, match=r"in use.*service\.foxglove_port"):
            fox.start()
