"""The parts of a rolling plan (hand-model §8, steps 5–7) that the rolling step and the
workspace route (control/route.py) both work out for a candidate move of Finger 2: σd, where
Finger 1 must put A, its inverse kinematics, and the friction angles of the result."""

from __future__ import annotations

import math

from sdh2svc.model.contact import ContactEstimate
from sdh2svc.model.friction import omega
from sdh2svc.model.kinematics import Finger, IKResult, Point, finger_ik, segment
from sdh2svc.model.observe import ModelContext, Observation


def grip_force(c1: ContactEstimate, c2: ContactEstimate) -> float:
    """F, the grip's force (eq 3.16) in the controller's force (:attr:`ContactEstimate.force`)."""
    return (c1.force + c2.force) / 2


def sigma_desired(obs: Observation, B_d: Point, lambda_gain: float) -> float:
    """σd = σ + λ·dσ with dσ = σ(A→Bd) − σ (eq 3.13, its sign typo fixed; eq 3.14)."""
    assert obs.points is not None and obs.sigma is not None
    return obs.sigma + lambda_gain * (segment(obs.points.A, B_d)[1] - obs.sigma)


def finger1_to(obs: Observation, B_d: Point, sigma_d: float, lam: float,
               ctx: ModelContext) -> tuple[Point, IKResult]:  # fmt: skip
    """Ad on the circle of radius Λad (``lam``) around Bd at inclination σd, and Finger 1's
    inverse kinematics for it (the branch nearest its angles now)."""
    c1, pose = obs.contact1, obs.pose
    assert c1.r_mm is not None and c1.theta_rad is not None
    A_d = Point(B_d.y - lam * math.cos(sigma_d), B_d.z - lam * math.sin(sigma_d))
    ik = finger_ik(Finger.ONE, A_d, c1.r_mm, c1.theta_rad, (pose.phi2, pose.phi3), ctx.geom,
                   ctx.limits1)  # fmt: skip
    return A_d, ik


def omegas(obs: Observation, phi: tuple[float, float, float, float], A_d: Point, B_d: Point,
           ctx: ModelContext) -> tuple[float, float]:  # fmt: skip
    """ωA, ωB of the configuration φ2…φ5 with the contacts at Ad, Bd."""
    x1, x2 = obs.contact1.x3_mm, obs.contact2.x3_mm
    assert x1 is not None and x2 is not None
    pad = ctx.geom.pad
    return (omega(Finger.ONE, phi[0] + phi[1], x1, A_d, B_d, pad),
            omega(Finger.TWO, phi[2] + phi[3], x2, B_d, A_d, pad))  # fmt: skip
