"""Seeded campaign cases, and the named suites (``python -m sdh2svc.campaign.generate``).

A suite is made from its seed alone (``numpy.random.default_rng(seed)``, nothing else random)
and the packaged default configuration (the hand's geometry and pre-shape), so the same seed
always gives the same bytes: ``--write`` regenerates the packaged suite files, ``--check``
verifies that the committed ones are exactly what their seeds produce.

The ranges, and why:

* **Contact width** (the object's width along y0 at its placement, where the fingertips touch):
  15 … 120 mm. The grasp closes from the pre-shape (φ2 = φ4 = −30°, φ3 = φ5 = 30°: the distal
  pads upright and facing), where the pads stand 122.5 mm apart on their flat parts and 127 mm
  apart at z0 = 125 mm (the arcs bend away): a wider object would not fit between the open
  fingers (the fixture places an object only where the fingers leave room). 120 mm leaves a
  little clearance and keeps the presets' largest, stick119 (119.4 mm). Below 15 mm the
  fingertips' pads (20.4 mm wide, on fingers a 66 mm base apart) close almost onto each other.
* **Placement**: the object's centre at z0 = 125 ± 10 mm (sim.object_height_mm). During the grasp
  the distal pads stay upright and the distal joints sit at z0 ≈ 77 … 86 mm, so a contact at
  z0 ≈ 115 … 135 lands on the pad's sensing area (L ≈ 11 … 42 mm of 5.5 … 49.5 mm) for every
  width; each case is also checked (below). Initial angle per family: boxes ±25°, sticks ±20°,
  ellipses ±90°, circles and polygons any.
* **Friction** μ 0.3 … 1.2: the friction angle atan μ on both sides of the controller's α = 22°
  (μ = tan 22° ≈ 0.40). **Stiffness** 0.01 … 3 N/mm³, log-uniform: the foam cylinder (0.01) to
  the egg's shell (3; with the pads' 0.2 N/mm³ in series, anything stiffer is as rigid).
  **Mass** 5 … 250 g, log-uniform (it acts only with sim.physics.gravity set). **Depth** across
  the pad 4 … 120 mm, log-uniform.
* **Sensor** per run: gain × 0.5 … 1.5, creep gain 0.05 … 0.30 (config 0.15), creep rise
  2 … 8 s (config 4 s), noise 1 … 6 counts (config 3); one dead texel on a coupled finger's
  distal pad (matrix 1 or 5) in about one case of four.

Each scalar is drawn by Latin hypercube over the suite (one draw per stratum of 1/n), so even a
20-case suite spans every range; the families take turns. Every case is checked before it is kept
(:func:`check_placement`; else its angle and shape are drawn again, its width, height, material and
sensor kept; after ``MAX_TRIES`` draws its width is narrowed by 2 % and the draws begin again: near
120 mm and low down the open fingers hold a little less): it validates, fits between the open
fingers with ``CLEARANCE_MM`` to spare, and closing each finger as the grasp does (proximal +δ,
distal −δ) touches the object first with its distal pad, on the pad's sensing area at least one row
in from its ends, before ``run.grasp_max_close_deg`` — and both fingertips touch it within
``MAX_TOUCH_LAG_DEG`` of closing of each other. That last one matters: the fixture holds the object
where it is placed and withdraws it if one finger pushes 1 mm into it before the other touches, and
a tilted object's two touching points sit at different heights, where the pads' arcs stand at
different distances. So an asymmetric outline (an irregular or odd-sided polygon) is first turned
to the nearest angle at which its extent along y0 is centred on its centre, and tilts are kept
where the two touches still come together (sticks end up within a few degrees of level). The checks
are geometry only: whether the run then holds and rolls the object is what a campaign measures.
"""

from __future__ import annotations

import argparse
import itertools
import math
import sys
from collections.abc import Callable, Sequence
from functools import lru_cache
from pathlib import Path

import numpy as np

