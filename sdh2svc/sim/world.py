"""The seam between the device emulators and the simulated physical hand.

The emulators implement firmware: the DSACON32m's acquisition modes and settings, the SDH2's
controllers and motion profiles. What the hand physically does lives behind :class:`HandWorld`:
where the joints actually are when the servos pull towards a reference, and what the six pads
feel. Both emulators share one world; the world advances lazily to the ``now`` of each call
(seconds on the emulators' clock, monotonic), so it runs on the wall clock or a virtual one alike.

:class:`ScriptedWorld` is the simple source: joints follow their reference exactly and the pads
show a scripted pattern. The physics simulation implements the same protocol.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import numpy as np

from sdh2svc.model.contact import FULL_SCALE_COUNTS
from sdh2svc.protocol.sdh import NUM_AXES

MAX_COUNT = FULL_SCALE_COUNTS  # a cell's highest reading, as the controller's model has it
FACTORY_SENSITIVITY = 0.5  # protocols.md §1.4.4


class HandWorld(Protocol):
    """What the device emulators ask of the physical hand."""

    @property
    def matrix_shapes(self) -> tuple[tuple[int, int], ...]:
        """(rows, cols) of the six tactile matrices, in wire order (row 0 first, cols fastest)."""
        ...

    def move_joints(
        self, now: float, reference_deg: Sequence[float], powered: Sequence[bool]
    ) -> tuple[float, ...]:
        """Advance to ``now`` with each powered servo pulling towards its reference angle.

        Returns the 7 actual angles (deg). Unpowered axes are limp: they stay where they are
        unless something moves them. A world may defer its own work until a tactile frame (or
        a larger move) needs it, as long as the returned angles are what the hand does."""
        ...

    def tactile_frame(
        self, now: float, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        """Advance to ``now``; raw 12-bit counts of all six matrices, flat uint16 in wire order,
        after the per-matrix sensitivity (0…1) and threshold (counts) of the controller."""
        ...


def apply_sensor_settings(
    raw: np.ndarray,
    shapes: Sequence[tuple[int, int]],
    sensitivity: Sequence[float],
    threshold: Sequence[int],
) -> np.ndarray:
    """Per-matrix gain (sensitivity relative to the factory 0.5), threshold (below → 0) and
    saturation at 4095, on a flat array of counts in wire order. Returns uint16."""
    out = np.empty(raw.shape, dtype=np.uint16)
    start = 0
    for m, (rows, cols) in enumerate(shapes):
        seg = raw[start : start + rows * cols].astype(np.float64) * (
            sensitivity[m] / FACTORY_SENSITIVITY
        )
        seg = np.clip(np.rint(seg), 0, MAX_COUNT)
        seg[seg < threshold[m]] = 0
        out[start : start + rows * cols] = seg
        start += rows * cols
    return out


Pattern = Callable[[float], np.ndarray]


class ScriptedWorld:
    """Joints follow their reference exactly; the pads show ``pattern(now)`` (flat float counts).

    The default pattern presses a small blob on each distal pad that slides slowly along it, so
    a driver sees frames that change over time and contacts that move.
    """

    def __init__(
        self,
        matrix_shapes: Sequence[tuple[int, int]],
        pattern: Pattern | None = None,
        initial_deg: Sequence[float] = (0.0,) * NUM_AXES,
    ) -> None:
        self._shapes = tuple((int(r), int(c)) for r, c in matrix_shapes)
        self._pattern = pattern or sliding_blobs(self._shapes)
        self._angles = tuple(float(a) for a in initial_deg)

    @property
    def matrix_shapes(self) -> tuple[tuple[int, int], ...]:
        return self._shapes

    def move_joints(
        self, now: float, reference_deg: Sequence[float], powered: Sequence[bool]
    ) -> tuple[float, ...]:
        self._angles = tuple(
            float(ref) if on else cur
            for ref, on, cur in zip(reference_deg, powered, self._angles, strict=True)
        )
        return self._angles

    def tactile_frame(
        self, now: float, sensitivity: Sequence[float], threshold: Sequence[int]
    ) -> np.ndarray:
        return apply_sensor_settings(self._pattern(now), self._shapes, sensitivity, threshold)


def sliding_blobs(
    shapes: Sequence[tuple[int, int]], distal: Sequence[int] = (1, 5), period_s: float = 4.0
) -> Pattern:
    """A 2-row blob of ~1500 counts on each of the ``distal`` matrices, sliding tip ↔ base."""
    sizes = [r * c for r, c in shapes]
    offsets = np.cumsum([0, *sizes])

    def pattern(now: float) -> np.ndarray:
        out = np.zeros(offsets[-1], dtype=np.float64)
        for k, m in enumerate(distal):
            rows, cols = shapes[m]
            phase = 2 * math.pi * now / period_s + k * math.pi / 2
            centre = (rows - 2) * (0.5 + 0.5 * math.sin(phase))
            grid = np.zeros((rows, cols))
            for r in range(rows):
                grid[r, 1 : cols - 1] = 1500.0 * max(0.0, 1.0 - abs(r - centre) / 1.5)
            out[offsets[m] : offsets[m + 1]] = grid.ravel()
        return out

    return pattern
