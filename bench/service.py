"""The service under load: a real-time simulated run with no clients, then the same run with 20
WebSocket clients and the viser 3-D view connected — loop rate, sense→command latency, messages
dropped per client, and the service process's CPU use."""

from __future__ import annotations

import asyncio
import json
import os
import tempfile
import time
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect
from websockets.typing import Subprotocol

from sdh2svc.service.launch import LiveService, start_service

CLIENTS = 20


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def _client(url: str, counts: dict[str, int], stop: asyncio.Event) -> None:
    async with connect(url, max_size=2**24) as ws:
        while not stop.is_set():
            try:
                text = await asyncio.wait_for(ws.recv(), 0.5)
            except TimeoutError:
                continue
            msg = json.loads(text)
            counts[msg["type"]] = counts.get(msg["type"], 0) + 1
            if msg["type"] == "dropped":
                counts["dropped_total"] = msg["count"]


async def _viser(url: str, counts: dict[str, int], stop: asyncio.Event) -> None:
    """A 3-D view client: the viser websocket, reading every scene message it is sent."""
    import viser

    proto = [Subprotocol(f"viser-v{viser.__version__}")]
    async with connect(url.replace("http://", "ws://"), max_size=2**26, subprotocols=proto) as ws:
        while not stop.is_set():
            try:
                await asyncio.wait_for(ws.recv(), 0.5)
                counts["viser_msgs"] = counts.get("viser_msgs", 0) + 1
            except TimeoutError:
                continue


async def _run(svc: LiveService, clients: int, viewer: bool) -> dict[str, Any]:
    stop = asyncio.Event()
    counts = [dict[str, int]() for _ in range(clients)]
    viser_counts: dict[str, int] = {}
    tasks = [asyncio.create_task(_client(svc.ws_url, c, stop)) for c in counts]
    if viewer and svc.viewer_url:
        tasks.append(asyncio.create_task(_viser(svc.viewer_url, viser_counts, stop)))
    await asyncio.sleep(1.0)
    cpu0, t0 = _cpu_s(svc.proc.pid), time.monotonic()
    async with svc.client() as c:
        r = await c.post("/api/runs", json={"object": "egg", "params": {"cycles": 1}})
        run_id = r.json()["run_id"]
        while True:
            st = (await c.get("/api/status")).json()
            if st["last_run"] and st["last_run"]["id"] == run_id:
                break
            await asyncio.sleep(0.25)
        summary = (await c.get(f"/api/runs/{run_id}")).json()["summary"]
    cpu = (_cpu_s(svc.proc.pid) - cpu0) / (time.monotonic() - t0)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    return {"summary": summary, "cpu": cpu, "counts": counts, "viser": viser_counts,
            "disconnected": st["telemetry"]["disconnected_slow"]}  # fmt: skip


def run() -> dict[str, float]:
    with tempfile.TemporaryDirectory() as tmp:
        svc = start_service(Path(tmp), viewer=True)
        try:
            base = asyncio.run(_run(svc, 0, viewer=False))
            loaded = asyncio.run(_run(svc, CLIENTS, viewer=True))
        finally:
            svc.stop()
    b, lo = base["summary"], loaded["summary"]
    print("service under load (real-time simulated egg run, 1 stroke)")
    print(f"  {'':28s} {'no clients':>12s} {f'{CLIENTS} WS + viser':>16s} {'ratio':>7s}")
    rows = [("loop rate, Hz", b["loop_hz"], lo["loop_hz"]),
            ("sense→command p50, ms", b["latency_ms"]["p50"], lo["latency_ms"]["p50"]),
            ("sense→command p99, ms", b["latency_ms"]["p99"], lo["latency_ms"]["p99"]),
            ("tactile frames/s", b["frames"]["frames_per_s"], lo["frames"]["frames_per_s"]),
            ("service CPU, % of a core", 100 * base["cpu"], 100 * loaded["cpu"])]  # fmt: skip
    for name, x, y in rows:
        print(f"  {name:28s} {x:12.1f} {y:16.1f} {y / x:7.2f}")
    samples = [c.get("sample", 0) for c in loaded["counts"]]
    dropped = [c.get("dropped_total", 0) for c in loaded["counts"]]
    print(f"  status: {b['status']} / {lo['status']}; iterations {b['iterations']} / "
          f"{lo['iterations']}")  # fmt: skip
    print(f"  per client: samples received min {min(samples)} max {max(samples)} of "
          f"{lo['iterations']}; dropped max {max(dropped)}; slow clients cut off "
          f"{loaded['disconnected']}")  # fmt: skip
    print(f"  viser messages received: {loaded['viser'].get('viser_msgs', 0)}")
    worse = lo["latency_ms"]["p99"] / b["latency_ms"]["p99"] - 1
    slower = 1 - lo["loop_hz"] / b["loop_hz"]
    print(f"  target < 10 % worse: loop rate {slower * 100:+.1f} %, p99 latency "
          f"{worse * 100:+.1f} %")  # fmt: skip
    return {"loop_ratio": lo["loop_hz"] / b["loop_hz"], "p99_ratio": worse + 1}
