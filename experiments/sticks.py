"""Thesis §3.4.2 reproduced kinematically: the two-finger algorithm on sticks, as the thesis did it.

    python -m experiments.sticks [--out DIR]

The thesis simulated its two-finger algorithm (§3.4.1, steps 1–2f) on sticks of 98.46 mm (Figs 31,
32: k = 5 and k = 2), 62.038 and 119.405 mm (Figs 34, 33), with the hand model alone: the
contact points are the stick's two ends and stay where the grasp put them on the pads (S1, S2
computed once), Λ is the stick's length throughout, there is no sensor, no force, no physics and
no servo — each iteration starts from the configuration the previous one commanded.

One iteration (the project's pure model: :mod:`sdh2svc.model.kinematics`,
:mod:`sdh2svc.model.friction`): Finger 2 steps along its route φ4 − Δφ, φ5 + k·Δφ (eqs 3.11,
3.12); dσ = σ(Ac→Bd) − σ(Ac→Bc) (eq 3.13, sign typo fixed); σd = σ + λ·dσ (eq 3.14); Finger 1's
IK puts A on the circle of radius Λ around Bd at inclination σd; the configuration is commanded
if both fingers are within their joint limits, Finger 1 reaches Ad, and ωA, ωB are inside
90° ± α; otherwise the rotation reverses (Δφ → −Δφ) and nothing is commanded that iteration.

Other readings of what the thesis's lost program may have done (eq 3.13's printed "+", σ's
angle convention, Finger 2's route, Finger 1's IK branch or a clipped IK, σ carried from the
command, a flat pad, the cone on ωA only, eq 3.9's exact "=", Δφ, λ, α) are options of
:class:`Params` (defaults: hand-model.md's reading) and are run and judged in the report's
*Other readings* section (``READINGS``).

Writes ``report.md`` (the plots next to the thesis's captions and statements, every figure
computed here) and the PNG plots into ``experiments/sticks/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import itertools
import math
import random
import sys
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from sdh2svc.config import Settings, load_config
from sdh2svc.control.rolling import Reversal
from sdh2svc.model.friction import inside_cone, omega
from sdh2svc.model.geometry import L_from_x3, pad_slope, pad_y3, virtual_joint, x3_from_L
from sdh2svc.model.kinematics import (
    Finger,
    HandPoints,
    HandPose,
    IKFailure,
    IKSolution,
    Point,
    contact_point,
    distal_joint,
    finger_ik,
    frame3_axes,
    ik_branches,
    pad_point,
    segment,
    wrap_angle,
)
from sdh2svc.model.observe import ModelContext

DEFAULT_OUT = Path(__file__).parent / "sticks"

# thesis Table 8 (Δφ, λ, α) and §3.4.2 (k = 5: Fig 31, k = 2: Fig 32)
DELTA_PHI_DEG = 0.25
LAMBDA_GAIN = 5.0
ALPHA_DEG = 22.0
KS = (5.0, 2.0)
MAIN_LENGTH = 98.46  # Figs 31, 32
LENGTHS = (98.46, 62.038, 73.8, 119.405)  # Figs 31–32, 34, §3.3.2, 33
FIGURE = {98.46: "Figs 31, 32", 62.038: "Fig 34", 73.8: "— (§3.3.2's stick)", 119.405: "Fig 33"}
REVERSALS = 6  # the project's 3 strokes (rolling.cycles): stop at the 6th reversal
MAX_ITERATIONS = 5000

# The unintended reversal (thesis Fig 31.d): within a half stroke, σ runs against the half
# stroke's own direction for at least BACKWARD_ITERATIONS consecutive commanded iterations and
# by at least BACKWARD_DEG in all. The kinematic model has no noise: its only quanta are the
# iteration and the route's step. One iteration is a sample, not "a period of time", so a
# period is two or more; and a backward run is counted only when it undoes at least one step of
# Finger 2's proximal joint, Δφ = 0.25°, the smallest angle the route commands. A stall ("the
# inclination only remains constant for some time", Fig 32.d) is the same span of iterations
# over which σ moves by less than that step.
BACKWARD_ITERATIONS = 2
BACKWARD_DEG = DELTA_PHI_DEG


# --- the set-up -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class PadContact:
    """A fixed contact point on a distal pad: frame-3 coordinates, virtual link, L and S."""

    x3: float
    y3: float
    r: float
    theta: float
    L: float  # curved distance from the pad's base I, mm
    S: float  # the tactile centroid height that reports this point (the calibration inverted)


@dataclass(frozen=True, slots=True)
class Grasp:
    """The initial configuration: the stick between the fingertips, the fingers in a mirror pose."""

    length: float
    height: float  # z0 of the stick
    pose: HandPose
    contact1: PadContact  # A on Finger 1's pad
    contact2: PadContact  # B on Finger 2's pad


def _bisect(f: Callable[[float], float], lo: float, hi: float, n: int = 60) -> float | None:
    """A root of f in [lo, hi] by bisection, None without a sign change."""
    flo = f(lo)
    if flo * f(hi) > 0.0:
        return None
    for _ in range(n):
        mid = 0.5 * (lo + hi)
        fm = f(mid)
        if flo * fm <= 0.0:
            hi = mid
        else:
            lo, flo = mid, fm
    return 0.5 * (lo + hi)


def pad_contact(x3: float, ctx: ModelContext) -> PadContact:
    """The pad point at x3, with the S that the tactile calibration maps to it."""
    pad = ctx.geom.pad
    y3 = pad_y3(x3, pad)
    r, theta = virtual_joint(x3, y3)
    L = L_from_x3(x3, pad)
    s_range = (ctx.distal.rows - 1) * ctx.pitch_mm
    dist = ctx.calib.distance
    S = _bisect(lambda s: dist.L_from_S(s, s_range, pad) - L, -s_range, 2.0 * s_range)
    return PadContact(x3, y3, r, theta, L, math.nan if S is None else S)


def initial_grasp(length: float, ctx: ModelContext, height: float, psi: float) -> Grasp:
    """The fingers close from the pre-shape as the project's grasp closes them — proximal +step,
    distal −step, so ψ = φ2 + φ3 keeps its pre-shape value — on a stick held level at ``height``
    midway between the proximal joints, until each pad's surface reaches the stick's end."""
    pad, geom = ctx.geom.pad, ctx.geom
    end_y = geom.base_offset_mm / 2 - length / 2  # A's y0 (B's is mirrored)

    def surface(phi2: float, x3: float) -> Point:
        return pad_point(Finger.ONE, phi2, psi - phi2, x3, pad_y3(x3, pad), geom)

    def x3_at_height(phi2: float) -> float | None:
        return _bisect(
            lambda x: surface(phi2, x).z - height, pad.flat_start_x3_mm, pad.tip_end_x3_mm
        )

    def gap(phi2: float) -> float:
        x3 = x3_at_height(phi2)
        return math.nan if x3 is None else surface(phi2, x3).y - end_y

    # the proximal angles at which some pad point is level with the stick, open to closed
    grid = [math.radians(a) for a in range(-90, 91)]
    level = [a for a in grid if x3_at_height(a) is not None]
    phi2 = None
    for a, b in itertools.pairwise(level):
        if gap(a) <= 0.0 <= gap(b):
            phi2 = _bisect(gap, a, b)
            break
    if phi2 is None:
        raise ValueError(
            f"a {length} mm stick at z0 = {height} mm cannot be grasped from ψ = "
            f"{math.degrees(psi):.1f}°"
        )
    x3 = x3_at_height(phi2)
    assert x3 is not None
    c = pad_contact(x3, ctx)
    return Grasp(length, height, HandPose(phi2, psi - phi2, phi2, psi - phi2), c, c)


def grasp_from_settings(length: float, cfg: Settings) -> Grasp:
    """The grasp with the project's pre-shape ψ and the simulator's object height."""
    pre = cfg.run.preshape_deg
    psi = math.radians(pre[cfg.axes.phi2] + pre[cfg.axes.phi3])
    return initial_grasp(length, cfg.model_context(), cfg.sim.object_height_mm, psi)


def mirror_grasp(length: float, ctx: ModelContext, x3: float, psi: float) -> Grasp | None:
    """A mirror grasp (σ = 0) with the contact at x3 on both pads and Finger 1's ψ given, or None
    when no proximal angle within the joint limits puts A at the stick's end."""
    geom = ctx.geom
    c = pad_contact(x3, ctx)
    end_y = geom.base_offset_mm / 2 - length / 2
    lim = ctx.limits1

    def gap(phi2: float) -> float:
        return contact_point(Finger.ONE, phi2, psi - phi2, c.r, c.theta, geom).y - end_y

    phi2 = _bisect(gap, lim.proximal_min, lim.proximal_max)
    if phi2 is None or not lim.contains(phi2, psi - phi2):
        return None
    A = contact_point(Finger.ONE, phi2, psi - phi2, c.r, c.theta, geom)
    return Grasp(length, A.z, HandPose(phi2, psi - phi2, phi2, psi - phi2), c, c)


# --- the kinematic run ------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Params:
    """One run's parameters. Every field after ``max_iterations`` is a reading of what the
    thesis's own program may have done (its code is lost); the defaults are hand-model.md's
    reading, and each other value is tried in the report's *Other readings* section."""

    k: float
    delta_phi: float = math.radians(DELTA_PHI_DEG)
    lambda_gain: float = LAMBDA_GAIN
    alpha: float = math.radians(ALPHA_DEG)
    reversals: int = REVERSALS
    max_iterations: int = MAX_ITERATIONS
    printed_eq313: bool = False  # eq 3.13 as printed, σ(Ac→Bd) + σ(Ac→Bc): a check only
    # Ad by the thesis's quadratic and root test (eqs 3.6–3.9) comparing inclinations within this
    # tolerance, instead of the closed form: a check only. ``root_last_wins``: when both roots
    # pass, the one tried last is kept (a loop over i = 1, 2 without a break). ``root_nomatch``:
    # what Ad is when neither passes — "closed" (the closed form), "last_tried" / "first_tried"
    # (the loop's variable keeps the root tried last, z02, or first, z01), "stale" (Az keeps its
    # previous value, Ay by eq 3.8).
    root_tol_deg: float | None = None
    root_last_wins: bool = True
    root_nomatch: str = "closed"
    # σ as the program measured it: "atan2" (A→B, hand-model §6), "atan" (eq 3.3 literally,
    # values in (−90°, 90°)), "atan2_BA" (from B to A, in (−180°, 180°]: its cut is at σ = 0)
    sigma_from: str = "atan2"
    # Finger 2's route: "thesis" (φ4 − Δφ, φ5 + kΔφ), "k_proximal" (φ4 − kΔφ, φ5 + Δφ),
    # "same_sense" (φ4 − Δφ, φ5 − kΔφ: φ5 counted the other way)
    route: str = "thesis"
    first_direction: int = 1  # +1: the first half stroke has Δφ > 0
    # Finger 1's IK: "nearest" (the branch nearest to now), "branch+" (φ2 = β − o always),
    # "branch-" (φ2 = β + o always); ``ik_clip``: acos's argument clipped to [−1, 1] (MATLAB's
    # real(acos)), so an unreachable Ad stretches the finger towards it instead of reversing
    ik: str = "nearest"
    ik_clip: bool = False
    # the next iteration's Ac and σc: "reached" (FK of the commanded angles) or "commanded"
    # (Ad and σd carried over, as a program that never re-measures would)
    sigma_source: str = "reached"
    flat_pad: bool = False  # ω against the distal link's axis, not the pad profile's tangent
    cone_A_only: bool = False  # the cone test on ωA only


@dataclass(frozen=True, slots=True)
class Iteration:
    """One iteration: the configuration it starts from, and what it commanded or why it reversed.

    ``direction`` is the sign of this iteration's Δφ (+1: Finger 2's proximal opens, clockwise
    per the thesis); ``target`` is None when it reversed (``reversal`` says why).
    """

    i: int
    direction: int
    pose: HandPose
    points: HandPoints
    Lambda: float
    sigma: float
    omega_A: float
    omega_B: float
    target: HandPose | None
    reversal: Reversal | None
    sigma_d: float | None = None
    omega_A_d: float | None = None
    omega_B_d: float | None = None


@dataclass
class Run:
    grasp: Grasp
    params: Params
    iterations: list[Iteration] = field(default_factory=list)
    end: str = "max_iterations"  # "done" (REVERSALS reached), "stuck", "max_iterations"

    @property
    def reversals(self) -> list[Iteration]:
        return [it for it in self.iterations if it.reversal is not None]


