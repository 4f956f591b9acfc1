"""How deep a contact sits below the undeformed pad surface (docs/contact-depth.md).

The thesis's model puts each contact point on the undeformed pad surface. A pressed object sits
deeper: the pad's rubber is compressed under it, and the finger itself yields along the pad
normal (structure, gears, servo), which the joint encoders do not see. Both shorten the measured
Λ = |AB|. This module estimates, from one pad's tactile matrix alone, how far below the surface
the contact really is:

    depth = e + c

* e = N / k_f: the finger's yield, N the pad's normal force (Σ p × cell area, with the pad's
  *physical* pressure calibration), k_f the finger's stiffness along the pad normal.
* c: the rubber's compression at the contact (its pressure-weighted mean under the object),
  from an elastic foundation (Winkler) model of the rubber, p = k_r · c, with k_r the rubber's
  stiffness (pressure per mm of compression) and c ≤ t, its thickness (it bottoms out on the
  finger's shell). For any convex contact profile (a face pressed flat, a curved surface, a
  corner) the pressure-weighted mean compression is

      c = Σ p² / (k_r Σ p)  ≈ κ · P' / (k_r · σ_p),   κ = 0.27,

  where P' = N / w is the load per mm of the band the object presses across the pad (w, from the
  columns) and σ_p the standard deviation of the pressure along the pad (κ is 1/(2√3) = 0.289 for
  a uniform footprint, 0.268 for a parabolic one, 0.272 for a triangular one). The sensor blurs
  and averages: the row profile's variance is σ_p² + s² + a²/12 (s the rubber's spread of a
  point load, a the cell pitch), so σ_p² is the measured variance less that. A load narrower
  than a cell (an edge, a corner, a thin rounded end) is not resolved: σ_p is then unknown and
  the estimate falls back on a wedge whose faces rise from the pad at slope m (``corner_slope``),
  for which P' = k_r δ²/m and c = (2/3)·δ, i.e.

      c_wedge = (2/3) · sqrt(P' · m / k_r).

  The estimate is c = min(c_footprint, c_wedge), never less than the cell-averaged value
  Σ p_row² / (k_r Σ p_row) (averaging can only flatten a peak) and never more than t.

Everything here is known to the controller: the matrix, the pitch and mask, and properties of
the hand (rubber stiffness and thickness, the finger's stiffness, the pads' physical pressure
per count, the rubber's spread). Nothing about the object is assumed beyond the corner slope of
an unresolved load. The pressure scale of real pads drifts (±50 % in the simulated campaign):
e and a resolved c scale with it, c_wedge with its square root.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

import numpy as np
from pydantic import Field

from sdh2svc.model.base import Finite

# pressure-weighted mean compression ≈ KAPPA · P' / (k_r σ_p) for convex contact profiles
KAPPA = 0.27


class ContactDepthModel(Finite):
    """Which contact-depth model the hand model uses (``[hand.contact_depth]``).

    ``model = "none"``: the thesis's model, every contact on the undeformed pad surface.
    ``model = "winkler"``: the contact moved along the pad normal, into the pad, by the finger's
    yield plus the rubber's compression (:func:`contact_depth`).
    """

    model: Literal["none", "winkler"] = "winkler"
    # tan of the angle at which the faces of an unresolved load (an edge, a corner, a thin end)
    # rise from the pad: 1.0 is a right-angled corner pressed point first
    corner_slope: Annotated[float, Field(gt=0.0, le=10.0)] = 1.0


@dataclass(frozen=True, slots=True)
class PadCompliance:
    """What the depth estimate needs to know about the hand and its pads."""

    rubber_stiffness_n_per_mm3: float  # pressure per mm of rubber compression
    rubber_thickness_mm: float  # the most the rubber compresses
    finger_stiffness_n_per_mm: float  # the finger's yield along the pad normal
    pressure_per_count_n_per_mm2: float  # physical pressure per raw count
    spread_mm: float  # the rubber's spread of a point load (Gaussian σ) before the cells
    corner_slope: float  # see ContactDepthModel


@dataclass(frozen=True, slots=True)
class ContactDepth:
    """Result of :func:`contact_depth`, mm (and N): ``depth_mm = yield_mm + compression_mm``."""

    depth_mm: float
    yield_mm: float
    compression_mm: float
    normal_force_n: float
    band_mm: float  # width of the pressed band across the pad
    footprint_sd_mm: float | None  # σ_p along the pad; None: not resolved (narrower than a cell)


NO_DEPTH = ContactDepth(0.0, 0.0, 0.0, 0.0, 0.0, None)


def contact_depth(
    counts: np.ndarray,
    contact: np.ndarray,
    full_rows: np.ndarray,
    pitch_mm: float,
    hand: PadCompliance,
    total_counts: float | None = None,
) -> ContactDepth:
    """Depth of one contact below the undeformed pad surface.

    ``counts``: the pad's raw counts (rows along the pad, row 0 at the fingertip's end), masked
    cells 0; ``contact``: boolean, the cells of this contact (its blob); ``full_rows``: the rows
    with every column a real cell (they measure the band's width); ``total_counts``: the sum of
    the counts of every loaded cell of the pad (the finger's load), default the contact's.
    """
    values = counts * contact
    # along the pad: each row's load and its largest cell (counts), as plain floats: 13 rows are
    # too few for numpy to pay off
    rows = values.sum(axis=1).tolist()
    peaks = values.max(axis=1).tolist()
    return row_depth(rows, peaks, full_rows.tolist(), pitch_mm, hand, total_counts)


def row_depth(
    rows: list[float],
    peaks: list[float],
    full_rows: Sequence[bool],
    pitch_mm: float,
    hand: PadCompliance,
    total_counts: float | None = None,
) -> ContactDepth:
    """:func:`contact_depth` from the contact's rows alone: each row's load ``rows`` and its
    largest cell ``peaks`` (counts; 0.0 in rows the contact does not touch)."""
    per = hand.pressure_per_count_n_per_mm2
    total = sum(rows)
    if total <= 0.0:
        return NO_DEPTH
    cell = pitch_mm * pitch_mm
    force = (total if total_counts is None else total_counts) * per * cell
    e = force / hand.finger_stiffness_n_per_mm
    k, t = hand.rubber_stiffness_n_per_mm3, hand.rubber_thickness_mm
    # across the pad: the band's width, each full row's load over its largest cell (in cells),
    # averaged over those rows by load (over every loaded row if no full row is loaded)
    num = den = num_all = s1 = s2 = sq = 0.0
    for j, (q, top, full) in enumerate(zip(rows, peaks, full_rows, strict=True)):
        if q <= 0.0:
            continue
        num_all += q * q / top
        if full:
            num += q * q / top
            den += q
        s1 += q * j
        s2 += q * j * j
        sq += q * q
    band = pitch_mm * (num / den if den > 0.0 else num_all / total)
    load = total * per * cell / band  # P': N per mm of band
    # (3) on the rows: the mean pressure under the band in each row is q·per·pitch/band
    c_cells = per * pitch_mm / band * sq / (k * total)
    mean = s1 / total
    var = (s2 / total - mean * mean) * cell  # the rows' variance along the pad, mm²
    var_p = var - hand.spread_mm**2 - cell / 12.0
    c_wedge = 2.0 / 3.0 * math.sqrt(load * hand.corner_slope / k)
    sd = math.sqrt(var_p) if var_p > 0.0 else None
    c_foot = KAPPA * load / (k * sd) if sd is not None else math.inf
    c = min(max(min(c_foot, c_wedge), c_cells), t)
    return ContactDepth(e + c, e, c, force, band, sd)
