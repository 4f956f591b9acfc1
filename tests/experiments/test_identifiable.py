"""experiments.recognition.identifiable: which first strokes a box (or a circle) could have
shown as well, on hand-built touches."""

from __future__ import annotations

import math

import numpy as np

from experiments.recognition.identifiable import Touch, bound, box_like, circle_like, misses
from sdh2svc.sim.objects import Ellipse, Polygon


def _on_edge(core: np.ndarray, i: int, t: float) -> tuple[float, float]:
    u, v = core[i], core[(i + 1) % len(core)]
    p = u + t * (v - u)
    return float(p[0]), float(p[1])


def _edge_dir(core: np.ndarray, i: int) -> float:
    u, v = core[i], core[(i + 1) % len(core)]
    return math.atan2(v[1] - u[1], v[0] - u[0]) % math.pi


def _faces(poly: Polygon, edges: tuple[int, int]) -> list[list[Touch]]:
    """Both pads on the middle of a face each, sliding a little along it."""
    core, _ = poly.outline()
    return [[Touch(pad, _on_edge(core, i, t), _edge_dir(core, i))
             for pad, i in zip(("distal1", "distal2"), edges, strict=True)]
            for t in np.linspace(0.4, 0.6, 10)]  # fmt: skip


def test_a_rectangle_like_polygon_is_box_like_and_a_triangle_is_not() -> None:
    quad = Polygon(
        vertices_mm=[(-30.0, -10.0), (30.0, -10.0), (30.0, 10.0), (-30.0, 10.0)], depth_mm=20.0
    )
    assert box_like(quad, _faces(quad, (0, 2)))  # two antiparallel faces: a box shows that
    tri = Polygon(vertices_mm=[(-30.0, -17.0), (30.0, -17.0), (0.0, 35.0)], depth_mm=20.0)
    assert not box_like(tri, _faces(tri, (0, 1)))  # faces 60° apart


def test_a_corner_pivoting_across_parallel_is_not_box_like() -> None:
    """A regular pentagon held face to corner: the corner opposite the face turns the pad both
    ways of parallel, which no box's corner does; pivoting one way only, a box could."""
    ang = np.radians(90.0 + 72.0 * np.arange(5))
    penta = Polygon(vertices_mm=[(30 * math.cos(a), 30 * math.sin(a)) for a in ang], depth_mm=20.0)
    core, _ = penta.outline()
    top = int(np.argmax(core[:, 1]))
    base = int(np.argmin([(core[i][1] + core[(i + 1) % 5][1]) for i in range(5)]))
    face_dir = _edge_dir(core, base)

    def stroke(sweep_deg: tuple[float, float]) -> list[list[Touch]]:
        turn = np.radians(np.linspace(*sweep_deg, 20))
        return [[Touch("distal1", _on_edge(core, base, 0.5), face_dir),
                 Touch("distal2", (float(core[top][0]), float(core[top][1])),
                       (face_dir + d) % math.pi)] for d in turn]  # fmt: skip

    assert not box_like(penta, stroke((-15.0, 15.0)))
    assert box_like(penta, stroke((3.0, 25.0)))


def test_a_near_round_ellipse_is_circle_like_only_within_the_tolerance() -> None:
    ell = Ellipse(axis_a_mm=62.0, axis_b_mm=60.0, depth_mm=20.0)
    t = np.radians(np.linspace(-10.0, 10.0, 15))
    pts = [(31.0 * math.cos(a), 30.0 * math.sin(a)) for a in t]
    stroke = [[Touch("distal1", p, 0.0), Touch("distal2", (-p[0], -p[1]), 0.0)] for p in pts]
    assert circle_like(ell, stroke, tol_radius=0.2)
    assert not circle_like(ell, stroke, tol_radius=0.02)  # ρ = b²/a at the tips: 6 % short
    assert not circle_like(
        Ellipse(axis_a_mm=90.0, axis_b_mm=60.0, depth_mm=20.0), stroke, tol_radius=0.2
    )


def test_the_bound_counts_what_cannot_be_split() -> None:
    rows = [{"class": "box", "looks_like": None}] * 6 + [
        {"class": "polygon", "looks_like": "box"},
        {"class": "polygon", "looks_like": None},
        {"class": "ellipse", "looks_like": "circle"},
        {"class": "circle", "looks_like": None},
    ]
    got = bound(rows)
    assert got["runs"] == 10 and got["looks_like_another"] == {"polygon": 1, "ellipse": 1}
    assert got["bound"] == 0.8


def test_misses_are_sorted_into_look_alikes_and_the_rest() -> None:
    rows = [
        {"id": "p1", "class": "polygon", "looks_like": "box"},
        {"id": "p2", "class": "polygon", "looks_like": "box"},
        {"id": "p3", "class": "polygon", "looks_like": "box"},
        {"id": "e1", "class": "ellipse", "looks_like": None},
        {"id": "b1", "class": "box", "looks_like": None},
    ]
    evaluated = {"cases": [
        {"id": "p1", "class": "polygon", "class_first_stroke": "box"},  # inherent
        {"id": "p2", "class": "polygon", "class_first_stroke": "stick"},  # looks like a box
        {"id": "p3", "class": "polygon", "class_first_stroke": "polygon"},  # a look-alike, right
        {"id": "e1", "class": "ellipse", "class_first_stroke": "circle"},
        {"id": "b1", "class": "box", "class_first_stroke": None},  # no first stroke
        {"id": "x9", "class": "box", "class_first_stroke": "stick"},  # not judged here
    ]}  # fmt: skip
    got = misses(rows, evaluated)
    assert [m["id"] for m in got["misses"]] == ["p1", "p2", "e1"]
    assert got["inherent"] == 1 and got["look_alikes_read_right"] == 1
    assert got["other"] == {"polygon -> stick": 1, "ellipse -> circle": 1}
