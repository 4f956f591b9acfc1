"""Run the recognizer over captured cases and judge it against the truth.

    python -m experiments.recognition.evaluate /tmp/recog/test.jsonl [--model FILE] [--json OUT]

Per case: the contact kind at every iteration with both contacts (against
:func:`experiments.recognition.truth.feature`; beside it, as a secondary figure, the same with
an edge read as a curve or the reverse counted right where the touched radius is within 20 %
of the line between them, :func:`~experiments.recognition.truth.near_the_line`), the radius
at every iteration where both the truth and the estimate are curved, the class after the first
full stroke and at the end, and the rotation against the true ψ − ψ(first iteration): over the
run (the estimate's excursion against the true one) and at every counted half stroke's end.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from experiments.recognition.truth import (
    kind_at,
    radius_near_the_line,
    spec_of,
    touched_radius,
    true_class,
    true_sizes,
)
from sdh2svc.config import load_config
from sdh2svc.control.recognition import (
    ContactKind,
    Recognition,
    RecognitionModel,
    Recognizer,
    packaged_model,
)
from sdh2svc.model.kinematics import HandPose
from sdh2svc.model.observe import ModelContext, Observation, observe

PADS = ("distal1", "distal2")


@dataclass
class Step:
    obs: Observation
    m1: np.ndarray
    m2: np.ndarray
    strokes: int
    half_strokes: int
    psi: float | None  # the object's true angle, rad
    truth: tuple[tuple[ContactKind, float | None] | None, ...]  # per pad
    # per pad: the touched surface's radius within 20 % of the line between edge and curve
    near_line: tuple[bool, ...] = (False, False)


@dataclass
class Case:
    id: str
    family: str
    spec: Any
    steps: list[Step] = field(default_factory=list)


def context() -> ModelContext:
    return load_config(use_env=False).model_context()


def load_cases(path: str | Path, ctx: ModelContext) -> Iterator[Case]:
    """Every captured case with its observations (the controller's own :func:`observe`)."""
    with Path(path).open() as fh:
        for line in fh:
            raw = json.loads(line)
            spec = spec_of(raw)
            case = Case(raw["id"], raw["family"], spec)
            for it in raw["iterations"]:
                m1, m2 = np.asarray(it["m1"]), np.asarray(it["m2"])
                obs = observe(HandPose(*it["pose"]), m1, m2, ctx)
                tr = it["truth"]
                pose = tr.get("object_pose")
                # the touched radius once per pad: the kind and the line's nearness from it
                radii = [touched_radius(spec, tuple(tr[p]["object_point"])) if p in tr else None
                         for p in PADS]  # fmt: skip
                truth = tuple(None if r is None else kind_at(r) for r in radii)
                near = tuple(r is not None and radius_near_the_line(r) for r in radii)
                case.steps.append(
                    Step(
                        obs,
                        m1,
                        m2,
                        it["strokes"],
                        it["half_strokes"],
                        None if pose is None else pose[2],
                        truth,
                        near,
                    )
                )
            yield case


def run(case: Case, ctx: ModelContext, model: RecognitionModel) -> list[Recognition]:
    rec = Recognizer(ctx, model)
    return [rec.update(s.obs, s.m1, s.m2) for s in case.steps]


def judge(case: Case, recs: list[Recognition]) -> dict[str, Any]:
    """The case's scores (see the module docstring)."""
    kinds_ok = kinds_n = kinds_near_line = 0
    confusion: dict[str, int] = {}
    radius_err: list[float] = []
    for s, r in zip(case.steps, recs, strict=True):
        if s.obs.Lambda is None:
            continue
        for truth, near, kind, radius in (
            (s.truth[0], s.near_line[0], r.kind1, r.radius1),
            (s.truth[1], s.near_line[1], r.kind2, r.radius2),
        ):
            if truth is None or kind is None:
                continue
            kinds_n += 1
            kinds_ok += kind is truth[0]
            # an edge read as a curve or the reverse, where the radius is near the line
            kinds_near_line += (
                near and kind is not truth[0] and ContactKind.FLAT not in (kind, truth[0])
            )
            key = f"{truth[0].value}->{kind.value}"
            confusion[key] = confusion.get(key, 0) + 1
            if truth[0] is ContactKind.CURVED and kind is ContactKind.CURVED:
                assert truth[1] is not None and radius is not None
                radius_err.append(radius / truth[1] - 1.0)
    cls = true_class(case.family, case.spec)
    first = next((r for s, r in zip(case.steps, recs, strict=True) if s.strokes >= 1), None)
    end = recs[-1] if recs else None
    # rotation: from the first iteration with both contacts
    both = [(s, r) for s, r in zip(case.steps, recs, strict=True) if s.psi is not None]
    rot: dict[str, Any] = {}
    if both and any(s.obs.Lambda is not None for s, _ in both):
        i0 = next(i for i, (s, _) in enumerate(both) if s.obs.Lambda is not None)
        psi0, est0 = both[i0][0].psi, both[i0][1].rotation
        assert psi0 is not None
        t = np.degrees([s.psi - psi0 for s, _ in both[i0:]])  # type: ignore[operator]
        e = np.array([r.rotation - est0 for _, r in both[i0:]])
        true_range = float(t.max() - t.min())
        rot = {
            "true_range_deg": true_range,
            "est_range_deg": float(e.max() - e.min()),
            "rms_err_deg": float(np.sqrt(np.mean((e - t) ** 2))),
            "max_err_deg": float(np.max(np.abs(e - t))),
        }
        # at every half stroke's end: the turn since the one before
        ends = [
            i
            for i in range(1, len(both) - i0)
            if both[i0 + i][0].half_strokes != both[i0 + i - 1][0].half_strokes
        ]
        marks = [0, *ends]
        rot["half_strokes"] = [
            (float(t[b] - t[a]), float(e[b] - e[a])) for a, b in itertools.pairwise(marks)
        ]
    return {
        "id": case.id,
        "family": case.family,
        "class": cls.value,
        "sizes": true_sizes(case.spec),
        "class_first_stroke": first.object_class.value if first and first.object_class else None,
        "confidence_first_stroke": first.confidence if first else None,
        "class_end": end.object_class.value if end and end.object_class else None,
        "sizes_end": (end.size_a, end.size_b) if end else None,
        "strokes": max((s.strokes for s in case.steps), default=0),
        "kinds_ok": kinds_ok,
        "kinds_n": kinds_n,
        "kinds_near_line": kinds_near_line,
        "confusion": confusion,
        "radius_err": radius_err,
        "rotation": rot,
    }


def aggregate(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The suite's figures against the issue's targets."""
    stroked = [r for r in rows if r["strokes"] >= 1]
    cls_ok = sum(r["class_first_stroke"] == r["class"] for r in stroked)
    kinds_ok = sum(r["kinds_ok"] for r in rows)
    kinds_n = sum(r["kinds_n"] for r in rows)
    near_line = sum(r["kinds_near_line"] for r in rows)
    rad = np.abs(np.asarray([e for r in rows for e in r["radius_err"]], dtype=float))
    halves = [h for r in rows for h in r["rotation"].get("half_strokes", []) if abs(h[0]) >= 1.0]
    half_err = np.array([abs(e - t) / abs(t) for t, e in halves]) if halves else np.zeros(0)
    ranges = [
        (r["rotation"]["true_range_deg"], r["rotation"]["est_range_deg"])
        for r in rows
        if r["rotation"] and r["rotation"]["true_range_deg"] >= 1.0
    ]
    range_err = np.array([abs(e - t) / t for t, e in ranges]) if ranges else np.zeros(0)
    confusion: dict[str, int] = {}
    for r in rows:
        for k, v in r["confusion"].items():
            confusion[k] = confusion.get(k, 0) + v
    by_class: dict[str, list[int]] = {}
    for r in stroked:
        ok = by_class.setdefault(r["class"], [0, 0])
        ok[0] += r["class_first_stroke"] == r["class"]
        ok[1] += 1
    size_err: dict[str, list[float]] = {}
    for r in rows:  # the sizes at the run's end, where its class is right
        if r["class_end"] != r["class"] or not r["sizes_end"]:
            continue
        for name, want, got in zip(("a", "b"), r["sizes"], r["sizes_end"], strict=True):
            if want is not None and got is not None:
                size_err.setdefault(f"{r['class']} {name}", []).append(abs(got / want - 1.0))
    return {
        "cases": len(rows),
        "cases_with_a_stroke": len(stroked),
        "class_at_end": sum(r["class_end"] == r["class"] for r in rows) / max(1, len(rows)),
        "size_median_rel_err_where_class_right": {
            k: f"{np.median(v):.3f} (n={len(v)})" for k, v in sorted(size_err.items())
        },
        "class_after_first_stroke": cls_ok / max(1, len(stroked)),
        "class_by_true_class": {k: f"{a}/{b}" for k, (a, b) in sorted(by_class.items())},
        "contact_kind": kinds_ok / max(1, kinds_n),
        "contact_iterations": kinds_n,
        # the edge/curve mix-ups where the touched radius is within 20 % of the 4 mm line,
        # counted right: a secondary figure (the target is contact_kind)
        "contact_kind_near_line_forgiven": (kinds_ok + near_line) / max(1, kinds_n),
        "kind_confusion_truth_to_estimate": dict(sorted(confusion.items())),
        "radius_within_20pct": float(np.mean(rad <= 0.2)) if rad.size else None,
        "radius_median_abs_err": float(np.median(rad)) if rad.size else None,
        "radius_samples": int(rad.size),
        "rotation_half_strokes": len(halves),
        "rotation_half_stroke_within_20pct": float(np.mean(half_err <= 0.2)) if halves else None,
        "rotation_half_stroke_median_err": float(np.median(half_err)) if halves else None,
        "rotation_range_within_20pct": float(np.mean(range_err <= 0.2)) if ranges else None,
        "rotation_range_median_err": float(np.median(range_err)) if ranges else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+")
    ap.add_argument("--model", help="a model JSON file (default: the packaged one)")
    ap.add_argument("--json", help="write the per-case rows and the aggregate here")
    ap.add_argument("--cases", action="store_true", help="print one line per case")
    a = ap.parse_args()
    model = packaged_model()
    if a.model:
        model = RecognitionModel.load(json.loads(Path(a.model).read_text()))
    ctx = context()
    rows = []
    t0 = time.perf_counter()
    for path in a.captures:
        for case in load_cases(path, ctx):
            row = judge(case, run(case, ctx, model))
            rows.append(row)
            if a.cases:
                rot = row["rotation"]
                print(
                    f"{row['id']:28s} {row['class']:8s} → {row['class_first_stroke']!s:8s} "
                    f"/ {row['class_end']!s:8s} kinds {row['kinds_ok']}/{row['kinds_n']} "
                    f"rot {rot.get('true_range_deg', math.nan):5.1f} vs "
                    f"{rot.get('est_range_deg', math.nan):5.1f}"
                )
    agg = aggregate(rows)
    print(json.dumps(agg, indent=1))
    print(f"({time.perf_counter() - t0:.0f} s)")
    if a.json:
        Path(a.json).write_text(json.dumps({"aggregate": agg, "cases": rows}, indent=1))


if __name__ == "__main__":
    main()