from sdh2svc.campaign.case import (
    FAMILIES,
    GAIN_FACTOR,
    SUITES_DIR,
    Case,
    SensorVariation,
    Suite,
    Texel,
    contact_width_mm,
    extent_along_y0,
    load_suite,
    wrap_deg,
)
from sdh2svc.config import Settings, default_config
from sdh2svc.model.kinematics import HandPose
from sdh2svc.sim.objects import (
    PRESETS,
    Box,
    Circle,
    Ellipse,
    Material,
    Outline,
    Polygon,
    Shape,
    Stick,
)
from sdh2svc.sim.physics import (
    DISTAL1,
    DISTAL2,
    PALM,
    PROXIMAL1,
    PROXIMAL2,
    Surface,
    build_surfaces,
    link_frame_rows,
)

__all__ = [
    "GENERATED",
    "SUITE_SEEDS",
    "build_suite",
    "generate_cases",
    "generated_id",
    "load_suite",
]

GENERATED: tuple[str, ...] = tuple(f for f in FAMILIES if f != "thesis")


def generated_id(prefix: str, family: str, i: int) -> str:
    """The id of a suite's ``i``-th generated case (``prefix``: the suite's name and a dash)."""
    return f"{prefix}{family}-{i:03d}"


# ranges (see the module docstring)
WIDTH_MM = (15.0, 120.0)
HEIGHT_MM = 125.0  # sim.object_height_mm of config/sim.toml
HEIGHT_SPAN_MM = 10.0
FRICTION = (0.3, 1.2)
STIFFNESS = (0.01, 3.0)
MASS_G = (5.0, 250.0)
DEPTH_MM = (4.0, 120.0)
CREEP_GAIN = (0.05, 0.30)
CREEP_RISE_S = (2.0, 8.0)
NOISE_COUNTS = (1.0, 6.0)
DEAD_TEXEL_SHARE = 0.25
ANGLE_DEG = {"box": 25.0, "rounded": 25.0, "stick": 20.0, "ellipse": 90.0, "circle": 180.0,
             "polygon": 180.0}  # fmt: skip
BOX_ASPECT = (1 / 5, 5.0)  # height / width (the side across y0 / the side along it)
ELLIPSE_ASPECT = (1 / 3, 3.0)
STICK_DIAMETER_MM = (1.5, 12.0)
POLYGON_SIDES = (3, 12)  # a polygon's corners (kept when its shape is drawn again)
REGULAR_SHARE = 0.4  # of the polygons: regular ones
KEEP_SIDES_TRIES = 100  # draws with a polygon's corners and regularity before others are drawn

# checks on every case
CLEARANCE_MM = 2.0  # between the object and any surface of the open hand (pre-shape)
EDGE_ROWS = 1.0  # the first touch this many rows inside the distal pad's sensing area
MIN_EDGE_MM = 1.0  # a polygon's shortest side
MIN_TURN_DEG = 3.0  # a polygon's least turn at a corner (none nearly in line)
MAX_OFFSET_MM = 0.05  # extent along y0 centred on the object's centre within this
MAX_TOUCH_LAG_DEG = 0.4  # both fingertips touch it within this much closing of each other
DECIMALS = 3  # every generated number is rounded (mm, g, …): readable, and exact in JSON
WIDTH_DECIMALS = 6  # the true contact width, computed from them
MAX_TRIES = 500
WIDTH_SHRINK = 0.98  # after MAX_TRIES draws that do not fit, the width is made this much smaller
SWEEP_CHUNK = 16  # grasp steps checked per distance evaluation

# the named suites: name → (seed, cases, description)
SUITE_SEEDS: dict[str, tuple[int, int, str]] = {
    "smoke": (20261123, 20, "every family at a glance: small enough for CI"),
    "bench-v1": (1_000_001, 360, "the headline benchmark: every family over every range"),
}
THESIS = ("rubber", "egg", "cylinder", "stick62", "stick74", "stick98", "stick119")


# --- geometry checks ----------------------------------------------------------------------------


