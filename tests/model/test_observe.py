"""The sensing half of an iteration: tactile matrices + angles → A, B, Λ, σ, ω."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sdh2svc.config import Settings, load_config
from sdh2svc.model.kinematics import HandPose
from sdh2svc.model.observe import observe


def s20(cfg: Settings) -> np.ndarray:
    """A distal frame whose centroid is S = 20 mm: rows 5 and 6 loaded 200 : 1500."""
    m = np.zeros((cfg.tactile.distal.rows, cfg.tactile.distal.cols), dtype=np.uint16)
    m[5, :] = 200
    m[6, :] = 1500
    return m


def test_observe_mirror_pose(cfg: Settings) -> None:
    """hand-model §6's check values: the thesis's model, contacts on the undeformed pads."""
    ctx = load_config(None, ["hand.contact_depth.model=none"]).model_context()
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))
    obs = observe(pose, s20(cfg), s20(cfg), ctx)
    assert obs.contact1.S_mm == pytest.approx(20.0)
    assert obs.points is not None
    assert obs.Lambda == pytest.approx(82.20, abs=0.005)
    assert obs.sigma == pytest.approx(0.0, abs=1e-12)
    assert math.degrees(obs.omega_A) == pytest.approx(91.39, abs=0.005)
    assert obs.omega_A == pytest.approx(obs.omega_B)


def test_observe_without_second_contact(cfg: Settings) -> None:
    ctx = cfg.model_context()
    pose = HandPose(0.0, 0.0, 0.0, 0.0)
    obs = observe(pose, s20(cfg), np.zeros_like(s20(cfg)), ctx)
    assert obs.contact1.present and not obs.contact2.present
    assert obs.points is None
    assert obs.Lambda is None and obs.omega_A is None
