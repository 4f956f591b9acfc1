"""The rolling step on hand-built situations (hand-model §8)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sdh2svc.config import Settings
from sdh2svc.control.params import RollingParams
from sdh2svc.control.rolling import (
    ESCAPE_AFTER,
    FOLLOW_SLACK,
    RETREAT_LIMIT,
    TURN_MARGIN,
    WAY_BACK,
    Reversal,
    RollState,
    StepResult,
    _adjusted_lambda,
    step,
)
from sdh2svc.control.sample import Sample
from sdh2svc.model.kinematics import Finger, HandPose, Point, contact_point, segment

rad = math.radians
MIRROR = HandPose(rad(-20), rad(30), rad(-20), rad(30))


def frame(S: float, amplitude: float = 1000.0) -> np.ndarray:
    """A distal frame whose pressure centroid is exactly S (two neighbouring rows)."""
    m = np.zeros((13, 6), dtype=np.uint16)
    j = min(int(S // 3.4), 11)
    w = S / 3.4 - j
    m[j, 1:5] = round(amplitude * (1 - w))
    m[j + 1, 1:5] = round(amplitude * w)
    return m


def params(cfg: Settings, **kw: object) -> RollingParams:
    """The configured parameters with ``kw``; Finger 1's step unlimited unless given, so that
    each iteration takes the route's full step."""
    return cfg.rolling.model_copy(update={"finger1_max_step_deg": 10.0, **kw})


RUNNING = RollState(iteration=1)  # after the first iteration (see RollState.alpha_held)
TILTED = HandPose(rad(-20), rad(30), rad(-14), rad(26))  # σ ≠ 0


@pytest.mark.parametrize("pose", [MIRROR, TILTED], ids=["mirror", "tilted"])
def test_normal_step_follows_the_route(cfg: Settings, pose: HandPose) -> None:
    ctx, p = cfg.model_context(), params(cfg)
    r = step(RollState(), pose, frame(20.0), frame(24.0), p, ctx)
    assert r.reversal is None and r.targets is not None and r.plan is not None
    t = r.targets
    # Finger 2's route: φ4 − Δφ, φ5 + k·Δφ
    assert t.phi4 == pytest.approx(pose.phi4 - rad(0.25))
    assert t.phi5 == pytest.approx(pose.phi5 + 2 * rad(0.25))
    c1, c2 = r.obs.contact1, r.obs.contact2
    A_d = contact_point(Finger.ONE, t.phi2, t.phi3, c1.r_mm, c1.theta_rad, ctx.geom)
    B_d = contact_point(Finger.TWO, t.phi4, t.phi5, c2.r_mm, c2.theta_rad, ctx.geom)
    assert A_d == pytest.approx(r.plan.A_d, abs=1e-9)  # IK puts A exactly on Ad
    assert B_d == pytest.approx(r.plan.B_d, abs=1e-9)
    lam, sig = segment(A_d, B_d)
    assert lam == pytest.approx(r.plan.Lambda_ad) and sig == pytest.approx(r.plan.sigma_d)
    # σd = σc + λ·(σ(Ac→Bd) − σc)
    sigma_c = r.obs.sigma
    d_sigma = segment(r.obs.points.A, B_d)[1] - sigma_c
    assert r.plan.sigma_d == pytest.approx(sigma_c + 5.0 * d_sigma)
    assert abs(d_sigma) > 1e-4  # Finger 2's move does tilt AB
    assert r.state.iteration == 1 and r.state.direction == 1 and r.state.F_prev == r.F


def test_finger1_step_limit_slows_the_whole_iteration(cfg: Settings) -> None:
    """Finger 1 needing more than its largest step: the iteration is taken at the fraction of Δφ
    that keeps it (about) within the limit, still on the route and with A on the circle."""
    ctx = cfg.model_context()
    free = step(RollState(), TILTED, frame(20.0), frame(24.0),
                params(cfg, finger1_max_step_deg=10.0), ctx)  # fmt: skip
    assert free.targets is not None
    need = max(abs(free.targets.phi2 - TILTED.phi2), abs(free.targets.phi3 - TILTED.phi3))
    assert free.targets.phi4 == pytest.approx(TILTED.phi4 - rad(0.25))  # the full step
    limit = math.degrees(need) / 4
    r = step(RollState(), TILTED, frame(20.0), frame(24.0),
             params(cfg, finger1_max_step_deg=limit), ctx)  # fmt: skip
    assert r.reversal is None and r.targets is not None and r.plan is not None
    t = r.targets
    taken = max(abs(t.phi2 - TILTED.phi2), abs(t.phi3 - TILTED.phi3))
    assert math.degrees(taken) == pytest.approx(limit, rel=0.1)
    scale = (TILTED.phi4 - t.phi4) / rad(0.25)
    assert 0.15 < scale < 0.35  # Finger 2 slowed by the same factor …
    assert t.phi5 - TILTED.phi5 == pytest.approx(2 * (TILTED.phi4 - t.phi4))  # … on its route
    c1 = r.obs.contact1
    A_d = contact_point(Finger.ONE, t.phi2, t.phi3, c1.r_mm, c1.theta_rad, ctx.geom)
    assert A_d == pytest.approx(r.plan.A_d, abs=1e-9)
    assert segment(r.plan.A_d, r.plan.B_d)[0] == pytest.approx(r.plan.Lambda_ad)


