"""The third finger and a person's press: the middle finger's joints and pads in the simulated
world, and a press by pad, position, force, area and duration read through the DSACON32m's bytes."""

from __future__ import annotations

import math

import numpy as np
import pytest

from sdh2svc.config import ConfigError, Settings, load_config
from sdh2svc.connect import Simulated, connect_hand, hand_model
from sdh2svc.model.contact import MatrixLayout
from sdh2svc.sim.clock import run_fast
from sdh2svc.sim.hand import MIDDLE_PARKED_DEG, PhysicsWorld
from sdh2svc.sim.press import Press, parse_spec, press_cells

PITCH = 3.4
SPREAD = 1.0  # sim.toml's sensor.spread_mm
DISTAL = MatrixLayout(rows=13, cols=6)


def moments(cells: np.ndarray, pitch: float = PITCH) -> tuple[float, float, float, float]:
    """Total force (N) from mean cell pressures, the load's centre (x across, y along, mm) and
    the radius of the uniform disc whose spread load has that variance along the pad."""
    rows, cols = cells.shape
    w = cells * pitch * pitch
    force = float(w.sum())
    y = (np.arange(rows) + 0.5) * pitch
    x = (np.arange(cols) + 0.5) * pitch
    cy = float((w.sum(axis=1) * y).sum() / force)
    cx = float((w.sum(axis=0) * x).sum() / force)
    var_y = float((w.sum(axis=1) * (y - cy) ** 2).sum() / force)
    # a disc's variance along one axis is r²/4; the rubber adds σ², the cells pitch²/12
    radius = 2 * math.sqrt(max(0.0, var_y - SPREAD**2 - pitch**2 / 12))
    return force, cx, cy, radius


def test_a_press_carries_its_force_over_its_disc() -> None:
    for r in (2.0, 4.0, 6.0):
        press = Press(pad=1, x_mm=10.2, y_mm=22.1, force_n=2.0, radius_mm=r)
        force, cx, cy, radius = moments(press_cells(press, DISTAL, PITCH, SPREAD))
        assert force == pytest.approx(2.0, rel=1e-3)  # far from the edges: nothing lost
        assert (cx, cy) == pytest.approx((10.2, 22.1), abs=0.05)
        assert radius == pytest.approx(r, rel=0.15)  # sampled on the cells' grid: ≈
    # at the very tip, the load the rubber spreads beyond the pad's edge is lost
    edge = Press(pad=1, x_mm=10.2, y_mm=0.0, force_n=2.0, radius_mm=3.0)
    assert 0.4 < press_cells(edge, DISTAL, PITCH, SPREAD).sum() * PITCH**2 < 1.1


@pytest.mark.parametrize(
    ("spec", "want"),
    [
        ("pad=3,x=10,y=12,force=2,radius=4,duration=1.5,at=5",
         (Press(pad=3, x_mm=10, y_mm=12, force_n=2, radius_mm=4, duration_s=1.5), 5.0)),
        ("pad=0 x=1.5  y=2, force=0.5",
         (Press(pad=0, x_mm=1.5, y_mm=2, force_n=0.5), 0.0)),
    ],
)  # fmt: skip
def test_the_spec_parser_reads_a_press(spec: str, want: tuple[Press, float]) -> None:
    assert parse_spec(spec) == want


@pytest.mark.parametrize(
    ("spec", "why"),
    [
        ("pad=3,x=10,y=12", "missing force"),
        ("pad=3,x=10,y=12,force=2,colour=red", "'colour=red': expected key=value"),
        ("pad=3,x=10,y=12,force=two", "force='two': not a number"),
        ("pad=3,x=10,y=12,force=nan", "not a finite number"),
        ("pad=2.5,x=10,y=12,force=2", "pad=2.5: a matrix number"),
        ("pad=6,x=10,y=12,force=2", "pad: Input should be less than or equal to 5"),
        ("pad=3,x=10,y=12,force=0", "force: Input should be greater than 0"),
        ("pad=3,x=10,y=12,force=500", "force: Input should be less than or equal to 50"),
        ("pad=3,x=10,y=12,force=1,duration=61", "duration: Input should be less than or equal"),
        ("pad=3,x=10,y=12,force=1,at=-1", "at=-1: a delay is ≥ 0 s"),
        ("pad=3,pad=4,x=10,y=12,force=1", "pad given twice"),
    ],
)
def test_the_spec_parser_says_what_is_wrong(spec: str, why: str) -> None:
    with pytest.raises(ValueError) as e:
        parse_spec(spec)
    assert why in str(e.value)


@pytest.fixture(scope="module")
def cfg() -> Settings:
    return load_config(overrides=["sim.object='egg'"], use_env=False)


def test_a_press_off_its_pad_is_refused(cfg: Settings) -> None:
    world = PhysicsWorld(hand_model(cfg), cfg.sim)
    with pytest.raises(ValueError, match=r"y_mm = 45 is off pad 3 \(0…44.2 mm along\)"):
        world.press(Press(pad=3, x_mm=10, y_mm=45, force_n=1), 0.0)
    with pytest.raises(ValueError, match=r"x_mm = 21 is off pad 2 \(0…20.4 mm across\)"):
        world.press(Press(pad=2, x_mm=21, y_mm=10, force_n=1), 0.0)


