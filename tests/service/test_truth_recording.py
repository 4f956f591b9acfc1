"""The simulated object's truth in a recording: per iteration in the store, in the MCAP's /scene,
in a replayed iteration's ``sim`` message — and none on a real hand or in an older database."""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import sqlite3
from pathlib import Path
from typing import Any

import httpx
import pytest
from mcap_check import read
from test_store import _samples

from sdh2svc import __version__
from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Bench, Simulated
from sdh2svc.control.observer import BaseObserver, Event, EventKind
from sdh2svc.control.sample import Sample
from sdh2svc.model.hand import matrix_shapes
from sdh2svc.provenance import code_version
from sdh2svc.service import headless
from sdh2svc.service.api.deps import Services
from sdh2svc.service.app import create_app
from sdh2svc.service.hub import TelemetryHub
from sdh2svc.service.recording import RecordedRun
from sdh2svc.service.replay_feed import recorded_iteration
from sdh2svc.service.store import SCHEMA, TRUTH_COLUMNS, Recorder, RunStore
from sdh2svc.service.telemetry import OUTLINE_POINTS, Sim, Tactile, recorded_truth
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.hand import Truth


class Probe(BaseObserver):
    """What the bench says at every sample (read without stepping the physics), and the truth
    once the run has ended."""

    def __init__(self, bench: Bench | None) -> None:
        assert bench is not None
        self.bench = bench
        self.poses: dict[int, tuple[float, float, float]] = {}
        self.end: Truth | None = None

    def sample(self, s: Sample) -> None:
        self.poses[s.iteration] = self.bench.object_pose()

    def event(self, e: Event) -> None:
        if e.kind is EventKind.END:
            self.end = self.bench.truth()


@dataclasses.dataclass
class SimRun:
    cfg: Settings
    summary: dict[str, Any]
    probe: Probe


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory: pytest.TempPathFactory) -> SimRun:
    """One short simulated run on the virtual clock (≈ 1 s): one cycle on the rubber ball."""
    db = tmp_path_factory.mktemp("truth") / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'", "rolling.cycles=1",
                                 "sim.object='rubber'"], use_env=False)  # fmt: skip
    probes: list[Probe] = []

    def observer(bench: Bench | None) -> Probe:
        probes.append(Probe(bench))
        return probes[-1]

    summary = run_fast(headless.run_once(cfg, Simulated(fast=True), observer=observer))
    assert summary["status"] == "completed" and summary["iterations"] > 50
    return SimRun(cfg, summary, probes[0])


def _store(run: SimRun) -> RunStore:
    return RunStore(run.cfg.storage.db_path, create=False)


