"""The REST/WebSocket API against a real ``sdh2svc serve --sim`` (uvicorn, sockets, SQLite)."""

from __future__ import annotations

import asyncio
import contextlib
import csv
import io
import itertools
import json
import socket
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import httpx
import pytest
from mcap_check import read
from websockets.asyncio.client import ClientConnection, connect

from sdh2svc.config import load_config
from sdh2svc.service.store import RunStore
from tests.live_service import LiveService, service_command, start_service

RUN_TIMEOUT_S = 120.0


@pytest.fixture(scope="module")
def svc(
    tmp_path_factory: pytest.TempPathFactory, long_runs: tuple[str, ...]
) -> Iterator[LiveService]:
    s = start_service(tmp_path_factory.mktemp("api"), viewer=False, extra=long_runs)
    try:
        yield s
    finally:
        assert s.stop() == 0, "".join(s.log)


class Telemetry:
    """Everything one WebSocket client receives, collected in the background."""

    def __init__(self, ws: ClientConnection) -> None:
        self.ws = ws
        self.messages: list[dict[str, Any]] = []
        self._task = asyncio.create_task(self._collect())

    async def _collect(self) -> None:
        with contextlib.suppress(Exception):
            async for text in self.ws:
                self.messages.append(json.loads(text))

    def of(self, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.messages if m["type"] == kind]

    def samples(self, run_id: int) -> list[dict[str, Any]]:
        return [m["sample"] for m in self.of("sample") if m["run_id"] == run_id]

    def events(self, run_id: int, kind: str) -> list[dict[str, Any]]:
        return [m for m in self.of("event") if m["run_id"] == run_id and m["kind"] == kind]

    async def until(self, what: Callable[[], Any], timeout: float = RUN_TIMEOUT_S) -> Any:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            got = what()
            if got:
                return got
            await asyncio.sleep(0.05)
        raise AssertionError(f"timed out; last messages: {self.messages[-3:]}")


@contextlib.asynccontextmanager
async def telemetry(svc: LiveService, query: str = "") -> AsyncIterator[Telemetry]:
    async with connect(svc.ws_url + query, max_size=2**24) as ws:
        t = Telemetry(ws)
        yield t
        t._task.cancel()


async def run_state(client: httpx.AsyncClient) -> dict[str, Any]:
    return (await client.get("/api/status")).json()


async def wait_run_end(client: httpx.AsyncClient, run_id: int) -> dict[str, Any]:
    deadline = time.monotonic() + RUN_TIMEOUT_S
    while time.monotonic() < deadline:
        st = await run_state(client)
        if st["last_run"] and st["last_run"]["id"] == run_id:
            return st
        await asyncio.sleep(0.2)
    raise AssertionError(f"run {run_id} did not end")


async def test_status_and_clear_errors(svc: LiveService) -> None:
    async with svc.client() as c:
        st = await run_state(c)
        assert st["sim"] is True and st["auth_required"] is False
        assert st["hand"]["connected"] == {"joints": True, "tactile": True}
        assert st["links"]["tactile"]["connected"] is True
        assert st["object"]["kind"] in {"ellipse", "box", "circle", "stick", "polygon"}

        r = await c.patch("/api/params", json={"k": 0.5})
        assert r.status_code == 422
        body = r.json()
        assert body["error"] == "invalid rolling parameters"
        assert any(d.startswith("k = 0.5") and "1.0 < k ≤ 10.0" in d for d in body["details"])
        r = await c.patch("/api/params", json={"delta_phi_deg": 0})
        assert r.status_code == 422 and "must not be 0" in r.json()["details"][0]
        r = await c.patch("/api/params", json={"no_such": 1})
        assert r.status_code == 422 and "no_such" in r.json()["details"][0]
        assert (await c.get("/api/params")).json()["k"] == 2.0  # nothing half-applied

        r = await c.post("/api/runs/stop", json={})
        assert r.status_code == 409 and r.json()["error"] == "no run is running"
        r = await c.get("/api/runs/9999")
        assert r.status_code == 404 and "no run 9999" in r.json()["error"]
        r = await c.get("/api/runs/1/samples", params={"limit": 0})
        assert r.status_code == 422 and "limit" in r.json()["details"][0]
        r = await c.put("/api/sim/object", json={"name": "teapot"})
        assert r.status_code == 422 and "teapot" in r.json()["error"]
        r = await c.put("/api/sim/object", json={"spec": {"kind": "circle", "diameter_mm": -3}})
        assert r.status_code == 422 and any("diameter_mm" in d for d in r.json()["details"])
        r = await c.post("/api/runs", json={"params": {"alpha_deg": 90}})
        assert r.status_code == 422 and "alpha_deg" in r.json()["details"][0]
        assert (await run_state(c))["run"] is None  # the refused run never started

        r = await c.put("/api/sim/object", json={"name": "rubber"})
        assert r.status_code == 200 and r.json()["object"]["name"] == "rubber"
        assert "egg" in r.json()["presets"]
        assert (await c.get("/api/sim/object")).json()["object"]["name"] == "rubber"
        schema = (await c.get("/api/params/schema")).json()
        assert schema["properties"]["k"]["exclusiveMinimum"] == 1.0
        assert (await c.get("/docs")).status_code == 200
        assert (await c.get("/api/viewer")).json() == {"url": None}


