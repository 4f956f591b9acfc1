"""The runner's recognition: every rolling iteration's estimate in its Sample, the run's in the
summary and the end event; an estimator that fails never stops the rolling (fast mode, the
simulated hand, a test double for the estimator)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from sdh2svc.connect import Simulated, connect_hand
from sdh2svc.control.observer import BaseObserver, Event, EventKind
from sdh2svc.control.recognition import ContactKind, ObjectClass, Recognition, Recognizer
from sdh2svc.control.runner import RecognizerFactory, Runner, RunResult
from sdh2svc.control.sample import Sample
from sdh2svc.model.observe import Observation
from sdh2svc.sim.clock import run_fast
from tests.control.test_runner import cfg_with

ITERATIONS = 12  # rolling iterations before the test stops the run


class Fixed(Recognizer):
    """A double: a box turning 0.5° per iteration, from the pads' counts it is given."""

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self.n = 0
        self.shapes: set[tuple[int, ...]] = set()

    def update(self, obs: Observation, counts1: np.ndarray, counts2: np.ndarray) -> Recognition:
        self.n += 1
        self.shapes |= {counts1.shape, counts2.shape}
        return Recognition(
            kind1=ContactKind.FLAT, kind2=ContactKind.CURVED, radius1=None, radius2=21.5,
            object_class=ObjectClass.BOX, confidence=0.75, size_a=40.0, size_b=25.0,
            rotation=0.5 * self.n,
        )  # fmt: skip

    def summary(self) -> dict[str, Any]:
        return {"object_class": "box", "confidence": 0.75, "rotation_deg": 0.5 * self.n}


class Failing(Fixed):
    """Fails at its third iteration (and would at every one after)."""

    def update(self, obs: Observation, counts1: np.ndarray, counts2: np.ndarray) -> Recognition:
        if self.n >= 2:
            raise ZeroDivisionError("a broken estimator")
        return super().update(obs, counts1, counts2)


class Stopper(BaseObserver):
    """Keeps the samples and the end event; stops the run after ITERATIONS samples."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []
        self.end: dict[str, Any] | None = None
        self.runner: Runner | None = None
        self.events: list[Event] = []

    def sample(self, sample: Sample) -> None:
        self.samples.append(sample)
        if len(self.samples) == ITERATIONS and self.runner is not None:
            self.runner.request_stop()

    def event(self, event: Event) -> None:
        self.events.append(event)
        if event.kind is EventKind.END:
            self.end = event.detail


def roll(tmp: Path, recognizer: RecognizerFactory) -> tuple[RunResult, Stopper, Recognizer]:
    cfg = cfg_with(tmp)
    seen = Stopper()

    async def main() -> RunResult:
        async with connect_hand(cfg, Simulated(fast=True)) as hand:
            runner = Runner(cfg.control(), hand.joints, hand.tactile, observer=seen,
                            recognizer=recognizer)  # fmt: skip
            seen.runner = runner
            result = await runner.run()
            made.append(runner._recognizer)
            return result

    made: list[Any] = []
    return run_fast(main()), seen, made[0]


def test_each_sample_carries_the_estimate_and_the_summary_the_runs(tmp_path: Path) -> None:
    result, seen, rec = roll(tmp_path, Fixed)
    assert result.status == "stopped" and len(seen.samples) >= ITERATIONS
    first, last = seen.samples[0], seen.samples[-1]
    assert (first.contact1_kind, first.contact2_kind) == ("flat", "curved")
    assert (first.radius1, first.radius2) == (None, 21.5)
    assert (first.object_class, first.class_confidence) == ("box", 0.75)
    assert (first.size_a, first.size_b) == (40.0, 25.0)
    assert [s.rotation_est for s in seen.samples] == [
        0.5 * (i + 1) for i in range(len(seen.samples))
    ]
    assert last.recognition() == Recognition(
        ContactKind.FLAT, ContactKind.CURVED, None, 21.5, ObjectClass.BOX, 0.75, 40.0, 25.0,
        last.rotation_est or 0.0,
    )  # fmt: skip
    assert isinstance(rec, Fixed) and len(rec.shapes) == 1  # the two distal pads' matrices
    want = {"object_class": "box", "confidence": 0.75, "rotation_deg": 0.5 * len(seen.samples)}
    assert result.summary()["recognition"] == want
    assert seen.end is not None and seen.end["recognition"] == want


def test_a_failing_estimator_is_logged_once_and_the_rolling_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.ERROR, logger="sdh2svc.control.runner"):
        result, seen, _ = roll(tmp_path, Failing)
    assert result.status == "stopped" and len(seen.samples) >= ITERATIONS  # not faulted
    assert [s.rotation_est for s in seen.samples[:3]] == [0.5, 1.0, None]
    assert all(s.object_class is None and s.recognition() is None for s in seen.samples[2:])
    assert [r.message for r in caplog.records].count(
        "recognition failed: the run goes on without an estimate"
    ) == 1
    # the run says so (an event at the failing iteration), and its summary keeps what the
    # estimator had made before, with where and why it failed
    failed = [e for e in seen.events if e.kind is EventKind.RECOGNITION_FAILED]
    why = "ZeroDivisionError: a broken estimator"
    assert [(e.iteration, e.detail) for e in failed] == [(3, {"message": why})]
    want = {"object_class": "box", "confidence": 0.75, "rotation_deg": 1.0,
            "failed": {"iteration": 3, "message": why}}  # fmt: skip
    assert result.summary()["recognition"] == want
    assert seen.end is not None and seen.end["recognition"] == want
