"""Recognition while rolling (thesis §5.2): what touches the pads, what the object is, how far
it turned — from the tactile frames and the joint angles only, never the simulation's truth.

Pure and sans-I/O like :mod:`sdh2svc.control.rolling`: a :class:`Recognizer` per run takes
each iteration's :class:`~sdh2svc.model.observe.Observation` and the two distal pads' raw counts
and returns a :class:`Recognition`. The runner calls it after the rolling step; what it returns
goes into the run's :class:`~sdh2svc.control.sample.Sample`, telemetry and recordings.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import Any

import numpy as np

from sdh2svc.model.observe import ModelContext, Observation


class ContactKind(StrEnum):
    """What part of the object touches a pad."""

    FLAT = "flat"  # a flat face lying along the pad
    EDGE = "edge"  # an edge or corner of the object
    CURVED = "curved"  # a curved surface (its local radius is estimated)


class ObjectClass(StrEnum):
    """The object families a lab meets (the campaign generator's, sdh2svc.campaign)."""

    BOX = "box"
    POLYGON = "polygon"
    ELLIPSE = "ellipse"
    CIRCLE = "circle"
    STICK = "stick"


@dataclass(frozen=True, slots=True)
class Recognition:
    """What the rolling revealed so far (lengths in mm, angles in degrees).

    ``size_a``/``size_b`` by class: circle (radius, None); ellipse (semi-axes a ≥ b); box
    (side lengths a ≥ b); stick (length, diameter); polygon (circumradius, mean side length).
    """

    kind1: ContactKind | None = None  # Finger 1's contact (None: no contact)
    kind2: ContactKind | None = None  # Finger 2's contact
    radius1: float | None = None  # local radius of curvature at a curved contact, mm
    radius2: float | None = None
    object_class: ObjectClass | None = None  # None until the evidence decides
    confidence: float = 0.0  # of object_class, 0…1
    size_a: float | None = None
    size_b: float | None = None
    rotation: float = 0.0  # the object's rotation since the grasp (rolling kinematics), deg


class Recognizer:
    """One run's recognition: feed it every rolling iteration, in order."""

    def __init__(self, ctx: ModelContext) -> None:
        self.ctx = ctx
        self.last = Recognition()

    def update(self, obs: Observation, counts1: np.ndarray, counts2: np.ndarray) -> Recognition:
        """This iteration's estimate (the state carried from the iterations before)."""
        raise NotImplementedError

    def summary(self) -> dict[str, Any]:
        """The run's estimate for its summary: class, confidence, sizes, rotation (JSON)."""
        raise NotImplementedError


def outline(
    rec: Recognition, a: tuple[float, float], b: tuple[float, float], n: int = 64
) -> np.ndarray:
    """The reconstructed outline in the hand's y0z0 plane (``n`` × 2, mm), placed so that it
    touches the contacts ``a`` (on Finger 1) and ``b`` (on Finger 2) and turned by
    ``rec.rotation``; empty (0 × 2) while no class is known."""
    raise NotImplementedError
