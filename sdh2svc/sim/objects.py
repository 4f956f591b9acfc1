"""Objects for the simulated hand, defined by data (presets, TOML or JSON).

Every shape is a convex polygon in its own frame, grown by a rounding radius (a Minkowski sum
with a disk): a ``circle`` is a point grown by its radius, a ``stick`` a segment grown by half its
diameter, a ``box`` a rectangle with optionally rounded corners, an ``ellipse`` a fine polygon,
a ``polygon`` itself. One signed-distance function then serves all of them (which points are
inside), and one ray exit (how deep a point lies along a direction: the pads' compression along
their normals, see ``sdh2svc/sim/physics.py``).
"""

from __future__ import annotations

import json
import math
import tomllib
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import Field, Strict, TypeAdapter, model_validator

from sdh2svc.model.base import Finite

# What the two fingertips could hold. Their proximal joints are 66 mm apart (hand.base_offset_mm)
# and each finger is 86.5 + 68 mm long, with a 44 mm sensing pad near its tip: an object much
# wider than ≈ 150 mm across cannot be reached by both pads at once (the presets span 22 mm, the
# rubber's thickness, to 119.4 mm, stick119). From the default pre-shape the open pads stand
# 122.5 mm apart, so wider objects are never gripped there (campaign/generate.py keeps contact
# widths ≤ 120 mm); the bound here is the geometry's. Below ≈ 5 mm across, the pads (20.4 mm
# wide, 2 mm of rubber each) would meet before they press the object. Any other dimension (a stick's
# diameter, a box's thinner side, the depth across the pad) may be as small as 1 mm: the
# simulation samples the pads' surface every 0.25 mm, so a thinner object would fall between
# its samples. Strict: a number, never true/false or a string; finite.
MIN_SIZE_MM, MAX_SIZE_MM = 5.0, 150.0  # the object's largest extent: the width between the pads
MIN_DIM_MM = 1.0  # any other dimension
MAX_VERTICES = 64  # of a polygon: a fine enough outline, and a bounded cost per physics step
Mm = Annotated[float, Strict(), Field(ge=MIN_DIM_MM, le=MAX_SIZE_MM, allow_inf_nan=False)]
SizeMm = Annotated[float, Strict(), Field(ge=MIN_SIZE_MM, le=MAX_SIZE_MM, allow_inf_nan=False)]
Coord = Annotated[float, Strict(), Field(ge=-MAX_SIZE_MM, le=MAX_SIZE_MM, allow_inf_nan=False)]
ELLIPSE_VERTICES = 96
_MIN_TURN_RAD = 1e-3  # a polygon's vertex that turns less is collinear with its neighbours


# Constants as 0-d arrays: a numpy call takes one at half the overhead of a Python float (the
# same float64 operation, so the same values); the rows' operations below run per evaluation.
_ZERO, _ONE, _TINY = np.array(0.0), np.array(1.0), np.array(1e-300)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)  # cached and shared: nobody may change it in place
    return a


class Material(Finite):
    """Mass, friction with the pads and contact stiffness of an object."""

    mass_g: Annotated[float, Strict(), Field(gt=0.0, le=5000.0)] = 20.0
    friction: Annotated[float, Strict(), Field(gt=0.0, le=3.0)] = 0.6
    stiffness_n_per_mm3: Annotated[float, Strict(), Field(gt=0.0, le=100.0)] = Field(
        default=1.0, description="foundation stiffness: pressure per mm of local compression"
    )


class _ShapeBase(Finite):
    name: str = Field("", max_length=64)
    depth_mm: Mm = Field(description="extent across the pad (how many texel columns it presses)")
    material: Material = Material()

    def outline(self) -> tuple[np.ndarray, float]:
        """The convex core polygon (object frame) and the rounding radius; computed once."""
        return self._outline

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:  # pragma: no cover - overridden
        raise TypeError("abstract")

    def _check_size(self, size: float, what: str) -> None:
        if not MIN_SIZE_MM <= size <= MAX_SIZE_MM:
            raise ValueError(f"{what} is {size:.6g} mm: the fingertips hold objects "
                             f"{MIN_SIZE_MM:g} … {MAX_SIZE_MM:g} mm across")  # fmt: skip


