"""What the first stroke can tell at all: how many objects look like another class's.

The recognizer's class after the first stroke is judged against the object's family. This asks
the question below any estimator: of the surface the pads truly touched during the grasp and
the first stroke (the simulation's contact points on the object, and the pad's direction
there), how much could tell the object from one of another class? It uses the truth only,
never the tactile data, so it is what a perfect sensor and a perfect estimator would have.

* **A polygon that looks like a box.** A box (of any aspect ratio, the generator's boxes take
  every one) shows faces in two directions at right angles and corners it pivots on within a
  right angle. A polygon's first stroke is *box-like* when some orientation β makes every touched
  face's direction a multiple of 90° from β (within ``tol_deg``) and no pivot at a corner sweeps
  the pad across one of those directions (a box's corner turns the pad from one face's
  direction towards its neighbour's, never past one). A polygon is told from a box only by a
  touched pair of faces at another angle, or a corner whose pivot crosses a box direction (a
  regular odd polygon's corner opposite a face, pivoting both ways of parallel). This is the
  test behind :func:`sdh2svc.control.recognition.box_misfit`, but as a yes or no: *every* face
  within the tolerance (the recognizer's feature is the faces' mean distance, in degrees).
* **An ellipse that looks like a circle.** A circle's surface has one radius everywhere, and
  it is the radius of the circle through the touched points. An ellipse's first stroke is
  *circle-like* when its radius of curvature at the touched points varies by at most
  ``tol_radius`` (relative) and their median is within ``tol_radius`` of the radius of the
  circle fitted through them.

An estimator that sees only what was touched cannot call both the box-like polygons and the
boxes right (nor both the circle-like ellipses and the circles); with more boxes than box-like
polygons (and more circles than circle-like ellipses) in a suite, the best it can do is call
them all boxes (circles). So ``1 − (box-like polygons + circle-like ellipses) / runs`` bounds
the class's share right after the first stroke from above, even with every other class right.

    python -m experiments.recognition.identifiable /tmp/recog/test-17*.jsonl

With ``--misses EVAL_JSON`` (the file ``evaluate --json`` wrote for the same captures) it also
sorts the recognizer's misses after the first stroke: those read as the class the stroke looks
like, which no estimator at this resolution avoids, and the rest, by true class → estimate.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from experiments.recognition.truth import CORNER_MARGIN_MM, spec_of, true_class
from sdh2svc.config import load_config
from sdh2svc.control.recognition import ObjectClass, pad_normal_angle
from sdh2svc.model.geometry import x3_from_L
from sdh2svc.model.kinematics import Finger, HandPose
from sdh2svc.model.observe import ModelContext
from sdh2svc.sim.objects import Ellipse, Polygon, Shape

PADS = (("distal1", Finger.ONE), ("distal2", Finger.TWO))


@dataclass(frozen=True, slots=True)
class Touch:
    """One pad's true contact at one iteration: its point on the object (object frame) and the
    pad's surface direction there in the object frame (rad, modulo π)."""

    pad: str
    point: tuple[float, float]
    direction: float


def first_stroke(raw: dict[str, Any], ctx: ModelContext) -> list[list[Touch]] | None:
    """Every iteration's touches from the first up to the one that completes the first stroke
    (the recognizer's "after the first stroke"); None if the run never completed a stroke."""
    its = raw["iterations"]
    end = next((i for i, it in enumerate(its) if it["strokes"] >= 1), None)
    if end is None:
        return None
    out = []
    for it in its[: end + 1]:
        tr = it["truth"]
        pose = HandPose(*it["pose"])
        psi = tr["object_pose"][2] if "object_pose" in tr else None
        touches = []
        for pad, finger in PADS:
            if pad not in tr or psi is None:
                continue
            x3 = x3_from_L(tr[pad]["s_mm"], ctx.geom.pad)
            direction = (pad_normal_angle(finger, pose, x3, ctx) - psi) % math.pi
            touches.append(Touch(pad, tuple(tr[pad]["object_point"]), direction))
        out.append(touches)
    return out


