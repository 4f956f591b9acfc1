"""The case generator: valid, graspable cases; true widths; suites regenerated bit for bit."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from sdh2svc.campaign import generate as gen
from sdh2svc.campaign.case import (
    FAMILIES,
    Case,
    Suite,
    contact_width_mm,
    extent_along_y0,
    load_suite,
    suite_names,
)
from sdh2svc.config import default_config, load_config
from sdh2svc.connect import hand_model
from sdh2svc.sim.hand import PhysicsWorld
from sdh2svc.sim.objects import Box, Circle, Ellipse, Outline, Polygon, Shape, Stick, parse_object

TAN_ALPHA = math.tan(math.radians(22.0))  # μ at the controller's friction angle α = 22°


def boundary(obj: Shape, n: int = 20000) -> np.ndarray:
    """Points of the outline (object frame), found independently of the generator's support
    function: bisection of the signed distance along n rays from the centre (every shape is
    convex and contains its centre); spaced ≤ 2π·75 mm / n ≈ 0.024 mm apart."""
    outline = Outline(obj)
    t = np.linspace(0, 2 * math.pi, n, endpoint=False)
    u = np.stack([np.cos(t), np.sin(t)], axis=1)
    lo, hi = np.zeros(n), np.full(n, outline.bound_radius + 1.0)
    for _ in range(50):
        mid = (lo + hi) / 2
        inside = outline.sdf(u * mid[:, None]) < 0
        lo, hi = np.where(inside, mid, lo), np.where(inside, hi, mid)
    return u * lo[:, None]


def sampled_width(obj: Shape, angle_deg: float) -> float:
    """The y0-extent of the boundary points turned by angle_deg (as the world turns the object:
    y0 = cos·x − sin·y)."""
    a = math.radians(angle_deg)
    pts = boundary(obj)
    y = math.cos(a) * pts[:, 0] - math.sin(a) * pts[:, 1]
    return float(y.max() - y.min())


def check_case(case: Case) -> None:
    again = Case.model_validate_json(case.model_dump_json())  # validates, round trips exactly
    assert again == case
    obj = parse_object(case.object.model_dump())  # objects.py's validation (convex polygons …)
    assert case.family in gen.GENERATED
    assert abs(case.true_width_mm - sampled_width(obj, case.angle_deg)) <= 0.05
    assert abs(case.true_width_mm - contact_width_mm(obj, case.angle_deg)) <= 1e-6
    assert gen.WIDTH_MM[0] - 0.01 <= case.true_width_mm <= gen.WIDTH_MM[1] + 0.01
    assert abs(case.height_mm - gen.HEIGHT_MM) <= gen.HEIGHT_SPAN_MM
    m = obj.material
    assert gen.FRICTION[0] <= m.friction <= gen.FRICTION[1]
    assert gen.STIFFNESS[0] <= m.stiffness_n_per_mm3 <= gen.STIFFNESS[1]
    assert gen.check_placement(obj, case.height_mm, case.angle_deg) is None
    kinds = {"box": Box, "rounded": Box, "polygon": Polygon, "ellipse": Ellipse,
             "circle": Circle, "stick": Stick}  # fmt: skip
    assert isinstance(obj, kinds[case.family])
    if case.family == "rounded":
        assert isinstance(obj, Box) and obj.corner_radius_mm > 0
    for t in case.sensor.dead_texels:
        assert t.matrix in (1, 5)


@settings(derandomize=True, max_examples=12, deadline=None)
@given(seed=st.integers(0, 2**63 - 1))
def test_generated_cases_validate_and_their_true_width_is_right(seed: int) -> None:
    cases = gen.generate_cases(seed, len(gen.GENERATED))
    assert [c.family for c in cases] == list(gen.GENERATED)
    for case in cases:
        check_case(case)


def test_a_width_the_fingers_cannot_hold_at_its_height_is_narrowed() -> None:
    """Seed 3's 25 cases draw a 118.8 mm box 116.5 mm up, where no angle or aspect fits: it is
    narrowed until one does (before, generation stopped with an error)."""
    cases = gen.generate_cases(3, 25)
    box = next(c for c in cases if c.id == "box-024")
    assert box.height_mm < 117.0 and 110.0 < box.true_width_mm < 118.8 * gen.WIDTH_SHRINK + 0.5
    for case in cases:
        check_case(case)


_mm = st.floats(5.0, 140.0)


@st.composite
def objects(draw: st.DrawFn) -> Shape:
    kind = draw(st.sampled_from(["box", "ellipse", "circle", "stick", "polygon"]))
    if kind == "box":
        w, h = draw(_mm), draw(_mm)
        r = draw(st.floats(0.0, 0.5)) * min(w, h)
        return Box(width_mm=w, height_mm=h, corner_radius_mm=r, depth_mm=10.0)
    if kind == "ellipse":
        return Ellipse(axis_a_mm=draw(_mm), axis_b_mm=draw(_mm), depth_mm=10.0)
    if kind == "circle":
        return Circle(diameter_mm=draw(_mm), depth_mm=10.0)
    if kind == "stick":
        length = draw(_mm)
        diameter = draw(st.floats(1.0, length - 0.5))  # (as long as thick: a zero segment)
        return Stick(length_mm=length, diameter_mm=diameter, depth_mm=10.0)
    n = draw(st.integers(3, 12))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    v = gen._irregular(n, rng) * draw(st.floats(20.0, 120.0))
    return Polygon(vertices_mm=[(float(x), float(y)) for x, y in v], depth_mm=10.0)


@settings(derandomize=True, max_examples=60, deadline=None)
@given(obj=objects(), angle=st.floats(-180.0, 180.0))
def test_contact_width_is_the_outline_extent_along_y0(obj, angle: float) -> None:
    try:
        obj = parse_object(obj.model_dump())
    except ValueError:  # a random polygon with a corner nearly in line: not an object
        return
    width = contact_width_mm(obj, angle)
    assert abs(width - sampled_width(obj, angle)) <= 0.05
    lo, hi = extent_along_y0(obj, angle)
    assert hi - lo == width and lo < 0 < hi


def test_width_is_not_the_width_across_corners() -> None:
    box = Box(width_mm=60.0, height_mm=20.0, depth_mm=10.0)
    assert contact_width_mm(box, 0.0) == pytest.approx(60.0)
    assert contact_width_mm(box, 90.0) == pytest.approx(20.0)
    a = math.radians(30.0)
    assert contact_width_mm(box, 30.0) == pytest.approx(60 * math.cos(a) + 20 * math.sin(a))
    stick = Stick(length_mm=100.0, diameter_mm=4.0, depth_mm=10.0)
    assert contact_width_mm(stick, 10.0) == pytest.approx(96 * math.cos(math.radians(10)) + 4)
    egg = Ellipse(axis_a_mm=53.0, axis_b_mm=39.0, depth_mm=39.0)
    assert contact_width_mm(egg, 90.0) == pytest.approx(39.0)


def test_generation_is_bit_for_bit_reproducible() -> None:
    a = Suite(name="x", generator_seed=5, cases=tuple(gen.generate_cases(5, 12)))
    b = Suite(name="x", generator_seed=5, cases=tuple(gen.generate_cases(5, 12)))
    assert a.to_json() == b.to_json()
    c = Suite(name="x", generator_seed=6, cases=tuple(gen.generate_cases(6, 12)))
    assert c.to_json() != a.to_json()


# bench-v1 (360 cases, ≈ 15 s to regenerate) is checked by `python -m sdh2svc.campaign.generate
# --check`; the same generator makes smoke, so a change that moves one moves the other
@pytest.mark.parametrize("name", ["smoke", "thesis"])
def test_committed_suites_are_what_their_seeds_make(name: str) -> None:
    assert gen.check_suites(names=[name]) == []


def test_check_and_write_commands(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert gen.main(["--check", "--dir", str(tmp_path), "smoke"]) == 1  # missing
    assert gen.main(["--write", "--dir", str(tmp_path), "smoke", "thesis"]) == 0
    assert gen.main(["--check", "--dir", str(tmp_path), "smoke", "thesis"]) == 0
    path = tmp_path / "smoke.json"
    path.write_text(path.read_text().replace('"friction": 0.', '"friction": 1.', 1))
    assert gen.main(["--check", "--dir", str(tmp_path), "smoke", "thesis"]) == 1
    assert "smoke" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        gen.main(["--check", "nosuch"])


def test_packaged_suites_load_by_name_and_path() -> None:
    assert suite_names() == ["bench-v1", "smoke", "thesis"]
    smoke = load_suite("smoke")
    assert load_suite(gen.SUITES_DIR / "smoke.json") == smoke
    assert load_suite(str(gen.SUITES_DIR / "smoke.json")) == smoke
    with pytest.raises(FileNotFoundError, match=r"no suite 'nosuch' \(packaged suites: bench"):
        load_suite("nosuch")


@pytest.mark.parametrize("name", ["smoke", "bench-v1"])
def test_generated_suites_cover_every_family_and_range(name: str) -> None:
    suite = load_suite(name)
    seed, n, _ = gen.SUITE_SEEDS[name]
    assert suite.name == name and suite.generator_seed == seed and len(suite.cases) == n
    cases = suite.cases
    assert len({c.id for c in cases}) == n
    assert {c.family for c in cases} == set(gen.GENERATED) == set(FAMILIES) - {"thesis"}
    assert min(sum(c.family == f for c in cases) for f in gen.GENERATED) >= n // 6
    tight = 1.0 / n  # Latin hypercube: the extreme strata are 1/n of each range
    widths = [c.true_width_mm for c in cases]
    assert min(widths) <= 15.0 + 105.0 * 2 * tight + 0.5 and max(widths) >= 120.0 - 105 * tight
    mu = [c.object.material.friction for c in cases]
    assert min(mu) < TAN_ALPHA < max(mu)
    assert sum(m < TAN_ALPHA for m in mu) >= n // 20  # both sides, not just one case
    assert min(mu) <= 0.3 + 0.9 * tight + 1e-9 and max(mu) >= 1.2 - 0.9 * tight - 1e-9
    gain = [c.sensor.gain_factor for c in cases]
    assert min(gain) <= 0.5 + tight + 1e-9 and max(gain) >= 1.5 - tight - 1e-9
    k = [c.object.material.stiffness_n_per_mm3 for c in cases]
    assert min(k) < 0.02 and max(k) > 2.0  # foam to rigid
    heights = [c.height_mm for c in cases]
    assert min(heights) < 117.0 and max(heights) > 133.0
    assert 0 < sum(bool(c.sensor.dead_texels) for c in cases) < n / 2
    assert {t.matrix for c in cases for t in c.sensor.dead_texels} == {1, 5}
    polygons = [c.object for c in cases if isinstance(c.object, Polygon)]
    assert {len(p.vertices_mm) for p in polygons} >= ({3, 4, 12} if n > 100 else set())
    for case in cases:
        assert abs(case.true_width_mm - contact_width_mm(case.object, case.angle_deg)) <= 1e-6


def test_bench_cases_all_check_out() -> None:
    for case in load_suite("bench-v1").cases[::9]:  # a sample: the full check is the seed's
        check_case(case)


def test_thesis_suite_is_the_presets_at_the_configured_placement() -> None:
    suite = load_suite("thesis")
    cfg = default_config()
    assert suite.generator_seed is None
    assert [c.id for c in suite.cases] == list(gen.THESIS)
    widths = {"rubber": 60.5, "egg": 53.0, "cylinder": 68.0, "stick62": 62.038,
              "stick74": 73.8, "stick98": 98.46, "stick119": 119.405}  # fmt: skip
    for c in suite.cases:
        assert c.family == "thesis" and c.object.name == c.id
        assert c.height_mm == cfg.sim.object_height_mm and c.angle_deg == cfg.sim.object_angle_deg
        assert c.true_width_mm == pytest.approx(widths[c.id], abs=1e-9)


def test_every_smoke_case_overrides_a_valid_configuration() -> None:
    base = default_config().sim.sensor.gain_vs_library
    for case in load_suite("smoke").cases:
        cfg = load_config(overrides=case.overrides(base), use_env=False)
        assert cfg.sim.object_height_mm == case.height_mm
        assert cfg.sim.sensor.gain_vs_library == pytest.approx(base * case.sensor.gain_factor)
        cells = tuple((t.matrix, t.row, t.col) for t in case.sensor.dead_texels)
        assert cfg.sim.sensor.dead_texels == cells


def fixture_lets_go(case: Case) -> bool:
    """Close both coupled fingers from the pre-shape as the grasp does (proximal +δ, distal −δ)
    on the simulated world of this case: do both distal pads press the object before one
    finger has pushed it out of the fixture? (Whether the fixture then lets go — the fingers
    can hold it — and whether they roll it is the run's result, not the placement's.)"""
    cfg = load_config(overrides=case.overrides(default_config().sim.sensor.gain_vs_library),
                      use_env=False)  # fmt: skip
    world = PhysicsWorld(hand_model(cfg), cfg.sim, case.object)
    a = cfg.axes
    q = list(cfg.run.preshape_deg)
    t = 0.0
    world.move_joints(t, q, [True] * 7)
    while q[a.phi2] < cfg.run.grasp_max_close_deg:
        t += 0.02
        for prox, dist in ((a.phi2, a.phi3), (a.phi4, a.phi5)):
            q[prox] += 0.1
            q[dist] -= 0.1
        world.move_joints(t, q, [True] * 7)
        if not world.physics.state.held_by_fixture:  # only when both distal pads hold it
            return True
        pressing = {c.surface for c in world.physics.contacts() if c.normal_force_n > 0.0}
        if {"distal1", "distal2"} <= pressing:
            return True
    return False


@pytest.mark.parametrize("name", ["smoke", "thesis"])
def test_the_simulated_fixture_lets_go_of_every_case(name: str) -> None:
    """The generator's geometric checks against the physics: in every case both fingertips
    reach the object together, on their pads (whether the run then holds it is the result)."""
    assert [c.id for c in load_suite(name).cases if not fixture_lets_go(c)] == []


def test_the_simulated_fixture_lets_go_of_every_bench_case() -> None:
    assert [c.id for c in load_suite("bench-v1").cases if not fixture_lets_go(c)] == []
