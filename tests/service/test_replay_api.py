"""The replay's routes in process (no hand, no browser): a run's tactile frames, paged; the 3-D
view's feed of a recorded iteration, and live again."""

from __future__ import annotations

import atexit
import base64
import functools
import json
import shutil
import tempfile
from collections.abc import AsyncIterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sdh2svc.client import AsyncClient
from sdh2svc.config import Settings, load_config
from sdh2svc.control.sample import Sample
from sdh2svc.model.hand import matrix_shapes
from sdh2svc.service.api.deps import Services
from sdh2svc.service.api.runs import SampleQuery, _frames_body, _samples_body, _truth_body
from sdh2svc.service.app import create_app
from sdh2svc.service.hub import TelemetryHub
from sdh2svc.service.replay_feed import Recorded, ReplayFeed
from sdh2svc.service.store import Recorder, RunStore
from sdh2svc.service.telemetry import (
    Pose,
    SampleMsg,
    Sim,
    Status,
    Tactile,
    frame_matrices,
    kind_of,
)

ITERATIONS = 12
TOKEN = "replay-test-token"


def sample(i: int) -> Sample:
    values: dict[str, Any] = dict.fromkeys(Sample.columns())
    values.update(iteration=i, t=0.02 * i, phi2=10.0 + i, phi3=20.0, phi4=30.0, phi5=40.0,
                  F1=1.0, F2=1.0, F=1.0, dF=0.0, Ay=20.0, Az=110.0, By=46.0, Bz=110.0,
                  direction=1, stroke=0, half_strokes=0, frame_age_ms=1.0, joint_age_ms=1.0,
                  latency_ms=1.0)  # fmt: skip
    return Sample(**values)


def texels(i: int, n: int) -> np.ndarray:
    return (np.arange(n, dtype=np.uint16) * (i + 1)) % 4096


class FakeView:
    """A view's replay feed, recording what reaches its store."""

    def __init__(self) -> None:
        self.kept: list[Any] = []
        self.replay = ReplayFeed(self.kept.append)


@pytest.fixture
def setup(tmp_path: Path) -> tuple[Settings, int, int]:
    cfg = load_config(overrides=[f"storage.db_path={tmp_path / 'runs.db'}",
                                 f"service.token={TOKEN}"], use_env=False)  # fmt: skip
    store = RunStore(cfg.storage.db_path)
    n = sum(r * c for r, c in matrix_shapes(cfg.tactile, cfg.axes))
    run_id = store.create_run({"params": {}})
    rec = Recorder(store.path, run_id)
    for i in range(ITERATIONS):
        s = sample(i)
        rec.sample(s)
        rec.frame(s.t, i, 1000 + i, texels(i, n))
        if i != 7:  # an iteration without truth
            rec.truth(i, s.t, (30.0, 120.0, 0.01 * i), True, False, False, 0)
    rec.frame(0.5, None, 5000, texels(99, n))  # a frame without an iteration: not listed
    rec.close()
    store.finish_run(run_id, "completed", {})
    store.close()
    return cfg, run_id, n


@pytest.fixture
async def client(setup: tuple[Settings, int, int]) -> AsyncIterator[tuple[httpx.AsyncClient, Any]]:
    cfg = setup[0]
    services = Services(cfg, TelemetryHub(), station=None)  # type: ignore[arg-type]
    services.viewer = FakeView()
    app = create_app(services)
    transport = httpx.ASGITransport(app=app)
    headers = {"Authorization": f"Bearer {TOKEN}"}
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1",
                                 headers=headers) as c:  # fmt: skip
        yield c, services


