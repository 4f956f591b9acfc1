"""The rolling iteration (hand-model.md §8; thesis §3.3–3.5) as a pure step function.

``step(state, pose, counts1, counts2, params, ctx)`` takes the previous :class:`RollState`, the
actual joint angles φ2…φ5 and the raw counts of the two distal pads, and returns a
:class:`StepResult`: the four joint targets to command, or none and the reason the rotation
reverses, plus every quantity the thesis plots. No I/O, no clock: the runner feeds it fresh
frames, and the same inputs always give the same result.

Two-finger mode (default, §3.4–3.5): Finger 2 follows its route (φ4 − Δφ, φ5 + k·Δφ); the
inclination change it imposes, dσ, is reinforced by λ; Finger 1 puts A on the circle of radius
Λad around the new B at inclination σd. One-finger mode (§3.3): Finger 2 holds still and Finger 1
turns A around B by dσ per iteration.

Additions to the thesis (explained here and in config/default.toml), for objects nobody tuned it
for: a half stroke counts only once Finger 2 has travelled ``min_half_stroke_deg`` along its
route and the object has turned TURN_MARGIN × that by the rolling kinematics of its contacts
(:attr:`RollState.turned`); a reversal for any reason but a lost contact commits to the way back
(:attr:`RollState.waived`; a cone's way back goes on while its contact is still outside it
and each plan leans it less, :func:`_retreats`), and the pad's edge never refuses a way back,
nor, once the rotation dithers without half strokes, from its row's inner half
(:func:`_edge_refuses`); the cones are as wide as the grasp held
(:attr:`RollState.alpha_held`), and as wide as a contact holds once its cone refuses both
ways; a plan that widens the pads' wedge beyond its limit reverses; a plan Finger 1 cannot
follow reverses; Finger 1's step limit; the force band.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from sdh2svc.control.params import RollingParams
from sdh2svc.control.plan import finger1_to, grip_force, omegas, sigma_desired
from sdh2svc.control.route import Move, Predictor, candidates, finger2_move, turn_sense
from sdh2svc.model.friction import cone_margin, inside_cone, wedge
from sdh2svc.model.kinematics import (
    Finger,
    HandPoints,
    HandPose,
    IKFailure,
    IKResult,
    Point,
    contact_point,
)
from sdh2svc.model.observe import ModelContext, Observation, observe, rolling_turn

# How far beyond a cone the way back may plan ω (see RollState.waived): a rolling contact drifts
# from the plan by ≈ 0.3° per iteration, and sensor noise moves the measured ω by a few tenths.
RETREAT_LIMIT = math.radians(2.0)
# How far the way back is waived, in minimum half strokes (``min_half_stroke_deg``): ω turns
# back slowly after a reversal (the contact rolls on a little and the route first mostly moves
# the other contact), so a way back as short as one minimum half stroke meets the other
# direction's check while ω is still where the reversal left it, and the strokes shrink to a
# dither of ≈ 1° that barely turns the object.
WAY_BACK = 2.0
# A half stroke counts only once the object has turned min_half_stroke_deg by the rolling
# estimate (:func:`~sdh2svc.model.observe.rolling_turn`) times this: the estimate is within 20 %
# of the true turn on 94 % of half strokes (experiments/recognition/report.md), so an estimate
# of 1.2 × the minimum is at least the minimum of true turn.
TURN_MARGIN = 1.2


class Reversal(StrEnum):
    """Why the rotation direction reverses instead of commanding the next configuration."""

    CONE_A = "cone_A"  # ωA would leave 90° ± α
    CONE_B = "cone_B"  # ωB would leave 90° ± α
    WEDGE = "wedge"  # the pads' wedge, (ωA + ωB)/2 − 90°, would grow beyond its limit
    WORKSPACE = "workspace"  # Finger 2's next angles (or Finger 1's) outside the joint limits
    IK_UNREACHABLE = "ik_unreachable"  # Finger 1 cannot reach Ad
    CONTACT_EDGE = "contact_edge"  # a contact sits on the pad's first or last row
    CONTACT_LOST = "contact_lost"  # F1 or F2 at or below the contact threshold
    FORCE = "force"  # F above force_reverse × Fd and not falling


@dataclass(frozen=True, slots=True)
class RollState:
    """What one iteration hands to the next."""

    direction: int = 1  # +1: Δφ as configured; −1: reversed
    F_prev: float | None = None
    # reversals after Finger 2 travelled at least min_half_stroke_deg and the object turned
    # TURN_MARGIN × that (see ``turned``)
    half_strokes: int = 0
    iteration: int = 0
    consecutive_reversals: int = 0  # reversals since the last half stroke
    travel: float = 0.0  # Finger 2's route travel since the last reversal (rad of φ4; σ in
    # one-finger mode)
    # The check that caused the last reversal (any but a lost contact). While set, and until
    # ``travel`` reaches WAY_BACK half strokes, the way back is waived by the cones, the wedge,
    # the pad's edge and the force.
    # The plan respects a cone, but the rolling contact does not follow it exactly and can carry
    # ω past the limit (or a contact onto the edge row); near the end of a stroke the route then
    # barely changes ω, so both directions would "leave" the cone, a noisy ω or edge flag
    # flickers, and the thesis's rule reverses on the spot for ever. And at the end of a stroke
    # one check often stops one way and another the other way (the edge of Finger 1's pad and
    # Finger 2's cone, or Finger 1's reach and a cone): each waiving only itself, they refuse
    # both ways in turn. A cone still refuses a plan beyond it by more than RETREAT_LIMIT.
    waived: Reversal | None = None
    # The largest |ω − 90°| at the first iteration: the grasp holds the object there, so its
    # friction angle is at least this; the cones are max(α, this) wide. A grasp can end with AB
    # tilted beyond α against the pads (small objects touching the pads at different heights),
    # where the thesis's rule would refuse both directions from the start. Later, a cone that
    # refuses the way back from its own reversal widens them to its contact's |ω − 90°| then
    # (see _cone_held).
    alpha_held: float = 0.0
    # The object's rotation since the last half stroke ended (rad, rolling kinematics: the sum
    # of rolling_turn from one iteration to the next), and its largest excursion, ``turned``:
    # a reversal ends a half stroke only once the object has really turned. Finger 2's travel
    # alone does not tell: near a cone or the pad's end the fingers can move a degree while the
    # object turns a tenth of one, and such strokes are a dither, not a roll.
    turn: float = 0.0
    turned: float = 0.0
    # |ω − 90°| of the contact whose cone caused the last reversal, at that reversal (0.0 after
    # any other): its way back retreats on only while the contact leans less (_retreats)
    lean: float = 0.0
    prev: Observation | None = None  # the last iteration's observation (for rolling_turn)
    # Re-centring (``recentre_strokes``): the reference stroke's mean wedge (_stroke_wedge);
    # over the current half stroke and the last, the wedge's sum, its count, and the iterations
    # the lean could not act (at its bound, or no slope: _recentre); the last full stroke's mean
    # wedge minus the reference's with that stroke's iterations, and the sum of those errors
    # over the strokes the lean could act on (its integral)
    wedge_ref: float | None = None
    wedge_now: tuple[float, int, int] = (0.0, 0, 0)
    wedge_last: tuple[float, int, int] | None = None
    wedge_error: float = 0.0
    wedge_integral: float = 0.0
    stroke_iterations: int = 0

    @property
    def strokes(self) -> int:
        """Completed back-and-forth strokes (two reversals each)."""
        return self.half_strokes // 2

    def cone(self, p: RollingParams) -> float:
        """The friction cones' half-angle (rad): α, widened to what the grasp and the contacts
        held (:attr:`alpha_held`)."""
        return max(p.alpha, self.alpha_held)


@dataclass(frozen=True, slots=True)
class Plan:
    """The next configuration as far as it was worked out (radians, mm)."""

    Lambda_ad: float
    sigma_d: float | None = None
    A_d: Point | None = None
    B_d: Point | None = None
    omega_A_d: float | None = None  # at the desired configuration
    omega_B_d: float | None = None


@dataclass(frozen=True, slots=True)
class StepResult:
    """The decision of one iteration and everything it computed (F, ΔF in library units)."""

    state: RollState
    targets: HandPose | None  # None: command nothing this iteration
    reversal: Reversal | None
    obs: Observation
    F: float
    dF: float
    plan: Plan | None
    alpha: float  # the friction cones' half-angle from this iteration on (RollState.cone)

    @property
    def points(self) -> HandPoints | None:
        return self.obs.points


def _adjusted_lambda(lam: float, F: float, dF: float, p: RollingParams) -> float:
    """Λad: open by ΔΛ_inc when the force rises, close by ΔΛ_dec when it falls (hand-model §8);
    a change within the deadband is no change. Outside the force band the level decides (the
    derivative rule alone lets slow drifts through): below it close, above it open — or hold
    while the force is already on its way back. Never the derivative rule outside: a rise
    below the band is mostly the last closing's own, and opening on it undid that closing,
    a cycle that grows on a stiff object until the grip is lost."""
    rising, falling = dF > p.force_deadband, dF < -p.force_deadband
    if F < p.force_band_low * p.grasp_force:
        return lam if rising else lam - p.delta_lambda_dec_mm
    if F > p.force_band_high * p.grasp_force:
        return lam if falling else lam + p.delta_lambda_inc_mm
    if rising:
        return lam + p.delta_lambda_inc_mm
    if falling:
        return lam - p.delta_lambda_dec_mm
    return lam


@dataclass(frozen=True, slots=True)
class _Config:
    """One candidate next configuration: Finger 2's angles, the plan and Finger 1's IK."""

    phi4d: float
    phi5d: float
    plan: Plan
    ik: IKResult
    travel: float  # the route's step (rad of φ4; of σ in one-finger mode)


@dataclass(frozen=True, slots=True)
class _Route:
    """Steps 4–7 of hand-model §8 for one iteration, at a fraction of the full step."""

    state: RollState
    pose: HandPose
    obs: Observation
    lam_ad: float
    params: RollingParams
    ctx: ModelContext
    move: Move  # Finger 2's full step (control/route.py)
    bias: float = 0.0  # added to σd at the full step (re-centring, _recentre)

    def configure(self, scale: float) -> _Config | None:
        """The configuration ``scale`` × (Δφ, or dσ in one-finger mode) ahead; None when
        Finger 2's next angles leave its joint limits."""
        p, pose, obs, geom = self.params, self.pose, self.obs, self.ctx.geom
        c2 = obs.contact2
        assert obs.points is not None and obs.sigma is not None
        assert c2.r_mm is not None and c2.theta_rad is not None
        if p.mode == "two-finger":
            phi4d, phi5d = pose.phi4 + scale * self.move.d4, pose.phi5 + scale * self.move.d5
            if not self.ctx.limits2.contains(phi4d, phi5d):
                return None
            B_d = contact_point(Finger.TWO, phi4d, phi5d, c2.r_mm, c2.theta_rad, geom)
            sigma_d = sigma_desired(obs, B_d, p.lambda_gain) + scale * self.bias
        else:
            phi4d, phi5d, B_d = pose.phi4, pose.phi5, obs.points.B
            sigma_d = obs.sigma + scale * self.state.direction * p.d_sigma
        A_d, ik = finger1_to(obs, B_d, sigma_d, self.lam_ad, self.ctx)
        step = scale * (abs(p.delta_phi) if p.mode == "two-finger" else abs(p.d_sigma))
        return _Config(phi4d, phi5d, Plan(self.lam_ad, sigma_d, A_d, B_d), ik, step)


