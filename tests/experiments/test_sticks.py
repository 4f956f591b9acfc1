"""The kinematic reproduction of thesis §3.4.2 (experiments/sticks.py): the model's invariants,
the algorithm's reversals, and what the runs show about the unintended reversal."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest

from experiments import sticks as st
from sdh2svc.config import Settings, load_config
from sdh2svc.control.rolling import Reversal
from sdh2svc.model.friction import inside_cone
from sdh2svc.model.kinematics import (
    Finger,
    HandPoints,
    HandPose,
    IKFailure,
    Point,
    contact_point,
    finger_ik,
    pad_point,
    segment,
)
from sdh2svc.model.observe import ModelContext


@pytest.fixture(scope="module")
def cfg() -> Settings:
    return load_config(use_env=False)


@pytest.fixture(scope="module")
def ctx(cfg: Settings) -> ModelContext:
    return cfg.model_context()


@pytest.fixture(scope="module")
def runs(cfg: Settings) -> dict[tuple[float, float], st.Run]:
    return st.run_all(cfg)


def test_the_grasp_is_a_mirror_pose_holding_the_stick_level(
    cfg: Settings, ctx: ModelContext
) -> None:
    pre = cfg.run.preshape_deg
    psi = math.radians(pre[cfg.axes.phi2] + pre[cfg.axes.phi3])
    for length in st.LENGTHS:
        g = st.grasp_from_settings(length, cfg)
        p = g.pose
        assert (p.phi2, p.phi3) == (p.phi4, p.phi5)  # mirror
        assert p.phi2 + p.phi3 == pytest.approx(psi)  # closed as the project's grasp closes
        A = contact_point(Finger.ONE, p.phi2, p.phi3, g.contact1.r, g.contact1.theta, ctx.geom)
        B = contact_point(Finger.TWO, p.phi4, p.phi5, g.contact2.r, g.contact2.theta, ctx.geom)
        lam, sigma = segment(A, B)
        assert lam == pytest.approx(length, abs=1e-9) and sigma == pytest.approx(0.0, abs=1e-12)
        assert A.z == pytest.approx(cfg.sim.object_height_mm, abs=1e-9)
        assert 0.0 <= g.contact1.S <= 40.8  # on the sensor's rows


def test_lambda_stays_the_sticks_length(runs: dict[tuple[float, float], st.Run]) -> None:
    for (length, _), run in runs.items():
        for it in run.iterations:
            assert abs(it.Lambda - length) < 1e-6
            if it.target is not None:  # and the plan put Ad on the circle around Bd
                assert it.sigma_d is not None


def test_contacts_stay_at_the_same_pad_points(
    runs: dict[tuple[float, float], st.Run], ctx: ModelContext
) -> None:
    """A and B are the same pad points at every iteration: through the frame-3 axes (pad_point)
    as through the virtual link (contact_point)."""
    for run in runs.values():
        c1, c2 = run.grasp.contact1, run.grasp.contact2
        for it in run.iterations:
            p = it.pose
            A = pad_point(Finger.ONE, p.phi2, p.phi3, c1.x3, c1.y3, ctx.geom)
            B = pad_point(Finger.TWO, p.phi4, p.phi5, c2.x3, c2.y3, ctx.geom)
            assert math.dist(A, it.points.A) < 1e-9 and math.dist(B, it.points.B) < 1e-9


def test_commanded_angles_within_joint_limits_and_next_iteration_starts_there(
    runs: dict[tuple[float, float], st.Run], ctx: ModelContext
) -> None:
    for run in runs.values():
        its = run.iterations
        for a, b in itertools.pairwise(its):
            if a.target is None:
                assert b.pose == a.pose  # a reversal commands nothing
                continue
            t = a.target
            assert ctx.limits1.contains(t.phi2, t.phi3) and ctx.limits2.contains(t.phi4, t.phi5)
            assert b.pose == t  # no servo, no lag
        for it in its:
            assert inside_cone(it.omega_A, math.radians(st.ALPHA_DEG))
            assert inside_cone(it.omega_B, math.radians(st.ALPHA_DEG))


def _replan(it: st.Iteration, run: st.Run, ctx: ModelContext) -> tuple[object, ...]:
    """Steps 2a–2e recomputed independently for one iteration."""
    p, g, geom = run.params, run.grasp, ctx.geom
    dphi = it.direction * p.delta_phi
    phi4d, phi5d = it.pose.phi4 - dphi, it.pose.phi5 + p.k * dphi
    if not ctx.limits2.contains(phi4d, phi5d):
        return (Reversal.WORKSPACE,)
    B_d = contact_point(Finger.TWO, phi4d, phi5d, g.contact2.r, g.contact2.theta, geom)
    sigma_d = it.sigma + p.lambda_gain * (segment(it.points.A, B_d)[1] - it.sigma)
    A_d = Point(B_d.y - g.length * math.cos(sigma_d), B_d.z - g.length * math.sin(sigma_d))
    ik = finger_ik(Finger.ONE, A_d, g.contact1.r, g.contact1.theta,
                   (it.pose.phi2, it.pose.phi3), geom, ctx.limits1)  # fmt: skip
    if ik.solution is None:
        ws = ik.failure is IKFailure.JOINT_LIMITS
        return (Reversal.WORKSPACE if ws else Reversal.IK_UNREACHABLE,)
    s = ik.solution
    target = HandPose(s.proximal, s.distal, phi4d, phi5d)
    st_pts = st._measure(target, g, ctx)
    assert math.dist(st_pts[0].A, A_d) < 1e-9 and abs(st_pts[1] - g.length) < 1e-9
    return (None, target, st_pts[3], st_pts[4])


def test_reversals_exactly_where_a_cone_or_the_workspace_would_be_crossed(
    runs: dict[tuple[float, float], st.Run], ctx: ModelContext
) -> None:
    alpha = math.radians(st.ALPHA_DEG)
    reasons: set[Reversal] = set()
    for run in runs.values():
        assert run.end == "done" and len(run.reversals) == st.REVERSALS
        direction = 1
        for it in run.iterations:
            assert it.direction == direction
            plan = _replan(it, run, ctx)
            if plan[0] is not None:  # workspace: the iteration must have reversed for it
                assert it.reversal is plan[0] and it.target is None
            else:
                _, target, wa, wb = plan
                assert isinstance(wa, float) and isinstance(wb, float)
                if not inside_cone(wa, alpha):
                    assert it.reversal is Reversal.CONE_A
                elif not inside_cone(wb, alpha):
                    assert it.reversal is Reversal.CONE_B
                else:
                    assert it.reversal is None and it.target == target
            if it.reversal is not None:
                reasons.add(it.reversal)
                direction = -direction
    # the runs reach both cones and Finger 1's workspace (the 62 mm stick, k = 5)
    assert {Reversal.CONE_A, Reversal.CONE_B, Reversal.IK_UNREACHABLE} <= reasons


def test_the_first_half_stroke_turns_clockwise(runs: dict[tuple[float, float], st.Run]) -> None:
    """Δφ > 0 is the thesis's clockwise rotation: σ decreases (§3.4)."""
    for run in runs.values():
        start, turn = run.iterations[0], run.reversals[0]
        assert start.direction == 1 and turn.sigma < start.sigma


