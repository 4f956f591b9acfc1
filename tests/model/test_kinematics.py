"""Forward/inverse kinematics and friction-cone angles (hand-model §2, §6, §7)."""

from __future__ import annotations

import itertools
import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sdh2svc.config import Settings
from sdh2svc.model.friction import cone_margin, inside_cone, omega, pad_tangent
from sdh2svc.model.geometry import pad_point_from_L, pad_slope, virtual_joint
from sdh2svc.model.kinematics import (
    Finger,
    FingerLimits,
    HandGeometry,
    HandPose,
    IKFailure,
    Point,
    contact_point,
    finger_ik,
    frame3_axes,
    hand_points,
    ik_branches,
    pad_gap,
    pad_point,
    segment,
)

rad = math.radians
FINGERS = [Finger.ONE, Finger.TWO]
WIDE = FingerLimits(-math.pi, math.pi, -math.pi, math.pi)


def vj_for_S(cfg: Settings, S: float) -> tuple[float, float, float]:
    pad = cfg.hand.pad
    L = cfg.calibration.distance.L_from_S(S, 40.8, pad)
    x3, y3 = pad_point_from_L(L, pad)
    r, theta = virtual_joint(x3, y3)
    return r, theta, x3


def test_mirror_pose_check_values(cfg: Settings, geom: HandGeometry) -> None:
    """hand-model §6: φ2 = φ4 = −20°, φ3 = φ5 = 30°, S1 = S2 = 20 → Λ = 82.20, ωA = ωB = 91.39°."""
    r, theta, x3 = vj_for_S(cfg, 20.0)
    pose = HandPose(rad(-20), rad(30), rad(-20), rad(30))
    P = hand_points(pose, (r, theta), (r, theta), geom)
    lam, sigma = segment(P.A, P.B)
    assert lam == pytest.approx(82.20, abs=0.005)
    assert sigma == pytest.approx(0.0, abs=1e-12)
    wa = omega(Finger.ONE, pose.phi2 + pose.phi3, x3, P.A, P.B, geom.pad)
    wb = omega(Finger.TWO, pose.phi4 + pose.phi5, x3, P.B, P.A, geom.pad)
    assert math.degrees(wa) == pytest.approx(91.39, abs=0.005)
    assert wa == pytest.approx(wb, abs=1e-12)


@settings(max_examples=200, deadline=None)
@given(
    prox=st.floats(-80, 80),
    dist=st.floats(-80, 80),
    S=st.floats(0.0, 40.8),
)
def test_mirror_pose_gives_zero_inclination_equal_omegas(cfg: Settings, prox, dist, S) -> None:
    geom = cfg.hand
    r, theta, x3 = vj_for_S(cfg, S)
    pose = HandPose(rad(prox), rad(dist), rad(prox), rad(dist))
    P = hand_points(pose, (r, theta), (r, theta), geom)
    assert P.A.z == pytest.approx(P.B.z, abs=1e-9)
    assert P.A.y + P.B.y == pytest.approx(geom.base_offset_mm, abs=1e-9)
    if P.B.y - P.A.y > 1e-6:  # fingers not crossed: σ = 0
        assert segment(P.A, P.B)[1] == pytest.approx(0.0, abs=1e-9)
    wa = omega(Finger.ONE, pose.phi2 + pose.phi3, x3, P.A, P.B, geom.pad)
    wb = omega(Finger.TWO, pose.phi4 + pose.phi5, x3, P.B, P.A, geom.pad)
    assert wa == pytest.approx(wb, abs=1e-9)