# The half stroke whose end, with the one before, makes the re-centring's reference stroke: the
# second full stroke between two reversals (half strokes 4 and 5). The first half stroke starts
# at the grasp, halfway along the route, and the first strokes still settle in from it
# (bench-v1's polygon-151 turns 2.4°, 8.1°, 11.3°, 15.5°, 16.8° in its first five half strokes;
# the egg's first strokes last 250, 438, 444 iterations): held to one of those, a run is leaned
# towards where it started, not back from where it drifted. A run of 3 strokes is never leaned.
REFERENCE_HALF_STROKE = 5
# The largest lean of σd the re-centring adds per iteration (rad), about what the rolling itself
# turns σ by per iteration: a bound for a slope the model gets wrong, not the rule's gain.
RECENTRE_MAX = math.radians(0.025)
# σd's change the wedge's slope is taken over, either way (rad)
RECENTRE_PROBE = math.radians(0.5)
# A slope below this (wedge per σd) leaves the wedge to the rolling: σ would lean on and on
# while the wedge barely moves (the contacts on flat faces, where the wedge is the faces')
RECENTRE_MIN_SLOPE = 0.1


def _recentre(route: _Route) -> tuple[float, bool]:
    """σd's lean this iteration (rad) that brings the pads' wedge, averaged over the last full
    stroke, back to the reference stroke's within ``recentre_strokes`` strokes, and whether the
    lean could not act on the error (held at its bound, or no slope to act through).

    Nothing in the thesis's plan holds the wedge: Finger 2 follows its route, Finger 1 puts A
    at σd from B, and Λ follows the force; the grasp's one remaining freedom, how the pads lean
    on the object, is left to the rolling, and what each stroke leaves of it (the contacts roll
    a little further one way than back) adds up. On the egg the stroke's mean wedge grew from
    5° to 12.5° in 180 strokes, Finger 1 straightened towards its reach, the strokes shrank from
    412 to 70 iterations, and the run ended stuck. The lean spreads the last stroke's error over
    ``recentre_strokes`` strokes' iterations, through the model's slope of the wedge in σd
    (the route's full step planned at σd ± RECENTRE_PROBE).

    The error acted on is the last stroke's plus the errors' sum since the reference over 2 ×
    ``recentre_strokes`` (their integral, the lean's own horizon its time: a PI rule): with the
    error alone, a drift that goes on stroke after stroke is held only where the lean balances
    it, an error of ``recentre_strokes`` strokes' drift (a triangle's settled ≈ 6° above its
    reference); the integral takes that offset back too."""
    p, st = route.params, route.state
    if p.recentre_strokes <= 0.0 or st.stroke_iterations == 0 or p.mode != "two-finger":
        return 0.0, False  # off, no full stroke since the reference yet, or σ is the route
    w = []
    for d in (-RECENTRE_PROBE, RECENTRE_PROBE):
        cfg = replace(route, bias=d).configure(1.0)
        if cfg is None or cfg.ik.solution is None:
            return 0.0, True
        assert cfg.plan.A_d is not None and cfg.plan.B_d is not None
        phi = (cfg.ik.solution.proximal, cfg.ik.solution.distal, cfg.phi4d, cfg.phi5d)
        w.append(wedge(*omegas(route.obs, phi, cfg.plan.A_d, cfg.plan.B_d, route.ctx)))
    slope = (w[1] - w[0]) / (2 * RECENTRE_PROBE)
    if abs(slope) < RECENTRE_MIN_SLOPE:
        return 0.0, True
    error = st.wedge_error + st.wedge_integral / (2.0 * p.recentre_strokes)
    lean = -error / slope / (p.recentre_strokes * st.stroke_iterations)
    bound = max(-RECENTRE_MAX, min(RECENTRE_MAX, lean))
    # held at its bound, the integral would only grow while the stroke's error pushes the same
    # way (wind-up); while it pushes back, the integral unwinds
    return bound, bound != lean and st.wedge_error * error > 0.0


