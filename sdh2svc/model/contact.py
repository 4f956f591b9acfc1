"""Contact estimation from one tactile matrix (hand-model §5, protocols.md §1.9).

Input: the raw 12-bit counts of one pad as a (rows, cols) array, row 0 at the fingertip's end.
Output: whether there is a contact and, if so, where (S, L, pad point x3/y3, virtual joint r/θ),
how strong (both force conventions) and how large.

The contact point is where the object really is: the pad point under the pressure centroid
(x3, y3), moved into the pad along its normal by the contact's depth (finger yield plus rubber
compression, :mod:`sdh2svc.model.depth`, docs/contact-depth.md) when a depth model is given;
the virtual joint (r, θ) leads to that point.

Separate blobs (8-connected groups of cells above the threshold) are all reported; the contact
point comes from the *stronger* blob (largest pressure sum), so a second, weaker touch elsewhere
on the pad does not drag the centroid into empty space between the two. The forces and area
cover the whole matrix, as SDHLibrary's ``GetContactInfo`` does, so they stay library-identical.
"""

from __future__ import annotations

import itertools
import math
import operator
from dataclasses import dataclass
from functools import lru_cache
from typing import Annotated, Any

import numpy as np
from pydantic import Field, field_validator, model_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.calibration import DistanceMap
from sdh2svc.model.depth import NO_DEPTH, ContactDepth, PadCompliance, row_depth
from sdh2svc.model.geometry import PadProfile, pad_point_from_L, pad_slope, virtual_joint


class MatrixLayout(Finite):
    """Shape of one tactile matrix and which of its positions are real cells.

    ``mask`` is one string per row (row 0 first), one character per column: ``#`` a real cell,
    ``.`` an absent one (always read as 0). An empty mask means every position is a cell.
    """

    rows: Annotated[int, Field(ge=1, le=64)]
    cols: Annotated[int, Field(ge=1, le=64)]
    mask: tuple[str, ...] = ()

    @field_validator("mask")
    @classmethod
    def _mask_chars(cls, rows: tuple[str, ...]) -> tuple[str, ...]:
        for i, row in enumerate(rows):
            if set(row) - {"#", "."}:
                raise ValueError(
                    f"mask row {i} {row!r} may contain only '#' (cell) and '.' (absent)"
                )
        return rows

    @model_validator(mode="after")
    def _mask_shape(self) -> MatrixLayout:
        if self.mask and (
            len(self.mask) != self.rows or any(len(r) != self.cols for r in self.mask)
        ):
            raise ValueError(
                f"mask must have {self.rows} rows of {self.cols} characters "
                f"(got {len(self.mask)} rows of lengths {sorted({len(r) for r in self.mask})})"
            )
        return self

    @property
    def cells(self) -> int:
        return self.rows * self.cols

    def valid(self) -> np.ndarray:
        """Boolean (rows, cols) array, True where a real cell is."""
        return _mask_array(self.rows, self.cols, self.mask)


@lru_cache(maxsize=32)
def _mask_array(rows: int, cols: int, mask: tuple[str, ...]) -> np.ndarray:
    if not mask:
        arr = np.ones((rows, cols), dtype=bool)
    else:
        arr = np.array([[c == "#" for c in row] for row in mask], dtype=bool)
    arr.flags.writeable = False
    return arr


@dataclass(frozen=True, slots=True)
class _Grid:
    """A layout's cells by flat (row-major) index: their rows and columns, which are absent,
    each one's 8 neighbours, and which rows have every position a real cell (they measure a
    band's width)."""

    rows: int
    row_of: tuple[int, ...]
    col_of: tuple[int, ...]
    absent: tuple[int, ...]
    neighbours: tuple[tuple[int, ...], ...]
    full_rows: tuple[bool, ...]


