"""Λ at grasp − true width, with and without the contact-depth model, on captured grasps.

    python -m experiments.depth.evaluate /tmp/grasp.jsonl [--set key=value …]

The captured matrices and poses (:mod:`experiments.depth.capture`) go through the same
:func:`~sdh2svc.model.observe.observe` the controller runs, once with ``[hand.contact_depth]``
``model = "none"`` (the thesis's model) and once with the configuration's model. Also shown: Λ
from the simulation's true contact points (what a perfect depth estimate would give against the
campaign's true width) and the per-side depth error against the truth.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterable, Sequence

import numpy as np

from sdh2svc.config import load_config
from sdh2svc.model.geometry import PadProfile
from sdh2svc.model.kinematics import Finger, HandGeometry, HandPose, distal_joint, frame3_axes
from sdh2svc.model.observe import observe

WITHIN_MM = 1.7
RIGID = 0.5  # N/mm³: objects at least 2.5 × as stiff as the pad rubber
GAIN_BINS = ((0.5, 0.75), (0.75, 1.0), (1.0, 1.25), (1.25, 1.5001))


def to_frame3(
    finger: Finger, pose: HandPose, p: Sequence[float], geom: HandGeometry
) -> tuple[float, float]:
    """A frame-0 point (y, z) in the distal frame 3 of ``finger`` (x3, y3)."""
    prox, dist = pose.finger(finger)
    C = distal_joint(finger, prox, geom)
    ex, ey = frame3_axes(finger, prox + dist)
    dy, dz = p[0] - C.y, p[1] - C.z
    return dy * ex.y + dz * ex.z, dy * ey.y + dz * ey.z


def depth_below(x3: float, y3: float, pad: PadProfile) -> float:
    """How far a frame-3 point lies below the undeformed pad surface (positive: inside)."""
    if x3 <= pad.flat_end_x3_mm:
        return pad.flat_y3_mm - y3
    ky = pad.flat_y3_mm - pad.arc_radius_mm
    return pad.arc_radius_mm - math.hypot(x3 - pad.flat_end_x3_mm, y3 - ky)


def rows_of(path: str) -> Iterable[dict]:
    with open(path) as f:
        for line in f:
            if line.strip():
                yield json.loads(line)


def evaluate(path: str, overrides: Sequence[str], recalibrated: bool = False) -> list[dict]:
    """``recalibrated``: the pads' physical pressure per count as it truly is in each run (the
    nominal one divided by the run's gain factor), i.e. pads calibrated just before the run."""
    base = load_config(None, list(overrides))
    on = base.model_context()
    off = load_config(None, [*overrides, "hand.contact_depth.model=none"]).model_context()
    per = base.calibration.physical_pressure_per_count_n_per_mm2
    out = []
    for r in rows_of(path):
        if "pose" not in r:
            continue
        if recalibrated:
            key = f"calibration.physical_pressure_per_count_n_per_mm2={per / r['gain_factor']!r}"
            on = load_config(None, [*overrides, key]).model_context()
        pose = HandPose(*r["pose"])
        m1, m2 = np.array(r["m1"]), np.array(r["m2"])
        o_off, o_on = observe(pose, m1, m2, off), observe(pose, m1, m2, on)
        if o_off.Lambda is None or o_on.Lambda is None:
            continue
        width = r["true_width_mm"]
        row = {"id": r["id"], "family": r["family"], "k": r["stiffness"], "gain": r["gain_factor"],
               "before": o_off.Lambda - width, "after": o_on.Lambda - width}  # fmt: skip
        t = r["truth"]
        if "distal1" in t and "distal2" in t:
            row["truth_pts"] = math.dist(t["distal1"]["point"], t["distal2"]["point"]) - width
            for name, c, finger in (("distal1", o_on.contact1, Finger.ONE),
                                    ("distal2", o_on.contact2, Finger.TWO)):  # fmt: skip
                d = depth_below(*to_frame3(finger, pose, t[name]["point"], on.geom), on.geom.pad)
                row.setdefault("depth_err", []).append(c.depth.depth_mm - d)
        out.append(row)
    return out


