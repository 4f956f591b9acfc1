"""The hand's application service: the open hand (through :mod:`sdh2svc.connect`), the current
run, the parameters, the e-stop, and the telemetry that flows from them to the hub.

Everything a user can ask for (REST, the 3-D view's buttons) is a method here, with one rule per
conflict: one run at a time, no run while the e-stop is latched, no object change during a run.
Refusals are :class:`ServiceError` with a sentence a person can act on and an HTTP status.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import sqlite3
from collections.abc import Callable, Mapping
from contextlib import AsyncExitStack
from dataclasses import asdict
from typing import Any

from pydantic import ValidationError

from sdh2svc.bus.joint import EmergencyStopped, JointLink, JointLinkError
from sdh2svc.bus.tactile import Subscription, TactileBus, TactileFrame
from sdh2svc.config import Settings, format_errors
from sdh2svc.connect import Bench, Hand, Where, connect_hand
from sdh2svc.control.motion import move_to_preshape
from sdh2svc.control.observer import BaseObserver, EventKind
from sdh2svc.control.observer import Event as RunEvent
from sdh2svc.control.params import RollingParams
from sdh2svc.control.runner import Phase, Runner
from sdh2svc.control.safety import SafetyConfig, params_maxima, params_outside
from sdh2svc.control.sample import Sample
from sdh2svc.provenance import code_version
from sdh2svc.service.hub import TelemetryHub, cancel
from sdh2svc.service.latch import latched_elsewhere, tell_taken, this_program
from sdh2svc.service.recording import RecordedRun
from sdh2svc.service.store import (
    INTERRUPTED,
    RunStore,
    StoreError,
    locked,
    now_iso,
    opened_elsewhere,
)
from sdh2svc.service.telemetry import (
    OUTLINE_POINTS,
    Event,
    Pose,
    SampleMsg,
    Sim,
    Status,
    Tactile,
)
from sdh2svc.sim.objects import PRESETS, ObjectSpec, Shape, get_object, parse_object
from sdh2svc.sim.press import Press

log = logging.getLogger(__name__)
# How long an e-stop's answer waits for its latch to reach the disk (the stop itself does not
# wait): a run database another program holds locked would hold it busy_timeout_s.
RECORD_WAIT_S = 1.0
# A latch the run database did not take is written again this long after each failed write
# (which waited busy_timeout_s for a lock), until it takes it (a restart then keeps it) or the
# e-stop is released.
LATCH_RETRY_S = 2.0
ESTOP_REASON = "e-stop requested"  # the latch's reason, as the API's e-stop writes it
# How long a run's creation, on the event loop, waits for a lock another program holds on the
# run database: longer would hold up the e-stop's answer and the links with it.
CREATE_WAIT_S = 0.25

# Why a run was stopped, as its record says (the run's message)
STOPPED_BY_API = "through the API (POST /api/runs/stop)"
STOPPED_BY_VIEW = "from the 3-D view"
STOPPED_BY_SHUTDOWN = "as the service shut down"


class ServiceError(Exception):
    """A refused request: ``status`` is the HTTP status, ``details`` one line per problem."""

    def __init__(self, status: int, message: str, details: list[str] | None = None) -> None:
        super().__init__(message)
        self.status, self.message, self.details = status, message, details or []

    def __reduce__(self) -> tuple[Any, ...]:  # from a read's worker process, whole
        return (type(self), (self.status, self.message, self.details))


def validate_params(
    current: RollingParams, patch: dict[str, Any], safety: SafetyConfig
) -> RollingParams:
    """``current`` with ``patch`` laid over it, validated whole and against the supervisor's
    limits (422 naming each bad field: no parameter loosens a limit, :func:`params_outside`).
    Strictly: a value is taken as it is typed ("2" is no number; configuration files and
    --set, which are text, go through the lax path of sdh2svc.config)."""
    merged = {**current.model_dump(), **patch}
    try:
        new = RollingParams.model_validate(merged, strict=True)
    except ValidationError as e:
        lines = format_errors(e, RollingParams, maxima=params_maxima(safety))
        # and what the limits say of the fields that passed: every bad field in one answer
        bad = {str(err["loc"][0]) for err in e.errors() if err["loc"]}
        ok = {k: v for k, v in merged.items() if k not in bad}  # (each valid on its own)
        lines += params_outside(current.model_copy(update=ok), safety, section="")
        raise ServiceError(422, "invalid rolling parameters", lines) from None
    if problems := params_outside(new, safety, section=""):
        raise ServiceError(422, "invalid rolling parameters", problems)
    return new


def parse_object_request(name: str | None, spec: dict[str, Any] | None) -> Shape:
    """A preset by ``name`` or an object ``spec`` (422 naming the bad field)."""
    if (name is None) == (spec is None):
        raise ServiceError(422, "give either an object preset name or an object spec",
                           [f"presets: {', '.join(PRESETS)}"])  # fmt: skip
    if name is not None:
        try:
            return get_object(name)
        except KeyError as e:
            raise ServiceError(422, str(e.args[0])) from None
    try:
        shape = parse_object(spec or {})
    except ValidationError as e:
        raise ServiceError(422, "invalid object spec", format_errors(e, ObjectSpec)) from None
    if shape.name in PRESETS and shape != PRESETS[shape.name]:  # a record and a page would
        # show the preset's name for another object
        raise ServiceError(422, "invalid object spec", [
            f"name = {shape.name!r}: a preset's name, and this spec is not that preset: give "
            "the object a name of its own (or choose the preset by name)"])  # fmt: skip
    return shape


def _failure(stop: asyncio.Future[None]) -> str | None:
    """Why a finished e-stop did not reach the hand (None: it did)."""
    if stop.cancelled():
        return "the service closed"
    e = stop.exception()
    return None if e is None else str(e) or type(e).__name__


def _log_late_stop(stop: asyncio.Future[None]) -> None:
    """How an e-stop that outlived its answer ended."""
    if (e := _failure(stop)) is not None:
        log.error(
            "e-stop latched, but the hand was not reached: %s (its power-off is sent "
            "again as soon as the joint line answers)",
            e,
        )
    else:
        log.warning("e-stop: the hand confirmed the stop late")


class HandService:
    """Owns the open hand — a real one, or a simulated one with its bench — for the service's
    life."""

    def __init__(self, cfg: Settings, hub: TelemetryHub, where: Where) -> None:
        self.cfg, self.hub, self.where = cfg, hub, where
        self.params = cfg.rolling
        # whether the 3-D view is served (its process may die and take it away); None: no view
        self.view_served: Callable[[], bool] | None = None
        self._hand: Hand | None = None
        self._stack = AsyncExitStack()  # closes the hand (links, then a simulated hand)
        self.joints: JointLink | None = None
        self.tactile: TactileBus | None = None
        self.store: RunStore | None = None
        self.run: RecordedRun | None = None
        self._run_params: RollingParams | None = None
        self._run_task: asyncio.Task[None] | None = None
        self.last_run: dict[str, Any] | None = None
        self._monitor: Subscription | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._last_tactile = -math.inf
        self._opening: asyncio.Task[None] | None = None
        code_version()  # (a run records it: worked out here, not on a run's start)
        self._latch: dict[str, str] | None = None  # the e-stop latch as on disk (or unrecorded)
        self._closed = False
        self._shutting_down = False  # no new motion (stop_motion)
        self._late_stop: asyncio.Future[None] | None = None  # an e-stop outliving its answer
        self._latch_retry: asyncio.Task[None] | None = None  # an unrecorded latch written again
        self._releases = 0  # releases under way: no latch retry starts meanwhile

    # --- life -----------------------------------------------------------------------------------

    async def start(self) -> None:
        cfg = self.cfg
        self._hand = hand = await self._stack.enter_async_context(connect_hand(cfg, self.where))
        self.joints, self.tactile = hand.joints, hand.tactile
        self.store = RunStore(cfg.storage.db_path, busy_timeout_s=cfg.storage.busy_timeout_s)
        if others := opened_elsewhere(self.store.path):  # another service, a reader: say so
            log.warning("%s: it shares this service's runs and its one e-stop latch on disk "
                        "(each hand wants a run database of its own)", others)  # fmt: skip
        interrupted = self.store.mark_interrupted()
        if interrupted:
            log.warning("runs %s were still 'running' in %s, their process gone: marked "
                        "interrupted", interrupted, cfg.storage.db_path)  # fmt: skip
            # the status says so until the next run: the fingers stopped where they were (a
            # real hand may still hold the object), a person should look
            self.last_run = {"id": max(interrupted), "status": "interrupted",
                             "message": INTERRUPTED}  # fmt: skip
        self._latch = latch = self.store.estop_latch()
        if latch is not None:
            log.warning("the e-stop is latched (since %s: %s): motors off until released",
                        latch["since"], latch["reason"])  # fmt: skip
            with contextlib.suppress(JointLinkError):  # latches the link even if it fails
                await self.joints.emergency_stop()
        self.tactile.add_frame_listener(self._on_frame)
        if cfg.service.monitor_rate_hz > 0:
            self._monitor = self.tactile.subscribe(range(6), cfg.service.monitor_rate_hz)
        self._tasks = [asyncio.create_task(self._status_loop(), name="status"),
                       asyncio.create_task(self._pose_loop(), name="pose"),
                       asyncio.create_task(self._disk_latch_loop(), name="disk-latch")]  # fmt: skip
        ready = (
            "hand ready"
            if self.joints.connected and self.tactile.connected
            else ("waiting for the hand (each line opens as its controller answers)")
        )
        log.info("%s: dsa=%s sdh=%s sim=%s", ready, self.dsa_url, self.sdh_url, not hand.real)

    async def stop_motion(self) -> None:
        """The first step of shutting down, taken while the API still answers (an e-stop sent
        meanwhile reaches the hand): no new run or opening; the run stops and releases (e-stop
        past ``service.stop_timeout_s``); an opening hand holds. Idempotent."""
        self._shutting_down = True
        if self.running and self.run is not None:
            log.info("shutting down: stopping run %d first", self.run.run_id)
            self.run.runner.request_stop(STOPPED_BY_SHUTDOWN)
            try:
                await asyncio.wait_for(asyncio.shield(self._run_task),  # type: ignore[arg-type]
                                       self.cfg.service.stop_timeout_s)  # fmt: skip
            except (TimeoutError, Exception):
                log.warning("run %d did not stop in time: e-stop", self.run.run_id)
                with contextlib.suppress(Exception):
                    await self.run.runner.emergency_stop()
        await self._cancel_opening()

    async def close(self) -> None:
        """Stop motion first (:meth:`stop_motion`), then close."""
        if self._closed:
            return
        self._closed = True
        await self.stop_motion()  # (an opening hand's task cancelled there)
        await cancel(self._run_task)
        await self._end_latch_retry()
        if (self._latch or {}).get("recorded") in ("no", "pending"):  # said at the e-stop too
            log.warning("the e-stop's latch is not in %s: a restart comes up released (the "
                        "hand stays off until then)", self.cfg.storage.db_path)  # fmt: skip
        for task in self._tasks:
            await cancel(task)
        if self._monitor is not None:
            self._monitor.close()
        await self._stack.aclose()
        if self.store is not None:  # after a latch still being written (in a thread, as it)
            await asyncio.to_thread(self.store.close)
        log.info("hand closed")

    @property
    def bench(self) -> Bench | None:
        """The simulated hand's bench (None on a real hand, or before the hand is open)."""
        return self._hand.bench if self._hand else None

    @property
    def dsa_url(self) -> str:
        return self._hand.dsa_url if self._hand else ""

    @property
    def sdh_url(self) -> str:
        return self._hand.sdh_url if self._hand else ""

    # --- what users ask for ---------------------------------------------------------------------

    @property
    def running(self) -> bool:
        return self._run_task is not None and not self._run_task.done()

    @property
    def opening(self) -> bool:
        return self._opening is not None and not self._opening.done()

    def start_run(self, params: dict[str, Any] | None = None, obj: Any = None) -> dict[str, Any]:
        """Start a run (409 while one runs, while the hand opens, or the e-stop is latched; 503
        while a line is down: nothing is recorded, as a run could not even pre-shape)."""
        # the request first (422), then whether the hand can take it (409, 503)
        run_params = (
            validate_params(self.params, params, self.cfg.safety) if params else self.params
        )
        joints, tactile, store = self._links()
        self._refuse_if_shutting_down()
        if joints.estopped:  # first: an e-stopped run's task may still be ending
            raise ServiceError(409, "the e-stop is latched: release it first "
                               "(POST /api/estop/release)")  # fmt: skip
        if self.running and self.run is not None:
            raise ServiceError(409, self._run_busy("is already running"))
        if self.opening:
            raise ServiceError(409, "the hand is opening; start the run when it is open")
        self._require_lines(joints, tactile)
        if self.bench is not None:  # as in a lab: the object is put back in the fixture first
            self.set_object(obj or self.bench.obj)
        assert self._hand is not None  # open: _links() says so
        meta = {**self._hand.describe(), "service": True}
        try:  # on the event loop: a lock another program holds is waited for only briefly
            run = RecordedRun(self.cfg, joints, tactile, store, params=run_params, meta=meta,
                              bench=self.bench, observer=_RunTelemetry(self),
                              create_wait_s=CREATE_WAIT_S)  # fmt: skip
        except (sqlite3.OperationalError, StoreError) as e:
            if isinstance(e, sqlite3.OperationalError) and locked(e):
                why = (f"the run database {store.path} is locked by another program ({e}): no "
                       "run was started; try again once it lets go (a vacuum, a database "
                       "browser with unsaved changes)")  # fmt: skip
            else:  # a full disk, a read-only or failing one: no run without its record
                why = (f"the run database {store.path} did not take the run's start ({e}): no "
                       "run was started")  # fmt: skip
            raise ServiceError(503, why) from None
        self._run_params, self.run = run_params, run
        self._run_task = asyncio.create_task(self._execute(self.run), name="run")
        log.info("run %d started (cycles=%d)", self.run.run_id, run_params.cycles)
        return {"run_id": self.run.run_id, "state": self.run.runner.phase.value}

    def _run_busy(self, running: str, after_stop: str = "") -> str:
        """Why a command waits for the run: it runs, or it has ended and its end is still being
        written (another program holding the database, a full disk: up to a minute or more)."""
        assert self.run is not None
        phase = self.run.runner.phase
        if phase in (Phase.DONE, Phase.STOPPED, Phase.FAULTED, Phase.ESTOPPED):
            return (f"run {self.run.run_id} has ended ({phase.value}) and its record is still "
                    f"being written to {self.cfg.storage.db_path}: try again once it is (status "
                    "shows no run running)")  # fmt: skip
        return f"run {self.run.run_id} {running} ({phase.value}); stop it first{after_stop}"

    def stop_run(self, reason: str = STOPPED_BY_API) -> dict[str, Any]:
        """Stop the run (it releases the object; ``reason`` is its recorded message), or an
        opening hand where it is."""
        if self.opening and self._opening is not None:
            self._opening.cancel()  # its task holds the hand where it is
            return {"run_id": None, "state": "stopping"}
        if not self.running or self.run is None:
            raise ServiceError(409, "no run is running")
        self.run.runner.request_stop(reason)
        log.info("run %d: stop requested (%s)", self.run.run_id, reason)
        return {"run_id": self.run.run_id, "state": self.run.runner.phase.value}

    async def estop(self) -> dict[str, Any]:
        """Motors off now, from any state; never refused. The link latches at once (nothing
        moves the hand until released) and the stop goes to the hand while the latch is written
        to disk beside it (a restart keeps it): the disk write runs in a thread, so a locked or
        failing run database neither holds up the stop nor cancels it, and is reported
        (``recorded: false``). If the line is down, the stop is sent as soon as it is back."""
        joints, _, store = self._links()
        log.warning("E-STOP")
        joints.latch()
        # the run told in the same instant: its next command, refused by the latch, must not
        # end it as a fault before the stop below reaches it
        runner = self.run.runner if self.running and self.run is not None else None
        if runner is not None:
            runner.begin_emergency_stop()
        since = now_iso()  # when it was pressed, whenever the disk takes it
        record = asyncio.ensure_future(_write_latch(store, {"since": since}))
        stop = asyncio.ensure_future(self._stop_hand(joints, runner))
        # a silent line would hold the answer through the link's retries: the answer waits for
        # one reply's timeout; the stop goes on meanwhile (and the latch holds the line anyway)
        done, _ = await asyncio.wait({stop}, timeout=joints.timeout_s + 0.5)
        reached, problems = True, []
        if not done:
            reached = False
            problems.append("the hand has not confirmed the stop yet (the joint line does not "
                            "answer); its power-off is sent again as soon as the line "
                            "answers")  # fmt: skip
            self._late_stop = stop  # (held: the loop keeps only a weak reference to a task)
            stop.add_done_callback(_log_late_stop)
        elif (e := _failure(stop)) is not None:
            reached = False
            problems.append(f"the hand was not reached ({e}); its power-off is sent again as "
                            "soon as the line answers")  # fmt: skip
            log.error(
                "e-stop latched, but the hand was not reached: %s (its power-off is sent "
                "again as soon as the joint line answers)",
                e,
            )
        self.publish_status()
        recorded = await self._recorded(record, since)
        if recorded is None:
            problems.append(f"the latch is still being written to the run database "
                            f"({store.path}: another program holds it locked); the status's "
                            "estop.recorded says when it is on disk")  # fmt: skip
        elif not recorded:
            problems.append(f"the latch could not be written to the run database "
                            f"({store.path}): a restart would not keep it; it is written "
                            "again until the disk takes it")  # fmt: skip
        self.publish_status()
        out: dict[str, Any] = {"estopped": True, "hand_reached": reached,
                               "recorded": bool(recorded)}  # fmt: skip
        if problems:
            out["detail"] = "; ".join(problems)
        return out

    async def _stop_hand(self, joints: JointLink, runner: Runner | None) -> None:
        """The e-stop sent to the hand: the run that was running when it came ends e-stopped
        (one that had already ended, and is only being recorded, keeps its end), or an opening
        hand stops."""
        if runner is not None and runner.begin_emergency_stop():
            await runner.emergency_stop()
            return
        # the hand's own e-stop: no run, or one that has ended and is still being recorded.
        # The power-off first: an opening hand's cancellation holds it, through its retries on
        # a bad line (the latch already refuses its next increment)
        try:
            await joints.emergency_stop()
        finally:
            await self._cancel_opening()
            self._hand_event(EventKind.ESTOP, {})

    async def _recorded(self, record: asyncio.Future[dict[str, str]], since: str) -> bool | None:
        """The e-stop's latch written to disk (``self._latch``); False, logged, if it failed
        (the latch then stands in memory only, shown in the status without a record); None if
        the write is still out after RECORD_WAIT_S (a lock held by another program): the answer
        does not wait for it, the status says ``"recorded": "pending"`` until it is done."""
        done, _ = await asyncio.wait({record}, timeout=RECORD_WAIT_S)
        if not done:
            self._latch = self._latch or {"since": since, "reason": ESTOP_REASON,
                                          "recorded": "pending"}  # fmt: skip
            record.add_done_callback(lambda fut: self._latch_written(fut, since))
            return None
        return self._latch_written(record, since)

    def _latch_written(self, record: asyncio.Future[dict[str, str]], since: str) -> bool:
        """The latch as the disk write left it: on disk, or in memory only (logged)."""
        if record.cancelled():
            return False
        e = record.exception()
        if e is None:
            if self._latch is not None or self._latched_now():  # not released meanwhile
                self._latch = record.result()
            self.publish_status()
            return True
        log.error("e-stop latched, but not on disk: %s (written again until it is)", e)
        if self._latched_now():
            self._unrecorded({"since": since, "reason": ESTOP_REASON})
        self.publish_status()
        return False

    def _unrecorded(self, latch: Mapping[str, str]) -> None:
        """The latch stands in memory only: said in the status, and written again
        LATCH_RETRY_S after each failed write until the disk takes it (or the e-stop is
        released)."""
        self._latch = {**latch, "recorded": "no"}
        if self._closed or self._releases:  # (a release that fails starts them)
            return
        if self._latch_retry is None or self._latch_retry.done():
            self._latch_retry = asyncio.get_running_loop().create_task(
                self._write_latch_until_taken(), name="estop-latch-retry"
            )

    async def _write_latch_until_taken(self) -> None:
        store = self.store
        while store is not None:
            await asyncio.sleep(LATCH_RETRY_S)
            latch = self._latch or {}
            if latch.get("recorded") != "no" or not self._latched_now():
                return  # on disk by another press, or released
            write = asyncio.ensure_future(_write_latch(store, latch))
            try:
                self._latch = await asyncio.shield(write)
            except asyncio.CancelledError:  # (a release, a close) only once the write is done:
                with contextlib.suppress(Exception):  # its delete must come after it
                    await write
                raise
            except (OSError, sqlite3.Error):
                continue
            log.info("the e-stop's latch is on disk now")
            self.publish_status()
            return

    async def _end_latch_retry(self) -> None:
        """No further write of the latch (before a release deletes it, or the store closes)."""
        task, self._latch_retry = self._latch_retry, None
        if task is not None:
            await cancel(task)

    def _latched_now(self) -> bool:
        """Whether the joint link holds the e-stop latched (or has no link to ask)."""
        return self._hand is None or self._hand.joints.estopped

    async def release_estop(self) -> dict[str, Any]:
        """Release the latch: its record on disk first, then the hand (motors on). Either
        failing leaves the e-stop latched, on disk and in the hand (503). No latch retry runs
        meanwhile (one would write the latch back after the delete); a release that fails
        leaves an unrecorded latch to them again. Another program's lock can hold it up twice
        ``storage.busy_timeout_s``: a latch write under way is let finish (the delete must
        follow it), then the delete waits its own (docs/api.md)."""
        joints, _, store = self._links()
        if not joints.estopped and self._latch is None:
            # nothing of this service's to release: the latch on disk, if any, is another's (a
            # service on the same database), and deleting it would lose it at that one's restart
            return {"estopped": False}
        seen = joints.latches  # an e-stop pressed from here on is not released
        self._releases += 1
        try:
            await self._end_latch_retry()
            return await self._release(joints, store, seen)
        finally:
            self._releases -= 1
            if self._latch is not None and self._latch.get("recorded") == "no":
                self._unrecorded(self._latch)

    async def _release(self, joints: JointLink, store: RunStore, seen: int) -> dict[str, Any]:
        try:
            await asyncio.to_thread(store.release_estop)
        except (OSError, sqlite3.Error) as e:
            raise ServiceError(503, f"the run database did not take the release ({e}); the "
                               "e-stop stays latched") from None  # fmt: skip
        latch = self._latch or {}
        try:
            await joints.release(seen)
        except EmergencyStopped:
            # an e-stop came while the record was being deleted: its own write may have gone
            # first, and the delete taken it: on disk again, as the e-stop said
            await self._latch_again(store, self._latch or {})
            self.publish_status()
            raise ServiceError(409, "an e-stop came during the release: it stays latched "
                               "(release it again)") from None  # fmt: skip
        except JointLinkError as e:  # the hand stays latched: so does its record, as it was
            await self._latch_again(store, latch)
            raise ServiceError(503, f"the hand did not take the release: {e}; the e-stop "
                               "stays latched") from None  # fmt: skip
        self._latch = None
        log.info("e-stop released")
        self.publish_status()
        return {"estopped": joints.estopped}

    async def _latch_again(self, store: RunStore, latch: dict[str, Any]) -> None:
        """The latch written to disk again as ``latch`` had it, after a release that did not
        go through (the line or the disk may be the problem: not taken, it is written again
        until the disk takes it)."""
        latch = {k: v for k, v in latch.items() if k != "recorded"}
        try:
            self._latch = await _write_latch(store, latch)
        except (OSError, sqlite3.Error) as e:
            log.error("the e-stop stays latched, but not on disk: %s", e)
            self._unrecorded({"since": now_iso(), "reason": ESTOP_REASON, **latch})

    async def open_hand(self) -> dict[str, Any]:
        """Open the coupled fingers to the pre-shape pose (releasing whatever they hold), in
        short increments from a live loop; answers at once, the move goes on as a task.

        409 while a run is running, while the hand is already opening, or while the e-stop is
        latched; 503 when the links are not up. Events ``open`` (start) and ``opened`` / a
        ``fault`` go to the hub; ``status()["hand"]["opening"]`` is true meanwhile.
        """
        joints, _, _ = self._links()
        self._refuse_if_shutting_down()
        if joints.estopped:  # first: an e-stopped run's task may still be ending
            raise ServiceError(409, "the e-stop is latched: release it first "
                               "(POST /api/estop/release)")  # fmt: skip
        if self.running and self.run is not None:
            raise ServiceError(409, self._run_busy("is running", " (a stopped run opens the hand "
                                                                "itself)"))  # fmt: skip
        if self.opening:
            raise ServiceError(409, "the hand is already opening")
        self._require_lines(joints)
        self._opening = asyncio.create_task(self._open(joints), name="open-hand")
        self.publish_status()
        return {"state": "opening"}

    async def _open(self, joints: JointLink) -> None:
        lim = self.cfg.limits
        self._hand_event(EventKind.OPEN, {})
        try:
            await move_to_preshape(joints, self.cfg.run, (lim.min_deg, lim.max_deg),
                                   self.cfg.safety)  # fmt: skip
        except asyncio.CancelledError:  # said before the hold, which a cancel may cut short
            self._hand_event(EventKind.OPENED, {"completed": False, "message": "stopped"})
            with contextlib.suppress(Exception):
                await joints.hold()
            raise
        except Exception as e:  # the line failed, the fingers are blocked, an e-stop came
            if joints.estopped:  # the e-stop's latch refused the next increment: stopped
                self._hand_event(EventKind.OPENED, {"completed": False, "message": "stopped"})
            else:
                log.warning("opening the hand failed: %s", e)
                self._hand_event(EventKind.FAULT, {"fault": "open_failed", "message": str(e)})
            with contextlib.suppress(Exception):
                await joints.hold()
        else:
            self._hand_event(EventKind.OPENED, {"completed": True})
        finally:
            self.publish_status()

    async def _cancel_opening(self) -> None:
        task, self._opening = self._opening, None
        if task is not None:
            await cancel(task)

    def _hand_event(self, kind: EventKind, detail: dict[str, Any]) -> None:
        self.hub.publish(Event(None, None, None, kind, detail))

    @property
    def params_in_force(self) -> RollingParams:
        """The running run's parameters, else those the next run starts with."""
        return self._run_params if self.running and self._run_params else self.params

    def patch_params(self, patch: dict[str, Any]) -> RollingParams:
        """Validate and take ``patch`` for later runs and — applied whole at its next grasp
        frame or rolling iteration — for the running one (laid over its own parameters, e.g.
        its cycles)."""
        new = validate_params(self.params, patch, self.cfg.safety)
        if self.running and self.run is not None and self._run_params is not None:
            self._run_params = validate_params(self._run_params, patch, self.cfg.safety)
            self.run.runner.set_params(self._run_params)
        self.params = new
        log.info("parameters changed: %s", patch)
        self.publish_status()
        return self.params_in_force

    def object_info(self) -> dict[str, Any]:
        bench = self._bench()
        return {"object": bench.obj.model_dump(), "presets": list(PRESETS)}

    def set_object(self, obj: Shape) -> dict[str, Any]:
        """Place another object between the fingertips (simulation only, between runs; 409
        while the e-stop is latched: with the hand e-stopped nothing changes the world)."""
        bench = self._bench()
        if self.joints is not None and self.joints.estopped:
            raise ServiceError(409, "the e-stop is latched: release it first "
                               "(POST /api/estop/release)")  # fmt: skip
        if self.running:
            raise ServiceError(409, "the object cannot change during a run; stop the run first")
        bench.place(obj)
        log.info("simulated object: %s", obj.name or obj.kind)
        self.publish_status()
        return self.object_info()

    def press(self, press: Press) -> dict[str, Any]:
        """A person presses a pad of the simulated hand, starting now (422 if off the pad)."""
        bench = self._bench("not in simulation: press the real hand's pads with a finger")
        try:
            bench.press(press)
        except ValueError as e:
            raise ServiceError(422, "the press is off its pad", [str(e)]) from None
        log.info("pressing %s", press.describe())
        return press.model_dump()

    def release_presses(self) -> dict[str, int]:
        """Lift every press on the simulated hand's pads."""
        bench = self._bench("not in simulation: press the real hand's pads with a finger")
        return {"released": bench.release()}

    async def command(self, kind: str, args: dict[str, Any]) -> None:
        """The 3-D view's buttons and sliders; a refusal is logged and raised (the view shows
        it in its panel). The view cannot authenticate: with a token set, only the e-stop."""
        try:
            if self.cfg.service.token and kind != "estop":
                raise ServiceError(403, f"{kind!r} from the 3-D view refused: the service "
                                   "needs its token; use the dashboard or the API")  # fmt: skip
            if kind == "start":
                self.start_run()
            elif kind == "stop":
                self.stop_run(STOPPED_BY_VIEW)
            elif kind == "estop":
                await self.estop()
            elif kind == "release":
                await self.release_estop()
            elif kind == "params":
                self.patch_params(args)
            elif kind == "open":
                await self.open_hand()
            else:
                raise ServiceError(400, f"unknown command {kind!r}")
        except ServiceError as e:
            log.warning("3-D view command %s refused: %s %s", kind, e.message, e.details)
            raise

    # --- status ---------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        j, t = self.joints, self.tactile
        run = None
        if self.run is not None:
            r = self.run.runner
            run = {
                "id": self.run.run_id, "state": r.phase.value, "stroke": r.state.strokes,
                "strokes_total": r.params.cycles, "iteration": r.state.iteration,
                "status": r.result.status, "message": r.result.message,
            }  # fmt: skip
        joints_up = bool(j and j.connected and not j.silent)  # a silent line is down too
        tactile_up = bool(t and t.connected and not t.silent)
        connected = {"joints": joints_up, "tactile": tactile_up}
        return {
            "sim": self.bench is not None,
            "auth_required": bool(self.cfg.service.token),
            "estopped": bool(j and j.estopped),
            "estop": self._estop_status(j),
            "hand": {
                "connected": connected,
                "opening": self.opening,
                "angles_deg": list(j.last_actual) if j and j.last_actual else None,
            },
            "links": {
                "dsa_url": self.dsa_url,
                "sdh_url": self.sdh_url,
                "tactile": _stats(t) if t else None,
                "joints_down": _why_down(j, joints_up, "does not answer (its port is open)"),
                "tactile_down": _why_down(t, tactile_up, "sends no frames (its port is open)"),
            },
            "run": run,
            "last_run": self.last_run,
            "params": self.params_in_force.model_dump(),
            "object": self.bench.obj.model_dump() if self.bench else None,
            "telemetry": self.hub.stats(),
            "viewer": None if self.view_served is None else self.view_served(),
        }

    def _estop_status(self, j: JointLink | None) -> dict[str, Any] | None:
        """The latch as on disk, and whether the hand confirmed its power-off (every page sees
        what the e-stop's answer told only the one that asked)."""
        if self._latch is None:
            return None
        return {**self._latch, "hand_reached": bool(j is None or j.power_off_confirmed)}

    def publish_status(self) -> None:
        self.hub.publish(Status(self.status()))

    # --- internals ------------------------------------------------------------------------------

    def _require_lines(self, joints: JointLink, tactile: TactileBus | None = None) -> None:
        """503 naming the line that is down (the links reconnect by themselves meanwhile)."""
        if not joints.connected:
            raise ServiceError(503, f"the joint line ({self.sdh_url}) is down; it reconnects by "
                               "itself: try again when status shows it connected")  # fmt: skip
        if joints.silent:
            raise ServiceError(503, f"the joint line ({self.sdh_url}) does not answer (its port "
                               "is open): try again when status shows it connected")  # fmt: skip
        if tactile is not None and not tactile.connected:
            raise ServiceError(503, f"the tactile line ({self.dsa_url}) is down; it reconnects "
                               "by itself: try again when status shows it connected")  # fmt: skip
        if tactile is not None and tactile.silent:
            raise ServiceError(503, f"the tactile line ({self.dsa_url}) sends no frames (its "
                               "port is open): try again when status shows it up")  # fmt: skip

    def _refuse_if_shutting_down(self) -> None:
        if self._shutting_down:
            raise ServiceError(503, "the service is shutting down: no new motion")

    def _links(self) -> tuple[JointLink, TactileBus, RunStore]:
        if self.joints is None or self.tactile is None or self.store is None:
            raise ServiceError(503, "the hand's links are not open yet")
        return self.joints, self.tactile, self.store

    def _bench(
        self, why: str = "not in simulation: the object is whatever the real hand holds"
    ) -> Bench:
        if self.bench is None:
            raise ServiceError(404, why)
        return self.bench

    async def _execute(self, run: RecordedRun) -> None:
        try:
            summary = await run.execute()
        except asyncio.CancelledError:  # an e-stop (or shutdown) cancelled the run's task
            summary = run.summary or {"status": run.runner.result.status}
        except Exception as e:  # a bug must not take the service down; the run row says why
            log.exception("run %d crashed", run.run_id)
            summary = {"status": "faulted", "message": f"internal error: {e}"}
            result = run.runner.result  # the status shows the run as it ended, not running
            if result.status == "running":
                result.status, result.message = "faulted", summary["message"]
            with contextlib.suppress(Exception):  # in a thread: a locked database must not
                # hold up the event loop, and with it an e-stop
                await asyncio.to_thread(run.store.finish_run, run.run_id, "faulted", summary)
        self.last_run = {"id": run.run_id, "status": summary.get("status"),
                         "message": summary.get("message", "")}  # fmt: skip
        log.info("run %d ended: %s %s", run.run_id, summary.get("status"),
                 summary.get("message", ""))  # fmt: skip
        self.publish_status()

    def _on_frame(self, frame: TactileFrame) -> None:
        """Every delivered frame; forwarded at ≤ tactile_max_hz, and only if someone reads."""
        if frame.arrival - self._last_tactile < 1.0 / self.cfg.service.tactile_max_hz * 0.9:
            return
        if not self.hub.clients and not self.hub.has_listeners:
            return
        self._last_tactile = frame.arrival
        self.hub.publish(Tactile(frame.seq, frame.arrival, frame.matrices))

    async def _status_loop(self) -> None:
        period = 1.0 / self.cfg.service.status_hz
        while True:
            self.publish_status()
            await asyncio.sleep(period)

    async def _disk_latch_loop(self) -> None:
        """The e-stop another program latched in this service's database (`sdh2svc estop
        --latch` where it could not reach the API): taken as the API's e-stop, then said back to
        the database. Neither this service's own latch nor a release under way counts."""
        store, joints = self.store, self.joints
        assert store is not None and joints is not None
        while True:
            latch = await latched_elsewhere(
                store, joints, held=lambda: self._latch is not None or self._releases > 0
            )
            log.warning("the e-stop was latched in %s by another program (since %s: %s): "
                        "e-stop", store.path, latch["since"], latch["reason"])  # fmt: skip
            try:
                answer = await self.estop()
            except Exception:  # a bug must not end the watch: the next poll tries again
                log.exception("the e-stop for the latch on disk failed")
                continue
            await tell_taken(store, latch, this_program("the service"), answer["hand_reached"])

    async def _pose_loop(self) -> None:
        """Joint angles (polled between runs; during one, the runner's own reads) and sim truth."""
        period = 1.0 / self.cfg.service.pose_hz
        while True:
            await asyncio.sleep(period)
            j = self.joints
            if j is None:
                continue
            if not self.running and j.connected:
                with contextlib.suppress(Exception):
                    await j.get_actual()
            if j.last_actual is not None:
                self.hub.publish(Pose(tuple(j.last_actual)))
            if (bench := self.bench) is not None:
                self.hub.publish(Sim(bench.truth().scene(bench.outline, OUTLINE_POINTS)))


