"""A person pressing a tactile pad: a disc of force on one matrix, for a while.

A press is given as a person would give it: which pad (matrix 0…5, wire order), where on it (mm,
in the pad's cell frame: ``x_mm`` across the pad from its column 0 edge, ``y_mm`` along it from
its row 0 edge — the fingertip's end of a distal pad, the distal joint's end of a proximal one),
how hard (N), over what area (a disc of ``radius_mm``) and how long (s). The load is a uniform
pressure F / (π r²) over the disc; the pad's rubber spreads it as it spreads any load (the
sensor's Gaussian ``spread_mm``) before each cell averages what falls on it. The sensor model then
reads it as any other pressure: creep, noise, the controller's sensitivity and threshold.

Presses are timed on the world's clock (the emulators' ``now``: virtual in fast mode) and only
read pressure; they push no joint and no object.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from pydantic import Field, Strict, ValidationError

from sdh2svc.model.base import Finite
from sdh2svc.model.contact import MatrixLayout

MAX_FORCE_N = 50.0  # a firm press of a fingertip is ~10 N; more is a typo
MAX_DURATION_S = 60.0
MIN_RADIUS_MM, MAX_RADIUS_MM = 0.5, 25.0  # a point of a pen … a palm (a pad is 20.4 mm wide)


class Press(Finite):
    """One press on one pad (see the module docstring for the frame). Strict: numbers, never
    true/false or strings; finite (the bounds)."""

    pad: Annotated[int, Strict(), Field(ge=0, le=5, description="matrix 0…5 (wire order)")]
    x_mm: Annotated[float, Strict(), Field(ge=0.0, le=100.0, description="across, from column 0")]
    y_mm: Annotated[float, Strict(), Field(ge=0.0, le=100.0, description="along, from row 0")]
    force_n: Annotated[float, Strict(), Field(gt=0.0, le=MAX_FORCE_N, description="total force")]
    radius_mm: Annotated[
        float, Strict(), Field(ge=MIN_RADIUS_MM, le=MAX_RADIUS_MM, description="contact disc")
    ] = 3.0
    duration_s: Annotated[float, Strict(), Field(gt=0.0, le=MAX_DURATION_S)] = 1.0

    def check_on(self, layout: MatrixLayout, pitch_mm: float) -> None:
        """Raise ValueError unless the press's centre lies on the pad of ``layout``."""
        width, length = layout.cols * pitch_mm, layout.rows * pitch_mm
        if not 0.0 <= self.x_mm <= width:
            raise ValueError(f"x_mm = {self.x_mm:g} is off pad {self.pad} (0…{width:g} mm across)")
        if not 0.0 <= self.y_mm <= length:
            raise ValueError(f"y_mm = {self.y_mm:g} is off pad {self.pad} (0…{length:g} mm along)")

    def describe(self) -> str:
        return (f"pad {self.pad} at ({self.x_mm:g}, {self.y_mm:g}) mm, {self.force_n:g} N over "
                f"r = {self.radius_mm:g} mm for {self.duration_s:g} s")  # fmt: skip


def press_cells(
    press: Press, layout: MatrixLayout, pitch_mm: float, spread_mm: float
) -> np.ndarray:
    """(rows, cols) mean pressure (N/mm²) on each cell of the pad under ``press``.

    The disc is sampled on a grid (≤ 0.2 mm, at least 8 samples across its radius) carrying the
    whole force; each sample's load is spread by the rubber (Gaussian σ = ``spread_mm``) and
    shared out to rows and columns as :class:`~sdh2svc.sim.sensor.PadRaster` does along a pad.
    Load spread beyond the pad's edges is lost, as on the real pad; absent cells of the mask
    are left to the sensor (it reads them 0)."""
    from scipy.special import ndtr  # (here, not at the top: see sdh2svc.sim.sensor.PadRaster)

    r = press.radius_mm
    step = min(0.2, r / 8)
    n = max(1, math.ceil(2 * r / step))
    offsets = (np.arange(n) + 0.5) * step - n * step / 2
    disc = offsets[:, None] ** 2 + offsets[None, :] ** 2 <= r * r  # [along, across]
    p = press.force_n / (int(disc.sum()) * step * step)  # exactly the force, whatever the grid

    def share(samples: np.ndarray, cells: int) -> np.ndarray:
        edges = np.arange(cells + 1) * pitch_mm
        cdf = ndtr((edges[:, None] - samples[None, :]) / spread_mm)
        out: np.ndarray = (cdf[1:] - cdf[:-1]) * step / pitch_mm  # [cell, sample]
        return out

    rows = share(press.y_mm + offsets, layout.rows)
    cols = share(press.x_mm + offsets, layout.cols)
    cells: np.ndarray = rows @ (disc * p) @ cols.T
    return cells


