"""The run database failing under a run — its disk full or failing, the file deleted or
renamed — while the hand works: the rows wait and are written once the disk takes them again;
what is not written is said in the run's record and summary, never a run that looks whole.
A real SQLite file; the disk's refusal is SQLite's own error, raised by the recorder's
connection while a test holds the disk "full"."""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from test_sim_press import service
from test_store import _samples

from sdh2svc.config import Settings, load_config
from sdh2svc.connect import Bench, Simulated
from sdh2svc.control.observer import BaseObserver
from sdh2svc.control.sample import Sample
from sdh2svc.service import headless, store
from sdh2svc.service.recording import RecordedRun
from sdh2svc.service.store import Recorder, RunStore
from sdh2svc.sim.clock import run_fast

JSON = {"Content-Type": "application/json"}  # a command's, its body empty


class _FullDisk:
    """A recorder's connection that refuses its writes as SQLite does on a full disk while
    ``full`` is set (reads, and every other connection, as they are)."""

    def __init__(self, db: sqlite3.Connection, full: threading.Event) -> None:
        self._db, self._full = db, full

    def __getattr__(self, name: str) -> Any:
        return getattr(self._db, name)

    def __enter__(self) -> sqlite3.Connection:
        return self._db.__enter__()

    def __exit__(self, *exc: Any) -> Any:
        return self._db.__exit__(*exc)

    def execute(self, sql: str, *args: Any) -> sqlite3.Cursor:
        if self._full.is_set() and sql.lstrip().startswith(("INSERT", "UPDATE")):
            raise sqlite3.OperationalError("database or disk is full")
        return self._db.execute(sql, *args)


@pytest.fixture
def full(monkeypatch: pytest.MonkeyPatch) -> Iterator[threading.Event]:
    """Set: the recorders' disk is full (their retries 10 ms apart, not a second)."""
    disk_full = threading.Event()
    real = store.connect

    def connect(*args: Any, **kwargs: Any) -> Any:
        db = real(*args, **kwargs)
        if threading.current_thread().name.startswith("recorder-"):
            return _FullDisk(db, disk_full)
        return db

    monkeypatch.setattr(store, "connect", connect)
    monkeypatch.setattr(store, "RETRY_S", 0.01, raising=False)
    yield disk_full


def test_rows_wait_out_a_full_disk(cfg: Settings, tmp_path: Path, full: threading.Event) -> None:
    """A full disk ended the recorder's thread: every later row of the run was lost, and the
    record said nothing. The rows wait in memory and are written once there is room."""
    db = tmp_path / "runs.sqlite"
    runs = RunStore(db)
    run_id = runs.create_run({})
    full.set()
    rec = Recorder(db, run_id, flush_s=0.01)
    samples = _samples(cfg, 30)
    for s in samples[:10]:
        rec.sample(s)
    assert _until(lambda: rec.refusals > 0)
    for s in samples[10:]:
        rec.sample(s)
    full.clear()  # room again, before the run ends
    rec.close()
    assert rec.error is None and rec.lost == 0 and rec.committed == 30
    assert [r["iteration"] for r in runs.samples(run_id, 0, 100)] == [s.iteration for s in samples]


def test_rows_a_disk_never_took_are_counted(
    cfg: Settings, tmp_path: Path, full: threading.Event
) -> None:
    db = tmp_path / "runs.sqlite"
    run_id = RunStore(db).create_run({})
    full.set()
    rec = Recorder(db, run_id, flush_s=0.01)
    for s in _samples(cfg, 12):
        rec.sample(s)
    rec.close()  # gives up after its tries
    assert rec.committed == 0 and rec.lost == 12 and "disk is full" in str(rec.error)


class _FillsAt(BaseObserver):
    """Fills the disk at iteration ``at`` (None: never) and, at ``free``, frees it."""

    def __init__(self, full: threading.Event, at: int, free: int | None) -> None:
        self.full, self.at, self.free = full, at, free

    def sample(self, s: Sample) -> None:
        if s.iteration == self.at:
            self.full.set()
        if s.iteration == self.free:
            self.full.clear()


