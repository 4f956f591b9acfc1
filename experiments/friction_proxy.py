"""How well the controller's ω measures how hard each contact leans on its friction.

    python -m experiments.friction_proxy run SUITE OUT.jsonl [--set KEY=VALUE …] [--workers N]
    python -m experiments.friction_proxy report OUT.jsonl [OUT2.jsonl …]

The friction cones of the rolling step (control/rolling.py) judge a contact by its measured lean
|ω − 90°|: the angle between AB, from the two pads' pressure centroids, and the pad's normal
there. What friction really has to carry is the angle of the contact's force to the pad's
normal, atan(Ft/N). ``run`` runs every case of a suite in fast mode through the full byte path,
as ``sdh2svc campaign run`` does, and records at every rolling iteration both leans of both
distal contacts — the measured one, and the true one with the simulation's slipping flag
(:meth:`~sdh2svc.connect.Bench.contacts_now`, which steps nothing) — and the planned leans of
the configuration commanded. ``report`` prints what they show (markdown).

The instrument wraps the rolling step the runner calls; the step is pure and reading the truth
steps nothing, so each run is bit for bit the campaign's (its status is recorded to compare).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import sys
import tempfile
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

# one row per rolling iteration
COLUMNS = ("iteration", "lean_A", "lean_B", "plan_A", "plan_B", "true_A", "true_B",
           "slip_A", "slip_B", "alpha", "reversal")  # fmt: skip


def _lean(w: float | None) -> float | None:
    return None if w is None else abs(math.degrees(w) - 90.0)


@contextlib.contextmanager
def _probed_step(rows: list[list[Any]], bench: list[Any]) -> Iterator[None]:
    """The runner's rolling step, recording each iteration's row in ``rows`` (``bench[0]`` is the
    simulated hand's bench once the run is up)."""
    import sdh2svc.control.runner as runner

    step = runner.step

    def probed(state: Any, pose: Any, m1: Any, m2: Any, params: Any, ctx: Any) -> Any:
        r = step(state, pose, m1, m2, params, ctx)
        truth = {c.surface: c for c in bench[0].contacts_now()} if bench else {}

        def true(surface: str) -> tuple[float | None, bool | None]:
            c = truth.get(surface)
            if c is None or c.normal_force_n <= 0.0:
                return None, None
            return math.degrees(math.atan2(abs(c.tangential_force_n), c.normal_force_n)), c.slipping

        (ta, sa), (tb, sb) = true("distal1"), true("distal2")
        plan = r.plan if r.targets is not None else None
        rows.append([state.iteration, _lean(r.obs.omega_A), _lean(r.obs.omega_B),
                     _lean(plan.omega_A_d) if plan else None,
                     _lean(plan.omega_B_d) if plan else None, ta, tb, sa, sb,
                     math.degrees(r.alpha), r.reversal.value if r.reversal else None])  # fmt: skip
        return r

    runner.step = probed  # type: ignore[assignment]
    try:
        yield
    finally:
        runner.step = step  # type: ignore[assignment]


def probe_case(case_json: str, overrides: Sequence[str] = ()) -> dict[str, Any]:
    """One case, probed: its id, family, friction angle, verdict and rows."""
    from sdh2svc.campaign import run as camp
    from sdh2svc.campaign.case import Case
    from sdh2svc.connect import Simulated
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    case = Case.model_validate_json(case_json)
    truth = camp.TruthProbe()
    bench: list[Any] = []

    def observer(b: Any) -> camp.TruthProbe:
        bench.append(b)
        return truth(b)

    rows: list[list[Any]] = []
    with tempfile.TemporaryDirectory(prefix="sdh2svc-proxy-") as tmp:
        cfg = camp.case_settings(case, overrides, None, Path(tmp) / "run.sqlite")
        with _probed_step(rows, bench):
            summary = run_fast(run_once(cfg, Simulated(obj=case.object, fast=True),
                                        observer=observer))  # fmt: skip
        row = camp.finish_row(camp.case_columns(case) | camp.measure(summary, truth, cfg, case))
    return {"id": case.id, "family": case.family,
            "friction_deg": math.degrees(math.atan(case.object.material.friction)),
            "status": row["status"], "success": row["success"], "failure": row["failure"],
            "rows": rows}  # fmt: skip


def run(suite: str, out: Path, overrides: Sequence[str], workers: int) -> None:
    from sdh2svc.campaign.case import load_suite

    cases = [c.model_dump_json() for c in load_suite(suite).cases]
    with ProcessPoolExecutor(workers) as ex, out.open("w") as f:
        args = [(c, tuple(overrides)) for c in cases]
        for i, res in enumerate(ex.map(_probe_args, args), 1):
            f.write(json.dumps(res) + "\n")
            print(f"\r{i}/{len(cases)} {res['id']}: {res['status']}   ", end="", file=sys.stderr)
    print(file=sys.stderr)


def _probe_args(a: tuple[str, tuple[str, ...]]) -> dict[str, Any]:
    return probe_case(*a)


def _pct(x: np.ndarray) -> str:
    p5, p50, p95 = np.percentile(x, [5, 50, 95])
    return f"{x.mean():+.2f}° (median {p50:+.2f}°, 5–95 % {p5:+.2f}° to {p95:+.2f}°), n = {len(x)}"


def report(paths: Sequence[Path]) -> str:
    """The figures, as markdown."""
    runs = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line]
    col = {c: i for i, c in enumerate(COLUMNS)}
    err, slide, grasp, widen = [], [], [], []
    follow: dict[bool, list[float]] = {False: [], True: []}
    for case in runs:
        rows = case["rows"]
        for k, r in enumerate(rows):
            for x in "AB":
                m, t, s = r[col[f"lean_{x}"]], r[col[f"true_{x}"]], r[col[f"slip_{x}"]]
                if m is None or t is None:
                    continue
                err.append(m - t)
                if s:
                    slide.append(m - case["friction_deg"])
                if k == 0 and m > r[col["alpha"]] - 1e-9 and r[col["alpha"]] > 22.0 + 1e-9:
                    grasp.append(m - t)
                if k > 0:
                    prev = rows[k - 1]
                    planned, before = prev[col[f"plan_{x}"]], prev[col[f"lean_{x}"]]
                    if planned is not None and before is not None and planned - before > 0.05:
                        follow[bool(s)].append((m - before) / (planned - before))
            if k > 0 and r[col["alpha"]] > max(q[col["alpha"]] for q in rows[:k]) + 1e-9:
                x = min("AB", key=lambda x: abs((r[col[f"lean_{x}"]] or 0.0) - r[col["alpha"]]))
                if r[col[f"true_{x}"]] is not None:
                    widen.append(r[col[f"lean_{x}"]] - r[col[f"true_{x}"]])
    low = [c for c in runs if c["friction_deg"] < 22.0]  # α's cone wider than the object's
    followed = ", ".join(f"{'sliding' if s else 'holding'} {np.median(v):.2f} (n = {len(v)})"
                         for s, v in sorted(follow.items()) if v)  # fmt: skip
    lines = [
        f"{len(runs)} runs ({', '.join(str(p) for p in paths)}).",
        "",
        "| what | measured lean − true lean |",
        "|---|---|",
        f"| every rolling contact-iteration | {_pct(np.array(err))} |",
        f"| a contact that widened the cones at the grasp | {_pct(np.array(grasp))} |"
        if grasp
        else "| a contact that widened the cones at the grasp | none |",
        f"| a contact that widened the cones later (its cone refused both ways) | "
        f"{_pct(np.array(widen))} |"
        if widen
        else "| widened later | none |",
        "",
        f"Sliding contact-iterations, measured lean − the object's friction angle: "
        f"{_pct(np.array(slide))}."
        if slide
        else "No contact slid.",
        "",
        f"Objects whose friction angle is below α = 22°: {len(low)}, of which "
        f"{sum(bool(c['success']) for c in low)} succeed"
        + (f" (failed: {', '.join(c['id'] for c in low if not c['success'])})." if low else "."),
        "",
        "How far a contact's measured lean followed a plan that leaned it further (the change "
        f"of the measured lean over the planned one, from one iteration to the next), median: "
        f"{followed}.",
    ]
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m experiments.friction_proxy", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)  # fmt: skip
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="probe every case of a suite")
    r.add_argument("suite", help="a packaged suite's name or a suite file")
    r.add_argument("out", type=Path, help="the JSON-lines file to write")
    r.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    r.add_argument("--workers", type=int, default=2)
    rep = sub.add_parser("report", help="print the figures of probed suites")
    rep.add_argument("paths", type=Path, nargs="+")
    a = ap.parse_args(argv)
    if a.cmd == "run":
        run(a.suite, a.out, a.overrides, a.workers)
    else:
        print(report(a.paths))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