@dataclass(frozen=True, slots=True)
class _Active:
    start: float
    end: float
    first: int  # the pad's first cell in a frame (wire order)
    cells: np.ndarray  # flat, the pad's cells


class Presses:
    """The presses scheduled on the world's clock; their summed pressure at any ``now``."""

    def __init__(self, layouts: Sequence[MatrixLayout], pitch_mm: float, spread_mm: float) -> None:
        self.layouts = tuple(layouts)
        self.pitch_mm, self.spread_mm = pitch_mm, spread_mm
        sizes = [lay.rows * lay.cols for lay in self.layouts]
        self.offsets = [0, *np.cumsum(sizes).tolist()]
        self._presses: list[_Active] = []

    def add(self, press: Press, start: float) -> None:
        """Press from ``start`` (s, the world's clock) for the press's duration; ValueError if
        its centre is off the pad."""
        layout = self.layouts[press.pad]
        press.check_on(layout, self.pitch_mm)
        cells = press_cells(press, layout, self.pitch_mm, self.spread_mm).ravel()
        end = start + press.duration_s
        self._presses.append(_Active(start, end, self.offsets[press.pad], cells))

    def release(self, now: float) -> int:
        """Lift every press that has started by ``now`` (those scheduled later stay); returns
        how many were lifted."""
        before = len(self._presses)
        self._presses = [p for p in self._presses if p.start > now]
        return before - len(self._presses)

    def pressure(self, now: float) -> np.ndarray | None:
        """Flat pressure (N/mm², wire order) of the presses on at ``now``, None if none is; ended
        ones are forgotten (``now`` only grows)."""
        if not self._presses:  # the usual case, at every frame
            return None
        self._presses = [p for p in self._presses if p.end > now]
        out: np.ndarray | None = None
        for p in self._presses:
            if p.start <= now:
                if out is None:
                    out = np.zeros(self.offsets[-1])
                out[p.first : p.first + p.cells.size] += p.cells
        return out


# --- the command line's form: "pad=3,x=10,y=12,force=2,radius=4,duration=1.5,at=5" --------------

_KEYS = {"pad": "pad", "x": "x_mm", "y": "y_mm", "force": "force_n", "radius": "radius_mm",
         "duration": "duration_s"}  # fmt: skip
SPEC_HELP = "pad=0…5,x=MM,y=MM,force=N[,radius=MM (3)][,duration=S (1)][,at=S (0)]"


def parse_spec(spec: str) -> tuple[Press, float]:
    """A press and its delay ``at`` (s) from ``key=value`` pairs separated by commas or spaces
    (keys: pad, x, y, force, radius, duration, at). ValueError with one sentence if not."""
    values: dict[str, float] = {}
    at = 0.0
    seen: set[str] = set()
    for item in (s for s in re.split(r"[,\s]+", spec.strip()) if s):
        key, sep, text = item.partition("=")
        key = key.strip().lower()
        if not sep or key not in (*_KEYS, "at"):
            raise ValueError(f"{item!r}: expected key=value with a key of "
                             f"{', '.join((*_KEYS, 'at'))} ({SPEC_HELP})")  # fmt: skip
        if key in seen:  # which one was meant? (the last used to win without a word)
            raise ValueError(f"{key} given twice")
        seen.add(key)
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"{key}={text!r}: not a number") from None
        if not math.isfinite(value):
            raise ValueError(f"{key}={text!r}: not a finite number")
        if key == "at":
            if value < 0:
                raise ValueError(f"at={text}: a delay is ≥ 0 s")
            at = value
        else:
            values[_KEYS[key]] = value
    missing = [k for k, field in _KEYS.items() if field in ("pad", "x_mm", "y_mm", "force_n")
               and field not in values]  # fmt: skip
    if missing:
        raise ValueError(f"missing {', '.join(missing)} ({SPEC_HELP})")
    pad = values["pad"]
    if pad != int(pad):
        raise ValueError(f"pad={pad:g}: a matrix number 0…5")
    try:
        press = Press.model_validate({**values, "pad": int(pad)})
    except ValidationError as e:
        short = {v: k for k, v in _KEYS.items()}
        lines = [f"{short.get(str(err['loc'][0]), err['loc'][0])}: {err['msg']}"
                 for err in e.errors()]  # fmt: skip
        raise ValueError("; ".join(lines)) from None
    return press, at