# A slower plan may still need a little more than Finger 1's step (the step's scaling is linear,
# the inverse kinematics not); more than this factor means it cannot follow at any speed.
FOLLOW_SLACK = 1.5


def _finger1_step(cfg: _Config, pose: HandPose) -> float:
    assert cfg.ik.solution is not None
    return max(abs(cfg.ik.solution.proximal - pose.phi2), abs(cfg.ik.solution.distal - pose.phi3))


# Every reversal but a lost contact commits to its way back, which retraces the travel that led
# to it. A stroke that ends at Finger 1's reach or a joint limit has often carried a contact a
# little past its cone on the way (a diagonal grip held at ωB = 112°): refused by the cone on the
# way back and by the reach on the way forward, the run was stuck. A lost contact has no way
# back to trust.
_WAIVABLE = frozenset(Reversal) - {Reversal.CONTACT_LOST}


def _reverse(
    state: RollState, F: float, reason: Reversal, p: RollingParams, obs: Observation
) -> RollState:
    ended = (state.travel >= p.min_half_stroke
             and state.turned >= TURN_MARGIN * p.min_half_stroke)  # fmt: skip
    nxt = replace(
        state,
        direction=-state.direction,
        F_prev=F,
        half_strokes=state.half_strokes + ended,
        iteration=state.iteration + 1,
        consecutive_reversals=1 if ended else state.consecutive_reversals + 1,
        travel=0.0,
        waived=reason if reason in _WAIVABLE else None,
        alpha_held=max(state.alpha_held, _cone_held(reason, _waived(state, p), obs)),
        turn=0.0 if ended else state.turn,
        turned=0.0 if ended else state.turned,
        lean=_cone_lean(reason, obs),
    )
    return _stroke_wedge(nxt) if ended else nxt


