"""Planar quasi-static contact mechanics of the two coupled fingers and one object (y0z0 plane).

The fingers are position-controlled bodies; the object is free. Each step finds the object pose
(y, z, ψ) at which the contact forces (and gravity) balance, for the current finger joints:

* Surfaces: both distal pads (the profile of hand-model §3), both proximal pads (flat, along the
  proximal links) and the palm, each sampled every ``sample_spacing_mm`` along its length.
* Normal compliance, an elastic foundation ("Winkler") model: each pad sample that lies inside the
  object carries pressure k·δ (k: pad and object stiffness in series) over its strip of pad,
  pushing along the pad normal. The foundation's rubber is compressed along the pad's normal, so
  δ is the depth of the object's surface below the undeformed pad there, along that normal: the
  distance from the sample along −n (into the finger) to where that line leaves the object
  (``Outline.exit_distance``, a closed form for every shape), not the distance to the object's
  nearest surface (−sdf). The two agree for a shallow contact of nearly parallel surfaces (a face
  pressed flat: δ = −sdf); where they differ, the nearest surface can be the wrong one: a thin
  stick pushed end-first into a pad sinks by its whole protrusion, while −sdf would stop at its
  half thickness (its side being nearer), the force with it, and let the pad pass through the
  stick. Faces pressed flat spread over many samples; edges and curved objects concentrate —
  which is what the tactile sensor model rasterises. The point where pad and object touch is each
  sample pushed back along its normal by its δ (less the finger's yield): on the object's surface.
* Coulomb friction, per contact: a tangential spring anchored where the object and the pad touched
  at the previous step, capped at μ·N. Inside the cap the contact sticks, so the object rolls on
  the pad without slipping; at the cap it slides and a slip is recorded.
* The object starts held by a *fixture* (a person's hand placing it between the fingertips) and
  is released once both distal pads press it and hold it (a balance exists without the
  fixture, every contact sticking; a person does not let go of an object the fingers touch on
  two corners, or grip too lightly for its weight), or once their squeeze has stopped growing
  for a second (the object then stays or falls on its own); it is pulled back if a finger
  sweeps through it before both distal pads press it. A step without a force balance, or with
  no contact force left on a distal pad, means the object is no longer held: it is dropped.

Joint torques from the contact forces are checked against the motor limits: a joint whose next
step would need more torque stalls at its last angle (the firmware's "blocked"), so a finger
pressing a stiff object stops instead of passing through it. The world (hand.py) makes that check
at every servo tick, but steps this physics lazily: only once the joints have moved a whole
substep (``max_joint_step_deg``) or the state is read, so a stall lands within one substep.

Speed (fast mode runs thousands of steps per simulated minute) never changes the equations: the
surfaces are moved into frame 0 once per finger pose (cached on the exact pose), all nearby
samples are moved into the object frame by one affine product and tested in one pass (a box's
distance in closed form; an ellipse's test is a quadratic form of the samples' monomials, also
one product), the depths along the normals are worked out only for the few samples inside (their
points and normals moved into the object frame by one more product), the per-contact sums
and their overlap-weighted twins come from one product (the samples a yielding finger left weigh
0 instead of being picked out; the pressures are picked out only when a tactile frame asks for
them), and the finger's yield is found by Newton steps on the pad's linear law in plain floats,
exact once the set of samples in contact stops changing (the piecewise law only when a sample
bottoms out). Newton starts from the balance extrapolated along the fingers' motion (a parabola
through the last three balances, whatever the substeps' lengths), with a Jacobian kept from step
to step and corrected by Broyden's secant updates; the solver's pose, residual and Jacobian are
plain floats, and the anchors' springs are moved into frame 0 once per step. Convergence is
checked on the same residual and tolerance.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Annotated

import numpy as np
from pydantic import Field, model_validator

from sdh2svc.model.base import Finite
from sdh2svc.model.geometry import PadProfile, pad_point_from_L, pad_slope
from sdh2svc.model.kinematics import Finger, HandGeometry, HandPose
from sdh2svc.sim.objects import _ONE, _ZERO, Ellipse, Outline, Polygon

Gravity = Annotated[float, Field(ge=-100.0, le=100.0)]  # m/s², at most ≈ 10 g
Pair = tuple[float, float]
Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, ...]  # 3 rows
_Pull = tuple[float, float, float, float, float]  # an anchor's spring, see ContactPhysics._pulls
# each surface's (normals, points, columns) in frame 0 at the current pose, once computed
_World = list[tuple[np.ndarray, np.ndarray, np.ndarray] | None]


class PhysicsConfig(Finite):
    """Contact mechanics parameters (see config/sim.toml). The ranges are generous physical
    ones (a rubber 500 × softer or stiffer than the DSA's, a finger 10⁴ × stiffer); NaN and
    infinities are refused: they break the balance's solver rather than the simulated hand."""

    pad_stiffness_n_per_mm3: Annotated[float, Field(gt=0.0, le=100.0)]
    pad_thickness_mm: Annotated[float, Field(gt=0.0, le=20.0)]
    backing_stiffness_n_per_mm3: Annotated[float, Field(gt=0.0, le=1e4)]
    finger_stiffness_n_per_mm: Annotated[float, Field(gt=0.0, le=1e5)]
    tangential_stiffness_n_per_mm: Annotated[float, Field(gt=0.0, le=1e5)]
    gravity_m_per_s2: tuple[Gravity, Gravity, Gravity]  # (x0: out of the plane, y0, z0)
    sample_spacing_mm: Annotated[float, Field(gt=0.01, le=2.0)]
    max_joint_step_deg: Annotated[float, Field(gt=0.0, le=5.0)]
    release_force_n: Annotated[float, Field(ge=0.0, le=100.0)]
    fixture_max_overlap_mm: Annotated[float, Field(gt=0.0, le=50.0)]
    proximal_pad_offset_mm: Annotated[float, Field(ge=0.0, le=50.0)]
    proximal_pad_start_mm: Annotated[float, Field(ge=0.0, le=200.0)]
    proximal_pad_end_mm: Annotated[float, Field(ge=0.0, le=200.0)]
    palm_z_mm: Annotated[float, Field(ge=-100.0, le=50.0)]
    pad_width_mm: Annotated[float, Field(gt=0.0, le=100.0)]
    torque_limit_proximal_n_mm: Annotated[float, Field(gt=0.0, le=1e5)]
    torque_limit_distal_n_mm: Annotated[float, Field(gt=0.0, le=1e5)]

    @model_validator(mode="after")
    def _in_plane(self) -> PhysicsConfig:
        if self.gravity_m_per_s2[0] != 0.0:
            raise ValueError(
                f"gravity_m_per_s2's first component ({self.gravity_m_per_s2[0]:g}, x0: out of "
                "the fingers' plane) must be 0: the contacts are planar, friction across the "
                "plane is not modelled (point the hand so gravity lies in its y0-z0 plane)"
            )
        return self

    @model_validator(mode="after")
    def _proximal_pad(self) -> PhysicsConfig:
        if self.proximal_pad_start_mm >= self.proximal_pad_end_mm:
            raise ValueError(
                f"proximal_pad_start_mm ({self.proximal_pad_start_mm:g}) must be below "
                f"proximal_pad_end_mm ({self.proximal_pad_end_mm:g})"
            )
        return self


_ZERO3 = (0.0, 0.0, 0.0)
# The placing fixture (a person's hand) lets go once the fingers hold the object, or once their
# squeeze has not grown by FIXTURE_GROWTH for FIXTURE_PATIENCE_S (simulated seconds)
FIXTURE_GROWTH = 1.05
FIXTURE_PATIENCE_S = 1.0
MAX_HALVINGS = 3  # a substep without a balance is retried in halves down to 1/8 of its length
# The sampled surfaces make the contact forces jump by one sample's share as a sample enters or
# leaves a contact; on a thin object's few contact samples that can leave no exact balance
# anywhere, while the grip holds it as firmly as before. So before an object is called dropped,
# a pose whose force and moment residuals are within this fraction of the grip (Σ normal forces;
# N and N·mm), or within the force of the most loaded distal contact sample (the largest such
# jump), counts as a balance. Measured on bench-v1's soft thin sticks: residuals of 0.8 %; on
# compliant needles sunk deeper than their radius (vertical flanks: each 0.25 mm sample carries
# ≈ 5 % of the grip), 1.0–5.5 % (experiments/campaigns/unseen, fresh5401).
LOOSE_BALANCE = 0.01

# Surfaces, in a fixed order; a surface is a sampled curve in the frame of one link.
DISTAL1, PROXIMAL1, DISTAL2, PROXIMAL2, PALM = range(5)
SURFACE_NAMES = ("distal1", "proximal1", "distal2", "proximal2", "palm")
SURFACE_FINGER = (Finger.ONE, Finger.ONE, Finger.TWO, Finger.TWO, None)


@dataclass(frozen=True, slots=True)
class Surface:
    """Samples of one surface in its link frame: coordinates (a, b) along the link's (ex, ey),
    unit normals and tangents in the same frame, and the surface parameter s (mm) of each sample:
    L from the pad's base for a distal pad, the distance from O along the link for a proximal
    pad, y0 for the palm."""

    index: int
    s: np.ndarray
    local: np.ndarray
    normal: np.ndarray
    tangent: np.ndarray
    ds: float


def _distal_surface(index: int, pad: PadProfile, spacing: float) -> Surface:
    s = np.arange(spacing / 2, pad.max_L_mm, spacing)
    pts = np.array([pad_point_from_L(L, pad) for L in s])
    slope = np.array([pad_slope(x3, pad) for x3 in pts[:, 0]])
    norm = np.sqrt(1 + slope**2)
    tangent = np.stack([1 / norm, slope / norm], axis=1)
    normal = np.stack([-slope / norm, 1 / norm], axis=1)
    return Surface(index, s, pts, normal, tangent, spacing)


def _straight_surface(
    index: int, start: float, end: float, offset: float, spacing: float
) -> Surface:
    s = np.arange(start + spacing / 2, end, spacing)
    local = np.stack([s, np.full_like(s, offset)], axis=1)
    normal = np.tile([0.0, 1.0], (len(s), 1))
    tangent = np.tile([1.0, 0.0], (len(s), 1))
    return Surface(index, s, local, normal, tangent, spacing)


def build_surfaces(geom: HandGeometry, cfg: PhysicsConfig) -> tuple[Surface, ...]:
    sp = cfg.sample_spacing_mm
    prox = (cfg.proximal_pad_start_mm, cfg.proximal_pad_end_mm, cfg.proximal_pad_offset_mm, sp)
    # the palm: a line at z = palm_z across the hand, normal +z0 (its "link frame" is frame 0)
    palm_s = np.arange(-40.0, geom.base_offset_mm + 40.0, sp)
    palm = Surface(
        PALM, palm_s, np.stack([palm_s, np.full_like(palm_s, cfg.palm_z_mm)], axis=1),
        np.tile([0.0, 1.0], (len(palm_s), 1)), np.tile([1.0, 0.0], (len(palm_s), 1)), sp,
    )  # fmt: skip
    return (
        _distal_surface(DISTAL1, geom.pad, sp),
        _straight_surface(PROXIMAL1, *prox),
        _distal_surface(DISTAL2, geom.pad, sp),
        _straight_surface(PROXIMAL2, *prox),
        palm,
    )


def link_frame_rows(pose: HandPose, geom: HandGeometry) -> list[tuple[tuple[float, float], ...]]:
    """(origin, ex, ey) of each surface's link frame in frame 0, in surface order, as plain
    floats: :func:`distal_joint` and :func:`frame3_axes` written out (this runs at every
    substep)."""
    l1, base = geom.proximal_length_mm, geom.base_offset_mm
    s2, c2 = math.sin(pose.phi2), math.cos(pose.phi2)
    s23, c23 = math.sin(pose.phi2 + pose.phi3), math.cos(pose.phi2 + pose.phi3)
    s4, c4 = math.sin(pose.phi4), math.cos(pose.phi4)
    s45, c45 = math.sin(pose.phi4 + pose.phi5), math.cos(pose.phi4 + pose.phi5)
    return [
        ((l1 * s2, l1 * c2), (s23, c23), (c23, -s23)),  # distal 1, at C
        ((0.0, 0.0), (s2, c2), (c2, -s2)),  # proximal 1, at O
        ((base - l1 * s4, l1 * c4), (-s45, c45), (-c45, -s45)),  # distal 2 (mirrored), at D
        ((base, 0.0), (-s4, c4), (-c4, -s4)),  # proximal 2
        ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0)),  # the palm, in frame 0
    ]


