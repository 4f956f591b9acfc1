"""The supervisor's bound on every command the runner sends, whatever the grasp law and the
rolling step propose: within the joint limits and at most ``safety.max_step_deg`` from the
angles just read. The grasp law and the rolling step keep to it themselves, so only a law or a
step that does not (here: one that asks 10° and more) shows that the runner's clamp is there —
a mutation audit removed it and every other test passed."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest

from sdh2svc.control import runner as runner_module
from sdh2svc.control.grasp import GraspStep
from sdh2svc.control.rolling import StepResult
from sdh2svc.model.kinematics import HandPose
from tests.control.test_runner import cfg_with, fast, rig

JUMP_DEG = 10.0


def _watch(runner: Any) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    """Every target the runner sends, beside the angles it had just read."""
    sent: list[tuple[tuple[float, ...], tuple[float, ...]]] = []
    joints = runner.joints
    for name in ("set_targets", "send_targets"):
        real = getattr(joints, name)

        async def spy(angles: Any, _real: Any = real) -> Any:
            reading = joints.reading
            assert reading is not None
            sent.append((tuple(angles), tuple(reading.angles)))
            return await _real(angles)

        setattr(joints, name, spy)
    return sent


def _run_watched(cfg: Any, tmp_path: Path) -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
    """A whole run on the simulated hand; every target it sent, beside the angles read."""

    async def main() -> list[tuple[tuple[float, ...], tuple[float, ...]]]:
        async with rig(cfg, tmp_path) as (_hand, runner):
            sent = _watch(runner)
            await runner.run()
            return sent

    return fast(main)


def _within_bounds(sent: list[tuple[tuple[float, ...], tuple[float, ...]]], cfg: Any) -> None:
    step, lo, hi = cfg.safety.max_step_deg, cfg.limits.min_deg, cfg.limits.max_deg
    for want, actual in sent:
        for axis, (w, a) in enumerate(zip(want, actual, strict=True)):
            assert abs(w - a) <= step + 1e-6, (axis, w, a)
            assert lo[axis] <= w <= hi[axis], (axis, w)


def test_a_grasp_law_that_asks_a_jump_is_clamped_to_one_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = cfg_with(tmp_path, "run.grasp_timeout_s=3.0")
    # closes every coupled joint by 10° a frame (the distal ones the other way: past a limit
    # soon), far beyond max_step_deg
    monkeypatch.setattr(runner_module, "grasp_step", lambda *a: GraspStep(
        (JUMP_DEG, -JUMP_DEG, JUMP_DEG, -JUMP_DEG), None))  # fmt: skip

    sent = _run_watched(cfg, tmp_path)
    grasp = [(w, a) for w, a in sent if any(abs(x - y) > 1e-9 for x, y in zip(w, a, strict=True))]
    assert len(grasp) > 10  # the law's jumps went out, each cut to one step
    _within_bounds(sent, cfg)


def test_a_rolling_step_that_asks_a_jump_is_clamped_to_one_step(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    cfg = cfg_with(tmp_path, "rolling.cycles=1")
    real_step = runner_module.step
    jump = math.radians(JUMP_DEG)
    rolled = []

    def jumping(*args: Any) -> StepResult:
        r = real_step(*args)
        if r.targets is None:
            return r
        rolled.append(1)
        t = r.targets
        return replace(r, targets=HandPose(t.phi2 + jump, t.phi3 - jump, t.phi4 + jump,
                                           t.phi5 - jump))  # fmt: skip

    monkeypatch.setattr(runner_module, "step", jumping)

    sent = _run_watched(cfg, tmp_path)
    assert len(rolled) >= 3  # the rolling ran and its jumps went out (the grip soon lost)
    _within_bounds(sent, cfg)