@lru_cache(maxsize=32)
def _grid(rows: int, cols: int, mask: tuple[str, ...]) -> _Grid:
    valid = _mask_array(rows, cols, mask)
    neighbours = tuple(
        tuple(
            a * cols + b
            for a in range(i - 1, i + 2)
            for b in range(j - 1, j + 2)
            if (a, b) != (i, j) and 0 <= a < rows and 0 <= b < cols
        )
        for i in range(rows)
        for j in range(cols)
    )
    absent = tuple(int(k) for k in np.flatnonzero(~valid))
    row_of = tuple(k // cols for k in range(rows * cols))
    col_of = tuple(k % cols for k in range(rows * cols))
    full_rows = tuple(all(row) for row in valid.tolist())
    return _Grid(rows, row_of, col_of, absent, neighbours, full_rows)


def _label(flat: list[Any], threshold: float, neighbours: tuple[tuple[int, ...], ...]
           ) -> list[list[int]]:  # fmt: skip
    """The 8-connected groups of cells above ``threshold`` (flat indices), numbered as
    ``scipy.ndimage.label`` numbers them: by each group's first cell in row-major order. A
    breadth-first fill in plain Python: on 78 cells it is several times cheaper than scipy."""
    loaded = [v > threshold for v in flat]
    groups = []
    # compress reads ``loaded`` as it goes: a cell a group took is no start
    for start in itertools.compress(range(len(loaded)), loaded):
        loaded[start] = False
        group = [start]
        for k in group:  # grows while it is read: breadth first
            for nb in neighbours[k]:
                if loaded[nb]:
                    loaded[nb] = False
                    group.append(nb)
        groups.append(group)
    return groups


class TactileCalibration(Finite):
    """Raw counts → pressure, the contact threshold, and the S → distance map."""

    pressure_per_count_n_per_mm2: Annotated[float, Field(gt=0.0, le=1.0)]
    cell_threshold_counts: Annotated[int, Field(ge=0, le=4095)]
    edge_margin_rows: Annotated[float, Field(ge=0.0, le=6.0)]
    distance: DistanceMap
    # The controller's force: Σp × this area (see ContactEstimate.force); 0: the library's force.
    force_reference_area_mm2: Annotated[float, Field(ge=0.0, le=2000.0)] = 0.0
    # The pads' physical pressure per raw count (N/mm² per count; the contact-depth model's
    # scale, docs/contact-depth.md) and the rubber's spread of a point load before the cells.
    physical_pressure_per_count_n_per_mm2: Annotated[float, Field(gt=0.0, le=1.0)] = 1.5977e-5
    spread_mm: Annotated[float, Field(ge=0.0, le=10.0)] = 1.0

    def force_per_newton(self, pitch_mm: float) -> float | None:
        """The controller's force F for 1 N pressed on a pad whose cells read exactly as this
        calibration says (its physical pressure per count; no noise, creep, threshold or lost
        cell): Σp × the reference area, Σp = N / cell area × the library's pressure per count /
        the physical one. None for the library's force (no reference area), which depends on
        the contact's area, not on the force alone."""
        if self.force_reference_area_mm2 <= 0.0:
            return None
        scale = self.pressure_per_count_n_per_mm2 / self.physical_pressure_per_count_n_per_mm2
        return scale * self.force_reference_area_mm2 / (pitch_mm * pitch_mm)


@dataclass(frozen=True, slots=True)
class Blob:
    """One connected group of loaded cells."""

    S_mm: float  # pressure-centroid height from row 0's centre
    col_mm: float  # pressure-centroid across the pad from column 0's centre
    n_cells: int
    pressure_sum_n_per_mm2: float
    force_library: float
    force_physical_n: float
    first_row: int
    last_row: int


@dataclass(frozen=True, slots=True)
class ContactEstimate:
    """Result of :func:`estimate_contact`. Position fields are None when there is no contact.

    ``force_library`` is SDHLibrary's ``GetContactInfo`` force (Σp × total contact area), the
    convention of the thesis's Fd = 2; ``force_physical_n`` is Σp × cell area (eq 2.20, N).
    ``force`` is the one the controller uses: Σp × a fixed reference area
    (``TactileCalibration.force_reference_area_mm2``), or the library's force when that is 0.
    The library's force grows with the square of the contact's area (Σp already sums over the
    cells), so the same squeeze reads 10× less on a stick's end than on a box's face; Σp × a
    fixed area is proportional to the normal force whatever the contact's size, and equals the
    library's force for a contact of that area.

    ``x3_mm``, ``y3_mm`` are the pad surface point under the contact's centroid; ``r_mm``,
    ``theta_rad`` the virtual link to the contact itself, ``depth.depth_mm`` below that point
    along the pad normal (0 without a depth model: then the surface point).
    """

    present: bool
    S_mm: float | None
    L_mm: float | None
    x3_mm: float | None
    y3_mm: float | None
    r_mm: float | None
    theta_rad: float | None
    at_edge: bool
    force_library: float
    force_physical_n: float
    force: float
    area_mm2: float
    n_cells: int
    blobs: tuple[Blob, ...]
    depth: ContactDepth = NO_DEPTH
    # rows from the centroid to the nearer end row's centre (``at_edge``: within
    # edge_margin_rows); None without a contact
    edge_rows: float | None = None

    @property
    def virtual_joint(self) -> tuple[float, float] | None:
        if self.r_mm is None or self.theta_rad is None:
            return None
        return self.r_mm, self.theta_rad


NO_CONTACT = ContactEstimate(
    present=False,
    S_mm=None,
    L_mm=None,
    x3_mm=None,
    y3_mm=None,
    r_mm=None,
    theta_rad=None,
    at_edge=False,
    force_library=0.0,
    force_physical_n=0.0,
    force=0.0,
    area_mm2=0.0,
    n_cells=0,
    blobs=(),
)


def _forces(pressure_sum: float, n_cells: int, pitch: float) -> tuple[float, float]:
    """(library, physical) force of cells whose pressures sum to ``pressure_sum`` (N/mm²):
    SDHLibrary's Σp × total contact area, and Σp × cell area (eq 2.20)."""
    cell_area = pitch * pitch
    return pressure_sum * n_cells * cell_area, pressure_sum * cell_area


def _blob(flat: list[Any], cells: list[int], grid: _Grid, pitch: float, p_per_count: float
          ) -> Blob:  # fmt: skip
    # the counts are whole numbers, so these sums are exact in any order
    w = [flat[k] for k in cells]
    rows = [grid.row_of[k] for k in cells]
    cols = [grid.col_of[k] for k in cells]
    total = float(sum(w))
    n = len(cells)
    pressure = total * p_per_count
    library, physical = _forces(pressure, n, pitch)
    return Blob(
        S_mm=pitch * (float(sum(map(operator.mul, rows, w))) / total),
        col_mm=pitch * (float(sum(map(operator.mul, cols, w))) / total),
        n_cells=n,
        pressure_sum_n_per_mm2=pressure,
        force_library=library,
        force_physical_n=physical,
        first_row=min(rows),
        last_row=max(rows),
    )


def _row_profile(flat: list[Any], cells: list[int], grid: _Grid
                 ) -> tuple[list[float], list[float]]:  # fmt: skip
    """Each row's load and its largest cell over ``cells`` (0.0 in rows without one)."""
    load, peak = [0] * grid.rows, [0] * grid.rows
    for k in cells:
        i, v = grid.row_of[k], flat[k]
        load[i] += v
        if v > peak[i]:
            peak[i] = v
    return [float(q) for q in load], [float(p) for p in peak]


FULL_SCALE_COUNTS = 4095  # a cell's highest reading: the DSACON32m's 12-bit converter


def saturated_force(
    layout: MatrixLayout, pitch_mm: float, calib: TactileCalibration, pad: PadProfile
) -> float:
    """The controller's force F on a pad whose every cell reads full scale: no pad reads more,
    so a force limit at or above it can never trip."""
    full = np.full((layout.rows, layout.cols), FULL_SCALE_COUNTS, dtype=np.uint16)
    return estimate_contact(full, layout, pitch_mm, calib, pad).force


def estimate_contact(
    counts: np.ndarray,
    layout: MatrixLayout,
    pitch_mm: float,
    calib: TactileCalibration,
    pad: PadProfile,
    compliance: PadCompliance | None = None,
) -> ContactEstimate:
    """Estimate the contact on one pad from its raw counts, shape (rows, cols), row 0 at the tip.

    ``compliance``: the hand's depth model parameters; None puts the contact on the undeformed
    pad surface (the thesis's model)."""
    if counts.shape != (layout.rows, layout.cols):
        raise ValueError(
            f"tactile matrix has shape {counts.shape}, layout says {(layout.rows, layout.cols)}"
        )
    grid = _grid(layout.rows, layout.cols, layout.mask)
    flat = counts.ravel().tolist()
    for k in grid.absent:  # an absent position always reads 0
        flat[k] = 0
    groups = _label(flat, calib.cell_threshold_counts, grid.neighbours)
    if not groups:
        return NO_CONTACT
    p_per_count = calib.pressure_per_count_n_per_mm2
    blobs = tuple(_blob(flat, cells, grid, pitch_mm, p_per_count) for cells in groups)
    main_index = max(range(len(blobs)), key=lambda i: blobs[i].pressure_sum_n_per_mm2)
    main = blobs[main_index]
    # the blobs partition the loaded cells: the whole pad's totals are their sums
    n_cells = sum(b.n_cells for b in blobs)
    pressure = sum(b.pressure_sum_n_per_mm2 for b in blobs)
    library, physical = _forces(pressure, n_cells, pitch_mm)
    ref = calib.force_reference_area_mm2
    S = main.S_mm
    s_range = (layout.rows - 1) * pitch_mm
    L = calib.distance.L_from_S(S, s_range, pad)
    x3, y3 = pad_point_from_L(L, pad)
    depth = NO_DEPTH
    if compliance is not None:
        load, peaks = _row_profile(flat, groups[main_index], grid)
        depth = row_depth(load, peaks, grid.full_rows, pitch_mm, compliance,
                          total_counts=pressure / p_per_count)  # fmt: skip
    r, theta = virtual_joint(*below_surface(x3, y3, depth.depth_mm, pad))
    row = S / pitch_mm
    edge_rows = min(row, (layout.rows - 1) - row)
    return ContactEstimate(
        present=True,
        S_mm=S,
        L_mm=L,
        x3_mm=x3,
        y3_mm=y3,
        r_mm=r,
        theta_rad=theta,
        at_edge=edge_rows < calib.edge_margin_rows,
        force_library=library,
        force_physical_n=physical,
        force=pressure * ref if ref > 0 else library,
        area_mm2=n_cells * pitch_mm * pitch_mm,
        n_cells=n_cells,
        blobs=blobs,
        depth=depth,
        edge_rows=edge_rows,
    )


def below_surface(x3: float, y3: float, depth_mm: float, pad: PadProfile) -> tuple[float, float]:
    """The frame-3 point ``depth_mm`` below the pad surface point (x3, y3), along the pad's
    inward normal n = (m, −1)/sqrt(1 + m²), m the profile's slope dy3/dx3 at x3."""
    if depth_mm == 0.0:
        return x3, y3
    m = pad_slope(x3, pad)
    k = depth_mm / math.sqrt(1.0 + m * m)
    return x3 + m * k, y3 - k
