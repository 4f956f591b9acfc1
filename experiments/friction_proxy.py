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
import itertools
import json
import math
import sys
import tempfile
from collections.abc import Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

# one row per rolling iteration
COLUMNS = ("iteration", "lean_A", "lean_B", "plan_A", "plan_B", "true_A", "true_B",
           "slip_A", "slip_B", "alpha", "reversal")  # fmt: skip


def lean_deg(w: float | None) -> float | None:
    """A contact's lean |ω − 90°| (deg) from its ω (rad; None: no contact)."""
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
        rows.append([state.iteration, lean_deg(r.obs.omega_A), lean_deg(r.obs.omega_B),
                     lean_deg(plan.omega_A_d) if plan else None,
                     lean_deg(plan.omega_B_d) if plan else None, ta, tb, sa, sb,
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
    return {"id": case.id, "family": case.family, "alpha_deg": cfg.rolling.alpha_deg,
            "friction_deg": math.degrees(math.atan(case.object.material.friction)),
            "status": row["status"], "success": row["success"], "failure": row["failure"],
            "rows": rows}  # fmt: skip


def run(suite: str, out: Path, overrides: Sequence[str], workers: int) -> None:
    """Probe every case of ``suite`` on ``workers`` processes, one JSON line per case in ``out``
    (in the suite's order), the progress on stderr."""
    from sdh2svc.campaign import run as camp
    from sdh2svc.campaign.case import load_suite

    loaded = load_suite(suite)
    if loaded.cases:  # a bad --set is refused here, before any worker starts
        camp.case_settings(loaded.cases[0], overrides, None)
    cases = [c.model_dump_json() for c in loaded.cases]
    with ProcessPoolExecutor(workers) as ex, out.open("w") as f:
        results = ex.map(probe_case, cases, itertools.repeat(tuple(overrides), len(cases)))
        for i, res in enumerate(results, 1):
            f.write(json.dumps(res) + "\n")
            print(f"\r{i}/{len(cases)} {res['id']}: {res['status']}   ", end="", file=sys.stderr)
    print(file=sys.stderr)


def _pct(x: np.ndarray) -> str:
    p5, p50, p95 = np.percentile(x, [5, 50, 95])
    return f"{x.mean():+.2f}° (median {p50:+.2f}°, 5–95 % {p5:+.2f}° to {p95:+.2f}°), n = {len(x)}"


@dataclass
class _Figures:
    """What ``report`` counts, over every probed run."""

    error: list[float] = field(default_factory=list)  # measured − true lean, every one
    grasp: list[float] = field(default_factory=list)  # the same, the contact widening at grasp
    widened: list[float] = field(default_factory=list)  # ... a contact widening them later
    slide: list[float] = field(default_factory=list)  # a sliding contact's lean − friction angle
    # the measured lean's change over the planned one, where the plan leaned it further
    follow: dict[bool, list[float]] = field(default_factory=lambda: {False: [], True: []})


_COL = {c: i for i, c in enumerate(COLUMNS)}


def _scan(case: dict[str, Any], fig: _Figures) -> None:
    rows, alpha0 = case["rows"], case["alpha_deg"]
    widest = alpha0
    for k, r in enumerate(rows):
        alpha = r[_COL["alpha"]]
        for x in "AB":
            m, t, s = r[_COL[f"lean_{x}"]], r[_COL[f"true_{x}"]], r[_COL[f"slip_{x}"]]
            if m is None or t is None:
                continue
            fig.error.append(m - t)
            if s:
                fig.slide.append(m - case["friction_deg"])
            if k == 0 and alpha > alpha0 + 1e-9 and m > alpha - 1e-9:  # this lean widened them
                fig.grasp.append(m - t)
            planned, before = (None, None) if k == 0 else (
                rows[k - 1][_COL[f"plan_{x}"]], rows[k - 1][_COL[f"lean_{x}"]])  # fmt: skip
            if planned is not None and before is not None and planned - before > 0.05:
                fig.follow[bool(s)].append((m - before) / (planned - before))
        if k > 0 and alpha > widest + 1e-9:  # widened by the contact whose lean it took
            leans = {x: r[_COL[f"lean_{x}"]] for x in "AB" if r[_COL[f"lean_{x}"]] is not None}
            x = min(leans, key=lambda x: abs(leans[x] - alpha), default=None)
            if x is not None and r[_COL[f"true_{x}"]] is not None:
                fig.widened.append(leans[x] - r[_COL[f"true_{x}"]])
        widest = max(widest, alpha)


# A slide told by its lean stalling: over STALL_WINDOW iterations without a reversal, the plans
# asked a contact to lean STALL_PUSH degrees further in all while its measured lean rose less
# than STALL_RISE, and it leans at least STALL_LEAN (the lowest friction angle the lab expects,
# ``wedge_limit``: below it no object slides). One setting, to see whether such a rule could
# tell a slide from a hold; nothing in the controller uses it.
STALL_WINDOW, STALL_PUSH, STALL_RISE, STALL_LEAN = 6, 2.0, 0.2, 16.0


def stalls(rows: Sequence[Sequence[Any]]) -> list[tuple[int, str, bool]]:
    """Where a contact's lean stalled (see STALL_WINDOW): (row index, contact, whether the
    simulation had it slipping at any iteration of the window)."""
    out: list[tuple[int, str, bool]] = []
    rev = _COL["reversal"]
    for x in "AB":
        lean, plan, slip = _COL[f"lean_{x}"], _COL[f"plan_{x}"], _COL[f"slip_{x}"]
        for k in range(STALL_WINDOW, len(rows)):
            win = rows[k - STALL_WINDOW : k + 1]
            if any(r[rev] for r in win[:-1]) or any(r[lean] is None for r in win):
                continue
            if any(r[plan] is None for r in win[:-1]) or win[-1][lean] < STALL_LEAN:
                continue
            push = sum(r[plan] - r[lean] for r in win[:-1])
            if push > STALL_PUSH and win[-1][lean] - win[0][lean] < STALL_RISE:
                out.append((k, x, any(bool(r[slip]) for r in win)))
    return out


def _stall_line(runs: Sequence[dict[str, Any]]) -> str:
    found: dict[bool, list[list[tuple[int, str, bool]]]] = {True: [], False: []}  # by "slid"
    for c in runs:
        slid = any(r[_COL["slip_A"]] or r[_COL["slip_B"]] for r in c["rows"])
        found[slid].append(stalls(c["rows"]))
    slid, held = found[True], found[False]
    caught = sum(any(s for _, _, s in st) for st in slid)
    false = sum(bool(st) for st in held)
    return (f"A lean that stalls ({STALL_WINDOW} iterations without a reversal, a lean of at "
            f"least {STALL_LEAN:g}°, plans asking {STALL_PUSH:g}° more in all, a rise under "
            f"{STALL_RISE:g}°) is seen during a slide in {caught} of the {len(slid)} runs "
            f"whose contacts slid, and in {false} of the {len(held)} runs whose contacts "
            "never slid.")  # fmt: skip


def report(paths: Sequence[Path]) -> str:
    """The figures, as markdown."""
    runs = [json.loads(line) for p in paths for line in p.read_text().splitlines() if line]
    fig = _Figures()
    for case in runs:
        _scan(case, fig)

    def row(what: str, x: list[float]) -> str:
        return f"| {what} | {_pct(np.array(x)) if x else 'none'} |"

    low = [c for c in runs if c["friction_deg"] < c["alpha_deg"]]  # α's cone too wide for them
    failed = [c["id"] for c in low if not c["success"]]
    followed = ", ".join(f"{'sliding' if s else 'holding'} {np.median(v):.2f} (n = {len(v)})"
                         for s, v in sorted(fig.follow.items()) if v)  # fmt: skip
    slid = f"{_pct(np.array(fig.slide))}." if fig.slide else "none slid."
    return "\n".join([
        f"{len(runs)} runs ({', '.join(str(p) for p in paths)}).",
        "",
        "| what | measured lean − true lean |",
        "|---|---|",
        row("every rolling contact-iteration", fig.error),
        row("a contact that widened the cones at the grasp", fig.grasp),
        row("a contact that widened the cones later (its cone refused both ways)", fig.widened),
        "",
        f"Sliding contact-iterations, measured lean − the object's friction angle: {slid}",
        "",
        f"Objects whose friction angle is below α: {len(low)}, of which {len(low) - len(failed)} "
        f"succeed" + (f" (failed: {', '.join(failed)})." if failed else "."),
        "",
        "How far a contact's measured lean followed a plan that leaned it further (the change "
        "of the measured lean over the planned one, from one iteration to the next), median: "
        f"{followed or 'no such plan'}.",
        "",
        _stall_line(runs),
    ])  # fmt: skip


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
    if a.cmd == "run" and a.workers < 1:
        ap.error("--workers must be at least 1")
    try:
        if a.cmd == "run":
            run(a.suite, a.out, a.overrides, a.workers)
        else:
            print(report(a.paths))
    except (OSError, ValueError) as e:  # a missing suite or file, a bad --set (ConfigError)
        print(f"error: {e}", file=sys.stderr)
        return 2
    except (KeyError, IndexError, TypeError) as e:
        print(f"error: not the output of `friction_proxy run` ({e!r})", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
