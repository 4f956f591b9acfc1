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

Two additions to the thesis's reversal rule: a half stroke counts only when it moved, and when
the rolling contact has carried ω past a cone's limit, or a contact onto the pad's edge row, the
way back is not refused for still being there (see :attr:`RollState.out_A`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from enum import StrEnum

import numpy as np

from sdh2svc.control.params import RollingParams
from sdh2svc.model.friction import cone_margin, inside_cone, omega
from sdh2svc.model.kinematics import (
    Finger,
    HandPoints,
    HandPose,
    IKFailure,
    IKResult,
    Point,
    contact_point,
    finger_ik,
    segment,
)
from sdh2svc.model.observe import ModelContext, Observation, observe

# How much further out than now a step back may take ω (see RollState.out_A): the step's own
# effect on ω near a reversal is about 0.01°, the drift of a rolling contact 0.3° per iteration.
RETREAT_SLACK = math.radians(0.1)


class Reversal(StrEnum):
    """Why the rotation direction reverses instead of commanding the next configuration."""

    CONE_A = "cone_A"  # ωA would leave 90° ± α
    CONE_B = "cone_B"  # ωB would leave 90° ± α
    WORKSPACE = "workspace"  # Finger 2's next angles (or Finger 1's) outside the joint limits
    IK_UNREACHABLE = "ik_unreachable"  # Finger 1 cannot reach Ad
    CONTACT_EDGE = "contact_edge"  # a contact sits on the pad's first or last row
    CONTACT_LOST = "contact_lost"  # F1 or F2 at or below the contact threshold


@dataclass(frozen=True, slots=True)
class RollState:
    """What one iteration hands to the next."""

    direction: int = 1  # +1: Δφ as configured; −1: reversed
    F_prev: float | None = None
    half_strokes: int = 0  # half strokes that moved: a reversal on the spot is not one
    iteration: int = 0
    consecutive_reversals: int = 0
    last_move: int = 0  # the direction of the last commanded move (0: none yet)
    # While the measured ωA (ωB) is outside its cone: the direction of the move that carried it
    # out, else 0. The plan respects the cone, but the rolling contact does not follow the plan
    # exactly and can carry ω past the limit; near the end of a stroke the route then barely
    # changes ω (the pad and AB turn together), so both directions would "leave" the cone and
    # the thesis's rule reverses on the spot for ever. A step in the other direction passes that
    # cone's check unless it takes ω further out than now.
    out_A: int = 0
    out_B: int = 0
    out_edge: int = 0  # the same for a contact on its pad's first or last row

    @property
    def strokes(self) -> int:
        """Completed back-and-forth strokes (two reversals each)."""
        return self.half_strokes // 2


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

    @property
    def points(self) -> HandPoints | None:
        return self.obs.points


def _adjusted_lambda(lam: float, F: float, dF: float, p: RollingParams) -> float:
    """Λad: open by ΔΛ_inc when the force rises, close by ΔΛ_dec when it falls (hand-model §8);
    a change within the deadband is no change. Outside the force band the level decides (the
    derivative rule alone lets slow drifts through): below it close, above it open — unless
    the force is already on its way back, when the derivative rule decides as inside."""
    rising, falling = dF > p.force_deadband, dF < -p.force_deadband
    if F < p.force_band_low * p.grasp_force and not rising:
        return lam - p.delta_lambda_dec_mm
    if F > p.force_band_high * p.grasp_force and not falling:
        return lam + p.delta_lambda_inc_mm
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


@dataclass(frozen=True, slots=True)
class _Route:
    """Steps 4–7 of hand-model §8 for one iteration, at a fraction of the full step."""

    state: RollState
    pose: HandPose
    obs: Observation
    lam_ad: float
    params: RollingParams
    ctx: ModelContext

    def configure(self, scale: float) -> _Config | None:
        """The configuration ``scale`` × (Δφ, or dσ in one-finger mode) ahead; None when
        Finger 2's next angles leave its joint limits."""
        p, pose, obs, geom = self.params, self.pose, self.obs, self.ctx.geom
        c1, c2 = obs.contact1, obs.contact2
        assert obs.points is not None and obs.sigma is not None
        assert c1.r_mm is not None and c1.theta_rad is not None
        assert c2.r_mm is not None and c2.theta_rad is not None
        if p.mode == "two-finger":
            dphi = scale * self.state.direction * p.delta_phi
            phi4d, phi5d = pose.phi4 - dphi, pose.phi5 + p.k * dphi
            if not self.ctx.limits2.contains(phi4d, phi5d):
                return None
            B_d = contact_point(Finger.TWO, phi4d, phi5d, c2.r_mm, c2.theta_rad, geom)
            d_sigma = segment(obs.points.A, B_d)[1] - obs.sigma  # eq 3.13, sign typo fixed
            sigma_d = obs.sigma + p.lambda_gain * d_sigma
        else:
            phi4d, phi5d, B_d = pose.phi4, pose.phi5, obs.points.B
            sigma_d = obs.sigma + scale * self.state.direction * p.d_sigma
        lam = self.lam_ad
        A_d = Point(B_d.y - lam * math.cos(sigma_d), B_d.z - lam * math.sin(sigma_d))
        ik = finger_ik(Finger.ONE, A_d, c1.r_mm, c1.theta_rad, (pose.phi2, pose.phi3), geom,
                       self.ctx.limits1)  # fmt: skip
        return _Config(phi4d, phi5d, Plan(lam, sigma_d, A_d, B_d), ik)


def _reverse(state: RollState, F: float, reason: Reversal) -> RollState:
    moved = state.consecutive_reversals == 0 and state.iteration > 0
    return replace(
        state,
        direction=-state.direction,
        F_prev=F,
        half_strokes=state.half_strokes + moved,
        iteration=state.iteration + 1,
        consecutive_reversals=state.consecutive_reversals + 1,
    )


def _carried_out(was: int, out: bool, state: RollState) -> int:
    """The new RollState.out_A/out_B/out_edge, given whether the condition holds now."""
    return (was or state.last_move) if out else 0


def _outside(w: float | None, alpha: float) -> bool:
    return w is not None and not inside_cone(w, alpha)


def _cone_refuses(w_d: float, w: float | None, out: int, direction: int, alpha: float) -> bool:
    """Whether the planned ω ``w_d`` reverses the rotation: it leaves the cone (thesis), and
    is not a step back from a measured ω already outside by no more than the slack."""
    if inside_cone(w_d, alpha):
        return False
    if w is None or direction != -out:  # out == 0: not carried out by a move
        return True
    return cone_margin(w_d, alpha) < cone_margin(w, alpha) - RETREAT_SLACK


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
    c1, c2 = obs.contact1, obs.contact2
    F = (c1.force + c2.force) / 2  # eq 3.16 (ContactEstimate.force: which force)
    dF = 0.0 if state.F_prev is None else F - state.F_prev

    alpha = params.alpha
    state = replace(
        state,
        out_A=_carried_out(state.out_A, _outside(obs.omega_A, alpha), state),
        out_B=_carried_out(state.out_B, _outside(obs.omega_B, alpha), state),
        out_edge=_carried_out(state.out_edge, c1.at_edge or c2.at_edge, state),
    )

    def reverse(reason: Reversal, plan: Plan | None = None) -> StepResult:
        return StepResult(_reverse(state, F, reason), None, reason, obs, F, dF, plan)

    present = min(c1.force, c2.force) > params.contact_force_min
    if not present or obs.points is None or obs.Lambda is None or obs.sigma is None:
        return reverse(Reversal.CONTACT_LOST)
    if (c1.at_edge or c2.at_edge) and state.direction != -state.out_edge:
        return reverse(Reversal.CONTACT_EDGE)  # unless moving back the way it came
    assert c1.r_mm is not None and c1.theta_rad is not None and c1.x3_mm is not None
    assert c2.r_mm is not None and c2.theta_rad is not None and c2.x3_mm is not None

    lam_ad = _adjusted_lambda(obs.Lambda, F, dF, params)
    route = _Route(state, pose, obs, lam_ad, params, ctx)
    cfg = route.configure(1.0)
    if cfg is None:
        return reverse(Reversal.WORKSPACE, Plan(lam_ad))
    if cfg.ik.solution is not None:  # Finger 1 can follow at most its step per iteration
        need = max(abs(cfg.ik.solution.proximal - pose.phi2),
                   abs(cfg.ik.solution.distal - pose.phi3))  # fmt: skip
        if need > params.finger1_max_step:
            slower = route.configure(params.finger1_max_step / need)
            if slower is not None and slower.ik.solution is not None:
                cfg = slower
    plan, ik, phi4d, phi5d = cfg.plan, cfg.ik, cfg.phi4d, cfg.phi5d
    A_d, B_d = plan.A_d, plan.B_d
    assert A_d is not None and B_d is not None
    if ik.solution is None:
        limits = ik.failure is IKFailure.JOINT_LIMITS
        return reverse(Reversal.WORKSPACE if limits else Reversal.IK_UNREACHABLE, plan)
    phi2d, phi3d = ik.solution.proximal, ik.solution.distal
    pad = ctx.geom.pad
    wa = omega(Finger.ONE, phi2d + phi3d, c1.x3_mm, A_d, B_d, pad)
    wb = omega(Finger.TWO, phi4d + phi5d, c2.x3_mm, B_d, A_d, pad)
    plan = replace(plan, omega_A_d=wa, omega_B_d=wb)
    if _cone_refuses(wa, obs.omega_A, state.out_A, state.direction, alpha):
        return reverse(Reversal.CONE_A, plan)
    if _cone_refuses(wb, obs.omega_B, state.out_B, state.direction, alpha):
        return reverse(Reversal.CONE_B, plan)
    nxt = replace(state, F_prev=F, iteration=state.iteration + 1, consecutive_reversals=0,
                  last_move=state.direction)  # fmt: skip
    targets = HandPose(phi2d, phi3d, phi4d, phi5d)
    return StepResult(nxt, targets, None, obs, F, dF, plan)