def _stroke_wedge(state: RollState) -> RollState:
    """``state`` at a half stroke's end (``half_strokes`` counts it): the mean wedge over it
    and the half stroke before (a full stroke) and their iterations. The full stroke ending
    with half stroke REFERENCE_HALF_STROKE is the reference the later ones are held to
    (``wedge_ref``); each later one's error adds to their integral (``wedge_integral``) by the
    share of its iterations whose lean was free to act."""
    last, now = state.wedge_last, state.wedge_now
    state = replace(state, wedge_now=(0.0, 0, 0), wedge_last=now)
    n = 0 if last is None else last[1] + now[1]
    if state.half_strokes < REFERENCE_HALF_STROKE or last is None or n == 0:
        return state
    mean = (last[0] + now[0]) / n
    if state.wedge_ref is None:
        return replace(state, wedge_ref=mean)
    error = mean - state.wedge_ref
    acted = max(0.0, 1.0 - (last[2] + now[2]) / n)  # the share of the stroke the lean could act
    return replace(state, wedge_error=error, stroke_iterations=n,
                   wedge_integral=state.wedge_integral + acted * error)  # fmt: skip


def _cone_lean(cone: Reversal, obs: Observation) -> float:
    """|ω − 90°| now of the contact whose cone is ``cone`` (0.0 for any other check, or
    without ω)."""
    w = {Reversal.CONE_A: obs.omega_A, Reversal.CONE_B: obs.omega_B}.get(cone)
    return 0.0 if w is None else abs(w - math.pi / 2)


