"""Keeping the run database small: runs deleted with everything recorded with them, the older
ones pruned, the file vacuumed — never a run being recorded. A real SQLite file throughout;
the command line in-process (its exit statuses and messages)."""

from __future__ import annotations

import contextlib
import json
import logging
import sqlite3
import subprocess
import sys
import time
from collections.abc import Iterator
from datetime import UTC, datetime, timedelta
from pathlib import Path

import numpy as np
import pytest

from sdh2svc.cli import Exit, main
from sdh2svc.service.store import (
    DELETE_CHUNK,
    STALE_S,
    Recorder,
    RunBusy,
    RunStore,
    held_elsewhere,
    opened_elsewhere,
    openers,
)

TABLES = ("samples", "events", "frames", "truth", "outlines", "owners")
STARTS = ["2026-10-01T09:00:00.000+0200", "2026-11-01T09:00:00.000+0000",
          "2026-11-20T09:00:00.000+0000", "2026-12-01T09:00:00.000+0000"]  # fmt: skip


def _record(store: RunStore, iterations: int = 50, started_at: str | None = None) -> int:
    """A finished run with samples' worth of rows in every table (raw rows: what a run writes)."""
    run_id = store.create_run({"object": "egg"})
    rec = Recorder(store.path, run_id)
    for i in range(iterations):
        rec.event(i / 30, i, "reversal", {"reason": "cone_A"})
        rec.frame(i / 30, i, i, np.full(486, i, dtype=np.uint16))
        rec.truth(i, i / 30, (0.0, 80.0, 0.1), True, False, False, 0)
    rec.close()
    assert rec.error is None
    store.set_outline(run_id, "egg", 40.0, [(0.0, 1.0), (1.0, 0.0), (0.0, -1.0)])
    with store.db:
        store.db.execute("INSERT INTO samples (run_id, iteration, t) VALUES (?, 0, 0.0)",
                         (run_id,))  # fmt: skip
        if started_at:
            store.db.execute("UPDATE runs SET started_at = ? WHERE id = ?", (started_at, run_id))
    store.finish_run(run_id, "completed", {"status": "completed"})
    return run_id


def _rows(db: Path, run_id: int) -> dict[str, int]:
    """How many rows each table holds of ``run_id`` (``runs``: its own)."""
    with contextlib.closing(sqlite3.connect(db)) as c:
        count = "SELECT COUNT(*) FROM {} WHERE {} = ?"
        rows = {t: c.execute(count.format(t, "run_id"), (run_id,)).fetchone()[0] for t in TABLES}
        rows["runs"] = c.execute(count.format("runs", "id"), (run_id,)).fetchone()[0]
    return rows


@pytest.fixture
def store(four_runs: Path) -> Iterator[RunStore]:
    """A store on ``four_runs`` (closed after the test)."""
    store = RunStore(four_runs)
    try:
        yield store
    finally:
        store.close()