def campaign_rows(before_dir: str, after_dir: str) -> list[dict]:
    """Rows as :func:`evaluate` makes them, from two campaigns' ``lambda_error_mm`` (the same
    suite run with ``hand.contact_depth.model=none`` and with the model)."""
    import pyarrow.parquet as pq

    def load(d: str) -> dict[str, dict]:
        return {r["id"]: r for r in pq.read_table(f"{d}/results.parquet").to_pylist()}

    a, b = load(before_dir), load(after_dir)
    out = []
    for case_id, ra in a.items():
        rb = b.get(case_id)
        if rb is None or ra["lambda_error_mm"] is None or rb["lambda_error_mm"] is None:
            continue
        k = json.loads(ra["spec"])["object"]["material"]["stiffness_n_per_mm3"]
        out.append({"id": case_id, "family": ra["family"], "k": k, "gain": ra["gain_factor"],
                    "before": ra["lambda_error_mm"], "after": rb["lambda_error_mm"],
                    "success": (ra["success"], rb["success"])})  # fmt: skip
    return out


def _cells(errs: Sequence[float]) -> str:
    if not errs:
        return "– | – | – | –"
    q5, q50, q95 = np.percentile(errs, [5, 50, 95])
    share = float(np.mean(np.abs(np.asarray(errs)) <= WITHIN_MM)) * 100
    return f"{q50:+.2f} | {q5:+.2f} | {q95:+.2f} | {share:.0f} %"


def table(groups: dict[str, list[dict]]) -> str:
    """Markdown: before and after (median, 5 %, 95 %, share within 1.7 mm); for captured grasps
    also the share within 1.7 mm of Λ from the true contact points and of the corrected Λ
    against them; for campaigns the successes before and after."""
    truth = any("truth_pts" in r for sel in groups.values() for r in sel)
    extra = ("true points within | after vs true points within" if truth
             else "successes before | after")  # fmt: skip
    out = [f"| cases | n | before: median | 5 % | 95 % | within | after: median | 5 % | 95 % "
           f"| within | {extra} |", "|---" * 12 + "|"]  # fmt: skip
    for name, sel in groups.items():
        if truth:
            tp = [r["truth_pts"] for r in sel if "truth_pts" in r]
            vs = [r["after"] - r["truth_pts"] for r in sel if "truth_pts" in r]
            a = float(np.mean(np.abs(tp) <= WITHIN_MM)) * 100 if tp else math.nan
            b = float(np.mean(np.abs(vs) <= WITHIN_MM)) * 100 if vs else math.nan
            tail = f"{a:.0f} % | {b:.0f} %"
        else:
            tail = f"{sum(r['success'][0] for r in sel)} | {sum(r['success'][1] for r in sel)}"
        before, after = _cells([r["before"] for r in sel]), _cells([r["after"] for r in sel])
        out.append(f"| {name} | {len(sel)} | {before} | {after} | {tail} |")
    return "\n".join(out)


def report(rows: list[dict]) -> None:
    rigid = [r for r in rows if r["k"] >= RIGID]
    groups = {"all (any stiffness)": rows, f"rigid (k ≥ {RIGID} N/mm³)": rigid,
              "k ≥ 1 N/mm³": [r for r in rows if r["k"] >= 1.0]}  # fmt: skip
    for fam in sorted({r["family"] for r in rigid}):
        groups[f"rigid {fam}"] = [r for r in rigid if r["family"] == fam]
    for lo, hi in GAIN_BINS:
        groups[f"rigid, gain ×{lo:.2f}–{min(hi, 1.5):.2f}"] = [
            r for r in rigid if lo <= r["gain"] < hi
        ]
    print(table(groups))
    de = [d for r in rigid for d in r.get("depth_err", [])]
    if de:
        q = np.percentile(de, [5, 50, 95])
        print(
            f"\nrigid: depth error per side (estimate − truth), median {q[1]:+.2f} mm, "
            f"5 % {q[0]:+.2f}, 95 % {q[2]:+.2f}"
        )


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("captured", help="a capture's JSONL, or a campaign directory (with --after)")
    ap.add_argument("--after", help="the campaign directory run with the model")
    ap.add_argument("--set", action="append", default=[], dest="overrides")
    ap.add_argument("--recalibrated", action="store_true",
                    help="the pads' pressure scale of each run known (no gain drift)")  # fmt: skip
    ap.add_argument("--list", action="store_true", help="every rigid case outside ±1.7 mm")
    a = ap.parse_args()
    rows = (
        campaign_rows(a.captured, a.after)
        if a.after
        else evaluate(a.captured, a.overrides, a.recalibrated)
    )
    report(rows)
    if a.list:
        for r in rows:
            if r["k"] >= RIGID and abs(r["after"]) > WITHIN_MM:
                print(
                    f"  {r['id']:12s} k {r['k']:.2f} gain {r['gain']:.2f} before {r['before']:+.2f}"
                    f" after {r['after']:+.2f} true points {r.get('truth_pts', math.nan):+.2f}"
                )


if __name__ == "__main__":
    main()
