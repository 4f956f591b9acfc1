"""The e-stop against what else happens in the same moment — a release, a shutdown — in this
process (the app over ASGI, or a real uvicorn server; the simulated hand in real time: a disk
write is held in its thread by an event, which the virtual clock's inline executor cannot do)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import signal
import sqlite3
import threading
from pathlib import Path
from typing import Any

import httpx
import pytest
import uvicorn
from test_retention import another_process_open
from test_sim_press import service

from sdh2svc.config import load_config
from sdh2svc.connect import Simulated
from sdh2svc.service import hand_service
from sdh2svc.service.app import close_services, create_app, open_services
from sdh2svc.service.recording import RecordedRun
from sdh2svc.service.server import _Server, listen_socket
from sdh2svc.service.store import RunStore

JSON = {"Content-Type": "application/json"}  # a command's, its body empty


def test_an_estop_pressed_while_a_release_deletes_its_record_stays_latched(
    tmp_path: Path,
) -> None:
    """The release deletes the latch's record first (a thread: milliseconds, or as long as
    another program holds the database), then powers the hand on. An e-stop pressed meanwhile
    answered "estopped", and the release then powered the hand on and cleared the latch. It
    now refuses (409), the hand stays off, and the latch is on disk again (the delete may have
    taken the e-stop's own record); a release after that powers the hand on."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> None:
        async with service(cfg, Simulated()) as (c, services):
            st = services.station
            assert st.bench is not None and st.joints is not None and st.store is not None
            sdh, store = st.bench.sim.sdh, st.store
            assert (await c.post("/api/estop")).json()["estopped"] is True
            assert not any(sdh.powered)
            deleting, go = threading.Event(), threading.Event()
            delete = store.release_estop

            def slow_delete() -> None:  # the e-stop's write lands before the delete
                deleting.set()
                assert go.wait(30)
                delete()

            store.release_estop = slow_delete  # type: ignore[method-assign]
            release = asyncio.create_task(c.post("/api/estop/release", headers=JSON))
            assert await asyncio.to_thread(deleting.wait, 30)
            again = await c.post("/api/estop")
            assert again.status_code == 200 and again.json()["estopped"] is True
            go.set()
            refused = await release
            assert refused.status_code == 409, refused.text
            assert "an e-stop came during the release" in refused.json()["error"]
            assert not any(sdh.powered) and st.joints.estopped
            assert store.estop_latch() is not None  # on disk again: a restart keeps it
            assert (await c.get("/api/status")).json()["estopped"] is True
            store.release_estop = delete  # type: ignore[method-assign]
            assert (await c.post("/api/estop/release", headers=JSON)).json() == {"estopped": False}
            assert all(sdh.powered) and store.estop_latch() is None

    asyncio.run(main())


def test_a_release_of_a_service_not_estopped_leaves_another_services_latch_on_disk(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Two services on one run database (one e-stop latch on disk between them): a release
    pressed on the one that was not stopped deleted the other's latch, which its restart then
    lost (found by a CLI audit). It now touches nothing; the second service said at its start
    that another program shares the database."""
    db = tmp_path / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'"], use_env=False)
    RunStore(db).close()

    async def main() -> None:
        async with service(cfg, Simulated()) as (c, services):
            st = services.station
            assert st.store is not None and st.joints is not None
            st.store.latch_estop("the other service's e-stop")
            answer = await c.post("/api/estop/release", headers=JSON)
            assert answer.status_code == 200 and answer.json() == {"estopped": False}
            latch = st.store.estop_latch()
            assert latch is not None and latch["reason"] == "the other service's e-stop"
            assert not st.joints.estopped

    # the other service, which latched its own hand
    with another_process_open(db), caplog.at_level("WARNING", "sdh2svc.service.hand_service"):
        asyncio.run(main())
    said = [r.getMessage() for r in caplog.records]
    assert any("another program has the run database open" in m and "e-stop latch" in m
               for m in said), said  # fmt: skip


def test_a_latch_that_failed_during_a_release_is_not_written_back_after_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """An e-stop whose latch waits for another program's lock, then a release whose delete
    waits behind it: the latch's write fails during the release. Its retries began then, and
    one queued behind the delete wrote the latch back after it — the service released, the
    disk latched (a restart came up e-stopped). Nothing is written during a release now."""
    monkeypatch.setattr(hand_service, "LATCH_RETRY_S", 0.05)
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> None:
        async with service(cfg, Simulated()) as (c, services):
            st = services.station
            assert st.store is not None
            store, write = st.store, st.store.latch_estop
            write_go, deleting, delete_go = threading.Event(), threading.Event(), threading.Event()

            def locked_out(reason: str, since: str | None = None) -> dict[str, str]:
                store.latch_estop = write  # type: ignore[method-assign]  # (the retries' own)
                assert write_go.wait(30)
                raise sqlite3.OperationalError("database is locked")

            def delete_behind_the_lock() -> None:  # as the real delete waits: in the lock
                with store._lock:
                    deleting.set()
                    assert delete_go.wait(30)
                    store._durably_locked("DELETE FROM estop")

            store.latch_estop = locked_out  # type: ignore[method-assign]
            store.release_estop = delete_behind_the_lock  # type: ignore[method-assign]
            assert (await c.post("/api/estop")).json()["recorded"] is False
            release = asyncio.create_task(c.post("/api/estop/release", headers=JSON))
            assert await asyncio.to_thread(deleting.wait, 30)
            write_go.set()  # the e-stop's write fails while the delete waits
            while (await c.get("/api/status")).json()["estop"].get("recorded") != "no":
                await asyncio.sleep(0.01)
            await asyncio.sleep(0.3)  # (a retry had time to queue behind the delete)
            delete_go.set()
            assert (await release).json() == {"estopped": False}
            await asyncio.sleep(0.3)  # (and to write after it)
            assert store.estop_latch() is None
            assert (await c.get("/api/status")).json()["estop"] is None

    asyncio.run(main())


def test_closing_the_service_waits_for_an_estops_latch_still_being_written(
    tmp_path: Path,
) -> None:
    """An e-stop whose latch waits for another program's lock on the run database, then the
    service shuts down (SIGTERM's way): the database was closed under the waiting write, which
    crashed the process now and then. Closing now waits for the write: once closed, the latch
    is on disk for the next start."""
    db = tmp_path / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'", "storage.busy_timeout_s=30"],
                      use_env=False)  # fmt: skip
    other = sqlite3.connect(db, timeout=0, check_same_thread=False)
    let_go = threading.Event()

    def hold_then_let_go() -> None:
        assert let_go.wait(30)
        other.rollback()

    async def main() -> None:
        async with service(cfg, Simulated()) as (c, services):
            store = services.station.store
            assert store is not None
            close = store.close

            def closing() -> None:  # the other program lets go once the close has begun
                let_go.set()
                close()

            store.close = closing  # type: ignore[method-assign]
            other.execute("BEGIN EXCLUSIVE")
            pressed = (await c.post("/api/estop")).json()
            assert pressed["estopped"] is True and pressed["recorded"] is False
            assert (await c.get("/api/status")).json()["estop"]["recorded"] == "pending"
            holder = threading.Thread(target=hold_then_let_go)
            holder.start()
        holder.join()

    asyncio.run(main())
    other.close()
    with contextlib.closing(sqlite3.connect(db)) as fresh:
        assert fresh.execute("SELECT reason FROM estop").fetchall() == [("e-stop requested",)]


def test_an_estop_reaches_the_hand_while_a_shutdown_stops_the_run(tmp_path: Path) -> None:
    """SIGTERM or Ctrl-C: the run stops and releases before the service exits. uvicorn closed
    its listener and connections first, so an e-stop sent while the fingers still moved found
    no one to take it. Motion is now stopped first, the API still answering."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'", "service.port=0"],
                      use_env=False)  # fmt: skip

    async def main() -> tuple[list[dict[str, Any]], Any, tuple[bool, ...]]:
        services = await open_services(cfg, Simulated(), viewer=False)
        st = services.station
        assert st.bench is not None
        sock = listen_socket(cfg)
        base = f"http://127.0.0.1:{sock.getsockname()[1]}"
        server = _Server(uvicorn.Config(create_app(services), log_config=None, lifespan="on"))
        answered: list[dict[str, Any]] = []
        stop_motion = st.stop_motion

        async def pressed_meanwhile() -> None:  # an e-stop while the service stops the run
            if answered:  # (close() stops motion again: nothing left to stop)
                return await stop_motion()
            async with httpx.AsyncClient(base_url=base, timeout=30) as c:
                answered.append((await c.post("/api/estop")).json())
                await stop_motion()
                late = await c.post("/api/runs", json={})  # and no new run meanwhile
                answered.append({"start": late.status_code, **late.json()})

        st.stop_motion = pressed_meanwhile  # type: ignore[method-assign]
        try:
            async with asyncio.timeout(60):
                serving = asyncio.create_task(server.serve(sockets=[sock]))
                while not server.started:
                    await asyncio.sleep(0.01)
                async with httpx.AsyncClient(base_url=base, timeout=30) as c:
                    assert (await c.post("/api/runs", json={})).status_code == 201
                while not st.running:
                    await asyncio.sleep(0.01)
                server.should_exit = True  # as its signal handler does, the run pre-shaping
                await serving
        finally:
            await close_services(services)
        return answered, st.last_run, st.bench.sim.sdh.powered

    answered, last, powered = asyncio.run(main())
    assert answered[0]["estopped"] is True, answered
    assert answered[1]["start"] == 503 and "shutting down" in answered[1]["error"], answered
    assert last is not None and last["status"] == "e-stopped" and not any(powered), last


def test_an_estop_answers_while_a_crashed_runs_record_waits_for_a_lock(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A run that crashes (a bug) is recorded as faulted; another program holding the run
    database locked meanwhile held the event loop up to the busy timeout, an e-stop with it,
    and the record was then given up (the run left 'running'). The record is written in a
    thread: the e-stop answers at once, and the record is written once the lock is let go."""
    db = tmp_path / "runs.sqlite"
    cfg = load_config(overrides=[f"storage.db_path='{db}'", "storage.busy_timeout_s=20"],
                      use_env=False)  # fmt: skip

    # another program; its BEGIN waits out the recorder's own first write
    other = sqlite3.connect(db, timeout=30, check_same_thread=False)

    crashed = asyncio.Event()

    async def crash(self: RecordedRun) -> dict[str, Any]:
        other.execute("BEGIN EXCLUSIVE")  # another program, from the run's start on
        asyncio.get_running_loop().call_soon(crashed.set)  # once its record is under way
        raise RuntimeError("a bug")

    monkeypatch.setattr(RecordedRun, "execute", crash)

    async def main() -> None:
        async with service(cfg, Simulated()) as (c, services):
            st = services.station
            started = await c.post("/api/runs", json={})
            assert started.status_code == 201, started.text
            await crashed.wait()  # the crashed run's record now waits for the lock
            pressed = await c.post("/api/estop", timeout=30)
            assert pressed.status_code == 200 and pressed.json()["estopped"] is True
            other.rollback()  # the record, waiting for it, is written now (on the event
            # loop it had given up after the busy timeout: the run left 'running')
            assert st._run_task is not None
            await st._run_task
            run = st.store.run(started.json()["run_id"])
            assert run is not None and run["status"] == "faulted", run
            assert run["summary"]["message"] == "internal error: a bug"

    asyncio.run(main())
    other.close()


def test_with_a_token_the_3d_view_may_only_estop(tmp_path: Path) -> None:
    """The 3-D view cannot authenticate, and with a token set it listens where the service
    does: its buttons may stop the hand, nothing else (a mutation audit removed the rule and
    every other test passed)."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'",
                                 "service.token='s3cret'"], use_env=False)  # fmt: skip

    async def main() -> None:
        async with service(cfg, Simulated()) as (_c, services):
            st = services.station
            assert st.joints is not None
            for kind, args in (("start", {}), ("stop", {}), ("open", {}), ("release", {}),
                               ("params", {"grasp_force": 3.0})):  # fmt: skip
                with pytest.raises(hand_service.ServiceError) as refused:
                    await st.command(kind, args)
                assert refused.value.status == 403, kind
                assert "needs its token" in str(refused.value), kind
            assert not st.running and not st.opening and st.params.grasp_force == 2.0
            await st.command("estop", {})
            assert st.joints.estopped
            with pytest.raises(hand_service.ServiceError):  # nor may it undo the e-stop
                await st.command("release", {})
            assert st.joints.estopped

    asyncio.run(main())


