"""Finger 2's route (control/route.py): the thesis's coupling and the workspace route."""

from __future__ import annotations

import math
from dataclasses import replace

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from sdh2svc.campaign.case import Case
from sdh2svc.campaign.run import run_case
from sdh2svc.config import Settings
from sdh2svc.control import route
from sdh2svc.control.params import RollingParams
from sdh2svc.control.plan import grip_force
from sdh2svc.control.rolling import RollState, step
from sdh2svc.control.route import (
    CONE_MARGIN,
    LIMIT_MARGIN,
    REACH_FLOOR_MM,
    REACH_MARGIN_MM,
    Margins,
    Move,
    Predictor,
    candidates,
    thesis_move,
    turn_sense,
    workspace_move,
)
from sdh2svc.model.friction import cone_margin
from sdh2svc.model.kinematics import Finger, HandPose, contact_point, segment
from sdh2svc.model.observe import ModelContext, observe
from sdh2svc.sim.objects import get_object
from tests.control.test_rolling import frame

rad = math.radians
TILTED = HandPose(rad(-20), rad(30), rad(-14), rad(26))
FIRM = 3000.0  # a frame amplitude whose force (≈ 0.9 × Fd) is within the route's grip band


@pytest.fixture(scope="module")
def ctx(cfg: Settings) -> ModelContext:
    return cfg.model_context()


def workspace(cfg: Settings, **kw: object) -> RollingParams:
    return cfg.rolling.model_copy(update={"route": "workspace", **kw})


def test_the_default_route_is_the_thesis_coupling(cfg: Settings, ctx: ModelContext) -> None:
    assert cfg.rolling.route == "thesis"
    p = cfg.rolling.model_copy(update={"finger1_max_step_deg": 10.0})  # the full step
    r = step(RollState(), TILTED, frame(20.0), frame(24.0), p, ctx)
    assert r.targets is not None
    assert r.targets.phi4 == pytest.approx(TILTED.phi4 - rad(0.25))
    assert thesis_move(-1, cfg.rolling) == Move(rad(0.25), -2 * rad(0.25))


def test_candidates_keep_the_thesis_length(cfg: Settings) -> None:
    base = thesis_move(1, cfg.rolling)
    moves = candidates(base)
    assert moves[0] == base and len(moves) == 7
    for m in moves:
        assert math.hypot(m.d4, m.d5) == pytest.approx(math.hypot(base.d4, base.d5))


def test_the_workspace_route_turns_ab_at_least_as_far(cfg: Settings, ctx: ModelContext) -> None:
    """Where the thesis's move is allowed, the chosen move's predicted turn of AB is as large
    (in the same sense), and strictly larger here, where Finger 1 may take any step: the
    thesis's direction is not the best."""
    p = workspace(cfg, finger1_max_step_deg=10.0)
    obs = observe(TILTED, frame(20.0, FIRM), frame(24.0, FIRM), ctx)
    assert obs.Lambda is not None
    pred = Predictor(TILTED, obs, obs.Lambda, p.alpha, p, ctx)
    base = thesis_move(1, p)
    t_base, move = pred.turn(base), workspace_move(1, pred)
    t_move = pred.turn(move)
    assert t_base is not None and t_move is not None
    assert t_move * t_base > 0 and abs(t_move) > 1.2 * abs(t_base)


