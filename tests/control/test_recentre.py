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
    s, pose, w = _half_stroke(s, pose, 5, p, cfg)
    seen.append(w)
    assert s.stroke_iterations == 9 and s.wedge_ref == pytest.approx(ref)
    assert s.wedge_error == pytest.approx(np.mean(seen[5] + seen[6]) - ref)


def _plans(cfg: Settings, error_deg: float, strokes: float) -> tuple[StepResult, StepResult]:
    """The thesis's plan and the plan re-centring against a stroke-mean wedge ``error_deg``
    above the reference stroke's (over a 400-iteration stroke), from the same observation."""
    ctx, m1, m2 = cfg.model_context(), frame(20.0), frame(24.0)
    state = RollState(iteration=5, wedge_ref=0.0, wedge_error=rad(error_deg),
                      stroke_iterations=400)  # fmt: skip
    off = step(replace(state, wedge_error=0.0), TILTED, m1, m2, params(cfg), ctx)
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
