"""Finger 2's route: its move per iteration (hand-model §8 step 4; thesis §5.2's future work).

``rolling.route = "thesis"``: the thesis's fixed coupling, φ4 − Δφ, φ5 + k·Δφ.

``rolling.route = "workspace"``: a few moves of the same length in the (φ4, φ5) plane, the
thesis's turned by up to ±:data:`TURNS`, are each carried through the rest of the iteration by
the model alone (B by FK, dσ, σd = σ + λ·dσ, A on the circle of radius Λad, Finger 1's IK,
ωA and ωB), and the one that turns AB furthest in the stroke's sense per iteration wins (a move
Finger 1 cannot follow within ``finger1_max_step`` counts at the fraction the rolling step will
take of it), among those that keep both fingers :data:`LIMIT_MARGIN` inside their joint limits,
Finger 1 :data:`REACH_MARGIN_MM` short of stretched (while the grip is firm, closer: moves
that spend none of the reach left, down to :data:`REACH_FLOOR_MM`), both ω :data:`CONE_MARGIN`
inside their cones, the pads' wedge as far inside its limit and both contacts within the lowest
friction angle expected (``wedge_limit``). The thesis's single line through joint space ends its
stroke where the first of these limits binds; choosing the move afresh each iteration
follows that limit's edge instead and turns on. Where no move keeps the margins, the hand is
already within one of them or a contact is near its pad's end (:data:`EDGE_MARGIN_MM`,
:data:`TIP_MARGIN_MM`), it is the thesis's move, so that near the limits the rolling step's
checks reverse as they do on the thesis's route; while the grip is outside :data:`GRIP_BAND`,
the chosen move at half its length.

Pure: numbers in, a move out; the same inputs always give the same move.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from sdh2svc.control.params import RollingParams
from sdh2svc.control.plan import finger1_to, grip_force, omegas, sigma_desired
from sdh2svc.model.friction import cone_margin, wedge
from sdh2svc.model.kinematics import (
    Finger,
    FingerLimits,
    HandPose,
    Point,
    contact_point,
    segment,
)
from sdh2svc.model.observe import ModelContext, Observation

# The turns of the thesis's direction tried in the (φ4, φ5) plane, either way (0 is the thesis's
# own): 90° moves one joint alone when k ≫ 1 would not.
TURNS = (math.radians(30.0), math.radians(60.0), math.radians(90.0))
# How far inside its cone a planned ω must stay: a rolling contact drifts from the plan by
# ≈ 0.3° per iteration and sensor noise moves the measured ω by a few tenths (rolling.py).
CONE_MARGIN = math.radians(2.0)
# How far inside the joint limits a planned joint must stay: the servo overshoots a little, and
# Finger 1's IK turns steep near its limits.
LIMIT_MARGIN = math.radians(3.0)
# How far inside Finger 1's reach (|OA| ≤ l1 + r1) a planned A must stay: near the stretched
# finger its IK is singular, a step needs large joint moves and Λ's own correction (ΔΛ) or the
# contact rolling a little can put A out of reach both ways.
REACH_MARGIN_MM = 2.0
# Within REACH_MARGIN_MM of stretched, while the grip is firm (F ≥ force_band_low × Fd), the
# route follows Finger 1's reach edge, with moves that spend none of the reach left, down to
# this margin; closer, the thesis's move. The IK's joint change per mm of |OA| grows as
# 1/√margin (≈ 7°/mm at 1 mm, 16°/mm at 0.2 mm): each iteration's small shortfall of the
# fingers against their targets there swings the grip, and on the way back from such a stroke
# end F fell to 0.2 × Fd (bench-v1's circle-027, polygon-319).
REACH_FLOOR_MM = 1.0
# The grip the route plans full moves within, × Fd: outside it the route's move at half its
# length (in its own direction), so that Λ's correction gets twice the iterations per degree
# while it brings the force back. On the thesis's route the lowest F after the grasp stays
# above 0.54 × Fd and the highest below 1.97 × Fd in 95 % of bench-v1's runs. Handing over to
# the thesis's move there instead, up to 90° away from the route's, zigzagged Finger 2 through
# joint space whenever F hovered at the band's edge, and the grip swung with it (bench-v1's
# circle-027: between 0.3 and 0.8 × Fd every two or three iterations, down to 0.22 × Fd); the
# route's move at full length outside the band lost six more runs to F below 0.25 × Fd.
GRIP_BAND = (0.5, 2.0)
# How far from the ends of its pad's range a contact must be for the route to plan (mm; the
# pad-edge check reverses at half a row, 1.7 mm). The model holds the contacts fixed on the pads,
# but the route's longer strokes carry them towards the pads' ends. Towards the base (S large)
# the pad is flat from S ≈ 31 mm on: there a corner does not travel as the finger turns (its
# radius is ≈ 0), stays lodged whichever way the fingers turn, and every later half stroke turns
# the object by < 1° (bench-v1's polygon-151, stick-100, rounded-221: S at 39.2 mm in both
# directions). Towards the tip the pad curves (R = 60 mm) and carries the contact back as the
# finger turns. Within these margins the thesis's move and its checks end the stroke.
EDGE_MARGIN_MM = 8.0  # from the base end, on the flat part
TIP_MARGIN_MM = 5.0  # from the tip end, on the arc


@dataclass(frozen=True, slots=True)
class Move:
    """Finger 2's change of φ4 and φ5 for one full iteration (radians)."""

    d4: float
    d5: float


