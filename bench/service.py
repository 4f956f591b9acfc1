"""The service under load: real-time simulated runs with no clients, and the same runs with 20
WebSocket clients and the viser 3-D view connected — loop rate, sense→command latency, messages
dropped per client, and the CPU use of the service (and of its 3-D view's process) — in two
configurations:

* embedded (``serve --sim``): the simulated hand's controllers share the service's event loop,
  so the telemetry work delays their replies too — which a real hand's firmware would not
  suffer: the pessimistic figure;
* external, as in a lab: the hand is a process of its own (``sdh2svc sim``, both devices on
  TCP) and the service drives it through ``--dsa``/``--sdh socket://…`` URLs. Its lab assistant
  puts the egg back between the fingertips after each run (a run here does not choose the
  object; the bench waits for the put-back line on the simulator's stderr).

The machine is shared: the load averages are printed with the figures, and the runs of the two
settings alternate so that drifts hit both alike."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from websockets.asyncio.client import ClientConnection, connect
from websockets.exceptions import ConnectionClosed
from websockets.typing import Subprotocol

from bench.common import p99_ratio_interval, percentile
from sdh2svc.client import AsyncClient
from tests.live_service import LiveService, start_service

CLIENTS = 20
PAIRS = 3
TARGET = 0.10  # p99 latency with clients at most this much worse
PUT_BACK_TIMEOUT_S = 30.0


def _cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (Linux /proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _children(pid: int) -> list[int]:
    """The child processes of ``pid`` (the service's: the 3-D view, multiprocessing's tracker)."""
    kids: list[int] = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            kids += [int(k) for k in (task / "children").read_text().split()]
    return kids


def _load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


@dataclass
class ExternalHand:
    """``sdh2svc sim`` as a process of its own, its stderr collected (the put-back lines)."""

    proc: subprocess.Popen[str]
    dsa: str
    sdh: str
    err: list[str] = field(default_factory=list)

    def put_backs(self) -> int:
        return sum("put back" in line for line in list(self.err))


@contextmanager
def external_hand() -> Iterator[ExternalHand]:
    cmd = [sys.executable, "-m", "sdh2svc", "sim", "--json", "--no-pty", "--dsa-port", "0",
           "--sdh-port", "0", "--object", "egg"]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None and proc.stderr is not None
        info = json.loads(proc.stdout.readline())
        hand = ExternalHand(proc, info["dsa"][0], info["sdh"][0])
        threading.Thread(target=lambda: hand.err.extend(proc.stderr), daemon=True).start()  # type: ignore[arg-type]
        yield hand
    finally:
        proc.terminate()
        proc.wait(20)
        for stream in (proc.stdout, proc.stderr):
            stream.close()  # type: ignore[union-attr]


def _kind(text: str) -> str:
    """A message's type without parsing it all: the clients stand in for browsers on other
    machines, and their CPU here would be taken from the service and the hand."""
    start = text.index('"type":"') + 8
    return text[start : text.index('"', start)]


async def _close_on(stop: asyncio.Event, ws: ClientConnection) -> None:
    await stop.wait()
    await ws.close()


async def _client(url: str, counts: dict[str, int], stop: asyncio.Event) -> None:
    async with connect(url, max_size=2**24, compression=None) as ws:
        closer = asyncio.create_task(_close_on(stop, ws))
        with contextlib.suppress(ConnectionClosed):
            async for text in ws:
                kind = _kind(str(text))
                counts[kind] = counts.get(kind, 0) + 1
                if kind == "dropped":
                    counts["dropped_total"] = json.loads(text)["count"]
        await closer


async def _viser(url: str, counts: dict[str, int], stop: asyncio.Event) -> None:
    """A 3-D view client: the viser websocket, reading every scene message it is sent."""
    import msgspec.msgpack
    import viser
    from viser import _messages

    proto = [Subprotocol(f"viser-v{viser.__version__}")]
    async with connect(url.replace("http://", "ws://"), max_size=2**26, subprotocols=proto) as ws:
        camera = _messages.ViewerCameraMessage(  # as a browser showing the scene sends
            wxyz=(1.0, 0.0, 0.0, 0.0),
            position=(0.3, 0.0, 0.2),
            fov=1.0,
            near=0.01,
            far=100.0,
            image_height=720,
            image_width=1280,
            look_at=(0.0, 0.0, 0.0),
            up_direction=(0.0, 0.0, 1.0),
        )
        await ws.send(msgspec.msgpack.encode(camera.as_serializable_dict()))
        closer = asyncio.create_task(_close_on(stop, ws))
        with contextlib.suppress(ConnectionClosed):
            async for _ in ws:
                counts["viser_msgs"] = counts.get("viser_msgs", 0) + 1
        await closer


async def _run(
    svc: LiveService, clients: int, viewer: bool, hand: ExternalHand | None = None
) -> dict[str, Any]:
    stop = asyncio.Event()
    counts = [dict[str, int]() for _ in range(clients)]
    viser_counts: dict[str, int] = {}
    tasks = [asyncio.create_task(_client(svc.ws_url, c, stop)) for c in counts]
    if viewer and svc.viewer_url:
        tasks.append(asyncio.create_task(_viser(svc.viewer_url, viser_counts, stop)))
    await asyncio.sleep(1.0)
    kids = _children(svc.proc.pid)
    pids = [svc.proc.pid, os.getpid()] + ([hand.proc.pid] if hand else []) + kids
    cpu0, t0 = [_cpu_s(p) for p in pids], time.monotonic()
    put_backs = hand.put_backs() if hand else 0
    # embedded: the service puts the egg between the fingertips; external: the lab assistant
    obj = "egg" if hand is None else None
    async with AsyncClient(svc.url, token=svc.token) as c:
        run_id = (await c.start_run({"cycles": 1}, obj))["run_id"]
        await c.wait_run(run_id, poll_s=0.25)
        st = await c.status()
        summary = (await c.run(run_id))["summary"]
        page = await c.samples(run_id, limit=10_000)
    dt = time.monotonic() - t0
    cpu = [(_cpu_s(p) - c0) / dt for p, c0 in zip(pids, cpu0, strict=True)]
    stop.set()
    await asyncio.gather(*tasks, return_exceptions=True)
    if hand is not None:  # the next run needs the egg between the fingertips again
        deadline = time.monotonic() + PUT_BACK_TIMEOUT_S
        while hand.put_backs() <= put_backs and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
    return {"summary": summary, "cpu": cpu[0], "clients_cpu": cpu[1],
            "hand_cpu": cpu[2] if hand else None, "view_cpu": sum(cpu[-len(kids):] if kids else []),
            "counts": counts, "viser": viser_counts,
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
        "hand_cpu": 100 * statistics.fmean(r["hand_cpu"] or 0.0 for r in runs),
        "view_cpu": 100 * statistics.fmean(r["view_cpu"] for r in runs),
        "clients_cpu": 100 * statistics.fmean(r["clients_cpu"] for r in runs),
        "skipped": sum(r["summary"].get("frames_skipped") or 0 for r in runs),
    }  # fmt: skip


def _measure(svc: LiveService, pairs: int, hand: ExternalHand | None) -> dict[str, Any]:
    base: list[dict[str, Any]] = []
    loaded: list[dict[str, Any]] = []
    loads = [_load()]
    for _ in range(pairs):  # alternate, so drifts of a shared machine hit both alike
        base.append(asyncio.run(_run(svc, 0, viewer=False, hand=hand)))
        loaded.append(asyncio.run(_run(svc, CLIENTS, viewer=True, hand=hand)))
        loads.append(_load())
    return {"base": base, "loaded": loaded, "loads": loads}


def _report(title: str, m: dict[str, Any]) -> dict[str, float]:
    base, loaded = m["base"], m["loaded"]
    b, lo = _pool(base), _pool(loaded)
    print(f"{title}: {len(base)} runs each, alternating; latencies pooled: "
          f"{b['n']} / {lo['n']} iterations")  # fmt: skip
    print(f"  load averages (1, 5, 15 min) before and after each pair: {' | '.join(m['loads'])}")
    print(f"  {'':28s} {'no clients':>12s} {f'{CLIENTS} WS + viser':>16s} {'ratio':>7s}")
    rows = [("loop rate, Hz", "loop"), ("sense→command p50, ms", "p50"),
            ("sense→command p99, ms", "p99"), ("tactile frames/s", "fps"),
            ("service CPU, % of a core", "cpu")]  # fmt: skip
    if b["hand_cpu"] > 0:
        rows.append(("hand process CPU, %", "hand_cpu"))
    if lo["view_cpu"] > 0:
        rows.append(("3-D view process CPU, %", "view_cpu"))
    rows.append(("bench (clients) CPU, %", "clients_cpu"))
    for name, key in rows:
        ratio = f"{lo[key] / b[key]:7.2f}" if b[key] else f"{'–':>7s}"
        print(f"  {name:28s} {b[key]:12.1f} {lo[key]:16.1f} {ratio}")
    print(f"  {'frames skipped by the loop':28s} {b['skipped']:12.0f} {lo['skipped']:16.0f}")
    per_run = [(percentile(r["latencies"], 99), percentile(q["latencies"], 99))
               for r, q in zip(base, loaded, strict=True)]  # fmt: skip
    print("  p99 per run (none / loaded), ms: "
          + "  ".join(f"{x:.1f}/{y:.1f}" for x, y in per_run))  # fmt: skip
    print("  status: " + " ".join(r["summary"]["status"] for r in base) + " / "
          + " ".join(r["summary"]["status"] for r in loaded))  # fmt: skip
    samples = [c.get("sample", 0) for r in loaded for c in r["counts"]]
    dropped = [c.get("dropped_total", 0) for r in loaded for c in r["counts"]]
    sent = [r["summary"]["iterations"] for r in loaded]
    print(f"  per client: samples received min {min(samples)} max {max(samples)} (runs had "
          f"{min(sent)}–{max(sent)} iterations); dropped per client max {max(dropped)}, "
          f"total {sum(dropped)}; slow clients cut off "
          f"{sum(r['disconnected'] for r in loaded[-1:])}")  # fmt: skip
    print(f"  viser messages received: {sum(r['viser'].get('viser_msgs', 0) for r in loaded)}")
    worse = lo["p99"] / b["p99"] - 1
    slower = 1 - lo["loop"] / b["loop"]
    verdict = "met" if worse < TARGET else "NOT met"
    low, high = p99_ratio_interval([r["latencies"] for r in base],
                                   [r["latencies"] for r in loaded])  # fmt: skip
    print(f"  target p99 < {TARGET * 100:.0f} % worse: {worse * 100:+.1f} % ({verdict}); "
          f"95 % interval over runs and iterations {(low - 1) * 100:+.0f} … "
          f"{(high - 1) * 100:+.0f} %; loop rate {-slower * 100:+.1f} %")  # fmt: skip
    return {"loop_ratio": lo["loop"] / b["loop"], "p99_ratio": worse + 1}


def run(pairs: int = PAIRS) -> dict[str, float]:
    out: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        emb_dir, ext_dir = Path(tmp) / "embedded", Path(tmp) / "external"
        emb_dir.mkdir()
        ext_dir.mkdir()
        svc = start_service(emb_dir, viewer=True)
        try:
            embedded = _measure(svc, pairs, None)
        finally:
            svc.stop()
        title = "service under load, embedded hand (serve --sim; real-time egg runs, 1 stroke)"
        out |= {f"embedded_{k}": v for k, v in _report(title, embedded).items()}
        print()
        with external_hand() as hand:
            extra = ["--dsa", hand.dsa, "--sdh", hand.sdh]
            svc = start_service(ext_dir, viewer=True, sim=False, extra=extra)
            try:
                external = _measure(svc, pairs, hand)
            finally:
                svc.stop()
        title = ("service under load, external hand (`sdh2svc sim` process, TCP; serve "
                 "--dsa/--sdh socket://…; real-time egg runs, 1 stroke)")  # fmt: skip
        out |= {f"external_{k}": v for k, v in _report(title, external).items()}
    return out
