"""The supervisor's decisions (control.safety), each on both sides of its boundary."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest

from sdh2svc.config import Settings
from sdh2svc.control import safety
from sdh2svc.control.params import RollingParams
from sdh2svc.control.rolling import Reversal, RollState, StepResult, step
from sdh2svc.control.safety import Fault, Violation
from tests.control.test_rolling import MIRROR, frame, params


def fault(v: Violation | None) -> Fault | None:
    return None if v is None else v.fault


def test_frame_age_allows_up_to_the_limit_and_faults_beyond_or_without_a_frame(
    cfg: Settings,
) -> None:
    s = cfg.safety  # 300 ms
    assert safety.stale_s(s) == 0.3
    assert safety.frame_age(0.0, s) is None
    assert safety.frame_age(0.3, s) is None
    v = safety.frame_age(0.301, s)
    assert v == Violation(Fault.STALE_SENSOR, "tactile frame 301 ms old")
    assert safety.frame_age(None, s) == Violation(Fault.STALE_SENSOR, "no tactile frame for 300 ms")


def test_joint_age_allows_up_to_the_limit_and_faults_beyond_or_without_a_reading(
    cfg: Settings,
) -> None:
    s = cfg.safety
    limit = s.stale_joint_ms / 1000
    assert safety.joint_age(0.0, s) is None
    assert safety.joint_age(limit, s) is None
    v = safety.joint_age(limit + 0.001, s)
    assert v is not None and v.fault is Fault.JOINT_ERROR
    assert f"{s.stale_joint_ms + 1:.0f} ms old" in v.message
    v = safety.joint_age(None, s)
    assert v is not None and v.fault is Fault.JOINT_ERROR and "no reading" in v.message


def test_force_ceiling_is_the_factor_times_fd(cfg: Settings) -> None:
    s = cfg.safety  # 3 × Fd
    assert safety.force_ceiling(6.0, 6.0, 2.0, s) is None
    v = safety.force_ceiling(6.01, 5.0, 2.0, s)
    assert v == Violation(Fault.FORCE_CEILING, "F1 = 6.01 above 3 × Fd")


def test_the_force_ceiling_watches_each_pad_not_their_mean(cfg: Settings) -> None:
    """One pad pressed hard while the other barely touches (the grip's F, their mean, 3.5)."""
    v = safety.force_ceiling(0.5, 6.5, 2.0, cfg.safety)
    assert v == Violation(Fault.FORCE_CEILING, "F2 = 6.50 above 3 × Fd")


def test_the_force_ceiling_never_rises_above_its_maximum(cfg: Settings) -> None:
    """Fd is a run parameter; the ceiling's maximum is not (a model_copy skips the checks that
    keep Fd below it, as a future route to Fd might)."""
    s = cfg.safety  # 3 × Fd, at most 12
    assert s.ceiling(2.0) == 6.0 and s.ceiling(4.0) == 12.0 and s.ceiling(50.0) == 12.0
    assert safety.force_ceiling(12.0, 11.0, 50.0, s) is None
    v = safety.force_ceiling(12.01, 11.0, 50.0, s)
    assert v == Violation(Fault.FORCE_CEILING, "F1 = 12.01 above the ceiling's maximum 12 "
                          "(safety.force_ceiling_max)")  # fmt: skip


def test_parameters_within_the_supervisors_limits_pass(cfg: Settings) -> None:
    assert safety.params_outside(cfg.rolling, cfg.safety) == []
    k5 = cfg.rolling.model_copy(update={"k": 5.0})  # Finger 2 clipped to 1° a step: allowed
    assert safety.params_outside(k5, cfg.safety) == []
    fast = cfg.rolling.model_copy(update={"finger1_max_step_deg": 1.01, "grasp_force": 4.01})
    assert len(safety.params_outside(fast, cfg.safety)) == 2


@pytest.mark.parametrize("ceiling_max", [12.0, 30.0, 600.0])
def test_the_parameters_schema_offers_only_what_the_limits_allow(
    cfg: Settings, ceiling_max: float
) -> None:
    """A form built from the schema offers no value params_outside refuses: each limited
    field's maximum passes and a hair above it does not; where the field's own maximum is
    the tighter (a ceiling of 600 allows Fd up to 200, the field 50), it stays."""
    s = cfg.safety.model_copy(update={"force_ceiling_max": ceiling_max})
    schema = safety.params_schema(s, cfg.rolling)
    for key in ("grasp_force", "finger1_max_step_deg"):
        top = schema["properties"][key]["maximum"]
        assert top <= RollingParams.model_json_schema()["properties"][key]["maximum"]
        at = cfg.rolling.model_copy(update={key: top})
        assert safety.params_outside(at, s) == []
        above = cfg.rolling.model_copy(update={key: top * 1.001})
        if top == RollingParams.model_json_schema()["properties"][key]["maximum"]:
            with pytest.raises(ValueError):  # the field's own range refuses it
                RollingParams.model_validate(above.model_dump())
        else:
            assert len(safety.params_outside(above, s)) == 1
    assert schema["properties"]["grasp_force"]["maximum"] == min(ceiling_max / 3.0, 50.0)
    # a form's defaults are the configuration's values (re-centring on, not the model's off)
    defaults = {k: f["default"] for k, f in schema["properties"].items()}
    assert defaults == cfg.rolling.model_dump(mode="json")
    assert defaults["recentre_strokes"] != RollingParams.model_fields["recentre_strokes"].default


@pytest.mark.parametrize(
    ("c1", "c2", "want"),
    [(True, True, None), (True, False, None), (False, True, None), (False, False, Fault.DROPPED)],
)
def test_dropped_only_when_both_contacts_are_lost(c1: bool, c2: bool, want: Fault | None) -> None:
    assert fault(safety.dropped(c1, c2)) is want


def test_stuck_beyond_the_allowed_reversals_in_a_row(cfg: Settings) -> None:
    s = cfg.safety  # 6
    assert safety.stuck(6, Reversal.CONE_A, s) is None
    v = safety.stuck(7, Reversal.CONE_A, s)
    assert v == Violation(Fault.STUCK, "7 reversals in a row without a half stroke (last: cone_A)")


def test_a_stuck_run_names_the_pad_that_reads_nothing(cfg: Settings) -> None:
    why = safety.one_contact_lost(1.2, 0.0, True, False)
    assert why == ("Finger 2's distal pad reads no contact while Finger 1's reads F1 = 1.20 "
                   "(the object slid off that pad, or the pad stopped reading)")  # fmt: skip
    assert safety.one_contact_lost(0.0, 0.9, False, True).startswith("Finger 1's distal pad")
    assert safety.one_contact_lost(0.1, 0.9, True, True) == ""  # both read: no pad to name
    assert safety.one_contact_lost(0.0, 0.0, False, False) == ""  # that is a drop
    v = safety.stuck(7, Reversal.CONTACT_LOST, cfg.safety, why)
    assert v is not None and v.message == f"7 reversals in a row without a half stroke (last: " \
        f"contact_lost): {why}"  # fmt: skip


def test_grasp_timeout_only_under_fd_and_after_the_timeout(cfg: Settings) -> None:
    run = cfg.run  # 20 s
    assert safety.grasp_timeout(1.0, 2.0, 120.0, 100.0, run) is None
    v = safety.grasp_timeout(1.0, 2.0, 120.001, 100.0, run)
    assert v == Violation(Fault.NO_CONTACT, "no grasp (F = 1.00 < Fd = 2.0) within 20 s")
    assert safety.grasp_timeout(2.0, 2.0, 500.0, 100.0, run) is None  # held: no timeout


def test_a_grasp_timeout_names_fingers_too_slow_to_follow(cfg: Settings) -> None:
    run = cfg.run
    plain = "no grasp (F = 0.00 < Fd = 2.0) within 20 s"
    # (closed °, commanded °/s) over the 21 s since the grasp began: 2.9, 1.5 and 0.87 °/s;
    # closing at half the commanded speed or more, an untouched grasp goes on (a small object
    # is touched late; closed_empty ends an approach that meets nothing)
    assert safety.grasp_timeout(0.0, 2.0, 121.0, 100.0, run, (2.9 * 21, 3.0)) is None
    assert safety.grasp_timeout(0.0, 2.0, 121.0, 100.0, run, (1.5 * 21, 3.0)) is None
    assert safety.grasp_timeout(0.0, 2.0, 121.0, 100.0, run, (1.49 * 21, 3.0)) is not None
    # once touched, the timeout counts from the touch, however fast the fingers closed before
    assert safety.grasp_timeout(0.5, 2.0, 121.0, 100.0, run) == Violation(
        Fault.NO_CONTACT, "no grasp (F = 0.50 < Fd = 2.0) within 20 s"
    )
    slow = safety.grasp_timeout(0.0, 2.0, 121.0, 100.0, run, (0.87 * 21, 3.0))
    assert slow is not None and slow.message.startswith(plain + "; untouched, the fingers ")
    assert "0.87°/s of the 3°/s commanded: they lag behind their targets" in slow.message


def test_a_grasp_timeout_after_a_touch_names_the_other_finger_if_it_drags(cfg: Settings) -> None:
    run = cfg.run
    plain = "no grasp (F = 1.00 < Fd = 2.0) within 20 s"
    # (finger, its proximal joint's closing since the touch 21 s ago (°), commanded °/s): at
    # half its speed or more it is named nowhere; the timeout counts from the touch either way
    assert safety.grasp_timeout(1.0, 2.0, 120.0, 100.0, run, None, (2, 0.1, 2.0)) is None
    ok = safety.grasp_timeout(1.0, 2.0, 121.0, 100.0, run, None, (2, 1.0 * 21, 2.0))
    assert ok == Violation(Fault.NO_CONTACT, plain)
    slow = safety.grasp_timeout(1.0, 2.0, 121.0, 100.0, run, None, (1, 0.99 * 21, 2.0))
    assert slow is not None and slow.message == (
        plain + "; Finger 1's pad has read nothing, and it closed at 0.99°/s of the 2°/s "
        "commanded since the other touched: it lags behind its targets (an axis that moves "
        "slower than commanded)"
    )


def test_an_untouched_grasp_ends_when_its_pads_come_close() -> None:
    assert safety.pads_met(5.0) is None and safety.pads_met(50.0) is None
    assert safety.pads_met(4.94) == Violation(
        Fault.NO_CONTACT, "fingers closed without touching anything (the pads 4.9 mm apart)"
    )
    assert safety.pads_met(0.0) is not None
    lost = safety.pads_met(4.0, lost=True)  # a pad had touched: the object went, or the pads
    assert lost is not None and lost.message.startswith("the contact was lost and the fingers ")


def test_an_untouched_grasp_that_slows_down_ends_within_its_window() -> None:
    # (closed over the window °, window s, closed since the start °, since s, commanded °/s)
    assert safety.grasp_stalled(0.0, 1.99, 30.0, 16.0, 3.0) is None  # not a whole window yet
    assert safety.grasp_stalled(3.8, 2.0, 30.0, 16.0, 3.0) is None  # 1.9 °/s, as before
    assert safety.grasp_stalled(0.74, 2.0, 7.4, 20.0, 3.0) is None  # slow from the start: lines
    v = safety.grasp_stalled(1.2, 2.0, 30.0, 16.0, 3.0)  # 0.6 °/s after 1.88 °/s: stopped
    assert v == Violation(Fault.NO_CONTACT, "the fingers stopped closing with nothing touched "
                          "(0.60°/s over the last 2.0 s, after 1.88°/s; 3°/s commanded): "
                          "something stops them where no distal pad senses it")  # fmt: skip
    # Fd lowered mid-grasp: 0.5 °/s commanded now; 0.81 °/s after a mean of 1.67 is no stall
    assert safety.grasp_stalled(1.62, 2.0, 25.0, 15.0, 0.5) is None
    v = safety.grasp_stalled(1.2, 2.0, 30.0, 16.0, 3.0, lost=True)  # the pads read it, then not
    assert v is not None and v.message.startswith("no pad reads the contact any more, and the ")


def test_a_grasp_ends_only_with_both_contacts() -> None:
    assert safety.grasp_lost(True, True) is None
    v = safety.grasp_lost(True, False)
    assert v == Violation(Fault.NO_CONTACT, "no grasp: a contact lost as the grasp settled")
    v = safety.grasp_lost(False, False)
    assert v is not None and "both contacts" in v.message and v.fault is Fault.NO_CONTACT
    # a pad that never read anything while the other gripped is named, not called "lost"
    v = safety.grasp_lost(True, False, True, False)
    assert v is not None and v.message.startswith("no grasp: Finger 2's distal pad read no "
                                                  "contact during the whole grasp"), v  # fmt: skip
    v = safety.grasp_lost(False, True, False, True)
    assert v is not None and "Finger 1's distal pad read no contact" in v.message
    assert safety.grasp_lost(True, False, True, True) == Violation(
        Fault.NO_CONTACT, "no grasp: a contact lost as the grasp settled"
    )  # it had read one
    assert safety.grasp_lost(True, True, True, False) is None  # (both present: held)


def test_closed_empty_on_either_proximal_joint(cfg: Settings) -> None:
    run, axes = cfg.run.model_copy(update={"grasp_max_close_deg": 10.0}), cfg.axes
    wire = [0.0] * 7
    assert safety.closed_empty(wire, axes, run) is None
    for axis in (axes.phi2, axes.phi4):
        at, past = list(wire), list(wire)
        at[axis], past[axis] = 10.0, 10.5
        assert safety.closed_empty(at, axes, run) is None
        assert fault(safety.closed_empty(past, axes, run)) is Fault.NO_CONTACT
    others = [90.0 if i not in (axes.phi2, axes.phi4) else 0.0 for i in range(7)]
    assert safety.closed_empty(others, axes, run) is None  # distal joints, thumb: not closing


def _step(cfg: Settings) -> StepResult:
    return step(RollState(), MIRROR, frame(20.0), frame(20.0), params(cfg), cfg.model_context())


def test_rolling_step_checks_ceiling_then_drop_then_stuck(cfg: Settings) -> None:
    s, fd = cfg.safety, 2.0
    r = _step(cfg)
    assert r.obs.contact1.present and r.obs.contact2.present
    r = replace(r, F=fd)
    assert safety.rolling_step(r, fd, s) is None
    lost = replace(r.obs.contact1, present=False)
    none = replace(r, obs=replace(r.obs, contact1=lost, contact2=lost))
    stuck = replace(r, state=replace(r.state, consecutive_reversals=7), reversal=Reversal.WEDGE)
    assert fault(safety.rolling_step(none, fd, s)) is Fault.DROPPED
    assert fault(safety.rolling_step(stuck, fd, s)) is Fault.STUCK
    both = replace(none, state=stuck.state)
    assert fault(safety.rolling_step(both, fd, s)) is Fault.DROPPED
    pressed = replace(stuck.obs.contact2, force=3 * fd + 0.01)  # one pad, the other below Fd
    high = replace(stuck, obs=replace(stuck.obs, contact2=pressed))
    assert fault(safety.rolling_step(high, fd, s)) is Fault.FORCE_CEILING


def test_a_target_that_is_no_number_holds_its_axis() -> None:
    """NaN compares false with everything: min/max would turn it into one step towards the
    lower limit; ±inf would be a full step. The axis holds where it is instead."""
    lo, hi = [-90.0] * 3, [90.0] * 3
    got = safety.clamp_targets([math.nan, math.inf, -math.inf], [10.0, 20.0, 30.0], lo, hi, 1.0)
    assert got == (10.0, 20.0, 30.0)


def test_clamp_targets_refuses_an_axis_beyond_its_limits_by_more_than_a_step() -> None:
    """A finger 1.9° beyond a limit (narrowed since, or it sagged there unpowered): clipped to
    the limit, its target would be a 1.9° step; within one step it is clipped as any target."""
    lo, hi = [-90.0] * 2, [-25.0, 90.0]
    with pytest.raises(safety.OutsideLimits, match=r"axis 0 is at -23\.1°, outside its joint "
                       r"limits \[-90, -25\]° by more than one step \(1°\)"):  # fmt: skip
        safety.clamp_targets([-30.0, 0.0], [-23.1, 0.0], lo, hi, 1.0)
    with pytest.raises(safety.OutsideLimits):  # holding it there too
        safety.clamp_targets([-23.1, 0.0], [-23.1, 0.0], lo, hi, 1.0)
    assert safety.clamp_targets([-20.0, 0.0], [-24.2, 0.0], lo, hi, 1.0) == (-25.0, 0.0)


def test_clamp_targets_limits_the_step_and_the_range() -> None:
    lo, hi = [-90.0] * 3, [90.0] * 3
    got = safety.clamp_targets([5.0, -5.0, 95.0], [0.0, 0.0, 89.5], lo, hi, 1.0)
    assert got == (1.0, -1.0, 90.0)
    within = [0.5, 0.0, 89.7]
    assert safety.clamp_targets(within, [0.0, 0.0, 89.5], lo, hi, 1.0) == tuple(within)