def thesis_move(direction: int, p: RollingParams) -> Move:
    """The thesis's route: φ4 − Δφ, φ5 + k·Δφ (Δφ's sign times the current direction)."""
    dphi = direction * p.delta_phi
    return Move(-dphi, p.k * dphi)


def _limit_room(lim: FingerLimits, proximal: float, distal: float) -> float:
    """How far (rad) the nearer joint is from its limit; negative outside."""
    return min(proximal - lim.proximal_min, lim.proximal_max - proximal,
               distal - lim.distal_min, lim.distal_max - distal)  # fmt: skip


@dataclass(frozen=True, slots=True)
class Margins:
    """How far a configuration is from each limit the route keeps off (rad; reach in mm)."""

    cone_A: float
    cone_B: float
    wedge: float  # room to the wedge limit (inf without one)
    hold: float  # how far the more leaning contact's ω is inside the lowest friction angle expected
    joints1: float
    joints2: float
    reach: float  # l1 + r1 − |OA|: how far Finger 1 is from stretched

    def inside(self, reach: float = REACH_MARGIN_MM) -> bool:
        """Whether every margin is at least the route's (CONE_MARGIN, LIMIT_MARGIN, …), Finger 1's
        reach at least ``reach`` mm."""
        return (min(self.cone_A, self.cone_B, self.wedge) >= CONE_MARGIN and self.hold >= 0.0
                and min(self.joints1, self.joints2) >= LIMIT_MARGIN
                and self.reach >= reach)  # fmt: skip


@dataclass(frozen=True, slots=True)
class Prediction:
    """The configuration a candidate move leads to, by the model (radians, mm)."""

    phi: tuple[float, float, float, float]  # φ2…φ5
    A: Point
    sigma_d: float
    omega_A: float
    omega_B: float


@dataclass(frozen=True, slots=True)
class Predictor:
    """The rest of the iteration for a candidate move, by the model alone."""

    pose: HandPose
    obs: Observation
    lam_ad: float
    alpha: float  # the cones' half-angle this iteration (rad)
    params: RollingParams
    ctx: ModelContext

    def margins(self, phi: tuple[float, float, float, float], A: Point, wa: float,
                wb: float) -> Margins:  # fmt: skip
        """The margins of the configuration φ2…φ5 with contact A and friction angles ωA, ωB."""
        c1, p, ctx = self.obs.contact1, self.params, self.ctx
        assert c1.r_mm is not None
        wedge_room = (p.wedge_limit - abs(wedge(wa, wb))) if p.wedge_limit > 0.0 else math.inf
        # both contacts within the lowest friction angle the lab expects (wedge_limit): the
        # route dwells at the edge of what it allows, where α (the thesis's cone, a stroke's
        # end) overestimates a slippery object's friction. One contact beyond it there slides
        # along its pad while the other holds, the object turns back about the holding contact,
        # and the slide ends at the pad's base end or in a drop (bench-v1's rounded-221, μ = 0.30:
        # S2 24 → 39 mm in 80 iterations at ωB − 90° = 17.4°; polygon-151, μ = 0.34, 84 g).
        leaning = max(abs(wa - math.pi / 2), abs(wb - math.pi / 2))
        hold = (p.wedge_limit - leaning) if p.wedge_limit > 0.0 else math.inf
        return Margins(
            cone_margin(wa, self.alpha), cone_margin(wb, self.alpha), wedge_room, hold,
            _limit_room(ctx.limits1, phi[0], phi[1]), _limit_room(ctx.limits2, phi[2], phi[3]),
            ctx.geom.proximal_length_mm + c1.r_mm - math.hypot(A.y, A.z),
        )  # fmt: skip

    def grip_holds(self) -> bool:
        """Whether F is within GRIP_BAND × Fd."""
        F, fd = grip_force(self.obs.contact1, self.obs.contact2), self.params.grasp_force
        return GRIP_BAND[0] * fd <= F <= GRIP_BAND[1] * fd

    def firm(self) -> bool:
        """Whether F is at least the force band's low end (``force_band_low`` × Fd)."""
        F = grip_force(self.obs.contact1, self.obs.contact2)
        return F >= self.params.force_band_low * self.params.grasp_force

    def edge_room(self) -> float:
        """How far (mm) the nearer contact's centroid is inside the part of its pad the route
        plans in: TIP_MARGIN_MM off the first row (the tip), EDGE_MARGIN_MM off the last (the
        base); negative outside."""
        span = (self.ctx.distal.rows - 1) * self.ctx.pitch_mm
        room = math.inf
        for c in (self.obs.contact1, self.obs.contact2):
            if c.S_mm is not None:
                room = min(room, c.S_mm - TIP_MARGIN_MM, span - EDGE_MARGIN_MM - c.S_mm)
        return room

    def now(self) -> Margins:
        obs, pose = self.obs, self.pose
        assert obs.points is not None and obs.omega_A is not None and obs.omega_B is not None
        return self.margins((pose.phi2, pose.phi3, pose.phi4, pose.phi5), obs.points.A,
                            obs.omega_A, obs.omega_B)  # fmt: skip

    def predict(self, move: Move) -> Prediction | None:
        """The configuration ``move`` leads to by the model; None when Finger 1 cannot reach it."""
        pose, obs, ctx, p = self.pose, self.obs, self.ctx, self.params
        c2, sigma = obs.contact2, obs.sigma
        assert sigma is not None and c2.r_mm is not None and c2.theta_rad is not None
        phi4, phi5 = pose.phi4 + move.d4, pose.phi5 + move.d5
        B = contact_point(Finger.TWO, phi4, phi5, c2.r_mm, c2.theta_rad, ctx.geom)
        sigma_d = sigma_desired(obs, B, p.lambda_gain)
        A, ik = finger1_to(obs, B, sigma_d, self.lam_ad, ctx)
        if ik.solution is None:
            return None
        phi = (ik.solution.proximal, ik.solution.distal, phi4, phi5)
        wa, wb = omegas(obs, phi, A, B, ctx)
        return Prediction(phi, A, sigma_d, wa, wb)

    def turn(self, move: Move, reach: float = REACH_MARGIN_MM) -> float | None:
        """σd − σ for ``move`` (rad), scaled down as the rolling step will if Finger 1 cannot
        follow in one iteration (``finger1_max_step``); None when its configuration breaks the
        route's margins (:meth:`Margins.inside`, Finger 1's reach at least ``reach`` mm) or
        Finger 1 cannot reach it."""
        pose, obs = self.pose, self.obs
        assert obs.sigma is not None
        pr = self.predict(move)
        if pr is None or not self.margins(pr.phi, pr.A, pr.omega_A, pr.omega_B).inside(reach):
            return None
        need = max(abs(pr.phi[0] - pose.phi2), abs(pr.phi[1] - pose.phi3))
        scale = min(1.0, self.params.finger1_max_step / need) if need > 0 else 0.0
        return (pr.sigma_d - obs.sigma) * scale