@lru_cache(maxsize=1)
def _hand() -> tuple[Settings, tuple[Surface, ...], tuple[float, float]]:
    s = default_config()
    surfaces = build_surfaces(s.hand, s.sim.physics)
    pitch = s.tactile.texel_pitch_mm
    lo = s.hand.pad.pad_base_to_active_mm
    hi = lo + s.hand.pad.sensor_active_length_mm
    return s, surfaces, (lo + EDGE_ROWS * pitch, hi - EDGE_ROWS * pitch)


def _preshape(s: Settings) -> HandPose:
    return s.axes.pose(s.run.preshape_deg)


def _sdf_world(outline: Outline, centre: tuple[float, float], angle: float, pts: np.ndarray
               ) -> np.ndarray:  # fmt: skip
    """Signed distance of frame-0 points (y0, z0) to the placed object."""
    c, s = math.cos(angle), math.sin(angle)
    d = pts - np.asarray(centre)
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)  # Rᵀ·d
    d_mm: np.ndarray = outline.sdf(local)
    return d_mm


def _surface_points(
    surfaces: tuple[Surface, ...], pose: HandPose, s: Settings, j: int
) -> np.ndarray:
    o, ex, ey = link_frame_rows(pose, s.hand)[j]
    loc = surfaces[j].local
    pts: np.ndarray = np.asarray(o) + loc[:, :1] * np.asarray(ex) + loc[:, 1:2] * np.asarray(ey)
    return pts


def check_placement(obj: Shape, height_mm: float, angle_deg: float) -> str | None:
    """Why the object cannot be grasped at this placement (None: it can); see the module
    docstring."""
    s, surfaces, _ = _hand()
    outline = Outline(obj)
    centre = (s.hand.base_offset_mm / 2, height_mm)
    angle = math.radians(angle_deg)
    a, b = extent_along_y0(obj, angle_deg)
    if abs(a + b) / 2 > MAX_OFFSET_MM:
        return f"its extent along y0 is off its centre by {abs(a + b) / 2:.3f} mm"
    pose = _preshape(s)
    for j in (DISTAL1, PROXIMAL1, DISTAL2, PROXIMAL2, PALM):
        d = _sdf_world(outline, centre, angle, _surface_points(surfaces, pose, s, j))
        if float(d.min()) < CLEARANCE_MM:
            return f"it does not fit between the open fingers ({float(d.min()):.2f} mm)"
    touches = []
    for distal, proximal in ((DISTAL1, PROXIMAL1), (DISTAL2, PROXIMAL2)):
        got = _first_touch(outline, centre, angle, distal, proximal)
        if isinstance(got, str):
            return got
        touches.append(got)
    lag = abs(touches[0] - touches[1])
    if lag > math.radians(MAX_TOUCH_LAG_DEG):
        return f"one fingertip touches it {math.degrees(lag):.2f}° of closing before the other"
    return None


