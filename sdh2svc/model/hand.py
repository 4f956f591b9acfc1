"""The hand as a lab wires it: wire axes ↔ the thesis's joints, joint limits, tactile layouts.

The SDH2 has seven axes (wire order 0…6); the DSACON32m six pads. Which axis is φ2…φ5 and which
pad is a fingertip's is configuration (:class:`AxisMap`), as are the joint limits and the pads'
texel layouts — the same value for the model, the controller and the simulator.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Annotated

from pydantic import Field, field_validator, model_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.contact import MatrixLayout
from sdh2svc.model.kinematics import Finger, HandPose
from sdh2svc.protocol.sdh import NUM_AXES  # the wire's count, written once

AxisIndex = Annotated[int, Field(ge=0, le=6)]
MatrixIndex = Annotated[int, Field(ge=0, le=5)]
AngleDeg = Annotated[float, Field(ge=-180.0, le=180.0)]


class AxisMap(Finite):
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

    @property
    def coupled(self) -> tuple[int, int, int, int]:
        """Wire axes of φ2, φ3, φ4, φ5 (the coupled fingers the model knows)."""
        return self.phi2, self.phi3, self.phi4, self.phi5

    # The wire ↔ model conversion, here only: the wire has 7 axes in degrees, the model φ2…φ5
    # in radians (:class:`HandPose`); the axes the model does not know keep their angles.

    def pose(self, wire_deg: Sequence[float]) -> HandPose:
        """The model's pose from the wire's 7 angles (degrees)."""
        return HandPose.from_degrees(*(wire_deg[i] for i in self.coupled))

    def wire_targets(self, pose: HandPose, wire_deg: Sequence[float]) -> list[float]:
        """7 wire targets (degrees): ``pose``'s φ2…φ5, the other axes as in ``wire_deg``."""
        out = list(wire_deg)
        for axis, angle_deg in zip(self.coupled, pose.degrees(), strict=True):
            out[axis] = angle_deg
        return out

    def wire_steps(self, d_phi_deg: Sequence[float], wire_deg: Sequence[float]) -> list[float]:
        """7 wire targets (degrees): ``wire_deg`` with φ2…φ5 moved by ``d_phi_deg``."""
        out = list(wire_deg)
        for axis, inc in zip(self.coupled, d_phi_deg, strict=True):
            out[axis] = wire_deg[axis] + inc
        return out


# The SDH2's own range per wire axis (SCHUNK's library, protocols.md §2.2): configured limits
# may narrow it, never widen it (a target beyond it is the firmware's to refuse or to drive to)
HAND_MIN_DEG = (0.0, -90.0, -90.0, -90.0, -90.0, -90.0, -90.0)
HAND_MAX_DEG = (90.0, 90.0, 90.0, 90.0, 90.0, 90.0, 90.0)
# The SDH2's velocity limit per wire axis, deg/s: SDHLibrary-CPP's fixed limits (sdh/sdh.cpp,
# protocols.md §2.2), which the library takes when the firmware cannot report its own. A live
# hand reports its own with ``vlim`` (what the joint link checks commands against); SDHLibrary-
# Python's offline reply (83, 140, 200, …, the simulator's) differs: exact limits are [U]. Here
# for what no hand answers: the URDF's joint ``velocity`` limits.
HAND_VELOCITY_LIMIT_DEG_S = (85.7, 200.0, 157.8, 200.0, 157.8, 200.0, 157.8)


class JointLimits(Finite):
    """Joint limits per wire axis 0…6, degrees: within the hand's range (HAND_MIN_DEG …
    HAND_MAX_DEG)."""

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
        lo, hi = self.min_deg, self.max_deg
        wide = [i for i in range(NUM_AXES) if lo[i] < HAND_MIN_DEG[i] or hi[i] > HAND_MAX_DEG[i]]
        if wide:
            ranges = ", ".join(f"axis {i}: {HAND_MIN_DEG[i]:g}…{HAND_MAX_DEG[i]:g}°" for i in wide)
            raise ValueError(f"limits beyond the SDH2's own range ({ranges}): they may narrow "
                             "it, never widen it")  # fmt: skip
        return self


class TactileConfig(Finite):
    """Layouts of the proximal (6 × 14) and distal (6 × 13) matrices and their pitch."""

    texel_pitch_mm: Annotated[float, Field(gt=0.0, le=20.0)]
    proximal: MatrixLayout
    distal: MatrixLayout


def matrix_pads(axes: AxisMap, tactile: TactileConfig) -> tuple[tuple[str, MatrixLayout], ...]:
    """Each tactile matrix in wire order (a frame's texels are these matrices one after the
    other, each row-major): the pad it is, as the configuration wires it (with its layout's
    key), and its layout."""
    pads = {
        axes.finger1_proximal_matrix: ("Finger 1 proximal", "proximal"),
        axes.finger1_distal_matrix: ("Finger 1 distal", "distal"),
        axes.thumb_proximal_matrix: ("thumb proximal", "proximal"),
        axes.thumb_distal_matrix: ("thumb distal", "distal"),
        axes.finger2_proximal_matrix: ("Finger 2 proximal", "proximal"),
        axes.finger2_distal_matrix: ("Finger 2 distal", "distal"),
    }
    return tuple(
        (f"{name} pad, tactile.{key}", getattr(tactile, key))
        for name, key in (pads[m] for m in sorted(pads))
    )


def matrix_shapes(tactile: TactileConfig, axes: AxisMap) -> tuple[tuple[int, int], ...]:
    """(rows, columns) of each tactile matrix, in wire order (:func:`matrix_pads`)."""
    return tuple((lay.rows, lay.cols) for _, lay in matrix_pads(axes, tactile))