def _turned(state: RollState, obs: Observation, ctx: ModelContext) -> RollState:
    """The state with the object's turn since the last iteration added (rolling kinematics)
    and this observation kept for the next."""
    d = None if state.prev is None else rolling_turn(state.prev, obs.pose, ctx)
    if d is None:
        return replace(state, prev=obs)
    turn = state.turn + d
    return replace(state, turn=turn, turned=max(state.turned, abs(turn)), prev=obs)


def _cone_held(reason: Reversal, waived: Reversal | None, obs: Observation) -> float:
    """A cone that refuses the way back from its own reversal (``waived``: less than WAY_BACK
    half strokes ago) refuses both ways, while its contact holds the object where it is: the
    object's friction angle is at least that contact's |ω − 90°| now, and the cones widen to
    it, as they do to what the grasp held (:attr:`RollState.alpha_held`). The way back may then
    go RETREAT_LIMIT beyond it; the object is pushed further only where it held. 0.0 for any
    other reversal."""
    return _cone_lean(reason, obs) if reason is waived else 0.0


def _wedge_refuses(wa: float, wb: float, obs: Observation, waived: Reversal | None,
                   p: RollingParams) -> bool:  # fmt: skip
    """Whether the plan takes the pads' wedge beyond its limit and wider than it is now. With
    both ω beyond 90° on the same side, both contacts slide the same way and the squeeze pushes
    the object out between the pads once both exceed the object's own friction angle; the
    smaller of the two is at most the wedge, so a wedge within the lowest friction angle the
    lab expects keeps one contact holding whatever α assumes."""
    limit = p.wedge_limit
    if limit <= 0.0 or obs.omega_A is None or obs.omega_B is None:
        return False
    planned = abs(wedge(wa, wb))
    if planned <= limit or waived is not None:
        return False
    return planned > abs(wedge(obs.omega_A, obs.omega_B))


