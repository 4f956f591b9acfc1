"""Contact estimation on synthetic tactile matrices (hand-model §5, protocols.md §1.9)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from sdh2svc.config import Settings, load_config
from sdh2svc.model.contact import NO_CONTACT, estimate_contact

PITCH = 3.4


def est(cfg: Settings, counts: np.ndarray):
    return estimate_contact(
        counts, cfg.tactile.distal, cfg.tactile.texel_pitch_mm, cfg.calibration, cfg.hand.pad
    )


def empty(cfg: Settings) -> np.ndarray:
    return np.zeros((cfg.tactile.distal.rows, cfg.tactile.distal.cols), dtype=np.uint16)


def test_empty_frame_is_no_contact(cfg: Settings) -> None:
    e = est(cfg, empty(cfg))
    assert e is NO_CONTACT
    assert not e.present and e.S_mm is None and e.virtual_joint is None
    assert e.force_library == 0.0 and e.area_mm2 == 0.0


def test_below_threshold_is_no_contact(cfg: Settings) -> None:
    m = empty(cfg)
    m[:] = cfg.calibration.cell_threshold_counts  # equal to the threshold: not above it
    assert not est(cfg, m).present


@pytest.mark.parametrize("row", range(13))
def test_single_loaded_row_gives_its_height(cfg: Settings, row: int) -> None:
    m = empty(cfg)
    m[row, :] = 800
    e = est(cfg, m)
    assert e.present
    assert e.S_mm == pytest.approx(PITCH * row)
    valid_cols = cfg.tactile.distal.mask[row].count("#")
    assert e.n_cells == valid_cols


@pytest.mark.parametrize("row", range(12))
def test_symmetric_two_row_load_gives_mid_height(cfg: Settings, row: int) -> None:
    m = empty(cfg)
    m[row, 1:5] = 600
    m[row + 1, 1:5] = 600
    assert est(cfg, m).S_mm == pytest.approx(PITCH * (row + 0.5))


def test_masked_cells_are_ignored(cfg: Settings) -> None:
    m = empty(cfg)
    mask = cfg.tactile.distal.valid()
    absent = np.argwhere(~mask)
    assert len(absent) == 8  # thesis layout: 4 rows of 4 at the tip
    for r, c in absent:
        m[r, c] = 4095
    assert not est(cfg, m).present
    m[7, :] = 500
    e = est(cfg, m)
    assert e.S_mm == pytest.approx(PITCH * 7)
    assert e.n_cells == 6


def test_two_blobs_reported_and_stronger_used(cfg: Settings) -> None:
    m = empty(cfg)
    m[2, 2:4] = 300  # weak touch near the tip
    m[10, 1:5] = 900  # strong contact near the base
    e = est(cfg, m)
    assert len(e.blobs) == 2
    assert sorted(b.S_mm for b in e.blobs) == pytest.approx([2 * PITCH, 10 * PITCH])
    assert e.S_mm == pytest.approx(10 * PITCH)  # not the blend (≈ 8.6 rows)
    # forces and area cover the whole matrix, like SDHLibrary
    assert e.n_cells == 6
    assert e.force_library == pytest.approx(
        sum(b.pressure_sum_n_per_mm2 for b in e.blobs) * 6 * PITCH**2
    )


def test_force_conventions(cfg: Settings) -> None:
    c = cfg.calibration.pressure_per_count_n_per_mm2
    m = empty(cfg)
    m[6, 0:3] = 1000
    e = est(cfg, m)
    p = 3 * 1000 * c
    assert e.force_physical_n == pytest.approx(p * PITCH**2)
    assert e.force_library == pytest.approx(p * 3 * PITCH**2)  # Σp × total area
    assert e.area_mm2 == pytest.approx(3 * PITCH**2)


def test_contact_point_follows_linear_map(cfg: Settings) -> None:
    m = empty(cfg)
    m[6, :] = 700
    e = est(cfg, m)
    assert e.L_mm == pytest.approx(49.5 - 6 * PITCH * 44 / 40.8)
    assert e.r_mm == pytest.approx(math.hypot(e.x3_mm, e.y3_mm))
    assert e.theta_rad == pytest.approx(math.atan2(e.x3_mm, e.y3_mm))


def test_edge_rows_flagged(cfg: Settings) -> None:
    flags = {}
    for row in (0, 1, 11, 12):
        m = empty(cfg)
        m[row, 1:5] = 700
        flags[row] = est(cfg, m).at_edge
    assert flags == {0: True, 1: False, 11: False, 12: True}


def test_wrong_shape_rejected(cfg: Settings) -> None:
    with pytest.raises(ValueError, match="shape"):
        est(cfg, np.zeros((14, 6), dtype=np.uint16))


@settings(max_examples=200, deadline=None)
@given(counts=hnp.arrays(np.uint16, (13, 6), elements=st.integers(0, 4095)))
def test_any_frame_gives_a_consistent_estimate(cfg: Settings, counts: np.ndarray) -> None:
    e = est(cfg, counts)
    if e.present:
        assert 0.0 <= e.S_mm <= 12 * PITCH
        assert e.force_library >= 0.0 and e.n_cells >= 1
        assert e.n_cells == sum(b.n_cells for b in e.blobs)
        assert all(
            b.first_row * PITCH - 1e-9 <= b.S_mm <= b.last_row * PITCH + 1e-9 for b in e.blobs
        )
        assert math.isfinite(e.r_mm) and math.isfinite(e.theta_rad)
    else:
        assert e is NO_CONTACT


def test_a_measured_map_extrapolated_past_the_pad_leaves_the_contact_on_its_end() -> None:
    """A table whose line, extrapolated to row 0, puts the contact beyond the fingertip: L and
    the point both stay at the pad's end (one position for one contact)."""
    cfg = load_config(None, ['calibration.distance.kind="table"',
                             "calibration.distance.table=[[2.0, -4.0], [40.8, 44.0]]",
                             "hand.contact_depth.model=none"], use_env=False)  # fmt: skip
    ctx = cfg.model_context()
    pad = ctx.geom.pad
    m = np.zeros((ctx.distal.rows, ctx.distal.cols), dtype=np.uint16)
    m[0, :] = 1000  # row 0: the fingertip's end of the pad
    c = ctx.contact(m)
    assert c.S_mm == 0.0
    assert c.L_mm == pytest.approx(pad.max_L_mm) and c.x3_mm == pytest.approx(pad.tip_end_x3_mm)
