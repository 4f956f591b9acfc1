"""One run without a server: what ``sdh2svc run`` does, on a real hand or a simulated one.

The hand is opened through the seam (:func:`sdh2svc.connect.connect_hand`); everything is
recorded in the run database.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from typing import Any

from sdh2svc.config import Settings
from sdh2svc.connect import Bench, Where, connect_hand
from sdh2svc.control.observer import RunObserver
from sdh2svc.control.runner import Runner
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
            try:
                return await run.execute()
            finally:
                if ticker:
                    ticker.cancel()
    finally:
        store.close()


async def _tick(runner: Runner, progress: Callable[[Runner], None]) -> None:
    while True:
        progress(runner)
        await asyncio.sleep(0.5)
