"""Recognition while rolling: the contact-kind and class estimators on hand-built traces, the
whole recognizer on fast simulated runs of the thesis's objects against their truth, and the
reconstructed outline."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from sdh2svc.config import Settings, default_config
from sdh2svc.control.recognition import (
    PROFILE,
    RADIUS_FEATURES,
    ContactKind,
    ObjectClass,
    Recognition,
    RecognitionModel,
    Recognizer,
    Softmax,
    _ContactTrack,
    _Evidence,
    _Line,
    box_misfit,
    caliper_slope,
    centre_side,
    class_features,
    classify,
    contact_features,
    ellipse_ab,
    ellipse_axes,
    outline,
    pressure_profile,
    sizes,
)
from sdh2svc.model.contact import NO_CONTACT, Blob, ContactEstimate
from sdh2svc.model.depth import NO_DEPTH
from sdh2svc.model.kinematics import Finger, HandPose, Point
from sdh2svc.model.observe import observe

MODEL = RecognitionModel()


def _C(L: float) -> ContactEstimate:
    """A contact at pad distance L (only L matters to the rules)."""
    blob = Blob(20.0, 8.0, 12, 0.01, 1.0, 0.1, 4, 6)
    return replace(NO_CONTACT, present=True, L_mm=L, S_mm=20.0, blobs=(blob,), n_cells=12)


_COUNTS = np.zeros((13, 6))  # a pad's counts: _C's blob, rows 4–6, in a hump
_COUNTS[4:7] = [[300.0], [600.0], [300.0]]


def trace(track: _ContactTrack, L: np.ndarray, rel: np.ndarray) -> list[ContactKind | None]:
    """Feed a track the pad distances L (mm) and the relative turns ν − ψ (rad); its labels."""
    out = []
    for x, y in zip(L, rel, strict=True):
        track.update(_C(float(x)), float(y), 0.0, _COUNTS)
        out.append(track.kind)
    return out


def rolling(finger: Finger, n: int, dL: float, radius: float | None) -> tuple[np.ndarray, ...]:
    """n iterations of a contact travelling dL per iteration on a face (radius None), pivoting
    on an edge (dL = 0, the pad turning 0.1° per iteration), or rolling on radius r."""
    sign = -1.0 if finger is Finger.ONE else 1.0
    L = 20.0 + dL * np.arange(n)
    if radius is None:
        rel = np.full(n, 0.3)
    elif radius == 0.0:
        rel = 0.3 + np.radians(0.1) * np.arange(n)
    else:
        rel = 0.3 + sign * (L - L[0]) / radius
    return L, rel


def _n_features() -> int:
    """contact_features' length: a track's features after a few iterations, twice."""
    track = _ContactTrack(Finger.ONE, MODEL)
    trace(track, *rolling(Finger.ONE, 5, 0.1, None))
    assert track.features is not None
    return len(contact_features(track.features, track.features, 40.0))


N_FEATURES = _n_features()


@pytest.mark.parametrize("finger", [Finger.ONE, Finger.TWO])
def test_a_box_turning_through_face_edge_face(finger: Finger) -> None:
    track = _ContactTrack(finger, MODEL)
    segments = [
        (rolling(finger, 60, 0.15, None), ContactKind.FLAT),
        (rolling(finger, 60, 0.0, 0.0), ContactKind.EDGE),
        (rolling(finger, 60, -0.15, None), ContactKind.FLAT),
    ]
    for (L, rel), want in segments:
        labels = trace(track, L, rel - rel[0] + (track.short.y[-1] if track.short.y else 0.3))
        # a window's lag at each change, then the segment's kind throughout
        assert labels[MODEL.window :] == [want] * (len(labels) - MODEL.window)
        assert track.radius is None


@pytest.mark.parametrize("finger", [Finger.ONE, Finger.TWO])
@pytest.mark.parametrize("radius", [8.0, 20.0, 34.0, 60.0])
def test_a_curved_contact_and_its_radius(finger: Finger, radius: float) -> None:
    track = _ContactTrack(finger, MODEL)
    labels = trace(track, *rolling(finger, 40, 0.12, radius))
    assert labels[-1] is ContactKind.CURVED
    assert track.radius == pytest.approx(radius, rel=0.01)


def evidence(
    kinds: list[tuple[ContactKind, ContactKind]],
    lam: float,
    radius: float | None = None,
    parallel: bool = True,
) -> _Evidence:
    ev = _Evidence()
    for k1, k2 in kinds:
        ev.n += 1
        ev.add_width(lam, 0.0)
        for k in (k1, k2):
            setattr(ev, k.value, getattr(ev, k.value) + 1)
            if k is ContactKind.CURVED:
                assert radius is not None
                ev.radii.add(radius / (lam / 2))
                ev.ab.add(ellipse_ab(radius, lam / 2))  # as Recognizer._gather
        if k1 is k2 is ContactKind.FLAT:
            ev.both_flat += 1
            ev.parallel += parallel
    return ev


F, E, C = ContactKind.FLAT, ContactKind.EDGE, ContactKind.CURVED


def test_the_class_of_a_box_a_circle_and_a_stick() -> None:
    box = classify(evidence([(F, F)] * 50 + [(F, E)] * 30, 60.5), MODEL)
    assert box[0] is ObjectClass.BOX and box[2] == pytest.approx(60.5)
    circle = classify(evidence([(C, C)] * 80, 68.0, radius=34.5), MODEL)
    assert circle[0] is ObjectClass.CIRCLE and circle[2] == pytest.approx(34.0)
    stick = classify(evidence([(E, E)] * 80, 98.5), MODEL)
    assert stick[0] is ObjectClass.STICK and stick[2] == pytest.approx(98.5)
    polygon = classify(evidence([(F, F)] * 40 + [(F, E)] * 40, 50.0, parallel=False), MODEL)
    assert polygon[0] is ObjectClass.POLYGON


@pytest.mark.parametrize(
    ("lam", "radius"),
    [(53.0, 19.5**2 / 26.5), (39.0, 26.5**2 / 19.5)],
    ids=["held-across-its-long-axis", "held-across-its-short-axis"],
)
def test_the_class_and_axes_of_an_ellipse(lam: float, radius: float) -> None:
    # an ellipse of semi-axes 26.5 and 19.5 held at the ends of one axis, never turned to the
    # other: the widths show one axis, the contacts' radius (b²/a or a²/b) the other
    ev = evidence([(C, C)] * 80, lam, radius=radius)
    got = classify(ev, MODEL)
    assert got[0] is ObjectClass.ELLIPSE
    assert got[2] == pytest.approx(26.5, rel=0.01) and got[3] == pytest.approx(19.5, rel=0.01)


def test_the_ellipses_axes_from_its_widths_and_its_curvature() -> None:
    """ρ·p³ = (ab)² at every point of an ellipse (ρ its radius of curvature, p its tangent's
    distance from the centre): with the widths seen over any turn that reaches one axis, the
    other follows; without a·b, the widths alone."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        b, a = sorted(rng.uniform(5.0, 60.0, 2))
        lo = rng.uniform(0.0, math.pi / 2)
        reach = rng.choice([0.0, math.pi / 2])  # the turn reaches the long axis or the short
        t = np.linspace(min(lo, reach), max(lo, reach), 50)  # the tangent's direction
        p = np.sqrt(a**2 * np.cos(t) ** 2 + b**2 * np.sin(t) ** 2)  # the half caliper width
        rho = (a * b) ** 2 / p**3
        ab = float(np.median([ellipse_ab(r, q) for r, q in zip(rho, p, strict=True)]))
        got = ellipse_axes(float(p.max()), float(p.min()), ab)
        assert got == pytest.approx((a, b), rel=1e-9)
    assert ellipse_axes(30.0, 20.0, None) == (30.0, 20.0)