def test_unintended_reversal_findings(
    runs: dict[tuple[float, float], st.Run], ctx: ModelContext
) -> None:
    """What the kinematic runs show: no unintended reversal for k = 5 (unlike the thesis's Fig
    31.d), and for k = 2 neither a reversal nor a stall — σ never moves backwards at all."""
    k5, k2 = st.summarise(runs[(98.46, 5.0)]), st.summarise(runs[(98.46, 2.0)])
    assert k5.backward == [] and k5.backward_steps == 0 and k5.stalls == []
    assert k2.backward == [] and k2.backward_steps == 0 and k2.stalls == []
    assert k5.step_deg[0] > 0.5 and k2.step_deg[0] > 0.5  # σ turns ≥ 0.5° every iteration
    for length in st.LENGTHS:
        for k in st.KS:
            assert st.summarise(runs[(length, k)]).backward == []
    # the route's own first-order rate never reaches zero
    for k in st.KS:
        run = runs[(98.46, k)]
        assert min(st.route_rate(it, run.grasp, run.params, ctx) for it in run.iterations) > 0.3


def _fake_run(sigmas_deg: list[float], direction: int) -> st.Run:
    """A run whose σ follows ``sigmas_deg``, every iteration commanded in ``direction``."""
    pose, pt = HandPose(0.0, 0.0, 0.0, 0.0), Point(0.0, 0.0)
    pts = HandPoints(pt, pt, pt, pt)
    g = st.Grasp(1.0, 0.0, pose, *(st.PadContact(0, 0, 0, 0, 0, 0),) * 2)
    run = st.Run(g, st.Params(5.0))
    for i, s in enumerate(sigmas_deg):
        run.iterations.append(st.Iteration(i, direction, pose, pts, 1.0, math.radians(s),
                                           0.0, 0.0, pose, None))  # fmt: skip
    return run