class _RunTelemetry(BaseObserver):
    """A run's samples and events to the telemetry hub (its frames go there from the bus)."""

    def __init__(self, service: HandService) -> None:
        self.service = service

    def _run_id(self) -> int | None:
        return self.service.run.run_id if self.service.run else None

    def sample(self, sample: Sample) -> None:
        self.service.hub.publish(SampleMsg(self._run_id(), sample))

    def event(self, event: RunEvent) -> None:
        self.service.hub.publish(Event(self._run_id(), event.t, event.iteration, event.kind,
                                       event.detail))  # fmt: skip
        if event.kind is EventKind.PHASE:
            self.service.publish_status()


async def _write_latch(store: RunStore, latch: Mapping[str, str]) -> dict[str, str]:
    """``latch`` (its ``since`` and ``reason``) written to disk, in a thread: the latch on disk."""
    return await asyncio.to_thread(
        store.latch_estop, latch.get("reason", ESTOP_REASON), latch.get("since")
    )


def _why_down(link: JointLink | TactileBus | None, up: bool, silent: str) -> str | None:
    """Why a line is down, for the status (None while it is up): silent, or the last loss or
    failed reconnect (the port gone, refused, another controller answering, …)."""
    if up:
        return None
    if link is None:
        return "not open yet"
    if link.connected and link.silent:
        return silent
    return link.failure or "connecting"


def _stats(t: TactileBus) -> dict[str, Any]:
    st = asdict(t.stats)
    st["mode"] = str(st["mode"])
    return st