def widths(lam: np.ndarray, psi: np.ndarray, wedge: np.ndarray | None = None) -> _Evidence:
    ev = _Evidence()
    wedge = np.zeros(psi.size) if wedge is None else wedge
    for w, p, a in zip(lam, psi, wedge, strict=True):
        ev.add_width(float(w), float(p), float(a))
    return ev


def test_the_caliper_slope_tells_a_box_from_a_circle() -> None:
    """Λ against ψ: a circle's width stays while it turns; a 60 × 22 box held across its long
    side and tipped onto its corners widens as a·cos ψ + b·sin ψ (relative slope ≈ b/a); an
    ellipse's as 2·√(a²cos²ψ + b²sin²ψ), flat at its axis."""
    psi = np.radians(np.linspace(0.0, 15.0, 120))
    assert caliper_slope(widths(np.full(psi.size, 68.0), psi)) == pytest.approx(0.0, abs=1e-9)
    box = 60.0 * np.cos(psi) + 22.0 * np.sin(psi)
    want = np.polyfit(psi, box, 1)[0] / box.mean()
    assert caliper_slope(widths(box, psi)) == pytest.approx(want, rel=1e-6)
    assert 0.2 < want < 22.0 / 60.0
    ellipse = 2 * np.hypot(26.5 * np.cos(psi), 19.5 * np.sin(psi))
    assert abs(caliper_slope(widths(ellipse, psi))) < 0.5 * want
    assert caliper_slope(widths(box[:2], psi[:2])) == 0.0  # too few to tell
    # the class model sees its size: the circle's far below the box's
    f_circle = class_features(widths(np.full(psi.size, 68.0), psi))
    f_box = class_features(widths(box, psi))
    assert f_box[13] > f_circle[13] + 2.0  # log |caliper slope|