def _fast_run(db: Path, observer: BaseObserver) -> dict[str, Any]:
    """A short fast run (one stroke on the rubber ball) into ``db``, watched by ``observer``."""
    cfg = load_config(overrides=[f"storage.db_path='{db}'", "rolling.cycles=1",
                                 "sim.object='rubber'"], use_env=False)  # fmt: skip

    def watch(_bench: Bench | None) -> BaseObserver:
        return observer

    summary: dict[str, Any] = run_fast(headless.run_once(cfg, Simulated(fast=True), observer=watch))
    return summary


def _run(tmp_path: Path, observer: _FillsAt) -> tuple[dict[str, Any], dict[str, Any], int]:
    """A short fast run; its summary, its record and how many samples the record holds."""
    db = tmp_path / "runs.sqlite"
    summary = _fast_run(db, observer)
    runs = RunStore(db, create=False)
    record = runs.run(summary["run_id"])
    assert record is not None
    return summary, record, runs.sample_count(summary["run_id"])


def test_a_run_whose_disk_fills_says_what_its_record_lacks(
    tmp_path: Path, full: threading.Event
) -> None:
    """The disk full from iteration 20 to the run's end: the run completed (the fingers did
    their work), and its summary — returned, and recorded once the disk took the end — says
    how many recorded items are not in the database, and why (it said nothing: a completed
    run with 31 of its 273 samples)."""
    summary, record, kept = _run(tmp_path, _FillsAt(full, at=20, free=None))
    assert summary["status"] == "completed" and kept < summary["iterations"]
    lost = summary["not_recorded"]
    assert lost["items"] >= summary["iterations"] - kept and "disk is full" in lost["error"]
    said = f"{lost['items']} recorded items (samples, frames, events) are not in"
    assert said in summary["message"], summary["message"]
    assert record["status"] == "completed" and record["summary"] == summary


def test_a_run_whose_disk_fills_for_a_while_loses_nothing(
    tmp_path: Path, full: threading.Event
) -> None:
    summary, _, kept = _run(tmp_path, _FillsAt(full, at=20, free=60))
    assert summary["status"] == "completed" and kept == summary["iterations"]
    assert "not_recorded" not in summary and summary["message"] == ""


def _until(ok: Any, timeout_s: float = 30.0) -> bool:
    """Waits for ``ok()`` (a guard: it comes within a flush or two)."""
    deadline = time.monotonic() + timeout_s
    while not ok() and time.monotonic() < deadline:
        time.sleep(0.005)
    return bool(ok())


def test_a_run_the_database_cannot_start_is_a_503_that_says_why(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A full (read-only, failing) disk under POST /api/runs: a plain-text "Internal Server
    Error" (500) and a traceback in the log; now a JSON 503 naming the database and why — and
    after the disk has room, a run starts; and while a run's end is still being written (the
    disk full, another program's lock), a new run is refused as that, not as "already running
    (stopped); stop it first" of a run that had stopped."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'", "rolling.cycles=1"],
                      use_env=False)  # fmt: skip
    create, write_end = RunStore.create_run, RecordedRun._write_end
    writing, go = threading.Event(), threading.Event()

    def full_disk(*_: Any, **__: Any) -> int:
        raise sqlite3.OperationalError("database or disk is full")

    def held_end(self: RecordedRun, summary: dict[str, Any]) -> None:
        writing.set()
        assert go.wait(30)
        write_end(self, summary)

    async def main() -> None:
        async with service(cfg, Simulated(fast=True)) as (c, _):
            monkeypatch.setattr(RunStore, "create_run", full_disk)
            r = await c.post("/api/runs", json={})
            assert r.status_code == 503, r.text
            assert r.json()["error"] == (f"the run database {tmp_path}/runs.sqlite did not take "
                                         "the run's start (database or disk is full): no run was "
                                         "started")  # fmt: skip
            monkeypatch.setattr(RunStore, "create_run", create)
            monkeypatch.setattr(RecordedRun, "_write_end", held_end)
            assert (await c.post("/api/runs", json={})).status_code == 201
            assert (await c.post("/api/runs/stop", headers=JSON)).status_code == 202
            assert await asyncio.to_thread(writing.wait, 60)
            said = f"has ended (stopped) and its record is still being written to {tmp_path}"
            for path in ("/api/runs", "/api/hand/open"):
                r = await c.post(path, json={})
                assert r.status_code == 409 and said in r.json()["error"], r.text
            go.set()

    asyncio.run(main())


