"""One run without a server: what ``sdh2svc run`` does, on a real hand or a simulated one.

The hand is opened through the seam (:func:`sdh2svc.connect.connect_hand`); everything is
recorded in the run database.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

from sdh2svc.bus.joint import JointLink, JointLinkError
from sdh2svc.config import Settings
from sdh2svc.connect import Bench, Where, connect_hand
from sdh2svc.control.observer import RunObserver
from sdh2svc.control.runner import Runner
from sdh2svc.service.hub import cancel
from sdh2svc.service.latch import latched_elsewhere, tell_taken, this_program
from sdh2svc.service.recording import RecordedRun
from sdh2svc.service.store import EstopLatched, RunStore

log = logging.getLogger(__name__)


async def run_once(
    cfg: Settings,
    where: Where,
    *,
    progress: Callable[[Runner], None] | None = None,
    observer: Callable[[Bench | None], RunObserver] | None = None,
    started: Callable[[Runner], None] | None = None,
) -> dict[str, Any]:
    """Run once and return the summary (the ``--json`` object of ``sdh2svc run``).

    ``observer``, if given, is called once the links are up with the bench (None on a real
    hand) and returns what watches the run's events and samples, e.g. to sample the
    simulation's truth along the run (:mod:`sdh2svc.campaign.run`). ``started``, if given, is
    handed the run's runner before it starts (its ``request_stop`` stops the run as the
    service's stop does: the object released, the run recorded ``stopped``).
    """
    store = RunStore(cfg.storage.db_path, busy_timeout_s=cfg.storage.busy_timeout_s)
    try:
        if interrupted := store.mark_interrupted():  # as the service does when it starts
            log.warning("runs %s were still 'running' in %s, their process gone: marked "
                        "interrupted", interrupted, cfg.storage.db_path)  # fmt: skip
        async with connect_hand(cfg, where) as hand:
            # the latch belongs to the real hand, not a simulated one; checked before it moves
            if hand.real and (latch := store.estop_latch()) is not None:
                raise EstopLatched(latch)
            meta = hand.describe()
            obs = observer(hand.bench) if observer else None
            run = RecordedRun(cfg, hand.joints, hand.tactile, store, meta=meta, bench=hand.bench,
                              observer=obs)  # fmt: skip
            if started is not None:
                started(run.runner)
            ticker = asyncio.create_task(_tick(run.runner, progress)) if progress else None
            # a real hand stops for a latch another program writes meanwhile (estop --latch)
            obey = _ObeyLatch(store, run.runner, hand.joints) if hand.real else None
            try:
                return await (run.execute() if obey is None else _own_task(run))
            finally:
                if ticker:
                    ticker.cancel()
                if obey is not None:
                    await obey.end()
    finally:
        store.close()


async def _own_task(run: RecordedRun) -> dict[str, Any]:
    """The run in a task of its own, which an e-stop cancels (as the service's): recorded
    e-stopped, its summary is the answer; this task's own cancellation (a second Ctrl-C)
    cancels the run's task and comes once that has ended (its record written)."""
    task = asyncio.create_task(run.execute(), name="run")
    try:
        return await task
    except asyncio.CancelledError:
        me = asyncio.current_task()
        if (me is not None and me.cancelling()) or run.summary is None:
            raise
        return run.summary


class _ObeyLatch:
    """The e-stop latched in the run database by another program while this run drives a real
    hand: the run ends e-stopped, and the database hears that the hand stopped."""

    def __init__(self, store: RunStore, runner: Runner, joints: JointLink) -> None:
        self.store, self.runner, self.joints = store, runner, joints
        self.stopping = False
        self.task = asyncio.create_task(self._obey(), name="disk-latch")

    async def _obey(self) -> None:
        latch = await latched_elsewhere(self.store, self.joints)
        self.stopping = True
        log.warning("the e-stop was latched in %s by another program (since %s: %s): e-stop",
                    self.store.path, latch["since"], latch["reason"])  # fmt: skip
        try:
            await self.runner.emergency_stop()
        except JointLinkError as e:  # latched all the same: its power-off is sent once it answers
            log.error("e-stop latched, but the hand was not reached: %s", e)
        program = this_program("sdh2svc run")
        await tell_taken(self.store, latch, program, self.joints.power_off_confirmed)

    async def end(self) -> None:
        """Done watching once the run has ended: a stop under way is finished and told first."""
        if not self.stopping:
            await cancel(self.task)
            return
        with contextlib.suppress(Exception):
            await self.task


async def _tick(runner: Runner, progress: Callable[[Runner], None]) -> None:
    while True:
        progress(runner)
        await asyncio.sleep(0.5)
