"""The REST/WebSocket API against a real ``sdh2svc serve --sim`` (uvicorn, sockets, SQLite)."""

from __future__ import annotations

import asyncio
import contextlib
import csv
import functools
import io
import itertools
import json
import re
import socket
import time
from collections.abc import AsyncIterator, Callable, Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import httpx
import pytest
from mcap_check import read

from sdh2svc.client import (
    AsyncClient,
    AsyncTelemetry,
    Conflict,
    InvalidRequest,
    NotFound,
    Unauthorized,
)
from sdh2svc.config import load_config
from sdh2svc.service.store import RunStore
from tests.live_service import LiveService, service_command, start_run, start_service
from tests.service.conftest import PATIENT

RUN_TIMEOUT_S = 120.0


@pytest.fixture(scope="module")
def svc(
    tmp_path_factory: pytest.TempPathFactory, long_runs: tuple[str, ...]
) -> Iterator[LiveService]:
    s = start_service(tmp_path_factory.mktemp("api"), viewer=False, extra=(*long_runs, *PATIENT))
    try:
        yield s
    finally:
        assert s.stop() == 0, "".join(s.log)


class Telemetry:
    """Everything one telemetry client receives, collected in the background."""

    def __init__(self, tm: AsyncTelemetry) -> None:
        self.messages: list[dict[str, Any]] = []
        self._task = asyncio.create_task(self._collect(tm))

    async def _collect(self, tm: AsyncTelemetry) -> None:
        with contextlib.suppress(Exception):
            async for msg in tm:
                self.messages.append(msg)

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
async def telemetry(
    c: AsyncClient, decimate: int = 1, tactile: bool = True
) -> AsyncIterator[Telemetry]:
    async with c.telemetry(decimate=decimate, tactile=tactile) as tm:
        t = Telemetry(tm)
        yield t
        t._task.cancel()


async def wait_run_end(c: AsyncClient, run_id: int) -> dict[str, Any]:
    """The status once the run has ended."""
    await c.wait_run(run_id, timeout=RUN_TIMEOUT_S)
    return await c.status()


