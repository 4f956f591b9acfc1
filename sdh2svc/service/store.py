"""Every run in a real SQLite file: metadata and parameters, one row per iteration, the events,
the raw tactile frames, in simulation the object's truth (its outline once, in its own frame;
its pose and state per iteration) — and exports to CSV and MCAP.

An older file gets the tables and columns it lacks when it is opened (:func:`connect`).

Durability: :class:`Recorder` writes from its own thread in small transactions, at least every
``flush_s`` (50 ms); SQLite in WAL mode keeps every committed transaction through a ``kill -9``
of the process, so everything recorded more than ~100 ms before a crash is on disk.
"""

from __future__ import annotations

import contextlib
import csv
import json
import logging
import math
import os
import socket
import sqlite3
import struct
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from datetime import UTC, datetime
from enum import Enum
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import numpy as np

from sdh2svc.control.sample import Sample

log = logging.getLogger(__name__)

if TYPE_CHECKING:
    from sdh2svc.config import Settings

SAMPLE_COLUMNS = Sample.columns()
_ROWS_PER_INSERT = 200  # rows in one multi-row INSERT (within SQLite's variable limit)
_QUOTED = ", ".join(f'"{c}"' for c in SAMPLE_COLUMNS)
#: A recorded iteration's truth (simulation): the object's centre y, z (mm, frame 0), its angle
#: ψ (rad), whether held by the fingers, dropped or still in the fixture, and its slips so far.
TRUTH_COLUMNS = ("iteration", "t", "y", "z", "psi", "held", "dropped", "in_fixture", "slips")
_TRUTH_BOOLS = ("held", "dropped", "in_fixture")

SCHEMA = f"""
CREATE TABLE IF NOT EXISTS runs (
    id INTEGER PRIMARY KEY AUTOINCREMENT,
    started_at TEXT NOT NULL,
    ended_at TEXT,
    status TEXT NOT NULL,
    meta TEXT NOT NULL,
    summary TEXT
);
CREATE TABLE IF NOT EXISTS samples (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    {_QUOTED}
);
CREATE INDEX IF NOT EXISTS samples_run ON samples(run_id, iteration);
CREATE TABLE IF NOT EXISTS events (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    t REAL NOT NULL,
    iteration INTEGER,
    kind TEXT NOT NULL,
    detail TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS frames (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    t REAL NOT NULL,
    iteration INTEGER,
    timestamp_ms INTEGER NOT NULL,
    texels BLOB NOT NULL
);
CREATE INDEX IF NOT EXISTS frames_run ON frames(run_id, t);
CREATE TABLE IF NOT EXISTS truth (
    run_id INTEGER NOT NULL REFERENCES runs(id),
    iteration INTEGER NOT NULL,
    t REAL,
    y REAL NOT NULL,
    z REAL NOT NULL,
    psi REAL NOT NULL,
    held INTEGER NOT NULL,
    dropped INTEGER NOT NULL,
    in_fixture INTEGER NOT NULL,
    slips INTEGER NOT NULL
);
CREATE INDEX IF NOT EXISTS truth_run ON truth(run_id, iteration);
CREATE TABLE IF NOT EXISTS outlines (
    run_id INTEGER PRIMARY KEY REFERENCES runs(id),
    object TEXT NOT NULL,
    size_mm REAL NOT NULL,
    points TEXT NOT NULL
);
CREATE TABLE IF NOT EXISTS estop (
    id INTEGER PRIMARY KEY CHECK (id = 1),
    since TEXT NOT NULL,
    reason TEXT NOT NULL
);
-- the programs that stopped their hand for a latch another program wrote (sdh2svc estop --latch)
CREATE TABLE IF NOT EXISTS estop_taken (
    since TEXT NOT NULL,
    program TEXT NOT NULL,
    at TEXT NOT NULL,
    hand_reached INTEGER NOT NULL
);
CREATE TABLE IF NOT EXISTS owners (
    run_id INTEGER PRIMARY KEY REFERENCES runs(id),
    host TEXT NOT NULL,
    pid INTEGER NOT NULL,
    started TEXT NOT NULL,
    pidns TEXT,
    seen REAL
);
"""
# A run's recorder writes the time to its owner's row (``seen``, epoch seconds) at least this
# often; a run marked 'running' whose owner's process cannot be checked from here (another
# container or machine) is taken as recorded until the time is this old. A heartbeat works
# across containers, where a pid means nothing and /proc/locks lists no other namespace's locks.
HEARTBEAT_S = 1.0
# the summary of a run whose process died during it (nothing ended it to write its own)
INTERRUPTED = ("the process recording this run stopped during it (killed or crashed): the fingers "
               "stopped where they were and may still hold the object")  # fmt: skip
STALE_S = 30.0
DELETE_CHUNK = 1000  # rows deleted per transaction: a recorder or a run's start waits ~10 ms
# Indexes a later version added: made by a writer (the service, a run), never by a reading
# command, which an older database on a read-only medium must not fail
WRITER_INDEXES = "CREATE INDEX IF NOT EXISTS events_run ON events(run_id);"