def test_the_caliper_width_takes_the_pads_wedge_out() -> None:
    """A circle rolled between pads whose wedge opens from 0 to 20° touches them on a chord
    Λ = D·cos(w/2) that shrinks by 1.5 %: the caliper width D stays the diameter, so neither
    its slope nor its spread reads the wedge as the object's shape (Λ's would)."""
    psi = np.radians(np.linspace(0.0, 15.0, 120))
    wedge = np.radians(np.linspace(0.0, 20.0, 120))
    chord = 68.0 * np.cos(wedge / 2)
    ev = widths(chord, psi, wedge)
    assert caliper_slope(ev) == pytest.approx(0.0, abs=1e-9)
    assert ev.d_max - ev.d_min == pytest.approx(0.0, abs=1e-9)
    assert ev.lam_max - ev.lam_min == pytest.approx(68.0 * (1 - math.cos(math.radians(10))))
    assert sizes(ObjectClass.CIRCLE, ev)[0] == pytest.approx(34.0)  # not the mean chord's half
    seen_flat = class_features(widths(chord, psi))  # the same chords, the wedge not known
    assert class_features(ev)[13] < seen_flat[13] - 1.5  # log |caliper slope|
    assert class_features(ev)[9] < seen_flat[9] - 0.5  # log caliper spread


def outline_evidence(faces: list[float], sweeps: list[tuple[float, float]]) -> _Evidence:
    """Evidence whose touched outline shows these face directions and pivot sweeps (deg)."""
    ev = _Evidence()
    for d in faces:
        ev.add_face(d)
    for span in sweeps:
        ev.add_sweep(span)
    return ev


def test_the_touched_outline_tells_a_box_from_a_polygon() -> None:
    """A box's faces lie at right angles and its corners turn the pad within one: its misfit
    is the 1° bins' half degree whatever its orientation. An irregular polygon's faces at 36°
    do not fit a right angle; a regular pentagon's corner opposite a face, pivoting 20° either
    way of parallel, crosses a box direction (its faces alone fit one)."""
    for beta in (0.0, 17.0, 63.0):
        box = outline_evidence(
            [beta + 10] * 50 + [beta + 100] * 30, [(beta + 15, beta + 80), (beta - 75, beta - 20)]
        )
        assert box_misfit(box, []) == pytest.approx((0.5, 0.5))
    face, whole = box_misfit(outline_evidence([10.0] * 50 + [46.0] * 30, []), [])
    assert face == whole and 10.0 < face < 18.0
    face, whole = box_misfit(outline_evidence([0.0] * 50, [(-20.0, 20.0)]), [])
    assert face == pytest.approx(0.5) and whole == pytest.approx(19.5)
    # an edge run still open counts too, and leaves the evidence as it was
    ev = outline_evidence([0.0] * 50, [])
    assert box_misfit(ev, [(-20.0, 20.0)])[1] == pytest.approx(19.5)
    assert box_misfit(ev, []) == pytest.approx((0.5, 0.5))
    assert box_misfit(_Evidence(), []) == (0.0, 0.0)  # nothing touched yet


def test_the_windows_line_from_running_sums_matches_a_direct_fit() -> None:
    """Thousands of iterations through a 120-iteration window: the running sums' slope,
    travel, turn and residual stay those of a least-squares fit of the window itself."""
    rng = np.random.default_rng(3)
    line, xs, ys = _Line(120), [], []
    for k in range(3000):
        x = 20.0 + 5.0 * math.sin(k / 50) + rng.normal(0.0, 0.05)
        y = 0.3 + 0.1 * math.cos(k / 70) + rng.normal(0.0, 1e-3)
        line.add(x, y)
        xs.append(x)
        ys.append(y)
        if k % 97 or k < 3:
            continue
        X, Y = np.array(xs[-120:]), np.array(ys[-120:])
        slope, intercept = np.polyfit(X, Y, 1)
        resid = math.degrees(float(np.sqrt(np.mean((Y - slope * X - intercept) ** 2))))
        kappa, travel, turn, rms = line.fit()
        assert kappa == pytest.approx(slope, rel=1e-6, abs=1e-9)
        assert travel == pytest.approx(float(np.ptp(X)))
        assert turn == pytest.approx(math.degrees(float(np.ptp(Y))))
        assert rms == pytest.approx(resid, rel=1e-6, abs=1e-9)
    line.clear()
    line.add(1.0, 0.5)
    line.add(1.0, 0.6)  # no travel: no slope
    assert line.fit() == (0.0, 0.0, pytest.approx(math.degrees(0.1)), 0.0)