def _omega(
    finger: Finger, psi: float, x3: float, here: Point, other: Point, ctx: ModelContext, flat: bool
) -> float:
    """ω at ``here``: against the pad's tangent (hand-model §6) or, ``flat``, the distal link's
    axis ex3 (a pad without its arc)."""
    if not flat:
        return omega(finger, psi, x3, here, other, ctx.geom.pad)
    t = frame3_axes(finger, psi)[0]
    vy, vz = other.y - here.y, other.z - here.z
    return math.acos(max(-1.0, min(1.0, (t.y * vy + t.z * vz) / math.hypot(vy, vz))))


def _measure(
    pose: HandPose, g: Grasp, ctx: ModelContext, flat: bool = False
) -> tuple[HandPoints, float, float, float, float]:
    geom = ctx.geom
    c1, c2 = g.contact1, g.contact2
    A = contact_point(Finger.ONE, pose.phi2, pose.phi3, c1.r, c1.theta, geom)
    B = contact_point(Finger.TWO, pose.phi4, pose.phi5, c2.r, c2.theta, geom)
    pts = HandPoints(
        A, B, distal_joint(Finger.ONE, pose.phi2, geom), distal_joint(Finger.TWO, pose.phi4, geom)
    )
    lam, sigma = segment(A, B)
    wa = _omega(Finger.ONE, pose.phi2 + pose.phi3, c1.x3, A, B, ctx, flat)
    wb = _omega(Finger.TWO, pose.phi4 + pose.phi5, c2.x3, B, A, ctx, flat)
    return pts, lam, sigma, wa, wb


def inclination(A: Point, B: Point, how: str = "atan2") -> float:
    """σ of AB as a program measures it (``Params.sigma_from``). atan's branch cut is where
    By = Ay (σ = ±90°); atan2's from B to A is where the stick is level (σ_BA = ±180°)."""
    dy, dz = B.y - A.y, B.z - A.z
    if how == "atan":
        return math.atan(dz / dy)
    if how == "atan2_BA":
        return math.atan2(-dz, -dy)
    return math.atan2(dz, dy)


def thesis_roots(B: Point, lam: float, sigma_d: float) -> tuple[Point, Point]:
    """A1 and A3 of eqs 3.6–3.8: the roots z01, z02 of the circle of radius Λ around B, each with
    its y by eq 3.8 (the left semicircle)."""
    t2 = math.tan(sigma_d) ** 2
    root = math.sqrt(lam**2 * t2 + lam**2 * t2**2)
    zs = ((B.z + B.z * t2 - root) / (1 + t2), (B.z + B.z * t2 + root) / (1 + t2))
    return tuple(Point(B.y - math.sqrt(max(lam**2 - (z - B.z) ** 2, 0.0)), z) for z in zs)  # type: ignore[return-value]


def thesis_root(B: Point, lam: float, sigma_d: float, tol: float, last_wins: bool) -> Point | None:
    """Ad by eqs 3.6–3.9: the root whose inclination is σd within ``tol`` (rad), or None."""
    chosen: Point | None = None
    for A in thesis_roots(B, lam, sigma_d):
        if abs(math.atan((B.z - A.z) / (B.y - A.y)) - sigma_d) <= tol:
            chosen = A
            if not last_wins:
                break
    return chosen


def _desired_A(B: Point, lam: float, sigma_d: float, p: Params, az_var: float) -> Point:
    """Ad for σd as the program measures σ; ``az_var``: the z of the Ad computed last (what a
    root test that matches neither root leaves in its variable, ``root_nomatch="stale"``)."""
    u = -1.0 if p.sigma_from == "atan2_BA" else 1.0  # σ_BA points from B to A
    closed = Point(B.y - u * lam * math.cos(sigma_d), B.z - u * lam * math.sin(sigma_d))
    if p.root_tol_deg is None:
        return closed
    got = thesis_root(B, lam, sigma_d, math.radians(p.root_tol_deg), p.root_last_wins)
    if got is not None or p.root_nomatch == "closed":
        return got or closed
    if p.root_nomatch in ("last_tried", "first_tried"):
        return thesis_roots(B, lam, sigma_d)[p.root_nomatch == "last_tried"]
    return Point(B.y - math.sqrt(max(lam**2 - (az_var - B.z) ** 2, 0.0)), az_var)  # stale


def _route(pose: HandPose, dphi: float, p: Params) -> tuple[float, float]:
    """Finger 2's next φ4, φ5 (eqs 3.11–3.12 and the ``Params.route`` readings)."""
    if p.route == "k_proximal":
        return pose.phi4 - p.k * dphi, pose.phi5 + dphi
    if p.route == "same_sense":
        return pose.phi4 - dphi, pose.phi5 - p.k * dphi
    return pose.phi4 - dphi, pose.phi5 + p.k * dphi


def _ik1(
    A_d: Point, c1: PadContact, pose: HandPose, p: Params, ctx: ModelContext
) -> tuple[float, float] | Reversal:
    """Finger 1's angles for Ad (``Params.ik``, ``Params.ik_clip``), or why the route reverses."""
    geom, lim = ctx.geom, ctx.limits1
    if p.ik == "nearest" and not p.ik_clip:
        ik = finger_ik(Finger.ONE, A_d, c1.r, c1.theta, (pose.phi2, pose.phi3), geom, lim)
        if ik.solution is None:
            ws = ik.failure is IKFailure.JOINT_LIMITS
            return Reversal.WORKSPACE if ws else Reversal.IK_UNREACHABLE
        return ik.solution.proximal, ik.solution.distal
    if p.ik_clip:  # acos's argument clipped: the nearest reachable elbow angle
        l1, d = geom.proximal_length_mm, math.hypot(A_d.y, A_d.z)
        o = math.acos(max(-1.0, min(1.0, (l1 * l1 + d * d - c1.r**2) / (2.0 * l1 * d))))
        beta = math.atan2(A_d.y, A_d.z)
        sols = []
        for branch, prox in ((1, beta - o), (-1, beta + o)):
            C = Point(l1 * math.sin(prox), l1 * math.cos(prox))
            dist = wrap_angle(math.atan2(-(A_d.z - C.z), A_d.y - C.y) - prox + c1.theta)
            sols.append(IKSolution(wrap_angle(prox), dist, branch))
    else:
        sols = list(ik_branches(Finger.ONE, A_d, c1.r, c1.theta, geom))
        if not sols:
            return Reversal.IK_UNREACHABLE
    if p.ik != "nearest":
        sols = [s for s in sols if s.branch == (1 if p.ik == "branch+" else -1)] or sols[:1]
    valid = [s for s in sols if lim.contains(s.proximal, s.distal)]
    if not valid:
        return Reversal.WORKSPACE
    best = min(
        valid,
        key=lambda s: (
            abs(wrap_angle(s.proximal - pose.phi2)) + abs(wrap_angle(s.distal - pose.phi3))
        ),
    )
    return best.proximal, best.distal


def simulate(g: Grasp, p: Params, ctx: ModelContext) -> Run:
    """The two-finger algorithm of §3.4.1 on a stick with fixed contacts and constant Λ = length."""
    geom = ctx.geom
    c2, lam = g.contact2, g.length
    run = Run(g, p)
    pose, direction, last_reversed = g.pose, p.first_direction, False
    carried: tuple[Point, float] | None = None  # Ad, σd of the last command (sigma_source)
    az_var = _measure(pose, g, ctx)[0].A.z
    for i in range(p.max_iterations):
        pts, Lambda, sigma, wa, wb = _measure(pose, g, ctx, p.flat_pad)
        A_c = pts.A if carried is None else carried[0]
        sigma_c = inclination(A_c, pts.B, p.sigma_from) if carried is None else carried[1]
        dphi = direction * p.delta_phi
        phi4d, phi5d = _route(pose, dphi, p)  # eqs 3.11, 3.12
        reason: Reversal | None = None
        target = sigma_d = wa_d = wb_d = None
        if not ctx.limits2.contains(phi4d, phi5d):
            reason = Reversal.WORKSPACE
        else:
            B_d = contact_point(Finger.TWO, phi4d, phi5d, c2.r, c2.theta, geom)
            d_sigma = inclination(A_c, B_d, p.sigma_from) - sigma_c  # eq 3.13, sign typo fixed
            if p.printed_eq313:
                d_sigma += 2.0 * sigma_c
            sigma_d = sigma_c + p.lambda_gain * d_sigma  # eq 3.14
            A_d = _desired_A(B_d, lam, sigma_d, p, az_var)
            az_var = A_d.z
            ik = _ik1(A_d, g.contact1, pose, p, ctx)
            if isinstance(ik, Reversal):
                reason = ik
            else:
                cand = HandPose(ik[0], ik[1], phi4d, phi5d)
                _, _, _, wa_d, wb_d = _measure(cand, g, ctx, p.flat_pad)
                if not inside_cone(wa_d, p.alpha):
                    reason = Reversal.CONE_A
                elif not p.cone_A_only and not inside_cone(wb_d, p.alpha):
                    reason = Reversal.CONE_B
                else:
                    target = cand
        run.iterations.append(
            Iteration(
                i, direction, pose, pts, Lambda, sigma, wa, wb, target, reason, sigma_d, wa_d, wb_d
            )
        )
        if target is not None:
            pose, last_reversed = target, False  # no servo: the next iteration starts there
            if p.sigma_source == "commanded":
                assert sigma_d is not None
                carried = (A_d, sigma_d)
            continue
        if last_reversed:
            run.end = "stuck"  # both directions refused
            break
        direction, last_reversed = -direction, True
        if len(run.reversals) >= p.reversals:
            run.end = "done"
            break
    return run


# --- analysis ---------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Stretch:
    """Consecutive commanded iterations [first, last] of one half stroke, and σ's change over them
    along the half stroke's direction (negative: against it), degrees."""

    first: int
    last: int
    sigma_from_deg: float
    along_deg: float

    @property
    def iterations(self) -> int:
        return self.last - self.first + 1


def half_strokes(run: Run) -> list[list[Iteration]]:
    """The commanded iterations between two reversals (the reversal iterations left out)."""
    out: list[list[Iteration]] = [[]]
    for it in run.iterations:
        if it.reversal is None:
            out[-1].append(it)
        elif out[-1]:
            out.append([])
    return [h for h in out if h]


def intended(it: Iteration) -> int:
    """The sign σ should move in: Δφ > 0 turns clockwise (σ decreasing), Δφ < 0 anticlockwise."""
    return -it.direction


def sigma_steps(run: Run) -> list[tuple[Iteration, float]]:
    """Each commanded iteration with σ's change it made along its intended direction, degrees.

    A route read otherwise than eqs 3.11–3.12 (``Params.route``) whose Δφ > 0 turns the stick
    anticlockwise from the grasp has that sense taken as the intended one: a sign convention,
    not a reversal."""
    its, out = run.iterations, []
    for a, b in itertools.pairwise(its):
        if a.target is not None:
            out.append((a, math.degrees(b.sigma - a.sigma) * intended(a)))
    if run.params.route != "thesis" and out and out[0][1] < 0.0:
        out = [(a, -d) for a, d in out]
    return out


def _runs(
    steps: Sequence[tuple[Iteration, float]], pred: Callable[[float], bool]
) -> list[list[tuple[Iteration, float]]]:
    """Maximal runs of consecutive commanded iterations of one half stroke satisfying pred."""
    out: list[list[tuple[Iteration, float]]] = []
    cur: list[tuple[Iteration, float]] = []
    for s in steps:
        joined = cur and s[0].i == cur[-1][0].i + 1 and s[0].direction == cur[-1][0].direction
        if pred(s[1]) and (not cur or joined):
            cur.append(s)
            continue
        if cur:
            out.append(cur)
        cur = [s] if pred(s[1]) else []
    if cur:
        out.append(cur)
    return out


def _stretch(r: list[tuple[Iteration, float]]) -> Stretch:
    return Stretch(r[0][0].i, r[-1][0].i, math.degrees(r[0][0].sigma), sum(d for _, d in r))


def backward_stretches(
    run: Run, n: int = BACKWARD_ITERATIONS, x_deg: float = BACKWARD_DEG
) -> list[Stretch]:
    """Unintended reversals: σ against the half stroke's direction ≥ n iterations and ≥ x_deg."""
    runs = _runs(sigma_steps(run), lambda d: d < 0.0)
    return [s for s in map(_stretch, runs) if s.iterations >= n and -s.along_deg >= x_deg]


