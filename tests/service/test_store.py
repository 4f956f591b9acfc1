"""The run store: a real SQLite file, durable through kill -9, with CSV and MCAP exports."""

from __future__ import annotations

import contextlib
import csv
import io
import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mcap_check import read

from sdh2svc.config import Settings
from sdh2svc.control.rolling import RollState, step
from sdh2svc.control.sample import Sample
from sdh2svc.model.kinematics import HandPose
from sdh2svc.service.store import (
    INTERRUPTED,
    SAMPLE_COLUMNS,
    SCHEMA,
    Recorder,
    RunStore,
    connect,
)


def _frame(S: float) -> np.ndarray:
    m = np.zeros((13, 6), dtype=np.uint16)
    j = int(S // 3.4)
    w = S / 3.4 - j
    m[j, 1:5], m[j + 1, 1:5] = round(1000 * (1 - w)), round(1000 * w)
    return m


def _samples(cfg: Settings, n: int) -> list[Sample]:
    ctx, state = cfg.model_context(), RollState()
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))
    out = []
    for i in range(n):
        r = step(state, pose, _frame(20.0 + 0.1 * i), _frame(20.0), cfg.rolling, ctx)
        ages = {"frame_age_ms": 3.0, "joint_age_ms": 2.0, "latency_ms": 1.5}
        out.append(Sample.from_step(r, pose, t=i / 30, **ages))
        state, pose = r.state, r.targets or pose
    return out


def test_record_read_back_and_export(cfg: Settings, tmp_path: Path) -> None:
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    run_id = store.create_run({"object": "egg", "params": cfg.rolling.model_dump()})
    rec = Recorder(db, run_id)
    samples = _samples(cfg, 40)
    for s in samples:
        rec.sample(s)
    rec.event(0.5, 15, "reversal", {"reason": "cone_A"})
    tex = np.arange(486, dtype=np.uint16)
    rec.frame(0.1, 3, 1234, tex)
    rec.close()
    assert rec.error is None and rec.committed == 42
    store.finish_run(run_id, "completed", {"strokes": 3})

    run = store.run(run_id)
    assert run["status"] == "completed" and run["iterations"] == 40
    assert run["meta"]["object"] == "egg" and run["summary"] == {"strokes": 3}
    back = store.samples(run_id, offset=10, limit=5)
    assert [b["iteration"] for b in back] == [s.iteration for s in samples[10:15]]
    assert back[0]["Lambda"] == samples[10].Lambda and back[0]["S1"] == samples[10].S1
    assert store.events(run_id) == [
        {"t": 0.5, "iteration": 15, "kind": "reversal", "detail": {"reason": "cone_A"}}
    ]
    ((t, it, ts, texels),) = list(store.frames(run_id))
    assert (t, it, ts) == (0.1, 3, 1234) and np.array_equal(texels, tex)

    buf = io.StringIO()
    assert store.export_csv(run_id, buf) == 40
    rows = list(csv.DictReader(io.StringIO(buf.getvalue())))
    assert len(rows) == 40 and list(rows[0]) == list(Sample.csv_header())
    assert float(rows[5]["F [library force units]"]) == samples[5].F

    raw = io.BytesIO()
    n = store.export_mcap(run_id, raw)
    assert n == 40 * 3 + 1 + 6  # samples, their transforms and contacts; the event; six pads
    got = read(raw.getvalue())  # every message valid against its schema (tests/service/mcap_check)
    assert (
        len(got.messages["/samples"]) == 40 and got.messages["/samples"][7]["S1"] == samples[7].S1
    )
    assert got.messages["/events"][0]["name"] == "reversal"
    grid = got.messages["/tactile/finger1_proximal"][0]["_raw"]
    assert np.frombuffer(grid.data, "<u2")[:3].tolist() == [0, 1, 2]
    store.close()