def _edge_refuses(state: RollState, p: RollingParams, obs: Observation,
                  ctx: ModelContext) -> bool:  # fmt: skip
    """Whether a contact on the pad's edge reverses the rotation (a contact on the first or
    last row: ``at_edge``, within ``edge_margin_rows`` of its centre), never on a way back.

    Once the rotation has reversed ESCAPE_AFTER times in a row without a half stroke, the edge
    zone's inner half is given up: near a turning point of the route the object's rotation
    reverses within the half stroke and brings the contact back onto the edge row either way,
    and the thesis's rule dithers there until stuck. Only its outer half still refuses: a
    contact whose centroid nears the last row's centre is rolling off the pad (its sensed force
    falls), and beyond it nothing would be sensed."""
    if _on_way_back(state, p):
        return False
    c1, c2 = obs.contact1, obs.contact2
    if state.consecutive_reversals < ESCAPE_AFTER:
        return c1.at_edge or c2.at_edge
    outer = ctx.calib.edge_margin_rows / 2
    return any(c.edge_rows is not None and c.edge_rows < outer for c in (c1, c2))


def _on_way_back(state: RollState, p: RollingParams) -> bool:
    """Whether the rotation reversed, for any reason, less than WAY_BACK half strokes ago. The
    pad's edge refuses no such way back, a lost contact's included (the other checks follow
    ``waived``, see _WAIVABLE): it retraces the travel that carried the contact to the edge
    (bench-v1's circle-327 was stuck between the reach one way and the edge row the other)."""
    return state.consecutive_reversals > 0 and _within_way_back(state, p)


def _waived(state: RollState, p: RollingParams) -> Reversal | None:
    """The check the way back is waived by (:attr:`RollState.waived`) while it lasts."""
    return state.waived if _within_way_back(state, p) else None


def _within_way_back(state: RollState, p: RollingParams) -> bool:
    """Whether Finger 2 has travelled less than WAY_BACK half strokes since the last reversal."""
    return state.travel < WAY_BACK * p.min_half_stroke


def _cone_refuses(w_d: float, waived: Reversal | None, alpha: float) -> bool:
    """Whether the planned ω ``w_d`` reverses the rotation: it leaves the cone (thesis), unless
    on the way back (``waived``) ω stays within RETREAT_LIMIT beyond it."""
    if inside_cone(w_d, alpha):
        return False
    return waived is None or cone_margin(w_d, alpha) < -RETREAT_LIMIT