def stalls(run: Run, n: int = BACKWARD_ITERATIONS, x_deg: float = BACKWARD_DEG) -> list[Stretch]:
    """σ constant for a while: ≥ n consecutive commanded iterations of one half stroke over which
    σ moves by less than x_deg (a window sliding over each half stroke; overlaps merged)."""
    steps = sigma_steps(run)
    flagged: set[int] = set()
    for j in range(len(steps) - n + 1):
        win = steps[j : j + n]
        one = all(
            b[0].i == a[0].i + 1 and b[0].direction == a[0].direction
            for a, b in itertools.pairwise(win)
        )
        if one and abs(sum(d for _, d in win)) < x_deg:
            flagged.update(s[0].i for s in win)
    picked = [s for s in steps if s[0].i in flagged]
    return [_stretch(r) for r in _runs(picked, lambda d: True)]


@dataclass(frozen=True, slots=True)
class Summary:
    length: float
    k: float
    iterations: int
    end: str
    reversals: list[tuple[int, str, float]]  # iteration, reason, σ (deg)
    sigma_deg: tuple[float, float]
    omega_A_deg: tuple[float, float]
    omega_B_deg: tuple[float, float]
    phi_deg: dict[str, tuple[float, float]]
    lambda_error_mm: float  # max | |AB| − length |
    step_deg: tuple[float, float, float]  # σ per commanded iteration, along: min, median, max
    backward_steps: int  # commanded iterations that moved σ against the direction at all
    backward: list[Stretch]
    stalls: list[Stretch]


def summarise(run: Run) -> Summary:
    its = run.iterations
    deg = math.degrees

    def rng(vals: Sequence[float]) -> tuple[float, float]:
        return deg(min(vals)), deg(max(vals))

    steps = sorted(d for _, d in sigma_steps(run))
    med = steps[len(steps) // 2] if steps else math.nan
    names = ("phi2", "phi3", "phi4", "phi5")
    return Summary(
        length=run.grasp.length,
        k=run.params.k,
        iterations=len(its),
        end=run.end,
        reversals=[(it.i, str(it.reversal), deg(it.sigma)) for it in run.reversals],
        sigma_deg=rng([it.sigma for it in its]),
        omega_A_deg=rng([it.omega_A for it in its]),
        omega_B_deg=rng([it.omega_B for it in its]),
        phi_deg={n: rng([getattr(it.pose, n) for it in its]) for n in names},
        lambda_error_mm=max(abs(it.Lambda - run.grasp.length) for it in its),
        step_deg=(steps[0], med, steps[-1]) if steps else (math.nan,) * 3,
        backward_steps=sum(1 for d in steps if d < 0.0),
        backward=backward_stretches(run),
        stalls=stalls(run),
    )


def route_rate(it: Iteration, g: Grasp, p: Params, ctx: ModelContext) -> float:
    """dσ of Finger 2's route alone, to first order (per radian of Δφ, intended direction > 0):

        Λ · dσ/dΔφ = −[l1 · sin(φ4 − σ) − (k − 1) · r2 · cos(φ4 + φ5 − θ2 − σ)]

    (the component of B's step normal to AB). It changes sign — the only way σ can stall or
    run backwards within a half stroke, λ merely scaling it — only where the two terms cancel."""
    l1, c2 = ctx.geom.proximal_length_mm, g.contact2
    a = it.pose.phi4 + it.pose.phi5 - c2.theta - it.sigma
    return -(l1 * math.sin(it.pose.phi4 - it.sigma) - (p.k - 1) * c2.r * math.cos(a)) / g.length


@dataclass(frozen=True, slots=True)
class FlaggedGrasp:
    """A scanned grasp with an unintended reversal or a stall (mm, degrees)."""

    S1: float
    S2: float
    psi1: float  # φ2 + φ3
    sigma0: float
    phi4: float
    omega_A0: float
    omega_B0: float
    sigma_span: float  # σ's whole range over the run
    backward: bool
    stall: bool
    at_sigma: float  # σ where the first flagged stretch begins


@dataclass(frozen=True, slots=True)
class ScanResult:
    length: float
    k: float
    kind: str  # "mirror" or "any"
    grasps: int  # admissible grasps run (within joint limits, both ω inside the cone)
    with_backward: int
    with_stall: int
    backward_steps: int  # over all of them
    min_rate_ratio: float  # the smallest σ step / the run's median step, over all of them
    flagged: list[FlaggedGrasp] = field(default_factory=list)


def _pad_grid(ctx: ModelContext, n: int) -> list[float]:
    """n contact points x3 spread over the pad, 0.5 mm from its ends."""
    pad = ctx.geom.pad
    lo, hi = pad.flat_start_x3_mm + 0.5, pad.tip_end_x3_mm - 0.5
    return [lo + (hi - lo) * i / (n - 1) for i in range(n)]


MIRROR_GRID = (12, 21)  # contact points over the pad, values of ψ
ANY_N_X3 = 7  # contact points over each pad
ANY_OFFSETS = (-15.0, -7.5, 0.0, 7.5, 15.0)  # the stick's centre from midway, mm
ANY_HEIGHTS = (100.0, 115.0, 130.0, 145.0)  # z0 of its centre, mm
ANY_SIGMAS_DEG = (-15.0, -10.0, -5.0, 0.0, 5.0, 10.0, 15.0)


def mirror_grasps(
    length: float, ctx: ModelContext, n_x3: int = MIRROR_GRID[0], n_psi: int = MIRROR_GRID[1]
) -> list[Grasp]:
    """Mirror grasps (σ = 0): contact points x3 over the pad × Finger 1's ψ in [−30°, 60°]."""
    out = []
    for x3 in _pad_grid(ctx, n_x3):
        for j in range(n_psi):
            g = mirror_grasp(length, ctx, x3, math.radians(-30.0 + 90.0 * j / (n_psi - 1)))
            if g is not None:
                out.append(g)
    return out


def any_grasps(
    length: float,
    ctx: ModelContext,
    n_x3: int = ANY_N_X3,
    offsets: Sequence[float] = ANY_OFFSETS,
    heights: Sequence[float] = ANY_HEIGHTS,
    sigmas_deg: Sequence[float] = ANY_SIGMAS_DEG,
) -> list[Grasp]:
    """Grasps that need not be mirror images: the stick's centre moved sideways by ``offsets``
    from midway between the proximal joints, at ``heights``, inclined by ``sigmas_deg``, with its
    ends at any two contact points of a grid on the two pads (S1 ≠ S2); each finger's angles by
    IK, the branch nearest to a half-closed pose."""
    geom, lim1, lim2 = ctx.geom, ctx.limits1, ctx.limits2
    near = (math.radians(-20.0), math.radians(20.0))
    grid = [pad_contact(x3, ctx) for x3 in _pad_grid(ctx, n_x3)]
    out = []
    for dy in offsets:
        for z in heights:
            for sd in sigmas_deg:
                s0 = math.radians(sd)
                cy, h = geom.base_offset_mm / 2 + dy, length / 2
                A = Point(cy - h * math.cos(s0), z - h * math.sin(s0))
                B = Point(cy + h * math.cos(s0), z + h * math.sin(s0))
                for c1 in grid:
                    ik1 = finger_ik(Finger.ONE, A, c1.r, c1.theta, near, geom, lim1).solution
                    if ik1 is None:
                        continue
                    for c2 in grid:
                        ik2 = finger_ik(Finger.TWO, B, c2.r, c2.theta, near, geom, lim2).solution
                        if ik2 is None:
                            continue
                        pose = HandPose(ik1.proximal, ik1.distal, ik2.proximal, ik2.distal)
                        out.append(Grasp(length, z, pose, c1, c2))
    return out


def scan_grasps(grasps: Sequence[Grasp], k: float, ctx: ModelContext, kind: str) -> ScanResult:
    """Run every grasp inside both cones (3 reversals each) and count what the detectors find."""
    alpha, deg = math.radians(ALPHA_DEG), math.degrees
    n = back = stall = steps = 0
    ratio = math.inf
    flagged: list[FlaggedGrasp] = []
    length = grasps[0].length if grasps else math.nan
    for g in grasps:
        _, _, sigma0, wa, wb = _measure(g.pose, g, ctx)
        if not (inside_cone(wa, alpha) and inside_cone(wb, alpha)):
            continue
        s = summarise(simulate(g, Params(k, reversals=3, max_iterations=2000), ctx))
        n += 1
        back += bool(s.backward)
        stall += bool(s.stalls)
        steps += s.backward_steps
        if s.step_deg[1] > 0:
            ratio = min(ratio, s.step_deg[0] / s.step_deg[1])
        if s.backward or s.stalls:
            p = g.pose
            first = min(s.backward + s.stalls, key=lambda x: x.first)
            flagged.append(FlaggedGrasp(
                g.contact1.S, g.contact2.S, deg(p.phi2 + p.phi3), deg(sigma0), deg(p.phi4),
                deg(wa), deg(wb), _span(s), bool(s.backward), bool(s.stalls),
                first.sigma_from_deg,
            ))  # fmt: skip
    return ScanResult(length, k, kind, n, back, stall, steps, ratio, flagged)


# --- plots ------------------------------------------------------------------------------------

RED, GREEN, BLUE, YELLOW = "#d62728", "#2ca02c", "#1f77b4", "#f2d64b"


def _extremes(run: Run) -> tuple[Iteration, Iteration, Iteration]:
    """The initial configuration and the two extremes: largest σ (anticlockwise, green) and
    smallest σ (clockwise, blue)."""
    its = run.iterations
    return its[0], max(its, key=lambda it: it.sigma), min(its, key=lambda it: it.sigma)


def workspace(g: Grasp, ctx: ModelContext, step_deg: float = 1.5) -> tuple[list[float], ...]:
    """Finger 1's reachable A for its contact point: every (φ2, φ3) within the joint limits."""
    lim, c = ctx.limits1, g.contact1
    ys, zs = [], []
    n2 = int(math.degrees(lim.proximal_max - lim.proximal_min) / step_deg)
    n3 = int(math.degrees(lim.distal_max - lim.distal_min) / step_deg)
    for i in range(n2 + 1):
        p2 = lim.proximal_min + (lim.proximal_max - lim.proximal_min) * i / n2
        for j in range(n3 + 1):
            p3 = lim.distal_min + (lim.distal_max - lim.distal_min) * j / n3
            A = contact_point(Finger.ONE, p2, p3, c.r, c.theta, ctx.geom)
            ys.append(A.y)
            zs.append(A.z)
    return ys, zs


def _draw_hand(
    ax: plt.Axes, it: Iteration, color: str, obj: bool, label: str, base_offset: float
) -> None:
    p, base, o2 = it.points, (0.0, 0.0), (base_offset, 0.0)  # O and O'
    for o, j, c in ((base, p.C, p.A), (o2, p.D, p.B)):
        ax.plot(
            [o[0], j.y, c.y],
            [o[1], j.z, c.z],
            "-o",
            color=color,
            lw=1.6,
            ms=3,
            label=label if o is base else None,
        )
    if obj:
        ax.plot([p.A.y, p.B.y], [p.A.z, p.B.z], "-", color=color, lw=4, alpha=0.55)


def plot_run(run: Run, ctx: ModelContext, path: Path, title: str) -> None:
    """The six panels of thesis Figs 31/32."""
    deg = math.degrees
    fig, axs = plt.subplots(2, 3, figsize=(16, 9.5))
    its = run.iterations
    xs = [it.i for it in its]
    start, ccw, cw = _extremes(run)
    wy, wz = workspace(run.grasp, ctx)
    rev = [it.i for it in run.reversals]
    confs = (
        (start, RED, "initial"),
        (ccw, GREEN, "extreme, σ max (anticlockwise)"),
        (cw, BLUE, "extreme, σ min (clockwise)"),
    )
    for ax, obj, name in ((axs[0, 0], False, "a"), (axs[0, 1], True, "b")):
        if not obj:
            ax.scatter(
                wy,
                wz,
                s=2,
                color=YELLOW,
                alpha=0.35,
                lw=0,
                rasterized=True,
                label="Finger 1's workspace for this contact",
            )
        for it, col, lab in confs:
            _draw_hand(ax, it, col, obj, lab, ctx.geom.base_offset_mm)
        ax.plot([it.points.A.y for it in its], [it.points.A.z for it in its], "k-", lw=0.6)
        ax.plot([it.points.B.y for it in its], [it.points.B.z for it in its], "k-", lw=0.6)
        ax.set_aspect("equal")
        ax.set_xlabel("y0 (mm)")
        ax.set_ylabel("z0 (mm)")
        ax.set_title(
            f"{name}) configurations"
            + (" with the object (fingertips)" if obj else " and Finger 1's workspace")
        )
        ax.legend(fontsize=7, loc="lower center")
        ax.grid(alpha=0.3)
    ys = [q for it in its for q in (it.points.A.y, it.points.B.y, it.points.C.y, it.points.D.y)]
    axs[0, 1].set_xlim(min(ys) - 15, max(ys) + 15)
    axs[0, 1].set_ylim(min(it.points.C.z for it in its) - 15, max(it.points.A.z for it in its) + 15)

    def series(
        ax: plt.Axes, ys: Sequence[Sequence[float]], names: Sequence[str], title: str
    ) -> None:
        for y, n in zip(ys, names, strict=True):
            ax.plot(xs, y, lw=1.3, label=n)
        for r in rev:
            ax.axvline(r, color="0.6", lw=0.6, ls=":")
        ax.set_title(title)
        ax.set_xlabel("iteration")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)

    a = math.radians(ALPHA_DEG)
    series(
        axs[0, 2],
        [[deg(it.omega_A) for it in its], [deg(it.omega_B) for it in its]],
        ["ωA", "ωB"],
        "c) ω per iteration (deg), cone 90° ± α",
    )
    for lim in (90 - deg(a), 90 + deg(a)):
        axs[0, 2].axhline(lim, color="k", lw=0.9, ls="--")
    series(axs[1, 0], [[deg(it.sigma) for it in its]], ["σ"], "d) object inclination σ (deg)")
    for s in backward_stretches(run):
        axs[1, 0].axvspan(s.first, s.last + 1, color=RED, alpha=0.2)
    for s in stalls(run):
        axs[1, 0].axvspan(s.first, s.last + 1, color="0.5", alpha=0.2)
    series(
        axs[1, 1],
        [[deg(it.pose.phi2) for it in its], [deg(it.pose.phi3) for it in its]],
        ["φ2", "φ3"],
        "e) Finger 1's joint angles (deg)",
    )
    series(
        axs[1, 2],
        [[deg(it.pose.phi4) for it in its], [deg(it.pose.phi5) for it in its]],
        ["φ4", "φ5"],
        "f) Finger 2's joint angles (deg)",
    )
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def plot_inclination(runs: Sequence[Run], path: Path, title: str) -> None:
    """σ per iteration for k = 2 and k = 5 (thesis Figs 33, 34)."""
    fig, ax = plt.subplots(figsize=(8, 4))
    for run in runs:
        ax.plot(
            [it.i for it in run.iterations],
            [math.degrees(it.sigma) for it in run.iterations],
            lw=1.3,
            label=f"k = {run.params.k:g}",
        )
        for s in backward_stretches(run):
            ax.axvspan(s.first, s.last + 1, color=RED, alpha=0.2)
        for s in stalls(run):
            ax.axvspan(s.first, s.last + 1, color="0.5", alpha=0.2)
    ax.set_xlabel("iteration")
    ax.set_ylabel("σ (deg)")
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# --- report -----------------------------------------------------------------------------------


