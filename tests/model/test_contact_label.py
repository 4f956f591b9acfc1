"""The contact estimate's plain-Python labelling and row profile against scipy and numpy: the
same groups in the same order, the same depth to the last bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from sdh2svc.config import Settings
from sdh2svc.model.contact import _grid, _label, estimate_contact
from sdh2svc.model.depth import contact_depth

EIGHT = np.ones((3, 3), dtype=bool)


@pytest.mark.parametrize("shape", [(13, 6), (14, 6), (1, 1), (3, 9)])
def test_label_numbers_groups_as_scipy(shape: tuple[int, int]) -> None:
    rng = np.random.default_rng(7)
    grid = _grid(*shape, ())
    for _ in range(500):
        loaded = rng.random(shape) < rng.uniform(0.05, 0.7)
        want, n = ndimage.label(loaded, structure=EIGHT)
        got = np.zeros(shape, dtype=int)
        groups = _label(loaded.ravel().astype(int).tolist(), 0, grid.neighbours)
        for i, cells in enumerate(groups, start=1):
            got.ravel()[cells] = i
        assert len(groups) == n
        assert (got == want).all()


def test_estimate_matches_numpy_depth(cfg: Settings) -> None:
    """The depth from the main blob's rows equals contact_depth on the masked matrix."""
    layout, calib = cfg.tactile.distal, cfg.calibration
    ctx = cfg.model_context()
    assert ctx.compliance is not None
    rng = np.random.default_rng(3)
    valid = layout.valid()
    full_rows = valid.all(axis=1)
    for _ in range(300):
        counts = rng.integers(0, 4096, size=(layout.rows, layout.cols)).astype(np.uint16)
        counts[rng.random(counts.shape) < rng.uniform(0.3, 0.95)] = 0
        e = estimate_contact(counts, layout, ctx.pitch_mm, calib, cfg.hand.pad, ctx.compliance)
        values = np.where(valid, counts, 0).astype(np.float64)
        labels, n = ndimage.label(values > calib.cell_threshold_counts, structure=EIGHT)
        assert e.present == (n > 0) and len(e.blobs) == n
        if n == 0:
            continue
        main = 1 + max(range(n), key=lambda i: e.blobs[i].pressure_sum_n_per_mm2)
        total = sum(b.pressure_sum_n_per_mm2 for b in e.blobs) / calib.pressure_per_count_n_per_mm2
        want = contact_depth(values, labels == main, full_rows, ctx.pitch_mm, ctx.compliance,
                             total_counts=total)  # fmt: skip
        assert e.depth == want
        for i, b in enumerate(e.blobs, start=1):
            rows, cols = np.nonzero(labels == i)
            w = values[rows, cols]
            total = float(w.sum())
            assert (b.n_cells, b.first_row, b.last_row) == (rows.size, rows.min(), rows.max())
            assert b.S_mm == ctx.pitch_mm * (float((rows * w).sum()) / total)
            assert b.col_mm == ctx.pitch_mm * (float((cols * w).sum()) / total)
            assert b.pressure_sum_n_per_mm2 == total * calib.pressure_per_count_n_per_mm2
