"""Forward and inverse kinematics of the two coupled fingers in the y0z0 plane (hand-model §2, §7).

Frame 0: origin at Finger 1's proximal joint O, z0 along the straightened finger, y0 towards
Finger 2, whose proximal joint O' sits at y0 = base offset. Finger 2 is Finger 1 mirrored by
y → base − y, so every formula is written once for Finger 1 and mirrored. Points are (y, z) in mm;
angles in radians; positive proximal angles close the fingers towards each other.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum, StrEnum
from typing import Annotated, NamedTuple

import numpy as np
from pydantic import Field

from sdh2svc.model.base import Finite
from sdh2svc.model.depth import ContactDepthModel
from sdh2svc.model.geometry import PadProfile, pad_surface

PositiveMm = Annotated[float, Field(gt=0.0, le=1000.0)]


class Finger(IntEnum):
    """The two coupled fingers: ONE carries A (φ2, φ3), TWO carries B (φ4, φ5)."""

    ONE = 1
    TWO = 2


class Point(NamedTuple):
    """A point of the y0z0 plane, mm."""

    y: float
    z: float


class HandGeometry(Finite):
    """Link lengths of the coupled fingers and the fingertip pad (hand-model §2–§3)."""

    proximal_length_mm: PositiveMm
    base_offset_mm: PositiveMm
    distal_length_mm: PositiveMm
    distal_length_schunk_mm: PositiveMm
    pad: PadProfile
    # the finger's yield along the pad normal (structure, gears, servo), unseen by the encoders
    finger_stiffness_n_per_mm: Annotated[float, Field(gt=0.0, le=1e6)] = 10.0
    contact_depth: ContactDepthModel = ContactDepthModel()


@dataclass(frozen=True, slots=True)
class FingerLimits:
    """Joint limits of one finger, radians: [proximal_min, proximal_max] and the distal ones."""

    proximal_min: float
    proximal_max: float
    distal_min: float
    distal_max: float

    def contains(self, proximal: float, distal: float, tol: float = 1e-9) -> bool:
        return (
            self.proximal_min - tol <= proximal <= self.proximal_max + tol
            and self.distal_min - tol <= distal <= self.distal_max + tol
        )


@dataclass(frozen=True, slots=True)
class HandPose:
    """Joint angles of the coupled fingers, radians: φ2, φ3 (Finger 1) and φ4, φ5 (Finger 2)."""

    phi2: float
    phi3: float
    phi4: float
    phi5: float

    @classmethod
    def from_degrees(cls, phi2: float, phi3: float, phi4: float, phi5: float) -> HandPose:
        """The pose of φ2…φ5 given in degrees (as the wire and the records have them)."""
        return cls(math.radians(phi2), math.radians(phi3), math.radians(phi4), math.radians(phi5))

    def degrees(self) -> tuple[float, float, float, float]:
        """φ2…φ5 in degrees (as the wire and the records have them)."""
        d = math.degrees
        return d(self.phi2), d(self.phi3), d(self.phi4), d(self.phi5)

    def finger(self, finger: Finger) -> tuple[float, float]:
        return (self.phi2, self.phi3) if finger is Finger.ONE else (self.phi4, self.phi5)

    def with_finger(self, finger: Finger, proximal: float, distal: float) -> HandPose:
        if finger is Finger.ONE:
            return HandPose(proximal, distal, self.phi4, self.phi5)
        return HandPose(self.phi2, self.phi3, proximal, distal)


@dataclass(frozen=True, slots=True)
class HandPoints:
    """C, D (distal joints) and the contact points A (Finger 1) and B (Finger 2)."""

    A: Point
    B: Point
    C: Point
    D: Point


def _mirror(finger: Finger, p: Point, base: float) -> Point:
    return p if finger is Finger.ONE else Point(base - p.y, p.z)


def distal_joint(finger: Finger, proximal: float, geom: HandGeometry) -> Point:
    """C (Finger 1) or D (Finger 2): C = l1·(sin φ2, cos φ2); D is C mirrored."""
    l1 = geom.proximal_length_mm
    return _mirror(
        finger, Point(l1 * math.sin(proximal), l1 * math.cos(proximal)), geom.base_offset_mm
    )


def frame3_axes(finger: Finger, psi: float) -> tuple[Point, Point]:
    """ex3, ey3 of the distal frame in frame 0, for ψ = proximal + distal angle."""
    s, c = math.sin(psi), math.cos(psi)
    if finger is Finger.ONE:
        return Point(s, c), Point(c, -s)
    return Point(-s, c), Point(-c, -s)


def pad_point(
    finger: Finger, proximal: float, distal: float, x3: float, y3: float, geom: HandGeometry
) -> Point:
    """Frame-0 position of the pad point with frame-3 coordinates (x3, y3)."""
    C = distal_joint(finger, proximal, geom)
    ex, ey = frame3_axes(finger, proximal + distal)
    return Point(C.y + x3 * ex.y + y3 * ey.y, C.z + x3 * ex.z + y3 * ey.z)


def pad_gap(pose: HandPose, geom: HandGeometry) -> float:
    """The least distance (mm) between the two distal pads' surfaces (each sampled every 1 mm of
    x3: :func:`~sdh2svc.model.geometry.pad_surface`; within ≈ 0.3 mm of the exact distance).
    Unsigned: pads that have passed through each other (only in a simulation) read apart again."""
    x3, y3 = pad_surface(geom.pad)
    ends = []
    for f in (Finger.ONE, Finger.TWO):  # pad_point for every sample at once
        prox, dist = pose.finger(f)
        C = distal_joint(f, prox, geom)
        ex, ey = frame3_axes(f, prox + dist)
        ends.append((C.y + x3 * ex.y + y3 * ey.y, C.z + x3 * ex.z + y3 * ey.z))
    (y1, z1), (y2, z2) = ends
    return float(np.sqrt(np.min((y1[:, None] - y2) ** 2 + (z1[:, None] - z2) ** 2)))


def contact_point(
    finger: Finger, proximal: float, distal: float, r: float, theta: float, geom: HandGeometry
) -> Point:
    """A (or B) through the virtual link: A = C + r·(cos(ψ − θ), −sin(ψ − θ)), mirrored for B."""
    l1 = geom.proximal_length_mm
    a = proximal + distal - theta
    y = l1 * math.sin(proximal) + r * math.cos(a)
    z = l1 * math.cos(proximal) - r * math.sin(a)
    return _mirror(finger, Point(y, z), geom.base_offset_mm)


def hand_points(
    pose: HandPose, vj1: tuple[float, float], vj2: tuple[float, float], geom: HandGeometry
) -> HandPoints:
    """A, B, C, D for a pose and the virtual joints (r1, θ1), (r2, θ2) of the two contacts."""
    return HandPoints(
        A=contact_point(Finger.ONE, pose.phi2, pose.phi3, vj1[0], vj1[1], geom),
        B=contact_point(Finger.TWO, pose.phi4, pose.phi5, vj2[0], vj2[1], geom),
        C=distal_joint(Finger.ONE, pose.phi2, geom),
        D=distal_joint(Finger.TWO, pose.phi4, geom),
    )


def segment(A: Point, B: Point) -> tuple[float, float]:
    """Length Λ = |AB| and inclination σ = atan2(Bz − Az, By − Ay) of segment AB (eqs 3.1, 3.3)."""
    dy, dz = B.y - A.y, B.z - A.z
    return math.hypot(dy, dz), math.atan2(dz, dy)


def wrap_angle(a: float) -> float:
    """a wrapped into (−π, π]."""
    w = math.remainder(a, 2.0 * math.pi)
    return math.pi if w == -math.pi else w


class IKFailure(StrEnum):
    """Why a finger cannot reach a target."""

    OUT_OF_WORKSPACE = "out_of_workspace"
    JOINT_LIMITS = "joint_limits"


@dataclass(frozen=True, slots=True)
class IKSolution:
    """Proximal and distal angles (rad) reaching a target; branch +1: φ = β − o, −1: φ = β + o."""

    proximal: float
    distal: float
    branch: int


@dataclass(frozen=True, slots=True)
class IKResult:
    """The chosen solution, or why there is none (with the raw candidates for diagnosis)."""

    solution: IKSolution | None
    failure: IKFailure | None
    candidates: tuple[IKSolution, ...] = ()

    @property
    def ok(self) -> bool:
        return self.solution is not None


def ik_branches(
    finger: Finger, target: Point, r: float, theta: float, geom: HandGeometry
) -> tuple[IKSolution, ...]:
    """Both elbow branches reaching ``target`` with the virtual link (r, θ) (hand-model §7).

    Empty when the target lies outside the annulus |l1 − r| ≤ d ≤ l1 + r around the proximal joint.
    """
    l1 = geom.proximal_length_mm
    t = _mirror(finger, target, geom.base_offset_mm)  # solve as Finger 1
    d = math.hypot(t.y, t.z)
    if d > l1 + r or d < abs(l1 - r) or d == 0.0:
        return ()
    cos_o = (l1 * l1 + d * d - r * r) / (2.0 * l1 * d)
    o = math.acos(max(-1.0, min(1.0, cos_o)))
    beta = math.atan2(t.y, t.z)
    out = []
    for branch, prox in ((1, beta - o), (-1, beta + o)):
        cy, cz = l1 * math.sin(prox), l1 * math.cos(prox)
        dist = wrap_angle(math.atan2(-(t.z - cz), t.y - cy) - prox + theta)
        out.append(IKSolution(wrap_angle(prox), dist, branch))
        if o == 0.0:
            break
    return tuple(out)


def finger_ik(
    finger: Finger,
    target: Point,
    r: float,
    theta: float,
    current: tuple[float, float],
    geom: HandGeometry,
    limits: FingerLimits,
) -> IKResult:
    """Angles that put the contact point at ``target``: the branch nearest to ``current``
    (proximal, distal), or the reason there is none — JOINT_LIMITS when that branch is outside
    the limits, even if the other elbow is inside them (hand-model §7): the other elbow is
    the finger folded the other way, tens of degrees from where it is, not a way on."""
    candidates = ik_branches(finger, target, r, theta, geom)
    if not candidates:
        return IKResult(None, IKFailure.OUT_OF_WORKSPACE)
    best = min(
        candidates,
        key=lambda s: (
            abs(wrap_angle(s.proximal - current[0])) + abs(wrap_angle(s.distal - current[1]))
        ),
    )
    if not limits.contains(best.proximal, best.distal):
        return IKResult(None, IKFailure.JOINT_LIMITS, candidates)
    return IKResult(best, None, candidates)
