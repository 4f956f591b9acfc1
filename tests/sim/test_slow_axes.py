"""Axes slower than commanded (sim.slow_axes): a worn gearbox, a finger rubbing on something."""

from __future__ import annotations

import logging

import pytest

from sdh2svc.config import ConfigError, load_config
from sdh2svc.connect import Simulated, hand_model, simulated_hand
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import get_object

TICK_S = 0.005  # the SDH2's servo tick


def test_a_slow_axis_moves_at_its_speed_and_the_others_follow_their_reference() -> None:
    cfg = load_config(overrides=["sim.slow_axes=[[1, 2.0], [2, 0.0]]"], use_env=False)
    world = PhysicsWorld(hand_model(cfg), cfg.sim, get_object("egg"))
    start = list(cfg.sim.start_deg)
    ref = [10.0, start[1] + 20.0, start[2] + 5.0, *start[3:5], start[5] - 3.0, start[6]]
    t = 0.0
    world.move_joints(t, start, [True] * 7)
    for _ in range(200):  # 1 s of servo ticks
        t += TICK_S
        got = world.move_joints(t, ref, [True] * 7)
    assert got[1] == pytest.approx(start[1] + 2.0)  # 2°/s for 1 s, not the 20° asked
    assert got[2] == start[2]  # jammed
    assert [got[i] for i in (0, 3, 4, 5, 6)] == [ref[i] for i in (0, 3, 4, 5, 6)]
    for _ in range(2000):  # 10 s more: the slow axis arrives and stays there
        t += TICK_S
        got = world.move_joints(t, ref, [True] * 7)
    assert got[1] == ref[1] and got[2] == start[2]


def test_a_limp_slow_axis_stays_where_it_is() -> None:
    cfg = load_config(overrides=["sim.slow_axes=[[1, 2.0]]"], use_env=False)
    world = PhysicsWorld(hand_model(cfg), cfg.sim, get_object("egg"))
    start = list(cfg.sim.start_deg)
    world.move_joints(0.0, start, [True] * 7)
    got = world.move_joints(1.0, [a + 5.0 for a in start], [False] * 7)
    assert list(got) == start


@pytest.mark.parametrize(("value", "says"), [
    ("[[7, 1.0]]", "less than or equal to 6"),
    ("[[1, -1.0]]", "greater than or equal to 0"),
    ("[[1, 1.0], [1, 2.0]]", "axis 1 is given more than one speed"),
    ("[[1.5, 1.0]]", "valid integer"),
])  # fmt: skip
def test_a_bad_slow_axis_is_refused_naming_it(value: str, says: str) -> None:
    with pytest.raises(ConfigError, match="slow_axes") as e:
        load_config(overrides=[f"sim.slow_axes={value}"], use_env=False)
    assert says in str(e.value)


async def test_a_hand_that_drags_says_so_when_it_starts(caplog: pytest.LogCaptureFixture) -> None:
    cfg = load_config(overrides=["sim.slow_axes=[[1, 0.6], [5, 0]]"], use_env=False)
    with caplog.at_level(logging.WARNING, logger="sdh2svc.sim.lab"):
        async with simulated_hand(cfg, Simulated(fast=True)):
            pass
    said = [r.getMessage() for r in caplog.records if r.name == "sdh2svc.sim.lab"]
    assert said == ["the simulated hand drags (sim.slow_axes): axis 1 moves at most 0.6°/s; "
                    "axis 5 moves at most 0°/s"]  # fmt: skip


async def test_a_hand_that_does_not_drag_says_nothing_of_it(
    caplog: pytest.LogCaptureFixture,
) -> None:
    with caplog.at_level(logging.WARNING, logger="sdh2svc.sim.lab"):
        async with simulated_hand(load_config(use_env=False), Simulated(fast=True)):
            pass
    assert not [r for r in caplog.records if "drags" in r.getMessage()]
