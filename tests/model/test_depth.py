"""The contact-depth model (docs/contact-depth.md) on synthetic tactile matrices."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from sdh2svc.config import Settings, load_config
from sdh2svc.model.contact import below_surface, estimate_contact
from sdh2svc.model.depth import contact_depth
from sdh2svc.model.geometry import pad_slope
from sdh2svc.model.kinematics import Finger, HandPose, frame3_axes, hand_points
from sdh2svc.model.observe import observe

PITCH = 3.4


@pytest.fixture(scope="module")
def off() -> Settings:
    return load_config(None, ["hand.contact_depth.model=none"])


def empty(cfg: Settings) -> np.ndarray:
    return np.zeros((cfg.tactile.distal.rows, cfg.tactile.distal.cols), dtype=np.uint16)


def newtons_to_counts(cfg: Settings, newtons: float, cells: int) -> float:
    """Counts per cell that make ``newtons`` spread evenly over ``cells`` cells."""
    per = cfg.calibration.physical_pressure_per_count_n_per_mm2
    return newtons / (cells * PITCH * PITCH * per)


def flat_face(cfg: Settings, newtons: float) -> np.ndarray:
    """A face pressed flat: 8 full rows evenly loaded."""
    m = empty(cfg)
    m[4:12, :] = round(newtons_to_counts(cfg, newtons, 48))
    return m


def edge(cfg: Settings, newtons: float) -> np.ndarray:
    """An edge across the pad, as the rubber and the cells blur it: 1 : 10 : 1 over three rows."""
    m = empty(cfg)
    c = newtons_to_counts(cfg, newtons, 72)  # 12 row-units of 6 cells
    m[7, :], m[8, :], m[9, :] = round(c), round(10 * c), round(c)
    return m


def depth(cfg: Settings, m: np.ndarray):
    return cfg.model_context().contact(m).depth


def test_flat_face_hardly_compresses_the_rubber(cfg: Settings) -> None:
    d = depth(cfg, flat_face(cfg, 2.5))
    k = cfg.hand.pad.rubber_stiffness_n_per_mm3
    p = 2.5 / (48 * PITCH * PITCH)  # the face's pressure
    assert d.normal_force_n == pytest.approx(2.5, rel=0.01)
    assert d.band_mm == pytest.approx(6 * PITCH)
    assert d.compression_mm == pytest.approx(p / k, rel=0.05)  # ≈ 0.05 mm
    assert d.yield_mm == pytest.approx(2.5 / cfg.hand.finger_stiffness_n_per_mm, rel=0.01)
    assert d.depth_mm == pytest.approx(d.yield_mm + d.compression_mm)


def test_concentrated_load_sinks_deeper(cfg: Settings) -> None:
    flat, sharp = depth(cfg, flat_face(cfg, 2.5)), depth(cfg, edge(cfg, 2.5))
    assert sharp.normal_force_n == pytest.approx(flat.normal_force_n, rel=0.01)
    assert sharp.footprint_sd_mm is None  # narrower than the sensor resolves
    assert sharp.compression_mm > 5 * flat.compression_mm
    assert sharp.depth_mm > flat.depth_mm + 0.3


@pytest.mark.parametrize("shape", [flat_face, edge])
def test_depth_grows_with_force(cfg: Settings, shape) -> None:
    depths = [depth(cfg, shape(cfg, f)).depth_mm for f in (0.5, 1.0, 2.0, 4.0, 8.0)]
    assert all(b > a for a, b in itertools.pairwise(depths))


def test_compression_is_bounded_by_the_rubber(cfg: Settings) -> None:
    rng = np.random.default_rng(7)
    t = cfg.hand.pad.rubber_thickness_mm
    for _ in range(200):  # random loads, up to saturation
        m = empty(cfg)
        lo = int(rng.integers(0, 12))
        hi = int(rng.integers(lo + 1, 14))
        m[lo:hi, :] = rng.integers(0, 4096, size=(hi - lo, 6))
        m = np.where(cfg.tactile.distal.valid(), m, 0).astype(np.uint16)
        d = depth(cfg, m)
        assert 0.0 <= d.compression_mm <= t
        assert d.depth_mm == pytest.approx(d.yield_mm + d.compression_mm)
    # a thin rubber bottoms out: an edge pressed hard sinks by the rubber's thickness, no more
    thin = load_config(None, ["hand.pad.rubber_thickness_mm=0.3"])
    m = empty(thin)
    m[8, :] = 4095
    d = depth(thin, m)
    assert d.compression_mm == 0.3
    assert d.depth_mm == pytest.approx(d.yield_mm + 0.3)


def test_only_the_contacts_cells_shape_it(cfg: Settings) -> None:
    """A second, weaker touch elsewhere adds to the finger's load, not to the contact's shape."""
    m = edge(cfg, 2.0)
    both = m.copy()
    both[1, 2:4] = 300
    a, b = depth(cfg, m), depth(cfg, both)
    assert b.normal_force_n > a.normal_force_n
    assert b.compression_mm == pytest.approx(a.compression_mm)
    assert contact_depth(m.astype(float), np.zeros(m.shape, bool), np.ones(13, bool), PITCH,
                         cfg.model_context().compliance).depth_mm == 0.0  # fmt: skip


def test_below_surface_is_along_the_pad_normal(cfg: Settings) -> None:
    pad = cfg.hand.pad
    assert below_surface(25.0, 15.0, 0.7, pad) == pytest.approx((25.0, 14.3))  # flat part
    x3 = 50.0
    y3 = pad.flat_y3_mm - pad.arc_radius_mm + math.sqrt(pad.arc_radius_mm**2 - (x3 - 33.5) ** 2)
    x, y = below_surface(x3, y3, 0.7, pad)
    # on the arc: 0.7 mm closer to the arc's centre K, on the same radius
    K = (pad.flat_end_x3_mm, pad.flat_y3_mm - pad.arc_radius_mm)
    assert math.hypot(x - K[0], y - K[1]) == pytest.approx(pad.arc_radius_mm - 0.7)
    assert math.atan2(x - K[0], y - K[1]) == pytest.approx(math.atan2(x3 - K[0], y3 - K[1]))


def test_model_none_is_the_undeformed_surface(cfg: Settings, off: Settings) -> None:
    """The switch off reproduces the thesis's model exactly: virtual joint of the surface point."""
    m = edge(cfg, 3.0)
    c_off = off.model_context().contact(m)
    plain = estimate_contact(m, off.tactile.distal, PITCH, off.calibration, off.hand.pad)
    assert off.model_context().compliance is None
    assert c_off == plain
    assert c_off.depth.depth_mm == 0.0
    assert (c_off.r_mm, c_off.theta_rad) == (math.hypot(c_off.x3_mm, c_off.y3_mm),
                                             math.atan2(c_off.x3_mm, c_off.y3_mm))  # fmt: skip
    c_on = cfg.model_context().contact(m)
    assert (c_on.S_mm, c_on.x3_mm, c_on.force) == (c_off.S_mm, c_off.x3_mm, c_off.force)
    assert c_on.r_mm != c_off.r_mm