@pytest.mark.parametrize("amplitude", [1000.0, 8000.0], ids=["loose", "squeezed"])
def test_outside_the_grip_band_it_is_half_the_routes_move(
    cfg: Settings, ctx: ModelContext, amplitude: float
) -> None:
    """A grip outside the band slows the route down (half its move, in the direction it would
    take with the grip inside the band) instead of turning Finger 2 onto the thesis's line."""
    p = workspace(cfg, finger1_max_step_deg=10.0)
    obs = observe(TILTED, frame(20.0, amplitude), frame(24.0, amplitude), ctx)
    assert obs.Lambda is not None
    pred = Predictor(TILTED, obs, obs.Lambda, p.alpha, p, ctx)
    assert not pred.grip_holds()
    held = p.model_copy(update={"grasp_force": grip_force(obs.contact1, obs.contact2)})
    inside = Predictor(TILTED, obs, obs.Lambda, held.alpha, held, ctx)
    assert inside.grip_holds()
    full = workspace_move(1, inside)
    assert full != thesis_move(1, p)  # the route's own direction, not the thesis's
    assert workspace_move(1, pred) == Move(full.d4 / 2, full.d5 / 2)


def test_near_a_pads_end_it_is_the_thesis_move(
    cfg: Settings, ctx: ModelContext, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Finger 2's contact 4.3 mm from its pad's end: the thesis's move, whose way back carries
    the contact off the edge (bench-v1's ellipse-302, polygon-229, stick-100: the route's own
    way back left the contact there and every later half stroke turned the object by < 1°)."""
    p = workspace(cfg)
    hp = HandPose.from_degrees(-23.3, 28.1, -24.6, 29.1)
    obs = observe(hp, frame(20.6, FIRM), frame(36.5, FIRM), ctx)
    assert obs.Lambda is not None
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    assert pred.edge_room() < 0.0
    assert workspace_move(1, pred) == thesis_move(1, p)
    monkeypatch.setattr(route, "EDGE_MARGIN_MM", 0.0)  # without the margin: a move of its own
    assert workspace_move(1, pred) != thesis_move(1, p)


@pytest.mark.parametrize(("S1", "S2"), [(20.6, 33.5), (33.3, 24.0)], ids=["finger2", "finger1"])
def test_within_8_mm_of_a_pads_end_it_is_the_thesis_move(
    cfg: Settings, ctx: ModelContext, monkeypatch: pytest.MonkeyPatch, S1: float, S2: float
) -> None:
    """A contact 7.3–7.5 mm from its pad's end, off the pad's flat part: the thesis's move. With
    5 mm the route planned a move of its own there, and its long strokes lodged a corner at the
    pad's end, where every later half stroke turned the object by < 1° (bench-v1's polygon-151,
    stick-100) or both directions refused (polygon-229)."""
    p = workspace(cfg)
    hp = HandPose.from_degrees(-23.3, 28.1, -24.6, 29.1)
    obs = observe(hp, frame(S1, FIRM), frame(S2, FIRM), ctx)
    assert obs.Lambda is not None
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    assert -3.0 < pred.edge_room() < 0.0  # 5–8 mm from the base end
    assert workspace_move(1, pred) == thesis_move(1, p)
    monkeypatch.setattr(route, "EDGE_MARGIN_MM", 5.0)
    assert workspace_move(1, pred) != thesis_move(1, p)


def _lean(pred: Predictor, move: Move) -> float:
    """The smaller |ω − 90°| of the configuration ``move`` leads to (rad)."""
    pr = pred.predict(move)
    assert pr is not None
    return min(abs(pr.omega_A - math.pi / 2), abs(pr.omega_B - math.pi / 2))


# (φ2…φ5 in degrees, S1, S2): ωA ≈ 102.5°, ωB ≈ 74.8°, where the route's furthest turn would
# lean both contacts beyond 16° (ωA ≈ 107.9°, ωB ≈ 72.0°)
LEANING = ((-2.23, 11.99, -1.87, 8.3), 20.75, 28.25)
# ωA, ωB 18.8° and 17.9° off their pad normals: inside the 22° cones, beyond 16°
BOTH_LEAN = ((-18.45, 27.62, -17.24, 31.13), 28.55, 12.11)


def test_a_move_of_its_own_keeps_the_contacts_within_the_lowest_friction_angle(
    cfg: Settings, ctx: ModelContext
) -> None:
    """The route dwells at a cone's edge; where the object's friction is below α (bench-v1's
    polygon-151, μ = 0.34) the contacts then slide and the object falls. ``wedge_limit`` is the
    lowest friction angle the lab expects; without it the route leans both beyond it."""
    pose, S1, S2 = LEANING
    hp = HandPose.from_degrees(*pose)
    obs = observe(hp, frame(S1, FIRM), frame(S2, FIRM), ctx)
    assert obs.Lambda is not None
    p = workspace(cfg)
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    assert _lean(pred, workspace_move(1, pred)) <= p.wedge_limit
    free = workspace(cfg, wedge_limit_deg=0.0)  # no wedge limit: no lowest friction angle
    pred_free = Predictor(hp, obs, obs.Lambda, free.alpha, free, ctx)
    assert _lean(pred_free, workspace_move(1, pred_free)) > p.wedge_limit


# (φ2…φ5 in degrees, S1, S2): ωA 14.2° and ωB 0.2° off their pad normals; the furthest turn
# inside the cones (by CONE_MARGIN) leans A 17.0° off with B at 2.1°
ONE_LEANS = ((-6.66, 29.0, -11.03, 24.16), 20.21, 21.15)


def test_a_move_of_its_own_keeps_both_contacts_within_the_lowest_friction_angle(
    cfg: Settings, ctx: ModelContext
) -> None:
    """With one contact holding, the other beyond the object's friction angle slides along its
    pad while the route dwells there: bench-v1's rounded-221 (μ = 0.30, 16.7°) had Finger 2's
    contact at 17.4° for 80 iterations, S2 24 → 39 mm, ψ falling back, and every later half
    stroke turned < 1° at the pad's base end; polygon-151 (μ = 0.34, 84 g) dropped. The route
    gives up the further turn that leans one contact beyond ``wedge_limit``."""
    pose, S1, S2 = ONE_LEANS
    hp = HandPose.from_degrees(*pose)
    obs = observe(hp, frame(S1, FIRM), frame(S2, FIRM), ctx)
    assert obs.Lambda is not None and obs.sigma is not None
    sigma, p = obs.sigma, workspace(cfg)
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    base = thesis_move(-1, p)
    move = workspace_move(-1, pred)
    assert move != base and pred.now().inside()
    sense = turn_sense(base, hp, obs, ctx)

    def turn_and_leans(m: Move) -> tuple[float, float, float]:
        pr = pred.predict(m)
        assert pr is not None
        wa, wb = abs(pr.omega_A - math.pi / 2), abs(pr.omega_B - math.pi / 2)
        return (pr.sigma_d - sigma) * sense, min(wa, wb), max(wa, wb)

    turned, _, leans = turn_and_leans(move)
    assert turned > 0.0 and leans <= p.wedge_limit
    # a further turn that leans one contact beyond it while the other holds, inside the cones
    further = [m for m in candidates(base) if turn_and_leans(m)[0] > turned]
    one_leans = [m for m in further if turn_and_leans(m)[1] < rad(3) < p.wedge_limit
                 < turn_and_leans(m)[2] < p.alpha - route.CONE_MARGIN]  # fmt: skip
    assert one_leans


def test_with_both_contacts_beyond_the_lowest_friction_angle_it_is_the_thesis_move(
    cfg: Settings, ctx: ModelContext
) -> None:
    pose, S1, S2 = BOTH_LEAN
    hp = HandPose.from_degrees(*pose)
    obs = observe(hp, frame(S1, FIRM), frame(S2, FIRM), ctx)
    assert obs.Lambda is not None and obs.omega_A is not None and obs.omega_B is not None
    p = workspace(cfg)
    assert min(abs(obs.omega_A - math.pi / 2), abs(obs.omega_B - math.pi / 2)) > p.wedge_limit
    assert max(cone_margin(obs.omega_A, p.alpha), cone_margin(obs.omega_B, p.alpha)) > 0.0
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    assert not pred.now().inside()
    assert workspace_move(1, pred) == thesis_move(1, p)


# (φ2…φ5 in degrees, S1, S2, frame amplitude): anywhere, or near a mirror grasp with a firm
# grip (where the workspace route plans moves of its own about one time in five)
anywhere = st.tuples(st.tuples(*(st.floats(-80.0, 80.0) for _ in range(4))), st.floats(2.0, 38.0),
                     st.floats(2.0, 38.0), st.floats(800.0, 7000.0))  # fmt: skip
grasps = st.builds(
    lambda a2, a3, d4, d5, S, dS, amp: ((a2, a3, a2 + d4, a3 + d5), S, S + dS, amp),
    st.floats(-40.0, 30.0),
    st.floats(-10.0, 60.0),
    st.floats(-5.0, 5.0),
    st.floats(-5.0, 5.0),
    st.floats(5.0, 34.0),
    st.floats(-4.0, 4.0),
    st.floats(2000.0, 6000.0),
)


@settings(max_examples=150, deadline=None)
@given(case=st.one_of(anywhere, grasps), direction=st.sampled_from((1, -1)),
       iteration=st.sampled_from((0, 5)))  # fmt: skip
# a loose grip: the route halves the thesis's move (once taken for a move of its own)
@example(case=((0.0, 11.0, 11.0, 10.0), 11.0, 5.25, 800.0), direction=-1, iteration=0)
def test_workspace_route_stays_inside_limits_and_cones(
    cfg: Settings,
    case: tuple[tuple[float, float, float, float], float, float, float],
    direction: int,
    iteration: int,
) -> None:
    """Over random poses and contacts: a commanded target lies inside the joint limits, its plan
    inside both cones; a move other than the thesis's keeps the route's margins."""
    pose, S1, S2, amplitude = case
    ctx, p = cfg.model_context(), workspace(cfg)
    lim2 = ctx.limits2
    hp = HandPose.from_degrees(*pose)
    state = RollState(direction=direction, iteration=iteration)
    r = step(state, hp, frame(S1, amplitude), frame(S2, amplitude), p, ctx)
    if r.targets is not None:
        t = r.targets
        assert ctx.limits1.contains(t.phi2, t.phi3) and ctx.limits2.contains(t.phi4, t.phi5)
        assert r.plan is not None and r.plan.omega_A_d is not None
        assert r.plan.omega_B_d is not None
        alpha = max(p.alpha, r.state.alpha_held)
        assert cone_margin(r.plan.omega_A_d, alpha) > 0.0
        assert cone_margin(r.plan.omega_B_d, alpha) > 0.0
    obs = r.obs
    if obs.Lambda is None or obs.points is None or obs.sigma is None:
        return
    pred = Predictor(hp, obs, obs.Lambda, max(p.alpha, r.state.alpha_held), p, ctx)
    move = workspace_move(direction, pred)
    # outside the grip band the route halves the move it chose (the thesis's included, when no
    # other turned further): the checks are the whole one's
    base = thesis_move(direction, p)
    chosen = move if move == base or pred.grip_holds() else Move(2 * move.d4, 2 * move.d5)
    if chosen == base:
        return
    # a move of its own: planned from inside the route's margins, and keeping them; within
    # REACH_MARGIN_MM of Finger 1's stretch only while the grip is firm, spending none of it
    now = pred.now()
    assert now.inside(REACH_FLOOR_MM) and pred.edge_room() >= 0.0
    reach = REACH_MARGIN_MM
    if not now.inside():
        assert pred.firm() and now.reach < REACH_MARGIN_MM
        reach = now.reach
    phi4, phi5 = hp.phi4 + move.d4, hp.phi5 + move.d5
    room = min(phi4 - lim2.proximal_min, lim2.proximal_max - phi4,
               phi5 - lim2.distal_min, lim2.distal_max - phi5)  # fmt: skip
    assert room >= LIMIT_MARGIN - 1e-12
    # the margins kept (cones, wedge, both contacts within wedge_limit, Finger 1's joints, reach)
    assert pred.turn(chosen, reach) is not None
    # …and it turns AB the way the thesis's move does
    c2 = obs.contact2
    assert c2.r_mm is not None and c2.theta_rad is not None
    B = contact_point(Finger.TWO, phi4, phi5, c2.r_mm, c2.theta_rad, ctx.geom)
    Bt = contact_point(Finger.TWO, hp.phi4 + base.d4, hp.phi5 + base.d5, c2.r_mm,
                       c2.theta_rad, ctx.geom)  # fmt: skip
    sense = segment(obs.points.A, Bt)[1] - obs.sigma
    assert (segment(obs.points.A, B)[1] - obs.sigma) * sense > 0.0


def test_a_simulated_run_on_a_thesis_object_completes_with_the_workspace_route() -> None:
    """The thesis's rubber, one stroke on the simulated hand (fast mode, virtual clock)."""
    case = Case(id="rubber-ws", family="thesis", object=get_object("rubber"), height_mm=125.0,
                seed=1, true_width_mm=60.5)  # fmt: skip
    row = run_case(case.model_dump_json(), ['rolling.route="workspace"', "rolling.cycles=1"])
    assert row["status"] == "completed", row.get("traceback")
    assert row["success"] and not row["dropped"]
    assert row["strokes"] == 1