@pytest.fixture
def four_runs(tmp_path: Path) -> Path:
    """Runs 1–4, started on STARTS."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        assert [_record(store, started_at=s) for s in STARTS] == [1, 2, 3, 4]
    finally:
        store.close()
    return db


def test_a_deleted_run_leaves_nothing_behind_and_the_others_stay_whole(
    four_runs: Path, store: RunStore
) -> None:
    before = _rows(four_runs, 3)
    assert min(before.values()) >= 1
    assert store.delete_runs([2, 99]) == [2]  # 99 was never there
    assert store.run(2) is None and store.events(2) == [] and store.truth(2) == []
    assert set(_rows(four_runs, 2).values()) == {0}
    assert _rows(four_runs, 3) == before
    assert [r["id"] for r in store.runs()] == [4, 3, 1]
    _, free = store.size()
    assert free > 50 * 486 * 2  # the frames' pages wait for the next runs
    assert _record(store) == 5  # ids are never reused (AUTOINCREMENT)


def test_a_run_being_recorded_is_never_deleted_nor_the_file_vacuumed(store: RunStore) -> None:
    live = store.create_run({})  # this process records it: alive
    with pytest.raises(RunBusy, match=f"run {live} is being recorded"):
        store.delete_runs([1, live])
    assert store.run(1) is not None  # nothing deleted: the refusal comes first
    assert live not in store.prunable(keep=0)
    with pytest.raises(RunBusy, match="vacuum once it has ended"):
        store.vacuum()
    store.finish_run(live, "stopped", {})
    assert store.delete_runs([live]) == [live]


def test_prune_keeps_the_newest_and_takes_only_the_older_than_asked(store: RunStore) -> None:
    assert store.prunable(keep=0) == [1, 2, 3, 4]
    assert store.prunable(keep=1) == [1, 2, 3]
    assert store.prunable(keep=10) == []
    nov = datetime(2026, 11, 15, tzinfo=UTC)
    assert store.prunable(before=nov) == [1, 2]
    assert store.prunable(keep=3, before=nov) == [1]  # both: beyond the newest 3 and older
    # run 1 started 09:00 at +02:00, 07:00 UTC: before 08:00 UTC, not before 06:00 UTC
    at = datetime(2026, 10, 1, 8, tzinfo=UTC)
    assert store.prunable(before=at) == [1]
    assert store.prunable(before=at - timedelta(hours=2)) == []
    with pytest.raises(ValueError, match="time zone"):
        store.prunable(before=datetime(2026, 11, 15))  # the mistake tested


def test_vacuum_gives_the_deleted_runs_space_back(tmp_path: Path) -> None:
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        ids = [_record(store, iterations=400) for _ in range(3)]
        full, _ = store.size()
        store.delete_runs(ids[:2])
        assert store.size()[0] >= full * 0.9  # deleted: the file keeps its size …
        store.vacuum()
        small, free = store.size()
        assert small < full / 2 and free == 0  # … until it is vacuumed
        assert len(store.frames_from(ids[2], 0, 10**6, 10**6)) == 400
    finally:
        store.close()


def test_runs_are_listed_a_page_at_a_time(four_runs: Path) -> None:
    store = RunStore(four_runs, create=False)
    try:
        page, total = store.run_page(2)
        assert [r["id"] for r in page] == [4, 3] and total == 4
        page, _ = store.run_page(2, before=3)
        assert [r["id"] for r in page] == [2, 1]
        assert store.run_page(2, before=1) == ([], 4)
    finally:
        store.close()


# --- the command line -------------------------------------------------------------------------


def _cli(capsys: pytest.CaptureFixture[str], db: Path, *args: str) -> tuple[int, str, str]:
    status = main(["runs", *args, "--set", f"storage.db_path={json.dumps(str(db))}"])
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return status, out, err


def test_runs_delete_prune_and_vacuum_from_the_command_line(
    four_runs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, out, err = _cli(capsys, four_runs, "list")
    assert status == Exit.OK and len(out.splitlines()) == 4
    assert f"4 runs in {four_runs}: " in err and "free for new runs" in err

    status, _, err = _cli(capsys, four_runs, "delete", "2", "7")
    assert status == Exit.NOT_FOUND and "no run 7 in" in err and "(nothing deleted)" in err
    assert _rows(four_runs, 2)["runs"] == 1

    status, _, err = _cli(capsys, four_runs, "prune", "--keep", "1", "--dry-run")
    assert status == Exit.OK and "would delete 3 runs: 1–3" in err
    assert "prune: runs beyond the newest 1 (a run being recorded is left out)" in err
    # the moment WHEN names, in UTC as `runs list` shows the starts (CLI audit: read in local
    # time, it was never said which moment that was)
    status, _, err = _cli(capsys, four_runs, "prune", "--before", "2026-11-15T10:00+02:00",
                          "--dry-run")  # fmt: skip
    assert "runs started before 2026-11-15T08:00:00+0000 (" in err and "would delete 2" in err
    assert _rows(four_runs, 1)["runs"] == 1  # a dry run deletes nothing

    status, _, err = _cli(capsys, four_runs, "prune", "--keep", "1", "--before", "2026-11-15")
    assert status == Exit.OK and "deleted 2 runs: 1–2;" in err
    status, out, _ = _cli(capsys, four_runs, "list")
    assert [int(line.split()[0]) for line in out.splitlines()] == [4, 3]

    status, _, err = _cli(capsys, four_runs, "delete", "3", "--vacuum")
    assert status == Exit.OK and "deleted 1 run: 3;" in err and " MB → " in err
    status, _, err = _cli(capsys, four_runs, "prune", "--before", "2026-01-01")
    assert status == Exit.OK and "no run to delete" in err


def test_a_run_being_recorded_is_refused_by_name(
    four_runs: Path, store: RunStore, capsys: pytest.CaptureFixture[str]
) -> None:
    live = store.create_run({})
    status, _, err = _cli(capsys, four_runs, "delete", str(live))
    assert status == Exit.FAILED and f"run {live} is being recorded: stop it first" in err
    status, _, err = _cli(capsys, four_runs, "vacuum")
    assert status == Exit.FAILED and "vacuum once it has ended" in err
    status, _, err = _cli(capsys, four_runs, "prune", "--keep", "0")
    assert status == Exit.OK and "deleted 4 runs: 1–4;" in err  # all but the live one
    assert store.run(live) is not None


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["delete"], "delete: which run? (give its ID)"),
        (["prune"], "prune: which runs? (give --keep N, --before WHEN, or both)"),
        (["show", "1", "2"], "show: one run at a time (2 IDs given)"),
        (["list", "--keep", "3"], "--keep: not with runs list"),
        (["vacuum", "4", "5"], "the run IDs 4, 5: not with runs vacuum"),
        (["export", "1", "--dry-run"], "--dry-run: not with runs export"),
    ],
)
def test_what_an_action_does_not_take_is_a_usage_error(
    args: list[str], fragment: str, four_runs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = _cli(capsys, four_runs, *args)
    assert status == Exit.USAGE and fragment in err
    assert _rows(four_runs, 1)["runs"] == 1


def test_run_ids_may_follow_an_option(four_runs: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, _, err = _cli(capsys, four_runs, "delete", "--dry-run", "2", "3")
    assert status == Exit.OK and "would delete 2 runs: 2–3" in err
    status, _, err = _cli(capsys, four_runs, "delete", "1", "--vacuum", "4")
    assert status == Exit.OK and "deleted 2 runs: 1, 4;" in err
    _, out, _ = _cli(capsys, four_runs, "list")
    assert [int(line.split()[0]) for line in out.splitlines()] == [3, 2]
    for bad, said in ((["2x"], "sdh2svc runs: error: argument id: '2x': a run ID is written "
                               "in the digits 0–9"),  # runs's usage, as before an option
                      (["2", "--bogus"], "unrecognized arguments: 2 --bogus")):  # fmt: skip
        with pytest.raises(SystemExit) as refused:
            _cli(capsys, four_runs, "delete", "--dry-run", *bad)
        assert refused.value.code == Exit.USAGE and said in capsys.readouterr().err


@pytest.mark.parametrize("when", ["yesterday", "30x", "3w", "2026-13-01"])
def test_prune_before_takes_a_date_or_an_age(
    when: str, four_runs: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as bad:
        _cli(capsys, four_runs, "prune", "--before", when)
    assert bad.value.code == Exit.USAGE
    assert "give a date (2026-11-30), a date and time (2026-11-30T14:00) or an age" in (
        capsys.readouterr().err
    )


def test_the_index_a_delete_uses_is_made_by_writers_only(four_runs: Path) -> None:
    """A database from before the events' index gets it from the next writer (the service, a
    run); a reading command adds nothing (the file may sit on a read-only medium)."""
    with contextlib.closing(sqlite3.connect(four_runs)) as c, c:
        c.execute("DROP INDEX events_run")

    def has_index() -> bool:
        with contextlib.closing(sqlite3.connect(four_runs)) as c:
            q = "SELECT 1 FROM sqlite_master WHERE type = 'index' AND name = 'events_run'"
            return c.execute(q).fetchone() is not None

    RunStore(four_runs, create=False).close()
    assert not has_index()
    RunStore(four_runs).close()
    assert has_index()


# --- another process on the file: a container's service, a reader -----------------------------

HOLDER = """
import sqlite3, sys
db = sqlite3.connect(sys.argv[1])
db.execute("SELECT COUNT(*) FROM runs").fetchone()  # open, as a service's connection is
print("open", flush=True)
sys.stdin.readline()  # until the test closes stdin
"""


@contextlib.contextmanager
def another_process_open(db: Path) -> Iterator[int]:
    """Another process with the database open (its pid), until the block ends."""
    child = subprocess.Popen([sys.executable, "-c", HOLDER, str(db)], stdin=subprocess.PIPE,
                             stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert child.stdin is not None and child.stdout is not None
    try:
        assert child.stdout.readline() == "open\n"
        yield child.pid
    finally:
        child.stdin.close()
        child.wait(timeout=60)
        child.stdout.close()


def _owned_elsewhere(store: RunStore, run_id: int, host: str | None = None,
                     pidns: str | None = None) -> None:  # fmt: skip
    """``run_id``'s owner as a process of another host or pid namespace would record it."""
    with store.db:
        if host:
            store.db.execute("UPDATE owners SET host = ? WHERE run_id = ?", (host, run_id))
        if pidns:
            store.db.execute("UPDATE owners SET pidns = ? WHERE run_id = ?", (pidns, run_id))