def test_omega_is_90_along_pad_normal(cfg: Settings, geom: HandGeometry) -> None:
    pad = geom.pad
    for finger in FINGERS:
        for S in (0.0, 10.0, 20.0, 35.0, 40.8):
            r, theta, x3 = vj_for_S(cfg, S)
            prox, dist = rad(-15), rad(40)
            A = contact_point(finger, prox, dist, r, theta, geom)
            t = pad_tangent(finger, prox + dist, x3, pad)
            normal = Point(-t.z, t.y)  # t rotated by 90°; either side gives 90°
            other = Point(A.y + 50 * normal.y, A.z + 50 * normal.z)
            assert math.degrees(omega(finger, prox + dist, x3, A, other, pad)) == pytest.approx(
                90.0, abs=1e-9
            )
            # tilting AB by 10° towards the tangent moves ω by exactly 10°
            c, s = math.cos(rad(10)), math.sin(rad(10))
            tilted = Point(normal.y * c + t.y * s, normal.z * c + t.z * s)
            other = Point(A.y + 50 * tilted.y, A.z + 50 * tilted.z)
            assert math.degrees(omega(finger, prox + dist, x3, A, other, pad)) == pytest.approx(
                80.0, abs=1e-9
            )


def test_parallel_flat_pads_facing_each_other_give_90(cfg: Settings, geom: HandGeometry) -> None:
    """ψ = 0 and a contact on the flat part: the pad normals are both along y0."""
    r, theta, x3 = vj_for_S(cfg, 38.0)  # L < 16: flat part
    assert x3 < geom.pad.flat_end_x3_mm
    pose = HandPose(rad(20), rad(-20), rad(20), rad(-20))
    P = hand_points(pose, (r, theta), (r, theta), geom)
    assert math.degrees(omega(Finger.ONE, 0.0, x3, P.A, P.B, geom.pad)) == pytest.approx(90.0)


def test_cone_test() -> None:
    alpha = rad(22)
    assert inside_cone(rad(90), alpha)
    assert inside_cone(rad(111.9), alpha)
    assert not inside_cone(rad(112.1), alpha)
    assert not inside_cone(rad(67.9), alpha)
    assert cone_margin(rad(100), alpha) == pytest.approx(rad(12))
    assert cone_margin(rad(120), alpha) < 0


def test_contact_point_equals_pad_point_through_frame3(cfg: Settings, geom: HandGeometry) -> None:
    """The virtual-link formula and the frame-3 axes describe the same point (hand-model §2, §4)."""
    pad = geom.pad
    for finger in FINGERS:
        for S in (0.0, 13.0, 27.0, 40.8):
            L = cfg.calibration.distance.L_from_S(S, 40.8, pad)
            x3, y3 = pad_point_from_L(L, pad)
            r, theta = virtual_joint(x3, y3)
            for prox, dist in ((0.0, 0.0), (rad(30), rad(-50)), (rad(-70), rad(85))):
                a = contact_point(finger, prox, dist, r, theta, geom)
                b = pad_point(finger, prox, dist, x3, y3, geom)
                assert a == pytest.approx(b, abs=1e-9)


def test_frame3_axes_are_orthonormal_and_ey_faces_other_finger() -> None:
    for finger in FINGERS:
        ex, ey = frame3_axes(finger, 0.0)
        assert ex.y * ey.y + ex.z * ey.z == pytest.approx(0.0)
        # straight fingers: the pad of Finger 1 faces +y0 (towards Finger 2) and vice versa
        assert ey.y == (1.0 if finger is Finger.ONE else -1.0)


def test_positive_proximal_angles_close_the_fingers(cfg: Settings, geom: HandGeometry) -> None:
    r, theta, _ = vj_for_S(cfg, 20.0)
    open_ = hand_points(HandPose(0, 0, 0, 0), (r, theta), (r, theta), geom)
    closed = hand_points(HandPose(rad(10), 0, rad(10), 0), (r, theta), (r, theta), geom)
    assert segment(closed.A, closed.B)[0] < segment(open_.A, open_.B)[0]


# --- inverse kinematics --------------------------------------------------------------------