def _feature(core: np.ndarray, p: tuple[float, float]) -> tuple[str, int]:
    """("face", i) on the open part of edge i (from corner i to i + 1), ("corner", k) within
    CORNER_MARGIN_MM of corner k (as the scoring's truth draws it)."""
    q = np.asarray(p, dtype=float)
    n = len(core)
    best = (math.inf, 0.0, 0, 0.0)
    for i in range(n):
        u, v = core[i], core[(i + 1) % n]
        e = v - u
        length = float(np.hypot(*e))
        t = float(np.clip((q - u) @ e / (e @ e), 0.0, 1.0))
        d = float(np.hypot(*(q - (u + t * e))))
        if d < best[0]:
            best = (d, t, i, length)
    _, t, i, length = best
    along = t * length
    if along <= CORNER_MARGIN_MM:
        return "corner", i
    if along >= length - CORNER_MARGIN_MM:
        return "corner", (i + 1) % n
    return "face", i


def _edge_direction(core: np.ndarray, i: int) -> float:
    u, v = core[i], core[(i + 1) % len(core)]
    return math.atan2(v[1] - u[1], v[0] - u[0]) % math.pi


def _off_grid(angle: float, beta: float) -> float:
    """How far (rad) ``angle`` is from the nearest of β + k·90°."""
    d = (angle - beta) % (math.pi / 2)
    return min(d, math.pi / 2 - d)


def _sweep_crosses(directions: Iterable[float], beta: float, tol: float) -> bool:
    """Whether a corner's pivot swept the pad across one of β + k·90° by more than ``tol`` on
    both sides (its directions in order; unwrapped modulo π)."""
    seq = np.unwrap(np.array(list(directions)) * 2) / 2  # modulo π, without jumps
    lo, hi = float(seq.min()), float(seq.max())
    k = math.ceil((lo + tol - beta) / (math.pi / 2))
    return beta + k * math.pi / 2 < hi - tol


def box_like(spec: Polygon, stroke: list[list[Touch]], tol_deg: float = 2.0) -> bool:
    """Whether a box could have shown what the polygon's first stroke showed (module docstring)."""
    core, _ = spec.outline()
    tol = math.radians(tol_deg)
    faces: set[int] = set()
    pivots: dict[tuple[str, int], list[float]] = {}
    for touches in stroke:
        for t in touches:
            kind, idx = _feature(core, t.point)
            if kind == "face":
                faces.add(idx)
            else:
                pivots.setdefault((t.pad, idx), []).append(t.direction)
    face_dirs = [_edge_direction(core, i) for i in faces]
    for beta in np.radians(np.arange(0.0, 90.0, 0.1)):
        if any(_off_grid(d, beta) > tol for d in face_dirs):
            continue
        if any(_sweep_crosses(dirs, beta, tol) for dirs in pivots.values() if len(dirs) > 1):
            continue
        return True
    return False


def _ellipse_radius(spec: Ellipse, p: tuple[float, float]) -> float:
    a, b = spec.axis_a_mm / 2, spec.axis_b_mm / 2
    t = math.atan2(p[1] / b, p[0] / a)
    return float((a * a * math.sin(t) ** 2 + b * b * math.cos(t) ** 2) ** 1.5 / (a * b))


def _circle_fit(points: np.ndarray) -> float:
    """The radius of the least-squares circle through ``points`` (Kåsa's algebraic fit)."""
    x, y = points[:, 0], points[:, 1]
    A = np.column_stack([2 * x, 2 * y, np.ones(len(x))])
    (cx, cy, c), *_ = np.linalg.lstsq(A, x * x + y * y, rcond=None)
    return float(math.sqrt(c + cx * cx + cy * cy))


def circle_like(spec: Ellipse, stroke: list[list[Touch]], tol_radius: float = 0.05) -> bool:
    """Whether a circle could have shown what the ellipse's first stroke showed: the radius of
    curvature the same at every touched point, and that of the circle through them, within
    ``tol_radius`` (relative)."""
    pts = np.array([t.point for touches in stroke for t in touches])
    if len(pts) < 3:
        return True  # nothing touched to tell a circle by
    radii = np.array([_ellipse_radius(spec, (float(x), float(y))) for x, y in pts])
    same = radii.max() / radii.min() - 1.0 <= tol_radius
    return bool(same and abs(float(np.median(radii)) / _circle_fit(pts) - 1.0) <= tol_radius)


