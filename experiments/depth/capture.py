"""Capture what the controller sees at the grasp, and the simulation's truth, for campaign cases.

Each case runs exactly as in a campaign (:func:`sdh2svc.campaign.run.case_settings`, fast mode,
the full byte path) up to its first rolling iteration with both contacts — the iteration whose Λ
the campaign reports as "Λ at grasp" — and stops there. One JSON line per case: the joint pose,
both distal matrices (raw counts), the model's Λ, the true contact points (on the object's
surface), each finger's true yield along its pad normal, and the case's true width.

    python -m experiments.depth.capture --suite bench-v1 --every 3 --out /tmp/grasp.jsonl

Then :mod:`experiments.depth.evaluate` applies the contact-depth model offline to the captured
matrices (the same :func:`~sdh2svc.model.observe.observe` the controller runs).
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path
from typing import Any

import sdh2svc.control.runner as runner_mod
from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import case_settings
from sdh2svc.control.runner import RunFault
from sdh2svc.control.safety import Fault

DISTAL = {"distal1": 0, "distal2": 2}  # ContactPhysics surface indices


class _Captured(RunFault):
    pass


def capture_case(case: Any, workdir: Path, overrides: list[str] | None = None) -> dict[str, Any]:
    from sdh2svc.connect import Simulated
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    cfg = case_settings(case, overrides or [], None, workdir / f"{case.id}.sqlite")
    got: dict[str, Any] = {}
    holder: dict[str, Any] = {}
    real_step = runner_mod.step

    def observer(bench: Any) -> Any:
        holder["bench"] = bench

        class _Obs:
            def event(self, *a: Any) -> None:
                pass

            def sample(self, *a: Any) -> None:
                pass

        return _Obs()

    def step(state, pose, m1, m2, params, ctx):  # type: ignore[no-untyped-def]
        r = real_step(state, pose, m1, m2, params, ctx)
        if r.obs.Lambda is not None and not got:
            phys = holder["bench"].sim.world._physics
            contacts = {c.surface: c for c in phys.contacts()}
            truth = {}
            for name, j in DISTAL.items():
                c = contacts.get(name)
                if c is None:
                    continue
                comp = phys._last.compressions.get(j)
                truth[name] = {
                    "point": list(c.point),
                    "s_mm": c.s_mm,
                    "N": c.normal_force_n,
                    "yield_mm": phys._e_hint.get(j, 0.0),
                    "max_compression_mm": None if comp is None else float(comp[3]),
                }
            got.update(
                pose=[pose.phi2, pose.phi3, pose.phi4, pose.phi5],
                m1=m1.astype(int).tolist(),
                m2=m2.astype(int).tolist(),
                Lambda=r.obs.Lambda,
                F=r.F,
                object_pose=list(phys.state.pose.tolist()),
                truth=truth,
                others=sorted(contacts),
            )
            raise _Captured(Fault.STUCK, "captured")
        return r

    runner_mod.step = step
    try:
        run_fast(run_once(cfg, Simulated(obj=case.object, fast=True), observer=observer))
    finally:
        runner_mod.step = real_step
    spec = case.object
    return {
        "id": case.id, "family": case.family, "true_width_mm": case.true_width_mm,
        "angle_deg": case.angle_deg, "gain_factor": case.sensor.gain_factor,
        "stiffness": spec.material.stiffness_n_per_mm3, "kind": spec.kind,
        "spec": json.loads(case.model_dump_json()), **got,
    }  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--suite", default="bench-v1")
    ap.add_argument("--every", type=int, default=1, help="every n-th case")
    ap.add_argument("--offset", type=int, default=0)
    ap.add_argument("--min-stiffness", type=float, default=0.0)
    ap.add_argument("--out", required=True)
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    a = ap.parse_args()
    suite = load_suite(a.suite)
    cases = [c for c in suite.cases[a.offset :: a.every]
             if c.object.material.stiffness_n_per_mm3 >= a.min_stiffness]  # fmt: skip
    out = Path(a.out)
    done = set()
    if out.exists():
        done = {json.loads(line)["id"] for line in out.read_text().splitlines() if line}
    with tempfile.TemporaryDirectory() as tmp, out.open("a") as f:
        for case in cases:
            if case.id in done:
                continue
            t0 = time.perf_counter()
            row = capture_case(case, Path(tmp), a.overrides)
            f.write(json.dumps(row) + "\n")
            f.flush()
            lam = row.get("Lambda")
            err = None if lam is None else lam - case.true_width_mm
            print(f"{case.id}: err {err if err is None else round(err, 2)} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main()
