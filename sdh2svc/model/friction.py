"""Friction-cone angles ωA, ωB in vector form (hand-model §6).

ω is the angle between the pad tangent at a contact (pointing towards the fingertip's end) and
the vector to the other contact. The grasp holds while |ω − 90°| < α at both contacts.
"""

from __future__ import annotations

import math

from sdh2svc.model.geometry import PadProfile, pad_slope
from sdh2svc.model.kinematics import Finger, Point, frame3_axes


def pad_tangent(finger: Finger, psi: float, x3: float, pad: PadProfile) -> Point:
    """Unit pad tangent t = ex3 + (dy3/dx3)·ey3 at x3 in frame 0; ψ = proximal + distal angle."""
    ex, ey = frame3_axes(finger, psi)
    m = pad_slope(x3, pad)
    ty, tz = ex.y + m * ey.y, ex.z + m * ey.z
    n = math.hypot(ty, tz)
    return Point(ty / n, tz / n)


def omega(
    finger: Finger, psi: float, x3: float, here: Point, other: Point, pad: PadProfile
) -> float:
    """ω at the contact ``here`` on ``finger``: angle (rad, in [0, π]) between the pad tangent and
    here→other. 90° means the object segment lies along the pad normal."""
    t = pad_tangent(finger, psi, x3, pad)
    vy, vz = other.y - here.y, other.z - here.z
    n = math.hypot(vy, vz)
    if n == 0.0:
        return math.pi / 2
    c = (t.y * vy + t.z * vz) / n
    return math.acos(max(-1.0, min(1.0, c)))


def inside_cone(w: float, alpha: float) -> bool:
    """Coulomb test: 90° − α < ω < 90° + α (eqs 2.24–2.26)."""
    return abs(w - math.pi / 2) < alpha


def wedge(omega_a: float, omega_b: float) -> float:
    """The pads' wedge (rad): (ωA + ωB)/2 − 90°, half the angle between the two pad normals at
    the contacts — 0 when they face each other along AB, whatever the object's tilt (ωA − ωB)."""
    return (omega_a + omega_b) / 2 - math.pi / 2


def cone_margin(w: float, alpha: float) -> float:
    """How far (rad) ω is from leaving the cone; negative when outside."""
    return alpha - abs(w - math.pi / 2)