def test_openers_are_the_other_processes_with_the_file_open(
    four_runs: Path, store: RunStore
) -> None:
    # this process's own connection (store's) is no other's
    assert openers(four_runs) == [] and held_elsewhere(four_runs) is False
    with another_process_open(four_runs) as pid:
        assert openers(four_runs) == [pid] and held_elsewhere(four_runs) is True
    assert openers(four_runs) == [] and held_elsewhere(four_runs) is False
    # asking kept this process's own locks: its connection still works, and a vacuum (which
    # needs them) still runs
    store.delete_runs([1])
    store.vacuum()
    assert [r["id"] for r in store.runs()] == [4, 3, 2]


def test_a_process_of_another_pid_namespace_is_seen_though_not_listed(
    four_runs: Path, store: RunStore, monkeypatch: pytest.MonkeyPatch
) -> None:
    """/proc/locks lists only this pid namespace's locks: a service in another container was
    not seen, and a vacuum rewrote the file under it (and `estop --latch` said nothing of it).
    The kernel's lock test sees every process on the machine."""
    import sdh2svc.service.store as store_module

    monkeypatch.setattr(store_module, "openers", lambda path: [])  # as from another namespace
    store.delete_runs([1])
    with another_process_open(four_runs), pytest.raises(RunBusy) as refused:
        store.vacuum()
    assert "in another container or pid namespace" in str(refused.value)
    assert opened_elsewhere(four_runs) is None  # it let go


