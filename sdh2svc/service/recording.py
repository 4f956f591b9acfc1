"""Recording a run on an open hand: the runner, its recorder and its summary, in one place.

Used by ``sdh2svc run`` (:mod:`sdh2svc.service.headless`) and by the service
(:mod:`sdh2svc.service.hand_service`): both create the run's database row, record every sample,
event and frame, and finish the row with the summary. On a simulated hand (a bench), the summary
also holds the simulation's truth as the run let go.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Callable
from typing import Any, Protocol

from sdh2svc.bus.joint import JointLink
from sdh2svc.bus.tactile import TactileBus, TactileFrame
from sdh2svc.config import Settings
from sdh2svc.connect import Bench
from sdh2svc.control.observer import Event
from sdh2svc.control.params import RollingParams
from sdh2svc.control.runner import Runner
from sdh2svc.control.sample import Sample
from sdh2svc.service.store import Recorder, RunStore

EventSink = Callable[[float, int | None, str, dict[str, Any]], None]


class RunObserver(Protocol):
    """What watches a run from beside it (e.g. a campaign sampling the simulation's truth)."""

    def event(self, t: float, iteration: int | None, kind: str, detail: dict[str, Any]) -> None:
        """Every event of the run (phase, grasped, reversal, fault, end, …)."""

    def sample(self, sample: Sample) -> None:
        """Every iteration's record."""


class RecordedRun:
    """A :class:`Runner` whose samples, events and frames go to the database (and listeners)."""

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
        on_sample: Callable[[Sample], None] | None = None,
        on_event: EventSink | None = None,
        on_frame: Callable[[float, TactileFrame], None] | None = None,
    ) -> None:
        self.cfg, self.tactile, self.store, self.bench = cfg, tactile, store, bench
        params = params or cfg.rolling
        full_meta = {
            "params": params.model_dump(),
            "object": bench.obj.model_dump() if bench else None,
            **(meta or {}),
        }
        self.run_id = store.create_run(full_meta)
        self._rec = Recorder(store.path, self.run_id)
        self._truth: dict[str, Any] = {}
        self._on_sample, self._on_event, self._on_frame = on_sample, on_event, on_frame
        self.runner = Runner(
            cfg.control(), joints, tactile, params=params,
            observer=self,
        )  # fmt: skip
        self.summary: dict[str, Any] | None = None

    # --- control.observer.RunObserver: the runner reports here ---

    def sample(self, s: Sample) -> None:
        self._rec.sample(s)
        if self._on_sample:
            self._on_sample(s)

    def event(self, e: Event) -> None:
        t, iteration, kind, detail = e.t, e.iteration, e.kind, e.detail
        self._rec.event(t, iteration, kind, detail)
        # the simulation's truth as the run ends, before the fingers let go
        if self.bench is not None and kind == "phase" and detail["phase"] == "releasing":
            self._truth.update(self.bench.truth().summary())
        if self._on_event:
            self._on_event(t, iteration, kind, detail)

    def frame(self, t: float, frame: TactileFrame) -> None:
        self._rec.frame(t, None, frame.timestamp_ms, frame.texels)
        if self._on_frame:
            self._on_frame(t, frame)

    async def execute(self) -> dict[str, Any]:
        """Run to the end (completed, stopped, faulted, e-stopped) and return the summary."""
        try:
            result = await self.runner.run()
        except asyncio.CancelledError:
            result = self.runner.result
            if result.status == "running":
                result.status, result.message = "stopped", "cancelled"
            self.summary = self._finish(result.summary())
            raise
        finally:
            with contextlib.suppress(Exception):
                self._rec.close()
        self.summary = self._finish(result.summary())
        return self.summary

    def _finish(self, summary: dict[str, Any]) -> dict[str, Any]:
        st = self.tactile.stats
        summary["frames"] = {"received": st.frames, "crc_errors": st.crc_errors,
                             "resyncs": st.resyncs, "frames_per_s": st.frames_per_s}  # fmt: skip
        summary["run_id"] = self.run_id
        if self.bench is not None:
            summary["truth"] = self._truth or self.bench.truth().summary()
            if summary["truth"]["dropped"] and summary["status"] == "completed":
                summary["status"] = "dropped"
        self.store.finish_run(self.run_id, summary["status"], summary)
        return summary
