"""experiments.slide_trace: the contacts' common slide beyond the pads' motion, and the traced run
is the campaign's run."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import sdh2svc.control.runner as runner
from experiments.slide_trace import common_slide, trace
from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import run_case
from sdh2svc.config import Settings
from sdh2svc.model.kinematics import HandPose, Point
from sdh2svc.model.observe import Observation, observe


def _pressed(cfg: Settings) -> np.ndarray:
    m = np.zeros((cfg.tactile.distal.rows, cfg.tactile.distal.cols), dtype=np.uint16)
    m[5, :], m[6, :] = 200, 1500
    return m


@pytest.fixture(scope="module")
def held(cfg: Settings) -> Observation:
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))
    return observe(pose, _pressed(cfg), _pressed(cfg), cfg.model_context())


def test_contacts_that_stay_on_their_pad_points_slide_none(cfg: Settings,
                                                           held: Observation) -> None:  # fmt: skip
    assert common_slide(held, held, cfg.model_context()) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("d", [0.3, -0.5])
def test_both_contacts_moved_across_ab_slide_by_as_much(cfg: Settings, held: Observation,
                                                        d: float) -> None:  # fmt: skip
    pts = held.points
    assert pts is not None
    ab = (pts.B.y - pts.A.y, pts.B.z - pts.A.z)
    n = math.hypot(*ab)
    ty, tz = -ab[1] / n, ab[0] / n  # across AB

    def moved(p: Point, k: float) -> Point:
        return Point(p.y + k * ty, p.z + k * tz)

    both = dataclasses.replace(held, points=dataclasses.replace(pts, A=moved(pts.A, d),
                                                                B=moved(pts.B, d)))  # fmt: skip
    assert common_slide(held, both, cfg.model_context()) == pytest.approx(d, abs=1e-9)
    # a turn about AB's middle moves the two contacts opposite ways: no common part
    turned = dataclasses.replace(held, points=dataclasses.replace(pts, A=moved(pts.A, d),
                                                                  B=moved(pts.B, -d)))  # fmt: skip
    assert common_slide(held, turned, cfg.model_context()) == pytest.approx(0.0, abs=1e-9)


def test_the_traced_run_is_the_campaigns() -> None:
    case = load_suite("smoke").cases[0]
    row, rows = trace(case, ["rolling.cycles=1"])
    ref = run_case(case.model_dump_json(), ("rolling.cycles=1",))
    assert (row["status"], row["iterations"]) == (ref["status"], ref["iterations"])
    assert runner.step.__module__ == "sdh2svc.control.rolling"  # the runner's step restored
    # one row per iteration after the first (the common slide needs the previous one)
    assert [it for it, _, _ in rows] == list(range(2, ref["iterations"] + 1))
