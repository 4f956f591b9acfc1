"""Fit the recognizer's three small models on captured campaign cases, and ship them.

    python -m experiments.recognition.fit /tmp/recog/fit-*.jsonl

(the captures of :mod:`experiments.recognition.capture` for generator seeds 1701, 1703–1707
and 1711–1718, 840 cases; the held-out test suites are seeds 1702, 1709, 1710 and 1720). Writes
``sdh2svc/control/recognition_model.json``, its three models fitted in turn:

1. **contact kind** — a multinomial logistic model on each contact's features
   (:func:`~sdh2svc.control.recognition.contact_features`, with their pairwise products),
   labelled by the truth (:func:`experiments.recognition.truth.feature`) at every second
   iteration with both contacts;
2. **radius** — a linear model (the first RADIUS_FEATURES of them, and their pairwise products:
   all but the recent change and trend) of log(true radius /
   kinematic radius) where the truth and model 1 both say curved, fitted robustly (Huber's
   loss on the log ratio: the target counts radii within 20 %, so the bulk matters and not the
   outliers); its Huber width and L2 penalty chosen by 5-fold cross-validation by case
   (:func:`choose_radius`);
3. **object class** — a multinomial logistic model on the run's evidence
   (:func:`~sdh2svc.control.recognition.class_features`, with their pairwise products) as
   the recognizer with models 1 and 2 has gathered it at the end of every half stroke, of the first
   full stroke and of the run, labelled by the case's family
   (:func:`experiments.recognition.truth.true_class`); its L2 penalty chosen by 5-fold
   cross-validation by case on the fit suites: the least log loss of the first full stroke's
   class, so that its confidence is honest as well as its choice (:func:`choose_l2`).

``--class-only`` refits model 3 alone, on models 1 and 2 as the packaged file has them (a
change to the class's evidence needs no 30-minute refit of the contact kind).

1 and 3 are fitted by L-BFGS on the cross-entropy with an L2 penalty, 2 by iteratively
reweighted least squares; the features are standardised over the fit set. Deterministic: the
same captures give the same file.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

from experiments.recognition.evaluate import Case, context, load_cases
from experiments.recognition.truth import true_class
from sdh2svc.control.recognition import (
    CLASSES,
    KINDS,
    RADIUS_FEATURES,
    ContactKind,
    Linear,
    RecognitionModel,
    Recognizer,
    Softmax,
    _ContactTrack,
    class_features,
    contact_features,
    expand,
    packaged_model,
)

OUT = Path(__file__).resolve().parents[2] / "sdh2svc" / "control" / "recognition_model.json"
# fitted on seeds 1701, 1704–1707, 1711, 1712 and scored on 1703: 3e-3 and 0.01 alike, 0.03 worse
L2_KIND = 0.01
L2_CLASS_GRID = (0.001, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0)  # ascending: ties go to the stronger
FOLDS = 5
RADIUS_GRID = tuple((d, l2) for d in (0.03, 0.05, 0.1) for l2 in (3.0, 10.0, 30.0))
EVERY = 2  # iterations between kind and radius samples


def _standardised(F: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The features' means and scales over the fit set, and the features standardised (in
    ``F``'s place: the kind model's expanded samples take gigabytes)."""
    mean = F.mean(axis=0)
    var = np.zeros_like(mean)
    for i in range(0, len(F), _BLOCK):  # F.std's temporaries would double F
        F[i : i + _BLOCK] -= mean
        var += np.square(F[i : i + _BLOCK]).sum(axis=0)
    scale = np.sqrt(var / len(F)) + 1e-9
    F /= scale
    return mean, scale, F


_BLOCK = 20_000  # rows at a time through the large arrays


def _expanded(X: np.ndarray, rows: int = _BLOCK) -> np.ndarray:
    """``expand(X)`` a block of rows at a time, into one array (whole, its temporaries would
    take four times its size)."""
    out = np.empty((len(X), expand(X[:1]).shape[1]))
    for i in range(0, len(X), rows):
        out[i : i + rows] = expand(X[i : i + rows])
    return out


def fit_softmax(X: np.ndarray, y: np.ndarray, k: int, l2: float, quadratic: bool) -> Softmax:
    """Multinomial logistic regression (L-BFGS, L2 on the weights)."""
    mean, scale, Z = _standardised(_expanded(X) if quadratic else X.astype(float))
    n, f = Z.shape
    Y = np.eye(k)[y]

    def loss(w: np.ndarray) -> tuple[float, np.ndarray]:
        W, b = w[: k * f].reshape(k, f), w[k * f :]
        S = Z @ W.T + b
        S -= S.max(axis=1, keepdims=True)
        P = np.exp(S)
        P /= P.sum(axis=1, keepdims=True)
        value = -float(np.mean(np.log(P[np.arange(n), y] + 1e-12))) + l2 * float(np.sum(W * W))
        G = (P - Y) / n
        return value, np.concatenate([(G.T @ Z + 2 * l2 * W).ravel(), G.sum(axis=0)])

    res = minimize(
        loss, np.zeros(k * f + k), jac=True, method="L-BFGS-B", options={"maxiter": 1000}
    )
    W, b = res.x[: k * f].reshape(k, f), res.x[k * f :]
    return Softmax(mean, scale, W, b, quadratic)


