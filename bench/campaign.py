"""Campaign throughput: the smoke suite (3 strokes per case, fast mode, the full byte path) on 1
and on 2 worker processes.

Printed: runs per hour per core (from the CPU time the runs took, and from the wall time of the
1-worker campaign), the simulated-time ratio of a whole run (simulated seconds, start-up to
release, per wall second and per CPU second, summed over the cases), and the parallel
efficiency from 1 to 2 workers (the 2-worker throughput / twice the 1-worker one; target
≥ 0.85), and the event loop's work per simulated second in the first case (iterations, and the
callbacks it ran by source), and where the CPU of the first two cases goes by layer (sampled:
the innermost frame of sdh2svc's own code at each tick of the process's CPU clock).
Every case's CPU time is taken in the process that ran it.
Wall-clock figures count whatever else the machine runs meanwhile (its load average is printed):
run it when nothing else does; the CPU-time figures are far less disturbed.
"""

from __future__ import annotations

import asyncio
import os
import selectors
import signal
import tempfile
import time
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from types import FrameType
from typing import Any

from sdh2svc.campaign import run as camp
from sdh2svc.campaign.case import load_suite
from sdh2svc.sim import clock


def timed_case(case_json: str, *args: Any) -> dict[str, Any]:
    """:func:`~sdh2svc.campaign.run.run_case`, and the CPU seconds it took in its process
    (``cpu_s``, kept in ``cases.jsonl``)."""
    c0 = time.process_time()
    row = camp.run_case(case_json, *args)
    row["cpu_s"] = time.process_time() - c0
    return row


def _campaign(workers: int) -> tuple[float, list[dict[str, Any]]]:
    suite = load_suite("smoke")
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out"
        t0 = time.perf_counter()
        camp.run_campaign(suite, out, workers=workers, progress=False, case_fn=timed_case)
        wall = time.perf_counter() - t0
        return wall, camp.read_rows(out)


def _load() -> str:
    return "/".join(f"{x:.1f}" for x in os.getloadavg())


def _sums(rows: Sequence[dict[str, Any]]) -> tuple[float, float, float]:
    sim = sum(r.get("sim_s") or 0.0 for r in rows)
    cpu = sum(r.get("cpu_s") or 0.0 for r in rows)
    wall = sum(r.get("wall_s") or 0.0 for r in rows)
    return sim, cpu, wall


def _makespan(rows: Sequence[dict[str, Any]], workers: int) -> float:
    """How long ``workers`` processes that each had a core to themselves would have taken: the
    cases in suite order, each to the first free worker, each as long as the CPU it took."""
    free = [0.0] * workers
    for r in rows:
        i = free.index(min(free))
        free[i] += r.get("cpu_s") or 0.0
    return max(free)


def _source(handle: asyncio.Handle) -> str:
    """What a ready callback is: the task it steps (its coroutine's name) or the function."""
    cb: Any = handle._callback  # type: ignore[attr-defined]
    owner = getattr(cb, "__self__", None)
    if isinstance(owner, asyncio.Task):
        return "task " + getattr(owner.get_coro(), "__qualname__", "?")
    return getattr(cb, "__qualname__", repr(cb))


def loop_events(case_index: int = 0) -> tuple[float, int, Counter[str]]:
    """One smoke case on a virtual-clock loop that counts its iterations and the callbacks
    it runs by source: (simulated s, iterations, callbacks by source)."""
    count: Counter[str] = Counter()
    iterations = 0
    loop_cls = clock.VirtualTimeLoop
    stock, stock_io = loop_cls._run_once, loop_cls._process_events

    def counted(self: clock.VirtualTimeLoop) -> None:
        nonlocal iterations
        iterations += 1
        count.update(_source(h) for h in self._ready)  # queued before this iteration
        timers = [h for h in self._scheduled if not h._cancelled]
        stock(self)
        count.update("timer " + _source(h) for h in timers if not h._scheduled)  # those it ran

    def io(self: clock.VirtualTimeLoop, events: list[tuple[selectors.SelectorKey, int]]) -> None:
        count["socket readable"] += len(events)
        stock_io(self, events)

    loop_cls._run_once, loop_cls._process_events = counted, io  # type: ignore[method-assign, assignment]
    try:
        case = load_suite("smoke").cases[case_index]
        with tempfile.TemporaryDirectory() as tmp:
            row = camp.run_case(case.model_dump_json(), (), None, tmp)
    finally:
        loop_cls._run_once, loop_cls._process_events = stock, stock_io  # type: ignore[method-assign]
    return row.get("sim_s") or 0.0, iterations, count


# sdh2svc's files by layer, for cpu_by_layer (the first matching prefix wins)
LAYERS = (
    ("physics", ("sim/physics.py", "sim/objects.py")),
    ("sensor model", ("sim/sensor.py", "sim/press.py")),
    ("emulators", ("sim/sdh2.py", "sim/dsacon.py", "sim/hand.py", "sim/lab.py", "sim/world.py")),
    ("endpoints (line timing)", ("sim/endpoint.py", "sim/faults.py", "sim/cable.py")),
    ("event loop", ("sim/clock.py",)),
    ("drivers", ("bus/",)),
    ("codecs", ("protocol/",)),
    ("control and model", ("control/", "model/")),
)


