"""When do the contacts slide, and does an edge contact's travel along its pad tell it?

A corner or a stick's end rolls on a pad by pivoting: its contact stays where it is on the pad
(the rubber's wrap moves it a few hundredths of a millimetre a step). One that travels along
its pad is sliding. This replays recognition captures (:mod:`experiments.recognition.capture`;
their truth says, per pad and iteration, whether the simulated contact slides) through the
packaged recognizer and asks of every slide:

* how far the contact's measured lean |ω − 90°| at the slide's first iteration is from the
  object's friction angle atan μ;
* whether :func:`edge_slides` fires: a contact the recognizer has labelled an edge for
  ``WINDOW`` + 1 iterations running whose pressure centroid moved more than ``TRAVEL_MM``
  along its pad over them — in the runs that slid, and in the runs that never did.

    python -m experiments.recognition.slides /tmp/recog/test-17*.jsonl

Used by nothing in the controller (see ``experiments/campaigns/friction-proxy.md``).
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from experiments.friction_proxy import lean_deg
from experiments.recognition.evaluate import Case, context, load_cases
from sdh2svc.control.recognition import ContactKind, Recognizer, packaged_model
from sdh2svc.model.observe import ModelContext

WINDOW = 5  # iterations over which the travel is measured
# along the pad: over twice what a pivoting edge moves in WINDOW iterations at its 99th
# percentile per iteration (0.086 mm on the held-out captures; `moves` in the summary)
TRAVEL_MM = 1.0


def edge_slides(
    kinds: Sequence[ContactKind | None], x3: Sequence[float | None],
    window: int = WINDOW, travel_mm: float = TRAVEL_MM,
) -> list[int]:  # fmt: skip
    """The iterations at which one contact (its kind and position along the pad, mm, per
    iteration) has been an edge for ``window`` + 1 iterations running and moved more than
    ``travel_mm`` along its pad over them."""
    fired = []
    for j in range(window, len(kinds)):
        start, end = x3[j - window], x3[j]
        if start is None or end is None:
            continue
        edge = all(k is ContactKind.EDGE for k in kinds[j - window : j + 1])
        if edge and abs(end - start) > travel_mm:
            fired.append(j)
    return fired


def judge_case(raw: dict[str, Any], case: Case, ctx: ModelContext) -> dict[str, Any]:
    """One captured case: its slides (per pad: first iteration, lean there), the detector's
    fires (per pad: iterations, and how many fell within a slide) and how far each contact
    moved along its pad per iteration, by its label and whether it slid (``moves``)."""
    mu = raw["spec"]["object"]["material"]["friction"]
    rec = Recognizer(ctx, packaged_model())
    kinds: list[list[ContactKind | None]] = [[], []]
    x3: list[list[float | None]] = [[], []]
    slid: list[list[bool]] = [[], []]
    lean: list[list[float | None]] = [[], []]
    for it, step in zip(raw["iterations"], case.steps, strict=True):
        r = rec.update(step.obs, step.m1, step.m2)
        obs = step.obs
        for pad, (name, kind, contact, omega) in enumerate(
            (("distal1", r.kind1, obs.contact1, obs.omega_A),
             ("distal2", r.kind2, obs.contact2, obs.omega_B))
        ):  # fmt: skip
            kinds[pad].append(kind)
            x3[pad].append(contact.x3_mm if obs.points is not None else None)
            slid[pad].append(bool((it["truth"].get(name) or {}).get("slipping", False)))
            lean[pad].append(lean_deg(omega))
    angle = math.degrees(math.atan(mu))
    out: dict[str, Any] = {"id": raw["id"], "status": raw["status"], "mu": mu,
                           "friction_angle_deg": angle, "pads": [], "moves": {}}  # fmt: skip
    for pad in range(2):
        for j in range(1, len(x3[pad])):
            a, b, kind = x3[pad][j - 1], x3[pad][j], kinds[pad][j]
            if a is not None and b is not None and kind is not None:
                key = f"{kind.value} {'sliding' if slid[pad][j] else 'holding'}"
                out["moves"].setdefault(key, []).append(abs(b - a))
    for pad in range(2):
        first = next((j for j, s in enumerate(slid[pad]) if s), None)
        fires = edge_slides(kinds[pad], x3[pad])
        out["pads"].append({
            "slid_iterations": sum(slid[pad]),
            "first_slide": first,
            "lean_at_first_slide_deg": None if first is None else lean[pad][first],
            "fires": fires,
            "fires_in_a_slide": sum(1 for j in fires if any(slid[pad][j - WINDOW : j + 1])),
        })  # fmt: skip
    return out


def summary(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Counts over the cases (:func:`judge_case`'s rows)."""
    slid = [r for r in rows if any(p["slid_iterations"] for p in r["pads"])]
    held = [r for r in rows if r not in slid]
    gaps = [p["lean_at_first_slide_deg"] - r["friction_angle_deg"] for r in slid
            for p in r["pads"] if p["lean_at_first_slide_deg"] is not None]  # fmt: skip
    fires = sum(len(p["fires"]) for r in rows for p in r["pads"])
    true_fires = sum(p["fires_in_a_slide"] for r in rows for p in r["pads"])
    return {
        "runs": len(rows),
        "runs_that_slid": len(slid),
        "lean_at_first_slide_minus_friction_angle_deg": {
            "mean": sum(gaps) / len(gaps) if gaps else None,
            "min": min(gaps, default=None),
            "max": max(gaps, default=None),
        },
        "edge_slides_fired_in_runs_that_slid": sum(
            1 for r in slid if any(p["fires"] for p in r["pads"])
        ),
        "edge_slides_fired_in_runs_that_never_slid": sum(
            1 for r in held if any(p["fires"] for p in r["pads"])
        ),
        "fires": fires,
        "fires_outside_a_slide": fires - true_fires,
        "moves": _moves(rows),
    }


def _moves(rows: list[dict[str, Any]]) -> dict[str, dict[str, float]]:
    """Per contact label, holding or sliding: how far the contact moved along its pad per
    iteration (mm; count, median, 90th and 99th percentiles)."""
    pooled: dict[str, list[float]] = {}
    for r in rows:
        for key, values in r["moves"].items():
            pooled.setdefault(key, []).extend(values)
    out = {}
    for key in sorted(pooled):
        v = np.asarray(pooled[key])
        p50, p90, p99 = np.percentile(v, [50, 90, 99])
        out[key] = {"n": float(len(v)), "median": p50, "p90": p90, "p99": p99}
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+", help="capture files (experiments.recognition.capture)")
    ap.add_argument("--list", action="store_true", help="print every run that slid or fired")
    a = ap.parse_args()
    ctx = context()
    rows = []
    for path in a.captures:
        with Path(path).open() as fh:
            raws = [json.loads(line) for line in fh if line.strip()]
        for raw, case in zip(raws, load_cases(path, ctx), strict=True):
            rows.append(judge_case(raw, case, ctx))
    if a.list:
        for r in rows:
            if any(p["slid_iterations"] or p["fires"] for p in r["pads"]):
                print(json.dumps({k: v for k, v in r.items() if k != "moves"}))
    print(json.dumps(summary(rows), indent=1))


if __name__ == "__main__":
    main()