def assert_steps(samples: list[dict], dphi: float) -> None:
    """Finger 2's steps |φ4 − φ4d|: never beyond Δφ, and the full Δφ in most iterations."""
    steps = [abs(s["phi4"] - s["phi4_d"]) for s in samples]
    assert steps and max(steps) < dphi + 1e-6, steps
    assert sum(abs(st - dphi) < 1e-6 for st in steps) >= 0.8 * len(steps), steps


async def test_run_observed_params_changed_mid_run_stopped_exported(svc: LiveService) -> None:
    async with svc.client() as c, telemetry(svc) as tm, telemetry(svc, "?decimate=3") as tm3:
        await tm.until(lambda: tm.of("hello"))
        slow = {"cycles": 50, "delta_phi_deg": 0.05}  # Finger 1 within its step: Δφ in full
        r = await c.post("/api/runs", json={"object": "egg", "params": slow})
        assert r.status_code == 201, r.text
        run_id = r.json()["run_id"]
        r = await c.post("/api/runs", json={})
        assert r.status_code == 409 and "already running" in r.json()["error"]
        r = await c.put("/api/sim/object", json={"name": "egg"})
        assert r.status_code == 409

        # rolling: Finger 2 steps Δφ = 0.05° per iteration (φ4 − φ4d), less where Finger 1's
        # step limit slows an iteration down
        await tm.until(lambda: len(tm.samples(run_id)) >= 15)
        before = [s for s in tm.samples(run_id) if s["phi4_d"] is not None]
        assert_steps(before, 0.05)
        r = await c.patch("/api/params", json={"delta_phi_deg": 0.08})
        assert r.status_code == 200 and r.json()["delta_phi_deg"] == 0.08
        ev = await tm.until(lambda: tm.events(run_id, "params"))
        changed_at = ev[0]["iteration"]
        assert ev[0]["detail"]["params"]["delta_phi_deg"] == 0.08
        await tm.until(lambda: len([s for s in tm.samples(run_id)
                                    if s["iteration"] > changed_at + 5]))  # fmt: skip
        after = [s for s in tm.samples(run_id)
                 if s["iteration"] > changed_at and s["phi4_d"] is not None]  # fmt: skip
        assert_steps(after, 0.08)
        # … and Finger 2's route still has slope k
        for s in after:
            assert abs((s["phi5_d"] - s["phi5"]) / (s["phi4"] - s["phi4_d"]) - 2.0) < 1e-6

        st = await run_state(c)
        assert st["run"]["id"] == run_id and st["run"]["state"] == "rolling"
        assert st["run"]["strokes_total"] == 50
        assert st["links"]["tactile"]["frames_per_s"] > 5
        r = await c.post("/api/runs/stop", json={})
        assert r.status_code == 202
        st = await wait_run_end(c, run_id)
        assert st["last_run"]["status"] == "stopped"
        assert st["run"]["state"] == "stopped"
        await c.patch("/api/params", json={"delta_phi_deg": 0.25})

        # the record: every sample the clients saw is in the database, the exports parse
        seen = tm.samples(run_id)
        page = (await c.get(f"/api/runs/{run_id}/samples", params={"limit": 10000})).json()
        assert page["total"] == len(page["samples"]) >= len(seen) > 0
        by_iter = {s["iteration"]: s for s in page["samples"]}
        for s in seen:
            assert by_iter[s["iteration"]]["F"] == pytest.approx(s["F"])
        half = (await c.get(f"/api/runs/{run_id}/samples",
                            params={"offset": 5, "limit": 3})).json()  # fmt: skip
        assert [s["iteration"] for s in half["samples"]] == \
            [s["iteration"] for s in page["samples"][5:8]]  # fmt: skip
        run = (await c.get(f"/api/runs/{run_id}")).json()
        assert run["status"] == "stopped" and run["meta"]["object"]["name"] == "egg"
        kinds = [e["kind"] for e in run["events"]]
        assert "params" in kinds and "grasped" in kinds and kinds[-1] == "end"

        r = await c.get(f"/api/runs/{run_id}/export", params={"format": "csv"})
        assert r.status_code == 200 and "attachment" in r.headers["content-disposition"]
        rows = list(csv.DictReader(io.StringIO(r.text)))
        assert len(rows) == page["total"]
        assert float(rows[0]["F [library force units]"]) == page["samples"][0]["F"]
        r = await c.get(f"/api/runs/{run_id}/export", params={"format": "mcap"})
        assert r.status_code == 200
        got = read(r.content)  # every message valid against its schema (mcap_check)
        assert len(got.messages["/samples"]) == page["total"]
        assert len(got.messages["/tf"]) == len(got.messages["/scene"]) == page["total"]
        assert got.messages["/tactile/finger1_distal"] and got.messages["/events"]
        r = await c.get(f"/api/runs/{run_id}/export", params={"format": "xls"})
        assert r.status_code == 422

        # a decimating client got every third sample; tactile frames came at ≤ 30 Hz
        every = [s["iteration"] for s in tm.samples(run_id)]
        third = [s["iteration"] for s in tm3.samples(run_id)]
        assert third and third == every[::3][: len(third)]
        ts = [m["t"] for m in tm.of("tactile")]
        assert len(ts) > 30 and min(b - a for a, b in itertools.pairwise(ts)) > 0.9 / 30

        # the telemetry carried the other kinds too
        assert tm.of("tactile") and len(tm.of("tactile")[-1]["matrices"]) == 6
        assert len(tm.of("tactile")[-1]["matrices"][1]) == 13
        assert tm.of("pose") and len(tm.of("pose")[-1]["angles_deg"]) == 7
        truth = tm.of("sim")[-1]["truth"]
        assert truth["object"] == "egg" and len(truth["outline"]) > 20
        assert tm.of("status")