def _check_roundtrip(cfg: Settings, finger: Finger, prox: float, dist: float, S: float) -> None:
    geom = cfg.hand
    r, theta, _ = vj_for_S(cfg, S)
    target = contact_point(finger, prox, dist, r, theta, geom)
    branches = ik_branches(finger, target, r, theta, geom)
    assert branches, "a point reached by FK must be reachable"
    for sol in branches:  # every branch reaches the target
        p = contact_point(finger, sol.proximal, sol.distal, r, theta, geom)
        assert p == pytest.approx(target, abs=1e-7)
    # nearest to the true configuration: IK recovers it
    res = finger_ik(finger, target, r, theta, (prox, dist), geom, WIDE)
    assert res.ok and res.solution is not None
    assert res.solution.proximal == pytest.approx(prox, abs=1e-6)
    assert res.solution.distal == pytest.approx(dist, abs=1e-6)


@pytest.mark.parametrize("finger", FINGERS)
def test_fk_ik_roundtrip_grid(cfg: Settings, finger: Finger) -> None:
    for prox in range(-80, 81, 20):
        for dist in range(-80, 81, 20):
            for S in (0.0, 20.0, 40.8):
                _check_roundtrip(cfg, finger, rad(prox), rad(dist), S)


@settings(max_examples=300, deadline=None)
@given(
    finger=st.sampled_from(FINGERS),
    prox=st.floats(-89.0, 89.0),
    dist=st.floats(-89.0, 89.0),
    S=st.floats(0.0, 40.8),
)
def test_fk_ik_roundtrip_property(cfg: Settings, finger, prox, dist, S) -> None:
    _check_roundtrip(cfg, finger, rad(prox), rad(dist), S)


@pytest.mark.parametrize("finger", FINGERS)
def test_both_branches_are_distinct_elbows(cfg: Settings, finger: Finger) -> None:
    geom = cfg.hand
    r, theta, _ = vj_for_S(cfg, 20.0)
    target = contact_point(finger, rad(10), rad(40), r, theta, geom)
    a, b = ik_branches(finger, target, r, theta, geom)
    assert {a.branch, b.branch} == {1, -1}
    assert abs(a.proximal - b.proximal) > rad(5)
    # starting near the other elbow picks that one
    res = finger_ik(finger, target, r, theta, (b.proximal, b.distal), geom, WIDE)
    assert res.solution == b


@pytest.mark.parametrize("finger", FINGERS)
def test_ik_rejects_unreachable_target(cfg: Settings, finger: Finger) -> None:
    geom = cfg.hand
    r, theta, _ = vj_for_S(cfg, 20.0)
    base = Point(0.0, 0.0) if finger is Finger.ONE else Point(geom.base_offset_mm, 0.0)
    far = Point(base.y, base.z + geom.proximal_length_mm + r + 1.0)
    res = finger_ik(finger, far, r, theta, (0.0, 0.0), geom, WIDE)
    assert not res.ok and res.failure is IKFailure.OUT_OF_WORKSPACE
    near = Point(base.y, base.z + abs(geom.proximal_length_mm - r) - 1.0)
    assert finger_ik(finger, near, r, theta, (0.0, 0.0), geom, WIDE).failure is (
        IKFailure.OUT_OF_WORKSPACE
    )


@pytest.mark.parametrize("finger", FINGERS)
def test_ik_rejects_joint_limit_violation(cfg: Settings, finger: Finger) -> None:
    geom = cfg.hand
    limits = cfg.finger_limits(finger)
    r, theta, _ = vj_for_S(cfg, 20.0)
    # a target that needs a distal angle beyond +90° on either elbow
    target = contact_point(finger, rad(-10), rad(120), r, theta, geom)
    res = finger_ik(finger, target, r, theta, (0.0, 0.0), geom, limits)
    assert not res.ok and res.failure is IKFailure.JOINT_LIMITS
    assert len(res.candidates) == 2
    assert all(not limits.contains(c.proximal, c.distal) for c in res.candidates)


