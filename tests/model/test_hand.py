"""The wire ↔ model conversion (model.hand.AxisMap, model.kinematics.HandPose): the wire's 7
axes in degrees, the model's φ2…φ5 in radians, mapped by the configured axis map."""

from __future__ import annotations

import math

import pytest

from sdh2svc.config import default_config
from sdh2svc.model.hand import AxisMap
from sdh2svc.model.kinematics import HandPose

WIRE = (1.0, 10.0, 20.0, -3.0, -4.0, 50.0, 60.0)  # default map: φ2…φ5 on wire axes 1, 2, 5, 6


def swapped() -> AxisMap:
    """Finger 1 on axes 5, 6 and Finger 2 on 1, 2: a lab that wired it the other way round."""
    return default_config().axes.model_copy(update={"phi2": 5, "phi3": 6, "phi4": 1, "phi5": 2})


def test_pose_reads_the_coupled_axes_in_radians() -> None:
    pose = default_config().axes.pose(WIRE)
    assert pose == HandPose(*(math.radians(d) for d in (10.0, 20.0, 50.0, 60.0)))
    assert swapped().pose(WIRE) == HandPose(*(math.radians(d) for d in (50.0, 60.0, 10.0, 20.0)))


def test_wire_targets_replace_only_the_coupled_axes() -> None:
    target = HandPose.from_degrees(11.0, 22.0, 55.0, 66.0)
    assert default_config().axes.wire_targets(target, WIRE) == pytest.approx(
        [1.0, 11.0, 22.0, -3.0, -4.0, 55.0, 66.0], abs=1e-12
    )
    assert swapped().wire_targets(target, WIRE) == pytest.approx(
        [1.0, 55.0, 66.0, -3.0, -4.0, 11.0, 22.0], abs=1e-12
    )


def test_wire_steps_add_degrees_to_the_coupled_axes() -> None:
    steps = (0.5, -0.5, 0.25, -0.25)
    want = [1.0, 10.5, 19.5, -3.0, -4.0, 50.25, 59.75]
    assert default_config().axes.wire_steps(steps, WIRE) == want
    assert swapped().wire_steps(steps, WIRE) == [1.0, 10.25, 19.75, -3.0, -4.0, 50.5, 59.5]


def test_the_round_trip_keeps_the_wire_angles() -> None:
    axes = swapped()
    assert axes.wire_targets(axes.pose(WIRE), WIRE) == pytest.approx(WIRE, abs=1e-12)
    assert HandPose.from_degrees(*WIRE[:4]).degrees() == pytest.approx(WIRE[:4], abs=1e-12)