def test_the_middle_finger_parks_follows_its_targets_and_its_pads_read_a_press(
    cfg: Settings,
) -> None:
    """Through the bytes of both lines (fast mode): our drivers read the SDH2's angles and parse
    the DSACON32m's frames."""
    axes = cfg.axes
    middle = (axes.thumb_proximal, axes.thumb_distal)
    pad = axes.thumb_distal_matrix
    per_count = cfg.calibration.pressure_per_count_n_per_mm2 / cfg.sim.sensor.gain_vs_library

    async def main() -> None:
        async with connect_hand(cfg, Simulated(fast=True)) as hand:
            bench, joints = hand.bench, hand.joints
            assert bench is not None
            actual = await joints.get_actual()
            assert tuple(actual[i] for i in middle) == pytest.approx(MIDDLE_PARKED_DEG, abs=1e-3)

            # it follows its targets like the other joints
            targets = list(actual)
            targets[axes.thumb_proximal], targets[axes.thumb_distal] = -40.0, 25.0
            await joints.set_velocities([60.0] * 7)
            await joints.set_targets(targets)
            await joints.move()
            await joints.wait_idle()
            actual = await joints.get_actual()
            assert tuple(actual[i] for i in middle) == pytest.approx((-40.0, 25.0), abs=0.05)

            # a press on its distal pad, in the frames the bus parses
            sub = hand.tactile.subscribe(range(6), 30.0)
            before = await sub.next_frame()
            assert not before.matrices[pad].any()
            press = Press(pad=pad, x_mm=10.2, y_mm=20.0, force_n=1.5, radius_mm=4.0,
                          duration_s=0.5)  # fmt: skip
            bench.press(press)
            loop_t0 = before.arrival
            frames = []
            while (f := await sub.next_frame()).arrival < loop_t0 + 1.0:
                frames.append(f)
            on = [f for f in frames if f.matrices[pad].any()]
            # ≈ 0.5 s of frames at 30 fps, each with the press (and nothing on the other pads)
            assert 12 <= len(on) <= 17, len(on)
            assert on[-1].arrival - on[0].arrival <= 0.5 + 1e-6
            for f in on:
                counts = f.matrices[pad].astype(float)
                force, cx, cy, radius = moments(counts * per_count)
                assert force == pytest.approx(1.5, rel=0.05)  # noise, creep: a few %
                assert (cx, cy) == pytest.approx((10.2, 20.0), abs=0.2)
                assert radius == pytest.approx(4.0, rel=0.15)
                assert not any(f.matrices[m].any() for m in range(6) if m != pad)
            assert not frames[-1].matrices[pad].any()  # lifted after its duration
            sub.close()

    run_fast(main())


def test_the_smallest_press_is_still_a_disc() -> None:
    tiny = Press(pad=1, x_mm=10.2, y_mm=22.1, force_n=1e-300, radius_mm=0.5)
    cells = press_cells(tiny, DISTAL, PITCH, SPREAD)
    assert np.isfinite(cells).all() and cells.sum() * PITCH**2 == pytest.approx(1e-300, rel=1e-3)
    with pytest.raises(ValueError, match="radius_mm"):
        Press(pad=1, x_mm=10.2, y_mm=22.1, force_n=1, radius_mm=5e-324)


def test_the_pads_keep_their_own_sensitivity_whatever_the_controller_believes(
    cfg: Settings,
) -> None:
    """A mis-set calibration in the controller's configuration (here twice the nominal) changes
    what the controller reads, never what the simulated pads measure: the same press gives the
    same counts, so simulation shows a calibration error as a real hand would."""
    x = 2 * cfg.calibration.pressure_per_count_n_per_mm2
    doubled = load_config(overrides=["sim.object='egg'", "sim.sensor.noise=false",
                                     f"calibration.pressure_per_count_n_per_mm2={x!r}"],
                          use_env=False)  # fmt: skip
    plain = load_config(overrides=["sim.object='egg'", "sim.sensor.noise=false"], use_env=False)
    frames = []
    for c in (plain, doubled):
        world = PhysicsWorld(hand_model(c), c.sim)
        world.press(Press(pad=2, x_mm=10.0, y_mm=20.0, force_n=1.0), 0.0)
        frames.append(world.tactile_frame(0.1, [0.5] * 6, [0] * 6))
    assert frames[0].max() > 0 and np.array_equal(frames[0], frames[1])


def test_the_hand_starts_where_the_configuration_says_within_the_joint_limits() -> None:
    """sim.start_deg: the world's joint angles before anything moves them (a hand left in the
    pre-shape spares the first run its move there); beyond what the hand reaches it is refused,
    and tighter joint limits do not bound it (they bound commands, not where a hand was left)."""
    cfg = load_config(overrides=["sim.start_deg=[90, -30, 30, -90, 0, -30, 30]"], use_env=False)
    world = PhysicsWorld(hand_model(cfg), cfg.sim)
    assert world.move_joints(0.0, [0.0] * 7, [False] * 7) == (90, -30, 30, -90, 0, -30, 30)
    with pytest.raises(ConfigError, match=r"axis 0: -5 \(the hand reaches 0 … 90\)"):
        load_config(overrides=["sim.start_deg=[-5, 0, 0, -90, 0, 0, 0]"], use_env=False)
    narrow = ["limits.min_deg=[0, -90, -90, -90, -90, -90, -90]",
              "limits.max_deg=[90, -20, 90, 90, 90, 90, 90]"]  # fmt: skip
    assert load_config(overrides=narrow, use_env=False).sim.start_deg[1] == 0.0
    with pytest.raises(ConfigError, match="start_deg"):
        load_config(overrides=["sim.start_deg=[0, 0, 0]"], use_env=False)