async def test_frames_paged_in_iteration_order(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any]
) -> None:
    cfg, run_id, n = setup
    c, _ = client
    got: list[dict[str, Any]] = []
    start: int | None = 0
    pages = 0
    while start is not None:
        r = await c.get(f"/api/runs/{run_id}/frames", params={"from": start, "limit": 5})
        assert r.status_code == 200, r.text
        page = r.json()
        assert page["total"] == ITERATIONS and page["encoding"] == "base64-u16le"
        assert [tuple(s) for s in page["shapes"]] == list(matrix_shapes(cfg.tactile, cfg.axes))
        got += page["frames"]
        start = page["next"]
        pages += 1
    assert pages == 3
    assert [f["iteration"] for f in got] == list(range(ITERATIONS))
    for f in got:
        counts = np.frombuffer(base64.b64decode(f["texels"]), "<u2")
        assert np.array_equal(counts, texels(f["iteration"], n))
        assert f["timestamp_ms"] == 1000 + f["iteration"]
        assert f["t"] == pytest.approx(0.02 * f["iteration"])
    # a window of iterations
    r = await c.get(f"/api/runs/{run_id}/frames", params={"from": 4, "to": 6})
    assert [f["iteration"] for f in r.json()["frames"]] == [4, 5, 6]
    assert r.json()["next"] is None and r.json()["from"] == 4


async def test_a_long_run_read_at_one_iteration_in_every_k(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any]
) -> None:
    """Samples, frames and truth keep the same iterations, counted from the run's first
    sample's; samples page by `next` as frames and truth do."""
    _, run_id, _ = setup
    c, _ = client
    base = f"/api/runs/{run_id}"
    r = await c.get(f"{base}/samples", params={"every": 3})
    page = r.json()
    assert [s["iteration"] for s in page["samples"]] == [0, 3, 6, 9]
    assert page["every"] == 3 and page["total"] == ITERATIONS and page["next"] is None
    r = await c.get(f"{base}/frames", params={"every": 3})
    assert [f["iteration"] for f in r.json()["frames"]] == [0, 3, 6, 9]
    r = await c.get(f"{base}/truth", params={"every": 2})
    assert [t["iteration"] for t in r.json()["truth"]] == [0, 2, 4, 6, 8, 10]
    # from a later iteration the phase stays the run's: 4, then the multiples of 3 after it
    r = await c.get(f"{base}/samples", params={"every": 3, "from": 4, "limit": 1})
    assert [s["iteration"] for s in r.json()["samples"]] == [6] and r.json()["next"] == 9
    r = await c.get(f"{base}/truth", params={"every": 7})
    assert [t["iteration"] for t in r.json()["truth"]] == [0]  # 7 has none recorded
    # paged by `next`, every sample once, in order
    got: list[int] = []
    first: int | None = 0
    while first is not None:
        page = (await c.get(f"{base}/samples", params={"from": first, "limit": 5})).json()
        got += [s["iteration"] for s in page["samples"]]
        first = page["next"]
    assert got == list(range(ITERATIONS))
    r = await c.get(f"{base}/samples", params={"from": 5, "offset": 2, "limit": 2})
    assert [s["iteration"] for s in r.json()["samples"]] == [7, 8] and r.json()["next"] == 9
    for bad in ({"every": 0}, {"every": 10_001}, {"every": "x"}, {"from": -1}):
        for route in ("samples", "frames", "truth"):
            if route != "samples" and "from" in bad:
                continue
            r = await c.get(f"{base}/{route}", params=bad)
            assert r.status_code == 422 and r.json()["details"], (route, bad, r.text)


GAPPY = [i for i in range(3, 64) if i not in (7, 8, 30)]  # a run that lost some rows
WITH_TRUTH = {i for i in GAPPY if i % 5 != 2}


@functools.cache
def gappy_run() -> tuple[Settings, int]:
    """A run of iterations 3 … 63 with three of them lost, frames for each, truth for most."""
    folder = tempfile.mkdtemp(prefix="sdh2svc-gappy-")
    atexit.register(shutil.rmtree, folder, True)
    db = Path(folder) / "runs.db"
    cfg = load_config(overrides=[f"storage.db_path={db}"], use_env=False)
    store = RunStore(db)
    n = sum(r * c for r, c in matrix_shapes(cfg.tactile, cfg.axes))
    run_id = store.create_run({"params": {}})
    rec = Recorder(db, run_id)
    for i in GAPPY:
        s = sample(i)
        rec.sample(s)
        rec.frame(s.t, i, i, texels(i, n))
        if i in WITH_TRUTH:
            rec.truth(i, s.t, (30.0, 120.0, 0.0), True, False, False, 0)
    rec.close()
    store.close()
    return cfg, run_id


