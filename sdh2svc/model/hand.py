"""The hand as a lab wires it: wire axes ↔ the thesis's joints, joint limits, tactile layouts.

The SDH2 has seven axes (wire order 0…6); the DSACON32m six pads. Which axis is φ2…φ5 and which
pad is a fingertip's is configuration (:class:`AxisMap`), as are the joint limits and the pads'
texel layouts — the same value for the model, the controller and the simulator.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import Field, field_validator, model_validator

from sdh2svc.model.base import Frozen
from sdh2svc.model.contact import MatrixLayout
from sdh2svc.model.kinematics import Finger
from sdh2svc.protocol.sdh import NUM_AXES  # the wire's count, written once

AxisIndex = Annotated[int, Field(ge=0, le=6)]
MatrixIndex = Annotated[int, Field(ge=0, le=5)]
AngleDeg = Annotated[float, Field(ge=-180.0, le=180.0)]


class AxisMap(Frozen):
    """Thesis joint names → SDH2 wire axes, and finger pads → DSACON32m matrix indices."""

    phi1: AxisIndex
    phi2: AxisIndex
    phi3: AxisIndex
    phi4: AxisIndex
    phi5: AxisIndex
    thumb_proximal: AxisIndex
    thumb_distal: AxisIndex
    finger1_proximal_matrix: MatrixIndex
    finger1_distal_matrix: MatrixIndex
    thumb_proximal_matrix: MatrixIndex
    thumb_distal_matrix: MatrixIndex
    finger2_proximal_matrix: MatrixIndex
    finger2_distal_matrix: MatrixIndex

    @model_validator(mode="after")
    def _distinct(self) -> AxisMap:
        axes = [self.phi1, self.phi2, self.phi3, self.phi4, self.phi5]
        axes += [self.thumb_proximal, self.thumb_distal]
        if len(set(axes)) != NUM_AXES:
            raise ValueError(f"each wire axis 0…6 must be named exactly once, got {axes}")
        mats = [
            self.finger1_proximal_matrix,
            self.finger1_distal_matrix,
            self.thumb_proximal_matrix,
            self.thumb_distal_matrix,
            self.finger2_proximal_matrix,
            self.finger2_distal_matrix,
        ]
        if len(set(mats)) != len(mats):
            raise ValueError(f"each tactile matrix 0…5 must be named exactly once, got {mats}")
        return self

    def finger_axes(self, finger: Finger) -> tuple[int, int]:
        """Wire axes (proximal, distal) of a coupled finger."""
        return (self.phi2, self.phi3) if finger is Finger.ONE else (self.phi4, self.phi5)

    def distal_matrix(self, finger: Finger) -> int:
        return self.finger1_distal_matrix if finger is Finger.ONE else self.finger2_distal_matrix


class JointLimits(Frozen):
    """Joint limits per wire axis 0…6, degrees."""

    min_deg: tuple[AngleDeg, ...]
    max_deg: tuple[AngleDeg, ...]

    @field_validator("min_deg", "max_deg")
    @classmethod
    def _seven(cls, v: tuple[float, ...]) -> tuple[float, ...]:
        if len(v) != NUM_AXES:
            raise ValueError(f"needs {NUM_AXES} angles, one per wire axis 0…6 (got {len(v)})")
        return v

    @model_validator(mode="after")
    def _ordered(self) -> JointLimits:
        bad = [
            i for i, (lo, hi) in enumerate(zip(self.min_deg, self.max_deg, strict=True)) if lo >= hi
        ]
        if bad:
            raise ValueError(f"min_deg must be below max_deg for every axis; not so for axes {bad}")
        return self

    def clamp_deg(self, axis: int, angle_deg: float) -> float:
        return min(self.max_deg[axis], max(self.min_deg[axis], angle_deg))


class TactileConfig(Frozen):
    """Layouts of the proximal (6 × 14) and distal (6 × 13) matrices and their pitch."""

    texel_pitch_mm: Annotated[float, Field(gt=0.0, le=20.0)]
    proximal: MatrixLayout
    distal: MatrixLayout