def _process_start(pid: int) -> str | None:
    """When the process ``pid`` started, as the kernel counts it (/proc/PID/stat's field 22,
    clock ticks since boot: a later process with the same pid has another), or None where there
    is no such entry."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return stat.rsplit(")", 1)[1].split()[19]  # the fields after the command's name start at 3


def _pid_namespace() -> str:
    """The calling process's pid namespace ("pid:[4026531836]"; "" where there is no /proc):
    a pid means the same process only within one."""
    try:
        return os.readlink("/proc/self/ns/pid")
    except OSError:
        return ""


def _this_process() -> tuple[str, int, str, str]:
    """(host, pid, start, pid namespace) of the calling process: who records a run it
    creates."""
    pid = os.getpid()
    return socket.gethostname(), pid, _process_start(pid) or "", _pid_namespace()


class Owner(Enum):
    """What can be told here of the process that recorded a run."""

    ALIVE = "alive"
    DEAD = "dead"
    UNKNOWN = "unknown"  # another machine or container, or none recorded: not to be checked


def _owner_state(
    host: str | None, pid: int | None, started: str | None, pidns: str | None = None
) -> Owner:
    """Whether the process that recorded a run still runs, as far as this process can tell.
    Its pid means something here only on this host (SQLite's WAL keeps a run database on one
    machine; a container has a host name of its own) and in this pid namespace (``pidns``: as
    recorded since it was; a run recorded before is taken to be of this one)."""
    if host is None or pid is None or host != socket.gethostname():
        return Owner.UNKNOWN
    if pidns and pidns != _pid_namespace():
        return Owner.UNKNOWN
    now = _process_start(pid)
    if now is not None:
        return Owner.ALIVE if not started or now == started else Owner.DEAD
    if Path("/proc/self/stat").exists():
        return Owner.DEAD  # /proc lists every live process: this one is gone
    try:
        os.kill(pid, 0)  # no /proc: ask the kernel whether the pid is in use
    except ProcessLookupError:
        return Owner.DEAD
    except PermissionError:
        return Owner.ALIVE
    return Owner.ALIVE


def _owner_now(
    host: str | None, pid: int | None, started: str | None, pidns: str | None,
    seen: float | None, now: float,
) -> Owner:  # fmt: skip
    """ALIVE or DEAD: the owner's state, one that cannot be checked from here (another
    container or machine, or none recorded) told by its recorder's heartbeat ``seen`` (alive
    while younger than STALE_S at ``now``; a run of an older version has none: dead)."""
    owner = _owner_state(host, pid, started, pidns)
    if owner is Owner.UNKNOWN:
        return Owner.ALIVE if seen is not None and now - seen < STALE_S else Owner.DEAD
    return owner


def opened_elsewhere(path: Path) -> str | None:
    """ "another program has the run database open (pid …: a running service, a reader)", or
    None when no other process on this machine has it open — in this pid namespace or another
    (a container's service: :func:`held_elsewhere`)."""
    others = openers(path)
    if others:
        who = ", ".join(str(pid) for pid in others if pid) or "in another container"
        return f"another program has the run database open (pid {who}: a running service, a reader)"
    if held_elsewhere(path):
        return ("another program has the run database open (in another container or pid "
                "namespace, so its pid cannot be told: a running service, a reader)")  # fmt: skip
    return None


# The -shm files held_elsewhere asks about, by (device, inode), each open for as long as this
# process runs: closing any descriptor of a file drops every POSIX lock this process holds on it,
# among them its own SQLite connections' locks on that very file.
_shm_fds: dict[tuple[int, int], int] = {}
_FLOCK = "hhqqi4x"  # Linux's struct flock: l_type, l_whence, l_start, l_len, l_pid


def held_elsewhere(path: Path) -> bool | None:
    """Whether another process holds the run database at ``path`` open, wherever it runs on this
    machine: asked of the kernel (F_GETLK) for a lock on byte 128 of the ``-shm`` file, where
    every SQLite connection in WAL mode holds a read lock for as long as it is open. Unlike
    /proc/locks (:func:`openers`) this sees processes of other pid namespaces too, but not who
    they are. This process's own locks never count. None where that cannot be told (not Linux,
    the file unreadable)."""
    if sys.platform != "linux":
        return None
    import fcntl  # (Linux only: so is the struct)

    shm = f"{path}-shm"
    try:
        st = os.stat(shm)
    except FileNotFoundError:
        return False  # nobody has it open (the last connection to close removes it)
    except OSError:
        return None
    key = (st.st_dev, st.st_ino)
    fd = _shm_fds.get(key)
    if fd is None:
        try:
            fd = _shm_fds.setdefault(key, os.open(shm, os.O_RDONLY | os.O_CLOEXEC))
        except OSError:
            return None
    query = struct.pack(_FLOCK, fcntl.F_WRLCK, os.SEEK_SET, 128, 1, 0)
    try:
        answer = fcntl.fcntl(fd, fcntl.F_GETLK, query)
    except OSError:
        return None
    return bool(struct.unpack(_FLOCK, answer)[0] != fcntl.F_UNLCK)


def openers(path: Path) -> list[int] | None:
    """The other processes of this pid namespace that have the run database at ``path`` open
    (their pids), from the kernel's list of file locks: in WAL mode every SQLite connection
    holds a read lock on byte 128 of the ``-shm`` file for as long as it is open. Another
    container's processes are not listed (/proc/locks shows only this namespace's). None where
    that cannot be told (no /proc/locks). Read from /proc, never by locking: closing a
    descriptor of the file would drop this process's own SQLite locks on it."""
    try:
        st = os.stat(f"{path}-shm")
        table = Path("/proc/locks").read_text()
    except FileNotFoundError:
        return [] if Path("/proc/locks").exists() else None  # no -shm: nobody has it open
    except OSError:
        return None
    inode = f"{os.major(st.st_dev):02x}:{os.minor(st.st_dev):02x}:{st.st_ino}"
    me, pids = os.getpid(), []
    for line in table.splitlines():
        f = line.split()
        if "->" in f:  # a waiter, listed after the lock it waits for
            continue
        try:
            pid, where, start, end = int(f[4]), f[5], int(f[6]), f[7]
        except (IndexError, ValueError):
            continue
        if where == inode and pid != me and start <= 128 and (end == "EOF" or int(end) >= 128):
            pids.append(pid)
    return sorted(set(pids))


class StoreError(Exception):
    """The run database cannot be opened or read; the message names the path and why."""


class EstopLatched(Exception):
    """A run was refused: the e-stop is latched in the run database."""

    def __init__(self, latch: dict[str, str]) -> None:
        self.latch = latch
        super().__init__(f"the e-stop is latched (since {latch['since']}: {latch['reason']}); "
                         "release it with `sdh2svc estop --release` or, with the service "
                         "running, POST /api/estop/release")  # fmt: skip


class RunBusy(StoreError):
    """A run is being recorded (by this process or another live one on the same file): it
    cannot be deleted, nor the file vacuumed under it."""


class NoDatabase(StoreError):
    """There is no run database at the path (and the caller only reads: none was created)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        super().__init__(f"no run database at {path}")


def connect(
    path: str | Path, *, create: bool = True, busy_timeout_s: float = 10.0
) -> sqlite3.Connection:
    """Open the run database; WAL so a reader never blocks the recorder.

    ``create=True`` (the recorder, the service, ``sdh2svc run``) creates the file, its directory
    and the tables as needed. ``create=False`` (reading commands) creates no file or folder: a
    missing file raises :class:`NoDatabase`, a file without the ``runs`` table
    :class:`StoreError`. An older version's file is brought up to date (the tables and sample
    columns it lacks added) where it is writable, as opening it with the service would; a
    write-protected one is read as it is (:func:`_read_as_current`); the writer's own index
    and owner columns only a writer adds. Anything unusable — a directory, an unwritable place,
    a file that is not SQLite — raises :class:`StoreError` naming the path and the reason.
    """
    p = Path(path)
    if not create and not p.exists():
        raise NoDatabase(p)
    if p.is_dir():
        raise StoreError(f"cannot open the run database {p}: it is a directory")
    for parent in p.parents:  # the nearest existing ancestor must be a directory
        if parent.exists():
            if not parent.is_dir():
                raise StoreError(f"cannot open the run database {p}: {parent} is not a directory")
            break
    db: sqlite3.Connection | None = None
    try:
        if create:
            p.parent.mkdir(parents=True, exist_ok=True)
        if not create and _write_protected_alone(p):
            # read as it is: opened as usual, SQLite would leave a log and its index beside it,
            # as write-protected as the file, and once the file was writable again every writer
            # failed on them ("attempt to write a readonly database")
            db = _immutable(p)
        else:
            uri = f"{p.absolute().as_uri()}?mode={'rwc' if create else 'rw'}"
            db = sqlite3.connect(uri, uri=True, check_same_thread=False, timeout=busy_timeout_s)
        try:
            db.execute("PRAGMA journal_mode=WAL")
        except sqlite3.OperationalError as e:
            # a write-protected file in rollback-journal mode (an archive made by VACUUM INTO,
            # a copy): read in the mode it is in; in a write-protected folder (a read-only
            # share), where SQLite cannot make the log's index beside it: read as immutable
            code = e.sqlite_errorcode
            if (
                code == sqlite3.SQLITE_CANTOPEN
                and Path(f"{p}-wal").exists()
                and not os.access(p.parent, os.W_OK)
            ):
                code = sqlite3.SQLITE_READONLY_DIRECTORY  # (a log it cannot index there)
            if create or code not in _READONLY_PLACES:
                raise
            if code != sqlite3.SQLITE_READONLY:
                db.close()
                db = _immutable(p)
        db.execute("PRAGMA synchronous=NORMAL")
        if not create and not _has_runs_table(db):
            raise StoreError(f"{p} is not a run database (it has no runs table)")
        _check_tables(db, p)  # before a table of another shape is added to
        try:
            db.executescript(SCHEMA)
            _add_new_sample_columns(db)
        except sqlite3.OperationalError as e:
            # an older file nobody may write (an archive): a reading command reads it as it
            # is, with what a newer version added to the schema in its place
            if create or e.sqlite_errorcode != sqlite3.SQLITE_READONLY:
                raise
            _read_as_current(db)
        if create:
            _check_writable(db, busy_timeout_s)
            db.executescript(WRITER_INDEXES)  # (events_run: a deleted run's events found at once)
            have = _columns(db, "owners")
            for column, kind in (("pidns", "TEXT"), ("seen", "REAL")):
                if column not in have:
                    db.execute(f"ALTER TABLE owners ADD COLUMN {column} {kind}")
    except (OSError, sqlite3.Error) as e:
        if db is not None:
            db.close()
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e)
        raise StoreError(f"cannot open the run database {p}: {why}{stray_logs(p)}"
                         f"{_no_room(p)}") from None  # fmt: skip
    except BaseException:
        if db is not None:
            db.close()
        raise
    db.row_factory = sqlite3.Row
    return db


# a reading command's file it may not write (SQLITE_READONLY), or whose folder it may not write
# either (no -shm for the log's index: DIRECTORY, CANTINIT)
_READONLY_PLACES = (sqlite3.SQLITE_READONLY, sqlite3.SQLITE_READONLY_DIRECTORY,
                    sqlite3.SQLITE_READONLY_CANTINIT)  # fmt: skip


def _write_protected_alone(p: Path) -> bool:
    """A file this process may not write, with no log or log index beside it: nothing writes
    it, and it is read whole from the file itself."""
    return (p.is_file() and not os.access(p, os.W_OK)
            and not any(Path(f"{p}{end}").exists() for end in ("-wal", "-shm")))  # fmt: skip


NO_ROOM_B = 1 << 20  # a disk with less free than this cannot take a log's index and pages


def _no_room(p: Path) -> str:
    """Says that the disk holding ``p`` is full ("" if it has room, or cannot be asked):
    SQLite says "disk I/O error" when it cannot size the log's index there, even to read."""
    try:
        st = os.statvfs(p.parent if not p.is_dir() else p)
    except OSError:
        return ""
    free = st.f_bavail * st.f_frsize
    if free >= NO_ROOM_B:
        return ""
    return (
        f" (the disk holding it is full: {free // 1024} KiB free; make room there, then try again)"
    )