@pytest.mark.parametrize("where", ["another host", "another pid namespace"])
def test_a_run_whose_process_cannot_be_checked_is_spared_while_its_heartbeat_is_fresh(
    store: RunStore, where: str
) -> None:
    """A service in a container records a run; `runs prune` runs on the host (or the other way
    round): the run's pid means nothing here, and /proc/locks lists no other namespace's locks.
    Its recorder's heartbeat says it is recorded; once the heartbeat is STALE_S old it is not
    (its process died with the container), and it is marked interrupted and may go."""
    run_id = store.create_run({})  # its heartbeat: now
    if where == "another host":
        _owned_elsewhere(store, run_id, host="labpc-container")
    else:  # the same host name, another pid namespace (docker --network host)
        _owned_elsewhere(store, run_id, pidns="pid:[1]")
    assert store.recording() == [run_id]
    assert store.run(run_id)["status"] == "running"  # type: ignore[index]  (read so too)
    assert run_id not in store.prunable(keep=0)
    with pytest.raises(RunBusy, match=f"run {run_id} is being recorded"):
        store.delete_runs([run_id])
    assert store.mark_interrupted() == []  # nor marked interrupted under it
    with store.db:  # its container stopped a while ago
        store.db.execute("UPDATE owners SET seen = ? WHERE run_id = ?",
                         (time.time() - STALE_S - 1, run_id))  # fmt: skip
    assert store.recording() == []
    assert store.run(run_id)["status"] == "interrupted"  # type: ignore[index]
    assert store.mark_interrupted() == [run_id]
    assert store.delete_runs([run_id]) == [run_id]


