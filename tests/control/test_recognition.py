"""Recognition while rolling: the contact-kind and class estimators on hand-built traces, the
whole recognizer on fast simulated runs of the thesis's objects against their truth, and the
reconstructed outline."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sdh2svc.config import Settings
from sdh2svc.control.recognition import (
    ContactKind,
    ObjectClass,
    Recognition,
    RecognitionModel,
    _ContactTrack,
    _Evidence,
    classify,
    outline,
)
from sdh2svc.model.contact import NO_CONTACT, Blob, ContactEstimate
from sdh2svc.model.kinematics import Finger

MODEL = RecognitionModel()


def _C(L: float) -> ContactEstimate:
    """A contact at pad distance L (only L matters to the rules)."""
    blob = Blob(20.0, 8.0, 12, 0.01, 1.0, 0.1, 4, 6)
    return replace(NO_CONTACT, present=True, L_mm=L, S_mm=20.0, blobs=(blob,), n_cells=12)


def trace(track: _ContactTrack, L: np.ndarray, rel: np.ndarray) -> list[ContactKind | None]:
    """Feed a track the pad distances L (mm) and the relative turns ν − ψ (rad); its labels."""
    out = []
    for x, y in zip(L, rel, strict=True):
        track.update(_C(float(x)), float(y), 0.0)
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


@pytest.mark.parametrize("finger", [Finger.ONE, Finger.TWO])
def test_a_box_turning_through_face_edge_face(finger: Finger) -> None:
    track = _ContactTrack(finger, MODEL)
    segments = [
        (rolling(finger, 60, 0.15, None), ContactKind.FLAT),
        (rolling(finger, 60, 0.0, 0.0), ContactKind.EDGE),
        (rolling(finger, 60, -0.15, None), ContactKind.FLAT),
    ]
    for (L, rel), want in segments:
        labels = trace(track, L, rel - rel[0] + (track.rel[-1] if track.rel else 0.3))
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
    ev = _Evidence(radii=[])
    for k1, k2 in kinds:
        ev.n += 1
        ev.lam_min, ev.lam_max = min(ev.lam_min, lam), max(ev.lam_max, lam)
        ev.lam_sum += lam
        ev.lam_n += 1
        for k in (k1, k2):
            setattr(ev, k.value, getattr(ev, k.value) + 1)
            if k is ContactKind.CURVED:
                assert ev.radii is not None and radius is not None
                ev.radii.append(radius / (lam / 2))
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


def test_the_class_of_an_ellipse() -> None:
    ev = evidence([(C, C)] * 80, 39.0, radius=14.3)
    ev.lam_max = 53.0
    got = classify(ev, MODEL)
    assert got[0] is ObjectClass.ELLIPSE
    assert got[2] == pytest.approx(26.5) and got[3] == pytest.approx(19.5)


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


def test_no_outline_before_a_class() -> None:
    assert outline(Recognition(), (0.0, 100.0), (50.0, 100.0)).shape == (0, 2)


def test_the_packaged_model_loads(cfg: Settings) -> None:
    from sdh2svc.control.recognition import packaged_model

    assert isinstance(packaged_model(), RecognitionModel)
