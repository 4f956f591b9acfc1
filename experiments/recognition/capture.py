"""Capture what the recognizer sees at every rolling iteration, and the truth it is judged by.

Each case runs exactly as in a campaign (:func:`sdh2svc.campaign.run.case_settings`, fast mode,
the full byte path, :class:`~sdh2svc.campaign.run.TruthProbe` beside it, judged by
:func:`~sdh2svc.campaign.run.measure`). At every rolling iteration it stores the controller's
inputs — the joint pose and both distal matrices (raw counts) — and the simulation's truth: the
object's pose (y, z, ψ) and, per distal pad, the true contact's point on the object (object
frame), its surface parameter and normal force. The object's spec is stored with the case, so
which feature touches each pad is computed offline (:mod:`experiments.recognition.truth`).

    for s in 1701 1703 1704 1705 1706 1707 1711 1712 1713 1714 1715 1716 1717 1718; do
        python -m experiments.recognition.capture --seed $s --n 60 --out /tmp/recog/fit-$s.jsonl
    done  # the fit suites (two at a time on two cores: ≈ 3 min a pair)
    python -m experiments.recognition.capture --seed 1702 --n 60 --out /tmp/recog/test.jsonl
    python -m experiments.recognition.capture --seed 1709 --n 60 --out /tmp/recog/test2.jsonl
    python -m experiments.recognition.capture --seed 1710 --n 60 --out /tmp/recog/test3.jsonl
    python -m experiments.recognition.capture --seed 1720 --n 60 --out /tmp/recog/test4.jsonl
    python -m experiments.recognition.capture --suite thesis --out /tmp/recog/thesis.jsonl

One JSON line per case; a case already in the file is skipped (the capture resumes).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import sdh2svc.control.runner as runner_mod
from sdh2svc.campaign.case import Case, load_suite
from sdh2svc.campaign.run import TruthProbe, case_settings, measure
from sdh2svc.control.runner import RunFault
from sdh2svc.control.safety import Fault

DISTAL = ("distal1", "distal2")


class _Enough(RunFault):
    pass


def capture_case(
    case: Case, workdir: Path, overrides: list[str] | None = None, max_iterations: int | None = None
) -> dict[str, Any]:
    """One campaign run of ``case`` with every iteration's inputs and truth (stopped after
    ``max_iterations`` rolling iterations if given: then the run is not judged)."""
    from sdh2svc.connect import Simulated
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    cfg = case_settings(case, overrides or [], None, workdir / f"{case.id}.sqlite")
    probe = TruthProbe()
    its: list[dict[str, Any]] = []
    real_step = getattr(runner_mod, "step")  # noqa: B009 (patched below)

    def step(state, pose, m1, m2, params, ctx):  # type: ignore[no-untyped-def]
        r = real_step(state, pose, m1, m2, params, ctx)
        bench = probe.bench
        truth: dict[str, Any] = {}
        if bench is not None:
            contacts = {c.surface: c for c in bench.contacts_now()}
            for name in DISTAL:
                c = contacts.get(name)
                if c is not None:
                    truth[name] = {
                        "object_point": list(c.object_point),
                        "s_mm": c.s_mm,
                        "N": c.normal_force_n,
                        "slipping": c.slipping,
                    }
            truth["object_pose"] = list(bench.object_pose())
        its.append(
            {
                "iteration": r.state.iteration,
                "strokes": state.strokes,
                "half_strokes": state.half_strokes,
                "direction": state.direction,
                "pose": [pose.phi2, pose.phi3, pose.phi4, pose.phi5],
                "m1": m1.astype(int).tolist(),
                "m2": m2.astype(int).tolist(),
                "reversal": r.reversal.value if r.reversal else None,
                "truth": truth,
            }
        )
        if max_iterations is not None and len(its) >= max_iterations:
            raise _Enough(Fault.STUCK, "enough iterations captured")
        return r

    setattr(runner_mod, "step", step)  # noqa: B010
    t0 = time.perf_counter()
    try:
        summary = run_fast(run_once(cfg, Simulated(obj=case.object, fast=True), observer=probe))
        row = measure(summary, probe, cfg, case)
    finally:
        setattr(runner_mod, "step", real_step)  # noqa: B010
    return {
        "id": case.id,
        "family": case.family,
        "spec": json.loads(case.model_dump_json()),
        "psi_grasp": probe.psi_grasp,
        "status": row["status"],
        "strokes": row["strokes"],
        "dropped": row["dropped"],
        "half_stroke_rotation_deg": row["half_stroke_rotation_deg"],
        "wall_s": time.perf_counter() - t0,
        "iterations": its,
    }


def cases_for(suite: str | None, seed: int | None, n: int) -> list[Case]:
    if suite is not None:
        return list(load_suite(suite).cases)
    from sdh2svc.campaign.generate import generate_cases

    assert seed is not None
    return generate_cases(seed, n, prefix=f"s{seed}-")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--suite", help="a named suite (e.g. thesis) instead of generated cases")
    ap.add_argument("--seed", type=int, help="generate_cases(seed, n)")
    ap.add_argument("--n", type=int, default=60)
    ap.add_argument("--out", required=True)
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    a = ap.parse_args()
    if (a.suite is None) == (a.seed is None):
        ap.error("give --suite or --seed")
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    done = set()
    if out.exists():
        done = {json.loads(line)["id"] for line in out.read_text().splitlines() if line}
    with tempfile.TemporaryDirectory() as tmp, out.open("a") as f:
        for case in cases_for(a.suite, a.seed, a.n):
            if case.id in done:
                continue
            row = capture_case(case, Path(tmp), a.overrides)
            f.write(json.dumps(row) + "\n")
            f.flush()
            print(
                f"{case.id}: {row['status']}, {len(row['iterations'])} iterations "
                f"({row['wall_s']:.1f} s)",
                flush=True,
            )


if __name__ == "__main__":
    main()