def test_a_recorder_beats_while_it_has_nothing_to_write(four_runs: Path, store: RunStore) -> None:
    """During a grasp nothing is recorded for seconds: the heartbeat goes on regardless."""
    run_id = store.create_run({})
    with store.db:
        store.db.execute("UPDATE owners SET seen = 0 WHERE run_id = ?", (run_id,))
    rec = Recorder(four_runs, run_id, flush_s=0.01)
    try:
        deadline = time.monotonic() + 60  # (an event awaited, not a time window)
        while _seen(store, run_id) == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert time.time() - _seen(store, run_id) < STALE_S
    finally:
        rec.close()
    assert rec.error is None


def _seen(store: RunStore, run_id: int) -> float:
    row = store.db.execute("SELECT seen FROM owners WHERE run_id = ?", (run_id,)).fetchone()
    return float(row[0])


def test_a_long_run_is_deleted_a_chunk_at_a_time(tmp_path: Path) -> None:
    """Every row goes, in transactions of DELETE_CHUNK rows (a run's start waits for none
    longer than a chunk)."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        run_id = _record(store, iterations=3 * DELETE_CHUNK + 7)
        assert _rows(db, run_id)["frames"] == 3 * DELETE_CHUNK + 7
        statements: list[str] = []
        store.db.set_trace_callback(statements.append)
        assert store.delete_runs([run_id]) == [run_id]
        store.db.set_trace_callback(None)
        assert set(_rows(db, run_id).values()) == {0}
        assert sum("DELETE FROM frames" in q for q in statements) == 4 + 1  # 3 full, 7, none
    finally:
        store.close()


def test_vacuum_is_refused_while_another_process_has_the_file_open(
    four_runs: Path, store: RunStore
) -> None:
    """An idle service holds the file open: a vacuum would hold up its next run's start and an
    e-stop's latch for as long as it copies, and a reader keeps the copy in the log."""
    store.delete_runs([1, 2])
    with another_process_open(four_runs) as pid, pytest.raises(RunBusy) as refused:
        store.vacuum()
    assert f"another program has the run database open (pid {pid}: a running service" in (
        str(refused.value)
    )
    store.vacuum()
    assert store.size()[1] == 0


def test_a_run_is_not_created_while_another_program_holds_the_lock_beyond_the_wait(
    four_runs: Path,
) -> None:
    """The service creates a run on its event loop: it waits a moment for a lock, not
    storage.busy_timeout_s, and a refused creation leaves nothing behind."""
    store = RunStore(four_runs, busy_timeout_s=30.0)
    holder = sqlite3.connect(four_runs, isolation_level=None)
    try:
        holder.execute("BEGIN IMMEDIATE")  # a database browser with unsaved changes
        with pytest.raises(sqlite3.OperationalError, match="locked"):
            store.create_run({}, ("egg", 40.0, [(0.0, 1.0)]), wait_s=0.05)
        holder.execute("ROLLBACK")
        assert [r["id"] for r in store.runs()] == [4, 3, 2, 1]
        assert store.create_run({}, ("egg", 40.0, [(0.0, 1.0)])) == 5
        assert store.outline(5) == {"object": "egg", "size_mm": 40.0, "points": [[0.0, 1.0]]}
    finally:
        holder.close()
        store.close()