class Stick(_ShapeBase):
    kind: Literal["stick"] = "stick"
    length_mm: SizeMm
    diameter_mm: Mm = 2.0

    @model_validator(mode="after")
    def _thinner_than_long(self) -> Stick:
        if self.diameter_mm > self.length_mm:
            raise ValueError("diameter_mm must be at most length_mm")
        return self

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:
        half = (self.length_mm - self.diameter_mm) / 2
        if half <= 0.0:  # as thick as long: a disk (a zero-length segment has no direction)
            return _frozen(np.zeros((1, 2))), self.diameter_mm / 2
        return _frozen(np.array([[-half, 0.0], [half, 0.0]])), self.diameter_mm / 2

    @property
    def size_mm(self) -> float:
        return self.length_mm


class Box(_ShapeBase):
    kind: Literal["box"] = "box"
    width_mm: Mm
    height_mm: Mm
    corner_radius_mm: Annotated[float, Strict(), Field(ge=0.0, le=MAX_SIZE_MM / 2)] = 0.0

    @model_validator(mode="after")
    def _corner_fits(self) -> Box:
        if 2 * self.corner_radius_mm > min(self.width_mm, self.height_mm):
            raise ValueError("corner_radius_mm must be at most half the smaller side")
        self._check_size(max(self.width_mm, self.height_mm), "the larger side")
        return self

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:
        r = self.corner_radius_mm
        w, h = self.width_mm / 2 - r, self.height_mm / 2 - r
        return _frozen(np.array([[-w, -h], [w, -h], [w, h], [-w, h]])), r

    @property
    def size_mm(self) -> float:
        return self.width_mm


class Ellipse(_ShapeBase):
    kind: Literal["ellipse"] = "ellipse"
    axis_a_mm: Mm = Field(description="full length along the object's x axis")
    axis_b_mm: Mm = Field(description="full length along the object's y axis")

    @model_validator(mode="after")
    def _big_enough(self) -> Ellipse:
        self._check_size(max(self.axis_a_mm, self.axis_b_mm), "the longer axis")
        return self

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:
        t = np.linspace(0.0, 2 * math.pi, ELLIPSE_VERTICES, endpoint=False)
        # vertices on a slightly larger ellipse so the polygon's area-mean radius matches
        k = 1.0 / math.cos(math.pi / ELLIPSE_VERTICES)
        a, b = self.axis_a_mm / 2, self.axis_b_mm / 2
        v = np.stack([a * np.cos(t), b * np.sin(t)], axis=1) * (1 + (k - 1) / 2)
        return _frozen(v), 0.0

    @property
    def size_mm(self) -> float:
        return self.axis_a_mm


class Circle(_ShapeBase):
    kind: Literal["circle"] = "circle"
    diameter_mm: SizeMm

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:
        return _frozen(np.zeros((1, 2))), self.diameter_mm / 2

    @property
    def size_mm(self) -> float:
        return self.diameter_mm


