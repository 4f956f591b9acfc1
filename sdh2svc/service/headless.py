"""One run without a server: what ``sdh2svc run`` does, on a real hand or the simulated one.

With ``sim=True`` the simulated hand is started in this process and the drivers reach it through
the same URLs a real hand would have (TCP; Unix sockets in fast mode) — nothing above the
emulators knows. Everything is recorded in the run database.
"""

from __future__ import annotations

import asyncio
import contextlib
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus
from sdh2svc.config import Settings
from sdh2svc.control.runner import Runner
from sdh2svc.service.runs import RecordedRun, RunObserver, open_links
from sdh2svc.service.store import EstopLatched, RunStore
from sdh2svc.sim.hand import ObjectSpecT
from sdh2svc.sim.serve import SimulatedHand, start_simulated_hand


async def run_once(
    cfg: Settings,
    *,
    sim: bool,
    obj: ObjectSpecT | None = None,
    dsa_url: str | None = None,
    sdh_url: str | None = None,
    fast: bool = False,
    progress: Callable[[Runner], None] | None = None,
    observer: Callable[[SimulatedHand | None], RunObserver] | None = None,
) -> dict[str, Any]:
    """Run once and return the summary (the ``--json`` object of ``sdh2svc run``).

    ``observer``, if given, is called once the links are up with the simulated hand (None on a
    real one) and returns what watches the run's events and samples, e.g. to sample the
    simulation's truth along the run (:mod:`sdh2svc.campaign.run`).
    """
    hand: SimulatedHand | None = None
    tmp = tempfile.TemporaryDirectory(prefix="sdh2svc-") if fast else None
    joints: JointLink | None = None
    tactile: TactileBus | None = None
    store = RunStore(cfg.storage.db_path)
    try:
        if not sim and (latch := store.estop_latch()) is not None:
            raise EstopLatched(latch)  # the latch belongs to the real hand, not a simulated one
        if sim:
            unix_dir = Path(tmp.name) if tmp else None
            # one run: no lab assistant (nobody to put the object back for)
            hand = await start_simulated_hand(cfg, obj=obj, pty=False, tcp=not fast,
                                              unix_dir=unix_dir, dsa_port=0, sdh_port=0,
                                              replace_after_s=0.0)  # fmt: skip
            dsa_url, sdh_url = hand.urls("dsa")[0], hand.urls("sdh")[0]
        dsa_url = dsa_url or cfg.links.dsa_url
        sdh_url = sdh_url or cfg.links.sdh_url
        joints, tactile = await open_links(cfg, dsa_url, sdh_url)
        meta = {"sim": sim, "fast": fast, "dsa_url": dsa_url, "sdh_url": sdh_url}
        obs = observer(hand) if observer else None
        run = RecordedRun(cfg, joints, tactile, store, meta=meta, hand=hand,
                          on_event=obs.event if obs else None,
                          on_sample=obs.sample if obs else None)  # fmt: skip
        ticker = asyncio.create_task(_tick(run.runner, progress)) if progress else None
        try:
            return await run.execute()
        finally:
            if ticker:
                ticker.cancel()
    finally:
        for link in (tactile, joints):
            if link is not None:
                with contextlib.suppress(Exception):
                    await link.close()
        if hand is not None:
            await hand.stop()
        store.close()
        if tmp is not None:
            tmp.cleanup()


async def _tick(runner: Runner, progress: Callable[[Runner], None]) -> None:
    while True:
        progress(runner)
        await asyncio.sleep(0.5)