def _file_identity(p: Path) -> tuple[int, int] | None:
    """The file at ``p`` (device, inode); None if there is none."""
    try:
        st = p.stat()
    except OSError:
        return None
    return st.st_dev, st.st_ino


def stray_logs(p: Path) -> str:
    """Says which log files beside a writable database this process may not write ("" if
    none): what an older version's reading of the file while it was write-protected left."""
    if not p.is_file() or not os.access(p, os.W_OK):
        return ""
    stray = [f"{p.name}{end}" for end in ("-wal", "-shm")
             if Path(f"{p}{end}").exists() and not os.access(f"{p}{end}", os.W_OK)]  # fmt: skip
    if not stray:
        return ""
    it, are = ("it", "is") if len(stray) == 1 else ("them", "are")
    return (f" ({' and '.join(stray)} beside it {are} write-protected, left by reading the file "
            f"while it was: delete {it} while nothing has the database open, or make {it} "
            "writable)")  # fmt: skip


def _immutable(p: Path) -> sqlite3.Connection:
    """A database nobody may write (its folder or the file itself write-protected), opened as
    immutable (no lock, no log index): nothing can be writing it. A log beside it that still
    holds pages would be skipped, so such a file is refused rather than read without them."""
    wal = Path(f"{p}-wal")
    if wal.exists() and wal.stat().st_size > 0:
        raise StoreError(f"cannot read the run database {p} where it is: its folder is "
                         f"write-protected and {wal.name} beside it holds pages not yet in it; "
                         "copy both to a writable folder")  # fmt: skip
    uri = f"{p.absolute().as_uri()}?mode=ro&immutable=1"
    return sqlite3.connect(uri, uri=True, check_same_thread=False)


def _check_writable(db: sqlite3.Connection, busy_timeout_s: float) -> None:
    """SQLite opens a write-protected file read-only without a word, and the first write — a
    run's start, or its end — fails: find out now, with a write that changes nothing. A lock
    another program holds is no answer either way (and is not waited for)."""
    db.execute("PRAGMA busy_timeout = 0")
    try:
        version = int(db.execute("PRAGMA user_version").fetchone()[0])
        db.execute(f"PRAGMA user_version = {version}")
    except sqlite3.OperationalError as e:
        if read_only(e):
            raise
    finally:
        db.execute(f"PRAGMA busy_timeout = {round(busy_timeout_s * 1000)}")


def _columns(db: sqlite3.Connection, table: str) -> set[str]:
    return {row[1] for row in db.execute(f"PRAGMA table_info({table})")}


def _read_as_current(db: sqlite3.Connection) -> None:
    """An older database opened read-only, shown to the readers as the current schema: each
    table it lacks as an empty temporary one, and its samples through a temporary view that
    adds the newer Sample columns as nulls (temporary objects live in memory and come before
    the file's own under the same name). Nothing is written to the file."""
    db.rollback()  # (the failed statement's transaction, if any)
    for statement in SCHEMA.split(";"):
        words = statement.split()
        if words[:5] == ["CREATE", "TABLE", "IF", "NOT", "EXISTS"] and not _columns(db, words[5]):
            db.execute(statement.replace("CREATE TABLE", "CREATE TEMP TABLE", 1))
    missing = [c for c in SAMPLE_COLUMNS if c not in _columns(db, "samples")]
    if missing:
        nulls = ", ".join(f'NULL AS "{c}"' for c in missing)
        db.execute(f"CREATE TEMP VIEW samples AS SELECT *, {nulls} FROM main.samples")
    db.execute("PRAGMA query_only = ON")  # a write is refused as read-only, not by the shims


def _add_new_sample_columns(db: sqlite3.Connection) -> None:
    """A database made before a Sample field was added gets its column (null in older rows)."""
    have = _columns(db, "samples")
    for column in SAMPLE_COLUMNS:
        if column not in have:
            db.execute(f'ALTER TABLE samples ADD COLUMN "{column}"')


# the columns every version's tables have had (a table of the same name without them is someone
# else's, or a newer version's: not read, and nothing added to it)
_KEY_COLUMNS = {
    "runs": {"id", "started_at", "ended_at", "status", "meta", "summary"},
    "samples": {"run_id", "iteration", "t"},
    "frames": {"run_id", "t", "iteration", "timestamp_ms", "texels"},
    "events": {"run_id", "t", "iteration", "kind", "detail"},
}


def _check_tables(db: sqlite3.Connection, p: Path) -> None:
    for table, need in _KEY_COLUMNS.items():
        have = _columns(db, table)
        if have and not need <= have:
            raise StoreError(f"{p} is not a run database this version can read: its {table} "
                             f"table lacks {', '.join(sorted(need - have))}")  # fmt: skip


def _has_runs_table(db: sqlite3.Connection) -> bool:
    row = db.execute("SELECT 1 FROM sqlite_master WHERE type = 'table' AND name = 'runs'")
    return row.fetchone() is not None


def now_iso() -> str:
    """Now, local time with its UTC offset, to the millisecond (an MCAP export's time base)."""
    now = time.time()
    local = time.localtime(now)
    ms = int(now % 1 * 1000)
    return time.strftime("%Y-%m-%dT%H:%M:%S", local) + f".{ms:03d}" + time.strftime("%z", local)