def candidates(base: Move) -> list[Move]:
    """``base`` and the moves of its length turned by ±TURNS in the (φ4, φ5) plane."""
    out = [base]
    for a in TURNS:
        for t in (a, -a):
            c, s = math.cos(t), math.sin(t)
            out.append(Move(c * base.d4 - s * base.d5, s * base.d4 + c * base.d5))
    return out


def workspace_move(direction: int, pred: Predictor) -> Move:
    """The candidate that turns AB furthest in the thesis move's sense within the margins; the
    thesis's move when none does (or when the thesis's move turns AB by nothing, so that the
    stroke's sense is unknown). Within REACH_MARGIN_MM of Finger 1's stretch, while the grip is
    firm, the candidates must keep the reach the finger has left (down to REACH_FLOOR_MM).
    Half the move while the grip is outside GRIP_BAND."""
    base = thesis_move(direction, pred.params)
    ref = turn_sense(base, pred.pose, pred.obs, pred.ctx)
    if ref == 0.0:
        return base
    now, reach = pred.now(), REACH_MARGIN_MM
    if not now.inside():
        if not (now.inside(REACH_FLOOR_MM) and pred.firm()):
            return base  # the thesis's move, and its checks
        reach = now.reach  # on the reach edge: spend none of it
    if pred.edge_room() < 0.0:
        return base
    best, best_turn = base, 0.0
    for move in candidates(base):
        t = pred.turn(move, reach)
        if t is not None and t * ref > best_turn:
            best, best_turn = move, t * ref
    if not pred.grip_holds():
        return Move(best.d4 / 2, best.d5 / 2)
    return best


def turn_sense(move: Move, pose: HandPose, obs: Observation, ctx: ModelContext) -> float:
    """+1 or −1: the sense in which ``move`` turns AB (σ of A→Bd against σ; λ only scales it),
    whether or not Finger 2 may make it; 0 when it does not turn AB."""
    c2, pts, sigma = obs.contact2, obs.points, obs.sigma
    assert pts is not None and sigma is not None
    assert c2.r_mm is not None and c2.theta_rad is not None
    B = contact_point(Finger.TWO, pose.phi4 + move.d4, pose.phi5 + move.d5, c2.r_mm,
                      c2.theta_rad, ctx.geom)  # fmt: skip
    d = segment(pts.A, B)[1] - sigma
    return 0.0 if d == 0.0 else math.copysign(1.0, d)


def finger2_move(direction: int, pred: Predictor) -> Move:
    """Finger 2's move for this iteration under ``rolling.route``."""
    if pred.params.route == "workspace" and pred.params.mode == "two-finger":
        return workspace_move(direction, pred)
    return thesis_move(direction, pred.params)