def _first_touch(outline: Outline, centre: tuple[float, float], angle: float, distal: int,
                 proximal: int) -> float | str:  # fmt: skip
    """How far (rad) the finger with these surfaces closes from the pre-shape, as the grasp
    closes it (proximal +δ, distal −δ), before it touches the placed object; or why that touch
    is no grasp."""
    s, surfaces, (lo, hi) = _hand()
    pose = _preshape(s)

    def depths(d: float) -> tuple[np.ndarray, float]:
        p = HandPose(pose.phi2 + d, pose.phi3 - d, pose.phi4 + d, pose.phi5 - d)
        dd = _sdf_world(outline, centre, angle, _surface_points(surfaces, p, s, distal))
        dp = _sdf_world(outline, centre, angle, _surface_points(surfaces, p, s, proximal))
        return dd, float(dp.min())

    limit = math.radians(s.run.grasp_max_close_deg) - pose.phi2
    step = math.radians(0.25)
    n_d, n_p = len(surfaces[distal].s), len(surfaces[proximal].s)
    closing = np.arange(1, int(limit / step) + 1) * step
    for first in range(0, len(closing), SWEEP_CHUNK):  # a chunk of steps per evaluation
        chunk = closing[first : first + SWEEP_CHUNK]
        pts = []
        for d in chunk:
            p = HandPose(pose.phi2 + d, pose.phi3 - d, pose.phi4 + d, pose.phi5 - d)
            pts += [_surface_points(surfaces, p, s, distal),
                    _surface_points(surfaces, p, s, proximal)]  # fmt: skip
        sweep = _sdf_world(outline, centre, angle, np.concatenate(pts)).reshape(len(chunk), -1)
        hit = np.nonzero(sweep.min(axis=1) < 0.0)[0]
        if len(hit):
            break
    else:
        return "a finger closes past grasp_max_close_deg without touching it"
    k = first + int(hit[0]) + 1
    dd, dp = sweep[int(hit[0]), :n_d], float(sweep[int(hit[0]), n_d : n_d + n_p].min())
    a, b = (k - 1) * step, k * step  # untouched at a, touching at b
    for _ in range(16):
        mid = (a + b) / 2
        dd_mid, dp_mid = depths(mid)
        if min(float(dd_mid.min()), dp_mid) < 0.0:
            b, dd, dp = mid, dd_mid, dp_mid
        else:
            a = mid
    if dp <= float(dd.min()):
        return "a proximal pad touches it first"
    # the first touch: the samples within 0.1 mm of the deepest
    touch = surfaces[distal].s[dd < float(dd.min()) + 0.1]
    where = float(touch.mean())
    if not lo <= where <= hi:
        return f"a distal pad touches it at L = {where:.1f} mm, off the sensing area"
    return b


# --- shapes -------------------------------------------------------------------------------------


def _r(x: float) -> float:
    return round(float(x), DECIMALS)


def _true_width(obj: Shape, angle_deg: float) -> float:
    """:func:`contact_width_mm` to a nanometre: the suite's text then never depends on the last
    bit of the platform's sine and cosine."""
    return round(contact_width_mm(obj, angle_deg), WIDTH_DECIMALS)


def _log_uniform(u: float, lo: float, hi: float) -> float:
    return math.exp(math.log(lo) + u * (math.log(hi) - math.log(lo)))


def _lin(u: float, lo: float, hi: float) -> float:
    return lo + u * (hi - lo)


def _regular(n: int, rng: np.random.Generator) -> np.ndarray:
    t = 2 * math.pi * np.arange(n) / n + rng.uniform(0, 2 * math.pi / n)
    return np.stack([np.cos(t), np.sin(t)], axis=1)


def _irregular(n: int, rng: np.random.Generator) -> np.ndarray:
    """A random convex polygon with n corners (Valtr's algorithm: random x and y values, split
    into two chains each, paired and sorted by angle)."""

    def chains(v: np.ndarray) -> np.ndarray:
        v = np.sort(v)
        lo_last = hi_last = v[0]
        out = []
        for x in v[1:-1]:
            if rng.random() < 0.5:
                out.append(x - lo_last)
                lo_last = x
            else:
                out.append(hi_last - x)
                hi_last = x
        out.append(v[-1] - lo_last)
        out.append(hi_last - v[-1])
        return np.asarray(out)

    dx, dy = chains(rng.random(n)), chains(rng.random(n))
    dy = rng.permutation(dy)
    vec = np.stack([dx, dy], axis=1)
    vec = vec[np.argsort(np.arctan2(vec[:, 1], vec[:, 0]), kind="stable")]
    pts = np.cumsum(vec, axis=0)
    centred: np.ndarray = pts - pts.mean(axis=0)
    return centred


def _polygon_ok(v: np.ndarray) -> bool:
    e = np.roll(v, -1, axis=0) - v
    if np.min(np.hypot(e[:, 0], e[:, 1])) < MIN_EDGE_MM:
        return False
    nxt = np.roll(e, -1, axis=0)
    turn = np.arctan2(e[:, 0] * nxt[:, 1] - e[:, 1] * nxt[:, 0], np.sum(e * nxt, axis=1))
    turn = turn * (1.0 if turn.sum() >= 0 else -1.0)
    return bool(np.all(turn >= math.radians(MIN_TURN_DEG)))