def test_the_truth_of_every_iteration_is_the_benchs(sim_run: SimRun) -> None:
    store = _store(sim_run)
    run_id = sim_run.summary["run_id"]
    try:
        rows, outline = store.truth(run_id), store.outline(run_id)
        samples = store.samples(run_id, 0, 10**6)
    finally:
        store.close()
    assert [r["iteration"] for r in rows] == [s["iteration"] for s in samples]
    assert [r["t"] for r in rows] == [s["t"] for s in samples]
    probe = sim_run.probe
    assert {r["iteration"]: (r["y"], r["z"], r["psi"]) for r in rows} == probe.poses  # exactly
    assert all(r["held"] and not r["in_fixture"] and not r["dropped"] for r in rows)
    truth = sim_run.summary["truth"]
    assert (rows[-1]["dropped"], rows[-1]["slips"]) == (truth["dropped"], truth["slips"])
    # the outline once, in the object's frame; placed at a recorded pose it is the live message's
    assert outline is not None and outline["object"] == "rubber" == truth["object"]
    assert outline["size_mm"] == truth["size_mm"] and len(outline["points"]) == OUTLINE_POINTS
    assert probe.end is not None
    for row in (rows[0], rows[len(rows) // 2], rows[-1]):
        at = dataclasses.replace(probe.end, pose=(row["y"], row["z"], row["psi"]),
                                 held=row["held"], dropped=row["dropped"],
                                 in_fixture=row["in_fixture"], slips=row["slips"])  # fmt: skip
        live = at.scene(probe.bench.outline, OUTLINE_POINTS)
        assert {**recorded_truth(outline, row), "contacts": live["contacts"]} == live


def test_a_replayed_iteration_shows_the_object_where_it_was(sim_run: SimRun) -> None:
    store = _store(sim_run)
    run_id = sim_run.summary["run_id"]
    try:
        it = sim_run.summary["iterations"] // 2
        rec = recorded_iteration(store, sim_run.cfg, run_id, it)
        row, outline = store.truth_at(run_id, it), store.outline(run_id)
    finally:
        store.close()
    assert rec is not None and row is not None and outline is not None
    (sim,) = [m for m in rec.messages if isinstance(m, Sim)]
    assert sim.truth == recorded_truth(outline, row)
    assert sim.truth["pose"] == [row["y"], row["z"], row["psi"]] == list(sim_run.probe.poses[it])
    assert len(sim.truth["outline"]) == OUTLINE_POINTS and sim.truth["held"] is True
    assert sim.json()["type"] == "sim" and sim.truth["object"] == "rubber"


def test_a_run_records_which_sdh2svc_recorded_it(sim_run: SimRun) -> None:
    store = _store(sim_run)
    try:
        run = store.run(sim_run.summary["run_id"])
    finally:
        store.close()
    assert run is not None and run["meta"]["software"] == code_version()
    assert run["meta"]["software"]["version"] == __version__


def test_the_export_draws_the_hand_as_the_run_recorded_it(sim_run: SimRun) -> None:
    """Exported by a process configured otherwise (another finger length, another pad layout:
    the old export drew the links 8.5 mm off and failed on the grids), the file is the one the
    run's own configuration gives."""
    other = sim_run.cfg.as_recorded({
        "hand": {**sim_run.cfg.hand.model_dump(mode="json"), "proximal_length_mm": 95.0},
        "tactile": {**sim_run.cfg.tactile.model_dump(mode="json"),
                    "proximal": {"rows": 15, "cols": 6}},
    })  # fmt: skip
    store = _store(sim_run)
    run_id = sim_run.summary["run_id"]
    files = []
    try:
        for cfg in (sim_run.cfg, other):
            raw = io.BytesIO()
            store.export_mcap(run_id, raw, cfg)
            files.append(raw.getvalue())
    finally:
        store.close()
    assert files[0] == files[1]


def test_the_mcap_scene_carries_the_object(sim_run: SimRun) -> None:
    store = _store(sim_run)
    run_id = sim_run.summary["run_id"]
    try:
        raw = io.BytesIO()
        store.export_mcap(run_id, raw, sim_run.cfg)
        rows, outline = store.truth(run_id), store.outline(run_id)
    finally:
        store.close()
    assert outline is not None
    got = read(raw.getvalue())  # every message validated against the SDK's schema
    *scenes, end = got.messages["/scene"]
    assert len(scenes) == len(rows)
    # as live, the contacts go when the run ends (by id: the type's default, MatchingId)
    assert [d["id"] for d in end["deletions"]] == ["contacts"] and not end.get("entities")
    for scene, row in zip(scenes, rows, strict=True):
        (obj,) = [e for e in scene["entities"] if e["id"] == "object"]
        assert obj["frame_id"] == "frame0"
        (line,) = obj["lines"]
        assert line["type"] == "LINE_LOOP"
        pts = [c for p in line["points"] for c in (p.get("y", 0.0), p.get("z", 0.0))]
        want = [c * 1e-3 for p in recorded_truth(outline, row)["outline"] for c in p]
        assert pts == pytest.approx(want, abs=1e-12)  # m
        assert line["color"]["g"] == pytest.approx(0.8)  # held: green


def test_a_dropped_object_is_red_and_runs_without_truth_have_none(
    cfg: Settings, tmp_path: Path
) -> None:
    store = RunStore(tmp_path / "runs.sqlite")
    sim_id, real_id = store.create_run({}), store.create_run({})
    ring = [(10.0, 0.0), (0.0, 10.0), (-10.0, 0.0), (0.0, -10.0)]
    store.set_outline(sim_id, "disc", 20.0, ring)
    for run_id in (sim_id, real_id):
        rec = Recorder(store.path, run_id)
        for i, s in enumerate(_samples(cfg, 2)):
            rec.sample(s)
            if run_id == sim_id:
                dropped = i == 1
                rec.truth(s.iteration, s.t, (33.0, 120.0, 0.0), not dropped, dropped, False, 2)
        rec.close()
    colours = []
    for run_id in (sim_id, real_id):
        raw = io.BytesIO()
        store.export_mcap(run_id, raw, cfg)
        objects = [
            [e for e in scene["_raw"].entities if e.id == "object"]
            for scene in read(raw.getvalue()).messages["/scene"]
        ]
        colours.append([o[0].lines[0].color.r if o else None for o in objects])
    store.close()
    assert colours[0] == [pytest.approx(0.2), pytest.approx(0.9)]  # held, then dropped: red
    assert colours[1] == [None, None]  # a real hand's run: no object


def test_the_scene_draws_the_object_only_where_its_truth_was_recorded(
    cfg: Settings, tmp_path: Path
) -> None:
    """The export meets truth and samples in step (neither held whole): a sample without a
    truth row gets no object, and the rows after a gap still find their samples."""
    store = RunStore(tmp_path / "runs.sqlite")
    run_id = store.create_run({})
    store.set_outline(run_id, "disc", 20.0, [(10.0, 0.0), (0.0, 10.0), (-10.0, 0.0)])
    rec = Recorder(store.path, run_id)
    samples = _samples(cfg, 6)
    with_truth = {samples[i].iteration for i in (0, 2, 3)}
    for s in samples:
        rec.sample(s)
        if s.iteration in with_truth:
            rec.truth(s.iteration, s.t, (33.0, 120.0 + s.iteration, 0.0), True, False, False, 0)
    rec.close()
    raw = io.BytesIO()
    store.export_mcap(run_id, raw, cfg)
    store.close()
    scenes = read(raw.getvalue()).messages["/scene"][: len(samples)]
    drawn = [[e for e in sc["_raw"].entities if e.id == "object"] for sc in scenes]
    assert [bool(o) for o in drawn] == [s.iteration in with_truth for s in samples]
    zs = [o[0].lines[0].points[0].z for o in drawn if o]
    assert zs == pytest.approx([(120.0 + s.iteration) * 1e-3 for s in samples
                                if s.iteration in with_truth], abs=1e-9)  # fmt: skip


def test_a_run_without_a_bench_records_no_truth(cfg: Settings, tmp_path: Path) -> None:
    """A real hand (no bench): the run's samples, and no truth, no outline."""
    store = RunStore(tmp_path / "runs.sqlite")
    tactile: Any = None  # the runner is made, never run: the hand's links are not used
    run = RecordedRun(cfg, tactile, tactile, store)
    for s in _samples(cfg, 3):
        run.sample(s)
    run._rec.close()
    try:
        assert store.sample_count(run.run_id) == 3
        assert store.truth_count(run.run_id) == 0 and store.outline(run.run_id) is None
        assert store.truth_at(run.run_id, 1) is None
        rec = recorded_iteration(store, cfg, run.run_id, 1)
        assert rec is not None
        (sim,) = [m for m in rec.messages if isinstance(m, Sim)]
        assert sim.truth == {}  # hides the live object's outline while the replay shows
    finally:
        store.close()


def test_an_older_database_without_the_truth_opens(cfg: Settings, tmp_path: Path) -> None:
    """A file made before the truth tables: it opens (for reading too), its runs have none, and
    a run recorded into it now has its truth."""
    path = tmp_path / "old.sqlite"
    db = sqlite3.connect(path)
    db.executescript(SCHEMA)
    db.executescript("DROP TABLE truth; DROP TABLE outlines;")
    db.execute("INSERT INTO runs (started_at, status, meta) VALUES ('x', 'completed', '{}')")
    db.commit()
    db.close()
    store = RunStore(path, create=False)
    try:
        assert store.truth_count(1) == 0 and store.outline(1) is None and store.truth(1) == []
        rec = Recorder(path, store.create_run({}))
        rec.truth(0, 0.0, (1.0, 2.0, 0.5), True, False, False, 0)
        rec.close()
        assert store.truth(2) == [dict(zip(TRUTH_COLUMNS, (0, 0.0, 1.0, 2.0, 0.5, True, False,
                                                           False, 0), strict=True))]  # fmt: skip
    finally:
        store.close()


async def test_the_truth_api_pages_in_iteration_order(sim_run: SimRun, tmp_path: Path) -> None:
    cfg = sim_run.cfg
    run_id = sim_run.summary["run_id"]
    app = create_app(Services(cfg, TelemetryHub(), station=None))  # type: ignore[arg-type]
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
        got: list[dict[str, Any]] = []
        start: int | None = 0
        while start is not None:
            r = await c.get(f"/api/runs/{run_id}/truth", params={"from": start, "limit": 60})
            assert r.status_code == 200, r.text
            page = r.json()
            assert page["total"] == sim_run.summary["iterations"]
            assert page["outline"]["object"] == "rubber"
            assert len(page["outline"]["points"]) == OUTLINE_POINTS
            got += page["truth"]
            start = page["next"]
        assert (await c.get("/api/runs/999/truth")).status_code == 404
        assert (await c.get(f"/api/runs/{run_id}/truth", params={"limit": 0})).status_code == 422
    store = _store(sim_run)
    try:
        assert got == store.truth(run_id)
        outline = store.outline(run_id)
        assert outline is not None
        assert page["outline"]["points"] == outline["points"]
    finally:
        store.close()
    # a run without truth: none, and no outline
    db = tmp_path / "real.sqlite"
    store = RunStore(db)
    real_id = store.create_run({})
    store.close()
    app = create_app(Services(load_config(overrides=[f"storage.db_path='{db}'"], use_env=False),
                              TelemetryHub(), station=None))  # type: ignore[arg-type]  # fmt: skip
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://127.0.0.1") as c:
        page = (await c.get(f"/api/runs/{real_id}/truth")).json()
    assert page["outline"] is None and page["truth"] == [] and page["next"] is None


async def test_frames_and_replay_split_the_pads_as_the_run_recorded_them(
    sim_run: SimRun, tmp_path: Path
) -> None:
    """Read by a service whose matrix map differs (Finger 1's pads swapped), a run's frames are
    still split as recorded: `/frames`' shapes and a replayed iteration's matrices are the run's.
    A recorded configuration this version cannot read is a 409, not a wrong split."""
    run_id, it = sim_run.summary["run_id"], sim_run.summary["iterations"] // 2
    other = load_config(overrides=[f"storage.db_path='{sim_run.cfg.storage.db_path}'",
                                   "axes.finger1_proximal_matrix=1",
                                   "axes.finger1_distal_matrix=0"], use_env=False)  # fmt: skip
    want_shapes = [list(s) for s in matrix_shapes(sim_run.cfg.tactile, sim_run.cfg.axes)]
    assert want_shapes != [list(s) for s in matrix_shapes(other.tactile, other.axes)]
    store = _store(sim_run)
    try:
        recs = [recorded_iteration(store, c, run_id, it) for c in (sim_run.cfg, other)]
    finally:
        store.close()
    mats = [next(m for m in r.messages if isinstance(m, Tactile)).matrices for r in recs if r]
    assert len(mats) == 2 and [m.shape for m in mats[1]] == [tuple(s) for s in want_shapes]
    assert all((a == b).all() for a, b in zip(*mats, strict=True))
    app = create_app(Services(other, TelemetryHub(), station=None))  # type: ignore[arg-type]
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                 base_url="http://127.0.0.1") as c:  # fmt: skip
        r = await c.get(f"/api/runs/{run_id}/frames", params={"limit": 1})
    assert r.status_code == 200, r.text
    assert r.json()["shapes"] == want_shapes
    # a recorded configuration this version refuses
    db = tmp_path / "odd.sqlite"
    src = sqlite3.connect(sim_run.cfg.storage.db_path)
    with contextlib.closing(sqlite3.connect(db)) as dst:
        src.backup(dst)
    src.close()
    with contextlib.closing(sqlite3.connect(db)) as raw, raw:
        meta = json.loads(
            raw.execute("SELECT meta FROM runs WHERE id = ?", (run_id,)).fetchone()[0]
        )
        meta["configuration"]["tactile"]["proximal"]["rows"] = -1
        raw.execute("UPDATE runs SET meta = ? WHERE id = ?", (json.dumps(meta), run_id))
    odd = load_config(overrides=[f"storage.db_path='{db}'"], use_env=False)
    app = create_app(Services(odd, TelemetryHub(), station=None))  # type: ignore[arg-type]
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app),
                                 base_url="http://127.0.0.1") as c:  # fmt: skip
        r = await c.get(f"/api/runs/{run_id}/frames")
    assert r.status_code == 409 and "cannot be read by this version" in r.text, r.text
