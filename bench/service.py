"""The service under load: real-time simulated runs with no clients, and the same runs with 20
WebSocket clients and the viser 3-D view connected — loop rate, sense→command latency, messages
dropped per client, and the service process's CPU use.

The simulated hand is embedded (``serve --sim``): its controllers' replies share the service's
event loop, so the telemetry work delays them too — which a real hand's firmware would not
suffer. The figures are therefore on the pessimistic side."""

from __future__ import annotations

import asyncio
import json
import os
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from websockets.asyncio.client import connect
from websockets.typing import Subprotocol

from bench.common import percentile
from sdh2svc.service.launch import LiveService, start_service

CLIENTS = 20
PAIRS = 3


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
        page = (await c.get(f"/api/runs/{run_id}/samples", params={"limit": 10000})).json()
    cpu = (_cpu_s(svc.proc.pid) - cpu0) / (time.monotonic() - t0)
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    return {"summary": summary, "cpu": cpu, "counts": counts, "viser": viser_counts,
            "disconnected": st["telemetry"]["disconnected_slow"],
            "latencies": [s["latency_ms"] for s in page["samples"]]}  # fmt: skip


def _pool(runs: list[dict[str, Any]]) -> dict[str, float]:
    """Figures over several runs: latencies pooled (one run's p99 is its 2nd-worst iteration)."""
    lat = [x for r in runs for x in r["latencies"]]
    return {
        "loop": statistics.fmean(r["summary"]["loop_hz"] or 0.0 for r in runs),
        "p50": percentile(lat, 50), "p99": percentile(lat, 99), "n": len(lat),
        "fps": statistics.fmean(r["summary"]["frames"]["frames_per_s"] for r in runs),
        "cpu": 100 * statistics.fmean(r["cpu"] for r in runs),
    }  # fmt: skip


def run(pairs: int = PAIRS) -> dict[str, float]:
    base: list[dict[str, Any]] = []
    loaded: list[dict[str, Any]] = []
    with tempfile.TemporaryDirectory() as tmp:
        svc = start_service(Path(tmp), viewer=True)
        try:
            for _ in range(pairs):  # alternate, so drifts of a shared machine hit both alike
                base.append(asyncio.run(_run(svc, 0, viewer=False)))
                loaded.append(asyncio.run(_run(svc, CLIENTS, viewer=True)))
        finally:
            svc.stop()
    b, lo = _pool(base), _pool(loaded)
    print(f"service under load (real-time egg runs on the embedded simulated hand, "
          f"1 stroke; {pairs} runs each, "
          f"alternating; latencies pooled: {b['n']} / {lo['n']} iterations)")  # fmt: skip
    print(f"  {'':28s} {'no clients':>12s} {f'{CLIENTS} WS + viser':>16s} {'ratio':>7s}")
    rows = [("loop rate, Hz", "loop"), ("sense→command p50, ms", "p50"),
            ("sense→command p99, ms", "p99"), ("tactile frames/s", "fps"),
            ("service CPU, % of a core", "cpu")]  # fmt: skip
    for name, key in rows:
        print(f"  {name:28s} {b[key]:12.1f} {lo[key]:16.1f} {lo[key] / b[key]:7.2f}")
    print("  status: " + " ".join(r["summary"]["status"] for r in base) + " / "
          + " ".join(r["summary"]["status"] for r in loaded))  # fmt: skip
    samples = [c.get("sample", 0) for r in loaded for c in r["counts"]]
    dropped = [c.get("dropped_total", 0) for r in loaded for c in r["counts"]]
    sent = [r["summary"]["iterations"] for r in loaded]
    print(f"  per client: samples received min {min(samples)} max {max(samples)} (runs had "
          f"{min(sent)}–{max(sent)} iterations); dropped max {max(dropped)}; slow clients cut "
          f"off {sum(r['disconnected'] for r in loaded[-1:])}")  # fmt: skip
    print(f"  viser messages received: {sum(r['viser'].get('viser_msgs', 0) for r in loaded)}")
    worse = lo["p99"] / b["p99"] - 1
    slower = 1 - lo["loop"] / b["loop"]
    print(f"  target < 10 % worse: loop rate {slower * 100:+.1f} %, p99 latency "
          f"{worse * 100:+.1f} %")  # fmt: skip
    return {"loop_ratio": lo["loop"] / b["loop"], "p99_ratio": worse + 1}