@pytest.mark.parametrize(
    ("prev_F_delta", "expected"), [(-0.3, 0.7), (0.3, -0.3), (0.0, 0.0), (0.1, 0.0), (-0.1, 0.0)]
)
def test_delta_lambda_sign_logic(cfg: Settings, prev_F_delta: float, expected: float) -> None:
    """Rising force → open by ΔΛ_inc (0.7 mm here); falling → close by ΔΛ_dec (0.3 mm); a
    change within the deadband (0.15) → keep Λ. (The force band off: the thesis's rule alone.)"""
    ctx = cfg.model_context()
    p = params(cfg, delta_lambda_inc_mm=0.7, delta_lambda_dec_mm=0.3, force_band_low=0.0,
               force_band_high=20.0)  # fmt: skip
    F = step(RollState(), MIRROR, frame(20.0), frame(20.0), p, ctx).F
    r = step(RollState(F_prev=F + prev_F_delta), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert r.dF == pytest.approx(-prev_F_delta)
    assert r.plan.Lambda_ad == pytest.approx(r.obs.Lambda + expected)


@pytest.mark.parametrize(
    ("level", "prev_F_delta", "expected"),
    [
        (0.5, 0.0, -0.3),  # below the band, steady: close
        (0.5, 0.3, -0.3),  # below, still falling: close
        (0.5, -0.3, 0.0),  # below, but rising again: hold (never open below the band)
        (1.5, 0.0, 0.7),  # above, steady: open
        (1.5, -0.3, 0.7),  # above, still rising: open
        (1.5, 0.3, 0.0),  # above, but falling again: hold (never close above the band)
        (0.9, 0.0, 0.0),  # inside the band: the ΔF rule alone
        (0.9, 0.3, -0.3),
    ],
)
def test_force_band_decides_outside(
    cfg: Settings, level: float, prev_F_delta: float, expected: float
) -> None:
    """F at ``level`` × Fd with the band [0.75, 1.0] × Fd: outside it the level decides, and
    a force already heading back into the band holds Λ."""
    ctx = cfg.model_context()
    base = params(cfg, delta_lambda_inc_mm=0.7, delta_lambda_dec_mm=0.3, force_band_low=0.75,
                  force_band_high=1.0)  # fmt: skip
    F = step(RollState(), MIRROR, frame(20.0), frame(20.0), base, ctx).F
    p = base.model_copy(update={"grasp_force": F / level})
    r = step(RollState(F_prev=F + prev_F_delta), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert r.F / p.grasp_force == pytest.approx(level)
    assert r.plan.Lambda_ad == pytest.approx(r.obs.Lambda + expected)


@pytest.mark.parametrize("lag", [0, 1])
@pytest.mark.parametrize("stiffness", [2.0, 5.0])
def test_force_band_reaches_the_band_on_a_stiff_object(
    cfg: Settings, stiffness: float, lag: int
) -> None:
    """A stiff object (``stiffness`` force units per mm: one 0.1 mm step moves F by 0.1–0.25 ×
    Fd) whose grip follows the held distance ``lag`` iterations late, starting at 0.3 × Fd:
    F enters the band and then stays within one step of it. (Opening on the rise its own
    closing causes, below the band, kept F below it for ever.)"""
    p = cfg.rolling
    fd, width = p.grasp_force, 30.0
    held = [width - 0.3 * fd / stiffness] * (lag + 1)
    F_prev: float | None = None
    levels = []
    for _ in range(60):
        F = stiffness * (width - held[-1 - lag])
        levels.append(F / fd)
        held.append(_adjusted_lambda(held[-1], F, 0.0 if F_prev is None else F - F_prev, p))
        F_prev = F
    entered = next(i for i, f in enumerate(levels) if p.force_band_low <= f <= p.force_band_high)
    one_step = stiffness * p.delta_lambda_dec_mm / fd
    assert entered < 20
    after = levels[entered:]
    assert min(after) >= p.force_band_low - one_step - 1e-9
    assert max(after) <= p.force_band_high + one_step + 1e-9


def test_force_band_must_be_ordered(cfg: Settings) -> None:
    with pytest.raises(ValueError, match=r"force_band_low .* must not exceed force_band_high"):
        RollingParams.model_validate(
            {**cfg.rolling.model_dump(), "force_band_low": 1.5, "force_band_high": 1.0}
        )


def test_contact_lost_reverses(cfg: Settings) -> None:
    ctx = cfg.model_context()
    r = step(RollState(), MIRROR, frame(20.0), np.zeros((13, 6), np.uint16), params(cfg), ctx)
    assert r.reversal is Reversal.CONTACT_LOST and r.targets is None
    assert r.state.direction == -1
    assert r.state.half_strokes == 0  # reversed before it ever moved: no half stroke
    weak = frame(20.0, amplitude=15.0)  # present on the pad, but below contact_force_min
    r = step(RollState(), MIRROR, frame(20.0), weak, params(cfg), ctx)
    assert r.reversal is Reversal.CONTACT_LOST


def test_contact_at_pad_edge_reverses(cfg: Settings) -> None:
    m = np.zeros((13, 6), np.uint16)
    m[0, 1:5] = 1500  # on the first row, at the fingertip's end
    r = step(RollState(), MIRROR, m, frame(20.0), params(cfg), cfg.model_context())
    assert r.reversal is Reversal.CONTACT_EDGE


def test_cone_a_reverses(cfg: Settings) -> None:
    """In the mirror pose ωA ≈ 91.4°: a cone of ±1° is left at once, at A first."""
    r = step(RUNNING, MIRROR, frame(20.0), frame(20.0), params(cfg, alpha_deg=1.0),
             cfg.model_context())  # fmt: skip
    assert r.reversal is Reversal.CONE_A
    assert abs(math.degrees(r.plan.omega_A_d) - 90) >= 1.0


def test_cone_b_reverses(cfg: Settings) -> None:
    """Tilting Finger 2's pad alone: ωA stays inside, ωB leaves the cone."""
    ctx, p = cfg.model_context(), params(cfg, alpha_deg=10.0, lambda_gain=0.0)
    found = None
    for phi5 in range(30, 70):
        pose = HandPose(rad(-20), rad(30), rad(-20), rad(phi5))
        r = step(RUNNING, pose, frame(20.0), frame(20.0), p, ctx)
        if r.reversal is Reversal.CONE_B:
            found = r
            break
        assert r.reversal in (None, Reversal.CONE_B)
    assert found is not None
    assert abs(math.degrees(found.plan.omega_A_d) - 90) < 10.0
    assert abs(math.degrees(found.plan.omega_B_d) - 90) >= 10.0


def _past_cone_b(cfg: Settings, p: RollingParams, beyond_deg: float) -> HandPose:
    """A pose whose measured ωB is more than ``beyond_deg`` outside the cone."""
    for tenth in range(300, 900):
        pose = HandPose(rad(-20), rad(30), rad(-20), rad(tenth / 10))
        w = step(RollState(), pose, frame(20.0), frame(20.0), p, cfg.model_context()).obs.omega_B
        if abs(math.degrees(w) - 90) > p.alpha_deg + beyond_deg:
            return pose
    raise AssertionError("no pose found")


def test_the_way_back_from_a_cone_the_contact_already_left(cfg: Settings) -> None:
    """ωB already outside (the rolling contact overshot): the thesis's rule refuses both
    directions; after a reversal the way back is not refused by a cone until Finger 2 has
    travelled WAY_BACK half strokes, unless the plan goes beyond the cone by RETREAT_LIMIT."""
    ctx, p = cfg.model_context(), params(cfg, alpha_deg=10.0, lambda_gain=0.0)
    pose = _past_cone_b(cfg, p, beyond_deg=1.0)
    m = frame(20.0)
    for d in (1, -1):  # nothing waived: the thesis's rule
        r = step(replace(RUNNING, direction=d), pose, m, m, p, ctx)
        assert r.reversal is Reversal.CONE_B and r.state.waived is Reversal.CONE_B
    back = RollState(direction=1, iteration=9, waived=Reversal.CONE_B)
    r = step(back, pose, m, m, p, ctx)
    assert r.reversal is None and r.targets is not None
    assert r.state.travel == pytest.approx(rad(0.25)) and r.state.waived is Reversal.CONE_B
    # waived while the way back is shorter than WAY_BACK half strokes, and only so long
    way = WAY_BACK * p.min_half_stroke
    assert step(replace(back, travel=0.99 * way), pose, m, m, p, ctx).reversal is None
    r = step(replace(back, travel=way, turned=rad(2.0)), pose, m, m, p, ctx)
    assert r.reversal is Reversal.CONE_B and r.state.half_strokes == 1
    # the way back from another check (cone A, the pad's edge, Finger 1's reach, a joint limit)
    # passes cone B as well: at the end of a stroke one check stops one way and another the
    # other way
    for other in (Reversal.CONE_A, Reversal.CONTACT_EDGE, Reversal.WEDGE,
                  Reversal.IK_UNREACHABLE, Reversal.WORKSPACE):  # fmt: skip
        assert step(replace(back, waived=other), pose, m, m, p, ctx).reversal is None
    # nor a plan beyond cone B by more than RETREAT_LIMIT
    far = _past_cone_b(cfg, p, beyond_deg=math.degrees(RETREAT_LIMIT) + 1.0)
    assert step(back, far, m, m, p, ctx).reversal is Reversal.CONE_B


def test_the_way_back_from_a_cone_retreats_on_while_its_contact_is_outside(
    cfg: Settings,
) -> None:
    """Once the way back from a cone is travelled, a contact still outside that cone but
    leaning less than at the reversal is not refused as a new lean: a plan that leans it less
    than it leans now (and no more than RETREAT_LIMIT beyond) goes on. A contact that leans as
    far as at the reversal (sliding at its friction angle), a plan that leans it further, the
    way back from the other cone, or a plan beyond RETREAT_LIMIT are refused."""
    ctx, p = cfg.model_context(), params(cfg, alpha_deg=10.0, lambda_gain=0.0)
    pose = _past_cone_b(cfg, p, beyond_deg=0.5)
    m = frame(20.0)
    leans = {}
    for d in (1, -1):
        r = step(replace(RUNNING, direction=d), pose, m, m, p, ctx)
        assert r.reversal is Reversal.CONE_B  # the thesis's rule: outside, either way
        assert r.state.lean == pytest.approx(abs(r.obs.omega_B - math.pi / 2))
        leans[d] = abs(r.plan.omega_B_d - math.pi / 2) - abs(r.obs.omega_B - math.pi / 2)
    back, out = min(leans, key=leans.get), max(leans, key=leans.get)
    assert leans[back] < 0.0 < leans[out]  # one way retreats, the other leans further
    now = abs(r.obs.omega_B - math.pi / 2)
    done = RollState(direction=back, iteration=9, waived=Reversal.CONE_B, lean=now + rad(0.5),
                     travel=WAY_BACK * p.min_half_stroke, consecutive_reversals=1)  # fmt: skip
    r = step(done, pose, m, m, p, ctx)
    assert r.reversal is None and r.targets is not None
    assert step(replace(done, lean=now), pose, m, m, p, ctx).reversal is Reversal.CONE_B
    assert step(replace(done, direction=out), pose, m, m, p, ctx).reversal is Reversal.CONE_B
    assert step(replace(done, waived=Reversal.CONE_A), pose, m, m, p,
                ctx).reversal is Reversal.CONE_B  # fmt: skip
    far = _past_cone_b(cfg, p, beyond_deg=math.degrees(RETREAT_LIMIT) + 1.0)
    assert step(done, far, m, m, p, ctx).reversal is Reversal.CONE_B


def test_the_way_back_from_the_pad_edge(cfg: Settings) -> None:
    """A contact on the edge row reverses the rotation; the way back passes while the contact
    is still there (a reversal moves nothing, so the thesis's rule would repeat for ever)."""
    ctx, p = cfg.model_context(), params(cfg)
    edge = np.zeros((13, 6), np.uint16)
    edge[12, 1:5] = 1500  # on the last row
    r = step(RollState(iteration=5, travel=rad(3.0), turned=rad(3.0)), MIRROR, edge, edge, p, ctx)
    assert r.reversal is Reversal.CONTACT_EDGE and r.state.waived is Reversal.CONTACT_EDGE
    assert r.state.half_strokes == 1 and r.state.direction == -1 and r.state.travel == 0
    r = step(r.state, MIRROR, edge, edge, p, ctx)
    assert r.reversal is None and r.targets is not None  # on its way back
    s = replace(r.state, travel=WAY_BACK * p.min_half_stroke)  # the way back's end: it counts
    assert step(s, MIRROR, edge, edge, p, ctx).reversal is Reversal.CONTACT_EDGE
    # the way back from a cone passes the edge too
    back = replace(r.state, waived=Reversal.CONE_A)
    assert step(back, MIRROR, edge, edge, p, ctx).reversal is None
    # the way back from a reversal that waives nothing (Finger 1's reach, a joint limit) passes
    # the edge as well: it retraces the travel that carried the contact there
    reach = replace(back, waived=None)
    assert step(reach, MIRROR, edge, edge, p, ctx).reversal is None
    # before any reversal, and once the way back is travelled, the edge refuses
    assert step(replace(reach, consecutive_reversals=0), MIRROR, edge, edge, p,
                ctx).reversal is Reversal.CONTACT_EDGE  # fmt: skip
    far = replace(reach, travel=WAY_BACK * p.min_half_stroke)
    assert step(far, MIRROR, edge, edge, p, ctx).reversal is Reversal.CONTACT_EDGE


def test_a_dither_at_the_pad_edge_gives_up_the_edge_rows_inner_half(cfg: Settings) -> None:
    """After ESCAPE_AFTER reversals in a row without a half stroke (and off the way back), a
    contact on the edge row's inner half no longer reverses the rotation; one near the last
    row's centre, rolling off the pad, still does."""
    ctx, p = cfg.model_context(), params(cfg)
    pitch, last = ctx.pitch_mm, ctx.distal.rows - 1
    inner = frame((last - 0.4) * pitch)  # within edge_margin_rows (0.5), not within half of it
    outer = frame(last * pitch)
    fresh = RollState(iteration=5, travel=rad(3.0), consecutive_reversals=1)
    dithering = replace(fresh, consecutive_reversals=ESCAPE_AFTER)
    assert step(fresh, MIRROR, inner, frame(20.0), p, ctx).reversal is Reversal.CONTACT_EDGE
    assert step(dithering, MIRROR, inner, frame(20.0), p, ctx).reversal is None
    # (Finger 2's contact that far out leaves cone B at this pose: another check, not the edge)
    assert step(dithering, MIRROR, frame(20.0), inner, p, ctx).reversal is not Reversal.CONTACT_EDGE
    assert step(dithering, MIRROR, outer, frame(20.0), p, ctx).reversal is Reversal.CONTACT_EDGE
    assert step(dithering, MIRROR, frame(20.0), outer, p, ctx).reversal is Reversal.CONTACT_EDGE


def _roll(s: RollState, pose: HandPose, n: int, p: RollingParams, cfg: Settings,
          lost: bool = False) -> tuple[RollState, HandPose]:  # fmt: skip
    """``n`` iterations with the fingers where the last one commanded them (the object turns
    with the pads: the contacts stay where they are on both), then one with Finger 2's
    contact lost when ``lost``."""
    ctx = cfg.model_context()
    for _ in range(n):
        r = step(s, pose, frame(20.0), frame(20.0), p, ctx)
        s, pose = r.state, r.targets or pose
    if lost:
        s = step(s, pose, frame(20.0), np.zeros((13, 6), np.uint16), p, ctx).state
    return s, pose


def test_a_half_stroke_counts_only_after_finger2_travelled(cfg: Settings) -> None:
    p = params(cfg)
    # three steps of 0.25°: less than the 1° a half stroke needs
    s, pose = _roll(RollState(), MIRROR, 3, p, cfg)
    assert s.travel == pytest.approx(rad(0.75)) and s.turned > TURN_MARGIN * p.min_half_stroke
    s, pose = _roll(s, pose, 0, p, cfg, lost=True)
    assert s.half_strokes == 0 and s.consecutive_reversals == 1 and s.travel == 0
    assert s.waived is None  # a lost contact waives nothing on the way back
    s, pose = _roll(s, pose, 4, p, cfg, lost=True)
    assert s.half_strokes == 1 and s.consecutive_reversals == 1
    assert s.turn == 0.0 and s.turned == 0.0  # the next half stroke's turn starts afresh


def test_a_half_stroke_counts_only_once_the_object_turned(cfg: Settings) -> None:
    """Finger 2 travels its half stroke, but the fingers never get where they were sent (the
    pads, and the object, stay put: a dither at a cone or the pad's end): the reversal ends
    no half stroke and counts towards 'stuck' instead."""
    ctx, p = cfg.model_context(), params(cfg)
    s = RollState()
    for _ in range(6):  # the same pose every time: no rolling
        s = step(s, MIRROR, frame(20.0), frame(20.0), p, ctx).state
    assert s.travel >= p.min_half_stroke and s.turned == 0.0
    s = step(s, MIRROR, frame(20.0), np.zeros((13, 6), np.uint16), p, ctx).state
    assert s.half_strokes == 0 and s.consecutive_reversals == 1
    # it turned, but less than the margin over the estimate's error asks
    s = replace(s, travel=rad(2.0), turned=0.99 * TURN_MARGIN * p.min_half_stroke)
    s = step(s, MIRROR, frame(20.0), np.zeros((13, 6), np.uint16), p, ctx).state
    assert s.half_strokes == 0 and s.consecutive_reversals == 2
    s = replace(s, travel=rad(2.0), turned=1.01 * TURN_MARGIN * p.min_half_stroke)
    s = step(s, MIRROR, frame(20.0), np.zeros((13, 6), np.uint16), p, ctx).state
    assert s.half_strokes == 1 and s.consecutive_reversals == 1


def test_workspace_reverses_at_joint_limit(cfg: Settings) -> None:
    pose = HandPose(rad(-20), rad(30), rad(-89.9), rad(30))  # φ4 − Δφ would pass −90°
    r = step(RollState(), pose, frame(20.0), frame(20.0), params(cfg), cfg.model_context())
    assert r.reversal is Reversal.WORKSPACE and r.state.waived is Reversal.WORKSPACE
    # the other way round the same pose is fine for Finger 2
    r = step(RollState(direction=-1), pose, frame(20.0), frame(20.0), params(cfg),
             cfg.model_context())  # fmt: skip
    assert r.reversal is not Reversal.WORKSPACE


def test_ik_unreachable_reverses(cfg: Settings) -> None:
    """A huge reinforcement λ swings Ad out of Finger 1's reach."""
    ctx = cfg.model_context()
    p = params(cfg, lambda_gain=50.0, delta_phi_deg=5.0)
    r = step(RollState(), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert r.reversal is Reversal.IK_UNREACHABLE and r.state.waived is Reversal.IK_UNREACHABLE
    c1 = r.obs.contact1
    d = math.hypot(r.plan.A_d.y, r.plan.A_d.z)
    l1 = cfg.hand.proximal_length_mm
    assert d > l1 + c1.r_mm or d < abs(l1 - c1.r_mm)


def test_parameter_change_applies_at_next_iteration(cfg: Settings) -> None:
    ctx = cfg.model_context()
    r1 = step(RollState(), MIRROR, frame(20.0), frame(20.0), params(cfg), ctx)
    faster = params(cfg, delta_phi_deg=0.5, k=3.0)
    r2 = step(r1.state, r1.targets, frame(20.0), frame(20.0), faster, ctx)
    assert r2.targets.phi4 == pytest.approx(r1.targets.phi4 - rad(0.5))
    assert r2.targets.phi5 == pytest.approx(r1.targets.phi5 + 3 * rad(0.5))


def test_reversal_flips_direction_and_counts_strokes(cfg: Settings) -> None:
    ctx, p = cfg.model_context(), params(cfg)
    empty = np.zeros((13, 6), np.uint16)
    s, pose = RollState(), MIRROR
    for _ in range(4):  # move a half stroke's travel, then reverse: four half strokes
        s, pose = _roll(s, pose, 4, p, cfg, lost=True)
        assert s.consecutive_reversals == 1
    assert s.half_strokes == 4 and s.strokes == 2 and s.direction == 1
    for _ in range(3):  # reversing on the spot is not a half stroke
        s = step(s, pose, frame(20.0), empty, p, ctx).state
    assert s.half_strokes == 4 and s.consecutive_reversals == 4 and s.direction == -1
    r = step(RollState(direction=-1), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert r.targets.phi4 == pytest.approx(MIRROR.phi4 + rad(0.25))  # reversed route


def test_one_finger_mode_turns_A_around_B(cfg: Settings) -> None:
    ctx = cfg.model_context()
    p = params(cfg, mode="one-finger", d_sigma_deg=0.5)
    r = step(RollState(), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert r.reversal is None
    assert (r.targets.phi4, r.targets.phi5) == (MIRROR.phi4, MIRROR.phi5)  # Finger 2 holds
    B = r.obs.points.B
    assert r.plan.B_d == B
    A_d = contact_point(Finger.ONE, r.targets.phi2, r.targets.phi3, r.obs.contact1.r_mm,
                        r.obs.contact1.theta_rad, ctx.geom)  # fmt: skip
    lam, sig = segment(A_d, B)
    assert sig == pytest.approx(r.obs.sigma + rad(0.5))
    assert lam == pytest.approx(r.plan.Lambda_ad)
    assert isinstance(A_d, Point)


def test_the_cones_are_as_wide_as_the_grasp_held(cfg: Settings) -> None:
    """A grasp that ended with ωB beyond α shows the object holds there: from the first
    iteration on, the cones are that wide, and the run can start (the thesis's rule refuses
    both directions)."""
    ctx, p = cfg.model_context(), params(cfg, alpha_deg=10.0, lambda_gain=0.0)
    pose = _past_cone_b(cfg, p, beyond_deg=1.0)
    m = frame(20.0)
    r = step(RollState(), pose, m, m, p, ctx)
    held = abs(r.obs.omega_B - math.pi / 2)
    assert r.state.alpha_held == pytest.approx(held) and held > rad(10.0)
    assert r.reversal is None or r.reversal is Reversal.CONE_B
    assert step(replace(r.state, direction=-r.state.direction) if r.reversal else r.state,
                pose, m, m, p, ctx).state.alpha_held == pytest.approx(held)  # fmt: skip
    moved = [step(RollState(direction=d), pose, m, m, p, ctx).reversal for d in (1, -1)]
    assert None in moved  # at least one way to start
    assert all(step(replace(RUNNING, direction=d), pose, m, m, p, ctx).reversal
               is Reversal.CONE_B for d in (1, -1))  # fmt: skip


def test_a_cone_that_refuses_its_own_way_back_widens_to_what_its_contact_holds(
    cfg: Settings,
) -> None:
    """ωB far outside the cone, and cone B refuses the way back from its own reversal: it
    refuses both directions while contact B holds the object there. The cones then widen to
    ωB's angle now (the object's friction angle is at least that), and the way back passes.
    A first refusal, one on the way back from another check, or one after the way back do not
    widen them."""
    ctx, p = cfg.model_context(), params(cfg, alpha_deg=10.0, lambda_gain=0.0)
    far = _past_cone_b(cfg, p, beyond_deg=math.degrees(RETREAT_LIMIT) + 1.0)
    m = frame(20.0)
    back = RollState(direction=1, iteration=9, waived=Reversal.CONE_B)
    r = step(back, far, m, m, p, ctx)
    held = abs(r.obs.omega_B - math.pi / 2)
    assert r.reversal is Reversal.CONE_B
    assert r.state.alpha_held == pytest.approx(held) and held > rad(10.0) + RETREAT_LIMIT
    assert r.alpha == pytest.approx(held)  # the cones from now on, as recorded and drawn
    assert Sample.from_step(r, far, 1.0, 0.0, 0.0, 0.0).alpha == pytest.approx(math.degrees(held))
    again = step(r.state, far, m, m, p, ctx)  # the other way, from the same pose
    assert again.reversal is None and again.targets is not None
    assert again.state.alpha_held == pytest.approx(held)  # kept for the rest of the run
    assert again.alpha == pytest.approx(held)
    way = WAY_BACK * p.min_half_stroke
    for other in (RUNNING, replace(back, waived=Reversal.CONE_A),
                  replace(back, travel=way)):  # fmt: skip
        r = step(other, far, m, m, p, ctx)
        assert r.reversal is Reversal.CONE_B and r.state.alpha_held == 0.0
        assert r.alpha == pytest.approx(p.alpha)


def test_a_plan_that_widens_the_wedge_beyond_its_limit_reverses(cfg: Settings) -> None:
    """Both pads tilted apart (both ω on the same side of 90°): within wide cones, a plan that
    widens the wedge beyond ``wedge_limit_deg`` reverses; one that narrows it passes."""
    ctx = cfg.model_context()
    wedged = HandPose(rad(-20), rad(40), rad(-20), rad(40))
    m = frame(20.0)
    loose = params(cfg, alpha_deg=40.0, wedge_limit_deg=0.0)
    plans = {d: step(replace(RUNNING, direction=d), wedged, m, m, loose, ctx) for d in (1, -1)}
    r0 = plans[1]
    now = abs((r0.obs.omega_A + r0.obs.omega_B) / 2 - math.pi / 2)
    assert all(r.reversal is None for r in plans.values())
    wedge = {d: abs((r.plan.omega_A_d + r.plan.omega_B_d) / 2 - math.pi / 2)
             for d, r in plans.items()}  # fmt: skip
    wider = max(wedge, key=wedge.get)
    narrower = -wider
    assert wedge[wider] > now
    limit = math.degrees(now) - 0.5  # already beyond it
    p = params(cfg, alpha_deg=40.0, wedge_limit_deg=limit)
    r = step(replace(RUNNING, direction=wider), wedged, m, m, p, ctx)
    assert r.reversal is Reversal.WEDGE and r.state.waived is Reversal.WEDGE
    if wedge[narrower] < now:
        assert step(replace(RUNNING, direction=narrower), wedged, m, m, p, ctx).reversal is None
    # the way back is waived like a cone's
    r = step(replace(RUNNING, direction=wider, waived=Reversal.WEDGE), wedged, m, m, p, ctx)
    assert r.reversal is None


@pytest.mark.parametrize(
    ("level", "prev_F_delta", "reverses"),
    [
        (2.2, 0.3, True),  # above force_reverse × Fd and rising
        (2.2, 0.0, True),  # above and steady: the opening did not bring it back
        (2.2, -0.3, False),  # above but falling: the opening works, go on
        (1.8, 0.3, False),  # high but below force_reverse: the force band opens
    ],
)
def test_a_force_above_its_limit_and_not_falling_reverses(
    cfg: Settings, level: float, prev_F_delta: float, reverses: bool
) -> None:
    ctx = cfg.model_context()
    base = params(cfg, force_reverse=2.0)
    F = step(RUNNING, MIRROR, frame(20.0), frame(20.0), base, ctx).F
    p = base.model_copy(update={"grasp_force": F / level})
    r = step(replace(RUNNING, F_prev=F - prev_F_delta), MIRROR, frame(20.0), frame(20.0), p, ctx)
    assert (r.reversal is Reversal.FORCE) is reverses
    assert (r.targets is None) is reverses
    if reverses:  # and the way back is not refused by the same force at once
        assert r.state.waived is Reversal.FORCE
        back = step(r.state, MIRROR, frame(20.0), frame(20.0), p, ctx)
        assert back.reversal is None and back.targets is not None


def test_a_blocked_way_looks_for_another_move_once_the_rotation_dithers(cfg: Settings) -> None:
    """Finger 1 nearly stretched, its contact near the pad's tip (the end of a stroke on
    bench-v1's polygon-061): along the thesis's route Finger 1 cannot reach Ad, and the
    thesis's rule reverses. Once the rotation has reversed twice without travelling, Finger 2
    takes the nearest move of the same length that passes every check and turns AB the
    route's way."""
    ctx, p = cfg.model_context(), params(cfg)
    pose = HandPose(rad(1.26), rad(-16.49), rad(-8.14), rad(11.41))
    m1, m2 = frame(38.0), frame(26.84)
    fresh = step(RollState(iteration=3), pose, m1, m2, p, ctx)
    assert fresh.reversal is Reversal.IK_UNREACHABLE
    dithering = RollState(iteration=3, consecutive_reversals=2)
    r = step(dithering, pose, m1, m2, p, ctx)
    assert r.reversal is None and r.targets is not None
    d4, d5 = r.targets.phi4 - pose.phi4, r.targets.phi5 - pose.phi5
    assert math.hypot(d4, d5) == pytest.approx(math.hypot(p.delta_phi, p.k * p.delta_phi))
    assert (d4, d5) != pytest.approx((-p.delta_phi, p.k * p.delta_phi))  # not the route's
    c2 = r.obs.contact2
    B_d = contact_point(Finger.TWO, pose.phi4 - p.delta_phi, pose.phi5 + p.k * p.delta_phi,
                        c2.r_mm, c2.theta_rad, ctx.geom)  # fmt: skip
    route_turn = segment(r.obs.points.A, B_d)[1] - r.obs.sigma
    assert (r.plan.sigma_d - r.obs.sigma) * route_turn > 0  # the stroke's way
    assert r.plan.omega_A_d is not None and r.plan.omega_B_d is not None  # every check ran
    assert r.state.travel > 0 and r.state.consecutive_reversals == 2


def _finger1_step(r: StepResult, pose: HandPose) -> float:
    assert r.targets is not None
    t = r.targets
    return max(abs(t.phi2 - pose.phi2), abs(t.phi3 - pose.phi3))


@pytest.mark.parametrize(
    ("pose_deg", "S1", "S2", "direction"),
    [((-7.389, -30.819, 65.72, 22.707), 38.145, 19.739, -1),
     ((29.373, -19.125, 37.702, -23.55), 22.733, 18.779, 1)],
)  # fmt: skip
def test_a_slowed_plan_out_of_reach_reverses_instead_of_taking_the_full_step(
    cfg: Settings, pose_deg: tuple[float, ...], S1: float, S2: float, direction: int
) -> None:
    """Finger 1 stretched to its reach and the grip opening by ΔΛ: its full step (7–9°) is
    reachable, its step slowed to 1° is not. The full step went out, and the runner's per-axis
    clamp cut it off Finger 1's path; an unreachable plan reverses, whatever its speed."""
    ctx, p, pose = cfg.model_context(), cfg.rolling, HandPose.from_degrees(*pose_deg)
    first = step(RollState(iteration=1, direction=direction), pose, frame(S1), frame(S2), p, ctx)
    state = RollState(iteration=1, direction=direction, F_prev=first.F - 0.5)  # F rising: Λ opens
    r = step(state, pose, frame(S1), frame(S2), p, ctx)
    assert r.targets is None and r.reversal in (Reversal.IK_UNREACHABLE, Reversal.WORKSPACE)


@settings(max_examples=200, deadline=None)
@given(pose_deg=st.tuples(*(st.floats(-90.0, 90.0),) * 4),
       S=st.tuples(st.floats(2.0, 39.0), st.floats(2.0, 39.0)),
       direction=st.sampled_from((1, -1)), dF=st.sampled_from((-0.5, 0.0, 0.5)),
       route=st.sampled_from(("thesis", "workspace")))  # fmt: skip
def test_finger1_is_never_commanded_beyond_what_it_can_follow(
    cfg: Settings, pose_deg: tuple[float, float, float, float], S: tuple[float, float],
    direction: int, dF: float, route: str,
) -> None:  # fmt: skip
    """Over random poses and contacts, either route: a commanded step moves Finger 1's joints
    by at most FOLLOW_SLACK × rolling.finger1_max_step_deg (what the servo follows)."""
    ctx = cfg.model_context()
    p = cfg.rolling.model_copy(update={"route": route})
    pose = HandPose.from_degrees(*pose_deg)
    m1, m2 = frame(S[0]), frame(S[1])
    first = step(RollState(iteration=1, direction=direction), pose, m1, m2, p, ctx)
    r = step(RollState(iteration=1, direction=direction, F_prev=first.F - dF), pose, m1, m2, p,
             ctx)  # fmt: skip
    if r.targets is not None:
        assert _finger1_step(r, pose) <= FOLLOW_SLACK * p.finger1_max_step + 1e-12