@pytest.mark.parametrize("rows", [(5, 6), (1, 2)])  # flat part; arc
def test_observe_moves_A_and_B_into_the_pads(cfg: Settings, off: Settings, rows) -> None:
    m1 = empty(cfg)
    m1[rows[0], 1:5], m1[rows[1], 1:5] = 400, 1500
    m2 = empty(cfg)
    m2[rows[0], 1:5], m2[rows[1], 1:5] = 900, 900
    pose = HandPose(*(math.radians(a) for a in (-20, 30, -15, 25)))
    o_on, o_off = (
        observe(pose, m1, m2, cfg.model_context()),
        observe(pose, m1, m2, off.model_context()),
    )
    assert o_on.Lambda is not None and o_off.Lambda is not None
    assert o_on.points is not None and o_off.points is not None
    for finger, c, new, old in (
        (Finger.ONE, o_on.contact1, o_on.points.A, o_off.points.A),
        (Finger.TWO, o_on.contact2, o_on.points.B, o_off.points.B),
    ):
        prox, dist = pose.finger(finger)
        ex, ey = frame3_axes(finger, prox + dist)
        slope = pad_slope(c.x3_mm, cfg.hand.pad)
        n = math.hypot(1.0, slope)
        inward = ((slope * ex.y - ey.y) / n, (slope * ex.z - ey.z) / n)  # (m, −1)/√(1+m²)
        moved = (new.y - old.y, new.z - old.z)
        assert c.depth.depth_mm > 0.2
        assert moved == pytest.approx((c.depth.depth_mm * inward[0],
                                       c.depth.depth_mm * inward[1]), abs=1e-9)  # fmt: skip
    # the contacts move apart: Λ grows by about both depths; σ, ω come from the moved points
    grow = o_on.contact1.depth.depth_mm + o_on.contact2.depth.depth_mm
    assert o_on.Lambda - o_off.Lambda == pytest.approx(grow, rel=0.1)
    vj1, vj2 = o_on.contact1.virtual_joint, o_on.contact2.virtual_joint
    assert vj1 is not None and vj2 is not None
    assert hand_points(pose, vj1, vj2, cfg.hand) == o_on.points
    assert o_on.sigma != o_off.sigma or o_on.omega_A != o_off.omega_A
