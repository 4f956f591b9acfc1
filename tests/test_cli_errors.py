"""What the command line does with bad input and an unusable world: one line on stderr that
names the problem, a documented exit status (README, *Exit status*), never a traceback.

The cases run as a user runs them (a subprocess) where a process is the point — the devices,
the ports, the start-up of the service; the rest through :func:`sdh2svc.cli.main`.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import pty
import re
import socket
import subprocess
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from sdh2svc import cli
from sdh2svc.cli import Exit, main, status_url
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand
from sdh2svc.service.store import Recorder, RunStore
from tests.live_service import AT_PRESHAPE, FAST_GRASP
from tests.service.test_client_transport import status_server
from tests.service.test_replay_api import sample as replay_sample
from tests.service.test_retention import another_process_open

FOUND_NOTHING = "no run database at {} (set storage.db_path or run from the directory"


def run(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sdh2svc", *args],
        capture_output=True, text=True, timeout=60, cwd=cwd,
    )  # fmt: skip


def one_line(stderr: str, command: str) -> str:
    """The failure's message: the last line on stderr, ``sdh2svc COMMAND: …``."""
    assert "Traceback" not in stderr, stderr
    line = stderr.strip().splitlines()[-1]
    assert line.startswith(f"sdh2svc {command}: "), stderr
    return line