def _local_columns(surf: Surface) -> np.ndarray:
    """Per sample, in the link frame: normal, point × normal, point, 1, tangent and s (the 1
    right after the point: the affine move of the points into the object frame is a product)."""
    p, n = surf.local, surf.normal
    pxn = p[:, 0] * n[:, 1] - p[:, 1] * n[:, 0]
    return np.column_stack([n, pxn, p, np.ones(len(surf.s)), surf.tangent, surf.s])


# where _to_world's entries go in its 9 × 9 map (flat, row by row)
_MAP_ENTRIES = np.array([0, 1, 2, 9, 10, 11, 20, 30, 31, 39, 40, 48, 49, 50, 60, 61, 69, 70, 80])
# where ContactPhysics._depths's entries go in its 4 × 9 map to the object frame
_OBJECT_ENTRIES = np.array([3, 4, 5, 12, 13, 14, 18, 19, 27, 28])


def _along(dq: tuple[float, ...], ref: tuple[float, ...]) -> float | None:
    """dq as a multiple of ref when the two joint moves point the same way (else None)."""
    (a0, a1, a2, a3), (b0, b1, b2, b3) = dq, ref
    dd = a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3
    nn = b0 * b0 + b1 * b1 + b2 * b2 + b3 * b3
    mm = a0 * a0 + a1 * a1 + a2 * a2 + a3 * a3
    if nn <= 0.0 or dd <= 0.0 or dd * dd < 0.81 * nn * mm:
        return None
    return dd / nn


def _norm3(v: Sequence[float]) -> float:
    a, b, c = v
    return math.sqrt(a * a + b * b + c * c)