def judge(
    raw: dict[str, Any], ctx: ModelContext, tol_deg: float, tol_radius: float
) -> dict[str, Any] | None:
    """A case's class and whether its first stroke looks like another class's (None: no
    first stroke, so it is not among the runs the class is judged on)."""
    stroke = first_stroke(raw, ctx)
    if stroke is None:
        return None
    spec: Shape = spec_of(raw)
    cls = true_class(raw["family"], spec)
    alike = None
    if isinstance(spec, Polygon) and cls is ObjectClass.POLYGON:
        alike = ObjectClass.BOX if box_like(spec, stroke, tol_deg) else None
    elif isinstance(spec, Ellipse):
        like = circle_like(spec, stroke, tol_radius)
        alike = ObjectClass.CIRCLE if like else None
    return {"id": raw["id"], "class": cls.value, "looks_like": alike and alike.value}


def cases(paths: Iterable[str]) -> Iterator[dict[str, Any]]:
    for path in paths:
        with Path(path).open() as fh:
            for line in fh:
                if line.strip():
                    yield json.loads(line)


def bound(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The suite's counts and the upper bound on the share of classes right (module docstring)."""
    n = len(rows)
    per: dict[str, int] = {}
    alike: dict[str, int] = {}
    for r in rows:
        per[r["class"]] = per.get(r["class"], 0) + 1
        if r["looks_like"]:
            alike[r["class"]] = alike.get(r["class"], 0) + 1
    lost = 0
    for cls, other in (("polygon", "box"), ("ellipse", "circle")):
        # a group the estimator cannot split: at best all called the larger class
        lost += min(alike.get(cls, 0), per.get(other, 0))
    return {"runs": n, "per_class": per, "looks_like_another": alike,
            "bound": (n - lost) / n if n else math.nan}  # fmt: skip


def misses(rows: list[dict[str, Any]], evaluated: dict[str, Any]) -> dict[str, Any]:
    """The recognizer's misses after the first stroke (``evaluated``: what
    :mod:`experiments.recognition.evaluate` writes with ``--json``), each beside its verdict
    here: *inherent* where it was read as the class its first stroke looks like (no estimator
    at this resolution reads both it and that class right), else counted by true class →
    estimate. Cases judged here but not evaluated (or the reverse) are left out."""
    alike = {r["id"]: r["looks_like"] for r in rows}
    listed: list[dict[str, Any]] = []
    other: dict[str, int] = {}
    inherent = 0
    for case in evaluated["cases"]:
        est = case.get("class_first_stroke")
        if est is None or case["id"] not in alike or est == case["class"]:
            continue
        looks = alike[case["id"]]
        listed.append({"id": case["id"], "class": case["class"], "estimate": est,
                       "looks_like": looks})  # fmt: skip
        if looks == est:
            inherent += 1
        else:
            key = f"{case['class']} -> {est}"
            other[key] = other.get(key, 0) + 1
    right_alike = sum(
        1 for c in evaluated["cases"]
        if alike.get(c["id"]) and c.get("class_first_stroke") == c["class"]
    )  # fmt: skip
    return {"misses": listed, "inherent": inherent, "look_alikes_read_right": right_alike,
            "other": dict(sorted(other.items(), key=lambda kv: -kv[1]))}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+", help="capture files (experiments.recognition.capture)")
    ap.add_argument("--tol-deg", type=float, default=2.0)
    ap.add_argument("--tol-radius", type=float, default=0.05)
    ap.add_argument("--list", action="store_true", help="print every case's verdict")
    ap.add_argument(
        "--misses", metavar="EVAL_JSON",
        help="the recognizer's misses after the first stroke, from evaluate's --json file, "
        "beside these verdicts",
    )  # fmt: skip
    a = ap.parse_args()
    ctx = load_config(use_env=False).model_context()
    rows = [r for raw in cases(a.captures)
            if (r := judge(raw, ctx, a.tol_deg, a.tol_radius)) is not None]  # fmt: skip
    if a.list:
        for r in rows:
            print(r["id"], r["class"], r["looks_like"] or "-")
    out = bound(rows)
    if a.misses:
        out["misses"] = misses(rows, json.loads(Path(a.misses).read_text()))
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
