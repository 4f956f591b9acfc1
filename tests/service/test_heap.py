"""A run starts with its process's heap settled (``sdh2svc.heap``): a full collection of the
cyclic garbage collector in the middle of a run stopped the event loop that drives the hand for
20–70 ms — a tactile frame missed, its command late."""

from __future__ import annotations

import gc
import weakref
from collections.abc import Iterator
from pathlib import Path

import pytest

from sdh2svc.config import load_config
from sdh2svc.connect import Bench, Simulated
from sdh2svc.control.observer import BaseObserver
from sdh2svc.control.sample import Sample
from sdh2svc.heap import settle
from sdh2svc.service import headless
from sdh2svc.sim.clock import run_fast


@pytest.fixture(autouse=True)
def _thawed() -> Iterator[None]:
    """Whatever a test froze is looked at again by the collections of the tests after it."""
    yield
    gc.unfreeze()


class _Cycle:
    """An object only the cyclic collector frees: it refers to itself."""

    def __init__(self) -> None:
        self.me = self


def test_settle_frees_what_the_settle_before_froze_and_has_died_since() -> None:
    """A run's objects are alive at the next run's settle only if something still holds them:
    what died meanwhile is collected then (frozen, no collection looks at it)."""
    obj = _Cycle()
    dead = weakref.ref(obj)
    settle()  # the run before
    del obj
    gc.collect()
    assert dead() is not None  # frozen: out of every collection
    settle()  # the next run
    assert dead() is None


class _Watch(BaseObserver):
    """The collector's view of the heap at a run's first sample: how many objects are frozen,
    and how many a full collection would look at."""

    def __init__(self) -> None:
        self.seen: tuple[int, int] | None = None

    def sample(self, sample: Sample) -> None:
        if self.seen is None:
            self.seen = (gc.get_freeze_count(), len(gc.get_objects()))


def test_a_run_rolls_with_its_heap_frozen(tmp_path: Path) -> None:
    """Rolling, a full collection looks at a small part of the heap: what the run has allocated
    (the modules, the configuration, the links and the recorder were there before it moved)."""
    gc.unfreeze()
    db = f"storage.db_path='{tmp_path / 'runs.sqlite'}'"
    cfg = load_config(overrides=[db, "rolling.cycles=1", "sim.object='rubber'"], use_env=False)
    watch = _Watch()

    def observer(_bench: Bench | None) -> _Watch:
        return watch

    summary = run_fast(headless.run_once(cfg, Simulated(fast=True), observer=observer))
    assert summary["status"] == "completed"
    assert watch.seen is not None
    frozen, looked_at = watch.seen
    assert frozen > 10 * looked_at, watch.seen