def step(
    state: RollState,
    pose: HandPose,
    counts1: np.ndarray,
    counts2: np.ndarray,
    params: RollingParams,
    ctx: ModelContext,
) -> StepResult:
    """One rolling iteration (hand-model §8, step 2)."""
    obs = observe(pose, counts1, counts2, ctx)
    state = _turned(state, obs, ctx)
    c1, c2 = obs.contact1, obs.contact2
    F = grip_force(c1, c2)
    dF = 0.0 if state.F_prev is None else F - state.F_prev

    if obs.omega_A is not None and obs.omega_B is not None:
        w = wedge(obs.omega_A, obs.omega_B)
        total, count, blocked = state.wedge_now
        state = replace(state, wedge_now=(total + w, count + 1, blocked))
        if state.iteration == 0:
            held = max(abs(obs.omega_A - math.pi / 2), abs(obs.omega_B - math.pi / 2))
            state = replace(state, alpha_held=held)
    alpha = state.cone(params)
    waived = _waived(state, params)

    def reverse(reason: Reversal, plan: Plan | None = None) -> StepResult:
        nxt = _reverse(state, F, reason, params, obs)
        return StepResult(nxt, None, reason, obs, F, dF, plan, nxt.cone(params))

    present = min(c1.force, c2.force) > params.contact_force_min
    if not present or obs.points is None or obs.Lambda is None or obs.sigma is None:
        return reverse(Reversal.CONTACT_LOST)
    if _edge_refuses(state, params, obs, ctx):
        return reverse(Reversal.CONTACT_EDGE)
    if F > params.force_reverse * params.grasp_force and dF >= 0.0 and waived is None:
        return reverse(Reversal.FORCE)
    assert c1.r_mm is not None and c1.theta_rad is not None and c1.x3_mm is not None
    assert c2.r_mm is not None and c2.theta_rad is not None and c2.x3_mm is not None

    lam_ad = _adjusted_lambda(obs.Lambda, F, dF, params)
    move = finger2_move(state.direction, Predictor(pose, obs, lam_ad, alpha, params, ctx))
    route = _Route(state, pose, obs, lam_ad, params, ctx, move)
    lean, lean_held = _recentre(route)
    route = replace(route, bias=lean)
    if lean_held:
        total, count, blocked = state.wedge_now
        state = replace(state, wedge_now=(total, count, blocked + 1))
    reason, plan, cfg = _attempt(route, waived, alpha)
    if reason is not None and state.consecutive_reversals >= ESCAPE_AFTER:
        reason, plan, cfg = _escape(route, waived, alpha, (reason, plan, cfg))
    if reason is not None or cfg is None:
        return reverse(reason or Reversal.WORKSPACE, plan)
    assert cfg.ik.solution is not None
    nxt = replace(state, F_prev=F, iteration=state.iteration + 1,
                  travel=state.travel + cfg.travel)  # fmt: skip
    targets = HandPose(cfg.ik.solution.proximal, cfg.ik.solution.distal, cfg.phi4d, cfg.phi5d)
    return StepResult(nxt, targets, None, obs, F, dF, plan, alpha)


_Attempt = tuple[Reversal | None, Plan, _Config | None]


