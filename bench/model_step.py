"""One full model step: two contact estimates, FK, Λ/σ, IK of both fingers, ω for both fingers.

This is the arithmetic of one rolling iteration without any I/O; it has to stay far below the
tactile bus's frame period (≈ 33 ms at the controller's 30 fps cap).
"""

from __future__ import annotations

import math

import numpy as np

from bench.common import percentile, summary_us, time_calls
from sdh2svc.config import default_config
from sdh2svc.model.friction import omega
from sdh2svc.model.kinematics import Finger, HandPose, contact_point, finger_ik
from sdh2svc.model.observe import observe


def run(n: int = 20000) -> dict[str, float]:
    cfg = default_config()
    ctx = cfg.model_context()
    rng = np.random.default_rng(1)
    m1 = np.zeros((13, 6), dtype=np.uint16)
    m1[5:8, 1:5] = rng.integers(300, 1500, size=(3, 4))
    m2 = np.zeros((13, 6), dtype=np.uint16)
    m2[8:10, 0:6] = rng.integers(300, 1500, size=(2, 6))
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -20, 30)))

    def step() -> None:
        obs = observe(pose, m1, m2, ctx)
        assert obs.points is not None
        c1, c2 = obs.contact1, obs.contact2
        # Finger 2 steps, Finger 1 follows through IK; then ω at the desired configuration
        p4, p5 = pose.phi4 - 0.004, pose.phi5 + 0.008
        Bd = contact_point(Finger.TWO, p4, p5, c2.r_mm, c2.theta_rad, ctx.geom)
        Ad = obs.points.A
        ik1 = finger_ik(
            Finger.ONE, Ad, c1.r_mm, c1.theta_rad, (pose.phi2, pose.phi3), ctx.geom, ctx.limits1
        )
        ik2 = finger_ik(Finger.TWO, Bd, c2.r_mm, c2.theta_rad, (p4, p5), ctx.geom, ctx.limits2)
        assert ik1.solution is not None and ik2.solution is not None
        s1, s2 = ik1.solution, ik2.solution
        omega(Finger.ONE, s1.proximal + s1.distal, c1.x3_mm, Ad, Bd, ctx.geom.pad)
        omega(Finger.TWO, s2.proximal + s2.distal, c2.x3_mm, Bd, Ad, ctx.geom.pad)

    samples = time_calls(step, n)
    contact = time_calls(lambda: ctx.contact(m1), n // 4)
    med, p99 = float(np.median(samples)), percentile(samples, 99)
    frame_period_us = 1e6 / 30
    print("model step (2 contact estimates, FK, Λ/σ, 2 IK, 2 ω)")
    print(f"  full step          {summary_us(samples)}")
    print(f"  contact estimate   {summary_us(contact)}")
    print(
        f"  frame period at 30 fps = {frame_period_us:.0f} µs → step p99 uses "
        f"{100 * p99 / frame_period_us:.2f} % of it (ratio {frame_period_us / p99:.0f}×)"
    )
    return {"step_median_us": med, "step_p99_us": p99}