class RunStore:
    """Reads and the occasional write (run creation, finish) of the run database."""

    def __init__(
        self, path: str | Path, *, create: bool = True, busy_timeout_s: float = 10.0
    ) -> None:
        """Open the database at ``path``; ``create=False``: only an existing one (see
        :func:`connect`); a write waits up to ``busy_timeout_s`` for another program's lock."""
        self.path, self.busy_timeout_s = Path(path), busy_timeout_s
        self.db = connect(path, create=create, busy_timeout_s=busy_timeout_s)
        self._lock = threading.Lock()
        self._identity = _file_identity(self.path)  # the file opened (see :meth:`replaced`)

    def replaced(self) -> bool:
        """Whether ``path`` no longer names the file this store has open: deleted, renamed or
        replaced while it was open. Its writes then go to a file nobody finds there."""
        return _file_identity(self.path) != self._identity

    def _follow_path(self) -> None:
        """The file at ``path`` opened again if it is no longer the one open (a new one made if
        there is none there): what goes where a restart looks — an e-stop's latch, which a
        restart did not see after the file had been renamed under the service, and a new
        run's row, whose samples the recorder (which opens the path) wrote into another file
        without it. The caller holds the store's lock."""
        if not self.replaced():
            return
        log.error("the run database %s was deleted, renamed or replaced while it was open: "
                  "runs and the e-stop latch now go to the file at that path (a new one if "
                  "there is none)", self.path)  # fmt: skip
        self.db.close()
        self.db = connect(self.path, create=True, busy_timeout_s=self.busy_timeout_s)
        self._identity = _file_identity(self.path)

    def close(self) -> None:
        """Close the connection once a write in another thread is done with it (an e-stop's
        latch waiting for another program's lock: closed under it, SQLite crashed the process
        and the latch could be lost)."""
        with self._lock:
            self.db.close()

    def create_run(
        self,
        meta: dict[str, Any],
        outline: tuple[str, float, list[tuple[float, float]]] | None = None,
        wait_s: float | None = None,
    ) -> int:
        """A new run, 'running', owned by this process (see :meth:`mark_interrupted`), with
        its object's ``outline`` (:meth:`set_outline`'s name, size, points) in the same
        transaction. ``wait_s``: how long to wait for another program's lock (default
        ``busy_timeout_s``): sqlite3.OperationalError ("database is locked") after it, and
        nothing written."""
        with self._lock:
            self._follow_path()
            with self._waiting(wait_s), self.db:
                cur = self.db.execute(
                    "INSERT INTO runs (started_at, status, meta) VALUES (?, 'running', ?)",
                    (now_iso(), json.dumps(meta)),
                )
                run_id = cur.lastrowid
                assert run_id is not None
                self.db.execute("INSERT INTO owners (run_id, host, pid, started, pidns, seen) "
                                "VALUES (?, ?, ?, ?, ?, ?)",
                                (run_id, *_this_process(), time.time()))  # fmt: skip
                if outline is not None:
                    self._insert_outline(run_id, *outline)
        return run_id

    @contextlib.contextmanager
    def _waiting(self, wait_s: float | None) -> Iterator[None]:
        """A lock held by another program waited for ``wait_s`` (None: busy_timeout_s)."""
        if wait_s is None:
            yield
            return
        self.db.execute(f"PRAGMA busy_timeout = {round(wait_s * 1000)}")
        try:
            yield
        finally:
            self.db.execute(f"PRAGMA busy_timeout = {round(self.busy_timeout_s * 1000)}")

    def finish_run(self, run_id: int, status: str, summary: dict[str, Any]) -> None:
        with self._lock, self.db:
            done = self.db.execute(
                "UPDATE runs SET status = ?, ended_at = ?, summary = ? WHERE id = ?",
                (status, now_iso(), json.dumps(summary), run_id),
            ).rowcount
        if not done:  # deleted meanwhile, by a program that could not tell it was recorded
            log.error("run %d ended %s, but it is no longer in %s: its end is not recorded",
                      run_id, status, self.path)  # fmt: skip

    def mark_interrupted(self) -> list[int]:
        """Runs left 'running' by a process that died (killed, crashed, the PC lost power):
        mark them so (their data stays). A run another live process records (a second service,
        an ``sdh2svc run``, on the same file) is left running, and so is one whose process
        cannot be checked from here (another container) while its recorder's heartbeat is
        fresh."""
        with self._lock, self.db:
            ids = [i for i, owner in self._owners_of_running() if owner is Owner.DEAD]
            summary = json.dumps(_interrupted_summary())
            self.db.executemany("UPDATE runs SET status = 'interrupted', "
                                "summary = COALESCE(summary, ?) WHERE id = ?",
                                [(summary, i) for i in ids])  # fmt: skip
        return ids

    def _owners_of_running(self) -> list[tuple[int, Owner]]:
        """The runs marked 'running' with their owners' state (:func:`_owner_now`)."""
        rows = self.db.execute(
            f"SELECT r.id, {self._owner_columns} FROM runs r "
            "LEFT JOIN owners o ON o.run_id = r.id WHERE r.status = 'running'"
        ).fetchall()
        now = time.time()
        return [(run_id, _owner_now(host, pid, started, pidns, seen, now))
                for run_id, host, pid, started, pidns, seen in rows]  # fmt: skip

    @property
    def _owner_columns(self) -> str:
        """The owner's host, pid, started, pidns, seen (NULL for a column an older database
        lacks: a reading command adds none)."""
        have = _columns(self.db, "owners")
        return ", ".join(f"o.{c}" if c in have else "NULL"
                         for c in ("host", "pid", "started", "pidns", "seen"))  # fmt: skip

    # --- the e-stop latch: durable until an explicit release ------------------------------------

    def estop_latch(self) -> dict[str, str] | None:
        """The latched e-stop (``since``, ``reason``), or None when released."""
        row = self.db.execute("SELECT since, reason FROM estop WHERE id = 1").fetchone()
        return None if row is None else {"since": row["since"], "reason": row["reason"]}

    def estop_latch_held(self) -> dict[str, str] | None:
        """:meth:`estop_latch` from another thread: under the store's lock, so never on a
        connection :meth:`close` is closing (SQLite crashed the process)."""
        with self._lock:
            return self.estop_latch()

    def latch_estop(self, reason: str, since: str | None = None) -> dict[str, str]:
        """Latch the e-stop on disk before anything else happens: fsync'd (synchronous=FULL),
        so a restart — or the PC losing power — finds it still latched. ``since``: when it was
        pressed (default: now; a write that waited for a lock is later). Returns the latch (the
        first one's time and reason, if it was latched already)."""
        with self._lock:  # the read back too: :meth:`close` waits for both
            self._follow_path()
            self._durably_locked("INSERT OR IGNORE INTO estop (id, since, reason) VALUES "
                                 "(1, ?, ?)", (since or now_iso(), reason))  # fmt: skip
            latch = self.estop_latch()
        assert latch is not None
        return latch

    def release_estop(self) -> None:
        with self._lock:
            self._follow_path()
            self._durably_locked("DELETE FROM estop", more=("DELETE FROM estop_taken",))

    def took_estop(self, since: str, program: str, hand_reached: bool) -> None:
        """``program`` (e.g. "the service (pid 12 on lab-pc)") stopped its hand for the latch
        pressed at ``since``, which another program wrote: what ``sdh2svc estop --latch`` waits
        for. Nothing is written once that latch is gone (released meanwhile)."""
        with self._lock, self.db:
            self.db.execute("INSERT INTO estop_taken (since, program, at, hand_reached) SELECT "
                            "?, ?, ?, ? WHERE EXISTS (SELECT 1 FROM estop WHERE since = ?)",
                            (since, program, now_iso(), int(hand_reached), since))  # fmt: skip

    def estop_takers(self, since: str) -> list[dict[str, Any]]:
        """The programs that stopped their hand for the latch pressed at ``since`` (oldest
        first): ``program``, ``at``, ``hand_reached``."""
        rows = self.db.execute("SELECT program, at, hand_reached FROM estop_taken WHERE since = ? "
                               "ORDER BY rowid", (since,))  # fmt: skip
        return [{"program": r["program"], "at": r["at"], "hand_reached": bool(r["hand_reached"])}
                for r in rows]  # fmt: skip

    def _durably_locked(
        self, sql: str, params: tuple[Any, ...] = (), more: tuple[str, ...] = ()
    ) -> None:
        """One write (and ``more`` statements in its transaction), fsync'd before it returns
        (synchronous=FULL for this transaction); the caller holds the store's lock."""
        self.db.execute("PRAGMA synchronous=FULL")
        try:
            with self.db:
                self.db.execute(sql, params)
                for statement in more:
                    self.db.execute(statement)
        finally:
            self.db.execute("PRAGMA synchronous=NORMAL")

    def sample_count(self, run_id: int) -> int:
        row = self.db.execute("SELECT COUNT(*) FROM samples WHERE run_id = ?", (run_id,)).fetchone()
        return int(row[0])

    # a run as read: 'running' only while its owner lives (read-only: mark_interrupted writes)
    def _run_select(self) -> str:
        return ("SELECT r.*, (SELECT COUNT(*) FROM samples s WHERE s.run_id = r.id) AS "
                f"iterations, {self._owner_columns} FROM runs r "
                "LEFT JOIN owners o ON o.run_id = r.id")  # fmt: skip

    def runs(self) -> list[dict[str, Any]]:
        rows = self.db.execute(self._run_select() + " ORDER BY r.id DESC").fetchall()
        return [self._run_dict(r) for r in rows]

    def run(self, run_id: int) -> dict[str, Any] | None:
        r = self.db.execute(self._run_select() + " WHERE r.id = ?", (run_id,)).fetchone()
        return None if r is None else self._run_dict(r)

    def record(self, run_id: int) -> dict[str, Any] | None:
        """One run as ``GET /api/runs/{id}`` and ``sdh2svc runs show`` give it: :meth:`run`
        and its ``events``."""
        run = self.run(run_id)
        if run is not None:
            run["events"] = self.events(run_id)
        return run

    @staticmethod
    def _run_dict(r: sqlite3.Row) -> dict[str, Any]:
        *fields, host, pid, started, pidns, seen = tuple(r)
        d = dict(zip(r.keys()[: len(fields)], fields, strict=True))
        owner = _owner_now(host, pid, started, pidns, seen, time.time())
        if d["status"] == "running" and owner is not Owner.ALIVE:
            d["status"] = "interrupted"  # its process died; the next service or run marks it
        d["meta"] = json.loads(d["meta"])
        d["summary"] = json.loads(d["summary"]) if d["summary"] else None
        if d["status"] == "interrupted" and d["summary"] is None:  # as mark_interrupted writes
            d["summary"] = _interrupted_summary()
        return d

    def run_page(self, limit: int, before: int | None = None) -> tuple[list[dict[str, Any]], int]:
        """Up to ``limit`` runs, newest first, of ids below ``before`` (None: from the newest),
        and how many runs the database holds in all."""
        where, args = ("", ()) if before is None else (" WHERE r.id < ?", (before,))
        rows = self.db.execute(self._run_select() + where + " ORDER BY r.id DESC LIMIT ?",
                               (*args, limit)).fetchall()  # fmt: skip
        total = int(self.db.execute("SELECT COUNT(*) FROM runs").fetchone()[0])
        return [self._run_dict(r) for r in rows], total

    # --- retention: a run deleted with everything recorded with it; the file shrunk ------------

    def recording(self) -> list[int]:
        """The runs being recorded now: marked 'running', their process alive — or, one that
        cannot be checked from here (another container), its recorder's heartbeat fresh."""
        return [i for i, owner in self._owners_of_running() if owner is Owner.ALIVE]

    def prunable(self, keep: int | None = None, before: datetime | None = None) -> list[int]:
        """The runs a prune deletes, oldest first: all but the newest ``keep`` (None: no count
        kept), and of those only the ones started before ``before`` (None: any time); never
        one being recorded. ValueError for a ``before`` without its time zone."""
        if before is not None and before.tzinfo is None:
            raise ValueError("give `before` with its time zone")
        rows = self.db.execute("SELECT id, started_at FROM runs ORDER BY id DESC").fetchall()
        busy = set(self.recording())
        old = rows[keep or 0 :]
        return sorted(
            r["id"] for r in old
            if r["id"] not in busy and (before is None or _started(r["started_at"]) < before)
        )  # fmt: skip

    def refuse_recording(self, ids: list[int]) -> None:
        """:class:`RunBusy` if one of the runs ``ids`` is being recorded (a delete's check)."""
        busy = sorted(set(ids) & set(self.recording()))
        if busy:
            raise RunBusy(f"run {busy[0]} is being recorded: stop it first")

    def delete_runs(self, ids: list[int]) -> list[int]:
        """Delete the runs ``ids`` with everything recorded with them; returns those that
        existed (the others are not there to delete). :class:`RunBusy`, before anything is
        deleted, if one is being recorded. The rows go DELETE_CHUNK at a time, each chunk its
        own transaction, the run's own row last: a recorder, or the service starting a run
        (which waits only a moment for the lock), waits milliseconds, never a whole run's
        deletion; a deletion cut short leaves the run listed, to be deleted again. The pages
        freed hold the next runs (:meth:`vacuum` gives them back to the file system)."""
        self.check_writable()
        self.refuse_recording(ids)
        done = []
        for run_id in ids:
            for table in ("samples", "events", "frames", "truth"):
                chunk = (f"DELETE FROM {table} WHERE rowid IN (SELECT rowid FROM {table} "
                         "WHERE run_id = ? LIMIT ?)")  # fmt: skip
                while True:
                    with self._lock, self.db:
                        if not self.db.execute(chunk, (run_id, DELETE_CHUNK)).rowcount:
                            break
            with self._lock, self.db:
                for table in ("outlines", "owners"):
                    self.db.execute(f"DELETE FROM {table} WHERE run_id = ?", (run_id,))
                if self.db.execute("DELETE FROM runs WHERE id = ?", (run_id,)).rowcount:
                    done.append(run_id)
        return done

    def check_writable(self) -> None:
        """sqlite3.OperationalError, as a write would raise it, if this file cannot be written
        from here: write-protected, in a write-protected folder (read as immutable), or an
        older version's read as it is (:func:`connect`; refused as such, not through the
        temporary objects it is read through). A delete's and a vacuum's first check, and a
        dry run's."""
        if self.db.execute("PRAGMA query_only").fetchone()[0]:
            raise sqlite3.OperationalError("attempt to write a readonly database (a file of an "
                                           "older version, read as it is)")  # fmt: skip
        with self._lock:  # a write that changes nothing; another program's lock not waited for
            _check_writable(self.db, self.busy_timeout_s)

    def size(self) -> tuple[int, int]:
        """(bytes on disk: the file and its write-ahead log; bytes of it free for new runs)."""
        on_disk = sum(p.stat().st_size for p in (self.path, Path(f"{self.path}-wal"))
                      if p.exists())  # fmt: skip
        free = self.db.execute("PRAGMA freelist_count").fetchone()[0]
        page = self.db.execute("PRAGMA page_size").fetchone()[0]
        return on_disk, int(free) * int(page)

    def vacuum(self) -> None:
        """Rewrite the file without its free pages (SQLite's VACUUM), so that it shrinks.

        :class:`RunBusy` while a run is being recorded, or another program on this machine
        has the database open (a service, idle or not, also in another container; a reader:
        :func:`opened_elsewhere`): VACUUM holds the whole file for as long as it copies it —
        longer than a run's start or an e-stop's latch waits — and a reader keeps the copy in
        the write-ahead log, beside the old file, until it lets go.
        StoreError if a reader came meanwhile and the log could not be given back."""
        self.check_writable()
        others = opened_elsewhere(self.path)  # first: the end of a run would not be enough
        if others:
            raise RunBusy(f"{others}: a vacuum rewrites the whole file and holds it meanwhile; "
                          "vacuum while nothing else uses it")  # fmt: skip
        busy = self.recording()
        if busy:
            raise RunBusy(f"run {busy[0]} is being recorded: vacuum once it has ended")
        with self._lock:
            self.db.execute("VACUUM")
            # the log's copy written back and the log emptied (a reader that came meanwhile
            # keeps it: said, not taken for a shrunk file)
            busy_log = self.db.execute("PRAGMA wal_checkpoint(TRUNCATE)").fetchone()[0]
        if busy_log:
            raise StoreError(f"{self.path} was vacuumed, but another program read it meanwhile:"
                             " its write-ahead log keeps the new copy until that program lets "
                             "go (run `sdh2svc runs vacuum` again then)")  # fmt: skip

    def samples(
        self, run_id: int, offset: int = 0, limit: int = 1000, first: int = 0, every: int = 1
    ) -> list[dict[str, Any]]:
        """Up to ``limit`` samples in iteration order, from iteration ``first`` on, skipping
        ``offset`` of them; ``every``: only one iteration in that many (:meth:`_every`).

        By the index (run_id, iteration): a page costs the same wherever it lies in the run (an
        order by rowid sorted all the run's rows for every page: 0.2 s a page at 49 000)."""
        base, keep = self._every(run_id, every)
        rows = self.db.execute(
            f"SELECT * FROM samples WHERE run_id = ? AND iteration >= ?{keep} "
            "ORDER BY iteration LIMIT ? OFFSET ?",
            (run_id, first, *base, limit, offset),
        ).fetchall()
        return [{k: r[k] for k in SAMPLE_COLUMNS} for r in rows]

    def each_sample(self, run_id: int) -> Iterator[dict[str, Any]]:
        """Every sample of a run in iteration order, read as it is iterated (an export of a
        run of hours holds one at a time, not the run)."""
        for r in self.db.execute(
            "SELECT * FROM samples WHERE run_id = ? ORDER BY iteration", (run_id,)
        ):
            yield {k: r[k] for k in SAMPLE_COLUMNS}

    def _every(self, run_id: int, every: int) -> tuple[tuple[int, ...], str]:
        """The SQL condition (and its parameters) that keeps one iteration in ``every``, counted
        from the run's first sample's: the same iterations of samples, frames and truth."""
        if every <= 1:
            return (), ""
        row = self.db.execute(
            "SELECT MIN(iteration) FROM samples WHERE run_id = ?", (run_id,)
        ).fetchone()
        i0 = int(row[0]) if row is not None and row[0] is not None else 0
        return (i0, every), " AND (iteration - ?) % ? = 0"

    def events(self, run_id: int) -> list[dict[str, Any]]:
        rows = self.db.execute(
            "SELECT t, iteration, kind, detail FROM events WHERE run_id = ? ORDER BY rowid",
            (run_id,),
        ).fetchall()
        return [{**dict(r), "detail": json.loads(r["detail"])} for r in rows]

    def frames(self, run_id: int) -> Iterator[tuple[float, int | None, int, np.ndarray]]:
        """Every frame of a run in time order (recorded order where two share a time), read as
        it is iterated: by the index (run_id, t), with no sort of the run's texels."""
        for r in self.db.execute(
            "SELECT t, iteration, timestamp_ms, texels FROM frames WHERE run_id = ? "
            "ORDER BY t, rowid",
            (run_id,),
        ):
            yield r["t"], r["iteration"], r["timestamp_ms"], np.frombuffer(r["texels"], "<u2")

    # --- one iteration at a time (replay): by the indexes (run_id, iteration) and (run_id, t) ---

    def sample_at(self, run_id: int, iteration: int) -> dict[str, Any] | None:
        """The sample of one iteration, or None."""
        r = self.db.execute(
            "SELECT * FROM samples WHERE run_id = ? AND iteration = ? LIMIT 1", (run_id, iteration)
        ).fetchone()
        return None if r is None else {k: r[k] for k in SAMPLE_COLUMNS}

    def framed_count(self, run_id: int) -> int:
        """The run's frames linked to an iteration (those :meth:`frames_from` lists)."""
        row = self.db.execute(
            "SELECT COUNT(*) FROM frames WHERE run_id = ? AND iteration IS NOT NULL", (run_id,)
        ).fetchone()
        return int(row[0])

    def frames_from(
        self, run_id: int, first: int, last: int, limit: int, every: int = 1
    ) -> list[tuple[int, float, int, bytes]]:
        """Up to ``limit`` frames of iterations ``first``…``last`` in iteration order, as
        (iteration, t, timestamp_ms, texels as little-endian uint16 bytes); ``every``: only one
        iteration in that many, as :meth:`samples` keeps them.

        A frame is recorded with its iteration's sample and the same ``t``, which grows with the
        iteration: the sample index finds where ``first`` starts, the frame index (run, t)
        reads on from there."""
        start = self.db.execute(
            "SELECT t FROM samples WHERE run_id = ? AND iteration >= ? ORDER BY iteration LIMIT 1",
            (run_id, first),
        ).fetchone()
        t0 = start["t"] if start is not None and start["t"] is not None else -math.inf
        base, keep = self._every(run_id, every)
        rows = self.db.execute(
            "SELECT iteration, t, timestamp_ms, texels FROM frames WHERE run_id = ? AND t >= ? "
            f"AND iteration BETWEEN ? AND ?{keep} ORDER BY t LIMIT ?",
            (run_id, t0, first, last, *base, limit),
        ).fetchall()
        return [(r[0], r[1], r[2], bytes(r[3])) for r in rows]

    def frame_at(self, run_id: int, iteration: int, t: float | None = None) -> bytes | None:
        """The texels (little-endian uint16 bytes) of one iteration's frame; ``t``, the
        iteration's sample time, lets the frame index find it at once."""
        t0 = -math.inf if t is None else t
        r = self.db.execute(
            "SELECT texels FROM frames WHERE run_id = ? AND t >= ? AND iteration = ? "
            "ORDER BY t LIMIT 1",
            (run_id, t0, iteration),
        ).fetchone()
        return None if r is None else bytes(r[0])

    # --- the simulation's truth: the outline once per run, the object per iteration -----------

    def set_outline(
        self, run_id: int, obj: str, size_mm: float, points: list[tuple[float, float]]
    ) -> None:
        """The run's object: its name, size and outline (object frame, mm; once per run)."""
        with self._lock, self.db:
            self._insert_outline(run_id, obj, size_mm, points)

    def _insert_outline(
        self, run_id: int, obj: str, size_mm: float, points: list[tuple[float, float]]
    ) -> None:
        self.db.execute(
            "INSERT OR REPLACE INTO outlines (run_id, object, size_mm, points) VALUES (?, ?, ?, ?)",
            (run_id, obj, size_mm, json.dumps([[float(x), float(y)] for x, y in points])),
        )

    def outline(self, run_id: int) -> dict[str, Any] | None:
        """The run's object (``object``, ``size_mm``, ``points``: its outline in its own frame,
        mm); None for a run without truth (a real hand's)."""
        r = self.db.execute(
            "SELECT object, size_mm, points FROM outlines WHERE run_id = ?", (run_id,)
        ).fetchone()
        if r is None:
            return None
        return {"object": r["object"], "size_mm": r["size_mm"], "points": json.loads(r["points"])}

    def truth_count(self, run_id: int) -> int:
        row = self.db.execute("SELECT COUNT(*) FROM truth WHERE run_id = ?", (run_id,)).fetchone()
        return int(row[0])

    def truth(
        self, run_id: int, first: int = 0, limit: int = 10**9, every: int = 1
    ) -> list[dict[str, Any]]:
        """Up to ``limit`` iterations' truth from iteration ``first`` on, in iteration order
        (:data:`TRUTH_COLUMNS`); ``every``: only one iteration in that many, as :meth:`samples`
        keeps them."""
        base, keep = self._every(run_id, every)
        rows = self.db.execute(
            f"SELECT {', '.join(TRUTH_COLUMNS)} FROM truth WHERE run_id = ? AND iteration >= ?"
            f"{keep} ORDER BY iteration LIMIT ?",
            (run_id, first, *base, limit),
        ).fetchall()
        return [_truth_dict(r) for r in rows]

    def each_truth(self, run_id: int) -> Iterator[dict[str, Any]]:
        """Every iteration's truth in iteration order, read as it is iterated."""
        for r in self.db.execute(
            f"SELECT {', '.join(TRUTH_COLUMNS)} FROM truth WHERE run_id = ? ORDER BY iteration",
            (run_id,),
        ):
            yield _truth_dict(r)

    def truth_at(self, run_id: int, iteration: int) -> dict[str, Any] | None:
        """One iteration's truth, or None (not recorded: a real hand, or an older run)."""
        r = self.db.execute(
            f"SELECT {', '.join(TRUTH_COLUMNS)} FROM truth WHERE run_id = ? AND iteration = ? "
            "LIMIT 1",
            (run_id, iteration),
        ).fetchone()
        return None if r is None else _truth_dict(r)

    # --- exports --------------------------------------------------------------------------------

    def export_csv(self, run_id: int, out: IO[str]) -> int:
        """All samples of a run as CSV (header: the Sample's fields with their units, ``phi2
        [deg]``); returns the row count."""
        w = csv.writer(out)
        w.writerow(Sample.csv_header())
        n = 0
        for r in self.db.execute(
            f"SELECT {_QUOTED} FROM samples WHERE run_id = ? ORDER BY iteration",
            (run_id,),
        ):
            w.writerow(["" if v is None else v for v in r])
            n += 1
        return n

    def export_mcap(
        self, run_id: int, out: IO[bytes], cfg: Settings | None = None,
        progress: Callable[[int, int], None] | None = None,
    ) -> int:  # fmt: skip
        """The run as Foxglove-native MCAP (:mod:`sdh2svc.service.foxglove_mcap`): samples,
        the hand's transforms, contacts and friction cones, the pads as grids, events as logs,
        the run's metadata and the URDF; in simulation the object's true outline. The hand is
        drawn as the run recorded its configuration (``Settings.recorded``), in ``cfg`` (default:
        the packaged one), which a run recorded without one is drawn with. Returns the message
        count; :class:`~sdh2svc.config.ConfigError` if the recorded sections are not valid in
        this version. ``progress(done, total)``: samples written so far, every
        :data:`PROGRESS_EVERY` and at the last (an export of a run of hours takes minutes)."""
        from sdh2svc.config import default_config
        from sdh2svc.service.foxglove_mcap import write_mcap

        run = self.run(run_id) or {}
        t0 = _epoch_ns(run["started_at"]) if run else 0
        cfg = recorded_settings(run, cfg or default_config())
        samples = self.each_sample(run_id)
        if progress is not None:
            samples = _counted(samples, self.sample_count(run_id), progress)
        return write_mcap(
            out, cfg, run, t0, samples, self.events(run_id), self.frames(run_id),
            self.outline(run_id), self.each_truth(run_id),
        )  # fmt: skip


