"""How far the two contacts move together across AB, beyond what the pads' own motion explains:
the signal a grip that follows an object's weight would need (experiments/campaigns/grasp-force).

    python -m experiments.slide_trace --seed 3501 --n 48 [--set KEY=VALUE …]
    python -m experiments.slide_trace --suite bench-v1 --ids circle-081,ellipse-116 --set …

Each generated case runs as in a campaign (fast mode, the full byte path). At every rolling
iteration the pad points under the previous contacts are moved with the new pose (as
:func:`~sdh2svc.model.observe.rolling_turn` does); the contacts' mean displacement beyond them,
across AB, is the common part: a rigid object rolling without slip between antiparallel pads
adds none of it, a slide along both pads adds all of it. Printed per case: its verdict, the
largest leaky sum (× DECAY an iteration) of that common part, the same (and the largest single
iteration's) before the simulation's first sliding contact, and the iterations where the first
and the last slide began (truth).
"""

from __future__ import annotations

import argparse
import math
import tempfile
from pathlib import Path
from typing import Any

import sdh2svc.control.runner as runner_mod
from sdh2svc.campaign.case import Case, load_suite
from sdh2svc.campaign.generate import generate_cases
from sdh2svc.campaign.run import TruthProbe, case_settings, measure
from sdh2svc.model.kinematics import Finger, contact_point
from sdh2svc.model.observe import ModelContext, Observation

DECAY = 0.8


def common_slide(prev: Observation | None, obs: Observation, ctx: ModelContext) -> float | None:
    """The contacts' mean displacement across AB beyond the pad points under them (mm)."""
    if prev is None or prev.points is None or obs.points is None:
        return None
    vj1, vj2 = prev.contact1.virtual_joint, prev.contact2.virtual_joint
    if vj1 is None or vj2 is None:
        return None
    p = obs.pose
    A = contact_point(Finger.ONE, p.phi2, p.phi3, vj1[0], vj1[1], ctx.geom)
    B = contact_point(Finger.TWO, p.phi4, p.phi5, vj2[0], vj2[1], ctx.geom)
    ry = ((obs.points.A.y - A.y) + (obs.points.B.y - B.y)) / 2
    rz = ((obs.points.A.z - A.z) + (obs.points.B.z - B.z)) / 2
    dy, dz = obs.points.B.y - obs.points.A.y, obs.points.B.z - obs.points.A.z
    n = math.hypot(dy, dz)
    return (-dz * ry + dy * rz) / n if n > 1e-9 else None


_Row = tuple[int, float, bool]


def trace(case: Case, overrides: list[str]) -> tuple[dict[str, Any], list[_Row]]:
    """One campaign run of ``case``: its judged row, and per iteration (its number, the common
    slide, whether any contact of the simulation slides)."""
    from sdh2svc.connect import Simulated
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    real = getattr(runner_mod, "step")  # noqa: B009 (patched below)
    probe = TruthProbe()
    rows: list[_Row] = []

    def step(state, pose, m1, m2, params, ctx):  # type: ignore[no-untyped-def]
        r = real(state, pose, m1, m2, params, ctx)
        c = common_slide(state.prev, r.obs, ctx)
        bench = probe.bench
        sliding = bench is not None and any(x.slipping for x in bench.contacts_now())
        if c is not None:
            rows.append((r.state.iteration, c, sliding))
        return r

    with tempfile.TemporaryDirectory() as tmp:
        cfg = case_settings(case, overrides, None, Path(tmp) / "r.sqlite")
        setattr(runner_mod, "step", step)  # noqa: B010
        try:
            summary = run_fast(run_once(cfg, Simulated(obj=case.object, fast=True),
                                        observer=probe))  # fmt: skip
        finally:
            setattr(runner_mod, "step", real)  # noqa: B010
        return measure(summary, probe, cfg, case), rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--seed", type=int, default=3501)
    ap.add_argument("--n", type=int, default=48)
    ap.add_argument("--suite", help="a named suite's cases instead of generated ones")
    ap.add_argument("--ids", default="", help="with --suite: these cases only (comma-separated)")
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    a = ap.parse_args()
    if a.suite:
        ids = set(filter(None, a.ids.split(",")))
        cases = [c for c in load_suite(a.suite).cases if not ids or c.id in ids]
    else:
        cases = generate_cases(a.seed, a.n, prefix=f"s{a.seed}-")
    for case in cases:
        row, rows = trace(case, a.overrides)
        acc = peak = before = step = 0.0  # step: the largest |common slide| before a slide
        first = last = None  # the first sliding iteration; where the last slide began
        for k, (it, c, sliding) in enumerate(rows):
            acc = DECAY * acc + c
            peak = max(peak, abs(acc))
            if sliding and first is None:
                first = it
            if sliding and (k == 0 or not rows[k - 1][2]):
                last = it
            if first is None:
                before, step = peak, max(step, abs(c))
        end = rows[-1][0] if rows else 0
        print(f"{case.id:22s} {row['status']:10s} {row.get('fault') or '':12s} "
              f"last iteration {end:4d}  peak {peak:5.2f} mm  before a slide {before:5.2f} mm "
              f"(an iteration ≤ {step:4.2f} mm)  slides from {first} "
              f"(the last from {last})")  # fmt: skip


if __name__ == "__main__":
    main()
