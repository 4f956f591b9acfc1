"""Fingertip pad profile and the virtual joint (hand-model.md §3–§4).

Lengths in millimetres, angles in radians. Frame 3 sits at the distal joint (C or D): x3 runs
along the distal link towards the fingertip's end, y3 towards the pad, i.e. the other finger.
"""

from __future__ import annotations

import functools
import math
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from sdh2svc.model.base import Finite

PositiveMm = Annotated[float, Field(gt=0.0, le=1000.0)]


class PadProfile(Finite):
    """The distal pad surface in frame 3: a flat segment, then a circular arc (thesis eqs 2.4, 2.5).

    Flat part: y3 = flat_y3 for flat_start < x3 ≤ flat_end. Arc: centre K = (flat_end,
    flat_y3 − R), radius R, from x3 = flat_end to the pad's end at tip_end. The two meet with equal
    height and zero slope, so the profile is smooth at the boundary.
    """

    flat_start_x3_mm: Annotated[float, Field(ge=0.0, le=200.0)]
    flat_end_x3_mm: PositiveMm
    flat_y3_mm: PositiveMm
    arc_radius_mm: PositiveMm
    tip_end_x3_mm: PositiveMm
    sensor_active_length_mm: PositiveMm
    pad_base_to_active_mm: Annotated[float, Field(ge=0.0, le=100.0)]
    # The rubber over the sensor cells (docs/contact-depth.md): pressure per mm of compression,
    # and how far it compresses before the finger's shell stops it.
    rubber_stiffness_n_per_mm3: Annotated[float, Field(gt=0.0, le=100.0)] = 0.2
    rubber_thickness_mm: Annotated[float, Field(gt=0.0, le=20.0)] = 2.0

    @model_validator(mode="after")
    def _ordered(self) -> PadProfile:
        if not self.flat_start_x3_mm < self.flat_end_x3_mm < self.tip_end_x3_mm:
            raise ValueError(
                "pad points must be ordered: flat_start_x3_mm < flat_end_x3_mm < tip_end_x3_mm "
                f"(got {self.flat_start_x3_mm}, {self.flat_end_x3_mm}, {self.tip_end_x3_mm})"
            )
        if self.tip_end_x3_mm - self.flat_end_x3_mm >= self.arc_radius_mm:
            raise ValueError(
                "the arc cannot extend past a quarter circle: tip_end_x3_mm - flat_end_x3_mm "
                f"must be < arc_radius_mm ({self.arc_radius_mm})"
            )
        return self

    @property
    def flat_length_mm(self) -> float:
        """Curved distance L at which the flat part ends and the arc begins (16 mm)."""
        return self.flat_end_x3_mm - self.flat_start_x3_mm

    @property
    def max_L_mm(self) -> float:
        """Curved distance from the pad's base I to its end at the fingertip."""
        R = self.arc_radius_mm
        return self.flat_length_mm + R * math.asin((self.tip_end_x3_mm - self.flat_end_x3_mm) / R)


def pad_y3(x3: float, pad: PadProfile) -> float:
    """Pad height y3 at x3 (eqs 2.4, 2.5); the flat height before the flat part's start."""
    dx = x3 - pad.flat_end_x3_mm
    if dx <= 0.0:
        return pad.flat_y3_mm
    R = pad.arc_radius_mm
    return pad.flat_y3_mm - R + math.sqrt(R * R - dx * dx)


@functools.lru_cache(maxsize=8)
def pad_surface(pad: PadProfile, step_mm: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(x3, y3) of points at most ``step_mm`` apart in x3 along the pad's surface, from the flat
    part's start to the fingertip's end (:func:`pad_y3` at each; read-only arrays)."""
    n = math.ceil((pad.tip_end_x3_mm - pad.flat_start_x3_mm) / step_mm) + 1
    x3 = np.linspace(pad.flat_start_x3_mm, pad.tip_end_x3_mm, n)
    y3 = np.array([pad_y3(float(x), pad) for x in x3])
    x3.flags.writeable = y3.flags.writeable = False
    return x3, y3


def pad_slope(x3: float, pad: PadProfile) -> float:
    """dy3/dx3 of the pad profile: 0 on the flat part, −dx/sqrt(R² − dx²) on the arc."""
    dx = x3 - pad.flat_end_x3_mm
    if dx <= 0.0:
        return 0.0
    R = pad.arc_radius_mm
    return -dx / math.sqrt(R * R - dx * dx)


def x3_from_L(L: float, pad: PadProfile) -> float:
    """Frame-3 x coordinate of the pad point at curved distance L from the pad's base I.

    eqs 2.15, 2.16: x3 = 17.5 + L on the flat part (L < 16), x3 = 33.5 + 60·sin((L − 16)/60) on
    the arc. L off the pad (a measured distance map extrapolated past its ends) is clamped to
    the pad's base and tip: beyond them there is no pad to touch.
    """
    L = min(max(L, 0.0), pad.max_L_mm)
    flat = pad.flat_length_mm
    if L < flat:
        return pad.flat_start_x3_mm + L
    R = pad.arc_radius_mm
    return pad.flat_end_x3_mm + R * math.sin((L - flat) / R)


def L_from_x3(x3: float, pad: PadProfile) -> float:
    """Inverse of :func:`x3_from_L` on the pad: curved distance from I to the point at x3."""
    if x3 <= pad.flat_end_x3_mm:
        return x3 - pad.flat_start_x3_mm
    R = pad.arc_radius_mm
    return pad.flat_length_mm + R * math.asin(min((x3 - pad.flat_end_x3_mm) / R, 1.0))


def virtual_joint(x3: float, y3: float) -> tuple[float, float]:
    """Virtual link C→A for a pad point: r = |(x3, y3)|, θ = atan2(x3, y3) (eqs 2.1–2.7)."""
    return math.hypot(x3, y3), math.atan2(x3, y3)


def pad_point_from_L(L: float, pad: PadProfile) -> tuple[float, float]:
    """(x3, y3) of the pad point at curved distance L from the pad's base."""
    x3 = x3_from_L(L, pad)
    return x3, pad_y3(x3, pad)