class Polygon(_ShapeBase):
    kind: Literal["polygon"] = "polygon"
    vertices_mm: tuple[tuple[Coord, Coord], ...] = Field(
        min_length=3, max_length=MAX_VERTICES,
        description=f"3 … {MAX_VERTICES} corners of a convex polygon, in order (either way "
        f"round), each coordinate within ±{MAX_SIZE_MM:g} mm",
    )  # fmt: skip

    @model_validator(mode="after")
    def _convex_simple(self) -> Polygon:
        """Convex and simple: every corner turns the same way, by a clear angle, and the turns
        add up to one full turn (a star's add up to two or more: its edges cross)."""
        v = np.asarray(self.vertices_mm, dtype=float)
        e = np.roll(v, -1, axis=0) - v
        if np.any(np.hypot(e[:, 0], e[:, 1]) < 1e-3):
            raise ValueError("polygon vertices must differ (a repeated corner)")
        nxt = np.roll(e, -1, axis=0)
        turn = np.arctan2(e[:, 0] * nxt[:, 1] - e[:, 1] * nxt[:, 0], np.sum(e * nxt, axis=1))
        turn = turn * (1.0 if turn.sum() >= 0 else -1.0)
        if np.any(turn < _MIN_TURN_RAD):
            raise ValueError("polygon vertices must form a convex polygon: every corner turning "
                             "the same way, none in line with its neighbours")  # fmt: skip
        if abs(turn.sum() - 2 * math.pi) > 1e-6:
            raise ValueError("polygon edges must not cross (the outline must go round once)")
        self._check_size(self.size_mm, "its largest extent")
        if self._width_mm < MIN_DIM_MM:
            raise ValueError(f"the polygon is {self._width_mm:.3g} mm thin: at least "
                             f"{MIN_DIM_MM:g} mm")  # fmt: skip
        return self

    @cached_property
    def _outline(self) -> tuple[np.ndarray, float]:
        v = np.asarray(self.vertices_mm, dtype=float)
        v = v - v.mean(axis=0)
        nxt = np.roll(v, -1, axis=0)
        if float(np.sum(v[:, 0] * nxt[:, 1] - nxt[:, 0] * v[:, 1])) < 0:
            v = v[::-1]  # counter-clockwise, so edge normals point outwards
        return _frozen(np.ascontiguousarray(v)), 0.0

    @cached_property
    def size_mm(self) -> float:
        """The largest distance between two corners (once: N ≤ 64 corners, N² pairs)."""
        v = np.asarray(self.vertices_mm)
        return float(np.max(np.linalg.norm(v[:, None] - v[None], axis=2)))

    @cached_property
    def _width_mm(self) -> float:
        """The smallest width (convex: the least, over edges, of the farthest corner's distance
        from that edge's line)."""
        v = np.asarray(self.vertices_mm, dtype=float)
        e = np.roll(v, -1, axis=0) - v
        n = np.stack([e[:, 1], -e[:, 0]], axis=1) / np.hypot(e[:, 0], e[:, 1])[:, None]
        dist = np.abs((v[None, :, :] - v[:, None, :]) @ n[..., None])[..., 0]  # (edge, corner)
        return float(np.min(np.max(dist, axis=1)))


# Every shape there is, written once: a new shape is its class above and its name here.
Shape = Stick | Box | Ellipse | Circle | Polygon
# a shape as data: validated by its ``kind``
ObjectSpec = Annotated[Shape, Field(discriminator="kind")]
_ADAPTER: TypeAdapter[Any] = TypeAdapter(ObjectSpec)

PLASTIC = Material(mass_g=20.0, friction=0.6, stiffness_n_per_mm3=2.0)
RUBBER = Material(mass_g=18.0, friction=0.9, stiffness_n_per_mm3=0.5)
FOAM = Material(mass_g=15.0, friction=0.8, stiffness_n_per_mm3=0.01)
SHELL = Material(mass_g=58.0, friction=0.5, stiffness_n_per_mm3=3.0)

PRESETS: dict[str, Shape] = {
    # thesis ch. 4 objects
    "rubber": Box(name="rubber", width_mm=60.5, height_mm=22.0, corner_radius_mm=1.0,
                  depth_mm=11.0, material=RUBBER),
    "egg": Ellipse(name="egg", axis_a_mm=53.0, axis_b_mm=39.0, depth_mm=39.0, material=SHELL),
    "cylinder": Circle(name="cylinder", diameter_mm=68.0, depth_mm=116.0, material=FOAM),
    # thesis §3.4 simulated sticks
    "stick62": Stick(name="stick62", length_mm=62.038, depth_mm=10.0, material=PLASTIC),
    "stick74": Stick(name="stick74", length_mm=73.8, depth_mm=10.0, material=PLASTIC),
    "stick98": Stick(name="stick98", length_mm=98.46, depth_mm=10.0, material=PLASTIC),
    "stick119": Stick(name="stick119", length_mm=119.405, depth_mm=10.0, material=PLASTIC),
}  # fmt: skip