def _move(db: Path, to: Path | None) -> None:
    """The database and its log and index renamed to ``to`` (None: deleted), as a person
    archiving or clearing it while the service runs does."""
    for end in ("", "-wal", "-shm"):
        here = Path(f"{db}{end}")
        if here.exists():
            here.rename(f"{to}{end}") if to is not None else here.unlink()


@pytest.mark.parametrize("moved", [True, False], ids=["renamed", "deleted"])
def test_a_latch_and_a_new_run_go_where_a_restart_looks(
    cfg: Settings, tmp_path: Path, moved: bool
) -> None:
    """The database renamed or deleted under a service: the e-stop answered "recorded", but
    its latch went into the file the service had open — renamed away, or gone — and a restart
    came up unlatched; the next run's row went there too, while its recorder (which opens the
    path) wrote its samples into a new file without it, where a later run of the same id took
    them as its own. Both now go to the file at the path."""
    db = tmp_path / "runs.sqlite"
    runs = RunStore(db)
    first = runs.create_run({"first": True})
    _move(db, tmp_path / "archive.sqlite" if moved else None)
    assert runs.replaced()
    runs.latch_estop("e-stop requested")
    run_id = runs.create_run({"second": True})
    rec = Recorder(db, run_id, flush_s=0.01)
    for s in _samples(cfg, 5):
        rec.sample(s)
    rec.close()
    runs.close()
    restarted = RunStore(db, create=False)  # what a restart opens
    latch = restarted.estop_latch()
    assert latch is not None and latch["reason"] == "e-stop requested"
    record = restarted.run(run_id)
    assert record is not None and record["meta"] == {"second": True}
    assert restarted.sample_count(run_id) == 5 and not restarted.replaced()
    if moved:  # the first run stays in the archive, whole
        archived = RunStore(tmp_path / "archive.sqlite", create=False)
        assert archived.run(first) is not None and archived.estop_latch() is None


class _MovesAt(BaseObserver):
    def __init__(self, db: Path, at: int) -> None:
        self.db, self.at = db, at

    def sample(self, s: Sample) -> None:
        if s.iteration == self.at:
            _move(self.db, self.db.with_name("archive.sqlite"))


def test_a_run_whose_database_is_renamed_says_its_record_is_not_there(tmp_path: Path) -> None:
    """The file renamed mid-run: the run ended 'stopped' with no message and no log line,
    and was not in the file at the path. Its summary says so now."""
    db = tmp_path / "runs.sqlite"
    summary = _fast_run(db, _MovesAt(db, 20))
    assert summary["status"] == "completed"
    assert (f"the run database {db} was deleted, renamed or replaced during the run: its "
            "record is not in the file there") in summary["message"]  # fmt: skip
    archived = RunStore(db.with_name("archive.sqlite"), create=False).run(summary["run_id"])
    assert archived is not None and archived["status"] == "completed"  # whole, over there


