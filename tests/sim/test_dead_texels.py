"""Dead texels (sim.sensor.dead_texels): cells that never report pressure, whatever presses them."""

from __future__ import annotations

import numpy as np
import pytest

from sdh2svc.campaign.case import Case, SensorVariation, Texel
from sdh2svc.config import ConfigError, Settings, load_config
from sdh2svc.connect import hand_model
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import get_object


def grasped_frames(cfg: Settings) -> list[np.ndarray]:
    """The egg grasped by closing both coupled fingers in a mirror pose (as the grasp does) until
    its distal pads read a firm load, then held still: the raw frames of ten ticks (noise and
    creep on, as configured)."""
    world = PhysicsWorld(hand_model(cfg), cfg.sim, get_object("egg"))
    a = cfg.axes
    q = [90.0, -30.0, 30.0, 0.0, 0.0, -30.0, 30.0]
    t = 0.0
    for _ in range(600):
        t += 0.02
        world.move_joints(t, q, [True] * 7)
        frame = world.tactile_frame(t, [0.5] * 6, [0] * 6)
        if world.truth().held and frame.sum() > 5000:
            break
        for prox, dist in ((a.phi2, a.phi3), (a.phi4, a.phi5)):
            q[prox] += 0.1
            q[dist] -= 0.1
    else:
        raise AssertionError("no grasp")
    frames = []
    for _ in range(10):
        t += 0.02
        world.move_joints(t, q, [True] * 7)
        frames.append(world.tactile_frame(t, [0.5] * 6, [0] * 6))
    return frames


def cell(cfg: Settings, matrix: int, row: int, col: int) -> int:
    shapes = [(cfg.tactile.proximal.rows, cfg.tactile.proximal.cols),
              (cfg.tactile.distal.rows, cfg.tactile.distal.cols)] * 3  # fmt: skip
    off = int(np.sum([r * c for r, c in shapes[:matrix]]))
    return off + row * shapes[matrix][1] + col


def test_dead_texels_read_zero_under_load_and_nothing_else_changes() -> None:
    base = load_config(use_env=False)
    live = grasped_frames(base)
    a = base.axes
    dist = base.tactile.distal
    # the most loaded cell of each coupled finger's distal pad, while held
    dead = []
    for m in (a.finger1_distal_matrix, a.finger2_distal_matrix):
        start = cell(base, m, 0, 0)
        pad = live[-1][start : start + dist.rows * dist.cols].reshape(dist.rows, dist.cols)
        r, c = np.unravel_index(int(np.argmax(pad)), pad.shape)
        assert pad[r, c] > 100  # pressed
        dead.append(Texel(matrix=m, row=int(r), col=int(c)))
    case = Case(id="dead", family="thesis", object=get_object("egg"), height_mm=125.0,
                true_width_mm=53.0, sensor=SensorVariation(dead_texels=tuple(dead)))  # fmt: skip
    keys = [k for k in case.overrides(base.sim.sensor.gain_vs_library) if "dead_texels" in k]
    assert len(keys) == 1  # the case's override parses as a TOML list of [matrix, row, col]
    cfg = load_config(overrides=keys, use_env=False)
    assert cfg.sim.sensor.dead_texels == tuple((t.matrix, t.row, t.col) for t in dead)
    broken = grasped_frames(cfg)
    idx = [cell(cfg, t.matrix, t.row, t.col) for t in dead]
    for before, after in zip(live, broken, strict=True):
        assert all(before[i] > 0 for i in idx)
        assert all(after[i] == 0 for i in idx)  # dead: never any pressure
        others = np.ones(before.shape, dtype=bool)
        others[idx] = False
        assert np.array_equal(before[others], after[others])  # the same noise, the same world


@pytest.mark.parametrize("value", ["[[6, 0, 0]]", "[[1, 0]]", "[[1, -1, 0]]", "[[1, 0, 6]]"])
def test_impossible_dead_texels_are_refused(value: str) -> None:
    with pytest.raises(ConfigError, match="dead_texels"):
        load_config(overrides=[f"sim.sensor.dead_texels={value}"], use_env=False)


def test_a_dead_texel_outside_its_matrix_is_refused() -> None:
    # refused with the configuration, before anything runs (a campaign's case crashed at its
    # run, on every resume); the distal pads have 13 rows
    with pytest.raises(ConfigError, match="has rows 0…12 and columns 0…5"):
        load_config(overrides=["sim.sensor.dead_texels=[[1, 13, 0]]"], use_env=False)
    # a position without a cell (the fingertip end of the pad is 4 cells wide) reads 0 anyway:
    # a whole pad listed dead lists it too
    load_config(overrides=["sim.sensor.dead_texels=[[1, 0, 0]]"], use_env=False)