def _pages(body: Any, *args: Any) -> list[int]:
    """The iterations of every page, following `next` from the first."""
    got: list[int] = []
    first: int | None = args[0]
    while first is not None:
        page = json.loads(body(first, *args[1:]).content)
        rows = page.get("samples", page.get("frames", page.get("truth")))
        assert len(rows) <= args[1]
        got += [r["iteration"] for r in rows]
        first = page["next"]
    return got


@settings(max_examples=60, deadline=None, derandomize=True, database=None)
@given(first=st.integers(0, 70), limit=st.integers(1, 9), every=st.integers(1, 12))
def test_pages_followed_by_next_read_each_kept_iteration_once(
    first: int, limit: int, every: int
) -> None:
    """Whatever the page size, start and `every`, following `next` reads each iteration from
    `from` on that `every` keeps (counted from the run's first sample's) exactly once, in
    order — samples, frames and truth alike, across the iterations the run lost."""
    cfg, run_id = gappy_run()
    kept = [i for i in GAPPY if i >= first and (i - GAPPY[0]) % every == 0]
    samples = _pages(lambda f, n: _samples_body(cfg, run_id, SampleQuery(f, 0, n, every), False),
                     first, limit)  # fmt: skip
    frames = _pages(lambda f, n: _frames_body(cfg, run_id, f, None, n, every), first, limit)
    truth = _pages(lambda f, n: _truth_body(cfg, run_id, f, n, every), first, limit)
    assert samples == frames == kept
    assert truth == [i for i in kept if i in WITH_TRUTH]


@pytest.fixture
async def api_client(client: tuple[httpx.AsyncClient, Any]) -> AsyncClient:
    """sdh2svc's own client on the app in process (no socket)."""
    ac = AsyncClient("http://127.0.0.1", token=TOKEN)
    await ac._http.aclose()
    ac._http = client[0]
    return ac


async def test_the_client_pages_samples_by_iteration(
    setup: tuple[Settings, int, int], api_client: AsyncClient
) -> None:
    ac = api_client
    every = [s["iteration"] async for s in ac.iter_samples(setup[1], page=5)]
    assert every == list(range(ITERATIONS))
    fifth = [s["iteration"] async for s in ac.iter_samples(setup[1], page=2, every=5)]
    assert fifth == [0, 5, 10]
    page = await ac.samples(setup[1], first=10, limit=5)
    assert [s["iteration"] for s in page["samples"]] == [10, 11] and page["next"] is None
    truth = await ac.truth(setup[1], every=4)
    assert [t["iteration"] for t in truth["truth"]] == [0, 4, 8]
    frames = await ac.frames(setup[1], 1, every=4)
    assert [f["iteration"] for f in frames["frames"]] == [4, 8]


async def test_the_client_reads_frames(
    setup: tuple[Settings, int, int], api_client: AsyncClient
) -> None:
    page = await api_client.frames(setup[1], 10, limit=5)
    assert [f["iteration"] for f in page["frames"]] == [10, 11] and page["next"] is None


async def test_frames_404_and_422(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any]
) -> None:
    c, _ = client
    r = await c.get("/api/runs/999/frames")
    assert r.status_code == 404 and "no run 999" in r.json()["error"]
    for bad in ({"limit": 0}, {"limit": 2001}, {"from": -1}, {"from": 5, "to": 4},
                {"from": "x"}):  # fmt: skip
        r = await c.get(f"/api/runs/{setup[1]}/frames", params=bad)
        assert r.status_code == 422, (bad, r.text)
        assert r.json()["details"], bad
    r = await c.get("/api/runs/0/frames")
    assert r.status_code == 422