def test_a_run_end_the_disk_refused_is_written_once_it_takes_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The run's end refused (a full disk at the run's end): the run stayed 'running' for the
    service's life — not to be deleted, "being recorded" — and a restart called it killed or
    crashed. The service writes its end once the disk takes it."""
    from sdh2svc.service import recording

    finish, refusals = RunStore.finish_run, [2]

    def full_then_free(self: RunStore, *args: Any) -> None:
        if refusals[0]:
            refusals[0] -= 1
            raise sqlite3.OperationalError("database or disk is full")
        finish(self, *args)

    monkeypatch.setattr(RunStore, "finish_run", full_then_free)
    monkeypatch.setattr(recording, "END_RETRY_S", 0.01, raising=False)
    db = tmp_path / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'"], use_env=False)

    async def main() -> tuple[dict[str, Any], dict[str, Any]]:
        async with service(cfg, Simulated(fast=True)) as (c, services):
            st = services.station
            assert (await c.post("/api/runs", json={})).status_code == 201
            assert (await c.post("/api/runs/stop", headers=JSON)).status_code == 202
            while st.running:
                await asyncio.sleep(0.01)
            assert st.last_run is not None and st.store is not None
            runs = st.store
            run_id = st.last_run["id"]
            recorded = await asyncio.to_thread(
                _until, lambda: runs.run(run_id)["status"] != "running"
            )
            assert recorded
            return st.last_run, runs.run(run_id)

    summary, record = asyncio.run(main())
    assert f"its end is not recorded in {db}: database or disk is full" in summary["message"]
    assert record["status"] == "stopped" and refusals == [0]
    assert "not recorded" not in record["summary"]["message"]  # it is, now


def test_a_shutdown_with_an_unrecorded_latch_says_a_restart_comes_up_released(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    def full_disk(*_: Any, **__: Any) -> dict[str, str]:
        raise sqlite3.OperationalError("database or disk is full")

    monkeypatch.setattr(RunStore, "latch_estop", full_disk)
    db = tmp_path / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'"], use_env=False)

    async def main() -> dict[str, Any]:
        async with service(cfg, Simulated(fast=True)) as (c, _):
            return dict((await c.post("/api/estop")).json())

    with caplog.at_level(logging.WARNING):
        answer = asyncio.run(main())
    assert answer["estopped"] is True and answer["recorded"] is False
    said = [
        r.getMessage() for r in caplog.records if "a restart comes up released" in r.getMessage()
    ]
    assert said == [f"the e-stop's latch is not in {db}: a restart comes up released (the hand "
                    "stays off until then)"]  # fmt: skip


def test_a_database_on_a_full_disk_says_the_disk_is_full(tmp_path: Path) -> None:
    """On a full disk even `runs list` fails: SQLite cannot size the log's index to read, and
    says "disk I/O error". The message now says the disk is full. (A 1 MiB tmpfs in a mount
    namespace of the test's own.)"""
    db = tmp_path / "runs.sqlite"
    runs = RunStore(db)
    runs.create_run({})
    runs.close()
    for end in ("-wal", "-shm"):  # as a closed database leaves it
        Path(f"{db}{end}").unlink(missing_ok=True)
    if subprocess.run(["unshare", "--mount", "true"], capture_output=True).returncode != 0:
        pytest.skip("this machine lets no test make a mount namespace (unshare needs root)")
    disk = tmp_path / "disk"
    disk.mkdir()
    script = (f"mount -t tmpfs -o size=1m tmpfs {disk} && cp {db} {disk}/runs.sqlite && "
              f"(dd if=/dev/zero of={disk}/fill bs=64k 2>/dev/null; true) && "
              f"{sys.executable} -m sdh2svc runs list --set "
              f"'storage.db_path=\"{disk}/runs.sqlite\"'")  # fmt: skip
    r = subprocess.run(["unshare", "--mount", "sh", "-c", script], capture_output=True,
                       text=True, timeout=60)  # fmt: skip
    assert r.returncode == 4, r.stderr
    assert f"cannot open the run database {disk}/runs.sqlite: " in r.stderr
    assert "(the disk holding it is full: " in r.stderr and "make room there" in r.stderr


def test_a_recording_that_cannot_begin_counts_its_rows_lost(
    cfg: Settings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The recorder's own connection refused (a full disk, the file gone unwritable between the
    run's start and its recorder): its thread died with a traceback on stderr, and the rows
    were neither written nor said to be lost."""
    db = tmp_path / "runs.sqlite"
    run_id = RunStore(db).create_run({})
    real = store.connect

    def refused(*args: Any, **kwargs: Any) -> Any:
        if threading.current_thread().name.startswith("recorder-"):
            raise store.StoreError(f"cannot open the run database {db}: disk I/O error")
        return real(*args, **kwargs)

    monkeypatch.setattr(store, "connect", refused)
    rec = Recorder(db, run_id, flush_s=0.01)
    for s in _samples(cfg, 7):
        rec.sample(s)
    rec.close()
    assert rec.committed == 0 and rec.lost == 7 and "disk I/O error" in str(rec.error)