def _centred_angle(obj: Polygon, start_deg: float) -> float | None:
    """The first angle from ``start_deg`` (within half a turn) at which the polygon's extent along
    y0 is centred on its centre: the offset e(θ) turns into −e(θ) over half a turn, so it
    crosses zero on the way."""

    def off(a: float) -> float:
        lo, hi = extent_along_y0(obj, a)
        return (lo + hi) / 2

    grid = start_deg + np.arange(0, 181, 1.0)
    vals = [off(float(a)) for a in grid]
    for k in range(len(grid) - 1):
        a0, a1, f0, f1 = float(grid[k]), float(grid[k + 1]), vals[k], vals[k + 1]
        if f0 == 0.0:
            return a0
        if f0 * f1 < 0:
            for _ in range(60):
                mid = (a0 + a1) / 2
                fm = off(mid)
                if f0 * fm <= 0:
                    a1 = mid
                else:
                    a0, f0 = mid, fm
            return (a0 + a1) / 2
    return None


def _shape(family: str, width: float, angle_u: float, depth: float, material: Material,
           rng: np.random.Generator, name: str, sides: int = 3, regular: bool = False,
           ) -> tuple[Shape, float] | None:  # fmt: skip
    """One object of the family, scaled so that its contact width at its angle is ``width``,
    and its angle; None if this draw gives no valid object."""
    span = ANGLE_DEG[family]
    angle = _r(_lin(angle_u, -span, span)) if span < 180 else _r(_lin(angle_u, -180.0, 180.0))
    if angle >= 180.0:
        angle = -180.0
    common = {"name": name, "depth_mm": depth, "material": material}
    a = math.radians(angle)
    ca, sa = abs(math.cos(a)), abs(math.sin(a))
    if family in ("box", "rounded"):
        aspect = _log_uniform(rng.random(), *BOX_ASPECT)
        rho = 0.0 if family == "box" else _lin(rng.random(), 0.2, 1.0)
        # unit box: w = 1, h = aspect, corner r = rho·min/2; its width at the angle, scaled
        r1 = rho * min(1.0, aspect) / 2
        unit = (1 - 2 * r1) * ca + (aspect - 2 * r1) * sa + 2 * r1
        w = width / unit
        h, r = _r(w * aspect), _r(w * r1)
        w = _r(w)
        r = min(r, math.floor(min(w, h) / 2 * 10**DECIMALS) / 10**DECIMALS)
        return Box(width_mm=w, height_mm=h, corner_radius_mm=r, **common), angle
    if family == "ellipse":
        aspect = _log_uniform(rng.random(), *ELLIPSE_ASPECT)
        unit = math.hypot(ca, aspect * sa)
        ax = width / unit
        return Ellipse(axis_a_mm=_r(ax), axis_b_mm=_r(ax * aspect), **common), angle
    if family == "circle":
        return Circle(diameter_mm=_r(width), **common), angle
    if family == "stick":
        d = min(_log_uniform(rng.random(), *STICK_DIAMETER_MM), width / 3)
        length = (width - d) / ca + d
        return Stick(length_mm=_r(length), diameter_mm=_r(d), **common), angle
    if family == "polygon":
        unit_v = _regular(sides, rng) if regular else _irregular(sides, rng)
        shape = Polygon(vertices_mm=[(float(x), float(y)) for x, y in unit_v * 50.0], **common)
        centred = _centred_angle(shape, angle)
        if centred is None:
            return None
        angle = _r(wrap_deg(centred))
        scale = width / contact_width_mm(shape, angle)
        v = np.round(unit_v * 50.0 * scale, DECIMALS)
        if not _polygon_ok(v):
            return None
        return Polygon(vertices_mm=[(float(x), float(y)) for x, y in v], **common), angle
    raise ValueError(f"unknown family {family!r}")


