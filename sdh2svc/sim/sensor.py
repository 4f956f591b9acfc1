"""The simulated DSA tactile pads: contact pressure → raw 12-bit counts, imperfectly.

* Geometry: each matrix's rows lie along its pad at the cell pitch, centred on the active area
  (distal pads: rows 0…12 from the fingertip's end, centred at L = 27.5 mm; proximal pads: row 0
  nearest the distal joint). The columns span the pad's width; the object presses a band of its
  depth across the middle of the pad.
* The pad's rubber spreads a load: pressure along the pad is blurred with a Gaussian of
  ``spread_mm`` before each cell averages what falls on it, so a point contact lights two or
  three rows and an edge concentrates while a face spreads.
* Counts: the inverse of SDHLibrary's nominal pressure formula (:data:`LIBRARY_PRESSURE_PER_COUNT`)
  scaled by ``gain_vs_library`` (1.0: exactly the library's nominal calibration; see sim.toml) —
  the simulated pads' own, whatever the controller's configuration believes (a mis-set
  ``calibration`` reads forces wrong in simulation as on a real hand),
  plus seeded Gaussian noise on loaded cells (an unloaded resistive cell reads a clean 0),
  then the controller's sensitivity, threshold and saturation at 4095.
* Pressure from outside the physics (a person pressing a pad, :mod:`sdh2svc.sim.press`) is
  added to the cells' pressure before creep and noise: it reads as any load does.
* Dead texels (``dead_texels``, [matrix, row, col] each) read 0 whatever presses them, as a
  broken cell of a worn pad does.
* Creep (thesis §2.8, §4.1): each cell keeps a memory m that follows its pressure with a time
  constant ``creep_rise_s`` while loaded and decays with ``creep_fall_s``; it reads
  P + creep_gain·min(m, P). Under a constant load the reading rises over seconds; unloaded it
  reads 0, but a load that comes back soon reads higher than it did the first time.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Annotated, Final

import numpy as np
from pydantic import Field, Strict, field_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.contact import MatrixLayout
from sdh2svc.sim.world import FACTORY_SENSITIVITY, MAX_COUNT

# SDHLibrary's nominal calibration, 0.000473 N/mm² per 592.1 counts: what gain_vs_library scales
LIBRARY_PRESSURE_PER_COUNT: Final = 7.988515453e-7  # N/mm² per count
MATRICES, MAX_ROWS, MAX_COLS = 6, 14, 6  # the DSA's six matrices; the largest (proximal) 14 × 6
DeadIndex = Annotated[int, Strict(), Field(ge=0)]
_Settings = tuple[tuple[float, ...], tuple[int, ...], np.ndarray, np.ndarray | None]


class SensorModelConfig(Finite):
    """Imperfections of the simulated tactile sensor (see config/sim.toml)."""

    spread_mm: Annotated[float, Field(gt=0.0, le=10.0)]
    gain_vs_library: Annotated[float, Field(gt=0.0, le=10.0)]
    noise: bool
    noise_counts: Annotated[float, Field(ge=0.0, le=500.0)]
    creep: bool
    creep_gain: Annotated[float, Field(ge=0.0, le=5.0)]
    creep_rise_s: Annotated[float, Field(gt=0.0, le=3600.0)]
    creep_fall_s: Annotated[float, Field(gt=0.0, le=3600.0)]
    # cells that never report pressure, [matrix, row, col] each (wire order of the six matrices)
    dead_texels: tuple[tuple[DeadIndex, DeadIndex, DeadIndex], ...] = ()

    @field_validator("dead_texels")
    @classmethod
    def _cells_exist(
        cls, cells: tuple[tuple[int, int, int], ...]
    ) -> tuple[tuple[int, int, int], ...]:
        for m, r, c in cells:
            if not (m < MATRICES and r < MAX_ROWS and c < MAX_COLS):
                bounds = f"matrix 0…{MATRICES - 1}, row 0…{MAX_ROWS - 1}, col 0…{MAX_COLS - 1}"
                raise ValueError(f"dead texel [{m}, {r}, {c}]: no such cell ({bounds})")
        return cells


class PadRaster:
    """Maps pressure samples along one surface onto the cells of one matrix."""

    def __init__(
        self, s: np.ndarray, ds: float, layout: MatrixLayout, pitch: float, centre_s: float,
        spread: float,
    ) -> None:  # fmt: skip
        # imported here, not at the top: every command imports this module with the
        # configuration, and scipy.special costs ≈ 0.2 s of its start
        from scipy.special import ndtr

        rows = layout.rows
        centres = centre_s + ((rows - 1) / 2 - np.arange(rows)) * pitch  # row 0 at high s
        hi = (centres[:, None] + pitch / 2 - s[None, :]) / spread
        lo = (centres[:, None] - pitch / 2 - s[None, :]) / spread
        # share of sample k's load (spread by the rubber) that falls on row j, per mm of row
        self.weights = (ndtr(hi) - ndtr(lo)) * ds / pitch
        self.row_centres = centres
        self.layout = layout
        self.pitch = pitch
        self._valid = layout.valid()
        self._spread: tuple[float, np.ndarray] | None = None  # (band, column share × valid)

    def _columns(self, band_mm: float) -> np.ndarray:
        """Share of each cell's width under the object's band, times the valid mask (cached:
        the band is the object's depth, fixed for a run)."""
        if self._spread is None or self._spread[0] != band_mm:
            cols = self.layout.cols
            left = (np.arange(cols) - cols / 2) * self.pitch
            right = np.minimum(left + self.pitch, band_mm / 2)
            overlap = np.clip(right - np.maximum(left, -band_mm / 2), 0.0, self.pitch)
            self._spread = (band_mm, (overlap / self.pitch)[None, :] * self._valid)
        return self._spread[1]

    def cells(self, idx: np.ndarray, pressure: np.ndarray, band_mm: float) -> np.ndarray:
        """(rows, cols) mean pressure on each cell for pressures at samples ``idx`` (ascending,
        as the physics gives them)."""
        # a contact presses one run of samples: a view of its columns instead of a copy
        run = idx.size and int(idx[-1]) - int(idx[0]) + 1 == idx.size
        w = self.weights[:, int(idx[0]) : int(idx[-1]) + 1] if run else self.weights[:, idx]
        row_p = w @ pressure
        out: np.ndarray = row_p[:, None] * self._columns(band_mm)
        return out


class TactileSensorModel:
    """All six matrices: pressure per surface → one flat frame of raw counts in wire order."""

    def __init__(
        self,
        cfg: SensorModelConfig,
        layouts: Sequence[MatrixLayout],
        rasters: Mapping[int, tuple[int, PadRaster]],
        seed: int,
    ) -> None:
        self.cfg = cfg
        self.layouts = tuple(layouts)
        self.shapes = tuple((lay.rows, lay.cols) for lay in layouts)
        self.rasters = dict(rasters)  # surface index → (matrix index, raster)
        self.per_count = LIBRARY_PRESSURE_PER_COUNT / cfg.gain_vs_library
        self.rng = np.random.default_rng(seed)
        sizes = [r * c for r, c in self.shapes]
        self.offsets = [0, *np.cumsum(sizes).tolist()]  # each matrix's start in a frame
        self.memory = np.zeros(self.offsets[-1])  # creep memory of every cell, wire order
        self.valid = np.concatenate([lay.valid().ravel() for lay in layouts])
        for m, r, c in cfg.dead_texels:  # a dead cell reads 0 whatever presses it
            if m >= len(self.shapes) or r >= self.shapes[m][0] or c >= self.shapes[m][1]:
                raise ValueError(f"dead texel [{m}, {r}, {c}]: matrix {m} has no such cell")
            self.valid[self.offsets[m] + r * self.shapes[m][1] + c] = False
        self._absent = np.flatnonzero(~self.valid)  # an index: cheaper than a mask per frame
        self._t: float | None = None
        # (sensitivity, threshold, gain per cell, threshold per cell or None when all are <= 0)
        self._settings: _Settings | None = None

    def fail(self, matrices: Sequence[int]) -> None:
        """Every cell of ``matrices`` reads 0 from now on, whatever presses it (a matrix that
        fails mid-run: its ribbon cable pulled; the frames go on)."""
        for m in matrices:
            self.valid[self.offsets[m] : self.offsets[m + 1]] = False
        self._absent = np.flatnonzero(~self.valid)

    def _flat_pressures(
        self, by_surface: Mapping[int, tuple[np.ndarray, np.ndarray]], band_mm: float
    ) -> np.ndarray:
        """True mean pressure (N/mm²) on every cell, flat in wire order."""
        out = np.zeros(self.memory.shape)
        for surface, (idx, p) in by_surface.items():
            if surface in self.rasters and len(idx):
                m, raster = self.rasters[surface]
                out[self.offsets[m] : self.offsets[m + 1]] += raster.cells(idx, p, band_mm).ravel()
        return out

    def pressures(
        self, by_surface: Mapping[int, tuple[np.ndarray, np.ndarray]], band_mm: float
    ) -> list[np.ndarray]:
        """True mean pressure (N/mm²) on every cell of the six matrices."""
        flat = self._flat_pressures(by_surface, band_mm)
        return [
            flat[self.offsets[m] : self.offsets[m + 1]].reshape(shape)
            for m, shape in enumerate(self.shapes)
        ]

    def frame(
        self,
        now: float,
        by_surface: Mapping[int, tuple[np.ndarray, np.ndarray]],
        band_mm: float,
        sensitivity: Sequence[float],
        threshold: Sequence[int],
        pressed: np.ndarray | None = None,
    ) -> np.ndarray:
        """Raw counts of all six matrices at ``now`` (flat uint16, wire order); ``pressed``: more
        pressure (N/mm², flat, wire order) from outside the physics — a person's press."""
        p = self._flat_pressures(by_surface, band_mm)
        if pressed is not None:
            p += pressed
        dt = 0.0 if self._t is None else max(0.0, now - self._t)
        self._t = now
        cfg = self.cfg
        reading = p
        if cfg.creep:  # all cells at once; the rate per cell is one of two
            mem = self.memory
            rise, fall = -np.expm1(-dt / cfg.creep_rise_s), -np.expm1(-dt / cfg.creep_fall_s)
            mem += (p - mem) * np.where(p > mem, rise, fall)
            reading = np.minimum(mem, p)  # p + creep_gain·min(m, p), in place (+ and · commute)
            reading *= cfg.creep_gain
            reading += p
        c = reading / self.per_count
        if cfg.noise and cfg.noise_counts > 0:
            # an unloaded resistive cell reads a clean 0; loaded ones are noisy (one draw per
            # cell, in wire order: the same stream as drawing matrix by matrix)
            noise = self.rng.normal(0.0, cfg.noise_counts, c.shape)
            # c + noise·(c > 0.5): an unloaded cell adds ±0.0 (the draws are finite), which
            # at most turns a -0.0 into 0.0, the same count; np.where or a masked add cost more
            noise *= c > 0.5
            c += noise
        np.maximum(c, 0.0, out=c)
        c[self._absent] = 0.0  # cells missing from the layout, and dead ones
        return self._apply_settings(c, sensitivity, threshold)

    def _apply_settings(
        self, raw: np.ndarray, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        """:func:`~sdh2svc.sim.world.apply_sensor_settings` on all matrices at once (the gain
        and threshold per cell are cached until the controller changes them)."""
        key_s, key_t = tuple(sensitivity), tuple(threshold)
        st = self._settings
        if st is None or st[0] != key_s or st[1] != key_t:
            sizes = np.diff(self.offsets)
            gain = np.repeat([float(v) / FACTORY_SENSITIVITY for v in key_s], sizes)
            thr = np.repeat(np.asarray([int(v) for v in key_t], dtype=float), sizes)
            # counts are >= 0 here: a threshold of 0 or below suppresses nothing
            st = (key_s, key_t, gain, thr if thr.max() > 0 else None)
            self._settings = st
        # np.clip's own overhead is far dearer than its two ufuncs; in place: no temporaries
        seg: np.ndarray = raw * st[2]
        np.rint(seg, out=seg)
        np.maximum(seg, 0.0, out=seg)
        np.minimum(seg, MAX_COUNT, out=seg)
        if st[3] is not None:
            seg[seg < st[3]] = 0
        return seg.astype(np.uint16)
