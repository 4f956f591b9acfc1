"""What really touches each pad: the feature of the simulated object under a true contact.

The simulation's objects are convex polygons grown by a rounding radius
(:mod:`sdh2svc.sim.objects`); an ellipse is a fine polygon standing for the analytic ellipse.
A true contact's point on the object (object frame, the pressure centroid) lies

* on a flat side (the open part of a polygon's edge, a stick's long side): **flat**;
* on a rounding arc or at a sharp corner: **edge** when the arc's radius is below
  :data:`EDGE_RADIUS_MM` (a sharp corner has radius 0), else **curved** with that radius;
* on an ellipse: **curved**, with the analytic ellipse's radius of curvature there, or an
  **edge** where that radius is below :data:`EDGE_RADIUS_MM` (a slender ellipse's tip: one line
  between edge and curve for every shape); on a circle: **curved**, its radius.

A flat side's contact whose centroid lies within :data:`CORNER_MARGIN_MM` of a sharp corner is
the corner's (a face–edge contact presses the corner into the pad: its centroid sits at the
corner, give or take the pad's spread).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from sdh2svc.control.recognition import ContactKind, ObjectClass
from sdh2svc.sim.objects import Box, Circle, Ellipse, Polygon, Shape, Stick, parse_object

EDGE_RADIUS_MM = 4.0  # below about one cell pitch (3.4 mm) a rounding is an edge to the pad
CORNER_MARGIN_MM = 1.5
RIGHT_ANGLE_TOL_DEG = 1.0  # a polygon's four corners this near 90° make it a rectangle


def true_class(family: str, spec: Shape) -> ObjectClass:
    """The right answer by the object's shape, not by the family that generated it: the
    generator's "rounded" family (boxes with rounded corners, up to a stadium) is a box, and so
    is a polygon that is a rectangle (the polygon family's regular 4-gons are squares: the same
    object as a box of equal sides); the thesis's presets by their shape."""
    if family == "rounded" or rectangle_sides(spec) is not None:
        return ObjectClass.BOX
    return {
        Box: ObjectClass.BOX,
        Polygon: ObjectClass.POLYGON,
        Ellipse: ObjectClass.ELLIPSE,
        Circle: ObjectClass.CIRCLE,
        Stick: ObjectClass.STICK,
    }[type(spec)]


def rectangle_sides(spec: Shape) -> tuple[float, float] | None:
    """A four-cornered polygon's sides (longer first) if every corner is a right angle within
    RIGHT_ANGLE_TOL_DEG, else None."""
    if not isinstance(spec, Polygon) or len(spec.vertices_mm) != 4:
        return None
    v = np.asarray(spec.vertices_mm, dtype=float)
    edges = np.roll(v, -1, axis=0) - v
    lengths = np.linalg.norm(edges, axis=1)
    nxt = np.roll(edges, -1, axis=0)
    cos = np.einsum("ij,ij->i", edges, nxt) / (lengths * np.roll(lengths, -1))
    if np.max(np.abs(np.degrees(np.arcsin(np.clip(cos, -1.0, 1.0))))) > RIGHT_ANGLE_TOL_DEG:
        return None
    a, b = (lengths[0] + lengths[2]) / 2, (lengths[1] + lengths[3]) / 2
    return float(max(a, b)), float(min(a, b))


def true_sizes(spec: Shape) -> tuple[float, float | None]:
    """size_a, size_b as :class:`~sdh2svc.control.recognition.Recognition` defines them (a
    rectangular polygon's as a box's)."""
    if (sides := rectangle_sides(spec)) is not None:
        return sides
    if isinstance(spec, Circle):
        return spec.diameter_mm / 2, None
    if isinstance(spec, Ellipse):
        a, b = spec.axis_a_mm / 2, spec.axis_b_mm / 2
        return max(a, b), min(a, b)
    if isinstance(spec, Box):
        return max(spec.width_mm, spec.height_mm), min(spec.width_mm, spec.height_mm)
    if isinstance(spec, Stick):
        return spec.length_mm, spec.diameter_mm
    v = np.asarray(spec.vertices_mm, dtype=float)
    v = v - v.mean(axis=0)
    sides = np.linalg.norm(np.roll(v, -1, axis=0) - v, axis=1)
    return float(np.max(np.linalg.norm(v, axis=1))), float(sides.mean())


def feature(spec: Shape, p: tuple[float, float]) -> tuple[ContactKind, float | None]:
    """The kind of the object's surface at ``p`` (object frame) and its radius if curved."""
    return kind_at(touched_radius(spec, p))


def kind_at(radius: float) -> tuple[ContactKind, float | None]:
    """The kind of a surface of this radius of curvature (:func:`touched_radius`), and the
    radius if curved."""
    if radius == math.inf:
        return ContactKind.FLAT, None
    return (ContactKind.EDGE, None) if radius < EDGE_RADIUS_MM else (ContactKind.CURVED, radius)


def near_the_line(spec: Shape, p: tuple[float, float], within: float = 0.2) -> bool:
    """Whether the surface at ``p`` is rounded within ``within`` (relative) of the
    EDGE_RADIUS_MM line between edge and curve, where a few tenths of a millimetre of radius
    decide the label."""
    return radius_near_the_line(touched_radius(spec, p), within)


def radius_near_the_line(radius: float, within: float = 0.2) -> bool:
    """:func:`near_the_line` for a radius already found."""
    return abs(radius / EDGE_RADIUS_MM - 1.0) <= within


def touched_radius(spec: Shape, p: tuple[float, float]) -> float:
    """The object's radius of curvature at ``p`` (mm): ``math.inf`` on a flat side, the
    rounding's radius on a polygon's rounded corner or a stick's end (0 at a sharp corner, and
    on a flat side within CORNER_MARGIN_MM of a corner rounded below EDGE_RADIUS_MM), the
    analytic radius on an ellipse or a circle."""
    if isinstance(spec, Circle):
        return spec.diameter_mm / 2
    if isinstance(spec, Ellipse):
        a, b = spec.axis_a_mm / 2, spec.axis_b_mm / 2
        t = math.atan2(p[1] / b, p[0] / a)
        return float((a * a * math.sin(t) ** 2 + b * b * math.cos(t) ** 2) ** 1.5 / (a * b))
    core, r = spec.outline()
    q = np.asarray(p, dtype=float)
    n = len(core)
    best: tuple[float, float, int] = (math.inf, 0.0, 0)  # distance, edge parameter, edge
    segs = [(core[i], core[(i + 1) % n]) for i in range(n if n > 2 else n - 1)]
    for i, (u, v) in enumerate(segs):
        e = v - u
        t = float(np.clip((q - u) @ e / (e @ e), 0.0, 1.0))
        d = float(np.linalg.norm(q - (u + t * e)))
        if d < best[0]:
            best = (d, t, i)
    _, t, i = best
    u, v = segs[i]
    length = float(np.linalg.norm(v - u))
    along = t * length
    margin = CORNER_MARGIN_MM if r < EDGE_RADIUS_MM else 1e-6
    return math.inf if margin < along < length - margin else float(r)


def spec_of(case: dict[str, Any]) -> Shape:
    return parse_object(case["spec"]["object"])