def test_the_windows_sums_made_anew_are_the_windows_own() -> None:
    """Every n additions the running sums are made anew, so that rounding never builds up:
    to the last bit the window's values (and their products) added up in order from the
    oldest — the first time for a window of one, after a clear as well."""
    import functools
    import operator

    def in_order(values: list[float]) -> float:
        return functools.reduce(operator.add, values, 0.0)

    rng = np.random.default_rng(5)
    n, made = 20, 0
    line = _Line(n)
    for k in range(500):
        if k == 250:
            line.clear()
        line.add(float(rng.normal(25.0, 4.0)), float(rng.normal(0.0, 0.2)))
        if line._since:  # not made anew this time
            continue
        made += 1
        xs, ys = list(line.x), list(line.y)
        assert line._sums == [
            in_order(xs), in_order(ys), in_order([a * a for a in xs]),
            in_order([a * b for a, b in zip(xs, ys, strict=True)]), in_order([b * b for b in ys]),
        ]  # fmt: skip
    assert made == 2 * (1 + (250 - 1) // n)  # at the first value, then every n, per start


def test_the_outline_misfit_keeps_the_finished_sweeps() -> None:
    """box_misfit keeps the finished sweeps' crossings until another sweep ends: asked between
    sweeps, with and without open ones, it says what evidence built afresh says."""
    spans = [(-20.0, 20.0), (30.0, 41.0), (50.0, 140.0), (100.0, 104.0)]
    ev = outline_evidence([3.0] * 10 + [95.0] * 5, [])
    for k, span in enumerate(spans):
        ev.add_sweep(span)
        fresh = outline_evidence([3.0] * 10 + [95.0] * 5, spans[: k + 1])
        for open_sweeps in ([], [(80.0, 92.0)], [(170.0, 185.0), (5.0, 8.0)]):
            assert box_misfit(ev, open_sweeps) == box_misfit(fresh, open_sweeps)
            assert box_misfit(ev, open_sweeps) == box_misfit(fresh, open_sweeps)  # kept
    faces = [3.0] * 10 + [95.0] * 5  # a sweep still open counts as a finished one would
    assert box_misfit(outline_evidence(faces, []), spans) == box_misfit(
        outline_evidence(faces, spans), []
    )


def test_the_window_breaks_where_a_face_gives_way_to_a_corner() -> None:
    """_Line.split: a window of a face (the contact travels, ν − ψ still) then a rounding of
    5 mm (ν − ψ turns 1/5 rad per mm) breaks at the change, and the later line is the
    rounding's alone; a window on one line barely gains from a break; the break is the one a
    brute-force search finds."""
    line = _Line(20)
    for k in range(14):  # the face
        line.add(20.0 + 0.15 * k, 0.3)
    for k in range(1, 7):  # the rounding
        line.add(20.0 + 0.15 * (13 + k), 0.3 + 0.15 * k / 5.0)
    gain, since, kappa, travel, turn = line.split()
    assert since in (6.0, 7.0)  # the face's last point is on the rounding's line too
    assert gain > 10.0  # two lines fit exactly, one leaves a bend
    assert kappa == pytest.approx(1 / 5.0)
    assert travel == pytest.approx(0.15 * (since - 1))
    assert turn == pytest.approx(math.degrees(travel / 5.0))

    def sse(x: np.ndarray, y: np.ndarray) -> float:
        return float(np.sum((y - np.polyval(np.polyfit(x, y, 1), x)) ** 2))

    rng = np.random.default_rng(5)
    x, y = 20.0 + rng.normal(0.0, 1.0, 20), rng.normal(0.0, 0.01, 20)
    line.clear()
    for a, b in zip(x, y, strict=True):
        line.add(float(a), float(b))
    gain, since, *_ = line.split()
    cut = min(range(3, 18), key=lambda k: sse(x[:k], y[:k]) + sse(x[k:], y[k:]))
    assert since == 20 - cut
    best = sse(x[:cut], y[:cut]) + sse(x[cut:], y[cut:])
    assert gain == pytest.approx(math.log((sse(x, y) + 1e-7) / (best + 1e-7)), rel=1e-6)
    assert gain < 1.5  # noise on one line: a break explains little
    line.clear()
    assert line.split() == (0.0, 0.0, 0.0, 0.0, 0.0)  # too few points to break


def test_the_footprint_trend_starts_anew_after_a_lost_contact() -> None:
    """A track's trend features: the footprint's change over the last few iterations, nil
    while it holds still, and forgotten when the contact is lost."""
    from sdh2svc.control.recognition import TREND_AT

    track = _ContactTrack(Finger.ONE, MODEL)
    trace(track, *rolling(Finger.ONE, 12, 0.1, None))
    assert track.features is not None
    assert track.features[TREND_AT:] == [0.0] * (len(track.features) - TREND_AT)
    wide = replace(_C(22.0), n_cells=30)
    track.update(wide, 0.3, 0.0, _COUNTS)
    assert track.features[TREND_AT + 2] == 18.0  # cells: 12 → 30, over the near span
    track.lost()
    for k in range(4):
        track.update(wide, 0.3, 0.0, _COUNTS)
        track.update(replace(wide, L_mm=22.0 + 0.1 * k), 0.3, 0.0, _COUNTS)
    assert track.features is not None and track.features[TREND_AT + 2] == 0.0


def test_many_samples_score_as_one_at_a_time() -> None:
    """The kind model scores both contacts in one product: row by row the same as alone."""
    rng = np.random.default_rng(4)
    n = 6
    model = Softmax(rng.normal(size=n + n * (n + 1) // 2), np.full(n + n * (n + 1) // 2, 2.0),
                    rng.normal(size=(3, n + n * (n + 1) // 2)), rng.normal(size=3),
                    quadratic=True)  # fmt: skip
    x = rng.normal(size=(2, n))
    both = model.probabilities(x)
    for row in range(2):
        assert both[row] == pytest.approx(model.probabilities(x[row]))
        assert both[row].sum() == pytest.approx(1.0)


def test_the_pressure_profile_along_the_pad() -> None:
    """A face pressed evenly loads its rows alike, a tilted one in a ramp, a curved surface in
    a hump; the profile does not depend on the pressure's scale."""

    def profile(rows: list[float]) -> tuple[float, ...]:
        counts = np.zeros((13, 6))
        counts[3 : 3 + len(rows)] = np.asarray(rows)[:, None]
        return pressure_profile(counts, 3, 2 + len(rows))

    even, ramp, hump = (
        profile([400.0] * 7),
        profile([100.0 * i for i in range(1, 8)]),
        profile([100.0, 400.0, 700.0, 800.0, 700.0, 400.0, 100.0]),
    )
    peak_mean, skew, kurt, ends, spread, line = range(PROFILE)
    assert even[peak_mean] == pytest.approx(1.0) and even[ends] == pytest.approx(1.0)
    assert even[skew] == pytest.approx(0.0, abs=1e-9) and even[line] == pytest.approx(0.0)
    assert ramp[skew] > 0.2 and ramp[line] == pytest.approx(0.0, abs=1e-9)
    assert hump[peak_mean] > 1.5 and hump[ends] < 0.2 and hump[line] > 0.2
    assert hump[kurt] > even[kurt] and hump[spread] < even[spread]
    assert profile([40.0, 80.0, 70.0]) == pytest.approx(profile([400.0, 800.0, 700.0]))
    assert profile([500.0]) == (1.0, 0.0, 0.0, 0.0, 0.0, 0.0)  # one row: no shape


def test_a_soft_object_reads_soft() -> None:
    """The rubber's compression at a given force: a rigid object presses it as Hertz says
    (∝ F^⅔), a soft one takes part of the squeeze."""
    out = {}
    for name, compression in (("rigid", 0.8), ("foam", 0.2)):
        track = _ContactTrack(Finger.TWO, MODEL)
        for i, force in enumerate((1.0, 2.0, 4.0)):
            c = compression * force ** (2 / 3)
            depth = replace(NO_DEPTH, compression_mm=c)
            track.update(replace(_C(20.0 + i), force=force, depth=depth), 0.3, 0.0, _COUNTS)
        out[name] = track.softness
    assert out["rigid"] == pytest.approx(math.log(0.8), abs=0.02)
    assert out["foam"] < out["rigid"] - 1.0


@pytest.mark.parametrize(
    ("cls", "a", "b"),
    [
        (ObjectClass.CIRCLE, 34.0, None),
        (ObjectClass.ELLIPSE, 26.5, 19.5),
        (ObjectClass.BOX, 60.5, 22.0),
        (ObjectClass.STICK, 98.5, 2.0),
        (ObjectClass.POLYGON, 30.0, 30.0),
    ],
)
@pytest.mark.parametrize("turn", [0.0, 17.0])
def test_the_outline_touches_both_contacts(
    cls: ObjectClass, a: float, b: float | None, turn: float
) -> None:
    rec = Recognition(object_class=cls, size_a=a, size_b=b, rotation=turn, axis=3.0)
    A, B = (10.0, 120.0), (10.0 + 2 * a * 0.9 * math.cos(0.05), 120.0 + 2 * a * 0.9 * 0.05)
    if cls in (ObjectClass.BOX, ObjectClass.STICK):
        B = (10.0 + a * 0.95, 121.0)
    pts = outline(rec, A, B, n=400)
    assert pts.shape == (400, 2)
    for p in (A, B):
        assert float(np.min(np.hypot(*(pts - np.asarray(p)).T))) < 0.5


@pytest.mark.parametrize("c", [12.0, -12.0, 0.0])
def test_the_outline_lies_on_the_side_the_pads_normals_tell(c: float) -> None:
    """A circle (r 30 mm) held on a chord c off its centre: the pads' surfaces at the chord's
    ends tilt towards the centre, which tells its side of AB; the outline is drawn around the
    true centre, not its mirror across AB (on a centred chord the pads do not tell; the
    outline's centre is then on AB)."""
    r, z = 30.0, 100.0
    h = math.sqrt(r * r - c * c)
    A, B, centre = Point(-h, z), Point(h, z), np.array([0.0, z + c])
    nus = [math.atan2(-(p.y - centre[0]), p.z - centre[1]) for p in (A, B)]  # tangents
    side = centre_side(A, B, *nus)
    assert side == (0 if c == 0 else 1 if c > 0 else -1)  # +1: left of A→B (here +z)
    rec = Recognition(object_class=ObjectClass.CIRCLE, size_a=r, axis=0.0, side=side)
    pts = outline(rec, (A.y, A.z), (B.y, B.z), n=400)
    assert np.hypot(*(pts.mean(axis=0) - centre)) < 0.5
    if side:  # told the other side, it is drawn mirrored across AB: the side is what decides
        mirrored = outline(replace(rec, side=-side), (A.y, A.z), (B.y, B.z), n=400)
        mirror = centre - [0.0, 2 * c]  # the centre reflected across AB
        assert np.hypot(*(mirrored.mean(axis=0) - mirror)) < 0.5


def test_a_box_is_drawn_on_the_chord_through_its_centre() -> None:
    """Flat faces held parallel do not tell which side of AB the box's centre is: the outline
    is centred on AB (not on either chord of Λ's length, which flipped from side to side)."""
    A, B = (0.0, 100.0), (40.0, 100.0)
    for turn in (0.0, 10.0, -10.0):
        rec = Recognition(object_class=ObjectClass.BOX, size_a=40.0, rotation=turn, axis=0.0)
        pts = outline(rec, A, B, n=400)
        assert abs(float(pts.mean(axis=0)[1]) - 100.0) < 0.5


def test_no_outline_before_a_class() -> None:
    assert outline(Recognition(), (0.0, 100.0), (50.0, 100.0)).shape == (0, 2)


def test_the_packaged_model_loads(cfg: Settings) -> None:
    from sdh2svc.control.recognition import packaged_model

    model = packaged_model()
    assert isinstance(model, RecognitionModel)
    assert model.kind is not None and model.radius is not None and model.object_class is not None
    again = RecognitionModel.load(json.loads(json.dumps(model.dump())))  # a JSON round trip
    x = np.linspace(-1.0, 2.0, RADIUS_FEATURES)
    assert again.kind is not None and model.kind is not None
    xk = np.linspace(-1.0, 2.0, N_FEATURES)
    assert np.array_equal(again.kind.probabilities(xk), model.kind.probabilities(xk))
    assert again.radius is not None
    assert again.radius.predict(x) == model.radius.predict(x)


def test_the_radius_model_scales_the_kinematic_radius() -> None:
    """A curved contact's radius is the kinematic one times exp(the model's log ratio)."""
    from sdh2svc.control.recognition import Linear

    n = RADIUS_FEATURES
    lin = Linear(np.zeros(n), np.ones(n), np.zeros(n), np.asarray(math.log(0.8)))
    track = _ContactTrack(Finger.ONE, MODEL)
    track.kinematic_radius = 50.0
    rec = Recognizer(default_config().model_context(), replace(MODEL, radius=lin))
    assert rec._radius(track, np.zeros(n)) == pytest.approx(40.0)
    assert Recognizer(default_config().model_context(), MODEL)._radius(track, np.zeros(n)) == 50.0
    # far outside the fit suites (a real pad's odd reading): bounded, never an overflow
    wild = Linear(np.zeros(n), np.ones(n), np.zeros(n), np.asarray(800.0))
    rec = Recognizer(default_config().model_context(), replace(MODEL, radius=wild))
    assert rec._radius(track, np.zeros(n)) == pytest.approx(500.0)


def test_the_truth_draws_one_line_between_edge_and_curve() -> None:
    """The scoring's truth: a rounding, a stick's end and an ellipse's tip sharper than
    EDGE_RADIUS_MM are edges; blunter ones curved, with their radius."""
    from experiments.recognition.truth import EDGE_RADIUS_MM, feature, near_the_line, touched_radius
    from sdh2svc.sim.objects import Box, Ellipse, Stick

    r = EDGE_RADIUS_MM
    slender = Ellipse(axis_a_mm=40.0, axis_b_mm=12.0, depth_mm=10.0)  # tip radius 1.8 mm
    assert feature(slender, (20.0, 0.0)) == (ContactKind.EDGE, None)
    assert touched_radius(slender, (20.0, 0.0)) == pytest.approx(1.8, rel=1e-3)
    assert not near_the_line(slender, (20.0, 0.0))
    kind, radius = feature(slender, (0.0, 6.0))  # its side: radius 20²/6 ≈ 67 mm
    assert kind is ContactKind.CURVED and radius == pytest.approx(400.0 / 6.0, rel=1e-3)
    blunt = Ellipse(axis_a_mm=40.0, axis_b_mm=30.0, depth_mm=10.0)  # tip radius 11.25 mm
    kind, radius = feature(blunt, (20.0, 0.0))
    assert kind is ContactKind.CURVED and radius == pytest.approx(15.0**2 / 20.0, rel=1e-3)
    for d, want in ((2 * r - 1.0, ContactKind.EDGE), (2 * r + 1.0, ContactKind.CURVED)):
        stick = Stick(length_mm=60.0, diameter_mm=d, depth_mm=10.0)
        assert feature(stick, (30.0, 0.0))[0] is want
        box = Box(width_mm=40.0, height_mm=30.0, corner_radius_mm=d / 2, depth_mm=10.0)
        corner = (20.0 - d / 2 * (1 - math.sqrt(0.5)), 15.0 - d / 2 * (1 - math.sqrt(0.5)))
        assert feature(box, corner)[0] is want
        # within 20 % of the line either side: where the scoring forgives an edge/curve mix-up
        assert near_the_line(stick, (30.0, 0.0)) and near_the_line(box, corner)
    assert (
        touched_radius(Box(width_mm=40.0, height_mm=30.0, depth_mm=10.0), (0.0, 15.0)) == math.inf
    )
    assert not near_the_line(Stick(length_mm=60.0, diameter_mm=6.0, depth_mm=10.0), (30.0, 0.0))


def test_the_truth_classes_a_shape_by_its_shape_not_its_family() -> None:
    """A polygon whose four corners are right angles (the polygon family's regular 4-gons are
    squares) is a box, with a box's sides; one corner 3° off, or a fifth corner, is a polygon."""
    from experiments.recognition.truth import true_class, true_sizes
    from sdh2svc.sim.objects import Box, Polygon

    c, s = math.cos(0.4), math.sin(0.4)
    square = Polygon(depth_mm=10.0, vertices_mm=tuple(
        (round(20 * (x * c - y * s), 3), round(20 * (x * s + y * c), 3))
        for x, y in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ))  # fmt: skip
    assert true_class("polygon", square) is ObjectClass.BOX
    assert true_sizes(square) == pytest.approx((40.0, 40.0), abs=1e-3)
    rect = Polygon(depth_mm=10.0, vertices_mm=((0, 0), (50, 0), (50, 20), (0, 20)))
    assert true_class("polygon", rect) is ObjectClass.BOX
    assert true_sizes(rect) == pytest.approx((50.0, 20.0))
    lean = 20 * math.tan(math.radians(3))  # two corners 3° off a right angle
    tilted = Polygon(depth_mm=10.0, vertices_mm=((0, 0), (50, 0), (50 + lean, 20), (0, 20)))
    assert true_class("polygon", tilted) is ObjectClass.POLYGON
    pentagon = Polygon(depth_mm=10.0, vertices_mm=((0, 0), (50, 0), (50, 20), (25, 30), (0, 20)))
    assert true_class("polygon", pentagon) is ObjectClass.POLYGON
    assert true_class("box", Box(width_mm=40.0, height_mm=30.0, depth_mm=10.0)) is ObjectClass.BOX
    assert true_class("rounded", Box(width_mm=40.0, height_mm=30.0, corner_radius_mm=8.0,
                                     depth_mm=10.0)) is ObjectClass.BOX  # fmt: skip


# --- fast simulated runs of the thesis's objects (200 iterations each), against their truth


@pytest.fixture(scope="module")
def thesis_runs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, list[tuple[Any, ...]]]:
    """rubber, egg and cylinder, 200 iterations each (two half strokes and more), run as a
    campaign runs them: every iteration's observation, matrices, true ψ and truth per pad."""
    from experiments.recognition.capture import capture_case
    from experiments.recognition.truth import feature, spec_of
    from sdh2svc.campaign.case import load_suite

    ctx = default_config().model_context()
    suite = {c.id: c for c in load_suite("thesis").cases}
    out: dict[str, list[tuple[Any, ...]]] = {}
    for name in ("rubber", "egg", "cylinder"):
        raw = capture_case(suite[name], tmp_path_factory.mktemp(name), [], max_iterations=200)
        spec = spec_of(raw)
        rows = []
        for it in raw["iterations"]:
            m1, m2 = np.asarray(it["m1"]), np.asarray(it["m2"])
            tr = it["truth"]
            truth = [
                feature(spec, tuple(tr[p]["object_point"])) if p in tr else None
                for p in ("distal1", "distal2")
            ]
            obs = observe(HandPose(*it["pose"]), m1, m2, ctx)
            rows.append((obs, m1, m2, tr["object_pose"][2], truth))
        out[name] = rows
    return out


def recognise(rows: list[tuple[Any, ...]]) -> tuple[Recognizer, list[Recognition]]:
    rec = Recognizer(default_config().model_context())
    return rec, [rec.update(obs, m1, m2) for obs, m1, m2, *_ in rows]


@pytest.mark.parametrize("name", ["rubber", "egg", "cylinder"])
def test_the_rotation_follows_the_true_rotation(thesis_runs: dict[str, Any], name: str) -> None:
    rows = thesis_runs[name]
    _, recs = recognise(rows)
    both = [i for i, r in enumerate(rows) if r[0].Lambda is not None]
    i0 = both[0]
    true = np.degrees([rows[i][3] - rows[i0][3] for i in both])
    est = np.array([recs[i].rotation - recs[i0].rotation for i in both])
    span = float(true.max() - true.min())
    assert span > 5.0  # the stroke turned it
    assert abs(float(est.max() - est.min()) - span) <= 0.2 * span
    assert float(np.max(np.abs(est - true))) <= 0.2 * span


@pytest.mark.parametrize(("name", "share"), [("egg", 0.9), ("cylinder", 0.8)])
def test_the_egg_and_the_cylinder_roll_on_curved_contacts(
    thesis_runs: dict[str, Any], name: str, share: float
) -> None:
    """Mostly curved contacts (the foam cylinder's soft face reads flat at times), and the
    radius of curvature within 20 % of the truth's (median over the iterations)."""
    rows = thesis_runs[name]
    _, recs = recognise(rows)
    kinds = [k for r in recs for k in (r.kind1, r.kind2) if k is not None]
    assert kinds.count(ContactKind.CURVED) >= share * len(kinds)
    for pad in (0, 1):
        got = [
            ((r.radius1, r.radius2)[pad], t[pad][1])
            for r, (*_, t) in zip(recs, rows, strict=True)
            if (r.radius1, r.radius2)[pad] is not None and t[pad] is not None
        ]
        assert len(got) > 100
        assert np.median([g / want for g, want in got]) == pytest.approx(1.0, abs=0.2)


def test_the_eggs_short_axis_from_its_curvature(thesis_runs: dict[str, Any]) -> None:
    """The egg (semi-axes 26.5 and 19.5 mm) is held across its long axis and one stroke never
    turns it across its short one: the widths alone put b at ≈ 26 mm (half the narrowest seen);
    with a·b from the curved contacts, both axes come within 5 %."""
    _, recs = recognise(thesis_runs["egg"])
    end = recs[-1]
    assert end.object_class is ObjectClass.ELLIPSE
    assert end.size_a == pytest.approx(26.5, rel=0.05)
    assert end.size_b == pytest.approx(19.5, rel=0.05)


@pytest.mark.parametrize("name", ["egg", "cylinder"])
def test_the_radius_model_brings_the_radius_nearer_the_truth(
    thesis_runs: dict[str, Any], name: str
) -> None:
    """The reported radius (kinematic × the radius model's correction) is within 20 % of the
    truth at least as often as the kinematic radius alone (objects outside the fit suites)."""
    rec = Recognizer(default_config().model_context())
    near = {"reported": 0, "kinematic": 0}
    for obs, m1, m2, _, truth in thesis_runs[name]:
        r = rec.update(obs, m1, m2)
        for reported, track, t in zip((r.radius1, r.radius2), rec._tracks, truth, strict=True):
            if reported is None or t is None or t[0] is not ContactKind.CURVED:
                continue
            near["reported"] += abs(reported / t[1] - 1.0) <= 0.2
            near["kinematic"] += abs(track.kinematic_radius / t[1] - 1.0) <= 0.2
    assert near["reported"] > 100
    assert near["reported"] >= near["kinematic"]


def test_the_rubber_shows_flat_faces_and_edges(thesis_runs: dict[str, Any]) -> None:
    """The rubber rolls over its edges: flat and edge contacts, and most iterations right."""
    rows = thesis_runs["rubber"]
    _, recs = recognise(rows)
    pairs = [
        (k, t[0])
        for r, (*_, tt) in zip(recs, rows, strict=True)
        for k, t in ((r.kind1, tt[0]), (r.kind2, tt[1]))
        if k is not None and t is not None
    ]
    assert {ContactKind.FLAT, ContactKind.EDGE} <= {k for k, _ in pairs}
    assert sum(k is t for k, t in pairs) >= 0.75 * len(pairs)


@pytest.mark.parametrize("name", ["rubber", "egg", "cylinder"])
def test_the_live_outline_touches_the_contacts(thesis_runs: dict[str, Any], name: str) -> None:
    rows = thesis_runs[name]
    _, recs = recognise(rows)
    obs, rec = rows[-1][0], recs[-1]
    assert rec.object_class is not None and obs.points is not None
    pts = outline(rec, obs.points.A, obs.points.B, n=400)
    assert pts.shape == (400, 2)
    for p in (obs.points.A, obs.points.B):
        assert float(np.min(np.hypot(*(pts - np.asarray(p)).T))) < 0.5


def test_the_summary_is_json(thesis_runs: dict[str, Any]) -> None:
    rec, recs = recognise(thesis_runs["egg"])
    s = json.loads(json.dumps(rec.summary()))
    assert s["object_class"] == recs[-1].object_class
    assert s["rotation_deg"] == pytest.approx(recs[-1].rotation)
    assert 0.0 <= s["confidence"] <= 1.0


def test_importing_the_recognizer_loads_neither_config_nor_sim() -> None:
    code = (
        "import sys, sdh2svc.control.recognition as r\n"
        "r.packaged_model()\n"
        "bad = [m for m in sys.modules if m.startswith('sdh2svc.sim') or m == 'sdh2svc.config']\n"
        "assert not bad, sorted(bad)\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True)


@pytest.mark.parametrize("name", ["rubber", "egg", "cylinder"])
def test_no_class_before_the_object_has_turned_two_degrees(
    thesis_runs: dict[str, Any], name: str
) -> None:
    """A grasp alone shows little of the object: a class published from the first labelled
    iteration flickered (a cylinder read ellipse, box, ellipse, circle… in its first 100)."""
    rec, recs = recognise(thesis_runs[name])
    first = next(i for i, r in enumerate(recs) if r.object_class is not None)
    rot = [r.rotation for r in recs]
    assert (
        max(rot[:first]) - min(rot[:first]) < 2.0 <= max(rot[: first + 1]) - min(rot[: first + 1])
    )
    assert all(r.object_class is not None for r in recs[first:])
    s = rec.summary()
    assert s is not None and s["rotation_range_deg"] == pytest.approx(max(rot) - min(rot))


def test_nothing_labelled_is_no_summary(cfg: Settings) -> None:
    """Before a contact is labelled the summary is null, not a confidence of 0 and shares of 0."""
    assert Recognizer(cfg.model_context()).summary() is None
