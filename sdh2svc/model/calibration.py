"""Calibration of the contact height S to a distance along the pad (hand-model §5, thesis §2.7).

The sensor reports S, the pressure centroid's height in mm from the centre of row 0 (the
fingertip's end). A *distance map* turns S into the measured distance of the contact from the
active area's upper edge; the thesis's linear map is d = S·44/40.8 (eq 2.18), and a user can
measure a piecewise-linear table instead. The curved distance from the pad's base I is then
L = active_length − d + base_to_active (eq 2.19: L = 49.5 − S·44/40.8).
"""

from __future__ import annotations

import itertools
from typing import Annotated, Literal

import numpy as np
from pydantic import Field, model_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.geometry import PadProfile

TablePoint = tuple[
    Annotated[float, Field(ge=-10.0, le=100.0)], Annotated[float, Field(ge=-20.0, le=100.0)]
]


class DistanceMap(Finite):
    """S → measured distance (mm from the active area's upper edge).

    ``kind = "linear"`` is the thesis's map (|error| ≤ 1 mm over real distances −1 … 45 mm,
    Table 6);
    ``kind = "table"`` interpolates the user's measured ``table`` of (S_mm, distance_mm) points,
    ascending in S, and extends its end segments linearly.
    """

    kind: Literal["linear", "table"]
    table: tuple[TablePoint, ...] = ()

    @model_validator(mode="after")
    def _table_valid(self) -> DistanceMap:
        if self.kind == "linear" and self.table:  # measured, then never used: say so
            raise ValueError("a table is used only with kind = 'table' (this map is 'linear')")
        if self.kind == "table":
            if len(self.table) < 2:
                raise ValueError(
                    "a 'table' distance map needs at least 2 (S_mm, distance_mm) points"
                )
            s = [p[0] for p in self.table]
            if any(b <= a for a, b in itertools.pairwise(s)):
                raise ValueError(f"table S values must be strictly ascending, got {s}")
        return self

    def measured_distance(self, S: float, s_range_mm: float, pad: PadProfile) -> float:
        """Distance (mm) of the contact from the active area's upper edge, for centroid height S."""
        if self.kind == "linear":
            return S * pad.sensor_active_length_mm / s_range_mm
        xs = [p[0] for p in self.table]
        ys = [p[1] for p in self.table]
        if S <= xs[0] or S >= xs[-1]:
            i = 0 if S <= xs[0] else len(xs) - 2
            slope = (ys[i + 1] - ys[i]) / (xs[i + 1] - xs[i])
            return ys[i] + slope * (S - xs[i])
        return float(np.interp(S, xs, ys))

    def L_from_S(self, S: float, s_range_mm: float, pad: PadProfile) -> float:
        """Curved distance L (mm) of the contact from the pad's base I (eq 2.19), on the pad:
        a measured table extrapolated past its points is clamped to the pad's base and tip."""
        d = self.measured_distance(S, s_range_mm, pad)
        L = pad.sensor_active_length_mm - d + pad.pad_base_to_active_mm
        return min(max(L, 0.0), pad.max_L_mm)