@pytest.mark.parametrize(("amplitude", "follows"), [(4000.0, True), (2000.0, False)])
def test_the_route_follows_finger1s_reach_edge_only_while_the_grip_is_firm(
    cfg: Settings, amplitude: float, follows: bool
) -> None:
    """Stretched fingers leave Finger 1 between REACH_FLOOR_MM and REACH_MARGIN_MM of its reach:
    with F ≥ force_band_low × Fd the route plans a move that spends none of the reach left; with
    F below that it leaves the stroke to the thesis's move."""
    ctx, p = cfg.model_context(), workspace(cfg)
    hp = HandPose.from_degrees(0.0, 0.0, 0.0, 0.0)
    r = step(RollState(direction=-1), hp, frame(20.0, amplitude), frame(20.0, amplitude), p, ctx)
    obs = r.obs
    assert obs.Lambda is not None
    pred = Predictor(hp, obs, obs.Lambda, p.alpha, p, ctx)
    now = pred.now()
    assert REACH_FLOOR_MM <= now.reach < REACH_MARGIN_MM and now.inside(REACH_FLOOR_MM)
    assert pred.grip_holds() and pred.firm() == follows
    move = workspace_move(-1, pred)
    assert (move != thesis_move(-1, p)) == follows
    if follows:
        pr = pred.predict(move)
        assert pr is not None
        assert pred.margins(pr.phi, pr.A, pr.omega_A, pr.omega_B).reach >= now.reach


def test_the_routes_margins_are_kept_to_the_last_field() -> None:
    """A configuration is inside the route's margins only if every one holds: the joints
    LIMIT_MARGIN, the cones and the wedge CONE_MARGIN, the hold, Finger 1's reach (a mutation
    audit let the joints and the cones go negative and every other test passed)."""
    ok = Margins(cone_A=CONE_MARGIN, cone_B=CONE_MARGIN, wedge=CONE_MARGIN, hold=0.0,
                 joints1=LIMIT_MARGIN, joints2=LIMIT_MARGIN, reach=REACH_MARGIN_MM)  # fmt: skip
    assert ok.inside()
    short = 1e-6
    for field in ("cone_A", "cone_B", "wedge", "hold", "joints1", "joints2", "reach"):
        worse = replace(ok, **{field: getattr(ok, field) - short})
        assert not worse.inside(), field
    assert replace(ok, reach=REACH_FLOOR_MM).inside(REACH_FLOOR_MM)