WRITER = r"""
import sys, time, math
from sdh2svc.config import default_config
from sdh2svc.service.store import Recorder, RunStore
sys.path.insert(0, sys.argv[2])
from test_store import _samples
db = sys.argv[1]
run_id = RunStore(db).create_run({})
rec = Recorder(db, run_id)
samples = _samples(default_config(), 50)
last = -1
i = 0
while True:
    rec.sample(samples[i % 50])
    i += 1
    if rec.committed != last:
        last = rec.committed
        print(last, flush=True)
    time.sleep(0.002)
"""


def test_durable_through_sigkill(tmp_path: Path) -> None:
    db = tmp_path / "runs.sqlite"
    proc = subprocess.Popen(
        [sys.executable, "-c", WRITER, str(db), str(Path(__file__).parent)],
        stdout=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )  # fmt: skip
    assert proc.stdout is not None
    durable = 0  # the writer prints what its recorder has committed: on disk from then on
    while durable <= 100:  # it really was writing for a while (an event, not a time window)
        line = proc.stdout.readline()
        assert line, "the writer died"
        durable = int(line)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    store = RunStore(db)
    (run,) = store.runs()
    assert run["iterations"] >= durable
    # it never finished, and its process is gone: a crash, not a stop (read so; the database
    # says so once a service or a run starts on it: test_a_run_whose_process_died_…)
    assert run["status"] == "interrupted"
    store.close()


OWNER = """
import sys
from sdh2svc.service.store import RunStore
store = RunStore(sys.argv[1])
print(store.create_run({"who": "child"}), flush=True)
sys.stdin.readline()  # alive until the test closes stdin
"""


def _raw_status(db: Path, run_id: int) -> str:
    with contextlib.closing(sqlite3.connect(db)) as raw:
        return str(raw.execute("SELECT status FROM runs WHERE id = ?", (run_id,)).fetchone()[0])