def test_a_run_deleted_under_its_recorder_says_its_end_was_not_recorded(
    store: RunStore, caplog: pytest.LogCaptureFixture
) -> None:
    with store.db:  # as another program that deleted it would leave it
        store.db.execute("DELETE FROM runs WHERE id = 4")
    with caplog.at_level(logging.ERROR):
        store.finish_run(4, "completed", {})
    assert "run 4 ended completed, but it is no longer in" in caplog.text


def test_the_command_line_spares_what_the_store_spares(
    four_runs: Path, store: RunStore, capsys: pytest.CaptureFixture[str]
) -> None:
    live = store.create_run({})
    status, _, err = _cli(capsys, four_runs, "delete", str(live), "--dry-run")
    assert status == Exit.FAILED and f"run {live} is being recorded" in err
    store.finish_run(live, "stopped", {})
    store.delete_runs([1])
    with another_process_open(four_runs):
        status, _, err = _cli(capsys, four_runs, "vacuum")
        assert status == Exit.FAILED and "another program has the run database open" in err
    # nothing to prune, and --vacuum still vacuums
    status, _, err = _cli(capsys, four_runs, "prune", "--before", "2000-01-01", "--vacuum")
    assert status == Exit.OK and "no run to delete" in err and " MB → " in err
    with pytest.raises(SystemExit) as bad:
        _cli(capsys, four_runs, "prune", "--before", "1000000d")
    assert bad.value.code == Exit.USAGE
    assert "'1000000d': further back than the calendar goes" in capsys.readouterr().err


def test_an_older_write_protected_database_is_read_as_it_is(four_runs: Path) -> None:
    """An archive made by an older version (no truth, outlines, owners or e-stop tables; fewer
    sample columns), its file write-protected: the reading commands read it as that version
    did, adding nothing to it; deleting from it is refused as read-only. (Root writes anyway:
    its capabilities dropped.)"""
    import hashlib
    import os
    import shutil

    with contextlib.closing(sqlite3.connect(four_runs)) as c:
        c.executescript("""
            DROP TABLE truth; DROP TABLE outlines; DROP TABLE owners; DROP TABLE estop;
            CREATE TABLE old_samples AS SELECT run_id, iteration, t FROM samples;
            DROP TABLE samples; ALTER TABLE old_samples RENAME TO samples;
            PRAGMA wal_checkpoint(TRUNCATE);
        """)  # fmt: skip
        # an archive of it (VACUUM INTO: in the rollback journal's mode, not the log's)
        c.execute(f"VACUUM INTO '{four_runs.with_name('archive.sqlite')}'")
    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-all"] if os.geteuid() == 0 else []
    assert not drop or shutil.which("setpriv"), "setpriv (util-linux) is needed as root"
    for db in (four_runs, four_runs.with_name("archive.sqlite")):
        db.chmod(0o444)
        before = hashlib.sha256(db.read_bytes()).hexdigest()

        def runs(*args: str, db: Path = db) -> subprocess.CompletedProcess[str]:
            where = f"storage.db_path={json.dumps(str(db))}"
            return subprocess.run([*drop, sys.executable, "-m", "sdh2svc", "runs", *args, "--set",
                                   where], capture_output=True, text=True, timeout=60)  # fmt: skip

        listed = runs("list")
        assert listed.returncode == Exit.OK, listed.stderr
        assert [int(line.split()[0]) for line in listed.stdout.splitlines()] == [4, 3, 2, 1]
        shown = runs("show", "2")
        assert shown.returncode == Exit.OK and json.loads(shown.stdout)["id"] == 2, shown.stderr
        csv = runs("export", "2")
        assert csv.returncode == Exit.OK, csv.stderr
        header, first = csv.stdout.splitlines()[:2]
        assert header.startswith("iteration,t [s],") and "object_class" in header  # a newer one
        assert first.startswith("0,0.0,")
        for delete in (["delete", "2"], ["delete", "2", "--dry-run"]):  # the dry run says so too
            refused = runs(*delete)
            assert refused.returncode == Exit.UNAVAILABLE, refused.stderr
            assert f"{db} is write-protected: make it writable" in refused.stderr
        assert hashlib.sha256(db.read_bytes()).hexdigest() == before  # nothing written
        # nor beside it: a log and its index left there, write-protected as the file, made
        # every writer fail once the file was writable again (CLI audit)
        assert sorted(p.name for p in db.parent.iterdir() if p.name.startswith(db.name)) == [
            db.name]  # fmt: skip
        db.chmod(0o644)
        assert runs("delete", "2").returncode == Exit.OK