async def test_estop_mid_run_and_release(svc: LiveService) -> None:
    async with svc.client() as c, telemetry(svc, "?tactile=0") as tm:
        slow = {"cycles": 50, "delta_phi_deg": 0.05}  # Finger 1 within its step: Δφ in full
        r = await c.post("/api/runs", json={"object": "egg", "params": slow})
        run_id = r.json()["run_id"]
        await tm.until(lambda: tm.samples(run_id))
        t0 = time.monotonic()
        r = await c.post("/api/estop")
        assert r.status_code == 200 and r.json()["estopped"] is True
        assert time.monotonic() - t0 < 5.0  # generous: answered, not hung behind the run
        st = await wait_run_end(c, run_id)
        assert st["estopped"] is True and st["run"]["state"] == "e-stopped"
        assert st["last_run"]["status"] == "e-stopped"
        assert tm.events(run_id, "estop")
        n = len(tm.samples(run_id))
        r = await c.post("/api/runs", json={})
        assert r.status_code == 409 and "e-stop is latched" in r.json()["error"]
        # e-stop while idle works too, and the hand stays where it stopped
        assert (await c.post("/api/estop")).status_code == 200
        await asyncio.sleep(0.6)  # the angles shown between runs are polled at 5 Hz
        a1 = (await run_state(c))["hand"]["angles_deg"]
        await asyncio.sleep(1.0)
        a2 = (await run_state(c))["hand"]["angles_deg"]
        assert a1 == a2
        assert len(tm.samples(run_id)) == n  # no iteration after the e-stop
        r = await c.post("/api/estop/release", json={})
        assert r.status_code == 200 and r.json() == {"estopped": False}
        assert (await run_state(c))["estopped"] is False
        run = (await c.get(f"/api/runs/{run_id}")).json()
        assert run["status"] == "e-stopped"


