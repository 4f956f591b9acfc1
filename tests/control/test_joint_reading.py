"""An iteration takes the newest joint angles; stale ones are a fault, as a stale frame."""

from __future__ import annotations

import asyncio
from types import SimpleNamespace
from typing import Any

import pytest

from sdh2svc.bus.joint import JointReading
from sdh2svc.config import Settings
from sdh2svc.control.runner import RunFault, Runner
from sdh2svc.control.safety import Fault
from sdh2svc.sim.clock import run_fast

ANGLES = (10.0, -20.0, 15.0, -25.0, 5.0, -20.0, 10.0)


def _runner(cfg: Settings, reading: JointReading | None) -> Runner:
    joints: Any = SimpleNamespace(take_reading=lambda: reading)
    return Runner(cfg.control(), joints, tactile=None)  # type: ignore[arg-type]


def test_fresh_angles_and_their_age(cfg: Settings) -> None:
    async def main() -> tuple[tuple[float, ...], float]:  # on the virtual clock: time stands
        now = asyncio.get_running_loop().time()
        return _runner(cfg, JointReading(ANGLES, now - 0.004))._newest_angles()

    angles, age_ms = run_fast(main())
    assert angles == ANGLES
    assert age_ms == pytest.approx(4.0, abs=1e-9)


@pytest.mark.parametrize("age_s", [None, 0.301])
async def test_stale_or_missing_angles_fault(cfg: Settings, age_s: float | None) -> None:
    assert cfg.safety.stale_joint_ms == 300.0
    now = asyncio.get_running_loop().time()
    reading = None if age_s is None else JointReading(ANGLES, now - age_s)
    with pytest.raises(RunFault, match="joint angles") as info:
        _runner(cfg, reading)._newest_angles()
    assert info.value.fault is Fault.JOINT_ERROR