def _attempt(route: _Route, waived: Reversal | None, alpha: float) -> _Attempt:
    """Steps 4–7 for the route's move: the configuration to command, or why the rotation
    reverses instead (with the plan as far as it was worked out)."""
    params, pose, obs = route.params, route.pose, route.obs
    cfg = route.configure(1.0)
    if cfg is None:
        return Reversal.WORKSPACE, Plan(route.lam_ad), None
    if cfg.ik.solution is not None:  # Finger 1 can follow at most its step per iteration
        need = _finger1_step(cfg, pose)
        if need > params.finger1_max_step:
            # slowed to Finger 1's step; a slowed plan out of reach reverses below as any
            # unreachable plan does, never falling back to the full step (which the runner's
            # per-axis clamp would then cut off Finger 1's path)
            slower = route.configure(params.finger1_max_step / need)
            if slower is None:
                return Reversal.WORKSPACE, cfg.plan, None
            cfg = slower
            # still too far at a fraction of the step: Λ's own correction needs it, near a
            # stretched Finger 1 (singular); the servo could not follow
            if (
                cfg.ik.solution is not None
                and _finger1_step(cfg, pose) > FOLLOW_SLACK * params.finger1_max_step
            ):
                return Reversal.WORKSPACE, cfg.plan, None
    plan, ik = cfg.plan, cfg.ik
    assert plan.A_d is not None and plan.B_d is not None
    if ik.solution is None:
        limits = ik.failure is IKFailure.JOINT_LIMITS
        return (Reversal.WORKSPACE if limits else Reversal.IK_UNREACHABLE), plan, None
    phi = (ik.solution.proximal, ik.solution.distal, cfg.phi4d, cfg.phi5d)
    wa, wb = omegas(obs, phi, plan.A_d, plan.B_d, route.ctx)
    plan = replace(plan, omega_A_d=wa, omega_B_d=wb)
    for cone, w_d in ((Reversal.CONE_A, wa), (Reversal.CONE_B, wb)):
        if _cone_refuses(w_d, waived, alpha) and not _retreats(cone, w_d, route, alpha):
            return cone, plan, None
    if _wedge_refuses(wa, wb, obs, waived, params):
        return Reversal.WEDGE, plan, None
    return None, plan, cfg


def _retreats(cone: Reversal, w_d: float, route: _Route, alpha: float) -> bool:
    """Whether the way back from ``cone``'s reversal goes on beyond WAY_BACK: while that cone's
    contact is still outside it but leans less than at the reversal (:attr:`RollState.lean`), a
    plan that leans it less than it leans now, and no more than RETREAT_LIMIT beyond the cone,
    retreats on. A way back that ended a tenth of a degree outside the cone was refused there as
    if it were a new lean, and the rotation dithered at the same cone either way until stuck
    (bench-v1's ellipse-212, at cone B). A contact that leans as far as at the reversal, or
    further, is not coming back: a sliding contact stays at its friction angle whatever the
    plan, which assumes it rolls (confirm2115-polygon-001 slid the length of its pad with ωB
    held 1° outside the cone)."""
    state = route.state
    if state.waived is not cone or _within_way_back(state, route.params):
        return False
    lean = _cone_lean(cone, route.obs)
    if lean < alpha or lean >= state.lean:  # inside the cone, or not coming back
        return False
    margin = cone_margin(w_d, alpha)
    return margin > alpha - lean and margin >= -RETREAT_LIMIT


# Reversals in a row without a half stroke after which a refused move looks for another way.
ESCAPE_AFTER = 2


def _escape(route: _Route, waived: Reversal | None, alpha: float, refused: _Attempt) -> _Attempt:
    """When the rotation has reversed without travelling, both directions along the thesis's
    line through joint space are blocked (a cone one way and Finger 1's reach the other, or
    the same cone both ways, where the pad turns about as fast as AB). Finger 2 then tries the
    moves of the same length turned away from its route (control/route.py's candidates,
    nearest first) and takes the first that passes every check and still turns AB the
    stroke's way; none: the refusal stands."""
    if route.params.mode != "two-finger" or route.obs.sigma is None:
        return refused
    sense = turn_sense(route.move, route.pose, route.obs, route.ctx)
    if sense == 0.0:
        return refused
    for move in candidates(route.move)[1:]:
        reason, plan, cfg = _attempt(replace(route, move=move), waived, alpha)
        if (
            reason is None
            and plan.sigma_d is not None
            and (plan.sigma_d - route.obs.sigma) * sense > 0.0
        ):
            return reason, plan, cfg
    return refused
