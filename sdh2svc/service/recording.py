"""Recording a run on an open hand: the runner, its recorder and its summary, in one place.

Used by ``sdh2svc run`` (:mod:`sdh2svc.service.headless`) and by the service
(:mod:`sdh2svc.service.hand_service`): both create the run's database row, record every sample,
event and frame, and finish the row with the summary. On a simulated hand (a bench), the run
also records the simulation's truth: the object's outline once (its own frame), its pose and
state with every sample (as the physics last stepped: reading it steps nothing, so the run is
the one it would have been unrecorded), and in the summary the truth as the run let go.
"""

from __future__ import annotations

import asyncio
import logging
import sqlite3
import threading
import time
from collections.abc import Awaitable
from typing import Any, TypeVar

from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus, TactileFrame
from sdh2svc.config import Settings
from sdh2svc.connect import Bench
from sdh2svc.control.observer import BaseObserver, Event, EventKind, RunObserver
from sdh2svc.control.params import RollingParams
from sdh2svc.control.runner import Runner, RunResult
from sdh2svc.control.sample import Sample
from sdh2svc.heap import settle
from sdh2svc.provenance import code_version
from sdh2svc.service.store import Recorder, RunStore, retry_locked
from sdh2svc.service.telemetry import outline_points

log = logging.getLogger(__name__)
T = TypeVar("T")
END_RETRY_S = 5.0  # a run's end the database refused: tried again after this long


async def _whole(aw: Awaitable[T]) -> T:
    """``aw`` to its end even if the awaiting task is cancelled meanwhile: then it is awaited
    all the same, and the cancellation goes on once it is done."""
    fut = asyncio.ensure_future(aw)
    try:
        return await asyncio.shield(fut)
    except asyncio.CancelledError:
        await fut
        raise


