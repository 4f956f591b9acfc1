"""Rolling parameters (hand-model §8, thesis Table 8): one validated, immutable value.

A change between iterations replaces the whole value, so the controller always works with one
consistent set (atomic at the next iteration).
"""

from __future__ import annotations

import math
from typing import Annotated, Literal, Self

from pydantic import Field, ValidationInfo, field_validator, model_validator

from sdh2svc.model.base import Finite

MIN_STEP_DEG = 0.01  # |Δφ| and |dσ| at least (both signed: the sign is the direction)


class RollingParams(Finite):
    """Parameters of the rolling loop. Angles in degrees (converted by the properties below)."""

    mode: Literal["two-finger", "one-finger"] = Field(
        description="two-finger: thesis §3.4–3.5; one-finger: §3.3, Finger 2 holds still"
    )
    route: Literal["thesis", "workspace"] = Field(
        default="thesis",
        description="Finger 2's move per iteration in two-finger mode: thesis: φ4 − Δφ, φ5 + k·Δφ; "
        "workspace: the move, of the same length, whose predicted configuration turns the object "
        "most within the joint limits, Finger 1's reach and the cones, while the grip holds "
        "(control/route.py; not in the thesis)",
    )
    delta_phi_deg: Annotated[float, Field(ge=-5.0, le=5.0)] = Field(
        description="Δφ, Finger 2's step per iteration; its sign is the first rotation direction"
    )
    k: Annotated[float, Field(gt=1.0, le=10.0)] = Field(
        description="Finger 2's distal joint moves k·Δφ per Δφ of the proximal"
    )
    lambda_gain: Annotated[float, Field(ge=0.0, le=50.0)] = Field(
        description="λ, how strongly Finger 1 reinforces the inclination change of Finger 2"
    )
    d_sigma_deg: Annotated[float, Field(ge=-5.0, le=5.0)] = Field(
        description="dσ per iteration in one-finger mode"
    )
    alpha_deg: Annotated[float, Field(gt=0.0, lt=60.0)] = Field(
        description="α, friction-cone half-angle (atan μ)"
    )
    grasp_force: Annotated[float, Field(gt=0.0, le=50.0)] = Field(
        description="Fd, grasp force threshold, library force units"
    )
    contact_force_min: Annotated[float, Field(ge=0.0, le=10.0)] = Field(
        description="F1, F2 at or below this (library units) count as no contact"
    )
    force_deadband: Annotated[float, Field(ge=0.0, le=10.0)] = Field(
        description="|ΔF| at or below this (library units) leaves Λ unchanged (not in the thesis)"
    )
    finger1_max_step_deg: Annotated[float, Field(gt=0.0, le=10.0)] = Field(
        description="largest change of φ2 or φ3 per iteration: a larger one slows the whole "
        "iteration (Δφ, or dσ) down so that Finger 1 can follow (not in the thesis)"
    )
    force_band_low: Annotated[float, Field(ge=0.0, le=20.0)] = Field(
        description="× Fd: below this F, Λ closes by ΔΛ_dec, or holds while F is rising (not "
        "in the thesis; 0: off)"
    )
    force_band_high: Annotated[float, Field(ge=0.0, le=20.0)] = Field(
        description="× Fd: above this F, Λ opens by ΔΛ_inc, or holds while F is falling (not "
        "in the thesis; 20: off)"
    )
    delta_lambda_inc_mm: Annotated[float, Field(ge=0.0, le=10.0)] = Field(
        description="ΔΛ_inc, widening of the held distance when the force rises"
    )
    delta_lambda_dec_mm: Annotated[float, Field(ge=0.0, le=10.0)] = Field(
        description="ΔΛ_dec, narrowing of the held distance when the force falls"
    )
    min_half_stroke_deg: Annotated[float, Field(ge=0.0, le=90.0)] = Field(
        description="Finger 2's travel along its route (φ4; σ in one-finger mode) before a "
        "reversal counts as a half stroke, which also needs the object to have turned 1.2 × "
        "this by the contacts' rolling kinematics; other reversals count towards 'stuck' (not "
        "in the thesis)"
    )
    wedge_limit_deg: Annotated[float, Field(ge=0.0, le=60.0)] = Field(
        description="the pads' wedge, (ωA + ωB)/2 − 90°, a plan may not widen beyond this "
        "(not in the thesis; 0: off)"
    )
    force_reverse: Annotated[float, Field(ge=0.0, le=20.0)] = Field(
        description="× Fd: F above this and not falling reverses the rotation (a contact is "
        "sliding or the pads wedge the object; not in the thesis; 20: off)"
    )
    recentre_strokes: Annotated[float, Field(ge=0.0, le=100.0)] = Field(
        default=0.0,
        description="from the seventh half stroke on, the pads' wedge averaged over the last "
        "full stroke is brought back to the second full stroke's within this many strokes, by "
        "leaning Finger 1's σd, the difference's integral included (not in the thesis; 0: off)",
    )
    cycles: Annotated[int, Field(ge=1, le=10000)] = Field(
        description="back-and-forth strokes before the run ends"
    )

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool(cls, v: object, info: ValidationInfo) -> object:
        # pydantic would take true as 1 (cycles) or 1.0: a mistake, never meant
        if isinstance(v, bool) and info.field_name not in ("mode", "route"):
            raise ValueError("must be a number, not true/false")
        return v

    @field_validator("delta_phi_deg", "d_sigma_deg")
    @classmethod
    def _nonzero(cls, v: float) -> float:
        if v == 0.0:
            raise ValueError("must not be 0 (its sign is the rotation direction)")
        if abs(v) < MIN_STEP_DEG:  # a run that never moves, and never faults either
            per_degree = round(1 / MIN_STEP_DEG)
            raise ValueError(f"must be at least {MIN_STEP_DEG:g}° either way (a smaller step "
                             f"needs over {per_degree} iterations per degree)")  # fmt: skip
        return v

    @model_validator(mode="after")
    def _band_ordered(self) -> Self:
        if self.force_band_low > self.force_band_high:
            raise ValueError(f"force_band_low ({self.force_band_low:g}) must not exceed "
                             f"force_band_high ({self.force_band_high:g})")  # fmt: skip
        return self

    @property
    def delta_phi(self) -> float:
        return math.radians(self.delta_phi_deg)

    @property
    def d_sigma(self) -> float:
        return math.radians(self.d_sigma_deg)

    @property
    def finger1_max_step(self) -> float:
        return math.radians(self.finger1_max_step_deg)

    @property
    def min_half_stroke(self) -> float:
        return math.radians(self.min_half_stroke_deg)

    @property
    def wedge_limit(self) -> float:
        return math.radians(self.wedge_limit_deg)

    @property
    def alpha(self) -> float:
        return math.radians(self.alpha_deg)