def test_a_run_another_live_process_records_stays_running_until_it_dies(tmp_path: Path) -> None:
    """A second service or an `sdh2svc run` on the same file: its live run is not taken for
    one a crash left behind; once its process is gone, it is."""
    db = tmp_path / "runs.sqlite"
    child = subprocess.Popen([sys.executable, "-c", OWNER, str(db)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert child.stdout is not None and child.stdin is not None
    run_id = int(child.stdout.readline())
    store = RunStore(db)
    try:
        assert store.mark_interrupted() == []
        assert store.run(run_id)["status"] == "running"  # type: ignore[index]
        child.stdin.close()
        assert child.wait(timeout=60) == 0
        child.stdout.close()
        # read as interrupted at once, without a write (a reader never writes the status) …
        reader = RunStore(db, create=False)
        assert reader.run(run_id)["status"] == "interrupted"  # type: ignore[index]
        assert [r["status"] for r in reader.runs()] == ["interrupted"]
        why = {"status": "interrupted", "message": INTERRUPTED}  # what `runs list` shows, …
        assert reader.run(run_id)["summary"] == why  # type: ignore[index]
        reader.close()
        assert _raw_status(db, run_id) == "running"
        # … and marked so by the next service or run, with its summary
        assert store.mark_interrupted() == [run_id]
        assert _raw_status(db, run_id) == "interrupted"
        with sqlite3.connect(db) as raw:
            summary = raw.execute("SELECT summary FROM runs WHERE id = ?", (run_id,)).fetchone()
        assert json.loads(summary[0]) == why
        assert store.mark_interrupted() == []
    finally:
        store.close()


def test_a_run_whose_process_died_is_marked_interrupted_and_this_ones_are_not(
    tmp_path: Path,
) -> None:
    """Runs from before owners were kept, and a pid reused by another process, are not alive;
    this process's own run is."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        mine = store.create_run({})
        with store.db:
            legacy = store.db.execute("INSERT INTO runs (started_at, status, meta) "
                                      "VALUES ('x', 'running', '{}')").lastrowid  # fmt: skip
            reused = store.db.execute("INSERT INTO runs (started_at, status, meta) "
                                      "VALUES ('x', 'running', '{}')").lastrowid  # fmt: skip
            host, pid = store.db.execute("SELECT host, pid FROM owners WHERE run_id = ?",
                                         (mine,)).fetchone()  # fmt: skip
            store.db.execute("INSERT INTO owners (run_id, host, pid, started) "
                             "VALUES (?, ?, ?, 'started before')",
                             (reused, host, pid))  # fmt: skip
        assert store.run(mine)["status"] == "running"  # type: ignore[index]
        assert sorted(store.mark_interrupted()) == sorted([legacy, reused])
        assert store.run(mine)["status"] == "running"  # type: ignore[index]
    finally:
        store.close()


def test_an_older_database_gets_new_sample_columns(tmp_path: Path) -> None:
    path = tmp_path / "old.sqlite"
    with contextlib.closing(sqlite3.connect(path)) as old:
        old.executescript(SCHEMA.replace(', "joint_age_ms"', ""))
    db = connect(path)
    assert {row[1] for row in db.execute("PRAGMA table_info(samples)")} >= set(SAMPLE_COLUMNS)
    db.close()


RECOGNITION = ("contact1_kind", "contact2_kind", "radius1", "radius2", "object_class",
               "class_confidence", "size_a", "size_b", "rotation_est", "axis_est",
               "outline_side")  # fmt: skip


def test_the_recognition_round_trips_and_an_older_database_reads_as_none(
    cfg: Settings, tmp_path: Path
) -> None:
    """A file made before the recognition's columns: its samples read back without an estimate;
    a new run in it records and exports the estimate."""
    from sdh2svc.control.recognition import ContactKind, ObjectClass, Recognition

    assert SAMPLE_COLUMNS[-len(RECOGNITION) :] == RECOGNITION
    older = SAMPLE_COLUMNS[: -len(RECOGNITION)]
    path = tmp_path / "old.sqlite"
    old_sample = _samples(cfg, 1)[0]
    with contextlib.closing(sqlite3.connect(path)) as old:
        old_schema = SCHEMA.replace("".join(f', "{c}"' for c in RECOGNITION), "")
        assert '"rotation_est"' not in old_schema and '"axis_est"' not in old_schema
        old.executescript(old_schema)
        old.execute("INSERT INTO runs (started_at, status, meta) VALUES ('x', 'completed', '{}')")
        cols, marks = ", ".join(f'"{c}"' for c in older), ", ".join("?" * len(older))
        sql = f"INSERT INTO samples (run_id, {cols}) VALUES (1, {marks})"
        old.execute(sql, old_sample.row()[: len(older)])
        old.commit()
    store = RunStore(path)
    (row,) = store.samples(1)
    assert Sample(**row) == old_sample and Sample(**row).recognition() is None
    rec = Recognition(ContactKind.EDGE, ContactKind.CURVED, None, 18.0, ObjectClass.POLYGON,
                      0.9, 31.0, 20.5, -12.25, 8.5)  # fmt: skip
    r = step(RollState(), HandPose(*(math.radians(a) for a in (-20, 30, -20, 30))),
             _frame(20.0), _frame(20.0), cfg.rolling, cfg.model_context())  # fmt: skip
    new = Sample.from_step(r, HandPose(0, 0, 0, 0), 0.0, 1.0, 1.0, 1.0, rec)
    run_id = store.create_run({})
    recorder = Recorder(path, run_id)
    recorder.sample(new)
    recorder.close()
    (back,) = store.samples(run_id)
    assert Sample(**back) == new and Sample(**back).recognition() == rec
    assert (back["object_class"], back["contact1_kind"], back["rotation_est"]) == (
        "polygon", "edge", -12.25)  # fmt: skip
    buf = io.StringIO()
    store.export_csv(run_id, buf)
    (line,) = csv.DictReader(io.StringIO(buf.getvalue()))
    assert line["object_class"] == "polygon" and float(line["rotation_est [deg]"]) == -12.25
    assert line["radius1 [mm]"] == "" and float(line["radius2 [mm]"]) == 18.0
    store.close()


def test_the_export_time_base_is_to_the_millisecond_and_the_same_in_every_time_zone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A run's start is stored with its offset to the millisecond; an MCAP export's time base
    read back from it is that instant wherever the export runs (it was the local time read as
    if it were the process's zone, to the whole second)."""
    import time

    from sdh2svc.service.store import _epoch_ns, now_iso

    instant = 1796232027.707
    try:
        for zone in ("UTC", "Europe/Berlin", "America/New_York"):
            monkeypatch.setenv("TZ", zone)
            time.tzset()
            assert _epoch_ns("2026-12-02T17:20:27.707+0000") == round(instant * 1e3) * 10**6
            assert _epoch_ns("2026-12-02T18:20:27.707+0100") == round(instant * 1e3) * 10**6
            assert _epoch_ns("2026-12-02T17:20:27+0000") == 1796232027 * 10**9
            stamp = now_iso()
            assert abs(_epoch_ns(stamp) / 1e9 - time.time()) < 5.0, stamp
            assert len(stamp.split(".")[1]) == len("707+0000"), stamp
    finally:
        monkeypatch.delenv("TZ")
        time.tzset()
    assert _epoch_ns("not a time") == 0


def test_rows_wait_out_a_lock_another_program_holds(cfg: Settings, tmp_path: Path) -> None:
    """A DB browser or a sqlite3 shell holds the file locked for longer than busy_timeout_s:
    the recorder keeps the rows and writes them once the lock is gone (its thread died on the
    first refused batch before, and every later row of the run was lost)."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    run_id = store.create_run({})
    rec = Recorder(db, run_id, flush_s=0.01, busy_timeout_s=0.05)
    lock = sqlite3.connect(db, isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")
    samples = _samples(cfg, 30)
    for s in samples[:10]:
        rec.sample(s)
    deadline = time.monotonic() + 30  # (a guard: the lock is met within a flush or two)
    while rec.refusals == 0 and time.monotonic() < deadline:
        time.sleep(0.01)
    assert rec.refusals > 0 and rec.committed == 0
    for s in samples[10:]:
        rec.sample(s)
    lock.execute("ROLLBACK")
    lock.close()
    rec.close()
    assert rec.error is None and rec.committed == 30
    assert [r["iteration"] for r in store.samples(run_id, 0, 100)] == [s.iteration for s in samples]


def test_a_runs_reads_go_by_its_indexes_and_never_sort_it(cfg: Settings, tmp_path: Path) -> None:
    """Pages of samples, frames and truth, and both exports, read a run in the order of an index
    (run, iteration) or (run, t): none sorts the run's rows (the pages' order by rowid did, for
    every page, 0.2 s a page at 49 000 iterations; the MCAP export sorted every frame's texels),
    so a page deep in a run of hours costs what the first does and an export holds one row."""
    store = RunStore(tmp_path / "runs.sqlite")
    run_id = store.create_run({})
    rec = Recorder(store.path, run_id)
    for s in _samples(cfg, 12):
        rec.sample(s)
        rec.frame(s.t, s.iteration, 0, np.zeros(486, dtype=np.uint16))
        rec.truth(s.iteration, s.t, (30.0, 120.0, 0.0), True, False, False, 0)
    rec.close()
    seen: list[str] = []
    store.db.set_trace_callback(seen.append)  # each statement, its parameters filled in
    store.samples(run_id, 4, 3, first=2, every=3)
    store.samples(run_id)
    store.truth(run_id, 0, 5, every=2)
    store.frames_from(run_id, 3, 100, 5, every=2)
    store.export_csv(run_id, io.StringIO())
    store.export_mcap(run_id, io.BytesIO(), cfg)
    store.db.set_trace_callback(None)
    tables = ("FROM samples", "FROM frames", "FROM truth")
    reads = [q for q in seen if q.lstrip().startswith("SELECT") and any(t in q for t in tables)]
    assert len(reads) >= 8
    for q in reads:
        plan = " | ".join(r[3] for r in store.db.execute("EXPLAIN QUERY PLAN " + q))
        assert "TEMP B-TREE" not in plan and "USING" in plan, (q, plan)
    store.close()
