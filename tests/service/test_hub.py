"""The telemetry hub on its own: bounded queues, drop counting, decimation, the send timeout."""

from __future__ import annotations

import asyncio
import json
import math

from sdh2svc.service.hub import Client, TelemetryHub
from sdh2svc.service.telemetry import AnyMessage, encode, kind_of, to_json


def test_full_queue_drops_the_oldest_and_counts() -> None:
    hub = TelemetryHub()
    c = Client(max_queue=3)
    hub.clients.add(c)
    for i in range(5):
        hub.publish({"type": "event", "i": i})
    assert [json.loads(t)["i"] for t in c.queue] == [2, 3, 4]
    assert c.dropped == 2 and hub.stats()["dropped"] == 2


def test_decimation_and_tactile_opt_out() -> None:
    hub = TelemetryHub()
    c = Client(max_queue=100, decimate=4, tactile=False)
    hub.clients.add(c)
    for i in range(10):
        hub.publish({"type": "sample", "i": i})
        hub.publish({"type": "tactile", "i": i})
    got = [json.loads(t) for t in c.queue]
    assert [m["i"] for m in got if m["type"] == "sample"] == [0, 4, 8]
    assert not [m for m in got if m["type"] == "tactile"]


def test_non_finite_numbers_become_null() -> None:
    msg = json.loads(encode({"type": "status", "x": math.inf, "y": [math.nan, 1.0]}))
    assert msg == {"type": "status", "x": None, "y": [None, 1.0]}


async def test_drop_notice_precedes_the_next_message() -> None:
    hub = TelemetryHub()
    c = Client(max_queue=2)
    sent: list[dict[str, object]] = []
    gate = asyncio.Event()

    async def send(text: str) -> None:
        await gate.wait()
        sent.append(json.loads(text))

    task = asyncio.create_task(hub.serve(c, send))
    await asyncio.sleep(0)
    for i in range(5):
        hub.publish({"type": "event", "i": i})
    gate.set()
    while len(sent) < 3:
        await asyncio.sleep(0.01)
    task.cancel()
    assert sent[0] == {"type": "dropped", "count": 3}
    assert [m.get("i") for m in sent[1:]] == [3, 4]


async def test_a_stalled_client_is_cut_off_without_holding_others() -> None:
    hub = TelemetryHub(send_timeout_s=0.2)
    stalled, fine = Client(), Client()
    received: list[str] = []

    async def never(text: str) -> None:
        await asyncio.Event().wait()

    async def ok(text: str) -> None:
        received.append(text)

    t1 = asyncio.create_task(hub.serve(stalled, never))
    t2 = asyncio.create_task(hub.serve(fine, ok))
    await asyncio.sleep(0)
    for i in range(50):
        hub.publish({"type": "sample", "i": i})
        await asyncio.sleep(0.01)
    await asyncio.wait_for(t1, 1.0)  # serve() returned: disconnected
    assert hub.disconnected_slow == 1 and stalled not in hub.clients
    assert len(received) == 50
    t2.cancel()


def test_a_failing_listener_does_not_stop_publishing() -> None:
    hub = TelemetryHub()
    seen: list[int] = []

    def broken(msg: AnyMessage) -> None:
        raise RuntimeError("view crashed")

    hub.add_listener(broken)
    hub.add_listener(lambda m: seen.append(int(to_json(m)["i"])))
    hub.publish({"type": "event", "i": 1})
    assert seen == [1]


async def test_delivery_waits_for_the_end_of_the_iteration() -> None:
    """A frame's telemetry is delivered (listeners, queues) once the iteration's sample is out —
    the joint command is written then — and not while the runner works on the frame; without
    a sample it follows after a short hold. Order is kept."""
    hub = TelemetryHub()
    c = Client()
    hub.clients.add(c)
    seen: list[str] = []
    hub.add_listener(lambda m: seen.append(kind_of(m)))
    hub.publish({"type": "tactile", "seq": 1})
    assert not c.queue and not seen  # the frame has just arrived: nothing done yet
    hub.publish({"type": "sample", "iteration": 1})
    assert not c.queue  # delivered on the next turn of the loop, after the runner's step
    await asyncio.sleep(0)
    assert [json.loads(t)["type"] for t in c.queue] == seen == ["tactile", "sample"]
    hub.publish({"type": "pose", "angles_deg": [0.0] * 7})
    for _ in range(100):
        if len(seen) == 3:
            break
        await asyncio.sleep(0.01)
    assert seen[-1] == "pose" and json.loads(c.queue[-1])["type"] == "pose"
