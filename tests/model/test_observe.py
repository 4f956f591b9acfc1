"""The sensing half of an iteration: tactile matrices + angles → A, B, Λ, σ, ω."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sdh2svc.config import Settings, load_config
from sdh2svc.model.kinematics import HandPose
from sdh2svc.model.observe import observe


def s20(cfg: Settings) -> np.ndarray:
    """A distal frame whose centroid is S = 20 mm: rows 5 and 6 loaded 200 : 1500."""
    m = np.zeros((cfg.tactile.distal.rows, cfg.tactile.distal.cols), dtype=np.uint16)
    m[5, :] = 200
    m[6, :] = 1500
    return m


def test_observe_mirror_pose(cfg: Settings) -> None:
    """hand-model §6's check values: the thesis's model, contacts on the undeformed pads."""
    ctx = load_config(None, ["hand.contact_depth.model=none"]).model_context()
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))
    obs = observe(pose, s20(cfg), s20(cfg), ctx)
    assert obs.contact1.S_mm == pytest.approx(20.0)
    assert obs.points is not None
    assert obs.Lambda == pytest.approx(82.20, abs=0.005)
    assert obs.sigma == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(obs.omega_A) == pytest.approx(91.39, abs=0.005)
    assert obs.omega_A == pytest.approx(obs.omega_B)


def _doc_contact(S: float) -> tuple[float, float, float]:
    """hand-model §3–§5 written out with the thesis's numbers: S → L → x3 → (r, θ), and the
    pad's slope at x3 (independent of the code's geometry)."""
    L = 49.5 - S * 44.0 / 40.8
    x3 = 17.5 + L if L < 16.0 else 33.5 + 60.0 * math.sin((L - 16.0) / 60.0)
    y3 = 15.0 if x3 <= 33.5 else -45.0 + math.sqrt(60.0**2 - (x3 - 33.5) ** 2)
    slope = 0.0 if x3 <= 33.5 else -(x3 - 33.5) / math.sqrt(60.0**2 - (x3 - 33.5) ** 2)
    return math.hypot(x3, y3), math.atan2(x3, y3), slope


def _doc_observe(phi: tuple[float, ...], S1: float, S2: float) -> tuple[float, ...]:
    """§2 and §6 written out per finger (no mirroring): Λ, σ, ωA, ωB."""
    p2, p3, p4, p5 = phi
    r1, t1, k1 = _doc_contact(S1)
    r2, t2, k2 = _doc_contact(S2)
    C = np.array([86.5 * math.sin(p2), 86.5 * math.cos(p2)])
    D = np.array([66.0 - 86.5 * math.sin(p4), 86.5 * math.cos(p4)])
    A = C + r1 * np.array([math.cos(p2 + p3 - t1), -math.sin(p2 + p3 - t1)])
    B = D + r2 * np.array([-math.cos(p4 + p5 - t2), -math.sin(p4 + p5 - t2)])
    psi1, psi2 = p2 + p3, p4 + p5
    tA = np.array([math.sin(psi1), math.cos(psi1)]) + k1 * np.array(
        [math.cos(psi1), -math.sin(psi1)]
    )
    tB = np.array([-math.sin(psi2), math.cos(psi2)]) + k2 * np.array(
        [-math.cos(psi2), -math.sin(psi2)]
    )

    def angle(t: np.ndarray, v: np.ndarray) -> float:
        return math.acos(float(t @ v) / float(np.linalg.norm(t) * np.linalg.norm(v)))

    AB = B - A
    return (float(np.linalg.norm(AB)), math.atan2(AB[1], AB[0]), angle(tA, AB), angle(tB, -AB))


def test_observe_asymmetric_pose_against_the_doc(cfg: Settings) -> None:
    """Each finger's own contact, joint angles and pad in Λ, σ, ωA and ωB: a pose and contacts
    that differ between the fingers (the mirror pose cannot tell them apart)."""
    ctx = load_config(None, ["hand.contact_depth.model=none"]).model_context()
    phi = tuple(math.radians(a) for a in (-20.0, 30.0, -14.0, 26.0))
    m1 = s20(cfg)
    m2 = np.zeros_like(m1)
    m2[7, :] = 1000  # S2 = 7 × 3.4 = 23.8 mm
    obs = observe(HandPose(*phi), m1, m2, ctx)
    S1, S2 = obs.contact1.S_mm, obs.contact2.S_mm
    assert S1 == pytest.approx(20.0) and S2 == pytest.approx(23.8)
    lam, sigma, wa, wb = _doc_observe(phi, S1, S2)
    assert abs(wa - wb) > math.radians(1.0)  # the two ω differ here
    assert obs.Lambda == pytest.approx(lam, abs=1e-9)
    assert obs.sigma == pytest.approx(sigma, abs=1e-12)
    assert obs.omega_A == pytest.approx(wa, abs=1e-12)
    assert obs.omega_B == pytest.approx(wb, abs=1e-12)


def test_observe_without_second_contact(cfg: Settings) -> None:
    ctx = cfg.model_context()
    pose = HandPose(0.0, 0.0, 0.0, 0.0)
    obs = observe(pose, s20(cfg), np.zeros_like(s20(cfg)), ctx)
    assert obs.contact1.present and not obs.contact2.present
    assert obs.points is None
    assert obs.Lambda is None and obs.omega_A is None
