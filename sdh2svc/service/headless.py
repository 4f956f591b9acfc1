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
from sdh2svc.service.store import Recorder, RunStore
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
) -> dict[str, Any]:
    """Run once and return the summary (the ``--json`` object of ``sdh2svc run``)."""
    hand: SimulatedHand | None = None
    tmp = tempfile.TemporaryDirectory(prefix="sdh2svc-") if fast else None
    joints: JointLink | None = None
    tactile: TactileBus | None = None
    store = RunStore(cfg.storage.db_path)
    try:
        if sim:
            unix_dir = Path(tmp.name) if tmp else None
            hand = await start_simulated_hand(
                cfg, obj=obj, pty=False, tcp=not fast, unix_dir=unix_dir, dsa_port=0, sdh_port=0
            )
            dsa_url, sdh_url = hand.urls("dsa")[0], hand.urls("sdh")[0]
        dsa_url = dsa_url or cfg.links.dsa_url
        sdh_url = sdh_url or cfg.links.sdh_url
        lim = cfg.limits
        limits = list(zip(lim.min_deg, lim.max_deg, strict=True))
        joints = await JointLink.open(sdh_url, binary=cfg.links.binary, limits=limits)
        tactile = await TactileBus.open(dsa_url)
        meta = {
            "sim": sim, "fast": fast, "dsa_url": dsa_url, "sdh_url": sdh_url,
            "params": cfg.rolling.model_dump(),
            "object": hand.world.obj.model_dump() if hand else None,
        }  # fmt: skip
        run_id = store.create_run(meta)
        rec = Recorder(store.path, run_id)
        truth: dict[str, Any] = {}

        def on_event(t: float, iteration: int | None, kind: str, detail: dict[str, Any]) -> None:
            rec.event(t, iteration, kind, detail)
            # the simulation's truth as the run ends, before the fingers let go
            if hand is not None and kind == "phase" and detail["phase"] == "releasing":
                truth.update(_truth(hand))

        runner = Runner(
            cfg, joints, tactile, on_sample=rec.sample, on_event=on_event,
            on_frame=lambda t, f: rec.frame(t, None, f.timestamp_ms, f.texels),
        )  # fmt: skip
        ticker = asyncio.create_task(_tick(runner, progress)) if progress else None
        try:
            result = await runner.run()
        finally:
            if ticker:
                ticker.cancel()
            rec.close()
        summary = result.summary()
        st = tactile.stats
        summary["frames"] = {"received": st.frames, "crc_errors": st.crc_errors,
                             "resyncs": st.resyncs, "frames_per_s": st.frames_per_s}  # fmt: skip
        summary["run_id"] = run_id
        if hand is not None:
            summary["truth"] = truth or _truth(hand)
            if summary["truth"]["dropped"] and summary["status"] == "completed":
                summary["status"] = "dropped"
        store.finish_run(run_id, summary["status"], summary)
        return summary
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


def _truth(hand: SimulatedHand) -> dict[str, Any]:
    t = hand.world.truth()
    return {
        "object": t.object, "size_mm": t.size_mm, "dropped": t.dropped, "slips": t.slips,
        "rotation_range_deg": t.rotation_range_deg,
    }  # fmt: skip


async def _tick(runner: Runner, progress: Callable[[Runner], None]) -> None:
    while True:
        progress(runner)
        await asyncio.sleep(0.5)