def _nearly_balanced(ev: _Eval, x: np.ndarray, start: np.ndarray, grain: float) -> bool:
    """Within :data:`LOOSE_BALANCE` of the grip or within ``grain`` (one contact sample's force:
    :meth:`ContactPhysics._grain`), close to where the object was (5 mm, 10°)."""
    grip = sum(c[2] for c in ev.contacts.values())
    moved = np.abs(x - start)
    near = moved[0] < 5.0 and moved[1] < 5.0 and moved[2] < math.radians(10.0)
    tol = max(LOOSE_BALANCE * grip, grain)
    return grip > 0.0 and near and max(abs(v) for v in ev.residual) <= tol


def _solve3(J: Mat3, r: Sequence[float]) -> Vec3:
    """The Newton move: J·dx = −r (Cramer's rule, far cheaper than LAPACK for a 3 × 3);
    a (near-)singular J takes the least-squares move. Plain floats: the solver's 3-vectors
    and 3 × 3 matrices are too small for numpy to pay off."""
    (a, b, c), (d, e, f), (g, h, i) = J
    co0, co1, co2 = e * i - f * h, f * g - d * i, d * h - e * g
    det = a * co0 + b * co1 + c * co2
    scale = max(abs(a), abs(b), abs(c), abs(d), abs(e), abs(f), abs(g), abs(h), abs(i))
    if not abs(det) > 1e-12 * scale**3:
        x0, x1, x2 = np.linalg.lstsq(np.array(J), -np.array(r), rcond=None)[0].tolist()
        return x0, x1, x2
    r0, r1, r2 = -r[0], -r[1], -r[2]
    return (
        (co0 * r0 + (c * h - b * i) * r1 + (b * f - c * e) * r2) / det,
        (co1 * r0 + (a * i - c * g) * r1 + (c * d - a * f) * r2) / det,
        (co2 * r0 + (b * g - a * h) * r1 + (a * e - b * d) * r2) / det,
    )  # the adjugate (inverse × det) times −r


def _broyden(J: Mat3, s: Vec3, y: Sequence[float]) -> Mat3:
    """Broyden's rank-one update of J for the move s that changed the residual by y:
    J + (y − J·s)·sᵀ / (s·s)."""
    s0, s1, s2 = s
    ss = s0 * s0 + s1 * s1 + s2 * s2
    if not ss > 0.0:
        return J
    rows = []
    for (j0, j1, j2), yi in zip(J, y, strict=True):
        ui = (yi - (j0 * s0 + j1 * s1 + j2 * s2)) / ss
        rows.append((j0 + ui * s0, j1 + ui * s1, j2 + ui * s2))
    return tuple(rows)


def _ellipse_forms(
    ia: float, ib: float, cos_p: float, sin_p: float, ox: float, oy: float
) -> np.ndarray:
    """The quadratic form g² = |q|² of a frame-0 point (y, z) as coefficients of its monomials
    (y², yz, z², y, z, 1), for the ellipse at object offset (ox, oy) = Rᵀ·c turned by ψ, with
    q = (x/a, y/b) the point in the object frame scaled by the semi-axes. One product with the
    monomials then tests every sample (this ``g²`` is :meth:`Outline.sdf`'s, expanded)."""
    # q = (A1·y + B1·z + C1, A2·y + B2·z + C2); g² = Σ q_k² for q_k = (A, B, C)·(y, z, 1)
    a1, b1, c1 = cos_p * ia, sin_p * ia, -ox * ia
    a2, b2, c2 = -sin_p * ib, cos_p * ib, -oy * ib
    return np.array((
        a1 * a1 + a2 * a2, 2.0 * (a1 * b1 + a2 * b2), b1 * b1 + b2 * b2,
        2.0 * (a1 * c1 + a2 * c2), 2.0 * (b1 * c1 + b2 * c2), c1 * c1 + c2 * c2,
    ))  # fmt: skip


def to_world(frame: tuple[np.ndarray, np.ndarray, np.ndarray], local: np.ndarray) -> np.ndarray:
    o, ex, ey = frame
    out: np.ndarray = o + local[..., :1] * ex + local[..., 1:2] * ey
    return out


def rot(psi: float) -> np.ndarray:
    c, s = math.cos(psi), math.sin(psi)
    return np.array([[c, -s], [s, c]])


@dataclass(slots=True)
class Anchor:
    """Where object and surface stuck together at the end of the previous step."""

    obj_point: Pair  # object frame
    local_point: Pair  # surface link frame
    u: float  # elastic tangential displacement, mm


@dataclass(frozen=True, slots=True)
class ContactTruth:
    """Ground truth of one contact region (never visible to the controller)."""

    surface: str
    point: tuple[float, float]  # pressure centroid on the surface, frame 0 (y, z)
    s_mm: float  # surface parameter of the centroid (L for a distal pad)
    object_point: tuple[float, float]  # the same point in the object's frame
    normal_force_n: float
    tangential_force_n: float
    slipping: bool


@dataclass(slots=True)
class _Eval:
    residual: Vec3  # net force (y0, z0) and moment (in force units) on the object
    # surface → (centroid, tangent, N, tangential force, u, s of the centroid, slipping)
    contacts: dict[int, tuple[Pair, Pair, float, float, float, float, bool]]
    # surface → (the inside samples' indices into the evaluation's concatenation, the surface's
    # start in it, their compression (0 where the finger yielded off them), the largest one):
    # what ContactPhysics.pressures turns into pressures, once a frame asks
    compressions: dict[int, tuple[np.ndarray, int, np.ndarray, float]]
    max_depth: float = 0.0  # deepest geometric overlap of a surface into the object, mm
    # surface → (Σ p·w·ds·n, Σ p·w·ds·(point × n)) in frame 0: the joint torques' sums
    sums: dict[int, tuple[float, float, float]] = field(default_factory=dict)


@dataclass(slots=True)
class PhysicsState:
    pose: np.ndarray  # object (y, z, ψ) in frame 0
    held_by_fixture: bool = True
    present: bool = False  # placed between the fingers (while in the fixture)
    squeeze: float = 0.0  # the lesser distal pad's largest force on it, N (in the fixture)
    squeeze_t: float = 0.0  # when that squeeze came (ContactPhysics.clock)
    dropped: bool = False
    anchors: dict[int, Anchor] = field(default_factory=dict)
    slips: int = 0
    slip_distance_mm: float = 0.0
    psi_min: float = math.inf
    psi_max: float = -math.inf
    # the largest true grip so far, N: the mean of the distal pads' normal forces (as the
    # controller's F is the mean of F1 and F2), over every balance the fingers held it in
    grip_peak_n: float = 0.0
    slipping: set[int] = field(default_factory=set)


