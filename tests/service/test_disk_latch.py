"""The e-stop latch another program writes to the run database while a service or a real-hand
run drives the hand (`sdh2svc estop --latch` where it cannot reach the service's API): the hand
stops within a poll, and the database says so to the program that latched (a safety audit
found the latch on disk only, the service going on unaware until its next restart)."""

from __future__ import annotations

import asyncio
import json
import sqlite3
import sys
import threading
from pathlib import Path
from typing import Any

import pytest

from sdh2svc.cli import Exit
from sdh2svc.client import Conflict
from sdh2svc.config import load_config
from sdh2svc.connect import Simulated, simulated_hand
from sdh2svc.service import latch as latch_mod
from sdh2svc.service.headless import _own_task
from sdh2svc.service.latch import latched_elsewhere
from sdh2svc.service.store import RunStore, StoreError
from tests.live_service import AT_PRESHAPE, start_service
from tests.service.test_cli_estop import estop_latch


class _Link:
    """What the watcher asks of a joint link: whether it is latched, and how many times."""

    def __init__(self) -> None:
        self.estopped, self.latches = False, 0

    def latch(self) -> None:
        self.estopped, self.latches = True, self.latches + 1


def test_a_taker_is_written_only_for_the_latch_on_disk_and_a_release_clears_it(
    tmp_path: Path,
) -> None:
    store = RunStore(tmp_path / "runs.sqlite")
    try:
        store.took_estop("2026-01-01T00:00:00.000+0000", "the service (pid 1)", True)
        assert store.estop_takers("2026-01-01T00:00:00.000+0000") == []  # no such latch
        latch = store.latch_estop("latched from the command line")
        store.took_estop(latch["since"], "the service (pid 1 on lab)", False)
        store.took_estop(latch["since"], "sdh2svc run (pid 2 on lab)", True)
        takers = store.estop_takers(latch["since"])
        assert [(t["program"], t["hand_reached"]) for t in takers] == [
            ("the service (pid 1 on lab)", False),
            ("sdh2svc run (pid 2 on lab)", True),
        ]
        store.release_estop()
        assert store.estop_takers(latch["since"]) == []
        again = store.latch_estop("latched from the command line", since=latch["since"])
        assert store.estop_takers(again["since"]) == []  # the old takers went with the release
    finally:
        store.close()