class Outline:
    """A shape's convex core polygon (object frame) and rounding radius, with its SDF."""

    def __init__(self, spec: Shape) -> None:
        self.spec = spec
        self.vertices, self.radius = spec.outline()
        self.edges = np.roll(self.vertices, -1, axis=0) - self.vertices
        lengths = np.linalg.norm(self.edges, axis=1)
        self._closed = len(self.vertices) >= 3
        self._edge0_sq = float(self.edges[0] @ self.edges[0])  # a stick's squared length
        with np.errstate(invalid="ignore", divide="ignore"):
            normals = np.stack([self.edges[:, 1], -self.edges[:, 0]], axis=1)
            self.normals = normals / lengths[:, None]
        self.offsets = np.einsum("ij,ij->i", self.normals, self.vertices)
        self.half_extent = np.max(np.abs(self.vertices), axis=0) + self.radius
        self.bound_radius = float(np.max(np.linalg.norm(self.vertices, axis=1))) + self.radius
        # a box's core is axis-aligned: its distance has a closed form (see sdf)
        self._box_core: np.ndarray | None = None
        if isinstance(spec, Box):
            self._box_core = np.max(np.abs(self.vertices), axis=0)
            # its half sides as 0-d arrays (see _ZERO)
            self._box_half = (np.array(self._box_core[0]), np.array(self._box_core[1]))
        if self._box_core is not None:
            self._box_far = (self._box_core + self.radius)[:, None]  # its sides moved out by r
        self._ab: tuple[float, float] | None = None
        # a stick's core: its centre, direction and half length
        self._segment: tuple[tuple[float, float], tuple[float, float], float] | None = None
        self._centred = not self.vertices.any()  # a disk about the origin
        if len(self.vertices) == 2:
            half = float(lengths[0]) / 2
            mid, unit = self.vertices.mean(axis=0), self.edges[0] / lengths[0]
            self._segment = ((float(mid[0]), float(mid[1])), (float(unit[0]), float(unit[1])), half)
        # a stick's core along x (as Stick's is): its projection rel·e is the one product rel_x·e_x
        self._axial = len(self.vertices) == 2 and float(self.edges[0, 1]) == 0.0
        # the rows' constants as 0-d arrays (see _ZERO): the first vertex, the first edge's x,
        # its squared length, the radius and its square, a stick's half length
        self._v0 = (np.array(self.vertices[0, 0]), np.array(self.vertices[0, 1]))
        self._ex, self._e0_sq = np.array(self.edges[0, 0]), np.array(self._edge0_sq)
        self._r, self._rr = np.array(self.radius), np.array(self.radius * self.radius)
        self._half = np.array(self._segment[2] if self._segment else 0.0)
        if isinstance(spec, Ellipse):
            self._ab = (spec.axis_a_mm / 2, spec.axis_b_mm / 2)
            ia, ib = 2.0 / spec.axis_a_mm, 2.0 / spec.axis_b_mm
            self._inv_ab = np.array([[ia], [ib], [ia], [ib]])  # scales (px, py, dx, dy)
            self.half_extent = np.array(self._ab)
            self.bound_radius = max(self._ab)

    @cached_property
    def perimeter_points(self) -> np.ndarray:
        """180 boundary points (object frame), by bisection along rays from the centre."""
        t = np.linspace(0, 2 * math.pi, 180, endpoint=False)
        u = np.stack([np.cos(t), np.sin(t)], axis=1)
        lo, hi = np.zeros(len(t)), np.full(len(t), self.bound_radius + 1.0)
        for _ in range(40):  # the shape is convex and contains its centre: one crossing per ray
            mid = (lo + hi) / 2
            inside = self.sdf(u * mid[:, None]) < 0
            lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
        return u * lo[:, None]

    def sdf(self, p: np.ndarray) -> np.ndarray:
        """Signed distance (mm) of object-frame points p (N, 2) to the outline; < 0 inside.

        Exact for every shape but the ellipse, where it is the first-order distance
        (g − 1)/|∇g| of g = |(x/a, y/b)|: exact on the boundary, within a few µm for the
        sub-millimetre depths that contacts reach.
        """
        if self._ab is not None:  # an ellipse
            a, b = self._ab
            qx, qy = p[:, 0] / a, p[:, 1] / b
            g = np.sqrt(qx * qx + qy * qy)
            grad = np.sqrt((qx / a) ** 2 + (qy / b) ** 2) / np.maximum(g, 1e-12)
            return (g - 1.0) / np.maximum(grad, 1e-12)
        if self._box_core is not None:
            return self._box_sdf_rows(p[:, 0], p[:, 1])
        v, e = self.vertices, self.edges
        n = len(v)
        if n == 1 or self._axial:
            return self.sdf_rows(p.T)
        if not self._closed:  # a segment (stick)
            rel = p - v[0]
            t = _clip01(rel @ e[0] / self._edge0_sq)
            return _row_norms(rel - t[:, None] * e[0]) - self.radius
        side = p @ self.normals.T - self.offsets  # (N, E) signed distance to each edge's line
        outside = np.maximum.reduce(side, axis=1)
        d = outside.copy()
        out = outside > 0.0
        if self.radius > 0.0 and np.count_nonzero(out):  # exact distance to the core outside it
            rel = p[out][:, None, :] - v[None]
            t = np.clip(np.sum(rel * e[None], axis=2) / np.sum(e * e, axis=1)[None], 0.0, 1.0)
            d[out] = np.min(np.linalg.norm(rel - t[..., None] * e[None], axis=2), axis=1)
        return np.asarray(d - self.radius)

    def sdf_rows(self, pq: np.ndarray) -> np.ndarray:
        """:meth:`sdf` of points given as the two rows (x, y) of pq (2, N). A disk's and a stick
        along x are worked out on the rows (the same operations as sdf's, on contiguous 1-D
        arrays: far cheaper than on (N, 2) columns); the other shapes' by :meth:`sdf`."""
        v = self.vertices
        if self._box_core is not None:
            return self._box_sdf_rows(pq[0], pq[1])
        if self._ab is not None:
            return self.sdf(pq.T)
        if len(v) == 1:
            px, py = pq[0] - self._v0[0], pq[1] - self._v0[1]
            return np.asarray(np.sqrt(px * px + py * py) - self._r)
        if not self._axial:
            return self.sdf(pq.T)
        # the segment from v0 along (e_x, 0): the nearest point's parameter, clipped to [0, 1]
        rx, ry = pq[0] - self._v0[0], pq[1] - self._v0[1]
        ex = self._ex
        qx = rx - _clip01(rx * ex / self._e0_sq) * ex
        return np.asarray(np.sqrt(qx * qx + ry * ry) - self._r)

    def exit_distance(self, p: np.ndarray, d: np.ndarray) -> np.ndarray:
        """How far each object-frame point p (N, 2) inside the outline goes along its unit
        direction d (N, 2) before it leaves the outline: t ≥ 0 with p + t·d on the boundary.

        The outline is convex, so a ray from inside crosses its boundary once. Closed forms: an
        ellipse is a disk once scaled by its semi-axes, a quadratic in t; a polygon grown by r
        is first left through one of its edges moved out by r (the first half-plane the ray
        leaves), and where that exit lies beyond the ends of its edge it is in a rounded
        corner, on that vertex's circle (a stick: its two sides, then its end caps).
        """
        return self.exit_rows(np.concatenate((p.T, d.T)))

    def exit_rows(self, pd: np.ndarray) -> np.ndarray:
        """:meth:`exit_distance` of points and directions given as the four rows (px, py, dx,
        dy) of pd (4, N). Few points, so few whole-array operations: the coordinates are
        handled as rows (each numpy call on a few dozen values costs more than its work)."""
        if self._ab is not None:  # an ellipse: the unit circle, in coordinates scaled by 1/a, 1/b
            w = pd * self._inv_ab
            return _disk_exit(w[0], w[1], w[2], w[3], _ONE, scaled=True)
        if self._box_core is not None:
            return self._box_exit(pd[:2], pd[2:])
        v, r = self.vertices, self.radius
        if len(v) == 1:  # a disk (about the origin, as every circle's core is)
            if self._centred:
                return _disk_exit(pd[0], pd[1], pd[2], pd[3], self._rr)
            px, py, dx, dy = pd
            return _disk_exit(px - v[0, 0], py - v[0, 1], dx, dy, r * r)
        if not self._closed:
            return self._stick_exit(pd[0], pd[1], pd[2], pd[3])
        return self._polygon_exit(pd[:2].T, pd[2:].T)

    def _polygon_exit(self, p: np.ndarray, d: np.ndarray) -> np.ndarray:
        """:meth:`exit_distance` of a polygon grown by r: the first of its edges' half-planes,
        moved out by r, that the ray leaves; beyond an end of that edge, its vertex's circle."""
        (px, py), (dx, dy) = p.T, d.T
        v, r = self.vertices, self.radius
        dn = d @ self.normals.T
        room = self.offsets + r - p @ self.normals.T
        t_edges = np.divide(room, dn, out=np.full(room.shape, np.inf), where=dn > 0.0)
        if r <= 0.0:
            return np.asarray(t_edges.min(axis=1))
        k = np.argmin(t_edges, axis=1)
        t = t_edges[np.arange(len(k)), k]
        # beyond an end of that edge: the rounded corner, on its vertex's circle
        e = self.edges[k]
        along = ((px + t * dx - v[k, 0]) * e[:, 0] + (py + t * dy - v[k, 1]) * e[:, 1]) / (
            e[:, 0] * e[:, 0] + e[:, 1] * e[:, 1]
        )
        cap = (along < 0.0) | (along > 1.0)
        if np.count_nonzero(cap):
            corner = v[(k[cap] + (along[cap] > 1.0)) % len(v)]
            (wx, wy), (ux, uy) = (p[cap] - corner).T, d[cap].T
            t[cap] = _disk_exit(wx, wy, ux, uy, r * r)
        return np.asarray(t)

    def _box_exit(self, P: np.ndarray, D: np.ndarray) -> np.ndarray:
        """:meth:`exit_distance` of a box, points and directions as rows (x, y): its sides moved
        out by r are the lines |x| = hx + r and |y| = hy + r; an exit beyond the core's half
        side both ways is in a rounded corner."""
        side = (self._box_far - np.sign(D) * P) / np.maximum(np.abs(D), 1e-300)
        t = np.minimum(side[0], side[1])
        if self.radius <= 0.0:
            return np.asarray(t)
        Q = P + t * D
        core = self._box_core
        assert core is not None  # a box's
        beyond = np.abs(Q) > core[:, None]
        cap = beyond[0] & beyond[1]
        if not np.count_nonzero(cap):
            return np.asarray(t)
        wx, wy = P - np.copysign(core[:, None], Q)  # from the corner
        return np.where(cap, _disk_exit(wx, wy, D[0], D[1], self._rr), t)

    def _stick_exit(self, px: np.ndarray, py: np.ndarray, dx: np.ndarray, dy: np.ndarray
                    ) -> np.ndarray:  # fmt: skip
        """:meth:`exit_distance` of a segment grown by r: through a side (w = ±r across it) when
        that is within the segment's length, else through the end cap that way."""
        assert self._segment is not None  # a stick's
        (cx, cy), (ux, uy), half = self._segment
        if (cx, cy, ux, uy) != (0.0, 0.0, 1.0, 0.0):  # into the segment's frame
            px, py = (px - cx) * ux + (py - cy) * uy, (py - cy) * ux - (px - cx) * uy
            dx, dy = dx * ux + dy * uy, dy * ux - dx * uy
        r = self.radius
        t = (self._r - np.sign(dy) * py) / np.maximum(np.abs(dy), _TINY)
        u = px + t * dx
        cap = np.abs(u) > self._half
        if np.count_nonzero(cap):
            t = np.where(cap, _disk_exit(px - np.copysign(half, u), py, dx, dy, r * r), t)
        return np.asarray(t)

    def _box_sdf_rows(self, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """:meth:`sdf` of a box, the points' coordinates as rows: the same distances as the
        polygon's, without projecting every point on every edge (q: how far each coordinate
        lies beyond the core's half side)."""
        hx, hy = self._box_half
        qx, qy = np.abs(px) - hx, np.abs(py) - hy
        outside = np.maximum(qx, qy)  # inside the core: the distance to its nearest side
        if self.radius <= 0.0:
            return np.asarray(outside)  # as for any polygon: exact inside, positive outside
        corner = np.hypot(np.maximum(qx, _ZERO), np.maximum(qy, _ZERO))  # outside: to the core
        return np.asarray(np.where(outside > _ZERO, corner, outside) - self._r)


def _row_norms(q: np.ndarray) -> np.ndarray:
    """``np.linalg.norm(q, axis=1)`` for real (N, 2) rows: the same operations, without its
    Python-level argument handling (this runs at every physics evaluation)."""
    out: np.ndarray = np.sqrt(np.add.reduce(q * q, axis=1))
    return out


def _clip01(x: np.ndarray) -> np.ndarray:
    """``np.clip(x, 0.0, 1.0)`` without np.clip's own overhead (the same values)."""
    out: np.ndarray = np.minimum(np.maximum(x, _ZERO), _ONE)
    return out


def _disk_exit(
    wx: np.ndarray, wy: np.ndarray, dx: np.ndarray, dy: np.ndarray, rr: float | np.ndarray,
    scaled: bool = False,
) -> np.ndarray:  # fmt: skip
    """The larger root t of |w + t·d|² = r², for points w (from the disk's centre) and
    directions d given as their coordinates' rows, and the squared radius ``rr``: where a ray
    leaves the disk, (√(b² − dd·c) − b)/dd with b = w·d, c = w·w − r² and dd = d·d, 1 unless
    ``scaled``. A ray that misses the disk (only by rounding, at a tangent) gets its nearest
    approach."""
    b = wx * dx + wy * dy
    c = wx * wx + wy * wy - rr
    if not scaled:
        return np.asarray(np.sqrt(np.maximum(b * b - c, _ZERO)) - b)
    dd = dx * dx + dy * dy
    return np.asarray((np.sqrt(np.maximum(b * b - dd * c, _ZERO)) - b) / dd)


def load_object(path: str | Path) -> Shape:
    """An object from a TOML or JSON file (``kind = "box"``, ``width_mm = …``, …)."""
    path = Path(path)
    text = path.read_bytes()
    data = json.loads(text) if path.suffix.lower() == ".json" else tomllib.loads(text.decode())
    return parse_object(data)


def parse_object(data: dict[str, Any]) -> Shape:
    """Validate an object definition (raises pydantic.ValidationError with the field's name)."""
    shape: Shape = _ADAPTER.validate_python(data)
    return shape


def get_object(name: str) -> Shape:
    """A preset by name (``rubber``, ``egg``, ``cylinder``, ``stick62`` … ``stick119``)."""
    try:
        return PRESETS[name]
    except KeyError:
        shown = name if len(name) <= 80 else name[:80] + "…"
        raise KeyError(f"unknown object {shown!r} (the presets: {', '.join(PRESETS)})") from None