def test_the_detectors_see_what_they_define() -> None:
    # clockwise half stroke (σ should fall) with a 3-iteration rise of 0.6° in the middle
    sig = [-0.5 * i for i in range(10)] + [-4.3, -4.1, -3.9] + [-4.5 - 0.5 * i for i in range(5)]
    back = st.backward_stretches(_fake_run(sig, direction=1))
    assert len(back) == 1 and back[0].iterations == 3 and back[0].along_deg == pytest.approx(-0.6)
    # a single backward iteration, or two that undo less than Δφ, are not a reversal
    assert st.backward_stretches(_fake_run([0, -1, -0.5, -1.5], 1)) == []
    assert st.backward_stretches(_fake_run([0, -1, -0.9, -0.8, -2], 1)) == []
    # σ constant for three iterations: a stall, not a reversal
    flat = [0.0, 1.0, 2.0, 2.05, 2.1, 2.12, 3.0, 4.0]
    run = _fake_run(flat, direction=-1)
    assert st.backward_stretches(run) == []
    stalls = st.stalls(run)
    assert [(s.first, s.last) for s in stalls] == [(2, 4)]


def test_report_and_plots(
    tmp_path: Path, runs: dict[tuple[float, float], st.Run], cfg: Settings, ctx: ModelContext
) -> None:
    grasps = st.mirror_grasps(98.46, ctx, n_x3=4, n_psi=5)
    scans = [st.scan_grasps(grasps, k, ctx, "mirror") for k in st.KS]
    assert all(sc.grasps > 0 and sc.with_backward == 0 for sc in scans)
    g = st.grasp_from_settings(st.MAIN_LENGTH, cfg)
    printed = {k: st.simulate(g, st.Params(k, printed_eq313=True), ctx) for k in st.KS}
    path = st.write_report(runs, scans, printed, ctx, cfg, tmp_path)
    text = path.read_text(encoding="utf-8")
    assert "Fig 31.d" in text and "Fig 32" in text and "Fig 33" in text and "Fig 34" in text
    assert "**Not reproduced.**" in text and f"N = {st.BACKWARD_ITERATIONS}" in text
    st.plot_inclination([runs[(62.038, k)] for k in st.KS], tmp_path / "s.png", "t")
    assert (tmp_path / "s.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_the_thesis_root_test_is_the_closed_form_unless_both_roots_pass() -> None:
    B, lam = Point(50.0, 120.0), 98.46
    for sd in (math.radians(-3.0), math.radians(0.4), math.radians(4.0)):
        closed = Point(B.y - lam * math.cos(sd), B.z - lam * math.sin(sd))
        for last in (True, False):
            got = st.thesis_root(B, lam, sd, math.radians(0.1), last)
            assert got is not None and math.dist(got, closed) < 1e-9
    # |σd| ≤ tol / 2: both roots pass, and the kept one depends on the order tried
    sd, tol = math.radians(0.2), math.radians(1.0)
    last = st.thesis_root(B, lam, sd, tol, True)
    first = st.thesis_root(B, lam, sd, tol, False)
    assert last is not None and first is not None
    assert math.degrees(segment(last, B)[1]) == pytest.approx(-0.2)
    assert math.degrees(segment(first, B)[1]) == pytest.approx(0.2)


def test_the_root_test_candidate_is_reported(cfg: Settings) -> None:
    text = st._roots_section(st.root_test_runs(cfg, (0.1, 5.0)))
    assert "| 0.1° | last | 5 |" in text and "| 5° | first | 2 |" in text
    assert "does not explain Fig 31.d" in text or "k = 5 shows an unintended reversal" in text


# --- other readings of the thesis's program (Params options) ----------------------------------


@pytest.fixture(scope="module")
def grasps(cfg: Settings) -> dict[float, st.Grasp]:
    return {ln: st.grasp_from_settings(ln, cfg) for ln in st.STICKS_READ}


def _sigmas(run: st.Run) -> list[float]:
    return [it.sigma for it in run.iterations]


def _same_sigma(a: st.Run, b: st.Run) -> bool:
    return len(a.iterations) == len(b.iterations) and all(
        abs(x - y) < 1e-11 for x, y in zip(_sigmas(a), _sigmas(b), strict=True)
    )


def _reading(key: str) -> st.Reading:
    return next(rd for rd in st.READINGS if rd.key == key)


def test_sigma_conventions_change_nothing_for_these_sticks(
    grasps: dict[float, st.Grasp], ctx: ModelContext
) -> None:
    """atan (eq 3.3) cuts at σ = ±90°, atan2 from B to A at σ = 0 — where dσ jumps by 2π, which
    λ = 5 turns into 10π: both runs are hand-model's."""
    A, B = Point(0.0, 100.0), Point(98.0, 100.0 + 1e-9)
    assert st.inclination(A, B, "atan") == pytest.approx(st.inclination(A, B))
    assert st.inclination(A, B, "atan2_BA") == pytest.approx(-math.pi)  # the cut, at σ = 0
    assert st.inclination(A, Point(98.0, 100.0 - 1e-9), "atan2_BA") == pytest.approx(math.pi)
    g = grasps[98.46]
    for k in st.KS:
        base = st.simulate(g, st.Params(k), ctx)
        for how in ("atan", "atan2_BA"):
            assert _same_sigma(st.simulate(g, st.Params(k, sigma_from=how), ctx), base)


def test_route_readings_step_the_joints_as_named(
    grasps: dict[float, st.Grasp], ctx: ModelContext
) -> None:
    g, dphi = grasps[98.46], math.radians(st.DELTA_PHI_DEG)
    for route, d4, d5 in (("k_proximal", -5 * dphi, dphi), ("same_sense", -dphi, -5 * dphi)):
        it = st.simulate(g, st.Params(5.0, route=route), ctx).iterations[0]
        assert it.target is not None
        assert it.target.phi4 - it.pose.phi4 == pytest.approx(d4)
        assert it.target.phi5 - it.pose.phi5 == pytest.approx(d5)
    # φ5 the other way: the thesis's statements mirrored — k = 2 reverses near σ = 0, k = 5 not
    r5, r2 = (st.read_run(st.simulate(g, st.Params(k, route="same_sense"), ctx), ctx)
              for k in st.KS)  # fmt: skip
    assert r2.backward_near0 > 0 and r5.backward == 0 and r5.stalls > 0


def test_anticlockwise_first(grasps: dict[float, st.Grasp], ctx: ModelContext) -> None:
    run = st.simulate(grasps[98.46], st.Params(5.0, first_direction=-1), ctx)
    first, turn = run.iterations[0], run.reversals[0]
    assert first.direction == -1 and turn.sigma > first.sigma
    assert st.summarise(run).backward_steps == 0


def test_ik_branch_readings(grasps: dict[float, st.Grasp], ctx: ModelContext) -> None:
    """The grasp sits on the β − o elbow: that formula is hand-model's, the other one is
    refused at once in both directions."""
    g = grasps[98.46]
    base = st.simulate(g, st.Params(5.0), ctx)
    assert _same_sigma(st.simulate(g, st.Params(5.0, ik="branch+"), ctx), base)
    other = st.simulate(g, st.Params(5.0, ik="branch-"), ctx)
    assert other.end == "stuck" and all(it.target is None for it in other.iterations)


def test_clipped_ik_changes_only_the_reversal_reason(
    grasps: dict[float, st.Grasp], ctx: ModelContext
) -> None:
    g = grasps[62.038]
    base = st.simulate(g, st.Params(5.0), ctx)
    assert any(it.reversal is Reversal.IK_UNREACHABLE for it in base.reversals)
    for extra in ({}, {"sigma_source": "commanded"}):
        run = st.simulate(g, st.Params(5.0, ik_clip=True, **extra), ctx)  # type: ignore[arg-type]
        assert _same_sigma(run, base)
        assert not any(it.reversal is Reversal.IK_UNREACHABLE for it in run.reversals)


def test_flat_pad_and_cone_on_A_only_let_the_stick_leave_the_cone(
    grasps: dict[float, st.Grasp], ctx: ModelContext
) -> None:
    g = grasps[119.405]
    flat = st.simulate(g, st.Params(5.0, flat_pad=True), ctx)
    base = st.simulate(g, st.Params(5.0), ctx)
    assert flat.iterations[0].omega_A != pytest.approx(base.iterations[0].omega_A)
    assert st.read_run(flat, ctx).omega_dev_deg > st.ALPHA_DEG  # on the pad's real profile
    # no test on ωB: k = 5 runs backwards through zero inclination, k = 2 does not
    r5, r2 = (st.read_run(st.simulate(g, st.Params(k, cone_A_only=True), ctx), ctx)
              for k in st.KS)  # fmt: skip
    assert st.reproduces(r5, r2) and r5.omega_dev_deg > st.ALPHA_DEG


def test_eq39_with_an_exact_equality(grasps: dict[float, st.Grasp], ctx: ModelContext) -> None:
    assert st.exact_match_rate(n=500) < 0.2  # the correct root rarely passes "="
    g = grasps[98.46]
    for k in st.KS:
        # z02 kept: σ never rises past level and zig-zags there
        last = st.simulate(g, st.Params(k, root_tol_deg=0.0, root_nomatch="last_tried"), ctx)
        assert max(_sigmas(last)) < 1e-9
        assert st.read_run(last, ctx).back_steps_near0 > 0
    # the previous Az kept: A slides at a constant height between the rare matches
    stale = st.simulate(g, st.Params(2.0, root_tol_deg=0.0, root_nomatch="stale"), ctx)
    zs = [st._measure(it.target, g, ctx)[0].A.z for it in stale.iterations if it.target]
    same = sum(abs(a - b) < 1e-9 for a, b in itertools.pairwise(zs))
    assert same >= 0.8 * (len(zs) - 1)


def test_a_wide_cone_turns_the_distal_term_round(
    grasps: dict[float, st.Grasp], ctx: ModelContext
) -> None:
    """α = 45° on the 62 mm stick: k = 5 reverses near σ = 0 and k = 2 does not, where the
    route's first-order rate changes sign (the distal term beyond 90° from D→B)."""
    g = grasps[62.038]
    p5 = st.Params(5.0, alpha=math.radians(45.0))
    run5 = st.simulate(g, p5, ctx)
    run2 = st.simulate(g, st.Params(2.0, alpha=math.radians(45.0)), ctx)
    assert st.reproduces(st.read_run(run5, ctx), st.read_run(run2, ctx))
    s = st.backward_stretches(run5)[0]
    rates = [st.route_rate(it, g, p5, ctx) for it in run5.iterations[s.first : s.last + 1]]
    assert min(rates) < 0.0


def test_readings_section(cfg: Settings, ctx: ModelContext) -> None:
    keys = ("hand-model", "eq 3.9 “=”, root tried last", "eq 3.9 “=”, root tried first")
    readings = [_reading(k) for k in keys]
    res = st.reading_runs(cfg, readings)
    text = st._readings_section(res, None, ctx, readings)
    assert "## Other readings of the thesis's program" in text
    assert "| hand-model | 0 (0) · 0 · 0 (0) |" in text
    assert "*Eq 3.9's exact “=”.*" in text and "**No reading the text supports" in text