PROGRESS_EVERY = 1000  # samples between an export's progress calls


def _counted(
    items: Iterator[dict[str, Any]], total: int, progress: Callable[[int, int], None]
) -> Iterator[dict[str, Any]]:
    """``items`` passed on, ``progress(done, total)`` told every :data:`PROGRESS_EVERY` and at
    the end."""
    done = 0
    for done, item in enumerate(items, 1):
        yield item
        if done % PROGRESS_EVERY == 0:
            progress(done, total)
    if done % PROGRESS_EVERY:
        progress(done, total)


def recorded_settings(run: dict[str, Any], cfg: Settings) -> Settings:
    """The configuration ``run`` (a :meth:`RunStore.run`) was recorded with: ``cfg`` with the
    run's recorded sections (``Settings.recorded``) in place of its own — its matrices' shapes
    and order, its hand — or ``cfg`` itself for a run recorded without them.
    :class:`~sdh2svc.config.ConfigError` if they are not valid in this version."""
    recorded = (run.get("meta") or {}).get("configuration")
    return cfg.as_recorded(recorded) if isinstance(recorded, dict) else cfg


def _truth_dict(r: sqlite3.Row) -> dict[str, Any]:
    d = {k: r[k] for k in TRUTH_COLUMNS}
    for k in _TRUTH_BOOLS:
        d[k] = bool(d[k])
    return d


