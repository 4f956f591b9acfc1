"""The failure classes of tests/campaign/test_regressions.py (those it pins at the default, and
those near a limit it leaves to this bench), each judged over a family of grasp gains around the
default (2.40, 2.42, … 2.60 °/s per force unit; 2.5 the default).

A pinned case is one exact run: a controller change anywhere upstream moves its path, and a
case near a limit flips with it. When one fails, this tells a class that came back (it fails
for most gains) from a coin flip (it passed for some gains before, and does now): printed per
case, how many of the gains pass the test's own judgement and whether the default does.
The cases run on a process pool (all cores); ≈ 100 runs, a few minutes on 2 cores.
"""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any

from sdh2svc.campaign.run import run_case
from tests.campaign.test_regressions import CASES, FAILURE_CLASSES, NEAR_A_LIMIT, rolls_every_stroke

GAINS = tuple(round(2.40 + 0.02 * k, 2) for k in range(11))
DEFAULT_GAIN = 2.5


def _passes(case_id: str, gain: float) -> tuple[str, float, bool, str]:
    """One run of the case with the grasp's gain at ``gain``: (case, gain, passed, its end)."""
    row = run_case(CASES[case_id].model_dump_json(), (f"run.grasp_gain_deg_s={gain}",))
    try:
        rolls_every_stroke(row)
        ok = bool(row["success"])
    except AssertionError:
        ok = False
    return case_id, gain, ok, row.get("failure") or row.get("status", "")


def run() -> dict[str, Any]:
    classes = FAILURE_CLASSES + NEAR_A_LIMIT
    jobs = [(case_id, g) for case_id, _ in classes for g in GAINS]
    workers = os.cpu_count() or 1
    print(f"regressions: {len(classes)} failure classes × {len(GAINS)} grasp gains "
          f"({GAINS[0]}…{GAINS[-1]}), {workers} workers")  # fmt: skip
    with ProcessPoolExecutor(workers) as pool:
        results = list(pool.map(_passes, *zip(*jobs, strict=True)))
    out: dict[str, Any] = {}
    for case_id, baseline in classes:
        mine = [r for r in results if r[0] == case_id]
        passed = sum(r[2] for r in mine)
        default = next(r for r in mine if r[1] == DEFAULT_GAIN)
        ends = sorted({r[3] for r in mine if not r[2]})
        print(f"  {case_id:12s} (was {baseline}): {passed:2d}/{len(mine)} pass; the default "
              f"{'passes' if default[2] else 'fails'}"
              + (f"; failing: {', '.join(ends)}" if ends else ""))  # fmt: skip
        out[case_id] = passed / len(mine)
    return out
