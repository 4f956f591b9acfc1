"""Pad profile, S → L → pad point → virtual joint (hand-model §3–§5)."""

from __future__ import annotations

import itertools
import math

import pytest

from sdh2svc.config import Settings
from sdh2svc.model.geometry import (
    L_from_x3,
    PadProfile,
    pad_point_from_L,
    pad_slope,
    pad_y3,
    virtual_joint,
    x3_from_L,
)

# hand-model §5 check values: S → L, x3, y3, r, θ (degrees)
CHECK_VALUES = [
    (0.0, 49.50, 65.29, 5.89, 65.55, 84.85),
    (20.0, 27.93, 45.35, 13.82, 47.41, 73.06),
    (40.8, 5.50, 23.00, 15.00, 27.46, 56.89),
]


@pytest.mark.parametrize(("S", "L", "x3", "y3", "r", "theta_deg"), CHECK_VALUES)
def test_check_values(cfg: Settings, S, L, x3, y3, r, theta_deg) -> None:
    pad = cfg.hand.pad
    s_range = (cfg.tactile.distal.rows - 1) * cfg.tactile.texel_pitch_mm
    got_L = cfg.calibration.distance.L_from_S(S, s_range, pad)
    got_x3, got_y3 = pad_point_from_L(got_L, pad)
    got_r, got_theta = virtual_joint(got_x3, got_y3)
    assert got_L == pytest.approx(L, abs=0.01)
    assert got_x3 == pytest.approx(x3, abs=0.01)
    assert got_y3 == pytest.approx(y3, abs=0.01)
    assert got_r == pytest.approx(r, abs=0.01)
    assert math.degrees(got_theta) == pytest.approx(theta_deg, abs=0.01)


def test_profile_continuous_and_smooth_at_boundary(pad: PadProfile) -> None:
    x = pad.flat_end_x3_mm
    eps = 1e-7
    assert pad_y3(x - eps, pad) == pytest.approx(15.0, abs=1e-9)
    assert pad_y3(x + eps, pad) == pytest.approx(15.0, abs=1e-9)
    assert pad_slope(x - eps, pad) == 0.0
    assert pad_slope(x + eps, pad) == pytest.approx(0.0, abs=1e-8)


def test_virtual_joint_continuous_at_flat_arc_boundary(pad: PadProfile) -> None:
    L = pad.flat_length_mm
    assert L == pytest.approx(16.0)
    eps = 1e-7
    below = virtual_joint(*pad_point_from_L(L - eps, pad))
    above = virtual_joint(*pad_point_from_L(L + eps, pad))
    assert below[0] == pytest.approx(above[0], abs=1e-6)
    assert below[1] == pytest.approx(above[1], abs=1e-6)
    # and the point is the boundary point itself
    assert pad_point_from_L(L, pad) == pytest.approx((33.5, 15.0))


def test_arc_is_the_circle_around_K(pad: PadProfile) -> None:
    for x3 in (34.0, 40.0, 50.0, 60.0, 66.0):
        y3 = pad_y3(x3, pad)
        assert math.hypot(x3 - 33.5, y3 - (-45.0)) == pytest.approx(60.0)


def test_slope_matches_finite_difference(pad: PadProfile) -> None:
    h = 1e-6
    for x3 in (20.0, 30.0, 35.0, 45.0, 60.0):
        fd = (pad_y3(x3 + h, pad) - pad_y3(x3 - h, pad)) / (2 * h)
        assert pad_slope(x3, pad) == pytest.approx(fd, abs=1e-5)


def test_L_x3_inverse(pad: PadProfile) -> None:
    for L in (0.0, 5.0, 15.9, 16.0, 16.1, 30.0, 49.5):
        assert L_from_x3(x3_from_L(L, pad), pad) == pytest.approx(L, abs=1e-9)


def test_a_point_off_the_pad_is_clamped_to_its_ends(pad: PadProfile) -> None:
    """A measured distance map extrapolates past its points (L beyond the tip, or below the
    base): the contact stays on the pad, at its end, not past the fingertip on a circle that is
    not there."""
    assert x3_from_L(pad.max_L_mm + 19.0, pad) == pytest.approx(pad.tip_end_x3_mm, abs=1e-9)
    assert x3_from_L(pad.max_L_mm, pad) == pytest.approx(pad.tip_end_x3_mm, abs=1e-9)
    assert x3_from_L(-3.0, pad) == pad.flat_start_x3_mm


def test_arc_length_is_curved_distance(pad: PadProfile) -> None:
    """L measures along the surface: integrate the profile's length from I to the point."""
    x_end = x3_from_L(40.0, pad)
    n = 20000
    xs = [pad.flat_start_x3_mm + (x_end - pad.flat_start_x3_mm) * i / n for i in range(n + 1)]
    length = sum(
        math.hypot(b - a, pad_y3(b, pad) - pad_y3(a, pad)) for a, b in itertools.pairwise(xs)
    )
    assert length == pytest.approx(40.0, abs=1e-3)


def test_pad_profile_rejects_disordered_points() -> None:
    with pytest.raises(ValueError, match="ordered"):
        PadProfile(
            flat_start_x3_mm=40,
            flat_end_x3_mm=33.5,
            flat_y3_mm=15,
            arc_radius_mm=60,
            tip_end_x3_mm=66.4,
            sensor_active_length_mm=44,
            pad_base_to_active_mm=5.5,
        )