# --- cases and suites ---------------------------------------------------------------------------


def _strata(rng: np.random.Generator, n: int) -> np.ndarray:
    """n draws in [0, 1), one in each stratum of 1/n, in random order (Latin hypercube)."""
    return (rng.permutation(n) + rng.random(n)) / n


def _dead_cells(s: Settings) -> list[tuple[int, int, int]]:
    valid = s.tactile.distal.valid()
    mats = (s.axes.finger1_distal_matrix, s.axes.finger2_distal_matrix)
    return [(m, int(r), int(c)) for m in mats for r, c in zip(*np.nonzero(valid), strict=True)]


def generate_cases(
    seed: int, n: int, *, prefix: str = "", progress: Callable[[int, int], None] | None = None
) -> list[Case]:
    """``n`` cases from ``seed`` (bit for bit the same every time), families taking turns;
    ``progress(done, n)`` after each (a case takes tens of milliseconds: its placement is
    checked against the hand's geometry)."""
    rng = np.random.default_rng(seed)
    names = ("width", "height", "angle", "friction", "stiffness", "mass", "depth", "gain",
             "creep_gain", "creep_rise", "noise", "sides")  # fmt: skip
    u = {k: _strata(rng, n) for k in names}
    dead = rng.random(n) < DEAD_TEXEL_SHARE
    regular = rng.random(n) < REGULAR_SHARE
    lo_n, hi_n = POLYGON_SIDES
    sides = [lo_n + min(int(x * (hi_n - lo_n + 1)), hi_n - lo_n) for x in u["sides"]]
    s = _hand()[0]
    cells = _dead_cells(s)
    cases: list[Case] = []
    for i in range(n):
        family = GENERATED[i % len(GENERATED)]
        case_id = generated_id(prefix, family, i)
        material = Material(
            mass_g=_r(_log_uniform(u["mass"][i], *MASS_G)),
            friction=_r(_lin(u["friction"][i], *FRICTION)),
            stiffness_n_per_mm3=_r(_log_uniform(u["stiffness"][i], *STIFFNESS)),
        )
        depth = _r(_log_uniform(u["depth"][i], *DEPTH_MM))
        width = _lin(u["width"][i], *WIDTH_MM)
        height = _r(HEIGHT_MM + _lin(u["height"][i], -HEIGHT_SPAN_MM, HEIGHT_SPAN_MM))
        texels: tuple[Texel, ...] = ()
        if dead[i]:
            m, r, c = cells[int(rng.integers(len(cells)))]
            texels = (Texel(matrix=m, row=r, col=c),)
        sensor = SensorVariation(
            gain_factor=_r(_lin(u["gain"][i], *GAIN_FACTOR)),
            creep_gain=_r(_lin(u["creep_gain"][i], *CREEP_GAIN)),
            creep_rise_s=_r(_log_uniform(u["creep_rise"][i], *CREEP_RISE_S)),
            noise_counts=_r(_lin(u["noise"][i], *NOISE_COUNTS)),
            dead_texels=texels,
        )
        angle_u, n_sides, is_regular = u["angle"][i], sides[i], bool(regular[i])
        for attempt in itertools.count(1):
            try:
                got = _shape(family, width, angle_u, depth, material, rng, case_id,
                             n_sides, is_regular)  # fmt: skip
            except ValueError:  # pydantic's ValidationError is one: a draw out of bounds
                got = None
            if got is not None and check_placement(got[0], height, got[1]) is None:
                break
            angle_u = rng.random()  # another angle (and another shape) for this width
            if attempt % MAX_TRIES == 0:
                # The open fingers hold less at some heights than the widest of WIDTH_MM (a
                # 119 mm box at 116 mm up touches a pad off its sensing area or does not fit):
                # a little narrower, until it fits
                if width * WIDTH_SHRINK < WIDTH_MM[0]:  # pragma: no cover - 15 mm always fits
                    raise RuntimeError(f"no graspable {family} at {height} mm up")
                width *= WIDTH_SHRINK
            elif attempt % KEEP_SIDES_TRIES == 0:  # e.g. no regular triangle this wide fits
                n_sides = int(rng.integers(lo_n, hi_n + 1))  # at this height
                is_regular = bool(rng.random() < REGULAR_SHARE)
        assert got is not None  # the loop ends only with a placement
        obj, angle = got
        cases.append(Case(id=case_id, family=family, object=obj, height_mm=height,
                          angle_deg=angle, seed=i + 1, sensor=sensor,
                          true_width_mm=_true_width(obj, angle)))  # fmt: skip
        if progress is not None:
            progress(i + 1, n)
    return cases