def fit_huber(X: np.ndarray, y: np.ndarray, l2: float, delta: float) -> Linear:
    """Ridge regression with Huber's loss (width ``delta``) by iteratively reweighted least
    squares, on the features and their pairwise products."""
    mean, scale, Z = _standardised(_expanded(X))
    w: np.ndarray = np.zeros(Z.shape[1])
    bias, weight = float(np.mean(y)), np.ones(len(y))
    for _ in range(8):
        bias = float(np.average(y, weights=weight))
        Zw = Z * weight[:, None]
        w = np.linalg.solve(Z.T @ Zw + l2 * np.eye(Z.shape[1]), Zw.T @ (y - bias))
        r = np.abs(Z @ w + bias - y)
        weight = np.where(r <= delta, 1.0, delta / np.maximum(r, 1e-12))
    return Linear(mean, scale, w, np.asarray(bias), quadratic=True)


def replay(
    cases: list[Case], model: RecognitionModel, visit: Callable[[Case, int, Recognizer], None]
) -> None:
    ctx = context()
    for case in cases:
        rec = Recognizer(ctx, model)
        for i, s in enumerate(case.steps):
            rec.update(s.obs, s.m1, s.m2)
            visit(case, i, rec)


def _contacts(
    case: Case, i: int, rec: Recognizer
) -> Iterator[tuple[tuple[ContactKind, float | None], np.ndarray, _ContactTrack]]:
    """At every EVERY-th iteration with both contacts tracked: each contact with a truth, its
    features (:func:`contact_features`) and its track."""
    s = case.steps[i]
    t1, t2 = rec._tracks
    lam = s.obs.Lambda
    if i % EVERY or lam is None or t1.features is None or t2.features is None:
        return
    for truth, me, other in ((s.truth[0], t1, t2), (s.truth[1], t2, t1)):
        if truth is not None:
            assert me.features is not None and other.features is not None
            yield truth, contact_features(me.features, other.features, lam), me


def kind_samples(cases: list[Case], model: RecognitionModel) -> tuple[np.ndarray, np.ndarray]:
    X: list[np.ndarray] = []
    y: list[int] = []

    def visit(case: Case, i: int, rec: Recognizer) -> None:
        for truth, x, _ in _contacts(case, i, rec):
            X.append(x)
            y.append(KINDS.index(truth[0]))

    replay(cases, model, visit)
    return np.asarray(X), np.asarray(y)


def radius_samples(
    cases: list[Case], model: RecognitionModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where the truth and the kind model both say curved: the contact's features, log(true
    radius / kinematic radius), and the sample's case."""
    X: list[np.ndarray] = []
    y: list[float] = []
    group: list[int] = []
    index = {id(case): i for i, case in enumerate(cases)}
    curved = KINDS.index(ContactKind.CURVED)

    def visit(case: Case, i: int, rec: Recognizer) -> None:
        for truth, x, me in _contacts(case, i, rec):
            if truth[0] is ContactKind.CURVED and me.p is not None and np.argmax(me.p) == curved:
                assert truth[1] is not None
                X.append(x[:RADIUS_FEATURES])
                y.append(math.log(truth[1] / me.kinematic_radius))
                group.append(index[id(case)])

    replay(cases, model, visit)
    return np.asarray(X), np.asarray(y), np.asarray(group)


def case_folds(group: np.ndarray) -> Iterator[np.ndarray]:
    """FOLDS test masks over the samples, each holding out whole cases (the same split for
    every call on the same ``group``)."""
    order = np.random.default_rng(0).permutation(np.unique(group))
    for fold in np.array_split(order, FOLDS):
        yield np.isin(group, fold)


def choose_radius(X: np.ndarray, y: np.ndarray, group: np.ndarray) -> tuple[float, float]:
    """The radius model's (Huber width, L2) by 5-fold cross-validation over cases: the most
    radii within 20 % of the truth (ties: the first in RADIUS_GRID)."""
    best = (-1.0, RADIUS_GRID[0])
    for delta, l2 in RADIUS_GRID:
        right = 0
        for test in case_folds(group):
            m = fit_huber(X[~test], y[~test], l2, delta)
            err = m.scores(X[test]) - y[test]
            right += int(np.sum(np.abs(np.exp(err) - 1.0) <= 0.2))
        acc = right / len(y)
        print(f"  radius Huber {delta:g}, L2 {l2:g}: {acc:.3f} within 20 % (5-fold by case)")
        if acc > best[0]:
            best = (acc, (delta, l2))
    return best[1]