async def test_frames_are_in_the_openapi_with_models(client: tuple[Any, Any]) -> None:
    c, _ = client
    doc = (await c.get("/openapi.json")).json()
    ok = doc["paths"]["/api/runs/{run_id}/frames"]["get"]["responses"]["200"]
    assert ok["content"]["application/json"]["schema"]["$ref"].endswith("/FramePage")
    frame = doc["components"]["schemas"]["RecordedFrame"]["properties"]
    assert "base64" in frame["texels"]["description"]
    expect = {
        ("get", "/api/runs/{run_id}/frames"): {200, 400, 404, 409, 422, 503},
        ("put", "/api/viewer/replay"): {200, 400, 401, 403, 404, 409, 413, 415, 422, 503},
        ("delete", "/api/viewer/replay"): {200, 400, 401, 403, 409, 413, 415, 422},
    }
    for (method, path), codes in expect.items():
        responses = doc["paths"][path][method]["responses"]
        assert {int(k) for k in responses} == codes, (method, path)
        for code, resp in responses.items():
            schema = resp["content"]["application/json"]["schema"]
            ok = "/FramePage" if method == "get" else "/ReplayShown"
            assert schema["$ref"].endswith("/ErrorBody" if int(code) >= 400 else ok)


def test_frames_split_as_the_live_matrices(cfg: Settings) -> None:
    shapes = matrix_shapes(cfg.tactile, cfg.axes)
    ax = cfg.axes
    for pad in ("finger1", "thumb", "finger2"):
        assert shapes[getattr(ax, f"{pad}_proximal_matrix")] == (14, 6)
        assert shapes[getattr(ax, f"{pad}_distal_matrix")] == (13, 6)
    mats = frame_matrices(np.arange(486), shapes)
    assert [m.shape for m in mats] == list(shapes)
    assert mats[0][1, 0] == 6 and mats[1][0, 0] == shapes[0][0] * shapes[0][1]
    with pytest.raises(ValueError, match="485 texels"):
        frame_matrices(np.arange(485), shapes)


async def test_replay_feed_shows_a_recorded_iteration_then_live(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any]
) -> None:
    cfg, run_id, n = setup
    c, services = client
    view: FakeView = services.viewer
    live_status = Status({"run": None, "estopped": False})
    view.replay.live(live_status)
    r = await c.put("/api/viewer/replay", json={"run_id": run_id, "iteration": 7})
    assert r.status_code == 200, r.text
    assert r.json()["replay"] == {"run_id": run_id, "iteration": 7, "t": pytest.approx(0.14)}
    kinds = [kind_of(m) for m in view.kept]
    assert kinds == ["status", "pose", "sample", "tactile", "sim", "status"]
    pose, s, tac, sim, st = view.kept[1:]
    # φ2…φ5 the sample's; φ1 and the thumb as the run held them (its pre-shape), not the live
    # hand's: a sample does not carry them
    assert isinstance(pose, Pose)
    ax, pre, rec = cfg.axes, cfg.run.preshape_deg, sample(7)
    for name in ("phi1", "thumb_proximal", "thumb_distal"):
        assert pose.angles_deg[getattr(ax, name)] == pre[getattr(ax, name)]
    for name in ("phi2", "phi3", "phi4", "phi5"):
        assert pose.angles_deg[getattr(ax, name)] == getattr(rec, name)
    assert isinstance(s, SampleMsg) and s.sample == sample(7) and s.run_id == run_id
    assert s.view is not None and s.view.phi_deg[0] == 17.0 and s.view.A is not None
    shapes = matrix_shapes(cfg.tactile, cfg.axes)
    assert isinstance(tac, Tactile)
    want = frame_matrices(texels(7, n), shapes)
    assert all(np.array_equal(a, b) for a, b in zip(tac.matrices, want, strict=True))
    assert sim == Sim({})
    assert st.status["replay"]["iteration"] == 7
    # live messages wait; the status goes on, saying what is shown
    view.kept.clear()
    live = SampleMsg(None, sample(300))
    view.replay.live(live)
    view.replay.live(live_status)
    assert [kind_of(m) for m in view.kept] == ["status"]
    assert view.kept[0].status["replay"]["run_id"] == run_id
    # live again: the latest live messages come back
    view.kept.clear()
    r = await c.request("DELETE", "/api/viewer/replay", json={})
    assert r.status_code == 200 and r.json()["replay"] is None
    assert view.kept == [live, live_status]
    assert view.replay.showing is None