def thesis_suite() -> Suite:
    """The thesis's objects as presets, at the configuration's placement and nominal sensor."""
    s = default_config()
    cases = [
        Case(id=name, family="thesis", object=PRESETS[name], height_mm=s.sim.object_height_mm,
             angle_deg=s.sim.object_angle_deg, seed=s.sim.seed,
             true_width_mm=_true_width(PRESETS[name], s.sim.object_angle_deg))
        for name in THESIS
    ]  # fmt: skip
    return Suite(name="thesis", generator_seed=None, cases=tuple(cases),
                 description="the thesis's rubber, egg, cylinder and four simulated sticks, "
                 "as the configuration places them")  # fmt: skip


def build_suite(name: str) -> Suite:
    """The named suite as its seed (or, for ``thesis``, the presets) makes it."""
    if name == "thesis":
        return thesis_suite()
    seed, n, description = SUITE_SEEDS[name]
    return generated_suite(name, seed, n, description=description)


def generated_suite(
    name: str, seed: int, n: int, *, description: str, prefix: str = "",
    progress: Callable[[int, int], None] | None = None,
) -> Suite:  # fmt: skip
    """A suite of ``n`` cases from ``seed`` (:func:`generate_cases`, ids after ``prefix``)."""
    cases = tuple(generate_cases(seed, n, prefix=prefix, progress=progress))
    return Suite(name=name, generator_seed=seed, description=description, cases=cases)


SUITE_NAMES: tuple[str, ...] = (*SUITE_SEEDS, "thesis")


def check_suites(directory: Path = SUITES_DIR, names: Sequence[str] = SUITE_NAMES,
                 build: Callable[[str], Suite] = build_suite) -> list[str]:  # fmt: skip
    """The suites whose file differs from what their seed makes (or is missing)."""
    stale = []
    for name in names:
        path = directory / f"{name}.json"
        if not path.is_file() or path.read_text() != build(name).to_json():
            stale.append(name)
    return stale


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m sdh2svc.campaign.generate",
        description="regenerate or check the packaged campaign suites",
    )
    what = ap.add_mutually_exclusive_group(required=True)
    what.add_argument("--write", action="store_true", help="write the suite files")
    what.add_argument(
        "--check",
        action="store_true",
        help="exit 1 unless the suite files are what their seeds make",
    )
    ap.add_argument("--dir", type=Path, default=SUITES_DIR, help="the suites' directory")
    ap.add_argument("names", nargs="*", default=list(SUITE_NAMES), help="suites (default: all)")
    args = ap.parse_args(argv)
    for name in args.names:
        if name not in SUITE_NAMES:
            ap.error(f"unknown suite {name!r}; known: {', '.join(SUITE_NAMES)}")
    if args.check:
        stale = check_suites(args.dir, args.names)
        for name in stale:
            print(
                f"{name}: {args.dir / (name + '.json')} differs from what its seed makes",
                file=sys.stderr,
            )
        return 1 if stale else 0
    args.dir.mkdir(parents=True, exist_ok=True)
    for name in args.names:
        suite = build_suite(name)
        suite.dump(args.dir / f"{name}.json")
        print(f"{name}: {len(suite.cases)} cases → {args.dir / (name + '.json')}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