def _started(iso: str) -> datetime:
    """A run's stored start time (one without its offset: local time); one unreadable is taken
    as long ago."""
    try:
        return datetime.fromisoformat(iso).astimezone()
    except ValueError:
        return datetime.min.replace(tzinfo=UTC)


def _epoch_ns(iso: str) -> int:
    """A stored time (with its offset, to the second or the millisecond) as ns since the epoch,
    whatever the exporting process's time zone; 0 if it is not one."""
    try:
        return round(datetime.fromisoformat(iso).timestamp() * 1000) * 1_000_000
    except ValueError:
        return 0


# Tries a closing recorder makes for rows the database refused (each waits busy_timeout_s for
# a lock, RETRY_S for anything else)
CLOSE_TRIES = 6
RETRY_S = 1.0  # a recorder's rows a full or failing disk refused: tried again after this long
# items a recorder keeps in memory while the database refuses them (≈ 18 min of a run at 30
# Hz: a sample, its frame and truth each iteration; ≈ 100 MB); later ones are not kept
MAX_WAITING = 100_000


def locked(e: sqlite3.OperationalError) -> bool:
    """SQLite's "database is locked" / "busy": another connection's doing, not this data's."""
    text = str(e).lower()
    return "locked" in text or "busy" in text


def read_only(e: sqlite3.OperationalError) -> bool:
    """SQLite's "attempt to write a readonly database" (of any kind): this process may not write
    the file, its folder, or a log beside it — or the file is an older version's read as it is
    (:meth:`RunStore.check_writable`'s own refusal, which has no code)."""
    code = getattr(e, "sqlite_errorcode", None)
    if code is not None:
        return bool(code & 0xFF == sqlite3.SQLITE_READONLY)
    return "readonly database" in str(e)


