"""Run and safety settings, and the supervisor's checks — independent of the rolling step.

The supervisor never trusts the step: whatever it proposes is clamped to the joint limits and to
a maximum change per iteration, and the run is stopped on a force above the ceiling, on a silent
or stale sensor stream, on a dropped object or when the rotation keeps reversing on the spot.
"""

from __future__ import annotations

from collections.abc import Sequence
from enum import StrEnum
from typing import Annotated

from pydantic import Field, field_validator

from sdh2svc.model.base import Frozen

Deg7 = tuple[float, ...]


class RunConfig(Frozen):
    """How a run pre-shapes and grasps (config [run])."""

    preshape_deg: Deg7
    preshape_velocity_deg_s: Annotated[float, Field(gt=0.0, le=200.0)]
    grasp_gain_deg_s: Annotated[float, Field(gt=0.0, le=100.0)]
    grasp_max_velocity_deg_s: Annotated[float, Field(gt=0.0, le=100.0)]
    grasp_min_velocity_deg_s: Annotated[float, Field(ge=0.0, le=100.0)]
    grasp_align_gain: Annotated[float, Field(ge=0.0, le=1.0)]
    grasp_settle_s: Annotated[float, Field(ge=0.0, le=60.0)]
    grasp_timeout_s: Annotated[float, Field(gt=0.0, le=600.0)]
    grasp_max_close_deg: Annotated[float, Field(ge=-90.0, le=90.0)]
    tactile_rate_hz: Annotated[float, Field(gt=0.0, le=100.0)]
    watch_rate_hz: Annotated[float, Field(gt=0.0, le=100.0)]

    @field_validator("preshape_deg")
    @classmethod
    def _seven(cls, v: Deg7) -> Deg7:
        if len(v) != 7:
            raise ValueError(f"needs 7 angles, one per wire axis 0…6 (got {len(v)})")
        return v


class SafetyConfig(Frozen):
    """The supervisor's limits (config [safety])."""

    max_step_deg: Annotated[float, Field(gt=0.0, le=1.0)]
    force_ceiling_factor: Annotated[float, Field(gt=1.0, le=20.0)]
    stale_frame_ms: Annotated[float, Field(gt=0.0, le=10000.0)]
    stale_joint_ms: Annotated[float, Field(gt=0.0, le=10000.0)]
    max_consecutive_reversals: Annotated[int, Field(ge=2, le=1000)]


class Fault(StrEnum):
    """Why a run stopped on its own."""

    NO_CONTACT = "no_contact"  # the grasp found nothing
    FORCE_CEILING = "force_ceiling"
    STALE_SENSOR = "stale_sensor"
    DROPPED = "dropped"  # both contacts lost while rolling
    STUCK = "stuck"  # reversing on every iteration
    JOINT_ERROR = "joint_error"
    SENSOR_ERROR = "sensor_error"


def clamp_targets(
    targets: Sequence[float],
    current: Sequence[float],
    lo: Sequence[float],
    hi: Sequence[float],
    max_step: float,
) -> tuple[float, ...]:
    """Targets moved at most ``max_step`` from ``current`` and kept within [lo, hi] (degrees)."""
    out = []
    for t, c, a, b in zip(targets, current, lo, hi, strict=True):
        t = min(c + max_step, max(c - max_step, t))
        out.append(min(b, max(a, t)))
    return tuple(out)