def _layer(frame: FrameType | None) -> str:
    """The layer of the innermost frame in sdh2svc's code (asyncio's own: the event loop)."""
    while frame is not None:
        name = frame.f_code.co_filename
        if (k := name.rfind("/sdh2svc/")) >= 0:
            rel = name[k + len("/sdh2svc/") :]
            for layer, prefixes in LAYERS:
                if rel.startswith(prefixes):
                    return layer
            return "recorder, campaign, start-up"
        frame = frame.f_back
    return "event loop"


def cpu_by_layer(cases: int = 2, tick_s: float = 0.0005) -> Counter[str]:
    """Samples of the CPU clock by layer over the first ``cases`` smoke cases (run in this
    process); empty where the CPU-time timer is missing (not Linux or macOS)."""
    count: Counter[str] = Counter()
    if not hasattr(signal, "setitimer"):
        return count

    def tick(_sig: int, frame: FrameType | None) -> None:
        count[_layer(frame)] += 1

    stock = signal.signal(signal.SIGPROF, tick)
    signal.setitimer(signal.ITIMER_PROF, tick_s, tick_s)
    try:
        for case in load_suite("smoke").cases[:cases]:
            with tempfile.TemporaryDirectory() as tmp:
                camp.run_case(case.model_dump_json(), (), None, tmp)
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0.0, 0.0)
        signal.signal(signal.SIGPROF, stock)
    return count


def run() -> dict[str, float]:
    print(f"campaign (smoke suite; load average before: {_load()})")
    t1, rows1 = _campaign(1)
    load1 = _load()
    t2, rows2 = _campaign(2)
    n = len(rows1)
    sim, cpu, case_wall = _sums(rows1)
    sim2, cpu2, _ = _sums(rows2)
    eff = t1 / t2 / 2
    order = {c.id: k for k, c in enumerate(load_suite("smoke").cases)}
    rows2 = sorted(rows2, key=lambda r: order.get(r.get("id", ""), 0))
    eff_cpu = cpu / (2 * _makespan(rows2, 2))
    out = {
        "runs_per_hour_per_core_cpu": 3600 * n / cpu,
        "runs_per_hour_per_core_wall": 3600 * n / t1,
        "sim_per_wall": sim / case_wall,
        "sim_per_cpu": sim / cpu,
        "parallel_efficiency": eff,
        "parallel_efficiency_cpu": eff_cpu,
    }
    print(f"  {n} cases, {sim:.0f} simulated s in all (3 strokes each unless a case failed "
          "sooner)")  # fmt: skip
    per_cpu, per_wall = out["runs_per_hour_per_core_cpu"], out["runs_per_hour_per_core_wall"]
    print(f"  1 worker : {t1:.1f} s wall, {cpu:.1f} s CPU in the runs → {per_cpu:.0f} runs per "
          f"hour per core (CPU), {per_wall:.0f} (wall); load average after: {load1}")  # fmt: skip
    print(f"  a whole run (start-up to release): {out['sim_per_wall']:.1f}× real time per wall "
          f"second, {out['sim_per_cpu']:.1f}× per CPU second (target 30×)")  # fmt: skip
    print(f"  2 workers: {t2:.1f} s wall, {cpu2:.1f} s CPU in the runs → "
          f"{3600 * n / t2 / 2:.0f} runs per hour per core (wall); load average after: "
          f"{_load()}")  # fmt: skip
    print(f"  parallel efficiency 1 → 2 workers: {eff:.2f} (target ≥ 0.85; CPU per run "
          f"{cpu2 / cpu:.2f}× the 1-worker one)")  # fmt: skip
    print(f"  the same from CPU times, as if each worker had a core of its own (the cases in "
          f"suite order to the first free worker): {eff_cpu:.2f}")  # fmt: skip
    per_case = {r.get("id"): r.get("sim_s") for r in rows1}
    if any(per_case.get(r.get("id")) != r.get("sim_s") for r in rows2):  # (sums: another order)
        print(f"  (!) the 2-worker campaign simulated {sim2:.1f} s, not {sim:.1f} s")
    sim_e, iterations, count = loop_events()
    out["loop_iterations_per_sim_s"] = iterations / sim_e
    top = ", ".join(f"{name} {n / sim_e:.0f}" for name, n in count.most_common(10))
    print(f"  event loop, first case: {iterations / sim_e:.0f} iterations per simulated second; "
          f"callbacks per simulated second by source: {top}")  # fmt: skip
    layers = cpu_by_layer()
    total = sum(layers.values())
    if total:
        shares = ", ".join(f"{name} {100 * n / total:.0f} %" for name, n in layers.most_common())
        print(f"  CPU by layer, first two cases ({total} samples): {shares}")
    return out