def retry_locked(write: Callable[[], None]) -> None:
    """``write``, tried again while another program holds the database locked (each try waits
    storage.busy_timeout_s), up to CLOSE_TRIES times more."""
    for attempt in range(CLOSE_TRIES + 1):
        try:
            write()
            return
        except sqlite3.OperationalError as e:
            if not locked(e) or attempt == CLOSE_TRIES:
                raise
            log.warning("the run database is locked by another program (%s): trying again", e)


class Recorder:
    """Writes one run's samples, events, frames and truth from a background thread, in small
    batches.

    ``sample``/``event``/``frame`` never block the control loop: they only append to a buffer
    (a deque: no lock, no wake-up of the thread). The thread takes whatever is buffered at least
    every ``flush_s`` and commits it, each table's rows in multi-row ``INSERT`` statements;
    :meth:`close` flushes the rest. Waking the thread per row, or stepping SQLite per row, would
    hand the interpreter lock over per row: in fast mode, where the loop never idles, that cost
    the loop ≈ 20 % of its speed.
    """

    def __init__(
        self, path: str | Path, run_id: int, flush_s: float = 0.05, busy_timeout_s: float = 10.0
    ) -> None:
        self.path, self.run_id, self.flush_s = Path(path), run_id, flush_s
        self.busy_timeout_s = busy_timeout_s
        self._buf: deque[tuple[str, tuple[Any, ...]]] = deque()
        self._closing = threading.Event()
        self.committed = 0  # items on disk
        self.refusals = 0  # batches the database refused (they were tried again)
        self.lost = 0  # items not written (known once closed)
        self.error: BaseException | None = None  # why the thread gave up, if it did
        self.refused: BaseException | None = None  # the database's last refusal
        self._thread = threading.Thread(target=self._run, name=f"recorder-{run_id}", daemon=True)
        self._thread.start()

    def sample(self, s: Sample) -> None:
        self._buf.append(("s", (self.run_id, *s.row())))

    def event(self, t: float, iteration: int | None, kind: str, detail: dict[str, Any]) -> None:
        self._buf.append(("e", (self.run_id, t, iteration, kind, json.dumps(detail))))

    def frame(self, t: float, iteration: int | None, timestamp_ms: int, texels: np.ndarray) -> None:
        blob = np.ascontiguousarray(texels, dtype="<u2").tobytes()
        self._buf.append(("f", (self.run_id, t, iteration, timestamp_ms, blob)))

    def truth(
        self, iteration: int, t: float, pose: tuple[float, float, float], held: bool,
        dropped: bool, in_fixture: bool, slips: int,
    ) -> None:  # fmt: skip
        """One iteration's truth (simulation; see :data:`TRUTH_COLUMNS`)."""
        row = (self.run_id, iteration, t, *pose, held, dropped, in_fixture, slips)
        self._buf.append(("o", row))

    def close(self) -> None:
        self._closing.set()
        self._thread.join()
        self.lost += len(self._buf)  # what came after the thread gave up (none if it did not)
        self._buf.clear()

    def _run(self) -> None:
        try:
            db = connect(self.path, busy_timeout_s=self.busy_timeout_s)
        except (StoreError, sqlite3.Error) as e:  # (a full disk: its rows are counted lost)
            self.error = e
            log.error("run %d: its recording could not begin: %s", self.run_id, e)
            return
        tables = {
            "s": ("samples", f'"run_id", {_QUOTED}', len(SAMPLE_COLUMNS) + 1),
            "e": ("events", "run_id, t, iteration, kind, detail", 5),
            "f": ("frames", "run_id, t, iteration, timestamp_ms, texels", 5),
            "o": ("truth", f"run_id, {', '.join(TRUTH_COLUMNS)}", len(TRUTH_COLUMNS) + 1),
        }
        max_vars = db.getlimit(sqlite3.SQLITE_LIMIT_VARIABLE_NUMBER)
        per_stmt = {
            k: max(1, min(_ROWS_PER_INSERT, max_vars // n)) for k, (_, _, n) in tables.items()
        }
        sql: dict[tuple[str, int], str] = {}

        def insert(kind: str, rows: list[tuple[Any, ...]]) -> None:
            table, cols, n = tables[kind]
            step = per_stmt[kind]
            for i in range(0, len(rows), step):
                part = rows[i : i + step]
                key = (kind, len(part))
                if key not in sql:
                    one = "(" + ", ".join("?" * n) + ")"
                    sql[key] = f"INSERT INTO {table} ({cols}) VALUES " + ", ".join(
                        [one] * len(part)
                    )
                db.execute(sql[key], [v for row in part for v in row])

        buf = self._buf
        pending: list[tuple[str, tuple[Any, ...]]] = []  # taken from the buffer, not on disk
        in_a_row = tries_closing = 0  # refusals
        retry_at = 0.0  # (a full or failing disk: not tried again before then)
        beat = "UPDATE owners SET seen = ? WHERE run_id = ?"  # the heartbeat (STALE_S)
        last_beat = time.time()
        try:
            while True:
                done = self._closing.wait(self.flush_s)
                while buf:
                    item = buf.popleft()
                    if len(pending) < MAX_WAITING:
                        pending.append(item)
                    else:  # memory is not to run out while a disk stays full
                        self.lost += 1
                now = time.time()
                if pending and time.monotonic() < retry_at and not done:
                    continue
                if not pending and now - last_beat >= HEARTBEAT_S:
                    try:  # nothing to write: the heartbeat alone (refused: the next time)
                        with db:
                            db.execute(beat, (now, self.run_id))
                        last_beat = now
                    except sqlite3.OperationalError:
                        pass
                if pending:
                    # one transaction; each table's rows (in their order) in few statements:
                    # the tables' rows come interleaved (a sample, its truth, its frame, …)
                    by_table: dict[str, list[tuple[Any, ...]]] = {}
                    for kind, row in pending:
                        by_table.setdefault(kind, []).append(row)
                    try:
                        with db:
                            for kind, rows in by_table.items():
                                insert(kind, rows)
                            db.execute(beat, (now, self.run_id))
                        last_beat = now
                    except sqlite3.OperationalError as e:
                        # another program holds the file locked beyond busy_timeout_s, or the
                        # disk is full or failing: the rows wait for the next try (they were
                        # lost with the thread before); closing, it gives up after
                        # CLOSE_TRIES more
                        if done and tries_closing >= CLOSE_TRIES:
                            raise
                        tries_closing += done
                        self.refusals, self.refused = self.refusals + 1, e
                        in_a_row += 1
                        if not locked(e):
                            retry_at = time.monotonic() + RETRY_S  # (a clock set back)
                            if done:  # (the wait above no longer waits)
                                time.sleep(RETRY_S)
                        if in_a_row == 1:
                            why = ("is locked by another program" if locked(e) else
                                   "does not take them")  # fmt: skip
                            log.warning("run %d: the run database %s (%s); its rows wait in "
                                        "memory", self.run_id, why, e)  # fmt: skip
                        continue
                    if in_a_row:
                        log.info("run %d: the run database took its rows again", self.run_id)
                    self.committed += len(pending)
                    pending, in_a_row = [], 0
                if done and not buf:
                    break
        except BaseException as e:
            self.error = e
            self.lost += len(pending) + len(buf)
            buf.clear()
            log.error("run %d: its recording gave up: %d recorded items not written to %s: "
                      "%s", self.run_id, self.lost, self.path, e)  # fmt: skip
        finally:
            db.close()


def _interrupted_summary() -> dict[str, Any]:
    """What a run whose process died has for a summary: why it ended, as any run's says."""
    return {"status": "interrupted", "message": INTERRUPTED}