async def test_status_and_clear_errors(svc: LiveService) -> None:
    async with svc.client() as c:
        st = await c.status()
        assert st["sim"] is True and st["auth_required"] is False
        assert st["hand"]["connected"] == {"joints": True, "tactile": True}
        assert st["links"]["tactile"]["connected"] is True
        assert st["object"]["kind"] in {"ellipse", "box", "circle", "stick", "polygon"}

        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"k": 0.5})
        assert bad.value.status == 422 and bad.value.error == "invalid rolling parameters"
        assert any(d.startswith("k = 0.5") and "1.0 < k ≤ 10.0" in d for d in bad.value.details)
        with pytest.raises(InvalidRequest, match="must not be 0"):
            await c.patch_params({"delta_phi_deg": 0})
        with pytest.raises(InvalidRequest, match=r"at least 0\.01° either way"):
            await c.patch_params({"delta_phi_deg": 1e-300})  # a run that would never move
        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"no_such": 1})
        assert bad.value.status == 422 and "no_such" in bad.value.details[0]
        # no parameter loosens a safety limit: an Fd whose ceiling the maximum would cut (at 50
        # the ceiling was 150, above any pad's reading), steps the step limit would clip
        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"grasp_force": 50.0, "finger1_max_step_deg": 10.0})
        assert bad.value.details[0].startswith("grasp_force = 50: its ceiling")
        assert "safety.force_ceiling_max = 12" in bad.value.details[0]
        top = re.search(r"allowed: grasp_force ≤ ([0-9.]+)", bad.value.details[0])
        assert top is not None
        assert bad.value.details[1].startswith("finger1_max_step_deg = 10: above")
        # the range quoted is the one the limits allow, and every bad field is in one answer
        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"grasp_force": 60.0})
        assert bad.value.details == [
            f"grasp_force = 60.0: Input should be less than or equal "
            f"to {top[1]} (allowed: 0.0 < grasp_force ≤ {top[1]})"
        ]
        with pytest.raises(InvalidRequest) as bad:
            await c.patch_params({"k": 0.5, "grasp_force": 5.0})
        assert [d.split(":")[0] for d in bad.value.details] == ["k = 0.5", "grasp_force = 5"]
        with pytest.raises(InvalidRequest, match="force_ceiling_max"):
            await c.start_run({"grasp_force": 4.5})
        assert (await c.params())["k"] == 2.0  # nothing half-applied
        assert (await c.params())["grasp_force"] == 2.0

        with pytest.raises(Conflict) as none:
            await c.stop_run()
        assert none.value.status == 409 and none.value.error == "no run is running"
        with pytest.raises(NotFound, match="no run 9999"):
            await c.run(9999)
        with pytest.raises(InvalidRequest) as bad:
            await c.samples(1, limit=0)
        assert bad.value.status == 422 and "limit" in bad.value.details[0]
        with pytest.raises(InvalidRequest, match="teapot"):
            await c.set_sim_object(name="teapot")
        with pytest.raises(InvalidRequest) as bad:
            await c.set_sim_object(spec={"kind": "circle", "diameter_mm": -3})
        assert any("diameter_mm" in d for d in bad.value.details)
        async with httpx.AsyncClient(base_url=svc.url, headers=svc.headers()) as raw:
            # GET's {"object": …} put back as it came: the answer names the fields there are
            r = await raw.put("/api/sim/object", json={"object": {"kind": "circle"}})
        assert r.status_code == 422
        assert r.json()["details"] == ["body.object: unknown key (the keys there are: name, spec)"]
        with pytest.raises(InvalidRequest) as bad:
            await c.start_run({"alpha_deg": 90})
        assert "alpha_deg" in bad.value.details[0]
        assert (await c.status())["run"] is None  # the refused run never started

        got = await c.set_sim_object(name="rubber")
        assert got["object"]["name"] == "rubber" and "egg" in got["presets"]
        assert (await c.sim_object())["object"]["name"] == "rubber"
        schema = await c.params_schema()
        assert schema["properties"]["k"]["exclusiveMinimum"] == 1.0
        # the ranges this service's safety limits allow, not the fields' own (50 and 10)
        limits = (await c.config())["safety"]
        top = limits["force_ceiling_max"] / limits["force_ceiling_factor"]
        assert schema["properties"]["grasp_force"]["maximum"] == top < 50.0
        assert schema["properties"]["finger1_max_step_deg"]["maximum"] == limits["max_step_deg"]
        fd = (await c.params())["grasp_force"]
        assert (await c.patch_params({"grasp_force": top}))["grasp_force"] == top
        with pytest.raises(InvalidRequest):
            await c.patch_params({"grasp_force": top * 1.001})
        await c.patch_params({"grasp_force": fd})  # the module's service, as it was
        assert (await c.viewer()) == {"url": None}
    async with httpx.AsyncClient(base_url=svc.url) as browser:  # a page, not the API
        assert (await browser.get("/docs")).status_code == 200


def assert_steps(samples: list[dict], dphi: float) -> None:
    """Finger 2's steps |φ4 − φ4d|: never beyond Δφ, and the full Δφ in most iterations."""
    steps = [abs(s["phi4"] - s["phi4_d"]) for s in samples]
    assert steps and max(steps) < dphi + 1e-6, steps
    assert sum(abs(st - dphi) < 1e-6 for st in steps) >= 0.8 * len(steps), steps