async def test_replay_feed_refusals(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any]
) -> None:
    c, services = client
    run_id = setup[1]
    r = await c.put("/api/viewer/replay", json={"run_id": run_id, "iteration": 500})
    assert r.status_code == 404 and "no iteration 500" in r.json()["error"]
    r = await c.put("/api/viewer/replay", json={"run_id": 77, "iteration": 1})
    assert r.status_code == 404
    r = await c.put("/api/viewer/replay", json={"run_id": run_id, "iteration": -1})
    assert r.status_code == 422
    r = await c.put("/api/viewer/replay", json={"run_id": run_id, "iteration": 1},
                    headers={"Authorization": ""})  # fmt: skip
    assert r.status_code == 401
    services.viewer = None
    r = await c.put("/api/viewer/replay", json={"run_id": run_id, "iteration": 1})
    assert r.status_code == 409 and "3-D view is off" in r.json()["error"]


async def test_replay_feed_goes_live_without_news() -> None:
    kept: list[Any] = []
    feed = ReplayFeed(kept.append, ttl_s=0.0)
    live = SampleMsg(None, sample(1))
    feed.live(live)
    rec_msgs = (SampleMsg(3, sample(2)),)
    feed.show(Recorded(3, 2, 0.04, rec_msgs))
    assert feed.showing is not None
    assert feed._timer is not None
    feed._timer._run()  # the timer's moment (ttl 0): no sleeping on a clock
    assert feed.showing is None and kept[-1] is live


async def test_the_runs_recognition_in_its_summary_and_samples(
    setup: tuple[Settings, int, int], client: tuple[httpx.AsyncClient, Any],
    monkeypatch: pytest.MonkeyPatch,
) -> None:  # fmt: skip
    """GET /api/runs/{id} gives the summary's recognition (documented: RunDetail → RunSummary →
    RecognitionSummary); the samples, with ``outline=true``, their reconstructed outlines."""
    from sdh2svc.service import telemetry

    cfg, run_id, _ = setup
    c, _ = client
    rec = {"object_class": "ellipse", "confidence": 0.9, "size_a_mm": 30.0, "size_b_mm": 20.0,
           "rotation_deg": 41.5, "contacts": {"flat": 0.0, "edge": 0.1, "curved": 0.9}}  # fmt: skip
    store = RunStore(cfg.storage.db_path)
    store.finish_run(run_id, "completed", {"status": "completed", "recognition": rec})
    recorder = Recorder(store.path, run_id)
    recorder.sample(replace(sample(ITERATIONS), object_class="ellipse", size_a=30.0,
                            size_b=20.0, rotation_est=41.5))  # fmt: skip
    recorder.close()
    store.close()
    r = await c.get(f"/api/runs/{run_id}")
    assert r.status_code == 200 and r.json()["summary"]["recognition"] == rec

    plain = (await c.get(f"/api/runs/{run_id}/samples")).json()["samples"]
    assert "estimate_outline" not in plain[0]
    asked = {"outline": "true", "limit": 100}
    page = (await c.get(f"/api/runs/{run_id}/samples", params=asked)).json()
    outlines = [s["estimate_outline"] for s in page["samples"]]
    assert outlines[:ITERATIONS] == [[]] * ITERATIONS  # no class: nothing reconstructed
    # (made in a read process: as the live message would make it from the same sample)
    assert outlines[ITERATIONS] == telemetry.estimate_outline(plain[ITERATIONS]).tolist()
    assert len(outlines[ITERATIONS]) > 3
    r = await c.get(f"/api/runs/{run_id}/samples", params={**asked, "limit": 101})
    assert r.status_code == 422 and "at most 100" in r.json()["details"][0]
    # the flag alone: its own default page (100), not the plain one's 1000 and a 422
    alone = await c.get(f"/api/runs/{run_id}/samples", params={"outline": "true"})
    assert alone.status_code == 200 and alone.json()["limit"] == 100, alone.text
    assert alone.json()["samples"] == page["samples"]
    assert (await c.get(f"/api/runs/{run_id}/samples")).json()["limit"] == 1000

    doc = (await c.get("/openapi.json")).json()
    ok = doc["paths"]["/api/runs/{run_id}"]["get"]["responses"]["200"]
    assert ok["content"]["application/json"]["schema"]["$ref"].endswith("/RunDetail")
    schemas = doc["components"]["schemas"]
    assert set(rec) <= set(schemas["RecognitionSummary"]["properties"])
    assert "recognition" in schemas["RunSummary"]["properties"]