def test_an_estop_the_runs_next_command_meets_ends_the_run_estopped_not_faulted(
    tmp_path: Path,
) -> None:
    """The e-stop latches the link and tells the run in the same instant; the stop itself goes
    out a moment later. A command the run sends in between is refused by the latch: the run
    must end e-stopped, not "faulted: joint_error" (a mutation audit removed the telling and
    every other test passed)."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'"], use_env=False)

    async def main() -> tuple[dict[str, Any], list[str]]:
        async with service(cfg, Simulated()) as (c, services):
            st = services.station
            assert st.joints is not None and st.store is not None
            joints, pressed = st.joints, []
            real = joints.set_targets

            async def estop_first(angles: Any) -> Any:
                if st.running and not pressed and len(calls) >= 3:  # mid-move
                    pressed.append(asyncio.ensure_future(st.estop()))
                    await asyncio.sleep(0)  # the e-stop's first half runs: latch, the run told
                calls.append(1)
                return await real(angles)

            calls: list[int] = []
            joints.set_targets = estop_first  # type: ignore[method-assign]
            run_id = (await c.post("/api/runs", headers=JSON, json={})).json()["run_id"]
            async with asyncio.timeout(60):
                while not pressed or not pressed[0].done() or st.running:
                    await asyncio.sleep(0.02)
            kinds = [e["kind"] for e in st.store.events(run_id)]
            return st.last_run or {}, kinds

    last, kinds = asyncio.run(main())
    assert last.get("status") == "e-stopped", last
    assert "fault" not in kinds and "estop" in kinds, kinds


def test_a_second_ctrl_c_skips_the_wait_for_clients_not_the_close(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """Ctrl-C twice (uvicorn's "force quit": it no longer waits for connections to close) left
    the app's shutdown unsent: the event loop then cancelled it, and the journal showed "ERROR
    uvicorn.error: Traceback … CancelledError" under a clean exit. The app still shuts down."""
    cfg = load_config(overrides=[f"storage.db_path='{tmp_path}/runs.sqlite'", "service.port=0"],
                      use_env=False)  # fmt: skip
    closed: list[bool] = []

    async def main() -> None:
        services = await open_services(cfg, Simulated(), viewer=False)
        sock = listen_socket(cfg)
        server = _Server(uvicorn.Config(create_app(services), log_config=None, lifespan="on"))
        try:
            async with asyncio.timeout(60):
                serving = asyncio.create_task(server.serve(sockets=[sock]))
                while not server.started:
                    await asyncio.sleep(0.01)
                server.handle_exit(signal.SIGINT, None)  # as Ctrl-C's handler, twice
                server.handle_exit(signal.SIGINT, None)
                await serving
                closed.append(services.station._closed)
        finally:
            await close_services(services)

    with caplog.at_level(logging.INFO):
        asyncio.run(main())
    assert closed == [True]  # by the app's own shutdown, before serve() returned
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [r.getMessage() for r in errors]