def class_samples(
    cases: list[Case], model: RecognitionModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The class model's samples: the run's evidence at every half stroke's end, at the first
    full stroke's end (where the target is judged) and at the run's end; with each sample's
    case (for folds by case) and whether it is the first full stroke's."""
    X: list[np.ndarray] = []
    y: list[int] = []
    group: list[int] = []
    first: list[bool] = []
    index = {id(case): i for i, case in enumerate(cases)}

    def visit(case: Case, i: int, rec: Recognizer) -> None:
        steps = case.steps
        end = i == len(steps) - 1
        stroke = steps[i].strokes >= 1 and (i == 0 or steps[i - 1].strokes < 1)
        if rec._ev.n and (stroke or end or steps[i + 1].half_strokes != steps[i].half_strokes):
            X.append(class_features(rec._ev, rec.softness(), rec.open_sweeps()))
            y.append(CLASSES.index(true_class(case.family, case.spec)))
            group.append(index[id(case)])
            first.append(stroke)

    replay(cases, model, visit)
    return np.asarray(X), np.asarray(y), np.asarray(group), np.asarray(first)


def choose_l2(X: np.ndarray, y: np.ndarray, group: np.ndarray, first: np.ndarray) -> float:
    """The class model's L2 by 5-fold cross-validation over cases: the least log loss of the
    class at the first full stroke (ties: the stronger penalty). The share right is printed
    beside it; the log loss also judges the confidence, which the share right ignores."""
    best = (math.inf, 0.0)
    n = max(1, int(first.sum()))
    for l2 in L2_CLASS_GRID:
        right, loss = 0, 0.0
        for test in case_folds(group):
            m = fit_softmax(X[~test], y[~test], len(CLASSES), l2, quadratic=True)
            sel = test & first
            P = np.array([m.probabilities(x) for x in X[sel]]).reshape(-1, len(CLASSES))
            right += int(np.sum(P.argmax(axis=1) == y[sel]))
            loss -= float(np.sum(np.log(P[np.arange(len(P)), y[sel]] + 1e-12)))
        print(
            f"  class L2 {l2:g}: log loss {loss / n:.4f}, {right / n:.3f} right at the first "
            "stroke (5-fold by case)"
        )
        if loss / n <= best[0]:
            best = (loss / n, l2)
    return best[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("captures", nargs="+")
    ap.add_argument("--out", default=str(OUT))
    ap.add_argument(
        "--class-only", action="store_true",
        help="refit the object class only, on the packaged contact kind and radius models",
    )  # fmt: skip
    a = ap.parse_args()
    ctx = context()
    cases = [c for path in a.captures for c in load_cases(path, ctx)]
    print(f"{len(cases)} cases, {sum(len(c.steps) for c in cases)} iterations")
    with_kind = (
        replace(packaged_model(), object_class=None) if a.class_only else _kind_and_radius(cases)
    )
    X, y, group, first = class_samples(cases, with_kind)
    cls = fit_softmax(X, y, len(CLASSES), choose_l2(X, y, group, first), quadratic=True)
    acc = np.mean([np.argmax(cls.probabilities(x)) == t for x, t in zip(X, y, strict=True)])
    print(f"object class: {len(y)} samples, {acc:.3f} right on the fit set")
    data = {
        "_comment": "fitted by python -m experiments.recognition.fit (see its docstring)",
        **replace(with_kind, object_class=cls).dump(),
    }
    Path(a.out).write_text(json.dumps(data, indent=None, separators=(",", ":")) + "\n")
    print(f"wrote {a.out} ({Path(a.out).stat().st_size // 1024} KiB)")


def _kind_and_radius(cases: list[Case]) -> RecognitionModel:
    """Models 1 and 2, fitted in turn (the class model still unset)."""
    base = RecognitionModel()
    X, y = kind_samples(cases, base)
    kind = fit_softmax(X, y, len(KINDS), L2_KIND, quadratic=True)
    acc = np.mean([np.argmax(kind.probabilities(x)) == t for x, t in zip(X, y, strict=True)])
    print(f"contact kind: {len(y)} samples, {acc:.3f} right on the fit set")
    with_kind = replace(base, kind=kind)
    X, y, group = radius_samples(cases, with_kind)
    delta, l2 = choose_radius(X, y, group)
    radius = fit_huber(X, y, l2, delta)
    err = np.exp(radius.scores(X) - y) - 1.0
    print(
        f"radius: {len(y)} samples, {np.mean(np.abs(err) <= 0.2):.3f} within 20 % on the fit "
        f"set (kinematic alone {np.mean(np.abs(np.exp(-y) - 1.0) <= 0.2):.3f})"
    )
    return replace(with_kind, radius=radius)


if __name__ == "__main__":
    main()
