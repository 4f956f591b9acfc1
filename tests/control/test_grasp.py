"""The grasp's pure step (control/grasp.py) on hand-built situations."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sdh2svc.config import Settings
from sdh2svc.control.grasp import GraspLaw, GraspWatch, Held, grasp_step
from sdh2svc.control.safety import Fault, Violation
from sdh2svc.model.contact import NO_CONTACT, ContactEstimate
from sdh2svc.model.kinematics import HandPose
from sdh2svc.model.observe import observe
from tests.control.test_rolling import frame

rad = math.radians
# mirror poses: parallel distal links (no wedge) and tilted towards each other (a wedge)
PARALLEL = HandPose(rad(-20), rad(20), rad(-20), rad(20))
WEDGED = HandPose(rad(-20), rad(40), rad(-20), rad(40))


def law(**kw: float) -> GraspLaw:
    base = {"grasp_force": 2.0, "gain_deg_s": 2.5, "max_velocity_deg_s": 3.0,
            "min_velocity_deg_s": 0.5, "approach_velocity_deg_s": 2.0, "align_gain": 0.5,
            "period_s": 1 / 30, "max_step_deg": 1.0}  # fmt: skip
    return GraspLaw(**{**base, **kw})


def contacts(cfg: Settings, amplitude: float) -> tuple:
    ctx = cfg.model_context()
    return ctx.contact(frame(20.0, amplitude)), ctx.contact(frame(20.0, amplitude))


def test_no_contact_closes_at_the_approach_speed_keeping_the_pads_orientation(
    cfg: Settings,
) -> None:
    ctx = cfg.model_context()
    empty = ctx.contact(np.zeros((13, 6), np.uint16))
    g = grasp_step(PARALLEL, empty, empty, law(), ctx)
    step = 2.0 / 30  # the approach speed × one frame, not the force law's 3 °/s at F = 0
    assert g.d_phi == pytest.approx((step, -step, step, -step))
    assert g.wedge_deg is None


@pytest.mark.parametrize("first", [0, 1])
def test_the_first_pad_to_touch_waits_for_the_other(cfg: Settings, first: int) -> None:
    ctx = cfg.model_context()
    empty = ctx.contact(np.zeros((13, 6), np.uint16))
    touch = ctx.contact(frame(20.0, 100.0))
    assert touch.present and touch.force < 2.0  # a light first touch, far below Fd
    pair = (touch, empty) if first == 0 else (empty, touch)
    g = grasp_step(PARALLEL, *pair, law(align_gain=0.0), ctx)
    waiting, closing = (g.d_phi[0], g.d_phi[2]) if first == 0 else (g.d_phi[2], g.d_phi[0])
    assert waiting == pytest.approx(0.5 / 30)  # the speed floor, not Fd − F's 3 °/s
    assert closing == pytest.approx(2.0 / 30)  # the other comes on at the approach speed
    both = grasp_step(PARALLEL, touch, touch, law(align_gain=0.0), ctx)
    assert both.d_phi[0] == both.d_phi[2] > 0.5 / 30  # both touching: each by its own force


def test_near_fd_the_closing_speed_keeps_its_floor(cfg: Settings) -> None:
    ctx = cfg.model_context()
    c1, c2 = contacts(cfg, 1000.0)
    f = c1.force
    g = grasp_step(PARALLEL, c1, c2, law(grasp_force=f + 0.01, align_gain=0.0), ctx)
    assert g.d_phi[0] == pytest.approx(0.5 / 30)  # the floor, not 0.01 × 2.5 °/s
    above = grasp_step(PARALLEL, c1, c2, law(grasp_force=f / 2, align_gain=0.0), ctx)
    assert above.d_phi[0] < 0 and above.d_phi[2] < 0  # above Fd the fingers open


def test_no_finger_opens_while_the_grip_is_short_of_fd(cfg: Settings) -> None:
    """Pads that read one object's equal forces differently (gains apart, a contact smaller
    than the texel pitch): the one above Fd holds while the grip's mean is below it, and the
    other closes; once the mean reaches Fd, the one above it opens again."""
    ctx = cfg.model_context()
    high, low = ctx.contact(frame(20.0, 1000.0)), ctx.contact(frame(20.0, 500.0))
    fd = (high.force + low.force) / 2 + 0.05  # between the pads' readings, above their mean
    assert low.force < fd < high.force
    g = grasp_step(PARALLEL, high, low, law(grasp_force=fd, align_gain=0.0), ctx)
    assert g.d_phi[0] == 0.0 and g.d_phi[1] == 0.0  # Finger 1 holds: it does not open
    assert g.d_phi[2] >= 0.5 / 30  # Finger 2 closes, at least at the floor
    for pair in ((high, low), (low, high)):  # the same whichever finger reads higher
        g = grasp_step(PARALLEL, *pair, law(grasp_force=fd, align_gain=0.0), ctx)
        assert min(g.d_phi[0], g.d_phi[2]) == 0.0 and max(g.d_phi[0], g.d_phi[2]) > 0.0
    held = (high.force + low.force) / 2 - 0.05  # the mean above Fd, one pad still below
    g = grasp_step(PARALLEL, high, low, law(grasp_force=held, align_gain=0.0), ctx)
    assert g.d_phi[0] < 0.0 < g.d_phi[2]  # each by its own force again


def test_the_pads_turn_about_their_contacts_against_their_wedge(cfg: Settings) -> None:
    ctx = cfg.model_context()
    c1, c2 = contacts(cfg, 300.0)
    held = law(grasp_force=(c1.force + c2.force) / 2)  # F = Fd: held, the pads may turn
    g = grasp_step(WEDGED, c1, c2, held, ctx)
    plain = grasp_step(WEDGED, c1, c2, law(grasp_force=held.grasp_force, align_gain=0.0), ctx)
    assert g.wedge_deg is not None and abs(g.wedge_deg) > 5.0
    turned = HandPose(WEDGED.phi2 + rad(g.d_phi[0] - plain.d_phi[0]),
                      WEDGED.phi3 + rad(g.d_phi[1] - plain.d_phi[1]),
                      WEDGED.phi4 + rad(g.d_phi[2] - plain.d_phi[2]),
                      WEDGED.phi5 + rad(g.d_phi[3] - plain.d_phi[3]))  # fmt: skip
    before = observe(WEDGED, frame(20.0, 300.0), frame(20.0, 300.0), ctx)
    after = observe(turned, frame(20.0, 300.0), frame(20.0, 300.0), ctx)
    w0 = (before.omega_A + before.omega_B) / 2 - math.pi / 2
    w1 = (after.omega_A + after.omega_B) / 2 - math.pi / 2
    assert abs(w1) < abs(w0)  # the wedge shrank
    tilt0, tilt1 = before.omega_A - before.omega_B, after.omega_A - after.omega_B
    assert tilt1 == pytest.approx(tilt0, abs=rad(1.0))  # the tilt is nearly kept
    # each pad turned about its contact: the proximal joint followed, and |AB| is kept
    assert g.d_phi[0] != plain.d_phi[0] and g.d_phi[2] != plain.d_phi[2]
    joint_only = HandPose(WEDGED.phi2, turned.phi3, WEDGED.phi4, turned.phi5)
    squeezed = observe(joint_only, frame(20.0, 300.0), frame(20.0, 300.0), ctx)
    assert abs(after.Lambda - before.Lambda) < 0.1 * abs(squeezed.Lambda - before.Lambda)
    assert all(abs(d) <= 1.0 + 1e-12 for d in g.d_phi)


def test_below_fd_a_pad_turns_about_its_joint(cfg: Settings) -> None:
    # while the grip forms, the squeeze a turn about the joint adds helps it; the proximal
    # joints close as without a turn
    ctx = cfg.model_context()
    c1, c2 = contacts(cfg, 300.0)
    g = grasp_step(WEDGED, c1, c2, law(grasp_force=c1.force * 1.5), ctx)
    plain = grasp_step(WEDGED, c1, c2, law(grasp_force=c1.force * 1.5, align_gain=0.0), ctx)
    assert g.wedge_deg is not None and abs(g.wedge_deg) > 5.0
    assert g.d_phi[0] == plain.d_phi[0] > 0 and g.d_phi[2] == plain.d_phi[2] > 0
    assert g.d_phi[1] != plain.d_phi[1] and g.d_phi[3] != plain.d_phi[3]


def test_a_squeeze_at_twice_fd_stops_the_turn(cfg: Settings) -> None:
    ctx = cfg.model_context()
    c1, c2 = contacts(cfg, 1000.0)
    g = grasp_step(WEDGED, c1, c2, law(grasp_force=c1.force / 2.5), ctx)
    plain = grasp_step(WEDGED, c1, c2, law(grasp_force=c1.force / 2.5, align_gain=0.0), ctx)
    assert g.d_phi == plain.d_phi


# --- the grasp's supervision (GraspWatch) on hand-built frames ---------------------------------

PRESHAPE = (90.0, -30.0, 30.0, -90.0, 0.0, -30.0, 30.0)  # config/default.toml [run]
FD = 2.0


def touch(force: float) -> ContactEstimate:
    return replace(NO_CONTACT, present=force > 0, force=force)


def watch(cfg: Settings, align: bool = True) -> GraspWatch:
    return GraspWatch(run=cfg.run, axes=cfg.axes, geom=cfg.hand, contact_force_min=0.1,
                      alpha_deg=22.0, align=align, approach_deg_s=3.0, started=0.0)  # fmt: skip


def closed_by(deg: float) -> tuple[float, ...]:
    """The pre-shape with both proximal joints (φ2: axis 1, φ4: axis 3) closed by ``deg``."""
    a = list(PRESHAPE)
    a[1] += deg
    a[3] -= deg
    return tuple(a)


def see(w: GraspWatch, cfg: Settings, t: float, f1: float, f2: float, closed: float = 10.0,
        wedge: float | None = 0.0) -> object:  # fmt: skip
    actual = closed_by(closed)
    return w.observe(t, touch(f1), touch(f2), FD, actual, cfg.axes.pose(actual), wedge)


def test_the_grasp_holds_once_the_grip_reaches_fd_with_the_pads_aligned(cfg: Settings) -> None:
    w = watch(cfg)
    assert see(w, cfg, 0.0, 0.0, 0.0) is None  # closing
    assert see(w, cfg, 1.0, 1.0, 0.5) is None  # touched, under Fd
    assert isinstance(see(w, cfg, 2.0, 2.1, 2.0, wedge=5.0), Held)  # within α/2


def test_a_wedge_settles_until_its_time_is_up(cfg: Settings) -> None:
    w = watch(cfg)
    assert see(w, cfg, 1.0, 2.0, 2.0, wedge=30.0) is None  # held, the pads still turning
    # F dips below Fd as they turn: neither the timeout nor a held grasp
    assert see(w, cfg, 1.0 + cfg.run.grasp_settle_s / 2, 1.5, 1.5, wedge=20.0) is None
    assert isinstance(see(w, cfg, 1.0 + cfg.run.grasp_settle_s, 1.5, 1.5, wedge=20.0), Held)
    # without the alignment, a held grip is a grasp at once
    assert isinstance(see(watch(cfg, align=False), cfg, 1.0, 2.0, 2.0, wedge=30.0), Held)


def test_a_pad_lost_as_the_grasp_settles_is_no_grasp(cfg: Settings) -> None:
    w = watch(cfg)
    assert see(w, cfg, 1.0, 2.0, 2.0, wedge=30.0) is None
    v = see(w, cfg, 1.0 + cfg.run.grasp_settle_s, 4.0, 0.0)
    assert isinstance(v, Violation) and v.fault is Fault.NO_CONTACT
    assert "a contact lost as the grasp settled" in v.message


def test_a_pad_that_never_read_is_named(cfg: Settings) -> None:
    v = see(watch(cfg), cfg, 1.0, 4.5, 0.0)  # Finger 1's pad alone grips: F = 2.25 ≥ Fd
    assert isinstance(v, Violation) and "Finger 2's distal pad read no contact" in v.message


def test_the_timeout_counts_from_the_first_touch(cfg: Settings) -> None:
    w = watch(cfg)
    timeout = cfg.run.grasp_timeout_s
    assert see(w, cfg, 15.0, 0.0, 0.0, closed=15 * 3.0) is None  # closing at the approach speed
    assert see(w, cfg, 16.0, 0.5, 0.5, closed=48.0) is None  # touched at 16 s
    assert see(w, cfg, 16.0 + timeout, 1.0, 1.0, closed=48.0) is None
    v = see(w, cfg, 16.1 + timeout, 1.0, 1.0, closed=48.0)
    assert isinstance(v, Violation) and v.message.startswith("no grasp (F = 1.00 < Fd = 2.0)")


def test_an_untouched_grasp_that_stops_closing_has_stalled(cfg: Settings) -> None:
    w = watch(cfg)
    for i in range(10):  # 3°/s for 5 s: as commanded
        assert see(w, cfg, 0.5 * i, 0.0, 0.0, closed=1.5 * i) is None
    for i in range(1, 5):  # then it stops short of the object, nothing touched
        v = see(w, cfg, 4.5 + 0.5 * i, 0.0, 0.0, closed=13.5)
    assert isinstance(v, Violation) and v.fault is Fault.NO_CONTACT
    assert v.message.startswith("the fingers stopped closing with nothing touched"), v.message


def test_fingers_closed_past_the_limit_found_nothing(cfg: Settings) -> None:
    w = watch(cfg)
    beyond = cfg.run.grasp_max_close_deg - PRESHAPE[1] + 1.0  # φ2 past grasp_max_close_deg
    v = see(w, cfg, 1.0, 0.5, 0.5, closed=beyond)
    assert isinstance(v, Violation) and "closed without touching anything" in v.message