async def test_run_observed_params_changed_mid_run_stopped_exported(svc: LiveService) -> None:
    async with svc.client() as c, telemetry(c) as tm, telemetry(c, decimate=3) as tm3:
        await tm.until(lambda: tm.of("hello"))
        slow = {"cycles": 50, "delta_phi_deg": 0.05}  # Finger 1 within its step: Δφ in full
        run_id = (await start_run(c, slow, "egg"))["run_id"]
        with pytest.raises(Conflict, match="already running"):
            await c.start_run()
        with pytest.raises(Conflict):
            await c.set_sim_object(name="egg")
        with pytest.raises(Conflict, match=f"run {run_id} is being recorded"):
            await c.delete_run(run_id)

        # rolling: Finger 2 steps Δφ = 0.05° per iteration (φ4 − φ4d), less where Finger 1's
        # step limit slows an iteration down
        await tm.until(lambda: len(tm.samples(run_id)) >= 15)
        before = [s for s in tm.samples(run_id) if s["phi4_d"] is not None]
        assert_steps(before, 0.05)
        assert (await c.patch_params({"delta_phi_deg": 0.08}))["delta_phi_deg"] == 0.08
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

        st = await c.status()
        assert st["run"]["id"] == run_id and st["run"]["state"] == "rolling"
        assert st["run"]["strokes_total"] == 50
        assert st["links"]["tactile"]["frames_per_s"] > 5
        assert (await c.stop_run())["run_id"] == run_id  # 202: it stops and releases
        st = await wait_run_end(c, run_id)
        assert st["last_run"]["status"] == "stopped"
        assert st["run"]["state"] == "stopped"
        await c.patch_params({"delta_phi_deg": 0.25})

        # the record: every sample the clients saw is in the database, the exports parse
        seen = tm.samples(run_id)
        page = await c.samples(run_id, limit=10000)
        assert page["total"] == len(page["samples"]) >= len(seen) > 0
        by_iter = {s["iteration"]: s for s in page["samples"]}
        for s in seen:
            assert by_iter[s["iteration"]]["F"] == pytest.approx(s["F"])
        half = await c.samples(run_id, offset=5, limit=3)
        assert [s["iteration"] for s in half["samples"]] == \
            [s["iteration"] for s in page["samples"][5:8]]  # fmt: skip
        run = await c.run(run_id)
        assert run["status"] == "stopped" and run["meta"]["object"]["name"] == "egg"
        # the recognition's estimate: in every sample (its outline with the live ones), the
        # summary, and the end event
        assert all(s["rotation_est"] is not None and isinstance(s["estimate_outline"], list)
                   for s in seen)  # fmt: skip
        rec = run["summary"]["recognition"]
        assert rec["object_class"] == page["samples"][-1]["object_class"]
        assert run["events"][-1]["detail"]["recognition"] == rec
        kinds = [e["kind"] for e in run["events"]]
        assert "params" in kinds and "grasped" in kinds and kinds[-1] == "end"

        text = (await c.export_bytes(run_id, "csv")).decode()
        rows = list(csv.DictReader(io.StringIO(text)))
        assert len(rows) == page["total"]
        assert float(rows[0]["F [library force units]"]) == page["samples"][0]["F"]
        got = read(await c.export_bytes(run_id, "mcap"))  # every message valid (mcap_check)
        assert len(got.messages["/samples"]) == page["total"]
        assert len(got.messages["/tf"]) == len(got.messages["/scene"]) - 1 == page["total"]  # + end
        assert got.messages["/tactile/finger1_distal"] and got.messages["/events"]
        with pytest.raises(InvalidRequest):
            await c.export_bytes(run_id, "xls")  # type: ignore[arg-type]
        async with httpx.AsyncClient(base_url=svc.url) as browser:  # the download, as a file
            r = await browser.get(f"/api/runs/{run_id}/export", params={"format": "csv"})
            assert "attachment" in r.headers["content-disposition"] and r.text == text

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

        # the run history a page at a time, following the Link header: every run, once
        every_run = [r["id"] for r in await c.runs(limit=1000)]
        assert every_run[0] == run_id
        paged, url = [], "/api/runs?limit=1"
        async with httpx.AsyncClient(base_url=svc.url) as raw:
            while url:
                r = await raw.get(url)
                assert int(r.headers["x-total-count"]) == len(every_run)
                paged += [x["id"] for x in r.json()]
                link = r.headers.get("link")
                url = link.split(">")[0].lstrip("<") if link else ""
        assert paged == every_run
        # … then the run deleted, with everything recorded with it
        assert await c.delete_run(run_id) == {"deleted": run_id}
        for gone in (c.run, c.samples, c.truth, c.delete_run):
            with pytest.raises(NotFound, match=f"no run {run_id}"):
                await gone(run_id)
        assert [r["id"] for r in await c.runs()] == every_run[1:]