def _f(x: float, nd: int = 2) -> str:
    return "–" if math.isnan(x) else f"{x:.{nd}f}"


def _rng(r: tuple[float, float], nd: int = 2) -> str:
    return f"{_f(r[0], nd)} … {_f(r[1], nd)}"


def _stretches(ss: Sequence[Stretch]) -> str:
    if not ss:
        return "none"
    return "; ".join(
        f"it {s.first}–{s.last} at σ = {s.sigma_from_deg:.2f}°, {s.along_deg:+.2f}°" for s in ss
    )


def _png(length: float, k: float | None = None) -> str:
    tag = f"{length:g}".replace(".", "_")
    return f"stick_{tag}_k{k:g}.png" if k is not None else f"stick_{tag}_sigma.png"


def write_report(
    runs: dict[tuple[float, float], Run],
    scans: Sequence[ScanResult],
    printed: dict[float, Run],
    ctx: ModelContext,
    cfg: Settings,
    out: Path,
    roots: dict[tuple[float, bool, float, float], Summary] | None = None,
    readings: ReadingResults | None = None,
    rscans: dict[tuple[str, float], ReadingScan] | None = None,
) -> Path:
    S = {key: summarise(r) for key, r in runs.items()}
    main5, main2 = S[(MAIN_LENGTH, 5.0)], S[(MAIN_LENGTH, 2.0)]
    wider = sum(_span(S[(ln, 2.0)]) > _span(S[(ln, 5.0)]) for ln in LENGTHS)
    pre = cfg.run.preshape_deg
    psi = pre[cfg.axes.phi2] + pre[cfg.axes.phi3]

    def verdict(s: Summary) -> str:
        b = "**unintended reversal**" if s.backward else "no unintended reversal"
        st = "a stall" if s.stalls else "no stall"
        return f"{b}, {st}"

    L: list[str] = []
    add = L.append
    add("# Thesis §3.4.2 reproduced kinematically: the two-finger algorithm on sticks\n")
    add(
        "Generated by `python -m experiments.sticks`. Every number below is computed by that "
        "script; the thesis's words are quotes. The thesis's figures were lost in the text "
        "extraction, so each plot stands next to the caption and statements it reproduces.\n"
    )
    if readings:
        add(_readings_summary(readings, rscans))
    add("## What is simulated\n")
    add(
        "The thesis's simulation (§3.4.1 steps 1–2f) with the project's pure hand model "
        "(`sdh2svc/model/`: FK, IK, pad profile, ω) and nothing else: the stick's ends are the "
        "contact points and stay where the grasp put them on the pads (S1, S2, hence r, θ, "
        "fixed); Λ = the stick's length at every iteration; no sensor, force, physics or servo — "
        "each iteration starts from the configuration the previous one commanded.\n"
    )
    add("| parameter | value | source |\n|---|---|---|")
    add(f"| Δφ | {DELTA_PHI_DEG}° | Table 8 |")
    add(f"| λ | {LAMBDA_GAIN:g} | Table 8 |")
    add(
        f"| α | {ALPHA_DEG:g}° (cone 90° ± α = {90 - ALPHA_DEG:g}° … {90 + ALPHA_DEG:g}°) | "
        "Table 8 |"
    )
    add("| k | 5 (Fig 31), 2 (Fig 32) | §3.4.2 |")
    add("| joint limits | φ2 … φ5 in [−90°, 90°] | manufacturer (`config/default.toml`) |")
    add(
        f"| run length | until the {REVERSALS}th reversal (the project's 3 strokes), or until "
        "both directions are refused | — |\n"
    )
    add(
        "Iteration: Finger 2 steps φ4 − Δφ, φ5 + k·Δφ (eqs 3.11–3.12); dσ = σ(Ac→Bd) − "
        "σ(Ac→Bc) (eq 3.13, its “+” a typo, hand-model §8); σd = σ + λ·dσ (eq 3.14); Ad = Bd − "
        "Λ·(cos σd, sin σd); Finger 1's IK (branch nearest to now); commanded if Finger 2's "
        "angles are within limits, Finger 1 reaches Ad within its limits and ωA, ωB are inside "
        "the cone; otherwise the rotation reverses (Δφ → −Δφ) and that iteration commands "
        "nothing. Δφ > 0 opens Finger 2's proximal joint and turns the object clockwise (σ "
        "decreasing), as §3.4 says (“Δφ>0 for clockwise rotation”); the first half stroke is "
        "clockwise.\n"
    )
    add("## The initial configuration\n")
    add(
        "The thesis gives no numbers: “The initial upper and proximal joint angles for each of "
        "the two fingers are given close values as it would happen in a real grasp. The points "
        "of contact on the sensors surfaces S1 and S2 are also given close values.” (§3.3.2; "
        "§3.4.2 uses “the same object and initial position”). So the grasp is made as this "
        f"project makes a real one: from the pre-shape (φ3 = −φ2, ψ = φ2 + φ3 = {psi:g}°, "
        "`run.preshape_deg`) both fingers close in a mirror pose, proximal +step and distal "
        "−step (ψ constant, `Runner._grasp`), around the stick held level at the simulator's "
        f"object height z0 = {cfg.sim.object_height_mm:g} mm (`sim.object_height_mm`), midway "
        "between the proximal joints, until each pad's surface reaches the stick's end. The "
        "fingers are then a mirror image of each other, σ = 0, |AB| = the length, and S1 = S2 "
        "(“close values”, here equal). No value was chosen with the outcome in view, and the "
        "finding below does not depend on this choice (see *Every mirror grasp*).\n"
    )
    add(
        "| stick (mm) | thesis figure | φ2 = φ4 | φ3 = φ5 | x3 (mm) | L (mm) | S1 = S2 (mm) | "
        "r (mm) | θ | ωA = ωB at start |\n|---|---|---|---|---|---|---|---|---|---|"
    )
    for length in LENGTHS:
        r = runs[(length, 5.0)]
        gg, it0 = r.grasp, r.iterations[0]
        c = gg.contact1
        add(
            f"| {length:g} | {FIGURE[length]} | {math.degrees(gg.pose.phi2):.2f}° | "
            f"{math.degrees(gg.pose.phi3):.2f}° | {c.x3:.2f} | {c.L:.2f} | {c.S:.2f} | "
            f"{c.r:.2f} | {math.degrees(c.theta):.2f}° | {math.degrees(it0.omega_A):.2f}° |"
        )
    add("")
    add("## The unintended reversal, defined\n")
    add(
        f"Within one half stroke (the commanded iterations between two reversals), σ runs "
        f"against the half stroke's direction (clockwise for Δφ > 0, anticlockwise for Δφ < 0) "
        f"for **N = {BACKWARD_ITERATIONS}** or more consecutive iterations and by **X = "
        f"{BACKWARD_DEG}°** or more in all. The kinematic model has no noise and no sensor "
        "quantisation (the contacts are fixed): its only quanta are the iteration and the "
        "route's step. One iteration is one sample, not “a period of time”, hence N = 2; and a "
        "backward run counts only if it undoes at least one step of Finger 2's proximal joint, "
        "X = Δφ = 0.25°, the smallest angle the route commands. A **stall** (“the inclination "
        "only remains constant for some time”) is N or more consecutive iterations over which σ "
        "moves by less than X. Independently of N and X, the table also counts every commanded "
        "iteration that moved σ backwards by any amount.\n"
    )
    add("## Results\n")
    add(
        "| stick (mm) | k | iterations | end | reversals: iteration (reason, σ) | σ range | "
        "σ per iteration, along its direction: min / median / max | ωA range | ωB range | "
        "max ‖AB‖ − Λ | iterations with σ backwards | unintended reversal (N, X) | stall |"
    )
    add("|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for (length, k), s in sorted(S.items(), key=lambda kv: (LENGTHS.index(kv[0][0]), -kv[0][1])):
        revs = ", ".join(f"{i} ({why}, {sg:.2f}°)" for i, why, sg in s.reversals)
        add(
            f"| {length:g} | {k:g} | {s.iterations} | {s.end} | {revs} | "
            f"{_rng(s.sigma_deg)}° | {s.step_deg[0]:.3f} / {s.step_deg[1]:.3f} / "
            f"{s.step_deg[2]:.3f}° | {_rng(s.omega_A_deg)}° | {_rng(s.omega_B_deg)}° | "
            f"{s.lambda_error_mm:.1e} mm | {s.backward_steps} | {_stretches(s.backward)} | "
            f"{_stretches(s.stalls)} |"
        )
    add("")
    add("Joint ranges over the runs (deg):\n")
    add("| stick (mm) | k | φ2 | φ3 | φ4 | φ5 |\n|---|---|---|---|---|---|")
    for (length, k), s in sorted(S.items(), key=lambda kv: (LENGTHS.index(kv[0][0]), -kv[0][1])):
        ph = s.phi_deg
        add(
            f"| {length:g} | {k:g} | {_rng(ph['phi2'])} | {_rng(ph['phi3'])} | "
            f"{_rng(ph['phi4'])} | {_rng(ph['phi5'])} |"
        )
    add("")
    add("## Side by side with the thesis\n")
    add("| thesis (quoted) | this reproduction | computed here |\n|---|---|---|")
    add(
        f"| **Fig 31** (98.46 mm, k = 5): “a) The initial configuration (red) and the extreme "
        "configurations just before the forces exceed the friction cone (green), (blue) and "
        "Finger's 1 workspace for this contact point (yellow), b) The configurations of a where "
        "the object is also represented, c) the angles ω for each repetition of the algorithm, "
        "d) the object inclination, e) the joint angles of Finger 1 and f) the joint angles of "
        f"Finger 2.” | ![98.46 mm, k = 5]({_png(MAIN_LENGTH, 5.0)}) | "
        f"{_reversal_text(main5)} {verdict(main5).capitalize()}. |"
    )
    add(
        f"| **Fig 32** (98.46 mm, k = 2): the same six panels. | "
        f"![98.46 mm, k = 2]({_png(MAIN_LENGTH, 2.0)}) | {_reversal_text(main2)} "
        f"{verdict(main2).capitalize()}. |"
    )
    add(
        "| “It is observed in Fig 31.d that for a big value of k. there is a period of time "
        "around the zero inclination that the movement of Finger 2 reverses unwillingly the "
        "object rotation, provoking disorders in the inclination values.” (§3.4.2) | panel d of "
        f"the k = 5 plot (backward stretches would be shaded red) | k = 5: "
        f"{main5.backward_steps} iterations move σ backwards at all; unintended reversals: "
        f"{_stretches(main5.backward)}. "
        + ("**Reproduced.** |" if main5.backward else "**Not reproduced.** |")
    )
    add(
        "| “This effect is smaller for k=2 that the inclination only remains constant for some "
        "time.” (§3.4.2) | panel d of the k = 2 plot (stalls would be shaded grey) | k = 2: "
        f"unintended reversals: {_stretches(main2.backward)}; stalls: "
        f"{_stretches(main2.stalls)}; the slowest iteration still turns σ by "
        f"{main2.step_deg[0]:.3f}° (median {main2.step_deg[1]:.3f}°). "
        + (
            "An unintended reversal, unlike the thesis"
            if main2.backward
            else "No reversal, as the thesis says"
        )
        + ("; a stall, as the thesis says. |" if main2.stalls else "; **no stall either**. |")
    )
    add(
        "| “As seen in Fig 27.b … The distance between the fingers remains constant since A is "
        "drawing a circle around B.” (§3.3.2, the one-finger run; the same holds here by "
        "construction) | panels a, b | max ‖AB‖ − Λ over all runs: "
        f"{max(s.lambda_error_mm for s in S.values()):.1e} mm |"
    )
    add(
        "| “At both of the extreme configurations that the forces tend to exceed the friction "
        "cone limits ωΑ is the one that tends to get out of its range.” (§3.3.2, one finger) | "
        f"panel c | every reversal, every run: "
        f"{_reasons(S.values())} |"
    )
    for length, fig in ((119.405, "Fig 33"), (62.038, "Fig 34"), (73.8, None)):
        s5, s2 = S[(length, 5.0)], S[(length, 2.0)]
        cap = (
            (
                f"**{fig}**: “Simulation results for object with length {length:g} mm: The "
                "inclination for k=2 and k=5.”"
            )
            if fig
            else (f"(not in §3.4.2: the {length:g} mm stick of §3.3.2, Fig 27)")
        )
        add(
            f"| {cap} | ![{length:g} mm]({_png(length)}) | k = 5: σ {_rng(s5.sigma_deg)}°, "
            f"{len(s5.reversals)} reversals, {verdict(s5)}; k = 2: σ "
            f"{_rng(s2.sigma_deg)}°, {len(s2.reversals)} reversals, {verdict(s2)}. |"
        )
    add(
        "| “It seems that a smaller k is more appropriate to be used in the determination of "
        "Finger's 2 route.” (§3.4.2) | — | σ's range over the run: "
        + "; ".join(
            f"{ln:g} mm: k = 2 {_span(S[(ln, 2.0)]):.1f}°, k = 5 {_span(S[(ln, 5.0)]):.1f}°"
            for ln in LENGTHS
        )
        + f"; k = 2 turns the stick further for {wider} of {len(LENGTHS)} sticks (k = 5 "
        "turns faster per iteration but reaches a limit sooner). |"
    )
    add("")
    found = any(s.backward for s in S.values())
    add(
        "## The route's own rate\n" if found else "## Why the unintended reversal does not appear\n"
    )
    add(
        "Finger 1 only amplifies (σd − σ = λ·dσ): σ's direction within a half stroke is the "
        "sign of dσ, the inclination change of Finger 2's route step alone. To first order in Δφ "
        "(B's step normal to AB; l1 = 86.5 mm, r2, θ2 Finger 2's virtual link, ψ' = φ4 + φ5):\n"
    )
    add("    Λ · dσ = −Δφ · [ l1 · sin(φ4 − σ) − (k − 1) · r2 · cos(ψ' − θ2 − σ) ]\n")
    add(
        "Both of Finger 2's joints turn the object the same way unless the two terms cancel. "
        "The second is the distal joint's: cos(ψ' − θ2 − σ) is the cosine of the angle between "
        "the virtual link D→B and the object B→A. The virtual link is "
        f"{_rng(link_normal_range(ctx, sensor=True), 1)}° from the pad's normal at the contact "
        "over the sensor's range (L 5.5–49.5 mm; "
        f"{_rng(link_normal_range(ctx, sensor=False), 1)}° over the whole pad), and inside the "
        "cone the normal is within α of B→A, so that angle stays below "
        f"{link_normal_range(ctx, sensor=False)[1] + ALPHA_DEG:.1f}° < 90°: the distal term is "
        "always positive. The first is the proximal joint's: with σ near 0 it has the sign of "
        f"φ4, and a stick longer than the {ctx.geom.base_offset_mm:g} mm between the proximal "
        "joints, held level midway between them, needs φ4 < 0 (the fingers open; B's y0 = "
        "33 + Λ/2 exceeds the proximal joint's). Both terms then push σ in the intended "
        "direction, and a larger k "
        "only makes the distal term — the one that cannot change sign — larger: the model "
        "gives k = 5 a faster and steadier rotation, not a reversal. A stall would need the "
        "two terms to nearly cancel, which the same argument rules out for these sticks near "
        "σ = 0 except where both are small (below).\n"
    )
    add(
        "The computed rate agrees: over the 98.46 mm runs the first-order dσ of the route "
        "alone (°/° of Δφ, along the intended direction; λ multiplies it) stays within "
        + "; ".join(f"k = {k:g}: {_rng(_rate_range(runs[(MAIN_LENGTH, k)], ctx), 3)}" for k in KS)
        + " — never near zero.\n"
    )
    add("### Every other grasp\n")
    mirror = [sc for sc in scans if sc.kind == "mirror"]
    free = [sc for sc in scans if sc.kind == "any"]
    add(
        "The same runs (3 reversals each, same detectors) from other initial grasps, keeping "
        "those within the joint limits and inside both cones. *Mirror*: σ = 0, the two fingers "
        f"mirror images, the contact at {MIRROR_GRID[0]} points over the whole pad × Finger 1's "
        f"ψ = φ2 + φ3 at {MIRROR_GRID[1]} values in [−30°, 60°]. *Any*: the stick's centre "
        f"moved sideways by {_list(ANY_OFFSETS)} mm from midway "
        f"between the proximal joints, at z0 = {_list(ANY_HEIGHTS)}"
        f" mm, inclined by {_list(ANY_SIGMAS_DEG)}°, its ends at "
        f"any of {ANY_N_X3} × {ANY_N_X3} pairs of contact points over the two "
        "pads (S1 ≠ S2), each finger's angles by IK.\n"
    )
    add(
        "| grasps | stick (mm) | k | grasps run | with an unintended reversal | with a stall | "
        "iterations with σ backwards, all grasps | slowest σ step / median, worst grasp |"
    )
    add("|---|---|---|---|---|---|---|---|")
    for sc in scans:
        add(
            f"| {sc.kind} | {sc.length:g} | {sc.k:g} | {sc.grasps} | {sc.with_backward} | "
            f"{sc.with_stall} | {sc.backward_steps} | {_f(sc.min_rate_ratio)} |"
        )
    add("")
    n_back = sum(sc.with_backward for sc in scans)
    add(
        f"Unintended reversals (N = {BACKWARD_ITERATIONS}, X = {BACKWARD_DEG}°) over all "
        f"{sum(sc.grasps for sc in scans)} grasps run: **{n_back}** "
        f"(k = 5: {sum(sc.with_backward for sc in scans if sc.k == 5.0)}, k = 2: "
        f"{sum(sc.with_backward for sc in scans if sc.k == 2.0)}); stalls: "
        f"{sum(sc.with_stall for sc in mirror)} of the mirror grasps, "
        f"{sum(sc.with_stall for sc in free)} of the others. Every grasp flagged is listed "
        "here, with where on the pads its contacts are (the sensor reports S in 0–40.8 mm; "
        "beyond that the contact sits below its active area) and the σ at which the flagged "
        "stretch begins:\n"
    )
    flagged = [(sc, f) for sc in scans for f in sc.flagged]
    if flagged:
        add(
            "| grasps | stick (mm) | k | S1 | S2 | ψ1 | σ at start | φ4 at start | ωA, ωB at "
            "start | σ range of the run | flagged, at σ |"
        )
        add("|---|---|---|---|---|---|---|---|---|---|---|")
        for sc, f in flagged:
            what = ", ".join(w for w, on in (("unintended reversal", f.backward),
                                             ("stall", f.stall)) if on)  # fmt: skip
            add(
                f"| {sc.kind} | {sc.length:g} | {sc.k:g} | {f.S1:.1f} | {f.S2:.1f} | "
                f"{f.psi1:.1f}° | {f.sigma0:.1f}° | {f.phi4:.2f}° | {f.omega_A0:.1f}°, "
                f"{f.omega_B0:.1f}° | {f.sigma_span:.2f}° | {what}, {f.at_sigma:.2f}° |"
            )
        add("")
        near0 = [(sc, f) for sc, f in flagged if abs(f.at_sigma) < 2.0]
        margin = max(
            ALPHA_DEG - max(abs(f.omega_A0 - 90), abs(f.omega_B0 - 90)) for _, f in flagged
        )
        add(
            f"None of them reverses. {len(near0)} of the {len(flagged)} stalls begin near zero "
            "inclination (|σ| < 2°)"
            + (
                f", on the {_list(sorted({sc.length for sc, _ in near0}))} mm stick with k = "
                f"{_list(sorted({sc.k for sc, _ in near0}))}"
                if near0
                else ""
            )
            + f". Every flagged grasp starts within {margin:.1f}° of a cone's edge (α − |ω − 90°| "
            "at the start); with k = 5, "
            f"{sum(len(sc.flagged) for sc in scans if sc.k == 5.0)} grasps are flagged. The "
            "stalls occur where the route's two terms are both small (φ4 near 0 and a weak "
            "distal term, or Finger 2's contact at the base of its pad).\n"
        )
    add(
        "So the equations as the thesis states them (hand-model.md) do not produce the effect "
        "of Fig 31.d for these sticks, for either k, from any grasp tried.\n"
    )
    add(
        "What the thesis's own program did differently cannot be checked: its code and "
        "figures are lost. Two candidates. (1) Eq 3.13 as printed (“+”): dσ = σ(Ac→Bd) + σc "
        "gives σd ≈ (1 + 2λ)·σc + λ·dσ, which runs away from any σ ≠ 0; run here on the "
        "98.46 mm stick, "
        + "; ".join(_printed_text(printed[k], k) for k in KS)
        + " — no period of back-and-forth around zero, so not the thesis's effect either. "
        "(2) The root test of eq 3.9, which picks between A1 and its mirror A3 by comparing "
        "their inclinations ±σd with σd: near σd = 0 the two come close, so a comparison with a "
        "tolerance (or one that fails on rounding) can pick the mirror root and flip σ "
        "“around the zero inclination”. How the thesis's program compared them is not in the "
        "text, so it is tried below over a range of tolerances; the project's closed form "
        "(Ad = Bd − Λ·(cos σd, sin σd)) has no such ambiguity.\n"
    )
    if roots:
        add(_roots_section(roots))
    if readings:
        add(_readings_section(readings, rscans, ctx))
    add("## Plots\n")
    for k in KS:
        add(f"![{MAIN_LENGTH:g} mm, k = {k:g}]({_png(MAIN_LENGTH, k)})\n")
    for length in LENGTHS[1:]:
        add(f"![{length:g} mm, σ]({_png(length)})\n")
    if readings:
        add(f"![98.46 mm, eq 3.9 with an exact “=”, the root tried last kept]({_EQ39_PNG})\n")
    if rscans and rscans[("α = 45°", MAIN_LENGTH)].example is not None:
        add(f"![98.46 mm, α = 45°, a grasp that shows both statements]({_ALPHA45_PNG})\n")
    path = out / "report.md"
    path.write_text("\n".join(L), encoding="utf-8")
    return path


ROOT_TOLERANCES_DEG = (0.1, 0.25, 0.5, 1.0, 2.0, 5.0)


def root_test_runs(
    cfg: Settings, tolerances: Sequence[float] = ROOT_TOLERANCES_DEG
) -> dict[tuple[float, bool, float, float], Summary]:
    """Every stick and k with Ad by the thesis's root test, per tolerance and tie order."""
    ctx = cfg.model_context()
    out = {}
    for length in LENGTHS:
        g = grasp_from_settings(length, cfg)
        for tol, last, k in itertools.product(tolerances, (True, False), KS):
            params = Params(k, root_tol_deg=tol, root_last_wins=last)
            out[(tol, last, length, k)] = summarise(simulate(g, params, ctx))
    return out


def _roots_section(roots: dict[tuple[float, bool, float, float], Summary]) -> str:
    tolerances = sorted({key[0] for key in roots})
    rows = [
        "### Candidate (2): the root test of eq 3.9 with a tolerance\n",
        "Ad computed by eqs 3.6–3.8 and kept by eq 3.9's test |atan((Bz − Az)/(By − Ay)) − σd| ≤ "
        "tolerance; when both roots pass (|σd| ≤ tolerance / 2) either the one tried last or the "
        "first is kept. Same grasps, detectors (N = 2, X = 0.25°) and stop rule as above; summed "
        "over the four sticks.\n",
        "| tolerance | both pass: kept | k | runs ending stuck | unintended reversals | stalls "
        "| iterations with σ backwards |",
        "|---|---|---|---|---|---|---|",
    ]
    for tol, last, k in itertools.product(tolerances, (True, False), KS):
        ss = [roots[(tol, last, ln, k)] for ln in LENGTHS]
        rows.append(
            f"| {tol:g}° | {'last' if last else 'first'} | {k:g} | "
            f"{sum(s.end == 'stuck' for s in ss)} | {sum(len(s.backward) for s in ss)} | "
            f"{sum(len(s.stalls) for s in ss)} | {sum(s.backward_steps for s in ss)} |"
        )
    effect = [
        (tol, last)
        for tol, last in itertools.product(tolerances, (True, False))
        if any(roots[(tol, last, ln, 5.0)].backward for ln in LENGTHS)
        and not any(roots[(tol, last, ln, 2.0)].backward for ln in LENGTHS)
    ]
    back = {
        (t, la): [sum(roots[(t, la, ln, k)].backward_steps for ln in LENGTHS) for k in (2.0, 5.0)]
        for t, la in itertools.product(tolerances, (True, False))
    }
    picked = [b for b in back.values() if any(b)]
    worse2 = sum(b2 > b5 for b2, b5 in picked)
    verdict = (
        "For no tolerance and tie order does k = 5 show an unintended reversal while k = 2 does not"
        if not effect
        else "k = 5 shows an unintended reversal and k = 2 does not for: "
        + ", ".join(f"{t:g}° ({'last' if la else 'first'})" for t, la in effect)
    )
    rows.append(
        f"\n{verdict}. Where the mirror root is picked at all ({len(picked)} settings), k = 2 "
        f"has more iterations with σ backwards than k = 5 in {worse2}"
        + (
            " — the opposite of the thesis's observation: k = 2's smaller σ steps spend more "
            "iterations inside the band |σd| ≤ tolerance / 2"
            if 2 * worse2 > len(picked)
            else ""
        )
        + ". So this candidate does not explain Fig 31.d either.\n"
        if not effect
        else f"\n{verdict}.\n"
    )
    return "\n".join(rows)


# --- other readings of the thesis's program ---------------------------------------------------

ZERO_BAND_DEG = 2.0  # "around the zero inclination": within 2° of σ = 0 (σ spans ~ −3 … +8°)
STICKS_READ = (98.46, 62.038, 119.405, 73.8)  # Figs 31–32, 34, 33, §3.3.2


@dataclass(frozen=True, slots=True)
class Reading:
    """One reading of what the thesis's MATLAB-style program may have done: ``Params``
    overrides, the thesis's words it rests on (or that speak against it), and whether the text
    supports it."""

    key: str
    what: str
    overrides: tuple[tuple[str, object], ...]
    text: str
    supported: bool

    def params(self, k: float) -> Params:
        return Params(k, **dict(self.overrides))  # type: ignore[arg-type]


_EQ39 = (
    "eq 3.9 prints an exact test: “IF tan−1((Bz0 − Az0i)/(By0 − Ay0)) = σd THEN Az0 = Az0i, "
    "i=1,2”; what the program did when neither root passes is not written"
)
READINGS: tuple[Reading, ...] = (
    Reading("hand-model", "hand-model.md's equations (the report above)", (),
            "eqs 3.11–3.14, 3.3 as restated in hand-model.md", True),
    Reading("eq 3.13 “+”", "dσ = σ(Ac→Bd) + σ(Ac→Bc), as printed", (("printed_eq313", True),),
            "against: “we calculate the difference between the inclination of the segments "
            "AcBd(red) and the inclination of AcBc”", False),
    Reading("σ by atan", "σ = atan((Bz − Az)/(By − Ay)), eq 3.3 literally: values in "
            "(−90°, 90°), its branch cut where By = Ay (σ = ±90°), far from σ = 0",
            (("sigma_from", "atan"),), "eq 3.3: “σAB = tan−1((Bz0 − Az0)/(By0 − Ay0))”", True),
    Reading("σ from B to A", "σ = atan2(Az − Bz, Ay − By): its cut (±180°) is at σ = 0; dσ "
            "jumps by 2π there, but λ = 5 is an integer, so σd moves by 10π — the same "
            "direction", (("sigma_from", "atan2_BA"),),
            "against: eq 3.3 measures from A to B", False),
    Reading("k on φ4", "φ4 − kΔφ, φ5 + Δφ", (("route", "k_proximal"),),
            "against: “The angle of the proximal articulation φ4 will change at a lower rhythm "
            "than φ5”", False),
    Reading("φ5 the other way", "φ4 − Δφ, φ5 − kΔφ (φ5 counted in the other sense)",
            (("route", "same_sense"),),
            "against: “closing its proximal articulation and opening its upper articulation to "
            "increase the object's inclination”", False),
    Reading("anticlockwise first", "the first half stroke with Δφ < 0",
            (("first_direction", -1),),
            "§3.4.2 does not say; one finger went “first at the direction that decreases its "
            "inclination” (§3.3.2)", True),
    Reading("IK β − o", "Finger 1's elbow by one fixed formula, φ2 = β − o",
            (("ik", "branch+"),), "§2.12: one geometric solution, c and o by the law of "
            "cosines", True),
    Reading("IK β + o", "the other fixed elbow, φ2 = β + o", (("ik", "branch-"),),
            "§2.12 (as above); the grasp is on the β − o elbow", True),
    Reading("IK clipped", "acos's argument clipped to [−1, 1] (MATLAB's real(acos)): an "
            "unreachable Ad stretches Finger 1 towards it", (("ik_clip", True),),
            "partly against: 2f commands only “if the new configuration is inside the "
            "fingers' workspace”", False),
    Reading("IK clipped, A carried", "as above, and the next iteration's Ac, σc are the "
            "commanded Ad, σd, not re-measured", (("ik_clip", True), ("sigma_source",
                                                                      "commanded")),
            "for: steps 2b and 2f recompute “B, D” and “C” by direct kinematics, never A",
            True),
    Reading("flat pad", "ω against the distal link's axis, not the pad's tangent",
            (("flat_pad", True),), "against: eq 2.29 subtracts tan−1(A'y3(L1)), the pad's "
            "slope", False),
    Reading("cone on ωA only", "the cone tested on ωA alone", (("cone_A_only", True),),
            "partly for: “ωΑ is the one that tends to get out of its range” (§3.3.2); against: "
            "eqs 2.25–2.26 “must be met” for ωA and ωB, and 2f", False),
    Reading("Δφ = 1°", "Finger 2's step 1°", (("delta_phi", math.radians(1.0)),),
            "§3.4.2 gives no Δφ; Table 8 (0.25°) is chapter 4's", True),
    Reading("λ = 1", "Finger 1 reinforces once", (("lambda_gain", 1.0),),
            "§3.4.2 gives no λ; Table 8 (5) is chapter 4's", True),
    Reading("λ = 10", "Finger 1 reinforces ten times", (("lambda_gain", 10.0),),
            "(as above)", True),
    Reading("α = 30°", "a wider friction cone", (("alpha", math.radians(30.0)),),
            "§3.4.2 gives no α; Table 8's 22° is chapter 4's “typical small value”", True),
    Reading("α = 45°", "a much wider friction cone", (("alpha", math.radians(45.0)),),
            "(as above)", True),
    Reading("eq 3.9 “=”, root tried last", "Ad by eqs 3.6–3.9 with an exact “=”; when neither "
            "root passes, the loop's variable keeps z02, the root tried last",
            (("root_tol_deg", 0.0), ("root_nomatch", "last_tried")), "for: " + _EQ39, True),
    Reading("eq 3.9 “=”, root tried first", "as above, keeping z01",
            (("root_tol_deg", 0.0), ("root_nomatch", "first_tried")), "for: " + _EQ39, True),
    Reading("eq 3.9 “=”, Az unchanged", "as above; Az keeps its previous value (an IF "
            "without ELSE), Ay by eq 3.8", (("root_tol_deg", 0.0), ("root_nomatch", "stale")),
            "for: " + _EQ39, True),
)  # fmt: skip


def stretch_span(run: Run, s: Stretch) -> tuple[float, float]:
    """σ's range (deg) over a stretch, from its first iteration to where its last one took σ."""
    sig = [math.degrees(it.sigma) for it in run.iterations[s.first : s.last + 2]]
    return min(sig), max(sig)


def near_zero(run: Run, s: Stretch, band: float = ZERO_BAND_DEG) -> bool:
    lo, hi = stretch_span(run, s)
    return lo <= band and hi >= -band


@dataclass(frozen=True, slots=True)
class ReadingRun:
    """What one reading's run shows (the report's detectors; ω measured on the pad's profile)."""

    end: str
    backward: int  # unintended reversals (N, X)
    backward_near0: int  # of them, within ZERO_BAND_DEG of σ = 0
    stalls: int
    back_steps: int  # commanded iterations moving σ backwards at all
    back_steps_near0: int  # of them, starting within ZERO_BAND_DEG of σ = 0
    max_back_deg: float  # the largest single backward step (0 if none)
    sigma_deg: tuple[float, float]
    ab_error_mm: float  # max | |AB| − length |
    omega_dev_deg: float  # the largest |ω − 90°| of ωA, ωB over the run's configurations
    reasons: tuple[int, int, int]  # reversals at cone A, at cone B, at the workspace or IK


def read_run(run: Run, ctx: ModelContext) -> ReadingRun:
    ur = backward_stretches(run)
    steps = [(it, d) for it, d in sigma_steps(run) if d < 0.0]
    true = [_measure(it.pose, run.grasp, ctx) for it in run.iterations]
    dev = [max(abs(m[3] - math.pi / 2), abs(m[4] - math.pi / 2)) for m in true]
    sig = [math.degrees(it.sigma) for it in run.iterations]
    return ReadingRun(
        end=run.end,
        backward=len(ur),
        backward_near0=sum(near_zero(run, s) for s in ur),
        stalls=len(stalls(run)),
        back_steps=len(steps),
        back_steps_near0=sum(abs(math.degrees(it.sigma)) <= ZERO_BAND_DEG for it, _ in steps),
        max_back_deg=max((-d for _, d in steps), default=0.0),
        sigma_deg=(min(sig), max(sig)),
        ab_error_mm=max(abs(m[1] - run.grasp.length) for m in true),
        omega_dev_deg=math.degrees(max(dev)),
        reasons=(
            sum(it.reversal is Reversal.CONE_A for it in run.reversals),
            sum(it.reversal is Reversal.CONE_B for it in run.reversals),
            sum(it.reversal not in (Reversal.CONE_A, Reversal.CONE_B) for it in run.reversals),
        ),
    )


def reproduces(r5: ReadingRun, r2: ReadingRun) -> bool:
    """The thesis's two statements on one stick: k = 5 reverses unintentionally near σ = 0
    (N, X), k = 2 does not reverse."""
    return r5.backward_near0 > 0 and r2.backward == 0


ReadingResults = dict[tuple[str, float, float], tuple[Run, ReadingRun]]


def reading_runs(cfg: Settings, readings: Sequence[Reading] = READINGS) -> ReadingResults:
    """Every reading on the four sticks for k = 5 and 2, from the report's grasp."""
    ctx = cfg.model_context()
    grasps = {ln: grasp_from_settings(ln, cfg) for ln in STICKS_READ}
    out = {}
    for rd, ln, k in itertools.product(readings, STICKS_READ, KS):
        run = simulate(grasps[ln], rd.params(k), ctx)
        out[(rd.key, ln, k)] = (run, read_run(run, ctx))
    return out


# readings that let ωB go far enough for the distal term to change sign, scanned over grasps
SCAN_READINGS: tuple[Reading, ...] = (
    *(
        Reading(f"α = {a:g}°", "", (("alpha", math.radians(a)),), "", True)
        for a in (22, 35, 40, 45)
    ),
    next(rd for rd in READINGS if rd.key == "cone on ωA only"),
)


@dataclass(frozen=True, slots=True)
class ReadingScan:
    """Mirror grasps inside the 22° cone run under one reading (k = 5 and 2, 3 reversals)."""

    grasps: int
    reproducing: int  # k = 5 reverses near σ = 0, k = 2 does not
    k2_stall: int  # of them, k = 2 stalls
    example: Grasp | None  # the first reproducing grasp
    least_dev_deg: float  # over them, the smallest of k = 5's largest |ω − 90°|


def reading_scan(
    ctx: ModelContext, rd: Reading, length: float, grasps: Sequence[Grasp]
) -> ReadingScan:
    alpha, n, rep, k2s = math.radians(ALPHA_DEG), 0, 0, 0
    example, least = None, math.inf
    for g in grasps:
        _, _, _, wa, wb = _measure(g.pose, g, ctx)
        if not (inside_cone(wa, alpha) and inside_cone(wb, alpha)):
            continue
        n += 1
        r5, r2 = (
            read_run(simulate(g, replace(rd.params(k), reversals=3, max_iterations=2000), ctx), ctx)
            for k in KS
        )
        if reproduces(r5, r2):
            rep += 1
            k2s += r2.stalls > 0
            example = example or g
            least = min(least, r5.omega_dev_deg)
    return ReadingScan(n, rep, k2s, example, least)


def reading_scans(ctx: ModelContext) -> dict[tuple[str, float], ReadingScan]:
    out = {}
    for ln in STICKS_READ:
        grasps = mirror_grasps(ln, ctx)
        for rd in SCAN_READINGS:
            out[(rd.key, ln)] = reading_scan(ctx, rd, ln, grasps)
    return out


def exact_match_rate(n: int = 4000, seed: int = 0) -> float:
    """How often the correct root passes eq 3.9's test with an exact “=” in floating point:
    B, Λ (60–120 mm) and σd (±10°, not 0) drawn at random."""
    rng = random.Random(seed)
    hits = 0
    for _ in range(n):
        B = Point(rng.uniform(80.0, 130.0), rng.uniform(100.0, 150.0))
        sd = math.radians(rng.choice((-1.0, 1.0)) * rng.uniform(0.01, 10.0))
        hits += thesis_root(B, rng.uniform(60.0, 120.0), sd, 0.0, False) is not None
    return hits / n


def _cell(r: ReadingRun) -> str:
    end = "" if r.end == "done" else f" ({r.end})"
    return (
        f"{r.backward} ({r.backward_near0}) · {r.stalls} · {r.back_steps} "
        f"({r.back_steps_near0}){end}"
    )


def _verdict(rd: Reading, rr: dict[tuple[float, float], ReadingRun]) -> tuple[bool, str, str]:
    """Whether a reading reproduces §3.4.2 on the 98.46 mm stick as the thesis would have it,
    the sticks it reproduces on, and why not."""
    on = [ln for ln in STICKS_READ if reproduces(rr[(ln, 5.0)], rr[(ln, 2.0)])]
    err = max(r.ab_error_mm for r in rr.values())
    alpha = math.degrees(rd.params(5.0).alpha)
    dev = max(r.omega_dev_deg for r in rr.values())
    why = [
        w
        for w, bad in (
            ("not supported by the text", not rd.supported),
            (f"ω leaves 90° ± {alpha:g}°", dev >= alpha),
            ("|AB| not constant", err >= 1e-6),
            ("does not reproduce on the 98.46 mm stick", MAIN_LENGTH not in on),
        )
        if bad
    ]
    return not why, _list(on) + " mm" if on else "—", "; ".join(why)


def _readings_section(
    res: ReadingResults,
    scans: dict[tuple[str, float], ReadingScan] | None,
    ctx: ModelContext,
    readings: Sequence[Reading] = READINGS,
) -> str:
    rows = [
        "## Other readings of the thesis's program\n",
        "The thesis's program is lost, so each place where its text leaves the computation "
        "open, or prints something the restatement corrected, is tried as an option of "
        "`simulate` (`Params`, `READINGS` in the script), everything else as above: the same "
        f"grasp, stop rule and detectors (N = {BACKWARD_ITERATIONS}, X = {BACKWARD_DEG}°), σ "
        "measured A→B on the configuration reached, whatever the program measured. A reading "
        "is *supported* when the text speaks for it or leaves the point open (the quote says "
        "which). It *reproduces* §3.4.2 on a stick when k = 5 shows an unintended reversal "
        f"that comes within {ZERO_BAND_DEG:g}° of σ = 0 and k = 2 shows none. The thesis's "
        "other statements must still hold: |AB| constant (§3.3.2) and every configuration "
        "inside the cone (2f; Fig 31: “the extreme configurations just before the forces "
        "exceed the friction cone”). Where the runs reverse is shown too: §3.3.2's “ωΑ is the "
        "one that tends to get out of its range” is said of one finger, and hand-model's "
        "own runs reverse at both cones, so it is not a criterion.\n",
        "| reading | what the program does | the thesis's text | supported |",
        "|---|---|---|---|",
    ]
    rows += [
        f"| {rd.key} | {rd.what} | {rd.text} | {'yes' if rd.supported else 'no'} |"
        for rd in readings
    ]
    rows += [
        "",
        "Each cell: unintended reversals (of them near σ = 0) · stalls · iterations with σ "
        f"backwards (of them within {ZERO_BAND_DEG:g}° of σ = 0), and the end if not *done*. "
        "ω is measured on the pad's profile whatever the program tested.\n",
        "| reading | "
        + " | ".join(f"{ln:g} mm, k = {k:g}" for ln in STICKS_READ for k in KS)
        + " | max ‖AB‖ − Λ | max abs(ω − 90°) | reversals at cone A / cone B / workspace "
        "| reproduces on | verdict |",
        "|---|" + "---|" * (2 * len(STICKS_READ)) + "---|---|---|---|---|",
    ]
    good = []
    for rd in readings:
        rr = {(ln, k): res[(rd.key, ln, k)][1] for ln in STICKS_READ for k in KS}
        ok, on, why = _verdict(rd, rr)
        if ok:
            good.append(rd.key)
        rows.append(
            f"| {rd.key} | "
            + " | ".join(_cell(rr[(ln, k)]) for ln in STICKS_READ for k in KS)
            + f" | {max(r.ab_error_mm for r in rr.values()):.1e} mm | "
            f"{max(r.omega_dev_deg for r in rr.values()):.1f}° | "
            + " / ".join(str(sum(r.reasons[i] for r in rr.values())) for i in range(3))
            + f" | {on} | "
            + ("**reproduces Figs 31.d and 32.d**" if ok else why)
            + " |"
        )
    rows.append("")
    rows.append(_readings_findings(res, scans, ctx, readings, good))
    return "\n".join(rows)


def _same_as_model(res: ReadingResults, key: str) -> bool:
    """A reading's σ series equals hand-model's on every stick and k (within 1e-11 rad)."""
    pairs = [
        (res[(key, ln, k)][0].iterations, res[("hand-model", ln, k)][0].iterations)
        for ln in STICKS_READ
        for k in KS
    ]
    return all(
        len(a) == len(b) and all(abs(x.sigma - y.sigma) < 1e-11 for x, y in zip(a, b, strict=True))
        for a, b in pairs
    )


def _readings_summary(
    res: ReadingResults, scans: dict[tuple[str, float], ReadingScan] | None
) -> str:
    """The verdict on the other readings, for the top of the report."""
    good = [
        rd.key
        for rd in READINGS
        if _verdict(rd, {(ln, k): res[(rd.key, ln, k)][1] for ln in STICKS_READ for k in KS})[0]
    ]
    if good:
        return (
            f"**Fig 31.d reproduced under another reading of the thesis's program: "
            f"{', '.join(good)}** (see *Other readings of the thesis's program*).\n"
        )
    ex = scans.get(("α = 45°", MAIN_LENGTH)) if scans else None
    tail = (
        f" With a friction angle of 45° instead, {ex.reproducing} of {ex.grasps} mirror grasps "
        "of the 98.46 mm stick show both statements (plotted at the end)."
        if ex is not None and ex.reproducing
        else ""
    )
    others = READINGS[1:]
    elsewhere = [
        f"{rd.key} on the {ln:g} mm stick"
        for rd in others
        for ln in STICKS_READ
        if rd.supported and reproduces(res[(rd.key, ln, 5.0)][1], res[(rd.key, ln, 2.0)][1])
    ]
    return (
        f"**Fig 31.d is not reproduced.** Neither the hand model's equations nor any of the "
        f"{len(others)} other readings of the thesis's program tried (section *Other "
        f"readings*; {sum(rd.supported for rd in others)} of them supported by its text) "
        "gives k = 5 an unintended reversal near zero inclination and k = 2 none on the "
        "98.46 mm stick from the report's grasp"
        + (f" (a supported one does elsewhere: {'; '.join(elsewhere)})" if elsewhere else "")
        + ". The "
        "thesis's k-dependence does appear, by the mechanism that section derives, when the "
        "stick may turn more than 90° from Finger 2's virtual link — possible only if ωB "
        f"leaves Table 8's 22° cone, which the text does not say.{tail}\n"
    )


def _list_reasons(run: Run) -> str:
    c = Counter(str(it.reversal) for it in run.reversals)
    return ", ".join(f"{why} × {n}" for why, n in c.most_common())


def _wide_cone_text(res: ReadingResults, key: str = "α = 45°") -> str:
    """Where the wide-cone reading's first unintended reversal falls, from the report's grasp."""
    if (key, MAIN_LENGTH, 5.0) not in res:
        return ""
    first = {
        ln: (run, ur[0])
        for ln in STICKS_READ
        if (ur := backward_stretches(run := res[(key, ln, 5.0)][0]))
    }
    spans = "; ".join(f"{_rng(stretch_span(r, s), 1)}° ({ln:g} mm)" for ln, (r, s) in first.items())
    at0 = [ln for ln, (r, s) in first.items() if near_zero(r, s)]
    return (
        f" With {key}, k = 5 reverses on {_list(_reversing(res, key, 5.0)) or 'no'} mm sticks, "
        f"k = 2 on {_list(_reversing(res, key, 2.0)) or 'none'}; from the report's grasp the "
        f"first unintended reversal spans σ {spans or '—'}: it begins where ωB nears its "
        f"limit and comes within {ZERO_BAND_DEG:g}° of zero inclination on "
        f"{_list(at0) + ' mm' if at0 else 'no stick'}."
    )


def _reversing(res: ReadingResults, key: str, k: float) -> list[float]:
    """The sticks on which a reading's run with this k has an unintended reversal."""
    return [ln for ln in STICKS_READ if (key, ln, k) in res and res[(key, ln, k)][1].backward]


def _readings_findings(
    res: ReadingResults,
    scans: dict[tuple[str, float], ReadingScan] | None,
    ctx: ModelContext,
    readings: Sequence[Reading],
    good: Sequence[str],
) -> str:
    keys = [rd.key for rd in readings]
    out = []
    same = [k for k in keys if k != "hand-model" and _same_as_model(res, k)]
    if same:
        out.append(
            f"*Readings that change nothing.* {', '.join(same)}: σ's series on every stick and "
            "k is hand-model's within 1e-11 rad (eq 3.3's atan differs from atan2 only past "
            "σ = ±90°; measured from B to A, dσ jumps by 2π where the stick is level, and λ = 5 "
            "turns that into 10π; in these runs every configuration a clipped IK gives is then "
            "refused at the cone, so none is commanded — only the reversal's reason changes, "
            "ik_unreachable becoming cone_A or cone_B).\n"
        )
    eq39 = "eq 3.9 “=”, root tried last"
    if eq39 in keys:
        r5, r2 = res[(eq39, MAIN_LENGTH, 5.0)][1], res[(eq39, MAIN_LENGTH, 2.0)][1]
        f5 = res[("eq 3.9 “=”, root tried first", MAIN_LENGTH, 5.0)][1]
        out.append(
            "*Eq 3.9's exact “=”.* The correct root passes an exact floating-point comparison "
            f"in {100 * exact_match_rate():.0f} % of cases (4000 random B, Λ, σd), so what the "
            "program keeps when neither passes decides the run. Keeping z02 (the root tried "
            "last) puts A on the mirror root whenever σd > 0: σ can never rise past level "
            f"(98.46 mm: σ {_rng(r5.sigma_deg)}° for k = 5, {_rng(r2.sigma_deg)}° for k = 2) "
            "and, once an anticlockwise half stroke reaches σ = 0, zig-zags there between 0 and "
            f"−λ·dσ every iteration: {r5.back_steps_near0} backward iterations near σ = 0 for "
            f"k = 5, the largest {r5.max_back_deg:.2f}°; {r2.back_steps_near0} for k = 2, the "
            f"largest {r2.max_back_deg:.2f}°. This is the only reading whose “disorders” sit "
            "exactly at zero inclination, and k = 2's are about half as large, but each "
            "backward run lasts one iteration (below N), so the detectors see a stall for both "
            "k rather than a reversal for k = 5, and the stick never turns to the other side. "
            "Keeping z01 instead holds "
            f"σ at or above level with the same zig-zag (k = 5: σ {_rng(f5.sigma_deg)}°); "
            "keeping the previous Az makes A slide at a constant height, and most runs end "
            "stuck.\n"
        )
    lo, hi = link_normal_range(ctx, sensor=False)
    out.append(
        "*What produces the thesis's k-dependence.* In the first-order rate above, the distal "
        "term (k − 1)·r2·cos(ψ' − θ2 − σ) changes sign once the stick is more than 90° from "
        "Finger 2's virtual link D→B. The link is "
        f"{lo:.1f} … {hi:.1f}° from the pad's normal, so that needs |ωB − 90°| ≥ "
        f"{90 - hi:.1f} … {90 - lo:.1f}° on the far side: never inside Table 8's α = "
        f"{ALPHA_DEG:g}°. Past that point the two joints turn the stick opposite ways; with "
        "k = 5 the distal term (×4) wins and σ runs backwards, with k = 2 (×1) it only offsets "
        "part of the proximal term, σ slows and may stall — the shape of the thesis's two "
        "statements. Readings that let ωB get there: a wide cone or no cone test on ωB."
        + _wide_cone_text(res)
        + "\n"
    )
    if scans:
        out.append(
            "Where it comes depends on the grasp, which the thesis does not give. Over the "
            "mirror grasps of *Every other grasp* (inside the 22° cone at the start), the "
            "grasps on which k = 5 reverses near σ = 0 and k = 2 does not (of them, with a "
            "k = 2 stall):\n"
        )
        out.append(
            "| reading | "
            + " | ".join(f"{ln:g} mm" for ln in STICKS_READ)
            + " |\n|---|"
            + "---|" * len(STICKS_READ)
        )
        for rd in SCAN_READINGS:
            cells = [scans[(rd.key, ln)] for ln in STICKS_READ]
            out.append(
                f"| {rd.key} | "
                + " | ".join(f"{s.reproducing} of {s.grasps} ({s.k2_stall})" for s in cells)
                + " |"
            )
        ex = scans.get(("α = 45°", MAIN_LENGTH))
        if ex is not None and ex.example is not None:
            g = ex.example
            why = {
                k: _list_reasons(simulate(g, Params(k, alpha=math.radians(45.0)), ctx)) for k in KS
            }
            out.append(
                f"\nThe first such grasp on the 98.46 mm stick with α = 45° (S1 = S2 = "
                f"{g.contact1.S:.1f} mm, ψ1 = {math.degrees(g.pose.phi2 + g.pose.phi3):.1f}°) "
                f"is plotted below ({_ALPHA45_PNG}): k = 5 rocks the stick about zero "
                "inclination and runs backwards in every half stroke, k = 2 turns it further "
                "and stalls near the top. It shows both statements, but with a friction angle "
                "the thesis never states (twice Table 8's), and its reversals are not all at the "
                f"cone as Fig 31's caption has them (k = 5: {why[5.0]}; k = 2: {why[2.0]}).\n"
            )
    both = [
        (rd.key, ln)
        for rd in readings
        for ln in STICKS_READ
        if reproduces(res[(rd.key, ln, 5.0)][1], res[(rd.key, ln, 2.0)][1])
    ]
    pairs = [f"{key} on {ln:g} mm" for key, ln in both]
    least = min(
        [res[(key, ln, 5.0)][1].omega_dev_deg for key, ln in both]
        + [sc.least_dev_deg for sc in (scans or {}).values()],
        default=math.inf,
    )
    if good:
        out.append(f"**Reproduces both statements: {', '.join(good)}.**\n")
        return "\n".join(out)
    shown = math.isfinite(least)
    out.append(
        "**No reading the text supports reproduces both statements on the 98.46 mm stick** "
        "from the report's grasp."
        + (
            " The runs here that show both — "
            + "; ".join(pairs + (["the grasps in the scan"] if scans else []))
            + f" — all let ω leave the {ALPHA_DEG:g}° cone of Table 8 (each k = 5 run reaches "
            f"abs(ω − 90°) ≥ {least:.1f}°)."
            if shown
            else ""
        )
        + " The one mechanism found that gives the shape of the thesis's two statements is the "
        "stick turning past perpendicular to Finger 2's virtual link, which needs ωB to leave "
        "that cone (a wider α, or no test on ωB): a reading the surviving text neither states "
        "nor excludes. Whether the thesis's program did so cannot be checked.\n"
    )
    return "\n".join(out)


_ALPHA45_PNG = "stick_98_46_alpha45_sigma.png"
_EQ39_PNG = "stick_98_46_eq39_sigma.png"


def plot_readings(
    res: ReadingResults,
    scans: dict[tuple[str, float], ReadingScan],
    ctx: ModelContext,
    out: Path,
) -> None:
    """σ on the 98.46 mm stick under eq 3.9's exact “=” (the report's grasp), and with α = 45°
    from the first mirror grasp that shows both statements."""
    eq39 = [res[("eq 3.9 “=”, root tried last", MAIN_LENGTH, k)][0] for k in KS]
    title = "Stick 98.46 mm, eq 3.9 with an exact “=” (root tried last kept): σ"
    plot_inclination(eq39, out / _EQ39_PNG, title)
    g = scans[("α = 45°", MAIN_LENGTH)].example
    if g is not None:
        runs = [simulate(g, Params(k, alpha=math.radians(45.0)), ctx) for k in KS]
        title = (
            f"Stick 98.46 mm, α = 45°, S1 = S2 = {g.contact1.S:.1f} mm, ψ1 = "
            f"{math.degrees(g.pose.phi2 + g.pose.phi3):.1f}°: σ (reversals red, stalls grey)"
        )
        plot_inclination(runs, out / _ALPHA45_PNG, title)


def link_normal_range(ctx: ModelContext, sensor: bool, n: int = 400) -> tuple[float, float]:
    """Angle (deg) between the virtual link C→A and the pad's outward normal at the contact:
    θ − atan(−dy3/dx3), over the sensor's range of L (``sensor``) or the whole pad."""
    pad = ctx.geom.pad
    lo = pad.pad_base_to_active_mm if sensor else 0.0
    hi = lo + pad.sensor_active_length_mm if sensor else pad.max_L_mm
    vals = []
    for i in range(n + 1):
        x3 = x3_from_L(lo + (hi - lo) * i / n, pad)
        theta = virtual_joint(x3, pad_y3(x3, pad))[1]
        vals.append(math.degrees(theta - math.atan(-pad_slope(x3, pad))))
    return min(vals), max(vals)


def _printed_text(run: Run, k: float) -> str:
    revs = ", ".join(f"{it.i} ({it.reversal})" for it in run.reversals)
    n = sum(it.target is not None for it in run.iterations)
    return (
        f"with k = {k:g} it commands {n} iteration{'s' * (n != 1)}, reverses at {revs} and "
        f"ends {run.end}"
    )


def _list(xs: Sequence[float]) -> str:
    return ", ".join(f"{x:g}" for x in xs)


def _span(s: Summary) -> float:
    return s.sigma_deg[1] - s.sigma_deg[0]


def _reasons(ss: Iterable[Summary]) -> str:
    c = Counter(why for s in ss for _, why, _ in s.reversals)
    return ", ".join(f"{why} × {n}" for why, n in c.most_common())


def _reversal_text(s: Summary) -> str:
    revs = ", ".join(f"{i} ({why})" for i, why, _ in s.reversals)
    return (
        f"Reversals at iterations {revs}; σ {_rng(s.sigma_deg)}°; ωA "
        f"{_rng(s.omega_A_deg)}°, ωB {_rng(s.omega_B_deg)}° (cone {90 - ALPHA_DEG:g}–"
        f"{90 + ALPHA_DEG:g}°); φ2 {_rng(s.phi_deg['phi2'], 1)}°, φ3 "
        f"{_rng(s.phi_deg['phi3'], 1)}°, φ4 {_rng(s.phi_deg['phi4'], 1)}°, φ5 "
        f"{_rng(s.phi_deg['phi5'], 1)}°."
    )


def _rate_range(run: Run, ctx: ModelContext) -> tuple[float, float]:
    """The first-order dσ of the route alone per Δφ (°/°) over a run's iterations."""
    rates = [route_rate(it, run.grasp, run.params, ctx) for it in run.iterations]
    return min(rates), max(rates)


# --- main -------------------------------------------------------------------------------------


def run_all(cfg: Settings) -> dict[tuple[float, float], Run]:
    ctx = cfg.model_context()
    out = {}
    for length in LENGTHS:
        g = grasp_from_settings(length, cfg)
        for k in KS:
            out[(length, k)] = simulate(g, Params(k), ctx)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog="python -m experiments.sticks",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output directory")
    args = ap.parse_args(argv)
    cfg = load_config(use_env=False)
    ctx = cfg.model_context()
    out: Path = args.out
    out.mkdir(parents=True, exist_ok=True)
    runs = run_all(cfg)
    for k in KS:
        fig = "Fig 31" if k == 5.0 else "Fig 32"
        title = f"Stick {MAIN_LENGTH:g} mm, k = {k:g} (thesis {fig}), kinematic"
        plot_run(runs[(MAIN_LENGTH, k)], ctx, out / _png(MAIN_LENGTH, k), title)
    for length in LENGTHS[1:]:
        plot_inclination(
            [runs[(length, k)] for k in KS],
            out / _png(length),
            f"Stick {length:g} mm: inclination σ for k = 5 and k = 2",
        )
    scans = [scan_grasps(mirror_grasps(ln, ctx), k, ctx, "mirror") for ln in LENGTHS for k in KS]
    free = any_grasps(MAIN_LENGTH, ctx)
    scans += [scan_grasps(free, k, ctx, "any") for k in KS]
    g = grasp_from_settings(MAIN_LENGTH, cfg)
    printed = {k: simulate(g, Params(k, printed_eq313=True), ctx) for k in KS}
    readings = reading_runs(cfg)
    rscans = reading_scans(ctx)
    plot_readings(readings, rscans, ctx, out)
    path = write_report(runs, scans, printed, ctx, cfg, out, root_test_runs(cfg), readings, rscans)
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
