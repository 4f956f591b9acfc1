"""The telemetry messages (sdh2svc.service.telemetry): their JSON is docs/api.md's, byte for byte;
what the 3-D view draws of a sample is made once; a frame stays an array on its way to the view."""

from __future__ import annotations

import json
import math
import pickle
from typing import Any

import numpy as np
import pytest

from sdh2svc.config import Settings
from sdh2svc.control.sample import Sample
from sdh2svc.model.geometry import pad_point_from_L
from sdh2svc.model.kinematics import Finger, pad_point
from sdh2svc.service.hub import Client, TelemetryHub
from sdh2svc.service.telemetry import (
    AnyMessage,
    Dropped,
    Event,
    Hello,
    Pose,
    SampleMsg,
    SampleView,
    Sim,
    Status,
    Tactile,
    contact_normal,
    encode,
    sample_view,
)


def a_sample(**over: object) -> Sample:
    values: dict[str, object] = {c: float(i) / 4 for i, c in enumerate(Sample.columns())}
    values.update(iteration=7, direction=1, stroke=2, half_strokes=4, reversal=None)
    values.update(over)
    return Sample(**values)  # type: ignore[arg-type]


def test_each_message_encodes_as_its_documented_dict() -> None:
    """What the dashboard reads: the same text the service sent when it published dicts."""
    s = a_sample(S1=math.nan)
    mats = tuple(np.arange(84, dtype=np.uint16).reshape(14, 6) + k for k in range(6))
    pairs: list[tuple[AnyMessage, dict[str, Any]]] = [
        (Hello({"sim": True}), {"type": "hello", "status": {"sim": True}}),
        (Status({"run": None}), {"type": "status", "status": {"run": None}}),
        (SampleMsg(3, s), {"type": "sample", "run_id": 3,
                           "sample": {**dict(zip(Sample.columns(), s.row(), strict=True)),
                                      "estimate_outline": []}}),
        (Event(3, 1.5, 9, "reversal", {"why": "S1"}), {"type": "event", "run_id": 3, "t": 1.5,
                                                       "iteration": 9, "kind": "reversal",
                                                       "detail": {"why": "S1"}}),
        (Tactile(5, 2.0, mats), {"type": "tactile", "seq": 5, "t": 2.0,
                                 "matrices": [m.tolist() for m in mats]}),
        (Pose((90.0, -20.0)), {"type": "pose", "angles_deg": [90.0, -20.0]}),
        (Sim({"held": True}), {"type": "sim", "truth": {"held": True}}),
        (Dropped(4), {"type": "dropped", "count": 4}),
    ]  # fmt: skip
    for typed, old in pairs:
        assert encode(typed) == encode(old)
    assert json.loads(encode(SampleMsg(3, s)))["sample"]["S1"] is None  # NaN → null


def test_the_hub_takes_typed_messages_and_dicts_alike() -> None:
    hub = TelemetryHub()
    seen: list[object] = []
    hub.add_listener(seen.append)
    c = Client(max_queue=10, decimate=2, tactile=False)
    hub.clients.add(c)
    msgs: list[AnyMessage] = [SampleMsg(1, a_sample()), {"type": "sample", "i": 1},
                              SampleMsg(1, a_sample())]  # fmt: skip
    for m in msgs:
        hub.publish(m)
    hub.publish(Tactile(1, 0.0, (np.zeros((2, 2)),)))
    assert seen[:3] == msgs  # listeners get the values as published
    assert [json.loads(t)["type"] for t in c.queue] == ["sample", "sample"]  # every 2nd sample


def test_the_views_sample_has_the_contacts_and_their_pad_normals(cfg: Settings) -> None:
    p2, p3 = math.radians(-20.0), math.radians(30.0)
    x3, y3 = pad_point_from_L(40.0, cfg.hand.pad)
    A = pad_point(Finger.ONE, p2, p3, x3, y3, cfg.hand)
    s = a_sample(phi2=-20.0, phi3=30.0, phi4=-20.0, phi5=30.0, Ay=A.y, Az=A.z, By=None,
                 omega_A=90.0)  # fmt: skip
    msg = SampleMsg(1, s).with_view(cfg.hand)
    view = msg.view
    assert view is not None and view.phi_deg == (-20.0, 30.0, -20.0, 30.0)
    assert view.A is not None and view.B is None
    assert view.A.normal == contact_normal(Finger.ONE, p2, p3, A, cfg.hand)
    assert view.A.omega_deg == 90.0
    assert msg.with_view(cfg.hand) is msg  # made once
    assert msg.json() == SampleMsg(1, s).json()  # not part of the JSON
    # the JSON form (what tests and old publishers send) gives the same view
    assert sample_view(msg.json()["sample"], cfg.hand) == view