async def test_estop_mid_run_and_release(svc: LiveService) -> None:
    async with svc.client() as c, telemetry(c, tactile=False) as tm:
        slow = {"cycles": 50, "delta_phi_deg": 0.05}  # Finger 1 within its step: Δφ in full
        run_id = (await start_run(c, slow, "egg"))["run_id"]
        await tm.until(lambda: tm.samples(run_id))
        # answered while the run goes on, not behind it: this run takes many minutes, and
        # the client gives up on an answer after 30 s
        assert (await c.estop())["estopped"] is True
        st = await wait_run_end(c, run_id)
        assert st["estopped"] is True and st["run"]["state"] == "e-stopped"
        assert st["last_run"]["status"] == "e-stopped"
        # published before the run's end, delivered on the WebSocket within tens of ms: the
        # REST status may say so first
        await tm.until(lambda: tm.events(run_id, "estop"))
        n = len(tm.samples(run_id))
        with pytest.raises(Conflict, match="e-stop is latched"):
            await c.start_run()
        with pytest.raises(InvalidRequest, match="k = 0"):  # the request's own fault first
            await c.start_run({"k": 0})
        # e-stop while idle works too, and the hand stays where it stopped
        assert (await c.estop())["estopped"] is True
        await asyncio.sleep(0.6)  # the angles shown between runs are polled at 5 Hz
        a1 = (await c.status())["hand"]["angles_deg"]
        await asyncio.sleep(1.0)
        a2 = (await c.status())["hand"]["angles_deg"]
        assert a1 == a2
        assert len(tm.samples(run_id)) == n  # no iteration after the e-stop
        assert (await c.release_estop()) == {"estopped": False}
        assert (await c.status())["estopped"] is False
        recorded = await c.run(run_id)
        assert recorded["status"] == "e-stopped"
        # the record has the e-stop's events, as telemetry had them, and the run's end
        kinds = [(e["kind"], e["detail"].get("phase") or e["detail"].get("status"))
                 for e in recorded["events"]]  # fmt: skip
        assert kinds[-3:] == [("phase", "e-stopped"), ("estop", None), ("end", "e-stopped")]


