"""Reading old runs during a live one: real-time simulated runs (egg, 1 stroke) with no reader,
with two clients reading pages of 10 000 samples over and over, and with two clients exporting a
run as MCAP over and over — the loop's iterations and its sense→command latency in each.

The API's reads run in worker processes (``sdh2svc/service/reads.py``): before, in the
service's threads and encoded on its event loop, two page readers took the p99 from ≈ 1.6 ms to
≈ 190 ms and halved the iterations. The run read is a long one recorded first in fast mode
(``sdh2svc run --sim --fast``, 10 strokes) into the service's database. The settings alternate,
so that drifts of a shared machine hit all alike; the load averages are printed."""

from __future__ import annotations

import asyncio
import json
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

import httpx

from bench.common import percentile
from bench.service import _load
from sdh2svc.client import AsyncClient
from tests.live_service import LiveService, start_service

ROUNDS = 2
READERS = 2
SETTINGS = {
    "none": None,
    "2 × samples?limit=10000": "/api/runs/{id}/samples?limit=10000",
    "2 × export?format=mcap": "/api/runs/{id}/export?format=mcap",
}


def _record_long_run(db: Path) -> None:
    """A long recorded run (fast mode) in the database the service will use."""
    cmd = [sys.executable, "-m", "sdh2svc", "run", "--sim", "--fast", "--object", "egg",
           "--cycles", "10", "--set", f"storage.db_path={json.dumps(str(db))}"]  # fmt: skip
    subprocess.run(cmd, check=True, capture_output=True, timeout=600)


def _hammer(url: str, path: str | None, stop: threading.Event, count: list[int]) -> None:
    if path is None:
        return
    with httpx.Client(base_url=url, timeout=120) as c:
        while not stop.is_set():
            c.get(path).raise_for_status()
            count[0] += 1


async def _run(svc: LiveService, path: str | None, long_id: int) -> dict[str, Any]:
    stop, count = threading.Event(), [0]
    target = None if path is None else path.format(id=long_id)
    args = (svc.url, target, stop, count)
    readers = [threading.Thread(target=_hammer, args=args) for _ in range(READERS)]
    async with AsyncClient(svc.url) as c:
        run_id = (await c.start_run({"cycles": 1}, "egg"))["run_id"]
        for t in readers:
            t.start()
        try:
            await c.wait_run(run_id, poll_s=0.25)
        finally:
            stop.set()
            for t in readers:
                await asyncio.to_thread(t.join)
        summary = (await c.run(run_id))["summary"]
        page = await c.samples(run_id, limit=10_000)
    lat = [s["latency_ms"] for s in page["samples"] if s["latency_ms"] is not None]
    return {"status": summary["status"], "loop_hz": summary["loop_hz"] or 0.0,
            "latencies": lat, "reads": count[0]}  # fmt: skip


def run(rounds: int = ROUNDS) -> dict[str, float]:
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        _record_long_run(Path(tmp) / "runs.sqlite")
        svc = start_service(Path(tmp), viewer=False)
        try:
            long_id = max(httpx.get(svc.url + "/api/runs").json(), key=lambda r: r["iterations"])
            results: dict[str, list[dict[str, Any]]] = {name: [] for name in SETTINGS}
            loads = [_load()]
            for _ in range(rounds):
                for name, path in SETTINGS.items():
                    results[name].append(asyncio.run(_run(svc, path, long_id["id"])))
                loads.append(_load())
        finally:
            svc.stop()
    print(f"reading old runs during a live one (serve --sim; real-time egg runs, 1 stroke; "
          f"{READERS} readers of run {long_id['id']}, {long_id['iterations']} iterations; "
          f"{rounds} rounds, alternating)")  # fmt: skip
    print(f"  load averages (1, 5, 15 min) before and after each round: {' | '.join(loads)}")
    print(f"  {'':26s} {'loop Hz':>8s} {'sense→command p50 ms':>21s} {'p99 ms':>7s}"
          f" {'reads':>6s} {'p99 / none':>10s}")  # fmt: skip
    base_p99 = 0.0
    for name, runs in results.items():
        lat = [x for r in runs for x in r["latencies"]]
        rate = sum(r["loop_hz"] for r in runs) / len(runs)
        p50, p99 = percentile(lat, 50), percentile(lat, 99)
        base_p99 = base_p99 or p99
        reads = sum(r["reads"] for r in runs)
        print(f"  {name:26s} {rate:8.1f} {p50:21.2f} {p99:7.2f} {reads:6d} "
              f"{p99 / base_p99:10.2f}   ({' '.join(r['status'] for r in runs)})")  # fmt: skip
        out[f"{name}_p99_ms"] = p99
        out[f"{name}_rate"] = rate
    return out


if __name__ == "__main__":
    run()