async def test_token_required_when_exposed(tmp_path: Path) -> None:
    # exposed without a token: refused at start, with a reason
    s = await asyncio.to_thread(
        lambda: __import__("subprocess").run(
            [*_cmd(tmp_path), "--host", "0.0.0.0"], capture_output=True, text=True, timeout=60,
            cwd=tmp_path, env=_env_without_token(),
        )
    )  # fmt: skip
    assert s.returncode == 2 and "without a token" in s.stderr

    svc = await asyncio.to_thread(start_service, tmp_path, viewer=False, token="s3cret",
                                  extra=["--host", "0.0.0.0"])  # fmt: skip
    try:
        host = urlparse(svc.url)
        assert host.hostname == "0.0.0.0"
        url = f"http://127.0.0.1:{host.port}"
        async with httpx.AsyncClient(base_url=url, timeout=30) as c:
            assert (await c.get("/api/status")).json()["auth_required"] is True
            for method, path, body in (("PATCH", "/api/params", {"k": 3}),
                                       ("POST", "/api/runs", {}), ("POST", "/api/runs/stop", {}),
                                       ("POST", "/api/estop/release", {}),
                                       ("POST", "/api/hand/open", {}),
                                       ("PUT", "/api/sim/object", {"name": "egg"})):  # fmt: skip
                r = await c.request(method, path, json=body)
                assert r.status_code == 401, (method, path)
                assert "bearer token" in r.json()["error"]
                r = await c.request(method, path, json=body,
                                    headers={"Authorization": "Bearer wrong"})  # fmt: skip
                assert r.status_code == 401
            # stopping needs no token (nor JSON, nor an Origin of its own); releasing does
            r = await c.post("/api/estop", headers={"Origin": "http://evil.example"})
            assert r.status_code == 200 and r.json()["estopped"] is True
            r = await c.post("/api/estop/release", json={},
                             headers={"Authorization": "Bearer s3cret"})  # fmt: skip
            assert r.status_code == 200 and r.json() == {"estopped": False}
            # with the token too, a command must be JSON; and a huge body is refused before the
            # token is even looked at
            r = await c.post("/api/runs/stop", headers={"Authorization": "Bearer s3cret",
                                                        "Content-Type": "text/plain"})  # fmt: skip
            assert r.status_code == 415
            head = (
                f"PATCH /api/params HTTP/1.1\r\nHost: 127.0.0.1:{host.port}\r\n"
                f"Content-Type: application/json\r\nContent-Length: {300 * 2**20}\r\n\r\n"
            )
            with socket.create_connection(("127.0.0.1", host.port), timeout=10) as sock:
                sock.sendall(head.encode())  # and no body: it is refused before it is read
                assert sock.recv(64).startswith(b"HTTP/1.1 413")
            r = await c.patch("/api/params", json={"k": 3},
                              headers={"Authorization": "Bearer s3cret"})  # fmt: skip
            assert r.status_code == 200 and r.json()["k"] == 3
            assert (await c.get("/api/params")).json()["k"] == 3
            conf = (await c.get("/api/config")).json()
            assert conf["service"]["token"] == "***" and "s3cret" not in json.dumps(conf)
            assert conf["hand"]["pad"]["arc_radius_mm"] == 60.0 and conf["axes"]["phi4"] == 5
            viewer = await c.get("/api/viewer")
            assert viewer.json() == {"url": None}
    finally:
        assert await asyncio.to_thread(svc.stop) == 0


def _cmd(tmp: Path) -> list[str]:
    return service_command(tmp / "runs.sqlite", viewer=False)


def _env_without_token() -> dict[str, str]:
    import os

    return {k: v for k, v in os.environ.items() if k != "SDH2SVC_SERVICE__TOKEN"}