def call(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    status = main(list(args))
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    return status, out, err


def db_set(path: Path | str) -> list[str]:
    return ["--set", f"storage.db_path={json.dumps(str(path))}"]


@pytest.fixture
def closed_port() -> int:
    """A localhost port nothing listens on (bound, then closed)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def taken_port() -> Iterator[int]:
    """A localhost port that is bound (and listened on) for the test's duration."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield int(s.getsockname()[1])


@pytest.fixture
def one_run(tmp_path: Path) -> Path:
    """A run database holding run 1."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        assert store.create_run({"test": True}) == 1
    finally:
        store.close()
    return db


# --- the exit statuses are documented -------------------------------------------------------


def test_help_lists_the_exit_statuses(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as ei:
        main(["--help"])
    assert ei.value.code == 0
    out = capsys.readouterr().out
    assert "exit status:" in out
    for status in Exit:
        assert f"\n  {int(status):<4d} " in out, status


def test_every_option_with_a_default_says_it_in_its_help() -> None:
    """`health --timeout` waited 4 s and `demo --s1/--s2` took 20 mm without a word in --help,
    where the φ defaults were shown (CLI audit)."""
    import argparse

    silent = []
    for name in ("config", "demo", "sim", "run", "serve", "health", "runs", "estop", "campaign"):
        sub = cli._subparser(cli.build_parser(), name)
        assert sub is not None
        for action in sub._actions:
            if action.option_strings and action.default not in (None, False, [], argparse.SUPPRESS):
                said = (action.help or "") % vars(action)  # as argparse expands it
                if f"default {action.default}" not in said:
                    silent.append(f"{name} {action.option_strings[-1]}")
    assert silent == []


def test_readme_table_matches_the_codes() -> None:
    readme = (Path(__file__).resolve().parent.parent / "README.md").read_text()
    section = readme.split("### Exit status", 1)[1].split("\n#", 1)[0]
    for status in Exit:
        assert f"| {int(status)} |" in section, status


# --- configuration ---------------------------------------------------------------------------


def test_binary_config_file_is_invalid_configuration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    binary = tmp_path / "lab.toml"
    binary.write_bytes(bytes(range(256)))
    status, _, err = call(capsys, "config", "--config", str(binary))
    assert status == Exit.USAGE == 2
    line = one_line(err, "config")
    assert str(binary) in line and "not UTF-8" in line


def test_directory_as_config_is_invalid_configuration(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = call(capsys, "config", "--config", str(tmp_path))
    assert status == Exit.USAGE
    assert f"{tmp_path} is a directory" in one_line(err, "config")


@pytest.mark.parametrize(
    ("args", "key"),
    [
        (["--baud", "0"], "sim.links.baud = 0"),
        (["--ber", "2"], "sim.links.bit_error_rate = 2.0"),
        (["--boot-s", "-1"], "sim.links.dsa_boot_s = -1.0"),
        (["--seed", "-1"], "sim.seed = -1"),
        (["--replace-after", "-1"], "sim.replace_after_s = -1.0"),
        (["--baud", "0", "--set", "sim.links.baud=9600"], "sim.links.baud = 0"),  # the option's
    ],
)
def test_an_option_that_sets_a_key_is_named_as_typed_when_its_value_is_bad(
    args: list[str], key: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """`sim --baud 0` said "(--set sim.links.baud=0)", an option the user never typed (CLI
    audit): every option that stands for a configuration key is named itself."""
    status, _, err = call(capsys, "sim", *args)
    assert status == Exit.USAGE
    line = one_line(err, "sim")
    assert f"{key} ({args[0]} {args[1]}): " in line and "--set" not in line, line


def test_bad_environment_value_is_invalid_configuration(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("SDH2SVC_LIMITS__MIN_DEG", "[1, 2")
    status, _, err = call(capsys, "config")
    assert status == Exit.USAGE
    assert "SDH2SVC_LIMITS__MIN_DEG = '[1, 2': cannot be read" in one_line(err, "config")


# --- the run database ------------------------------------------------------------------------


def test_reading_commands_never_create_a_database(tmp_path: Path) -> None:
    """From a directory without data/: "no run database", named in full (a relative
    storage.db_path is another database in another directory), and still no data/ afterwards."""
    where = tmp_path.resolve() / "data" / "runs.sqlite"
    for args in (["list"], ["show", "1"], ["export", "1", "--format", "csv"]):
        r = run("runs", *args, cwd=tmp_path)
        assert r.returncode == Exit.NOT_FOUND == 3, r.stderr
        assert FOUND_NOTHING.format(where) in one_line(r.stderr, "runs")
    assert list(tmp_path.iterdir()) == []


def test_the_run_database_is_named_in_full(
    one_run: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """`runs list` said "1 run in runs.sqlite" for a relative storage.db_path, where `estop`
    says the whole path (CLI audit): every message of `runs` names it in full."""
    monkeypatch.chdir(one_run.parent)
    relative, where = db_set(one_run.name), one_run.resolve()
    status, _, err = call(capsys, "runs", "list", *relative)
    assert status == Exit.OK and f"1 run in {where}: " in err, err
    status, _, err = call(capsys, "runs", "show", "9", *relative)
    assert status == Exit.NOT_FOUND and f"no run 9 in {where}" in one_line(err, "runs")
    status, _, err = call(capsys, "runs", "delete", "9", *relative)
    assert status == Exit.NOT_FOUND and f"no run 9 in {where} (" in one_line(err, "runs")


def test_database_path_that_is_a_directory(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = call(capsys, "runs", "list", *db_set(tmp_path))
    assert status == Exit.UNAVAILABLE == 4
    assert f"{tmp_path}: it is a directory" in one_line(err, "runs")


def test_database_that_is_not_sqlite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    notes = tmp_path / "notes.txt"
    notes.write_text("not a database, just notes\n" * 100)
    status, _, err = call(capsys, "runs", "list", *db_set(notes))
    assert status == Exit.UNAVAILABLE
    line = one_line(err, "runs")
    assert str(notes) in line and "not a database" in line
    assert notes.read_text().startswith("not a database")  # left as it was


def test_sqlite_file_that_is_not_a_run_database(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3

    other = tmp_path / "other.sqlite"
    with sqlite3.connect(other) as db:
        db.execute("CREATE TABLE t (x)")
    db.close()
    status, _, err = call(capsys, "runs", "list", *db_set(other))
    assert status == Exit.UNAVAILABLE
    assert f"{other} is not a run database" in one_line(err, "runs")


def test_database_in_an_unwritable_place(tmp_path: Path, closed_port: int) -> None:
    """A writing command (run) whose database would live under a regular file."""
    blocker = tmp_path / "data"
    blocker.write_text("a file where a directory should be")
    url = f"socket://127.0.0.1:{closed_port}"
    r = run("run", "--dsa", "socket://127.0.0.1:1", "--sdh", url, *db_set(blocker / "runs.sqlite"))
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert f"{blocker} is not a directory" in one_line(r.stderr, "run")


def test_estop_on_a_locked_database_is_unavailable(
    one_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Another program holds the run database's write lock past the busy timeout."""
    import sqlite3

    lock = sqlite3.connect(one_run, isolation_level=None)
    try:
        lock.execute("BEGIN IMMEDIATE")
        for action in ("--latch", "--release"):
            status, _, err = call(capsys, "estop", action, *db_set(one_run),
                                  "--set", "storage.busy_timeout_s=0.2")  # fmt: skip
            assert status == Exit.UNAVAILABLE, err
            assert "database is locked" in one_line(err, "estop")
    finally:
        lock.execute("ROLLBACK")
        lock.close()
    assert call(capsys, "estop", *db_set(one_run))[1] == f"released (in {one_run})\n"


def test_estop_latched_here_while_a_service_has_the_database_open_says_it_stopped_nothing(
    one_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A running service reads the latch on disk only when it starts: `estop --latch` beside
    one said "latched" and exited 0 while the fingers went on (found by a safety audit). It
    now says the hand was not stopped, and how to stop it, and exits 1."""
    with another_process_open(one_run) as pid:  # as a service has it
        status, out, err = call(capsys, "estop", "--latch", *db_set(one_run))
        assert status == Exit.FAILED and out.startswith("latched since "), (out, err)
        assert f"pid {pid}" in err and "the hand was NOT stopped" in err
        assert "POST /api/estop" in err
        # released on disk only, a latched service would stay latched and say it is on disk,
        # while a restart came up released (docs audit): refused, the latch kept
        status, out, err = call(capsys, "estop", "--release", *db_set(one_run))
        assert status == Exit.FAILED and not out, (out, err)
        err = one_line(err, "estop")
        assert f"pid {pid}" in err and "not released" in err, err
        assert "POST /api/estop/release" in err
    assert call(capsys, "estop", *db_set(one_run))[1].startswith("latched since ")
    status, out, err = call(capsys, "estop", "--latch", *db_set(one_run))
    assert status == Exit.OK and not err  # nobody else has it open
    status, out, err = call(capsys, "estop", "--release", *db_set(one_run))
    assert status == Exit.OK and out.startswith("released") and not err


def test_estop_latched_where_there_was_no_database_says_it_made_one(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A mistyped storage.db_path: the latch went into a new database no service reads, and
    the command said only "latched" (CLI audit)."""
    typo = tmp_path / "dta" / "runs.sqlite"
    status, out, err = call(capsys, "estop", "--latch", *db_set(typo))
    assert status == Exit.OK and out.startswith("latched since ") and typo.exists()
    assert f"there was no run database at {typo}: a new one was made for the latch" in err
    status, out, err = call(capsys, "estop", "--latch", *db_set(typo))  # there now: no word
    assert status == Exit.OK and not err


def test_a_simulated_run_says_it_does_not_obey_a_latched_estop(
    one_run: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A lab rehearsing its e-stop on the simulator saw the latch do nothing, without a word
    (CLI audit); a real hand's run is refused (test_hardening). The database is named in full,
    given relative (CLI audit)."""
    monkeypatch.chdir(one_run.parent)
    assert call(capsys, "estop", "--latch", *db_set(one_run.name))[0] == Exit.OK
    status, _, err = call(capsys, "run", "--sim", "--fast", "--cycles", "1",
                          "--set", "sim.object_height_mm=300.0",  # nothing to grasp: ends soon
                          "--set", "run.grasp_timeout_s=2.0", *db_set(one_run.name))  # fmt: skip
    assert status == Exit.FAILED  # it ran (and found nothing to grasp)
    assert f"the e-stop is latched in {one_run.resolve()}" in err, err
    assert "a simulated run does not obey it" in err


def test_estop_latched_from_another_pid_namespace_says_it_stopped_nothing(
    one_run: Path,
) -> None:
    """The same from another container (here: a pid namespace of its own, which is what a
    container gives its processes), whose /proc/locks does not list the service's pid: `estop
    --latch` there said "latched" and exited 0 while the service went on."""
    if subprocess.run(["unshare", "--pid", "--fork", "--mount-proc", "true"],
                      capture_output=True, check=False).returncode != 0:  # fmt: skip
        pytest.skip("this machine lets no test create a pid namespace (unshare needs root)")
    with another_process_open(one_run):  # as a service has it
        r = subprocess.run(["unshare", "--pid", "--fork", "--mount-proc", sys.executable, "-m",
                            "sdh2svc", "estop", "--latch", *db_set(one_run)],
                           capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert r.returncode == Exit.FAILED and r.stdout.startswith("latched since "), r
    assert "in another container or pid namespace" in r.stderr, r.stderr
    assert "the hand was NOT stopped" in r.stderr


@pytest.mark.parametrize(
    ("args", "said"),
    [
        (["run", "--sim", "--obejct", "egg"], "sdh2svc run: error: unrecognized arguments: "
         "--obejct egg (did you mean --object?)"),
        (["serve", "--prot", "18120"], "sdh2svc serve: error: unrecognized arguments: --prot "
         "18120 (did you mean --port?)"),
        (["config", "--zzz"], "sdh2svc config: error: unrecognized arguments: --zzz"),
    ],
)  # fmt: skip
def test_a_mistyped_option_is_named_with_its_commands_usage_and_the_nearest_option(
    args: list[str], said: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """The top-level parser answered, with a usage that lists none of the command's options
    (CLI audit)."""
    with pytest.raises(SystemExit) as refused:
        main(args)
    err = capsys.readouterr().err
    assert refused.value.code == Exit.USAGE and err.rstrip().endswith(said), err
    assert err.startswith(f"usage: sdh2svc {args[0]} ")


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["sim", "--dsa-port", "99999"], "a port is 0 … 65535"),
        (["sim", "--sdh-port", "-1"], "a port is 0 … 65535"),
        (["serve", "--port", "http"], "'http' is no port number"),
        (["run", "--sdh", ""], "empty: give a device path"),
        (["serve", "--dsa", " "], "empty: give a device path"),
    ],
)
def test_bad_ports_and_empty_urls_are_usage_errors(
    args: list[str], fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as bad:
        main(args)
    assert bad.value.code == Exit.USAGE
    assert fragment in capsys.readouterr().err


@pytest.mark.parametrize("timeout", ["-1", "0", "nan", "inf", "soon"])
def test_health_timeout_must_be_seconds(timeout: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as bad:
        main(["health", "--timeout", timeout])
    assert bad.value.code == Exit.USAGE == 2
    assert "--timeout" in capsys.readouterr().err


def test_no_such_run_is_not_found(one_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, _, err = call(capsys, "runs", "show", "999", *db_set(one_run))
    assert status == Exit.NOT_FOUND
    assert f"no run 999 in {one_run}" in one_line(err, "runs")


def test_run_id_beyond_sqlite_integers_is_not_found(
    one_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    huge = str(10**30)
    for action in ("show", "export"):
        status, out, err = call(capsys, "runs", action, huge, *db_set(one_run))
        assert status == Exit.NOT_FOUND and out == ""
        assert f"no run {huge} in" in one_line(err, "runs")


def test_existing_run_still_shows(one_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, out, _ = call(capsys, "runs", "show", "1", *db_set(one_run))
    assert status == Exit.OK and json.loads(out)["meta"] == {"test": True}


def test_runs_list_names_the_object_and_why_a_run_ended_and_show_its_events(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`runs list` gave ID, start, status and iterations only, so a faulted run had to be
    opened one by one to learn why; `runs show` left out the events `GET /api/runs/{id}`
    gives (the phases, reversals, faults)."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    try:
        lost = store.create_run({"object": {"name": "egg", "kind": "ellipse"}})
        rec = Recorder(db, lost)
        rec.event(1.5, 40, "fault", {"fault": "tactile_stale", "message": "no frame"})
        rec.close()
        store.finish_run(lost, "faulted", {"status": "faulted",
                                           "message": "tactile line lost:\n no frame"})  # fmt: skip
        real = store.create_run({"object": None})  # a real hand's run: no simulated object
        store.finish_run(real, "completed", {"status": "completed", "message": ""})
    finally:
        store.close()
    status, out, _ = call(capsys, "runs", "list", *db_set(db))
    newest, oldest = out.splitlines()
    assert status == Exit.OK and newest.split()[2:] == ["completed", "0", "iterations", "-"]
    assert oldest.split()[2:6] == ["faulted", "0", "iterations", "egg"], oldest
    assert oldest.endswith("  tactile line lost: no frame"), oldest  # on its one line
    status, out, _ = call(capsys, "runs", "show", str(lost), *db_set(db))
    assert status == Exit.OK and json.loads(out)["events"] == [
        {"t": 1.5, "iteration": 40, "kind": "fault",
         "detail": {"fault": "tactile_stale", "message": "no frame"}}]  # fmt: skip


def test_export_to_an_unwritable_file(
    one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "missing-dir" / "run.csv"
    status, _, err = call(capsys, "runs", "export", "1", "-o", str(target), *db_set(one_run))
    assert status == Exit.UNAVAILABLE
    assert f"cannot write {target}" in one_line(err, "runs")


# An export that a signal interrupts once it has written part of the file (the signal sent by
# the export to its own process: the interruption lands mid-file every time)
INTERRUPTED_EXPORT = """
import os, signal, sys
from sdh2svc import cli
from sdh2svc.service.store import RunStore

def export(self, run_id, out, *rest):
    out.write(b"\\x89MCAP0\\r\\n" + b"x" * 100_000)
    out.flush()
    os.kill(os.getpid(), getattr(signal, sys.argv[1]))
    out.write(b"never")

RunStore.export_mcap = export
sys.exit(cli.main(sys.argv[2:]))
"""


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM"])
def test_an_interrupted_export_leaves_an_earlier_file_as_it_was_and_no_partial_one(
    one_run: Path, tmp_path: Path, sig: str
) -> None:
    """Ctrl-C (or a `kill`) during `runs export -o FILE` left a truncated file no reader
    opens, in place of a good export there before (found by a CLI audit)."""
    target = tmp_path / "run.mcap"
    target.write_bytes(b"the earlier export")
    r = subprocess.run([sys.executable, "-c", INTERRUPTED_EXPORT, sig, "runs", "export", "1",
                        "--format", "mcap", "-o", str(target), *db_set(one_run)],
                       capture_output=True, text=True, timeout=60, check=False)  # fmt: skip
    assert r.returncode == Exit.INTERRUPTED, r.stderr
    assert f"interrupted; {target} not written" in r.stderr
    assert target.read_bytes() == b"the earlier export"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.mcap", "runs.sqlite"]


def test_a_long_mcap_export_shows_its_progress_on_a_terminal(tmp_path: Path) -> None:
    """An MCAP export of a run of hours takes minutes: on a terminal its stderr counts the
    iterations written (every 1000, and the last) and ends the line before the message count;
    to a file or pipe it says only the count."""
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    run_id = store.create_run({})
    rec = Recorder(db, run_id)
    for i in range(2500):
        rec.sample(replay_sample(i))
    rec.close()
    store.close()
    target = tmp_path / "run.mcap"
    cmd = [sys.executable, "-m", "sdh2svc", "runs", "export", str(run_id), "--format", "mcap",
           "-o", str(target), *db_set(db)]  # fmt: skip
    master, slave = pty.openpty()
    proc = subprocess.Popen(cmd, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                            stderr=slave)  # fmt: skip
    os.close(slave)
    said = b""
    with contextlib.suppress(OSError):  # EIO once the command has closed the terminal
        while chunk := os.read(master, 4096):
            said += chunk
    os.close(master)
    assert proc.wait(timeout=120) == Exit.OK, said
    text = said.decode().replace("\r\n", "\n")
    counts = re.findall(r"\rrun 1: (\d+)/2500 iterations written", text)
    assert counts == ["1000", "2000", "2500"], text
    assert re.search(r"2500/2500 iterations written\n.*run\.mcap: 2500 iterations in \d+ "
                     "messages", text), text  # fmt: skip
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    assert r.returncode == Exit.OK and "iterations written" not in r.stderr, r.stderr
    # what it says at the end is what docs/foxglove.md says: the iterations it wrote
    assert re.fullmatch(r"\S+run\.mcap: 2500 iterations in \d+ messages", r.stderr.strip()), r


def test_an_export_replaces_an_earlier_file_whole_or_writes_into_a_device(
    one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    target = tmp_path / "run.csv"
    target.write_text("an earlier export, longer than the new one " * 100)
    status, _, err = call(capsys, "runs", "export", "1", "-o", str(target), *db_set(one_run))
    assert status == Exit.OK, err
    assert target.read_text().startswith("iteration,") and "earlier" not in target.read_text()
    assert oct(target.stat().st_mode & 0o777) == oct(0o666 & ~_umask())
    status, _, err = call(capsys, "runs", "export", "1", "-o", os.devnull, *db_set(one_run))
    assert status == Exit.OK and Path(os.devnull).is_char_device(), err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.csv", "runs.sqlite"]


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_an_export_takes_its_format_from_the_files_name_and_refuses_a_contradiction(
    one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`runs export 1 -o run.mcap` wrote CSV into it, which Foxglove cannot open (CLI audit);
    the client took the format from the name already."""
    mcap = tmp_path / "run.mcap"
    status, _, err = call(capsys, "runs", "export", "1", "-o", str(mcap), *db_set(one_run))
    assert status == Exit.OK and mcap.read_bytes()[:5] == b"\x89MCAP", err
    csv_file = tmp_path / "run.CSV"
    status, _, err = call(capsys, "runs", "export", "1", "-o", str(csv_file), *db_set(one_run))
    assert status == Exit.OK and csv_file.read_text().startswith("iteration,"), err
    for fmt, name in (("csv", "other.mcap"), ("mcap", "other.csv")):
        status, _, err = call(capsys, "runs", "export", "1", "--format", fmt,
                              "-o", str(tmp_path / name), *db_set(one_run))  # fmt: skip
        assert status == Exit.USAGE
        assert f"--format {fmt} into {tmp_path / name}: its name says" in one_line(err, "runs")
        assert not (tmp_path / name).exists()


@pytest.mark.parametrize("name", ["r1.txt", "r1", "r1.MCAP.bak"])
def test_an_export_into_a_file_named_neither_csv_nor_mcap_asks_for_the_format(
    name: str, one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`runs export 1 -o r1.txt` wrote CSV into it without a word, where the client's export
    asks for the format (CLI audit): refused, naming the suffix and how to choose; --format
    says it. A device, a folder and stdout are as before (the tests above and below)."""
    target = tmp_path / name
    status, _, err = call(capsys, "runs", "export", "1", "-o", str(target), *db_set(one_run))
    assert status == Exit.USAGE and not target.exists()
    suffix = f"its suffix {target.suffix}" if target.suffix else "no suffix"
    assert one_line(err, "runs") == (
        f"sdh2svc runs: -o {target}: {suffix} says no export format; .csv or .mcap does (name "
        "it so, or give --format csv or --format mcap)")  # fmt: skip
    target.write_text("an earlier file")  # there already: the same
    assert call(capsys, "runs", "export", "1", "-o", str(target), *db_set(one_run))[0] == 2
    assert target.read_text() == "an earlier file"
    for fmt, head in (("csv", b"iteration,"), ("mcap", b"\x89MCAP")):
        status, _, err = call(capsys, "runs", "export", "1", "--format", fmt, "-o", str(target),
                              *db_set(one_run))  # fmt: skip
        assert status == Exit.OK and target.read_bytes().startswith(head), err


def test_an_export_into_a_folder_or_a_full_device_is_refused_as_unwritable(
    one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A folder or /dev/full has no suffix either; what is wrong is that it cannot be written
    (exit 4), not its name."""
    for target, why in ((str(tmp_path), "Is a directory"), ("/dev/full", "No space left")):
        status, _, err = call(capsys, "runs", "export", "1", "-o", target, *db_set(one_run))
        assert status == Exit.UNAVAILABLE
        assert f"cannot write {target}: {why}" in one_line(err, "runs")


@pytest.mark.parametrize("args", [["config"], ["demo", "--json"], ["runs", "show", "1"]])
def test_output_onto_a_full_disk_is_unavailable_not_a_bug(one_run: Path, args: list[str]) -> None:
    """`… > /dev/full` (a full disk under a script's output) was "unexpected error (a bug)",
    exit 70 (CLI audit); it is the output not writable, exit 4, as for an export."""
    with open("/dev/full", "w") as full:
        r = subprocess.run([sys.executable, "-m", "sdh2svc", *args, *db_set(one_run)],
                           stdout=full, stderr=subprocess.PIPE, text=True, timeout=60)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert "cannot write its output: No space left on device" in one_line(r.stderr, args[0])


def test_an_export_to_dash_goes_to_stdout_mcap_too(one_run: Path, tmp_path: Path) -> None:
    """`-o -` made a file named "-" (CLI audit): it is standard output, for a pipe."""
    r = subprocess.run([sys.executable, "-m", "sdh2svc", "runs", "export", "1", "--format",
                        "mcap", "-o", "-", *db_set(one_run)], capture_output=True,
                       timeout=60, cwd=tmp_path)  # fmt: skip
    assert r.returncode == Exit.OK, r.stderr
    assert r.stdout[:5] == b"\x89MCAP" and r.stderr.decode().startswith("stdout: ")
    assert not (tmp_path / "-").exists()


def test_export_to_a_closed_stdout(one_run: Path) -> None:
    import shlex

    cmd = shlex.join([sys.executable, "-m", "sdh2svc", "runs", "export", "1", *db_set(one_run)])
    r = subprocess.run(["sh", "-c", f"exec {cmd} >&-"], capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert "cannot write stdout: it is closed" in one_line(r.stderr, "runs")


def test_which_run_is_a_usage_error(one_run: Path, capsys: pytest.CaptureFixture[str]) -> None:
    status, _, err = call(capsys, "runs", "show", *db_set(one_run))
    assert status == Exit.USAGE
    assert "which run?" in one_line(err, "runs")


def test_runs_without_an_action_asks_for_the_action_alone(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """`list`, `prune` and `vacuum` take no run ID: a missing action is all that is missing."""
    with pytest.raises(SystemExit) as bad:
        main(["runs"])
    assert bad.value.code == Exit.USAGE
    err = capsys.readouterr().err
    assert one_line(err, "runs").endswith("error: the following arguments are required: action")


@pytest.mark.parametrize("run_id", ["1_0", "+1", " 1", "١"])
def test_a_run_id_is_written_in_the_digits_0_to_9(
    run_id: str, one_run: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As the API takes it: int() would read "1_0" as run 10 and "+1" as run 1."""
    with pytest.raises(SystemExit) as bad:
        main(["runs", "show", run_id, *db_set(one_run)])
    assert bad.value.code == Exit.USAGE
    assert "a run ID is written in the digits 0–9" in capsys.readouterr().err


def test_a_run_database_of_another_shape_is_unusable_not_a_bug(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A runs table without the columns every version had (someone else's, or a newer
    version's): refused by name, for reading and for recording, and nothing is added to it."""
    import sqlite3

    other = tmp_path / "future.sqlite"
    with contextlib.closing(sqlite3.connect(other)) as db, db:
        db.execute("CREATE TABLE runs (id INTEGER PRIMARY KEY, began TEXT, state TEXT)")
        db.execute("INSERT INTO runs (began, state) VALUES ('x', 'y')")
    for args in (("runs", "list"), ("runs", "show", "1")):
        status, _, err = call(capsys, *args, *db_set(other))
        assert status == Exit.UNAVAILABLE, err
        line = one_line(err, "runs")
        assert f"{other} is not a run database this version can read" in line
        assert "runs table lacks ended_at, meta, started_at, status, summary" in line
    with pytest.raises(Exception, match="this version can read"):
        RunStore(other)  # what `run` and `serve` open: refused too
    with contextlib.closing(sqlite3.connect(other)) as db:
        tables = {r[0] for r in db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    assert tables == {"runs"}


def test_an_export_this_version_cannot_draw_leaves_no_file(
    one_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import sqlite3

    with contextlib.closing(sqlite3.connect(one_run)) as db, db:
        odd = {"configuration": {"limits": {"max_deg": [500] * 7}}}
        db.execute("UPDATE runs SET meta = ? WHERE id = 1", (json.dumps(odd),))
    target = tmp_path / "run.mcap"
    status, _, err = call(capsys, "runs", "export", "1", "--format", "mcap", "-o", str(target),
                          *db_set(one_run))  # fmt: skip
    assert status == Exit.USAGE
    assert "run 1 cannot be drawn by this version: limits" in one_line(err, "runs")
    assert not target.exists()


# --- devices and ports -----------------------------------------------------------------------


def test_a_signal_stops_a_run_as_the_services_stop_does(tmp_path: Path) -> None:
    """Ctrl-C mid-run (systemd's stop or kill, SIGTERM, the same: the next test sends it): the
    run releases the object and is recorded as stopped with its end, its summary printed and
    its one line on stderr; exit 130."""
    import signal

    db = tmp_path / "r.sqlite"
    with _begun_run(db, "--json") as proc:
        assert _runs(db) == [(1, "running")]
        proc.send_signal(signal.SIGINT)
        out, err = proc.communicate(timeout=60)
    assert proc.returncode == Exit.INTERRUPTED == 130, err
    assert _runs(db) == [(1, "stopped")]
    assert json.loads(out)["status"] == "stopped"
    assert one_line(err, "run").startswith("sdh2svc run: run 1 stopped")
    assert _phases(db)[-2:] == ["releasing", "stopped"]  # the object let go, the end recorded


def test_ctrl_c_while_the_command_loads_is_exit_130_without_a_traceback() -> None:
    """Loading the CLI takes about a second: Ctrl-C then printed a traceback of the imports
    (CLI audit). The interrupt lands in the import here every time."""
    script = (
        "import builtins, sys\n"
        "real = builtins.__import__\n"
        "def interrupted(name, *args, **kwargs):\n"
        "    if name == 'sdh2svc.config':\n"
        "        raise KeyboardInterrupt\n"
        "    return real(name, *args, **kwargs)\n"
        "builtins.__import__ = interrupted\n"
        "sys.argv = ['sdh2svc', 'config']\n"
        "from sdh2svc.entry import main\n"
        "main()\n"
    )
    r = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True,
                       timeout=60)  # fmt: skip
    assert r.returncode == Exit.INTERRUPTED and r.stderr == "", r.stderr


def test_a_second_signal_ends_the_run_at_once_and_says_where_it_left_the_hand(
    tmp_path: Path,
) -> None:
    """SIGTERM (which stops a run as Ctrl-C does: the fingers let go), then Ctrl-C while they
    let go: the run ends at once, the hand left where it is. It printed nothing and was
    recorded as a plain `stopped`, the word of a run that let its object go (CLI audit)."""
    import signal

    db = tmp_path / "r.sqlite"
    with _begun_run(db, *AT_PRESHAPE, *FAST_GRASP) as proc:
        # once the fingers hold the object: their release back to the pre-shape takes a second
        # or two (15–20°/s); from the pre-shape's own move it could end before the Ctrl-C came
        _until(lambda: "rolling" in _phases(db))
        proc.send_signal(signal.SIGTERM)
        _until(lambda: "releasing" in _phases(db))  # it lets go
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == Exit.INTERRUPTED, err
    assert "interrupted again: the run ended at once, recorded as interrupted" in err, err
    assert _runs(db) == [(1, "interrupted")]
    assert "stopped" not in _phases(db)  # its release was cut short


@contextlib.contextmanager
def _begun_run(db: Path, *args: str) -> Iterator[subprocess.Popen[str]]:
    """`sdh2svc run --sim` in real time, once its run has begun (its first phase recorded);
    killed at the end of the block if it has not ended."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "sdh2svc", "run", "--sim", *args, *db_set(db)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    try:
        _until(lambda: bool(_phases(db)))
        yield proc
    finally:
        proc.kill()


def _until(ok: Callable[[], bool], timeout_s: float = 60.0) -> None:
    """Wait (polling another process's record) until ``ok()``; at most ``timeout_s``."""
    import time

    deadline = time.monotonic() + timeout_s
    while not ok() and time.monotonic() < deadline:
        time.sleep(0.05)


def _phases(db: Path) -> list[str]:
    import sqlite3

    if not db.exists():
        return []
    with contextlib.closing(sqlite3.connect(db)) as con:
        try:
            rows = con.execute("SELECT detail FROM events WHERE kind = 'phase'").fetchall()
        except sqlite3.OperationalError:  # the tables are not made yet
            return []
    return [json.loads(r[0]).get("phase") for r in rows]


def _runs(db: Path) -> list[tuple[int, str]]:
    import sqlite3

    if not db.exists():
        return []
    with contextlib.closing(sqlite3.connect(db)) as con:
        try:
            return con.execute("SELECT id, status FROM runs").fetchall()
        except sqlite3.OperationalError:  # the tables are not made yet
            return []


def test_run_against_a_nonexistent_device(tmp_path: Path) -> None:
    missing = tmp_path / "ttyUSB9"
    r = run("run", "--dsa", str(tmp_path / "ttyUSB8"), "--sdh", str(missing),
            *db_set(tmp_path / "r.sqlite"))  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE == 4, r.stderr
    line = one_line(r.stderr, "run")
    assert "cannot reach the hand" in line and str(missing) in line
    assert "swapped" not in line  # a missing device: no swap explains it


def test_run_against_a_refused_socket(tmp_path: Path, closed_port: int) -> None:
    url = f"socket://127.0.0.1:{closed_port}"
    r = run("run", "--dsa", "socket://127.0.0.1:1", "--sdh", url, *db_set(tmp_path / "r.sqlite"))
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    line = one_line(r.stderr, "run")
    assert url in line and "refused" in line


def test_run_against_a_joint_controller_that_never_answers_says_it_in_one_line(
    tmp_path: Path,
) -> None:
    """The joint link's own warning ("… error ver: no reply within 1.0 s") reached stderr
    beside the failure's line, through logging's last resort."""
    with socket.create_server(("127.0.0.1", 0)) as mute:
        url = f"socket://127.0.0.1:{mute.getsockname()[1]}"
        r = run("run", "--dsa", "socket://127.0.0.1:1", "--sdh", url,
                *db_set(tmp_path / "r.sqlite"))  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert "no reply" in one_line(r.stderr, "run")


async def _run_cli(*args: str) -> tuple[int, str]:
    """``sdh2svc ARGS`` in a subprocess while this test's event loop serves a simulated hand:
    its exit status and stderr."""
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "sdh2svc", *args,
        stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
    )  # fmt: skip
    _, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode is not None
    return proc.returncode, err.decode()


async def test_a_run_on_swapped_lines_asks_whether_they_are_swapped(tmp_path: Path) -> None:
    """--dsa and --sdh swapped: the joint line, on the DSACON32m, hears nothing (it is silent to
    `ver`), and the run said only "no reply within 1.0 s (check --sdh/--dsa or links…)" (CLI
    audit); asked when the user gave both lines — given one, the other is the configuration's,
    and said so."""
    async with simulated_hand(load_config(), Simulated()) as bench:
        dsa, sdh = bench.sim.urls("dsa")[0], bench.sim.urls("sdh")[0]
        db = db_set(tmp_path / "r.sqlite")
        status, err = await _run_cli("run", "--dsa", sdh, "--sdh", dsa, *db)
        assert status == Exit.UNAVAILABLE and len(err.strip().splitlines()) == 1, err
        line = one_line(err, "run")
        assert f"joint line {dsa}: SDH not connected: ver: no reply within" in line, line
        assert line.endswith(" (are --dsa and --sdh swapped?)"), line
        # the joint line from the configuration: a warning names it; no question of a swap
        status, err = await _run_cli("run", "--dsa", sdh,
                                     "--set", f"links.sdh_url={json.dumps(dsa)}", *db)  # fmt: skip
    assert status == Exit.UNAVAILABLE, err
    warning, line = err.strip().splitlines()
    assert warning == (f"sdh2svc run: --sdh not given: the joint line is links.sdh_url = {dsa} "
                       "from the configuration")  # fmt: skip
    assert "no reply within" in line and "swapped" not in line, line


def test_a_run_given_one_line_says_which_the_other_is(tmp_path: Path) -> None:
    """The line not given is the configuration's (links.dsa_url, by default /dev/ttyS1):
    said on stderr before the run's own failure, which still names both places to check."""
    missing = str(tmp_path / "ttyUSB9")
    r = run("run", "--sdh", str(tmp_path / "ttyUSB8"), "--set",
            f"links.dsa_url={json.dumps(missing)}", *db_set(tmp_path / "r.sqlite"))  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    warning, _ = r.stderr.strip().splitlines()
    assert warning == (f"sdh2svc run: --dsa not given: the tactile line is links.dsa_url = "
                       f"{missing} from the configuration")  # fmt: skip
    assert one_line(r.stderr, "run").endswith("(check --sdh/--dsa or links.sdh_url/dsa_url)")


def test_run_with_one_port_for_both_lines_is_a_usage_error(tmp_path: Path) -> None:
    tty = str(tmp_path / "ttyUSB0")
    r = run("run", "--dsa", tty, "--sdh", tty, *db_set(tmp_path / "r.sqlite"))
    assert r.returncode == Exit.USAGE, r.stderr
    assert "the tactile and the joint line are both" in one_line(r.stderr, "run")


def test_serve_with_the_viser_port_in_use(tmp_path: Path, taken_port: int) -> None:
    r = run("serve", "--sim", "--port", "0", "--viser-port", str(taken_port),
            *db_set(tmp_path / "r.sqlite"), cwd=tmp_path)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    line = one_line(r.stderr, "serve")
    assert f"viser port {taken_port} is already in use" in line
    assert "cannot open the hand" not in r.stderr


def test_serve_with_the_foxglove_port_in_use_fails_before_the_hand(
    tmp_path: Path, taken_port: int
) -> None:
    """Found by a lab user: it was found only after both lines had been opened and closed."""
    r = run("serve", "--sim", "--port", "0", "--viser-port", "0", "--set",
            f"service.foxglove_port={taken_port}", *db_set(tmp_path / "r.sqlite"),
            cwd=tmp_path)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    line = one_line(r.stderr, "serve")
    assert f"port {taken_port} already in use" in line and "service.foxglove_port" in line
    assert "hand closed" not in r.stderr and "cannot open the hand" not in r.stderr


def test_a_viewer_that_lost_the_race_for_its_port_says_so_too() -> None:
    """The child's late report (the port taken between the check and viser's bind)."""
    from sdh2svc.config import default_config
    from sdh2svc.service.server import PortBusy, _start_error
    from sdh2svc.service.viewer_proc import ViewerError

    cfg = default_config()
    err = _start_error(ViewerError("cannot serve the 3-D view on 127.0.0.1:8080: in use"), cfg)
    assert isinstance(err, PortBusy)
    assert f"viser port {cfg.service.viser_port} is already in use" in str(err)
    assert _start_error(KeyError("a bug"), cfg) is None  # not dressed up as a start-up failure


def test_sim_with_its_port_in_use(taken_port: int) -> None:
    r = run("sim", "--no-pty", "--dsa-port", str(taken_port), "--sdh-port", "0", "--boot-s", "0")
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    assert str(taken_port) in one_line(r.stderr, "sim")


# --- health ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("given", "expected"),
    [
        ("http://127.0.0.1:8000", "http://127.0.0.1:8000/api/status"),
        ("http://127.0.0.1:8000/", "http://127.0.0.1:8000/api/status"),
        ("http://127.0.0.1:8000/api/status", "http://127.0.0.1:8000/api/status"),
        ("http://127.0.0.1:8000/api/status/", "http://127.0.0.1:8000/api/status"),
        ("127.0.0.1:8000", "http://127.0.0.1:8000/api/status"),
        ("https://lab.example/hand/", "https://lab.example/hand/api/status"),
        ("http://[::1]:8000", "http://[::1]:8000/api/status"),
    ],
)
def test_health_url_accepts_the_base_url(given: str, expected: str) -> None:
    assert status_url(given) == expected


@pytest.mark.parametrize("bad", ["ftp://127.0.0.1/", "http://127.0.0.1:99999", "http://"])
def test_health_url_that_cannot_be_is_a_usage_error(
    bad: str, capsys: pytest.CaptureFixture[str]
) -> None:
    status, _, err = call(capsys, "health", "--url", bad)
    assert status == Exit.USAGE
    assert repr(bad) in one_line(err, "health")


def test_health_of_a_service_that_does_not_answer(closed_port: int) -> None:
    r = run("health", "--url", f"http://127.0.0.1:{closed_port}", "--timeout", "2")
    assert r.returncode == Exit.FAILED == 1, r.stderr
    line = one_line(r.stderr, "health")
    assert f"http://127.0.0.1:{closed_port}/api/status" in line and "refused" in line


def test_health_takes_the_base_url_of_a_live_service(tmp_path: Path) -> None:
    from tests.live_service import start_service

    svc = start_service(tmp_path, viewer=False)
    try:
        for url in (svc.url, f"{svc.url}/", f"{svc.url}/api/status"):
            r = run("health", "--url", url)
            assert r.returncode == Exit.OK, r.stderr
            assert r.stdout.strip() == f"ok: {svc.url}/api/status"
    finally:
        assert svc.stop() == 0


# --- bugs ------------------------------------------------------------------------------------


def test_a_bug_is_one_line_unless_debugging(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def broken(_args: object) -> int:
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(cli, "cmd_demo", broken)
    monkeypatch.delenv("SDH2SVC_DEBUG", raising=False)
    status, _, err = call(capsys, "demo")
    assert status == Exit.BUG == 70
    assert "unexpected error (a bug): ZeroDivisionError" in one_line(err, "demo")
    assert main(["--debug", "demo"]) == Exit.BUG
    assert "Traceback" in capsys.readouterr().err
    monkeypatch.setenv("SDH2SVC_DEBUG", "1")
    assert main(["demo"]) == Exit.BUG
    assert "Traceback" in capsys.readouterr().err


def test_a_bad_object_file_is_named_field_by_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """--object-file: each bad field on one line with its range or the keys there are; a file
    that is not TOML says where."""
    bad = tmp_path / "mine.toml"
    bad.write_text('kind = "box"\nwidth_mm = -4\nheight_mm = 20\ndepth_mm = 30\ncolour = 3\n')
    assert main(["run", "--sim", "--fast", "--object-file", str(bad)]) == Exit.USAGE
    line = one_line(capsys.readouterr().err, "run")
    assert f"invalid object in {bad}: box.width_mm = -4:" in line
    assert "(allowed: 1.0 ≤ width_mm ≤ 150.0)" in line
    assert "box.colour = 3: unknown key (the keys there are: name, depth_mm," in line
    bad.write_text('kind = "blob"\n')
    assert main(["run", "--sim", "--fast", "--object-file", str(bad)]) == Exit.USAGE
    assert "'stick', 'box', 'ellipse', 'circle', 'polygon'" in capsys.readouterr().err
    bad.write_text('kind = "box\n')
    assert main(["run", "--sim", "--fast", "--object-file", str(bad)]) == Exit.USAGE
    line = one_line(capsys.readouterr().err, "run")
    assert f"the object file {bad}: " in line and "(at line 1, column 12)" in line
    missing = tmp_path / "missing.toml"
    assert main(["run", "--sim", "--fast", "--object-file", str(missing)]) == Exit.USAGE
    line = one_line(capsys.readouterr().err, "run")
    assert line.endswith(f"cannot read the object file {missing}: No such file or directory")


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["demo", "--phi2", "inf"], "--phi2 inf: outside axis 1's joint limits -90 … 90 deg"),
        (["demo", "--phi5", "nan"], "--phi5 nan: outside"),
        (["demo", "--phi3", "720"], "--phi3 720: outside"),
        (["demo", "--s1", "-500"], "--s1 -500: off the pad (0 … 40.8 mm)"),
        (["demo", "--s2", "1e6"], "--s2 1e+06: off the pad"),
        (["sim", "--no-pty", "--no-tcp"], "nothing to serve"),
        (["run", "--sim", "--dsa", "/dev/x"], "--dsa names a real hand's line: not with --sim"),
        (["serve", "--sim", "--dsa", "a", "--sdh", "b"], "--dsa and --sdh name a real hand's"),
        (["runs", "list", "5"], "the run ID 5: not with runs list"),
        (["runs", "list", "--format", "mcap"], "--format: not with runs list"),
        (["runs", "show", "5", "-o", "x.csv"], "--output: not with runs show"),
    ],
)
def test_inputs_the_model_or_the_simulator_cannot_use_are_usage_errors(
    args: list[str], fragment: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """A pose beyond the joint limits or a contact off the pad (the model would print a
    contact 1 km away, or crash); a simulator serving nothing; real lines beside --sim, and
    what only another `runs` action takes (`runs list 5 --format mcap` printed the whole list):
    ignored before."""
    status, _, err = call(capsys, *args)
    assert status == Exit.USAGE
    assert fragment in one_line(err, args[0])


@pytest.mark.parametrize("cycles", ["0", "10001", "two"])
def test_cycles_must_be_a_count_of_strokes(cycles: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as bad:
        main(["run", "--sim", "--cycles", cycles])
    assert bad.value.code == Exit.USAGE
    assert "argument --cycles" in capsys.readouterr().err


def test_a_failed_run_says_so_in_one_line_on_stderr(tmp_path: Path) -> None:
    """The summary is the output (stdout, or the JSON); the failure is stderr's one line."""
    for extra in ([], ["--json"]):
        # the fingers give up 10° into the grasp, before they reach the egg
        args = ["run", "--sim", "--fast", "--cycles", "1", "--set", "run.grasp_max_close_deg=-20"]
        r = run(*args, *extra, *db_set(tmp_path / "runs.sqlite"))
        assert r.returncode == Exit.FAILED
        line = one_line(r.stderr, "run")
        assert re.fullmatch(r"sdh2svc run: run \d+ faulted: no_contact: .*", line), line
        if extra:
            assert json.loads(r.stdout)["status"] == "faulted"
        else:
            assert "faulted" in r.stdout


def test_config_does_not_print_the_token(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("SDH2SVC_SERVICE__TOKEN", "sekrit")
    status, out, _ = call(capsys, "config")
    assert status == Exit.OK and "sekrit" not in out
    assert json.loads(out)["service"]["token"] == "***"


def test_a_write_protected_database_is_unavailable_not_a_bug(one_run: Path) -> None:
    """SQLite opens a write-protected file read-only without a word; the first write (a run's
    start) then failed as an unexpected error. Root writes anyway: its capabilities dropped."""
    import shutil

    one_run.chmod(0o444)
    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-all"] if os.geteuid() == 0 else []
    assert not drop or shutil.which("setpriv"), "setpriv (util-linux) is needed as root"
    r = subprocess.run([*drop, sys.executable, "-m", "sdh2svc", "run", "--sim", "--fast",
                        *db_set(one_run)], capture_output=True, text=True, timeout=60)  # fmt: skip
    assert r.returncode == Exit.UNAVAILABLE, r.stderr
    line = one_line(r.stderr, "run")
    assert f"cannot open the run database {one_run}" in line and "readonly" in line


def test_deleting_from_a_write_protected_database_says_so(one_run: Path) -> None:
    """`runs delete` or `prune` (a dry run too) on a write-protected database said SQLite's
    "attempt to write a readonly database" — of a dry run, which writes nothing. Now: what
    would go, and that the file (or its folder) is write-protected."""
    import shutil

    store = RunStore(one_run)
    store.finish_run(1, "completed", {"status": "completed"})
    store.close()
    one_run.chmod(0o444)
    drop = ["setpriv", "--inh-caps=-all", "--bounding-set=-all"] if os.geteuid() == 0 else []
    assert not drop or shutil.which("setpriv"), "setpriv (util-linux) is needed as root"
    said = f"{one_run} is write-protected: make it writable to delete runs or vacuum it"
    for action, first in ((["prune", "--keep", "0", "--dry-run"], "would delete 1 run: 1, but"),
                          (["delete", "1"], "nothing deleted:")):  # fmt: skip
        cmd = [*drop, sys.executable, "-m", "sdh2svc", "runs", *action, *db_set(one_run)]
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
        assert r.returncode == Exit.UNAVAILABLE, r.stderr
        assert f"sdh2svc runs: {first} {said}" in r.stderr, r.stderr
    assert RunStore(one_run, create=False).runs()[0]["id"] == 1


def test_export_into_a_pipe_its_reader_closed_is_quiet(one_run: Path) -> None:
    """`runs export 1 | head`: the reader had enough; no error, no traceback; 141, as every
    command whose reader went away."""
    store = RunStore(one_run)
    try:
        cols = ", ".join(f'"{c}"' for c in ("iteration", "t"))
        with store.db:
            store.db.executemany(f"INSERT INTO samples (run_id, {cols}) VALUES (1, ?, ?)",
                                 [(i, i * 0.01) for i in range(20_000)])  # fmt: skip
    finally:
        store.close()
    proc = subprocess.Popen([sys.executable, "-m", "sdh2svc", "runs", "export", "1",
                             *db_set(one_run)], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    head = proc.stdout.readline()
    proc.stdout.close()  # far more than a pipe's buffer is still to come
    err = proc.stderr.read()
    proc.stderr.close()
    assert proc.wait(timeout=60) == Exit.BROKEN_PIPE, err
    assert head.startswith("iteration") and err == ""


def test_sim_with_one_port_for_both_links_is_a_usage_error(
    capsys: pytest.CaptureFixture[str],
) -> None:
    status, _, err = call(capsys, "sim", "--dsa-port", "5001", "--sdh-port", "5001")
    assert status == Exit.USAGE
    assert "would both serve on TCP port 5001: one port each" in one_line(err, "sim")
    # a flag against the configuration's port for the other line (not "address in use")
    status, _, err = call(capsys, "sim", "--no-pty", "--dsa-port", "13023")
    assert status == Exit.USAGE
    assert "would both serve on TCP port 13023" in one_line(err, "sim")
    status, _, err = call(capsys, "sim", "--no-tcp", "--dsa-port", "5001")
    assert status == Exit.USAGE and "--no-tcp serves no TCP port" in one_line(err, "sim")


def test_serve_logging_json_logs_a_bad_configuration_as_json() -> None:
    """A service under a log collector: its one line of failure is a JSON record too."""
    r = run("serve", "--sim", "--log-format", "json", "--set", "rolling.k=0")
    assert r.returncode == Exit.USAGE, r.stderr
    records = [json.loads(line) for line in r.stderr.strip().splitlines()]
    assert records[-1]["level"] == "ERROR" and "rolling.k = 0" in records[-1]["msg"]


def test_output_whose_reader_went_away_ends_quietly() -> None:
    """`sdh2svc runs show 7 | head`, the reader gone before the output is written: exit 141
    (as a shell reports SIGPIPE) and nothing on stderr, not "unexpected error (a bug)"."""
    proc = subprocess.Popen([sys.executable, "-m", "sdh2svc", "config"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    assert proc.stdout is not None and proc.stderr is not None
    proc.stdout.close()  # long before the command has started, let alone written
    with proc.stderr:
        err = proc.stderr.read().decode()
    assert proc.wait(timeout=60) == Exit.BROKEN_PIPE and err == "", err


def test_config_given_twice_is_refused_not_the_first_dropped(tmp_path: Path) -> None:
    """argparse keeps the last of two --config silently: the first file's keys (its run
    database, and so its e-stop latch) would be dropped without a word."""
    first, second = tmp_path / "lab.toml", tmp_path / "hand.toml"
    first.write_text('[storage]\ndb_path = "/srv/sdh2svc/runs.sqlite"\n')
    second.write_text("[rolling]\nk = 3.0\n")
    r = run("config", "--config", str(first), "--config", str(second))
    assert r.returncode == 2, r
    assert "--config given twice" in r.stderr and "usage:" in r.stderr
    assert r.stdout == ""
    once = run("config", "--config", str(first), "--set", "rolling.k=3")
    assert once.returncode == 0, once.stderr
    cfg = json.loads(once.stdout)
    assert cfg["storage"]["db_path"] == "/srv/sdh2svc/runs.sqlite"
    assert cfg["rolling"]["k"] == 3.0


def test_health_asks_a_loopback_service_directly_whatever_http_proxy_says(
    closed_port: int, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A lab PC's (or a container's) http_proxy must not carry the check of a service on this
    machine: urllib sends loopback requests to the proxy too, which answers for another host or
    not at all."""
    up = {"hand": {"connected": {"joints": True, "tactile": True}}}
    for port in status_server(up):
        for name in ("http_proxy", "HTTP_PROXY"):  # a proxy that is not there
            monkeypatch.setenv(name, f"http://127.0.0.1:{closed_port}")
        monkeypatch.delenv("no_proxy", raising=False)
        monkeypatch.delenv("NO_PROXY", raising=False)
        for host in ("127.0.0.1", "localhost"):
            status, out, err = call(capsys, "health", "--url", f"http://{host}:{port}")
            assert status == Exit.OK, err
            assert out.strip() == f"ok: http://{host}:{port}/api/status"