def test_write_protected_logs_left_beside_a_writable_database_are_named(four_runs: Path) -> None:
    """What an older version's reading left beside a file that was write-protected then: the
    writers failed with "attempt to write a readonly database", naming the (writable) file."""
    import os
    import shutil

    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-all"] if os.geteuid() == 0 else []
    assert not drop or shutil.which("setpriv"), "setpriv (util-linux) is needed as root"
    with contextlib.closing(sqlite3.connect(four_runs)) as c:  # as that reading left them
        c.execute("SELECT COUNT(*) FROM runs").fetchone()
        shutil.copy(f"{four_runs}-shm", f"{four_runs}-shm.kept")
    os.replace(f"{four_runs}-shm.kept", f"{four_runs}-shm")
    Path(f"{four_runs}-shm").chmod(0o444)
    where = f"storage.db_path={json.dumps(str(four_runs))}"
    r = subprocess.run([*drop, sys.executable, "-m", "sdh2svc", "runs", "delete", "2", "--set",
                        where], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert "runs.sqlite-shm beside it is write-protected" in r.stderr
    assert "delete it while nothing has the database open" in r.stderr


def test_a_database_in_a_write_protected_folder_is_read_as_immutable(
    four_runs: Path, tmp_path: Path
) -> None:
    """A read-only share: SQLite cannot make the log's index beside the file, and every
    statement failed. Nobody can write there, so the file is read as immutable; unless a log
    beside it still holds pages, which that would skip: then it says to copy both."""
    import os
    import shutil

    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-all"] if os.geteuid() == 0 else []
    assert not drop or shutil.which("setpriv"), "setpriv (util-linux) is needed as root"
    shares = []
    for name, wal in (("share", b""), ("busy", b"pages not yet in the file")):
        share = tmp_path / name
        share.mkdir()
        shutil.copy(four_runs, share / "runs.sqlite")
        if wal:
            (share / "runs.sqlite-wal").write_bytes(wal)
        share.chmod(0o555)
        shares.append(share / "runs.sqlite")

    def runs(db: Path, *args: str) -> subprocess.CompletedProcess[str]:
        where = f"storage.db_path={json.dumps(str(db))}"
        return subprocess.run([*drop, sys.executable, "-m", "sdh2svc", "runs", *args, "--set",
                               where], capture_output=True, text=True, timeout=60)  # fmt: skip

    listed = runs(shares[0], "list")
    assert listed.returncode == Exit.OK, listed.stderr
    assert [int(line.split()[0]) for line in listed.stdout.splitlines()] == [4, 3, 2, 1]
    assert sorted(p.name for p in shares[0].parent.iterdir()) == ["runs.sqlite"]
    for delete in (["delete", "2"], ["prune", "--keep", "1", "--dry-run"]):  # nobody writes there
        refused = runs(shares[0], *delete)
        assert refused.returncode == Exit.UNAVAILABLE, refused.stderr
        assert f"{shares[0]} is in a write-protected folder" in refused.stderr
    busy = runs(shares[1], "list")
    assert busy.returncode == Exit.UNAVAILABLE
    assert "runs.sqlite-wal beside it holds pages not yet in it" in busy.stderr