class RecordedRun:
    """A :class:`Runner` whose samples, events and frames go to the database, then to
    ``observer`` (the service's telemetry, a campaign's truth probe)."""

    def __init__(
        self,
        cfg: Settings,
        joints: JointLink,
        tactile: TactileBus,
        store: RunStore,
        *,
        params: RollingParams | None = None,
        meta: dict[str, Any] | None = None,
        bench: Bench | None = None,
        observer: RunObserver | None = None,
        create_wait_s: float | None = None,
    ) -> None:
        """``create_wait_s``: how long the run's creation waits for a lock another program
        holds on the database (default ``storage.busy_timeout_s``): sqlite3.OperationalError
        after it, and nothing recorded."""
        self.cfg, self.tactile, self.store, self.bench = cfg, tactile, store, bench
        params = params or cfg.rolling
        full_meta = {
            "params": params.model_dump(),
            "object": bench.obj.model_dump() if bench else None,
            "configuration": cfg.recorded(),  # its export draws it as it was, not as is
            "software": code_version(),  # which sdh2svc recorded it
            **(meta or {}),
        }
        outline = None
        if bench is not None:
            obj, pts = bench.obj, outline_points(bench.outline.perimeter_points)
            outline = (obj.name or obj.kind, float(obj.size_mm), pts.tolist())  # as truth names it
        self.run_id = store.create_run(full_meta, outline, wait_s=create_wait_s)
        self._rec = Recorder(store.path, self.run_id, busy_timeout_s=store.busy_timeout_s)
        self._truth: dict[str, Any] = {}
        self._observer: RunObserver = observer or BaseObserver()
        self.runner = Runner(cfg.control(), joints, tactile, params=params, observer=self)
        self.summary: dict[str, Any] | None = None

    # --- control.observer.RunObserver: the runner reports here ---

    def sample(self, s: Sample) -> None:
        self._rec.sample(s)
        if self.bench is not None:
            o = self.bench.object_now()
            self._rec.truth(s.iteration, s.t, o.pose, o.held, o.dropped, o.in_fixture, o.slips)
        self._observer.sample(s)

    def event(self, e: Event) -> None:
        self._rec.event(e.t, e.iteration, e.kind, e.detail)
        # the simulation's truth as the run ends, before the fingers let go
        if (
            self.bench is not None
            and e.kind is EventKind.PHASE
            and e.detail["phase"] == "releasing"
        ):
            self._truth.update(self.bench.truth().summary())
        self._observer.event(e)

    def frame(self, t: float, iteration: int, frame: TactileFrame) -> None:
        self._rec.frame(t, iteration, frame.timestamp_ms, frame.texels)
        self._observer.frame(t, iteration, frame)

    async def execute(self) -> dict[str, Any]:
        """Run to the end (completed, stopped, faulted, e-stopped) and return the summary.

        The record is closed and the run's end written in threads (a run database another
        program holds locked must not hold the event loop: the service's every answer, its
        links and the e-stop go through it), and both finish even if this task is cancelled
        meanwhile (a run whose end was never written stayed ``running`` for good)."""
        settle()  # before anything moves: no full collection of the heap mid-run (sdh2svc.heap)
        try:
            try:
                result = await self.runner.run()  # (an e-stop's cancellation ends it too)
            finally:
                await self._close()
        except asyncio.CancelledError:
            result = self.runner.result
            if result.status == "running":  # as a run whose process died: nothing ended it
                result.status, result.message = "interrupted", (
                    "cancelled before it ended: the fingers stopped where they were and may "
                    "still hold the object")  # fmt: skip
            self.summary = await _whole(self._finish(result))
            raise
        self.summary = await _whole(self._finish(result))
        return self.summary

    async def _close(self) -> None:
        """The recording closed once the e-stop's events (if any) are in it."""
        try:
            await self.runner.estop_reported()  # the e-stop's events go to the record too
        finally:  # (closed also if the wait is cancelled)
            await _whole(asyncio.to_thread(self._close_recorder))

    def _write_end(self, summary: dict[str, Any]) -> None:
        retry_locked(lambda: self.store.finish_run(self.run_id, summary["status"], summary))

    def _close_recorder(self) -> None:
        try:
            self._rec.close()
        except Exception:
            log.exception("run %d: its recording did not close cleanly", self.run_id)

    async def _finish(self, result: RunResult) -> dict[str, Any]:
        """The summary completed and written as the run's end (a failure to write it is logged
        and noted in the summary: the run ended as it ended)."""
        # in a thread: a long run's statistics take ≈ 1 s a million iterations, and on the event
        # loop nothing else (an answer, the telemetry, an e-stop's request) goes meanwhile
        summary = await asyncio.to_thread(result.summary)
        st = self.tactile.stats
        summary["frames"] = {"received": st.frames, "crc_errors": st.crc_errors,
                             "resyncs": st.resyncs, "frames_per_s": st.frames_per_s}  # fmt: skip
        summary["run_id"] = self.run_id
        if self.bench is not None:
            summary["truth"] = self._truth or self.bench.truth().summary()
            if summary["truth"]["dropped"] and summary["status"] == "completed":
                summary["status"] = "dropped"
        if self.store.replaced():  # its rows went to a file nobody finds at the path
            gone = (f"the run database {self.store.path} was deleted, renamed or replaced "
                    "during the run: its record is not in the file there")  # fmt: skip
            log.error("run %d: %s", self.run_id, gone)
            _note(summary, gone)
        if self._rec.lost:  # said where the run is looked at, not in a log line alone
            why = self._rec.error or self._rec.refused or "the database refused them too long"
            summary["not_recorded"] = {"items": self._rec.lost, "error": str(why)}
            _note(summary, f"{self._rec.lost} recorded items (samples, frames, events) are not "
                           f"in {self.store.path}: {why}")  # fmt: skip
        try:  # in a thread: a database another program holds locked must not hold the loop
            await asyncio.to_thread(self._write_end, summary)
        except sqlite3.Error as e:  # the run ended as it ended; only its record is missing
            log.error("run %d: its end could not be recorded: %s; tried again every %g s",
                      self.run_id, e, END_RETRY_S)  # fmt: skip
            threading.Thread(target=self._write_end_later, args=(dict(summary),),
                             name=f"run-end-{self.run_id}", daemon=True).start()  # fmt: skip
            _note(summary, f"its end is not recorded in {self.store.path}: {e}")
        return summary

    def _write_end_later(self, summary: dict[str, Any]) -> None:
        """The run's end written once the disk takes it (a full disk freed): it stayed
        'running' for the service's life, could not be deleted as one being recorded, and a
        restart called it killed or crashed. Given up when the store closes."""
        while True:
            time.sleep(END_RETRY_S)
            try:
                self._write_end(summary)
            except sqlite3.ProgrammingError:  # the store is closed: a restart marks it
                return
            except sqlite3.Error:
                continue
            log.info("run %d: its end is recorded now", self.run_id)
            return


def _note(summary: dict[str, Any], note: str) -> None:
    """``note`` added to the summary's message."""
    summary["message"] = f"{summary['message']}; {note}" if summary.get("message") else note