async def test_the_object_stays_while_the_estop_is_latched(svc: LiveService) -> None:
    """With the hand e-stopped nothing changes its world: PUT /api/sim/object is refused (409,
    as a start or an opening is), the object stays; after the release it changes again."""
    async with svc.client() as c, httpx.AsyncClient(base_url=svc.url, headers=svc.headers()) as raw:
        info = await c.sim_object()
        before = info["object"]
        other = "cylinder" if before["name"] != "cylinder" else "egg"
        assert (await c.estop())["estopped"] is True
        try:
            r = await raw.put("/api/sim/object", json={"name": other})
            assert r.status_code == 409, r.text
            assert r.json() == {"error": "the e-stop is latched: release it first "
                                "(POST /api/estop/release)", "details": []}  # fmt: skip
            with pytest.raises(Conflict, match="e-stop is latched"):  # a spec the same
                await c.set_sim_object(spec={"kind": "circle", "diameter_mm": 40, "depth_mm": 30})
            assert (await c.sim_object())["object"] == before
            assert (await c.status())["object"] == before
        finally:
            assert (await c.release_estop()) == {"estopped": False}
        assert (await c.set_sim_object(other))["object"]["name"] == other
        # as it was, for the module's other tests
        if before["name"] in info["presets"]:
            await c.set_sim_object(before["name"])
        else:
            await c.set_sim_object(spec=before)


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
        async with AsyncClient(url) as anon, AsyncClient(url, token="wrong") as wrong:
            assert (await anon.status())["auth_required"] is True
            for who in (anon, wrong):
                for command in (
                    functools.partial(who.patch_params, {"k": 3}),
                    who.start_run,
                    who.stop_run,
                    who.release_estop,
                    who.open_hand,
                    functools.partial(who.set_sim_object, name="egg"),
                    functools.partial(who.delete_run, 1),
                ):
                    with pytest.raises(Unauthorized, match="bearer token"):
                        await command()
        async with httpx.AsyncClient(base_url=url, timeout=30) as raw:
            # stopping needs no token (nor JSON, nor an Origin of its own)
            r = await raw.post("/api/estop", headers={"Origin": "http://evil.example"})
            assert r.status_code == 200 and r.json()["estopped"] is True
            r = await raw.post("/api/estop/")  # a trailing slash: answered, not redirected
            assert r.status_code == 200 and r.json()["estopped"] is True
            for query in ("?source=pendant", "/?_=1733500000000"):  # nor a query of its own
                r = await raw.post(f"/api/estop{query}")
                assert r.status_code == 200 and r.json()["estopped"] is True, r.text
            # the scheme's name in any case; a command with a query parameter it does not
            # take is refused (FastAPI would ignore it: a misspelt one would do the default)
            r = await raw.post("/api/runs/stop?now=1", json={},
                               headers={"Authorization": "bearer s3cret"})  # fmt: skip
            said = "query.now = '1': no such query parameter"
            assert r.status_code == 422 and said in r.text, r.text
            # with the token too, a command must be JSON; and a huge body is refused before the
            # token is even looked at
            text = {"Authorization": "Bearer s3cret", "Content-Type": "text/plain"}
            r = await raw.post("/api/runs/stop", headers=text)
            assert r.status_code == 415
        head = (
            f"PATCH /api/params HTTP/1.1\r\nHost: 127.0.0.1:{host.port}\r\n"
            f"Content-Type: application/json\r\nContent-Length: {300 * 2**20}\r\n\r\n"
        )
        with socket.create_connection(("127.0.0.1", host.port), timeout=10) as sock:
            sock.sendall(head.encode())  # and no body: it is refused before it is read
            assert sock.recv(64).startswith(b"HTTP/1.1 413")
        async with AsyncClient(url, token="s3cret") as c:  # releasing needs the token
            assert (await c.release_estop()) == {"estopped": False}
            assert (await c.patch_params({"k": 3}))["k"] == 3
            assert (await c.params())["k"] == 3
            conf = await c.config()
            assert conf["service"]["token"] == "***" and "s3cret" not in json.dumps(conf)
            assert conf["hand"]["pad"]["arc_radius_mm"] == 60.0 and conf["axes"]["phi4"] == 5
            # what is in force, not what the service started with: the patched k, the lines
            # of the simulated hand (the configuration's are a real hand's /dev/ttyS*)
            assert conf["rolling"]["k"] == 3
            status = await c.status()
            assert conf["links"]["sdh_url"] == status["links"]["sdh_url"] != "/dev/ttyS0"
            assert (await c.viewer()) == {"url": None}
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


def _read_to_the_end(sock: socket.socket, limit_s: float = 60.0) -> bytes:
    """What a stalled client finds once it reads again: the frames the service had sent it,
    up to the close frame and the end of the connection (``limit_s``: a deadline to give up)."""
    sock.settimeout(limit_s)
    data = bytearray()
    while chunk := sock.recv(65536):
        data += chunk
    return bytes(data[-4096:])


async def _told_once_cut(c: AsyncClient, n: int, sock: socket.socket) -> tuple[int, bytes]:
    """How many stalled clients were cut off, once it is ``n``, and what ``sock`` found then."""
    cut = await _cut_off(c, n)
    return cut, await asyncio.to_thread(_read_to_the_end, sock)


async def _cut_off(c: AsyncClient, n: int, limit_s: float = RUN_TIMEOUT_S) -> int:
    """How many stalled telemetry clients the service has cut off, once it is ``n`` (the pads
    stream on between runs, so a stalled client's buffers keep filling until its send times out:
    when that happens depends on the buffers and the machine, not on the run)."""
    give_up = time.monotonic() + limit_s
    while (cut := (await c.status())["telemetry"]["disconnected_slow"]) < n:
        if time.monotonic() > give_up:
            break
        await asyncio.sleep(0.2)
    return int(cut)