class ContactPhysics:
    """The quasi-static world of one object between the coupled fingers."""

    def __init__(self, geom: HandGeometry, cfg: PhysicsConfig, outline: Outline, pose: HandPose,
                 object_pose: tuple[float, float, float]) -> None:  # fmt: skip
        self.geom, self.cfg, self.outline = geom, cfg, outline
        self.surfaces = build_surfaces(geom, cfg)
        spec = outline.spec
        self.width_mm = min(spec.depth_mm, cfg.pad_width_mm)
        kp, ko = cfg.pad_stiffness_n_per_mm3, spec.material.stiffness_n_per_mm3
        self.k = kp * ko / (kp + ko)  # pad and object in series
        # once the pad is squeezed to its backing, only the object (and the backing) yield
        self.knee = cfg.pad_thickness_mm * (1.0 + kp / ko)
        self.k_bottomed = 1.0 / (1.0 / ko + 1.0 / cfg.backing_stiffness_n_per_mm3)
        self.mu = spec.material.friction
        g = np.asarray(cfg.gravity_m_per_s2, dtype=float)
        self.gravity_n = spec.material.mass_g / 1000.0 * g  # (x0, y0, z0) newtons
        # the evaluation's constants, as plain floats
        self._gravity_yz = (float(self.gravity_n[1]), float(self.gravity_n[2]))
        self._wds = self.width_mm * cfg.sample_spacing_mm  # each sample's strip of pad, mm²
        self._kw = self.k * self._wds  # p·w·ds per mm of compression, below the knee
        self._kt = cfg.tangential_stiffness_n_per_mm
        self._kw0 = np.array(self._kw)  # as a 0-d array for numpy (see objects._ZERO)
        self._moment_scale = 1.0 / max(outline.bound_radius, 1.0)  # moment in force units
        self._pressures: tuple[_Eval, dict[int, tuple[np.ndarray, np.ndarray]]] | None = None
        self.hand_pose = pose
        self.state = PhysicsState(np.asarray(object_pose, dtype=float))
        self._jacobian: Mat3 | None = None
        self._motion: list[tuple[tuple[float, ...], Vec3]] = []  # last two (Δq, Δx)
        self.clock = 0.0  # simulated seconds, set by the world (the fixture's patience)
        self._last = _Eval(_ZERO3, {}, {})
        self._world_key: tuple[float, ...] | None = None
        self._world: _World = []
        self._groups: dict[tuple[int, ...], tuple[np.ndarray, list[int], np.ndarray]] = {}
        self._starts: dict[tuple[int, ...], list[int]] = {}  # each group's surface starts
        self._starts_array: dict[tuple[int, ...], np.ndarray] = {}  # the same, for searchsorted
        self._map = np.zeros((9, 9))  # see _to_world
        self._to_object = np.zeros((4, 9))  # see _depths
        self._frame_rows: list[tuple[tuple[float, float], ...]] = []
        self._world_circles: list[tuple[float, float, float]] = []
        # each surface's bounding circle in its link frame, (a, b), and the squared distance
        # within which the object's centre must come for the surface to touch it
        self._circles: list[tuple[float, float, float]] = []
        self._local_cols = [_local_columns(surf) for surf in self.surfaces]
        self._e_hint: dict[int, float] = {}  # each surface's last finger yield, Newton's start
        self._prefilter = isinstance(spec, Polygon)  # a box has a cheap closed form
        self._ellipse = (
            (2.0 / spec.axis_a_mm, 2.0 / spec.axis_b_mm)
            if isinstance(spec, Ellipse) else None
        )  # fmt: skip
        for surf in self.surfaces:
            mid = (surf.local.min(axis=0) + surf.local.max(axis=0)) / 2
            rad = float(np.max(np.linalg.norm(surf.local - mid, axis=1)))
            # with the object's reach: how close (squared) its centre must be to matter
            lim = (outline.bound_radius + rad) ** 2
            self._circles.append((float(mid[0]), float(mid[1]), lim))
        self._torques: tuple[_Eval, tuple[float, ...] | None, dict[str, float]] | None = None
        self._substep(pose)

    # --- geometry of one evaluation -----------------------------------------------------------

    def _world_samples(self, pose: HandPose) -> _World:
        """Link frames and each surface's bounding circle in frame 0 for ``pose``, cached on the
        exact pose (the joint emulator asks again and again for the same pose between servo
        ticks); the samples themselves are moved into frame 0 lazily, by :meth:`_surface`."""
        key = (pose.phi2, pose.phi3, pose.phi4, pose.phi5)
        if key == self._world_key:
            return self._world
        rows = link_frame_rows(pose, self.geom)
        circles = []
        for (ma, mb, lim), (o, ex, ey) in zip(self._circles, rows, strict=True):
            circles.append((o[0] + ma * ex[0] + mb * ey[0], o[1] + ma * ex[1] + mb * ey[1], lim))
        self._frame_rows = rows
        self._world_key, self._world_circles = key, circles
        self._world = [None] * len(self.surfaces)
        self._groups = {}
        return self._world

    def _surface(self, j: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Samples and normals of surface j in frame 0 at the current pose, and the columns
        :meth:`_evaluate` sums per sample: normal, point × normal, point, 1, tangent, s."""
        got = self._world[j]
        if got is None:
            cols: np.ndarray = self._local_cols[j] @ self._to_world(j)
            got = (cols[:, 3:5], cols[:, 0:2], cols)
            self._world[j] = got
        return got

    def _to_world(self, j: int) -> np.ndarray:
        """The affine map of surface j's local columns (see _local_columns) into frame 0:

            [a, b, b·o_y − a·o_z, 0, 0, 0, 0, 0, 0]    normal (u, v) → normal, o × normal
            [c, d, d·o_y − c·o_z, 0, 0, 0, 0, 0, 0]
            [0, 0, det,  0, 0, 0, 0, 0, 0]             p × n is kept or flipped (mirrored)
            [0, 0, 0,    a, b, 0, 0, 0, 0]             point (u, v, 1) → point, 1
            [0, 0, 0,    c, d, 0, 0, 0, 0]
            [0, 0, 0,  o_y, o_z, 1, 0, 0, 0]
            [0, 0, 0,    0, 0, 0, a, b, 0]             tangent
            [0, 0, 0,    0, 0, 0, c, d, 0]
            [0, 0, 0,    0, 0, 0, 0, 0, 1]             s

        with (a, b) = ex, (c, d) = ey. Written into one array, in place (it is consumed at
        once): filling 19 entries is cheaper than building a 9 × 9 array."""
        o, (a, b), (c, d) = self._frame_rows[j]  # local (u, v) → frame 0: u·ex + v·ey
        det = a * d - b * c  # −1: a mirrored frame, which flips the sign of p × n
        self._map.put(_MAP_ENTRIES, (
            a, b, -a * o[1] + b * o[0], c, d, -c * o[1] + d * o[0], det,
            a, b, c, d, o[0], o[1], 1.0, a, b, c, d, 1.0,
        ))  # fmt: skip
        return self._map

    def _evaluate(
        self, x: Sequence[float], world: _World, pulls: dict[int, _Pull] | None = None,
        slip: dict[int, float] | None = None,
    ) -> _Eval:  # fmt: skip
        """Net force and moment on the object at pose x (the residual), and the contacts.

        Sticking contacts pull with their tangential spring (``pulls``, see :meth:`_pulls`),
        uncapped; the contacts in ``slip`` (surface → sign) slide with the Coulomb force μ·N in
        that direction.
        """
        cy, cz, psi = x
        cos_p, sin_p = math.cos(psi), math.sin(psi)
        fy, fz = self._gravity_yz
        moment = 0.0
        contacts: dict[int, tuple[Pair, Pair, float, float, float, float, bool]] = {}
        pressures: dict[int, tuple[np.ndarray, int, np.ndarray, float]] = {}
        sums: dict[int, tuple[float, float, float]] = {}
        max_depth = 0.0
        wds, reach = self._wds, self.outline.bound_radius
        near_j = tuple([
            j
            for j, (my, mz, lim) in enumerate(self._world_circles)
            if (cy - my) ** 2 + (cz - mz) ** 2 <= lim
        ])  # the others are nowhere near the object  # fmt: skip
        # all nearby surfaces' samples at once, then each surface's share of those inside
        inside, depth, starts, cols_all = self._inside(near_j, cy, cz, cos_p, sin_p, reach * reach)
        bounds = inside.searchsorted(self._starts_array[near_j]).tolist()
        for k, j in enumerate(near_j):
            lo, hi = bounds[k], bounds[k + 1]
            if lo == hi:
                continue
            overlap = depth[lo:hi]
            ov = overlap.tolist()  # plain floats for the finger's yield: a few dozen samples
            deepest = max(ov)
            if deepest > max_depth:
                max_depth = deepest
            # the finger yields along the pad normal (structure and servo, in series with the pad)
            e = 0.0 if SURFACE_FINGER[j] is None else self._yield(overlap, wds, deepest, j, ov)
            # compression; the samples the yielding finger left (overlap ≤ e) weigh 0 rather
            # than being picked out (the pressures are only picked once a frame asks for them)
            c = np.maximum(overlap - e, _ZERO) if e > 0.0 else overlap
            top = deepest - e
            # p·w·ds per sample (the linear law's k·c below the knee), and times the overlap:
            # written straight into the two rows the product below takes
            weights = np.empty((2, hi - lo))
            pw = weights[0]
            if top <= self.knee:
                np.multiply(c, self._kw0, out=pw)
            else:
                np.multiply(self._pressure(c, top), wds, out=pw)
            np.multiply(pw, overlap, out=weights[1])
            # a convex object presses one run of samples: a view instead of a copy
            g0, g1 = int(inside[lo]), int(inside[hi - 1]) + 1
            sub = cols_all[g0:g1] if g1 - g0 == hi - lo else cols_all[inside[lo:hi]]
            # one product gives Σ p·w·ds·(n, p×n, point, 1, tangent, s) over the contact samples,
            # and the same weighted by the overlap (only its normal part is used)
            sums_pw, back = (weights @ sub).tolist()
            Fy, Fz, pxn, Py, Pz, total, Ty, Tz, S = sums_pw
            if total <= 0.0:  # the yielding finger left every sample: no contact here
                continue
            N = math.hypot(Fy, Fz)
            # Σ arm × f with arm = point − c, f = p·w·ds·n
            moment += pxn - (cy * Fz - cz * Fy)
            fy += Fy
            fz += Fz
            # where pad and object touch: each pad point pushed back by its overlap (finger
            # yield plus pad compression) lies on the object's surface
            cen_y, cen_z = (Py - back[0]) / total, (Pz - back[1]) / total
            t_norm = math.hypot(Ty, Tz)
            tan_y, tan_z = Ty / t_norm, Tz / t_norm
            u = 0.0
            pull = None if pulls is None else pulls.get(j)
            if pull is not None:
                ay, az, sy, sz, u0 = pull
                u = u0 + ((cy + cos_p * ay - sin_p * az - sy) * tan_y
                          + (cz + sin_p * ay + cos_p * az - sz) * tan_z)  # fmt: skip
            slipping = slip is not None and j in slip
            ft = slip[j] * self.mu * N if slip is not None and slipping else -self._kt * u
            ty, tz = ft * tan_y, ft * tan_z
            fy += ty
            fz += tz
            moment += (cen_y - cy) * tz - (cen_z - cz) * ty
            contacts[j] = ((cen_y, cen_z), (tan_y, tan_z), N, ft, u, S / total, slipping)
            pressures[j] = (inside[lo:hi], starts[k], c, top)
            sums[j] = (Fy, Fz, pxn)
        return _Eval((fy, fz, moment * self._moment_scale), contacts, pressures, max_depth, sums)

    def _inside(
        self, near_j: tuple[int, ...], cy: float, cz: float, cos_p: float, sin_p: float,
        reach2: float,
    ) -> tuple[np.ndarray, np.ndarray, list[int], np.ndarray]:  # fmt: skip
        """Samples of the surfaces near_j (concatenated) inside the object at (cy, cz) turned
        by ψ: their indices, their depths (see :meth:`_depths`), each surface's start, the
        columns."""
        group = self._groups.get(near_j)
        if group is None:  # the surfaces' columns in frame 0, moved straight into one array
            starts = self._starts.get(near_j)
            if starts is None:
                starts = [0]
                for j in near_j:
                    starts.append(starts[-1] + len(self._local_cols[j]))
                self._starts[near_j] = starts
                self._starts_array[near_j] = np.array(starts)
            cols = np.empty((starts[-1], 9))
            for k, j in enumerate(near_j):
                out = cols[starts[k] : starts[k + 1]]
                np.matmul(self._local_cols[j], self._to_world(j), out=out)
            # the points (y, z, 1) as rows: each evaluation moves them with one product; an
            # ellipse's tests are quadratic forms in them, so it takes their monomials instead
            if self._ellipse is None:
                points = np.ascontiguousarray(cols[:, 3:6].T)
            else:
                points = np.empty((6, starts[-1]))
                points[3:] = cols[:, 3:6].T
                y, z = points[3], points[4]
                np.multiply(y, y, out=points[0])
                np.multiply(y, z, out=points[1])
                np.multiply(z, z, out=points[2])
            group = (cols, starts, points)
            self._groups[near_j] = group
        cols, starts, points = group
        # the points in the object frame, Rᵀ·(p − c), as two rows (x, y)
        ox, oy = cy * cos_p + cz * sin_p, cz * cos_p - cy * sin_p
        if self._ellipse is not None:
            forms = _ellipse_forms(*self._ellipse, cos_p, sin_p, ox, oy)
            inside = (forms @ points < _ONE).nonzero()[0]  # g < 1 exactly when g² < 1
            return inside, self._depths(cols, inside, cos_p, sin_p, ox, oy), starts, cols
        rows = np.array(((cos_p, sin_p, -ox), (-sin_p, cos_p, -oy))) @ points  # (x, y)
        if not self._prefilter:
            inside = np.nonzero(self.outline.sdf_rows(rows) < _ZERO)[0]
        else:  # a polygon's sdf is dear: only for the samples in its bounding circle
            px, py = rows  # |local|² on the rows: the same unfused sum as an einsum's
            near = np.nonzero(px * px + py * py <= reach2)[0]
            inside = near[self.outline.sdf(rows.T[near]) < _ZERO]
        return inside, self._depths(cols, inside, cos_p, sin_p, ox, oy), starts, cols

    def _depths(
        self, cols: np.ndarray, inside: np.ndarray, cos_p: float, sin_p: float, ox: float,
        oy: float,
    ) -> np.ndarray:  # fmt: skip
        """Each inside sample's depth δ: how far the object's surface lies below the undeformed
        pad there, along the pad's normal — the distance from the sample along −n (into the
        finger) to where that line leaves the object (:meth:`Outline.exit_distance`). The
        foundation's rubber is compressed along the normal, so this, not the distance to the
        nearest surface (−sdf), is its compression: the two agree for a shallow contact of
        nearly parallel surfaces, but a thin object's end pushed into the pad sinks by its
        whole protrusion, which −sdf caps at the object's half thickness."""
        if not len(inside):
            return np.zeros(0)
        # (point, normal) → object frame, p = Rᵀ·(point − c) and d = −Rᵀ·n, as one product
        # with the columns (see _local_columns); rows (px, py, dx, dy)
        self._to_object.put(_OBJECT_ENTRIES, (cos_p, sin_p, -ox, -sin_p, cos_p, -oy,
                                              -cos_p, -sin_p, sin_p, -cos_p))  # fmt: skip
        pd = self._to_object @ cols.take(inside, axis=0).T  # take: cols[inside], cheaper
        return self.outline.exit_rows(pd)

    def _pulls(self) -> dict[int, _Pull]:
        """Each anchored contact's spring at the current pose, for :meth:`_evaluate`: its
        object point (object frame), its pad point moved into frame 0, its elastic stretch."""
        pulls = {}
        for j, anchor in self.state.anchors.items():
            o, ex, ey = self._frame_rows[j]
            a, b = anchor.local_point
            sy, sz = o[0] + a * ex[0] + b * ey[0], o[1] + a * ex[1] + b * ey[1]
            pulls[j] = (*anchor.obj_point, sy, sz, anchor.u)
        return pulls

    def _pressure(self, compression: np.ndarray, top: float | None = None) -> np.ndarray:
        """Contact pressure (N/mm²) for a local compression (mm): pad and object in series up
        to the knee where the pad bottoms out on its backing, far stiffer beyond. ``top``: the
        largest compression, if known (below the knee the law is linear)."""
        if top is not None and top <= self.knee:
            return self.k * compression
        soft = self.k * np.minimum(compression, self.knee)
        p: np.ndarray = soft + self.k_bottomed * np.maximum(compression - self.knee, 0.0)
        return p

    def _yield(
        self, overlap: np.ndarray, wds: float, deepest: float, j: int = -1,
        values: list[float] | None = None,
    ) -> float:  # fmt: skip
        """How far the finger backs off along the pad normal: the root e of
        h(e) = k_f·e − Σ p(δ − e)·w·ds (finger structure and servo, in series with the contact).

        h is piecewise linear, increasing and concave, so Newton's method lands on the root
        exactly once it reaches the root's segment. From above the root, one step lands at or
        below it (concavity); from below it climbs. It starts from surface j's last root.
        ``values``: the overlaps as plain floats, if at hand.
        """
        kf, k, kb, knee = self.cfg.finger_stiffness_n_per_mm, self.k, self.k_bottomed, self.knee
        e = min(self._e_hint.get(j, 0.0), deepest)
        # Below the knee the law is linear. Its root is the root of h when no sample bottoms
        # out there: a stiffer law beyond the knee only pushes the root further up.
        values = overlap.tolist() if values is None else values
        e_lin = self._yield_linear(values, wds * k, kf, e)
        if deepest - e_lin <= knee:
            self._e_hint[j] = e_lin
            return e_lin if e_lin > 1e-12 else 0.0
        e = max(e, e_lin)
        for _ in range(50):
            c = overlap - e if e else overlap
            act = c[c > 0.0]
            hard = act[act > knee]
            # Σ p = k·Σ min(c, knee) + kb·Σ max(c − knee, 0), over the active samples
            beyond = float(hard.sum()) - knee * hard.size if hard.size else 0.0
            force = wds * (k * (float(act.sum()) - beyond) + kb * beyond)
            slope = kf + wds * (k * (act.size - hard.size) + kb * hard.size)
            step = (force - kf * e) / slope
            if abs(step) <= 1e-12:
                break
            e = max(e + step, 0.0)
        self._e_hint[j] = e
        return e

    @staticmethod
    def _yield_linear(overlap: list[float], kw: float, kf: float, e: float) -> float:
        """:meth:`_yield` when no sample bottoms out: with the m samples deeper than e in
        contact the root is e_m = kw·Σ_m δ / (kf + kw·m), the root of h once those m are the
        ones that stay in contact. Newton's steps are these e_m; a step that keeps the set of
        samples in contact has landed (the sets are nested, so equal counts mean equal sets).
        Plain floats: a contact's few dozen samples are too few for numpy to pay off."""
        act = [d for d in overlap if d > e]
        for _ in range(len(overlap) + 2):
            e = kw * sum(act) / (kf + kw * len(act))
            nxt = [d for d in overlap if d > e]
            if len(nxt) == len(act):
                return e
            act = nxt
        return e  # not reached: each step from below the root drops a sample from contact

    # --- stepping -----------------------------------------------------------------------------

    def step(self, pose: HandPose) -> None:
        """Move the fingers to ``pose`` (in substeps no larger than max_joint_step_deg)."""
        cur = self.hand_pose
        delta = max(abs(pose.phi2 - cur.phi2), abs(pose.phi3 - cur.phi3),
                    abs(pose.phi4 - cur.phi4), abs(pose.phi5 - cur.phi5))  # fmt: skip
        if delta == 0.0 and not self.state.held_by_fixture:
            return  # quasi-static: nothing moved, nothing changes
        # (less a hair: 0.5° in radians and back is 0.5000000000000001°, which is not 3 substeps)
        n = max(1, math.ceil(math.degrees(delta) / self.cfg.max_joint_step_deg - 1e-9))
        for i in range(1, n + 1):
            f = i / n
            self._substep(HandPose(
                cur.phi2 + f * (pose.phi2 - cur.phi2), cur.phi3 + f * (pose.phi3 - cur.phi3),
                cur.phi4 + f * (pose.phi4 - cur.phi4), cur.phi5 + f * (pose.phi5 - cur.phi5),
            ))  # fmt: skip

    def _substep(self, pose: HandPose, halvings: int = 0) -> None:
        prev = self.hand_pose
        dq = (pose.phi2 - prev.phi2, pose.phi3 - prev.phi3, pose.phi4 - prev.phi4,
              pose.phi5 - prev.phi5)  # fmt: skip
        self.hand_pose = pose
        st = self.state
        world = self._world_samples(pose)
        if st.dropped:
            self._last = _Eval(_ZERO3, {}, {})
            return
        if st.held_by_fixture:
            ev = self._evaluate(st.pose.tolist(), world)
            n1 = ev.contacts.get(DISTAL1, (None, None, 0.0))[2]
            n2 = ev.contacts.get(DISTAL2, (None, None, 0.0))[2]
            squeeze = min(n1, n2)
            gripped = squeeze > max(self.cfg.release_force_n, 0.0)
            # A person places the object only where the fingers leave room for it, and pulls
            # it back if a finger sweeps through it before the grasp; once both distal pads
            # press it, it is the grasp's (a heavy object's grip grows deeper than that)
            limit = self.cfg.fixture_max_overlap_mm if st.present else 0.0
            st.present = ev.max_depth <= limit or (st.present and gripped)
            if not st.present:
                self._last = _Eval(_ZERO3, {}, {})
                return
            self._last = ev
            if gripped:
                self._fixture_grip(ev, world, squeeze)
            return
        if self._solve(world, dq):
            return
        if halvings >= MAX_HALVINGS and self._solve(world, dq, loose=True):
            return
        self._halve_or_drop(prev, pose, halvings)

    def _fixture_grip(self, ev: _Eval, world: _World, squeeze: float) -> None:
        """Both distal pads press the object in the fixture. The person lets go once the fingers
        hold it (a balance with every contact sticking: not two corners touched lightly, nor a
        grip its weight slides through), or once their squeeze has not grown for
        :data:`FIXTURE_PATIENCE_S` (they stopped closing on it): the object then stays, or
        falls, on its own."""
        st = self.state
        if squeeze > st.squeeze * FIXTURE_GROWTH:
            st.squeeze, st.squeeze_t = squeeze, self.clock
        waited = self.clock - st.squeeze_t >= FIXTURE_PATIENCE_S
        kept = (st.pose, st.psi_min, st.psi_max, st.slips, st.slip_distance_mm, st.grip_peak_n)
        st.held_by_fixture = False
        self._anchor(ev, st.pose, carry=False)
        if self._solve(world, None) and (waited or not st.slipping):
            return
        if waited:
            self._drop()
            return
        st.pose, st.psi_min, st.psi_max, st.slips, st.slip_distance_mm, st.grip_peak_n = (
            kept  # still held
        )
        st.held_by_fixture, st.anchors, st.slipping = True, {}, set()
        self._last = ev

    def _halve_or_drop(self, prev: HandPose, pose: HandPose, halvings: int) -> None:
        """No balance found at ``pose``: try the way from ``prev`` in halves before calling the
        object dropped. Newton's reach shrinks with the step (a warm start that lands beyond a
        kink of a thin object's few contact samples can lose its way), while an object that
        really slips out has no balance however small the steps."""
        if halvings >= MAX_HALVINGS:
            self._drop()
            return
        self.hand_pose = prev
        mid = HandPose((prev.phi2 + pose.phi2) / 2, (prev.phi3 + pose.phi3) / 2,
                       (prev.phi4 + pose.phi4) / 2, (prev.phi5 + pose.phi5) / 2)  # fmt: skip
        self._substep(mid, halvings + 1)
        self._substep(pose, halvings + 1)  # after a drop, this only moves the fingers on

    def _predict(self, dq: tuple[float, ...] | None) -> Vec3:
        """Newton's start: the last balance, moved on as it moved over the last substeps when
        the fingers keep moving the same way: linearly, or along the parabola through the last
        three balances (substeps of any lengths a2 : 1 : a1). A warm start saves iterations;
        the result is only ever checked against the residual's tolerance."""
        x0 = tuple(self.state.pose.tolist())
        if dq is None or not self._motion:
            return x0
        a1 = _along(dq, self._motion[-1][0])
        if a1 is None:
            return x0
        (y, z, psi), (dy, dz, dpsi) = x0, self._motion[-1][1]
        if len(self._motion) == 2:
            a2 = _along(self._motion[-1][0], self._motion[0][0])
            if a2 is not None and 0.5 <= a1 <= 2.0 and 0.5 <= a2 <= 2.0:
                curve = a1 * (a1 + 1.0) * a2 / (a2 + 1.0)  # Newton's divided differences
                my, mz, mpsi = self._motion[0][1]
                return (y + a1 * dy + curve * (dy - a2 * my), z + a1 * dz + curve * (dz - a2 * mz),
                        psi + a1 * dpsi + curve * (dpsi - a2 * mpsi))  # fmt: skip
        return y + a1 * dy, z + a1 * dz, psi + a1 * dpsi

    def _solve(self, world: _World, dq: tuple[float, ...] | None, loose: bool = False) -> bool:
        """Find the balancing pose: first with every contact sticking, then with the contacts
        whose friction would exceed μ·N sliding at μ·N (an active set, grown until consistent).
        False (nothing changed but the solver's caches) if there is none with both distal pads
        pressing. ``loose``: the last resort before a drop, a balance within
        :data:`LOOSE_BALANCE` of the grip is one (see there)."""
        st = self.state
        slip: dict[int, float] = {}
        x0 = self._predict(dq)
        pulls = self._pulls()
        for _ in range(len(self.surfaces) + 1):
            x, ev, converged = self._newton(x0, world, pulls, slip)
            if not converged:  # a kink (contact appearing, friction switching): MINPACK's hybrid
                x, ev, converged = self._hybrid(st.pose.copy(), world, pulls, slip)
            if not converged and loose:
                converged = _nearly_balanced(ev, x, st.pose, self._grain(ev))
            over = {
                j: math.copysign(1.0, c[3])
                for j, c in ev.contacts.items()
                if j not in slip and abs(c[3]) > self.mu * c[2]
            }
            if not converged or not over:
                break
            slip.update(over)
        n1 = ev.contacts[DISTAL1][2] if DISTAL1 in ev.contacts else 0.0
        n2 = ev.contacts[DISTAL2][2] if DISTAL2 in ev.contacts else 0.0
        if not converged or n1 <= 0.0 or n2 <= 0.0:
            return False
        self._anchor(ev, x, carry=True)
        if dq is not None:
            self._motion = [*self._motion[-1:], (dq, tuple((x - st.pose).tolist()))]
        else:
            self._motion = []
        st.pose = x
        st.psi_min = min(st.psi_min, float(x[2]))
        st.psi_max = max(st.psi_max, float(x[2]))
        st.grip_peak_n = max(st.grip_peak_n, (n1 + n2) / 2.0)
        self._last = ev
        return True

    def _grain(self, ev: _Eval) -> float:
        """The force the most loaded sample of a distal contact carries (N): how far the forces
        of two poses a sample's entering or leaving the contact tells apart can differ."""
        top = 0.0
        for j in (DISTAL1, DISTAL2):
            if j in ev.compressions and len(c := ev.compressions[j][2]):
                top = max(top, float(self._pressure(c).max()) * self._wds)
        return top

    def _drop(self) -> None:
        st = self.state
        st.dropped = True
        st.anchors.clear()
        self._last = _Eval(_ZERO3, {}, {})

    def _newton(
        self, x0: Vec3, world: _World, pulls: dict[int, _Pull], slip: dict[int, float]
    ) -> tuple[np.ndarray, _Eval, bool]:
        """Damped Newton on the 3 pose coordinates. The Jacobian (finite differences) is kept
        from step to step, corrected by Broyden's update after every move, and refreshed only
        when a move fails to lower the residual or progress is slow."""
        x = x0  # plain floats inside (see _solve3)
        ev = self._evaluate(x, world, pulls, slip)
        tol = 1e-6 + 1e-5 * sum(c[2] for c in ev.contacts.values())
        lim0, lim2 = 2.0, math.radians(3.0)  # a Newton move stays physical (mm, mm, rad)
        J, fresh = self._jacobian, False
        for _ in range(60):
            r = ev.residual
            if max(abs(r[0]), abs(r[1]), abs(r[2])) < tol:
                return np.array(x), ev, True
            if J is None:
                J, fresh = self._fd_jacobian(x, r, world, pulls, slip), True
            dx = _solve3(J, r)
            scale = min(1.0, lim0 / (abs(dx[0]) + 1e-300), lim0 / (abs(dx[1]) + 1e-300),
                        lim2 / (abs(dx[2]) + 1e-300))  # fmt: skip
            dx = (dx[0] * scale, dx[1] * scale, dx[2] * scale)
            base, step = _norm3(r), 1.0
            xa, xb, xc = x
            while step > 1e-3:
                x_c = (xa + step * dx[0], xb + step * dx[1], xc + step * dx[2])
                ev_c = self._evaluate(x_c, world, pulls, slip)
                r_c = ev_c.residual
                if _norm3(r_c) < base:
                    x, ev = x_c, ev_c
                    break
                step /= 2
            else:
                if fresh:
                    return np.array(x), ev, False
                J = None  # stale Jacobian: refresh and try again
                continue
            # Broyden's rank-one update: the secant of this move corrects J for free
            s = (step * dx[0], step * dx[1], step * dx[2])
            J = _broyden(J, s, (r_c[0] - r[0], r_c[1] - r[1], r_c[2] - r[2]))
            self._jacobian = J
            if not fresh and _norm3(r_c) > 0.25 * base:
                J = None  # slow progress: the kept Jacobian is too far off
        return np.array(x), ev, max(abs(v) for v in ev.residual) < tol

    def _hybrid(
        self, x: np.ndarray, world: _World, pulls: dict[int, _Pull], slip: dict[int, float]
    ) -> tuple[np.ndarray, _Eval, bool]:
        """Powell's hybrid method (scipy) as the fallback of :meth:`_newton`."""
        from scipy import optimize  # (not at the top: see sdh2svc.sim.sensor.PadRaster)

        sol = optimize.root(
            lambda v: np.array(self._evaluate(v.tolist(), world, pulls, slip).residual), x,
            method="hybr", options={"xtol": 1e-12, "maxfev": 400},
        )  # fmt: skip
        ev = self._evaluate(sol.x.tolist(), world, pulls, slip)
        tol = 1e-6 + 1e-5 * sum(c[2] for c in ev.contacts.values())
        moved = np.abs(sol.x - x)
        sane = moved[0] < 5.0 and moved[1] < 5.0 and moved[2] < math.radians(10.0)
        return sol.x, ev, max(abs(v) for v in ev.residual) < tol and sane

    def _fd_jacobian(
        self, x: Vec3, r: Vec3, world: _World, pulls: dict[int, _Pull], slip: dict[int, float]
    ) -> Mat3:
        cols = []
        for k, h in enumerate((1e-4, 1e-4, 1e-5)):
            xk = list(x)
            xk[k] += h
            rk = self._evaluate(xk, world, pulls, slip).residual
            cols.append(((rk[0] - r[0]) / h, (rk[1] - r[1]) / h, (rk[2] - r[2]) / h))
        return tuple(zip(*cols, strict=True))

    def _anchor(self, ev: _Eval, x: np.ndarray, carry: bool) -> None:
        """Re-anchor every contact at its current centroid, keeping the elastic displacement."""
        st = self.state
        self._world_samples(self.hand_pose)  # the frames of this pose
        cy, cz, psi = x.tolist()
        cos_p, sin_p = math.cos(psi), math.sin(psi)
        anchors = {}
        for j, (centroid, _tan, _n, ft, u, _s, slipping) in ev.contacts.items():
            if slipping:  # the spring keeps only what the Coulomb force stretches
                u_el = -ft / self.cfg.tangential_stiffness_n_per_mm
                st.slips += 0 if j in st.slipping else 1  # count slip onsets, not steps
                st.slip_distance_mm += abs(u - u_el)
                u = u_el
            (oy, oz), (exy, exz), (eyy, eyz) = self._frame_rows[j]
            ry, rz = centroid[0] - oy, centroid[1] - oz
            local = (ry * exy + rz * exz, ry * eyy + rz * eyz)
            dy, dz = centroid[0] - cy, centroid[1] - cz  # into the object frame: Rᵀ·(p − c)
            obj = (cos_p * dy + sin_p * dz, cos_p * dz - sin_p * dy)
            anchors[j] = Anchor(obj, local, u if carry else 0.0)
        st.slipping = {j for j, cinfo in ev.contacts.items() if cinfo[6]}
        st.anchors = anchors

    # --- results ------------------------------------------------------------------------------

    @property
    def held(self) -> bool:
        return not self.state.dropped

    def pressures(self) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Surface index → (sample indices, pressure N/mm²) of the last step's contact samples
        (worked out from its compressions once asked, then kept)."""
        last = self._last
        if self._pressures is None or self._pressures[0] is not last:
            out = {}
            for j, (idx, start, c, top) in last.compressions.items():
                touching = c > 0.0
                out[j] = (idx[touching] - start, self._pressure(c[touching], top))
            self._pressures = (last, out)
        return self._pressures[1]

    def contacts(self) -> list[ContactTruth]:
        x = self.state.pose
        c, R = x[:2], rot(float(x[2]))
        out = []
        for j, (centroid, _t, N, ft, _u, s, slipping) in sorted(self._last.contacts.items()):
            obj = R.T @ (np.array(centroid) - c)
            out.append(ContactTruth(SURFACE_NAMES[j], centroid, s,
                                    (float(obj[0]), float(obj[1])), N, ft, slipping))  # fmt: skip
        return out

    def joint_torques_n_mm(self) -> dict[str, float]:
        """Torque the contacts put on each coupled joint (N·mm), from the last step's pressures,
        in joint coordinates: positive turns the joint towards larger angles (closing, for the
        proximal joints). Finger 1's joints turn clockwise in the y0z0 plane as their angles
        grow, Finger 2's (mirrored) counter-clockwise, hence the sign per finger."""
        self._world_samples(self.hand_pose)
        frames = self._frame_rows
        cached = self._torques
        if cached is not None and cached[0] is self._last and cached[1] == self._world_key:
            return dict(cached[2])  # same step, same pose: the same torques
        tau = {"phi2": 0.0, "phi3": 0.0, "phi4": 0.0, "phi5": 0.0}
        names = {Finger.ONE: ("phi2", "phi3"), Finger.TWO: ("phi4", "phi5")}
        for j, (fy, fz, pxn) in self._last.sums.items():
            finger = SURFACE_FINGER[j]
            if finger is None:
                continue
            prox_name, dist_name = names[finger]
            O = frames[j + 1][0] if j in (DISTAL1, DISTAL2) else frames[j][0]
            for name, origin in ((prox_name, O), (dist_name, frames[j][0])):
                if name == dist_name and j not in (DISTAL1, DISTAL2):
                    continue
                # moment about the joint of the force on the finger, −p·w·ds·n per sample
                oy, oz = float(origin[0]), float(origin[1])
                moment = -(pxn - (oy * fz - oz * fy))
                tau[name] += -moment if finger is Finger.ONE else moment
        self._torques = (self._last, self._world_key, dict(tau))
        return tau