@pytest.mark.parametrize("dtype", [np.uint16, np.float64])
def test_a_frame_reaches_the_views_process_as_arrays(dtype: type) -> None:
    mats = tuple(np.full((13, 6), 7, dtype=dtype) for _ in range(6))  # type: ignore[var-annotated]
    back = pickle.loads(pickle.dumps(Tactile(1, 0.5, mats), protocol=pickle.HIGHEST_PROTOCOL))
    assert all(isinstance(m, np.ndarray) and m.dtype == dtype for m in back.matrices)
    assert all(np.array_equal(a, b) for a, b in zip(back.matrices, mats, strict=True))
    view = SampleView((None, None, None, None), None, None)
    assert pickle.loads(pickle.dumps(view)) == view


def test_the_reconstructed_outline_is_the_recognitions_sent_with_the_sample(
    cfg: Settings, monkeypatch: pytest.MonkeyPatch
) -> None:
    """One outline, made by recognition.outline from the sample's fields: in the JSON form
    (dashboard), in the view (3-D) and from a recorded row (replay) alike."""
    from sdh2svc.control.recognition import ObjectClass
    from sdh2svc.service import telemetry

    calls: list[tuple[Any, ...]] = []

    def square(rec: Any, a: Any, b: Any, n: int = 64) -> np.ndarray:
        calls.append((rec.object_class, rec.size_a, rec.rotation, a, b, n))
        return np.array([[0.0, 0.0], [rec.size_a, 0.0], [rec.size_a, rec.size_a]])

    monkeypatch.setattr(telemetry, "outline", square)
    monkeypatch.setattr(telemetry, "live_outline", telemetry.OutlineEvery(0.1))
    s = a_sample(Ay=1.0, Az=2.0, By=3.0, Bz=4.0, contact1_kind="flat", contact2_kind="edge",
                 object_class="box", class_confidence=0.5, size_a=10.0, size_b=5.0,
                 rotation_est=30.0)  # fmt: skip
    want = [[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]]
    assert SampleMsg(1, s).json()["sample"]["estimate_outline"] == want
    assert calls[-1] == (ObjectClass.BOX, 10.0, 30.0, (1.0, 2.0), (3.0, 4.0), 48)
    view = SampleMsg(1, s).with_view(cfg.hand).view
    assert view is not None and [list(p) for p in view.estimate] == want
    row = dict(zip(Sample.columns(), s.row(), strict=True))  # a recorded row, the JSON form
    assert telemetry.estimate_outline(row).tolist() == want
    # no class, no contact, or an outline that fails: nothing drawn, nothing raised
    assert SampleMsg(1, a_sample(object_class=None)).json()["sample"]["estimate_outline"] == []
    assert telemetry.estimate_outline({**row, "By": None}).shape == (0, 2)
    monkeypatch.setattr(telemetry, "outline", lambda *a: 1 / 0)
    assert telemetry.estimate_outline(s).shape == (0, 2)


def test_the_live_views_share_an_outline_made_at_most_every_period(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The outline costs milliseconds: the hub's JSON, the 3-D view and Foxglove take one of the
    same sample, and a later sample's only once ESTIMATE_PERIOD_S of the run has passed."""
    from sdh2svc.service import telemetry

    monkeypatch.setattr(telemetry, "outline", lambda rec, a, b, n: np.array([a, b, (0.0, 0.0)]))
    every = telemetry.OutlineEvery(0.1)
    est = {"Ay": 1.0, "Az": 2.0, "By": 3.0, "Bz": 4.0, "object_class": "box", "size_a": 10.0,
           "size_b": 5.0, "rotation_est": 3.0}  # fmt: skip
    samples = [a_sample(t=0.02 * i, **{**est, "Ay": 1.0 + i}) for i in range(12)]
    for s in samples:
        for _consumer in range(3):
            got = every(s)
    assert every.made == 3  # t = 0, 0.10, 0.20 (0.02 steps: a made one serves five)
    assert got[0, 0] == 1.0 + 10  # the last made: t = 0.20
    assert every(a_sample(t=0.0, **est)).tolist()[0] == [1.0, 2.0]  # back in time: a new run
    assert every(a_sample(t=0.01, **{**est, "object_class": "circle"})).shape == (3, 2)
    assert every.made == 5 and every(a_sample(t=0.02, **{**est, "object_class": None})).size == 0
