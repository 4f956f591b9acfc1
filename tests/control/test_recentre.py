"""Re-centring (``rolling.recentre_strokes``): the pads' wedge averaged over the last full stroke
is brought back to the grasp's by leaning Finger 1's σd (control/rolling.py, _recentre)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from sdh2svc.config import Settings
from sdh2svc.control.params import RollingParams
from sdh2svc.control.rolling import (
    RECENTRE_MAX,
    REFERENCE_HALF_STROKE,
    RollState,
    StepResult,
    step,
)
from sdh2svc.model.friction import wedge
from sdh2svc.model.kinematics import HandPose, segment
from tests.control.test_rolling import TILTED, frame, params

rad = math.radians
EMPTY = np.zeros((13, 6), np.uint16)


def _half_stroke(s: RollState, pose: HandPose, n: int, p: RollingParams,
                 cfg: Settings) -> tuple[RollState, HandPose, list[float]]:  # fmt: skip
    """``n`` iterations with the fingers where the last one commanded them, then a reversal
    (Finger 2's contact lost); the wedge each iteration observed."""
    ctx, seen = cfg.model_context(), []
    for _ in range(n):
        r = step(s, pose, frame(20.0), frame(24.0), p, ctx)
        seen.append(wedge(r.obs.omega_A, r.obs.omega_B))
        s, pose = r.state, r.targets or pose
    s = step(s, pose, frame(20.0), EMPTY, p, ctx).state
    return s, pose, seen


def test_the_wedge_error_is_the_last_full_strokes_mean_against_the_reference(
    cfg: Settings,
) -> None:
    """The reference is the full stroke of half strokes 4 and 5 (the first strokes settle in from
    the grasp); each later half stroke's end compares the last full stroke with it."""
    p = params(cfg, recentre_strokes=2.0)
    s, pose, seen = RollState(), TILTED, []
    for n in (6, 7, 5, 4):
        s, pose, w = _half_stroke(s, pose, n, p, cfg)
        seen.append(w)
    assert s.half_strokes == 4 and s.wedge_ref is None
    s, pose, w = _half_stroke(s, pose, 6, p, cfg)
    seen.append(w)
    assert s.half_strokes == REFERENCE_HALF_STROKE == 5
    ref = np.mean(seen[3] + seen[4])
    assert s.wedge_ref == pytest.approx(ref)
    assert s.wedge_error == 0.0 and s.stroke_iterations == 0
    # a reversal that ends no half stroke changes nothing
    held = step(s, pose, frame(20.0), EMPTY, p, cfg.model_context()).state
    assert held.half_strokes == 5 and held.wedge_ref == s.wedge_ref
    s, pose, w = _half_stroke(held, pose, 4, p, cfg)
    seen.append(w)
    assert s.stroke_iterations == 10
    assert s.wedge_error == pytest.approx(np.mean(seen[4] + seen[5]) - ref)
    assert s.wedge_error != 0.0
    # the integral adds each stroke's error × the share of its iterations whose lean was not
    # held at its bound: none leaned before the first error
    assert s.wedge_now == (0.0, 0, 0) and s.wedge_integral == s.wedge_error
    integral = s.wedge_integral
    s, pose, w = _half_stroke(s, pose, 5, p, cfg)
    seen.append(w)
    assert s.stroke_iterations == 9 and s.wedge_ref == pytest.approx(ref)
    assert s.wedge_error == pytest.approx(np.mean(seen[5] + seen[6]) - ref)
    # strokes this short lean at the bound (RECENTRE_MAX) the whole half stroke
    assert s.wedge_last is not None and s.wedge_last[2] == 5
    assert s.wedge_integral == pytest.approx(integral + (1 - 5 / 9) * s.wedge_error)


def _plans(cfg: Settings, error_deg: float, strokes: float,
           integral_deg: float = 0.0) -> tuple[StepResult, StepResult]:  # fmt: skip
    """The thesis's plan and the plan re-centring against a stroke-mean wedge ``error_deg``
    above the reference stroke's (over a 400-iteration stroke) and the errors' integral
    ``integral_deg``, from the same observation."""
    ctx, m1, m2 = cfg.model_context(), frame(20.0), frame(24.0)
    state = RollState(iteration=5, wedge_ref=0.0, wedge_error=rad(error_deg),
                      wedge_integral=rad(integral_deg), stroke_iterations=400)  # fmt: skip
    off = step(replace(state, wedge_error=0.0, wedge_integral=0.0), TILTED, m1, m2,
               params(cfg), ctx)  # fmt: skip
    on = step(state, TILTED, m1, m2, params(cfg, recentre_strokes=strokes), ctx)
    return off, on


def _planned_wedge(r: StepResult) -> float:
    assert r.plan is not None and r.plan.omega_A_d is not None and r.plan.omega_B_d is not None
    return wedge(r.plan.omega_A_d, r.plan.omega_B_d)


@pytest.mark.parametrize("error_deg", [2.0, -2.0])
def test_a_wedge_above_the_reference_strokes_leans_sigma_d_to_narrow_it(cfg: Settings,
                                                             error_deg: float) -> None:  # fmt: skip
    off, on = _plans(cfg, error_deg, 2.0)
    assert off.targets is not None and on.targets is not None
    assert off.plan is not None and on.plan is not None
    lean = on.plan.sigma_d - off.plan.sigma_d
    assert 0.0 < abs(lean) <= RECENTRE_MAX + 1e-12
    # the planned wedge moves back towards the reference stroke's
    moved = _planned_wedge(on) - _planned_wedge(off)
    assert math.copysign(1.0, moved) == -math.copysign(1.0, error_deg)
    # Finger 2 follows its route as before, Finger 1 keeps A on the circle of radius Λad
    assert (on.targets.phi4, on.targets.phi5) == (off.targets.phi4, off.targets.phi5)
    assert segment(on.plan.A_d, on.plan.B_d)[0] == pytest.approx(on.plan.Lambda_ad)


def test_the_lean_is_the_error_spread_over_the_strokes(cfg: Settings) -> None:
    """Halving the error or doubling ``recentre_strokes`` halves the lean (within its bound)."""
    off, base = _plans(cfg, 0.5, 2.0)
    _, half = _plans(cfg, 0.25, 2.0)
    _, slow = _plans(cfg, 0.5, 4.0)
    assert off.plan is not None and base.plan is not None
    assert half.plan is not None and slow.plan is not None
    lean = base.plan.sigma_d - off.plan.sigma_d
    assert 0.0 < abs(lean) < RECENTRE_MAX  # not at its bound
    assert half.plan.sigma_d - off.plan.sigma_d == pytest.approx(lean / 2, rel=1e-6)
    assert slow.plan.sigma_d - off.plan.sigma_d == pytest.approx(lean / 2, rel=1e-6)


def test_off_is_the_thesis_plan(cfg: Settings) -> None:
    off, on = _plans(cfg, 2.0, 0.0)
    assert off.plan == on.plan and off.targets == on.targets


def test_the_integral_leans_as_its_share_of_the_error(cfg: Settings) -> None:
    """The error acted on is the last stroke's plus the errors' integral over 2 ×
    ``recentre_strokes`` half strokes: an integral of 4 × 0.5° at 2 strokes leans σd as an
    error of 0.5° does, and adds to one."""
    off, error = _plans(cfg, 0.5, 2.0)
    _, integral = _plans(cfg, 0.0, 2.0, integral_deg=2.0)
    _, both = _plans(cfg, 0.25, 2.0, integral_deg=1.0)
    assert off.plan is not None and error.plan is not None
    assert integral.plan is not None and both.plan is not None
    lean = error.plan.sigma_d - off.plan.sigma_d
    assert 0.0 < abs(lean) < RECENTRE_MAX
    assert integral.plan.sigma_d - off.plan.sigma_d == pytest.approx(lean, rel=1e-6)
    assert both.plan.sigma_d - off.plan.sigma_d == pytest.approx(lean, rel=1e-6)


@pytest.mark.parametrize(
    ("error_deg", "integral_deg", "held"),
    [
        (0.5, 0.0, False),  # within its bound
        (30.0, 0.0, True),  # at its bound and the error pushes on: held
        (-30.0, 0.0, True),
        (-0.5, 400.0, False),  # at its bound but the error pushes back: the integral unwinds
        (0.0, 400.0, False),
    ],
)
def test_the_integral_holds_while_the_lean_is_at_its_bound(
    cfg: Settings, error_deg: float, integral_deg: float, held: bool
) -> None:
    """Wind-up: an iteration whose lean is at its bound while the stroke's error pushes the
    same way is counted (``wedge_now[2]``), and the stroke's error is added to the integral
    only for the share of its iterations that were not."""
    off, on = _plans(cfg, error_deg, 2.0, integral_deg)
    assert on.plan is not None and off.plan is not None and on.targets is not None
    assert on.state.wedge_now[1] == 1  # the wedge was observed this iteration
    assert on.state.wedge_now[2] == int(held)
    at_bound = abs(on.plan.sigma_d - off.plan.sigma_d) == pytest.approx(RECENTRE_MAX)
    assert at_bound == (abs(error_deg) > 1.0 or integral_deg > 0)


def test_a_stroke_the_lean_could_not_act_on_adds_its_share(cfg: Settings) -> None:
    """A half stroke's end adds the full stroke's error × the share of its iterations whose
    lean was not held (3 of 10 held: 0.7 × the error)."""
    p, ctx = params(cfg, recentre_strokes=2.0), cfg.model_context()
    s = RollState(iteration=50, half_strokes=6, wedge_ref=0.0, wedge_integral=rad(1.0),
                  wedge_last=(rad(4.0) * 6, 6, 1), wedge_now=(rad(4.0) * 4, 4, 2),
                  travel=10.0, turned=10.0, direction=1)  # fmt: skip
    r = step(s, TILTED, frame(20.0), EMPTY, p, ctx)  # Finger 2's contact lost: a reversal
    assert r.state.half_strokes == 7
    assert r.state.wedge_error == pytest.approx(rad(4.0))
    assert r.state.wedge_integral == pytest.approx(rad(1.0) + 0.7 * rad(4.0))
    assert r.state.stroke_iterations == 10 and r.state.wedge_now == (0.0, 0, 0)
