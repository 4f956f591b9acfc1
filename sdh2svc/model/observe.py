"""One observation of the hand: two distal tactile matrices and the joint angles → A, B, Λ, σ, ω.

This is the sensing half of a rolling iteration (hand-model §8, steps 1–2), shared by the
controller, the dashboards and the benchmarks.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from sdh2svc.model.contact import (
    ContactEstimate,
    MatrixLayout,
    TactileCalibration,
    estimate_contact,
)
from sdh2svc.model.depth import PadCompliance
from sdh2svc.model.friction import omega
from sdh2svc.model.kinematics import (
    Finger,
    FingerLimits,
    HandGeometry,
    HandPoints,
    HandPose,
    contact_point,
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
    # the depth model's parameters (None: contacts on the undeformed pad surface)
    compliance: PadCompliance | None = field(init=False, default=None)

    def __post_init__(self) -> None:
        object.__setattr__(self, "compliance", pad_compliance(self.geom, self.calib))

    def limits(self, finger: Finger) -> FingerLimits:
        return self.limits1 if finger is Finger.ONE else self.limits2

    def contact(self, counts: np.ndarray) -> ContactEstimate:
        return estimate_contact(counts, self.distal, self.pitch_mm, self.calib, self.geom.pad,
                                self.compliance)  # fmt: skip


def pad_compliance(geom: HandGeometry, calib: TactileCalibration) -> PadCompliance | None:
    """The contact-depth model's parameters from the configuration (None: model "none")."""
    if geom.contact_depth.model == "none":
        return None
    return PadCompliance(
        rubber_stiffness_n_per_mm3=geom.pad.rubber_stiffness_n_per_mm3,
        rubber_thickness_mm=geom.pad.rubber_thickness_mm,
        finger_stiffness_n_per_mm=geom.finger_stiffness_n_per_mm,
        pressure_per_count_n_per_mm2=calib.physical_pressure_per_count_n_per_mm2,
        spread_mm=calib.spread_mm,
        corner_slope=geom.contact_depth.corner_slope,
    )


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


def observe(
    pose: HandPose, counts1: np.ndarray, counts2: np.ndarray, ctx: ModelContext
) -> Observation:
    """Contact estimates on the distal pads of Finger 1 (S1) and Finger 2 (S2), then FK, Λ, σ, ω.

    A and B are the contacts themselves: with a depth model (``[hand.contact_depth]``) each lies
    below its pad's undeformed surface along the pad normal (:mod:`sdh2svc.model.depth`), so Λ,
    σ and ω are those of the corrected points."""
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


def rolling_turn(prev: Observation, pose: HandPose, ctx: ModelContext) -> float | None:
    """dψ (rad) of a rigid object rolling without slip from ``prev`` to ``pose``: the pad
    points under the previous contacts move by δA, δB; dψ = (AB × (δB − δA)) / |AB|²."""
    pts, vj1, vj2 = prev.points, prev.contact1.virtual_joint, prev.contact2.virtual_joint
    if pts is None or vj1 is None or vj2 is None:
        return None
    # A and B as hand_points has them (C and D are not needed)
    A = contact_point(Finger.ONE, pose.phi2, pose.phi3, vj1[0], vj1[1], ctx.geom)
    B = contact_point(Finger.TWO, pose.phi4, pose.phi5, vj2[0], vj2[1], ctx.geom)
    dy, dz = pts.B.y - pts.A.y, pts.B.z - pts.A.z
    vy = (B.y - pts.B.y) - (A.y - pts.A.y)
    vz = (B.z - pts.B.z) - (A.z - pts.A.z)
    d2 = dy * dy + dz * dz
    return (dy * vz - dz * vy) / d2 if d2 > 1e-9 else None