async def test_stalled_client_does_not_slow_the_loop(svc: LiveService) -> None:
    """One client never reads: it is dropped; the loop and a normal client lose nothing."""
    async with svc.client() as c:
        stalled = [_stalled_client(svc.ws_url) for _ in range(3)]
        try:
            # what the first one is told is read once all are cut (during the run: a stalled
            # client's close frame outlives the connection's keep-alive only so long)
            told = asyncio.create_task(_told_once_cut(c, 3, stalled[0]))
            async with telemetry(c) as tm:
                summary = await _one_stroke_run(c)
                run_id = summary["run_id"]
            samples = tm.samples(run_id)
            cut, told_them = await told
        finally:
            told.cancel()  # (the test failed before it was read)
            for s in stalled:
                s.close()
    assert summary["status"] == "completed", summary
    # the stalled clients were cut off after the send timeout, and told why (close 1008) …
    assert cut >= 3
    assert b"\x03\xf0too slow: took no message for" in told_them
    # … the reading client got every iteration, in order, none dropped
    assert [s["iteration"] for s in samples] == list(range(1, summary["iterations"] + 1))
    assert not tm.of("dropped")
    # … and the loop was never held up for the send timeout: a blocked event loop brings the
    # rate under half the frame rate (the simulated pads run on the same loop: blocked, they
    # send fewer frames; ≈ 29 Hz measured beside 4 busy loops, 8 Hz with the loop blocked
    # 0.1 s per sample). How many frames a loaded machine leaves unused (`frames_skipped`: 0–7
    # of ≈ 300 quiet, 36 once beside a browser test and an audit at load 5) is the machine's
    # pace, not the clients': bench/service.py measures it, with and without clients
    rate = load_config(use_env=False).run.tactile_rate_hz
    assert summary["loop_hz"] >= 0.5 * rate, summary


async def _one_stroke_run(c: AsyncClient) -> dict[str, Any]:
    run_id = (await start_run(c, {"cycles": 1}, "egg"))["run_id"]
    await c.wait_run(run_id, timeout=RUN_TIMEOUT_S)
    summary: dict[str, Any] = (await c.run(run_id))["summary"]
    return summary


async def test_sigterm_mid_run_stops_motion_then_exits_cleanly(
    tmp_path: Path, long_runs: tuple[str, ...]
) -> None:
    extra = (*long_runs, *PATIENT)
    svc = await asyncio.to_thread(start_service, tmp_path, viewer=False, extra=extra)
    try:
        async with svc.client() as c:
            run_id = (await start_run(c, {"cycles": 50}, "egg"))["run_id"]
            # mid-grasp: the fingers close on the object (a stop while rolling takes the same
            # path, later)
            await c.wait_status(lambda st: (st.get("run") or {}).get("state") == "grasping")
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
        assert run["summary"]["message"] == "as the service shut down"  # (it said nothing)
        phases = [e["detail"].get("phase") for e in store.events(run_id) if e["kind"] == "phase"]
        assert phases[-2:] == ["releasing", "stopped"]
    finally:
        store.close()


def test_unreachable_hand_waits_and_taken_port_fails_with_a_reason(tmp_path: Path) -> None:
    """A real hand nobody answers for: the service comes up anyway and says why each line is
    down (it exited 4, taking the dashboard and the e-stop with it); a taken HTTP port is still
    refused at once."""
    import subprocess
    import sys

    with socket.socket() as free:
        free.bind(("127.0.0.1", 0))
        dead = free.getsockname()[1]  # nothing listens here once closed
    waiting = start_service(tmp_path, viewer=False, sim=False, wait_hand=False, extra=(
        "--sdh", f"socket://127.0.0.1:{dead}", "--dsa", "socket://127.0.0.1:1"))  # fmt: skip
    try:
        with waiting.sync_client() as c:
            st = c.status()
    finally:
        assert waiting.stop() == 0, "".join(waiting.log)
    assert st["hand"]["connected"] == {"joints": False, "tactile": False}
    assert st["links"]["joints_down"] in ("connecting",) or "refused" in st["links"]["joints_down"]
    assert "Traceback" not in "".join(waiting.log)
    base = [sys.executable, "-m", "sdh2svc", "serve", "--no-viewer",
            "--set", f"storage.db_path={json.dumps(str(tmp_path / 'r.sqlite'))}"]  # fmt: skip
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        r = subprocess.run([*base, "--sim", "--port", str(port)], capture_output=True, text=True,
                           timeout=60)  # fmt: skip
    assert r.returncode == 4 and f"cannot listen on 127.0.0.1:{port}" in r.stderr
