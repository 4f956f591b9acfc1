"""One observation of the hand: two distal tactile matrices and the joint angles → A, B, Λ, σ, ω.

This is the sensing half of a rolling iteration (hand-model §8, steps 1–2), shared by the
controller, the dashboards and the benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from sdh2svc.model.contact import (
    ContactEstimate,
    MatrixLayout,
    TactileCalibration,
    estimate_contact,
)
from sdh2svc.model.friction import omega
from sdh2svc.model.kinematics import (
    Finger,
    FingerLimits,
    HandGeometry,
    HandPoints,
    HandPose,
    hand_points,
    segment,
)


@dataclass(frozen=True, slots=True)
class ModelContext:
    """Everything the pure model needs, gathered once (see ``Settings.model_context``)."""

    geom: HandGeometry
    distal: MatrixLayout
    pitch_mm: float
    calib: TactileCalibration
    limits1: FingerLimits
    limits2: FingerLimits

    def limits(self, finger: Finger) -> FingerLimits:
        return self.limits1 if finger is Finger.ONE else self.limits2

    def contact(self, counts: np.ndarray) -> ContactEstimate:
        return estimate_contact(counts, self.distal, self.pitch_mm, self.calib, self.geom.pad)


@dataclass(frozen=True, slots=True)
class Observation:
    """Contacts on both distal pads and, when both are present, the object segment AB.

    Λ = |AB|, σ = inclination of AB, ωA/ωB the friction-cone angles (radians); None without
    both contacts.
    """

    pose: HandPose
    contact1: ContactEstimate
    contact2: ContactEstimate
    points: HandPoints | None
    Lambda: float | None
    sigma: float | None
    omega_A: float | None
    omega_B: float | None

    @property
    def both_contacts(self) -> bool:
        return self.points is not None


def observe(
    pose: HandPose, counts1: np.ndarray, counts2: np.ndarray, ctx: ModelContext
) -> Observation:
    """Contact estimates on the distal pads of Finger 1 (S1) and Finger 2 (S2), then FK, Λ, σ, ω."""
    c1, c2 = ctx.contact(counts1), ctx.contact(counts2)
    vj1, vj2 = c1.virtual_joint, c2.virtual_joint
    if vj1 is None or vj2 is None or c1.x3_mm is None or c2.x3_mm is None:
        return Observation(pose, c1, c2, None, None, None, None, None)
    pts = hand_points(pose, vj1, vj2, ctx.geom)
    lam, sigma = segment(pts.A, pts.B)
    pad = ctx.geom.pad
    wa = omega(Finger.ONE, pose.phi2 + pose.phi3, c1.x3_mm, pts.A, pts.B, pad)
    wb = omega(Finger.TWO, pose.phi4 + pose.phi5, c2.x3_mm, pts.B, pts.A, pad)
    return Observation(pose, c1, c2, pts, lam, sigma, wa, wb)