@pytest.mark.parametrize("finger", FINGERS)
def test_ik_never_folds_the_finger_the_other_way_past_a_limit(
    cfg: Settings, finger: Finger
) -> None:
    """A joint 0.5° inside a limit and a target that needs it 0.5° past, where the other elbow
    fits within the limits: the target is refused (hand-model §7), never reached by folding
    the finger the other way; 0.5° inside the limit instead, it is reached as it is."""
    geom, lim = cfg.hand, cfg.finger_limits(finger)
    r, theta, _ = vj_for_S(cfg, 20.0)
    tried = 0
    edges = (
        (0, lim.proximal_max, 1),
        (0, lim.proximal_min, -1),
        (1, lim.distal_max, 1),
        (1, lim.distal_min, -1),
    )  # (joint, limit, outwards)
    for (joint, edge, out), other_deg in itertools.product(edges, range(-80, 81, 10)):

        def pose(off_deg: float, joint: int = joint, edge: float = edge, out: int = out,
                 other: float = rad(other_deg)) -> tuple[float, float]:  # fmt: skip
            """The joint ``off_deg`` beyond its limit (inside if negative), the other at
            ``other``."""
            at = edge + out * rad(off_deg)
            return (at, other) if joint == 0 else (other, at)

        now, past, inside = pose(-0.5), pose(0.5), pose(-1.0)
        target = contact_point(finger, *past, r, theta, geom)
        res = finger_ik(finger, target, r, theta, now, geom, lim)
        if not any(lim.contains(c.proximal, c.distal) for c in res.candidates):
            continue  # both elbows past a limit: refused either way
        tried += 1
        assert not res.ok and res.failure is IKFailure.JOINT_LIMITS, now
        to = contact_point(finger, *inside, r, theta, geom)
        near = finger_ik(finger, to, r, theta, now, geom, lim).solution
        assert near is not None and (near.proximal, near.distal) == pytest.approx(inside)
    assert tried >= 5  # poses whose other elbow fits were found and checked


def test_ik_solutions_respect_limits(cfg: Settings, geom: HandGeometry) -> None:
    limits = cfg.finger_limits(Finger.ONE)
    r, theta, _ = vj_for_S(cfg, 10.0)
    target = contact_point(Finger.ONE, rad(30), rad(60), r, theta, geom)
    res = finger_ik(Finger.ONE, target, r, theta, (rad(30), rad(60)), geom, limits)
    assert res.solution is not None
    assert limits.contains(res.solution.proximal, res.solution.distal)


def test_slope_is_used_in_tangent(cfg: Settings, geom: HandGeometry) -> None:
    """On the arc the tangent tilts away from ex3 by atan(slope)."""
    _, _, x3 = vj_for_S(cfg, 5.0)
    t = pad_tangent(Finger.ONE, 0.0, x3, geom.pad)
    assert math.atan2(-t.y, t.z) == pytest.approx(math.atan(-pad_slope(x3, geom.pad)), abs=1e-12)


def test_the_pads_gap_is_the_distance_between_their_flat_parts_when_upright(cfg: Settings) -> None:
    g, pad = cfg.hand, cfg.hand.pad
    for phi2 in (-30.0, -10.0, 0.0, 5.0):  # upright and facing: the flat parts bound the gap
        pose = HandPose.from_degrees(phi2, -phi2, phi2, -phi2)
        c = pad_point(Finger.ONE, rad(phi2), rad(-phi2), pad.flat_start_x3_mm, pad.flat_y3_mm, g)
        d = pad_point(Finger.TWO, rad(phi2), rad(-phi2), pad.flat_start_x3_mm, pad.flat_y3_mm, g)
        assert pad_gap(pose, g) == pytest.approx(d.y - c.y, abs=1e-9)
    assert pad_gap(HandPose.from_degrees(-30, 30, -30, 30), g) == pytest.approx(122.5, abs=0.1)
    # closing in the mirror pose, the gap shrinks to nothing as the pads meet
    gaps = [pad_gap(HandPose.from_degrees(a, -a, a, -a), g) for a in range(-30, 12)]
    assert all(b < a for a, b in itertools.pairwise(gaps)) and gaps[-1] < 10.0
    # tilted towards each other, their tips meet first
    tilted = HandPose.from_degrees(5, 10, 5, 10)
    assert pad_gap(tilted, g) < pad_gap(HandPose.from_degrees(5, -5, 5, -5), g)