async def test_the_watcher_takes_another_programs_latch_and_not_its_own(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(latch_mod, "LATCH_POLL_S", 0.0)
    store = RunStore(tmp_path / "runs.sqlite")
    link = _Link()
    try:
        # this program's own e-stop: the link latched before its latch reaches the disk
        link.latch()
        store.latch_estop("e-stop requested")
        watch = asyncio.create_task(latched_elsewhere(store, link))  # type: ignore[arg-type]
        for _ in range(20):
            await asyncio.sleep(0)
        assert not watch.done()  # latched here: the latch on disk is this program's own
        watch.cancel()

        # released, then another program latches: taken
        store.release_estop()
        link.estopped = False
        held = [True]
        watch = asyncio.create_task(
            latched_elsewhere(store, link, held=lambda: held[0])  # type: ignore[arg-type]
        )
        store.latch_estop("latched from the command line")
        for _ in range(20):
            await asyncio.sleep(0)
        assert not watch.done()  # held (a release under way): not yet
        held[0] = False
        found = await asyncio.wait_for(watch, 10.0)
        assert found["reason"] == "latched from the command line"
    finally:
        store.close()


async def test_a_read_during_which_the_link_latched_is_not_taken(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """This program's own e-stop and its release may both come while a read is out: the row the
    read saw was that e-stop's, gone since, so the read is dropped, not taken as another's."""
    monkeypatch.setattr(latch_mod, "LATCH_POLL_S", 0.0)
    store = RunStore(tmp_path / "runs.sqlite")
    link = _Link()
    reads: list[int] = []
    real_read = store.estop_latch

    def read() -> dict[str, str] | None:
        got = real_read()
        if not reads:  # the first read: this program latches and releases meanwhile
            link.latch()
            link.estopped = False
        reads.append(1)
        return got if len(reads) == 1 else None

    store.latch_estop("e-stop requested")
    monkeypatch.setattr(store, "estop_latch", read)
    try:
        watch = asyncio.create_task(latched_elsewhere(store, link))  # type: ignore[arg-type]
        async with asyncio.timeout(10):
            while len(reads) < 3:
                await asyncio.sleep(0.01)
        assert not watch.done()  # the first read's latch was dropped, and none came since
        watch.cancel()
    finally:
        store.close()


async def test_the_store_closes_only_once_a_read_of_the_latch_is_done(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A program closing its store while the watcher reads (in a thread) must wait for the read:
    SQLite closed under a running statement crashed the process (seen here, 2 runs in 8)."""
    monkeypatch.setattr(latch_mod, "LATCH_POLL_S", 0.0)
    store = RunStore(tmp_path / "runs.sqlite")
    reading, proceed = threading.Event(), threading.Event()
    real_read = store.estop_latch

    def read() -> dict[str, str] | None:
        reading.set()
        proceed.wait(30)
        return real_read()

    monkeypatch.setattr(store, "estop_latch", read)
    watch = asyncio.create_task(latched_elsewhere(store, _Link()))  # type: ignore[arg-type]
    assert await asyncio.to_thread(reading.wait, 30)
    closer = threading.Thread(target=store.close)
    closer.start()
    closer.join(0.2)
    try:
        assert closer.is_alive()  # held until the read is done
    finally:
        proceed.set()
        closer.join(30)
        watch.cancel()
    assert not closer.is_alive()


def free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def takers(db: Path) -> list[dict[str, Any]]:
    store = RunStore(db, create=False)
    try:
        latch = store.estop_latch()
        return [] if latch is None else store.estop_takers(latch["since"])
    finally:
        store.close()


def test_a_service_the_command_cannot_reach_stops_for_the_latch_on_disk(tmp_path: Path) -> None:
    svc = start_service(tmp_path, viewer=False)
    try:
        # a port no service listens on: the service started on its own (--port), unknown to
        # the configuration the command reads
        r = estop_latch(svc.db_path, free_port())
        assert r.returncode == Exit.OK, r
        assert "the service (pid " in r.stdout and "stopped its hand" in r.stdout, r
        with svc.sync_client() as c:
            status = c.status()
            assert status["estopped"] is True, status
            assert status["estop"]["reason"] == "latched from the command line", status
            assert status["estop"]["hand_reached"] is True, status
            with pytest.raises(Conflict, match="e-stop"):
                c.start_run()
            [taker] = takers(svc.db_path)
            assert taker["hand_reached"] is True and taker["program"].startswith("the service")
            assert c.release_estop()["estopped"] is False
            assert c.status()["estop"] is None
        assert takers(svc.db_path) == []  # released with the latch
    finally:
        assert svc.stop() == 0, "".join(svc.log)


async def test_a_real_hand_run_ends_e_stopped_for_the_latch_on_disk(tmp_path: Path) -> None:
    db = tmp_path / "runs.sqlite"
    async with simulated_hand(load_config(overrides=[AT_PRESHAPE[1]]), Simulated()) as bench:
        sim = bench.sim
        run = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "sdh2svc", "run", "--dsa", sim.urls("dsa")[0],
            "--sdh", sim.urls("sdh")[0], "--cycles", "20",
            "--set", f"storage.db_path={json.dumps(str(db))}",
            stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
        )  # fmt: skip
        try:
            async with asyncio.timeout(120):  # the fingers closing: a run to stop
                while not _in_phase(db, "grasping"):
                    assert run.returncode is None, await run.stderr.read()  # type: ignore[union-attr]
                    await asyncio.sleep(0.1)
            assert any(sim.sdh.powered)
            r = await asyncio.to_thread(estop_latch, db, free_port())
            out, err = await asyncio.wait_for(run.communicate(), 60)
        finally:
            if run.returncode is None:
                run.kill()
                await run.wait()
        assert r.returncode == Exit.OK, r
        assert "sdh2svc run (pid " in r.stdout and "stopped its hand" in r.stdout, r
        assert run.returncode == Exit.FAILED, err
        assert "e-stopped" in err.decode() and b": e-stopped" in out, (out, err)
        sim.sdh.next_wakeup(asyncio.get_running_loop().time())
        assert not any(sim.sdh.powered)  # motors off
    [taker] = takers(db)
    assert taker["hand_reached"] is True and taker["program"].startswith("sdh2svc run")


def _in_phase(db: Path, phase: str) -> bool:
    """The newest run in ``db`` has reached ``phase`` (recorded)."""
    if not db.exists():
        return False
    try:
        store = RunStore(db, create=False)
    except StoreError:
        return False
    try:
        runs = store.run_page(1)[0]
        return bool(runs) and any(
            e["kind"] == "phase" and e["detail"].get("phase") == phase
            for e in store.events(runs[0]["id"])
        )
    except sqlite3.Error:
        return False
    finally:
        store.close()


class _Run:
    """What a headless run's own task asks of a recorded run: execute() (its record written as
    it ends, however it ends) and the summary."""

    def __init__(self) -> None:
        self.summary: dict[str, Any] | None = None
        self.task: asyncio.Task[Any] | None = None
        self.recorded = False

    async def execute(self) -> dict[str, Any]:
        self.task = asyncio.current_task()
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            await asyncio.sleep(0.01)  # the end written (in a thread, in a real run)
            self.recorded, self.summary = True, {"status": "e-stopped"}
            raise
        raise AssertionError("unreachable")


async def test_an_e_stopped_run_answers_its_summary_and_a_cancelled_one_is_recorded_first() -> None:
    run = _Run()
    answer = asyncio.create_task(_own_task(run))  # type: ignore[arg-type]
    while run.task is None:
        await asyncio.sleep(0)
    run.task.cancel()  # the e-stop cancels the run's own task
    assert await answer == {"status": "e-stopped"} and run.recorded

    run = _Run()
    outer = asyncio.create_task(_own_task(run))  # type: ignore[arg-type]
    while run.task is None:
        await asyncio.sleep(0)
    outer.cancel()  # a second Ctrl-C: the run ends too, recorded before this goes on
    with pytest.raises(asyncio.CancelledError):
        await outer
    assert run.recorded