def _stalled_client(url: str) -> socket.socket:
    """A WebSocket client that completes the handshake and then never reads."""
    u = urlparse(url)
    sock = socket.socket()
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    sock.connect((u.hostname, u.port))
    sock.sendall(
        f"GET {u.path} HTTP/1.1\r\nHost: {u.hostname}:{u.port}\r\nUpgrade: websocket\r\n"
        "Connection: Upgrade\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
        "Sec-WebSocket-Version: 13\r\n\r\n".encode()
    )
    assert b"101" in sock.recv(12)
    return sock


async def test_stalled_client_does_not_slow_the_loop(svc: LiveService) -> None:
    """One client never reads: it is dropped; the loop and a normal client lose nothing."""
    async with svc.client() as c:
        stalled = [_stalled_client(svc.ws_url) for _ in range(3)]
        try:
            async with telemetry(svc) as tm:
                summary = await _one_stroke_run(c, svc)
                run_id = summary["run_id"]
                st = await run_state(c)
            samples = tm.samples(run_id)
        finally:
            for s in stalled:
                s.close()
    assert summary["status"] == "completed", summary
    # the stalled clients were cut off after the send timeout …
    assert st["telemetry"]["disconnected_slow"] >= 3
    # … the reading client got every iteration, in order, none dropped
    assert [s["iteration"] for s in samples] == list(range(1, summary["iterations"] + 1))
    assert not tm.of("dropped")
    # … and the loop kept its pace: the tactile frame rate, not the CPU, sets it (one iteration
    # per fresh frame at run.tactile_rate_hz = 30; 0.7 leaves room for a shared machine —
    # bench/service.py measures the latency with and without clients properly)
    rate = load_config(use_env=False).run.tactile_rate_hz
    assert summary["loop_hz"] >= 0.7 * rate, summary


async def _one_stroke_run(c: httpx.AsyncClient, svc: LiveService) -> dict[str, Any]:
    r = await c.post("/api/runs", json={"object": "egg", "params": {"cycles": 1}})
    assert r.status_code == 201, r.text
    run_id = r.json()["run_id"]
    await wait_run_end(c, run_id)
    return (await c.get(f"/api/runs/{run_id}")).json()["summary"]


async def test_sigterm_mid_run_stops_motion_then_exits_cleanly(
    tmp_path: Path, long_runs: tuple[str, ...]
) -> None:
    svc = await asyncio.to_thread(start_service, tmp_path, viewer=False, extra=long_runs)
    try:
        async with svc.client() as c, telemetry(svc, "?tactile=0") as tm:
            r = await c.post("/api/runs", json={"object": "egg", "params": {"cycles": 50}})
            run_id = r.json()["run_id"]
            await tm.until(lambda: tm.samples(run_id))
    finally:
        code = await asyncio.to_thread(svc.stop)
    log = "".join(svc.log)
    assert code == 0, log
    # the run was stopped and the fingers released before the links closed
    assert log.index(f"run {run_id} ended: stopped") < log.index("hand closed")
    store = RunStore(svc.db_path)
    try:
        run = store.run(run_id)
        assert run is not None and run["status"] == "stopped"
        phases = [e["detail"].get("phase") for e in store.events(run_id) if e["kind"] == "phase"]
        assert phases[-2:] == ["releasing", "stopped"]
    finally:
        store.close()


def test_unreachable_hand_and_taken_port_fail_with_a_reason(tmp_path: Path) -> None:
    import subprocess
    import sys

    base = [sys.executable, "-m", "sdh2svc", "serve", "--no-viewer",
            "--set", f"storage.db_path={json.dumps(str(tmp_path / 'r.sqlite'))}"]  # fmt: skip
    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        dead = free.getsockname()[1]  # nothing listens here once closed
    r = subprocess.run([*base, "--port", "0", "--sdh", f"socket://127.0.0.1:{dead}",
                        "--dsa", f"socket://127.0.0.1:{dead}"],
                       capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == 4 and "cannot open the hand" in r.stderr
    assert "Traceback" not in r.stderr
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([*base, "--sim", "--port", str(port)], capture_output=True, text=True,
                           timeout=60)  # fmt: skip
    assert r.returncode == 4 and f"cannot listen on 127.0.0.1:{port}" in r.stderr
