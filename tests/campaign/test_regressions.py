"""Failures `bench-v1` found in the controller, one representative case per class, each run as a
campaign runs it (fast simulation through the full byte path, judged from the simulation's
truth) with the default configuration. Each failed on a committed bench-v1 run: the baseline
(experiments/campaigns/bench-v1-baseline) or, where a later controller change broke it, the run
before its fix (polygon-313 and polygon-061: git history of experiments/campaigns/bench-v1).
The last tests are unseen suites' cases (experiments/campaigns/unseen): one that a first
version of a fix broke, and the grasp's failures an unseen suite found."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import (
    F_BAND,
    MIN_HALF_STROKE_DEG,
    case_settings,
    run_case,
    true_grip_scale,
)
from sdh2svc.sim import physics

CASES = {c.id: c for c in load_suite("bench-v1").cases}
UNSEEN = Path(__file__).parents[2] / "experiments" / "campaigns" / "unseen"


def run(case_id: str) -> dict[str, Any]:
    row = run_case(CASES[case_id].model_dump_json())
    assert row["status"] != "crashed", row["traceback"]
    return row


# (case, how it failed): one representative case per failure class (python -m bench regressions
# judges each over a family of grasp gains around the default: a class, not a coin flip)
FAILURE_CLASSES = [
    # a 116 mm box held on the pads' arcs: both cones refused both directions at once
    # (the pads' wedge at the grasp as wide as the cone) — stuck at iteration 7
    ("box-246", "faulted: stuck"),
    # a rounded stick's end loads a few cells: the library's force (∝ area²) never reached
    # Fd, the grasp timed out
    ("stick-358", "faulted: no_contact"),
    # reversals after a single moved iteration counted as half strokes: "completed" with
    # half strokes that turned the object 0.4°
    ("polygon-241", "half stroke < 1°"),
    # a small foam box squeezed while the grasp crept towards Fd, and dropped
    ("box-234", "dropped"),
    # friction below the cone α assumes (μ 0.34): the pads' wedge grew over a stroke until
    # both contacts slid the same way and the object was pushed out between the pads
    ("circle-075", "dropped"),
    # an 18 mm circle far from the pre-shape: the fingers touched it after 17 s of closing,
    # and the grasp's 20 s ran out before F reached Fd (the timeout now counts from the touch)
    ("circle-087", "faulted: no_contact"),
    # a triangle tipping over a corner: the rotation reversed between two refused
    # directions (workspace one way, a cone the other) until stuck; another move of the
    # same length turns it on
    ("polygon-061", "faulted: stuck"),
    # a 35 mm box whose third half stroke ended at Finger 1's reach after Finger 2's 1° of
    # travel but 0.9° of the object's turn: a half stroke now counts once the object turned
    ("box-006", "half stroke < 1°"),
]
# Classes whose representative case sits near a limit: judged over the grasp gains by python -m
# bench regressions, not pinned at the default here, where any change upstream flips it.
NEAR_A_LIMIT = [
    # an ellipse whose way back from cone B ended with ωB still a little outside the cone:
    # refused there as a new lean, the rotation reversed at cone B either way until stuck;
    # the way back now goes on while each plan leans the contact less. It passed at 6 of the
    # 11 gains, the default among them; since the joint poller plans again at every beat, at 8
    # of 11, the default not among them (the others stuck, or the true grip below its band)
    ("ellipse-212", "faulted: stuck"),
]


@pytest.mark.parametrize(("case_id", "baseline"), FAILURE_CLASSES)
def test_a_failure_class_bench_v1_found_is_fixed(case_id: str, baseline: str) -> None:
    """The run completes every stroke, each half stroke turning the object, nothing drops, and
    the true grip stays in its band."""
    row = run(case_id)
    rolls_every_stroke(row, baseline)
    assert row["success"], (baseline, row["failure"], row["message"])


# Two cases once here pinned a coin flip, not a class: rerun with the grasp's gain at 2.40, 2.42,
# … 2.60 °/s per force unit (11 runs each, around the default 2.5), rounded-011 (a rounded box
# on its pads' edge rows, pads ×0.57) ended stuck at the edge in 5 of 11 both before and after
# the grasp's approach speed of its own; polygon-313 (a foam triangle) rolled its 3 strokes in 6
# of 11 before and 2 of 11 after, dropped otherwise. Each passed only at the exact default of the
# controller it was fixed on. polygon-313's own class, a failed grasp, is pinned below.


def test_a_foam_triangle_touched_on_two_corners_is_grasped() -> None:
    # polygon-313: the placing hand let go at the first touch and it fell before the grasp
    # began (it now lets go once the fingers hold it); then the first pad to touch closed on at
    # full speed and pressed it 1 mm deep before the other arrived, and the placing hand took it
    # back (no grasp in 20 s). Grasped in each of the 22 runs above; its rolling is a coin flip
    row = run("polygon-313")
    assert row["iterations"] > 0, (row["failure"], row["message"])
    assert row["failure"] != "faulted: no_contact", row["message"]


def rolls_every_stroke(row: dict[str, Any], baseline: str = "") -> None:
    """Completed every stroke, each half stroke turning the object ≥ 1°, no drop, and the F the
    controller read within the band; a success but for a true grip above the band."""
    assert row["status"] == "completed", (baseline, row["failure"], row["message"])
    assert row["strokes"] == row["cycles"] and not row["dropped"]
    assert len(row["half_stroke_rotation_deg"]) == 2 * row["cycles"]
    assert min(row["half_stroke_rotation_deg"]) >= MIN_HALF_STROKE_DEG
    assert F_BAND[0] * row["fd"] <= row["f_min"] and row["f_max"] <= F_BAND[1] * row["fd"]
    assert row["failure"] in ("", "F above band"), row["failure"]


def test_a_firmly_held_thin_stick_is_not_dropped_by_the_sampled_surfaces() -> None:
    # A 2.4 mm foam stick (μ 0.98) held at 1.5 N per pad, both contacts sticking: the sampled
    # surfaces' force jumps left no exact balance, and the world called it dropped at iteration
    # 47 (bench-v1 at the real hand's line timing). A balance within 1 % of the grip holds it.
    row = run("stick-334")
    assert not row["dropped"], row["message"]
    assert row["success"], (row["failure"], row["message"])


def test_a_needle_sunk_deeper_than_its_radius_is_not_dropped_by_the_sampled_surfaces() -> None:
    # A 1.6 mm foam needle, 111 mm long, held end to end: its ends sink 7–8 mm past the pads, so
    # the pads meet its flanks and each 0.25 mm sample carries ≈ 5 % of the grip. The residual
    # jumped across zero by 5.5 % as one sample entered, no balance within 1 % of the grip
    # existed, and the world dropped it at iteration 205, both contacts sticking. A balance
    # within one sample's force holds it.
    row = unseen("fresh5401", "fresh5401-stick-028")
    assert not row["dropped"] and row["status"] == "completed", row["message"]


def test_a_contact_sliding_along_the_object_reverses_before_the_force_ceiling() -> None:
    # A long rounded box with friction below the cone α assumes (μ 0.30): contact A slid along
    # the object for 60 iterations while Λ opened, and F climbed to the ceiling (3 × Fd). F above
    # force_reverse × Fd and not falling reverses instead. (Its pads read ×0.78: the true grip
    # peaks at 2.8 × Fd, above the band — the controller cannot know its pads' gain.)
    row = run("rounded-221")
    rolls_every_stroke(row)
    assert row["f_max"] <= 2.5 * row["fd"]  # the F it reads, which it reverses on


def test_a_grasp_that_loses_a_contact_as_it_settles_is_no_grasp() -> None:
    # A 97 mm pentagon touched at both pads' ends with a wedge wider than its friction angle:
    # turning the pads against the wedge rolled both contacts off the pads' ends, and the grasp
    # ended "grasped" with F = 0; the rolling then reported a drop of an object the placing hand
    # still held. It is a grasp that failed (the placing hand, once the fingers stopped closing
    # on it, lets it go, and it falls: the fingers never held it).
    row = run("polygon-037")
    assert row["status"] == "faulted" and row["fault"] == "no_contact", row["message"]
    assert "settled" in row["message"] and row["iterations"] == 0


def test_a_dither_in_place_is_stuck_not_strokes() -> None:
    # A 29 mm box held with ωA just past the cone the grasp held: the rotation reversed at cone A
    # every 9 iterations both ways, Finger 2 travelled its 1° each time and the object turned
    # 0.05–0.14°; the run "completed" 3 strokes that never turned it. Such reversals end no half
    # stroke: the run faults stuck, and it says why.
    row = run("box-102")
    assert row["status"] == "faulted" and row["fault"] == "stuck", row["message"]
    assert "without a half stroke" in row["message"] and not row["dropped"]
    assert all(h >= MIN_HALF_STROKE_DEG for h in row["half_stroke_rotation_deg"])


def test_a_contact_sliding_just_outside_its_cone_is_no_way_back() -> None:
    # A foam quadrilateral (μ 0.39) whose contact B, after its cone's reversal, slid the length
    # of its pad (S2 19 → 3 mm, F falling to 0.18 × Fd) with ωB held 1° outside the cone, each
    # plan leaning it a little less than it did: the way back beyond WAY_BACK went on. It goes
    # on only while the contact leans less than at the reversal; a sliding one leans as far.
    case = next(c for c in load_suite(UNSEEN / "confirm2115" / "suite.json").cases
                if c.id == "confirm2115-polygon-001")  # fmt: skip
    row = run_case(case.model_dump_json())
    assert row["success"], (row["failure"], row["message"])


def unseen(suite: str, case_id: str, *overrides: str) -> dict[str, Any]:
    case = next(c for c in load_suite(UNSEEN / suite / "suite.json").cases if c.id == case_id)
    row = run_case(case.model_dump_json(), overrides)
    assert row["status"] != "crashed", row["traceback"]
    return row


def test_a_small_object_touched_after_the_grasps_timeout_is_grasped() -> None:
    # A 15 mm box, far from the pre-shape: the fingers, closing at 1.9 of the 3 °/s commanded
    # (each frame's increment from the newest angles), touched it after 20 s, as the grasp's
    # timeout ran out. An untouched grasp that closes as commanded now goes on.
    row = unseen("unseen38", "unseen38-box-138", "rolling.cycles=1")
    assert row["success"], (row["failure"], row["message"])


def test_pads_that_read_one_grip_differently_still_reach_fd() -> None:
    # A 68 mm stick of 2 mm diameter held at its ends: its pads read 2.4 and 1.55 for the
    # same force (a contact smaller than the texel pitch). Finger 1 opened as fast as Finger 2
    # closed and F crept to 1.97 < Fd in 20 s. No finger opens now while F is below Fd.
    row = unseen("unseen38", "unseen38-stick-022", "rolling.cycles=1")
    assert row["iterations"] > 0 and row["fault"] != "no_contact", row["message"]


def test_the_peak_force_counts_the_grasps_closing(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # The judged peak took the true grip at the grasped event and at each rolling iteration
    # only: this polygon's grasp pressed it with 3.0 (in Fd's units; Fd = 2) on its way to the
    # grasp, where the grip was 2.25, and the row said 2.25. It is now the largest over every
    # balance the physics held the object in (every step, the grasp's closing included).
    grips: list[float] = []
    solve = physics.ContactPhysics._solve

    def watched(self: physics.ContactPhysics, *args: Any, **kwargs: Any) -> bool:
        held = solve(self, *args, **kwargs)
        if held:
            c = self._last.contacts
            grips.append((c[physics.DISTAL1][2] + c[physics.DISTAL2][2]) / 2.0)
        return held

    monkeypatch.setattr(physics.ContactPhysics, "_solve", watched)
    case = {c.id: c for c in load_suite("smoke").cases}["polygon-007"]
    row = run_case(case.model_dump_json(), ("rolling.cycles=1",))
    assert row["status"] != "crashed", row["traceback"]
    k = true_grip_scale(case_settings(case, ("rolling.cycles=1",), None, tmp_path / "c.sqlite"))
    assert k is not None and row["peak_force"] == pytest.approx(k * max(grips), rel=1e-9)


def test_a_long_run_holds_the_pads_wedge_where_its_second_stroke_had_it() -> None:
    # A 27 mm circle rolled for 30 strokes (experiments/campaigns/recentre): without
    # re-centring, what each stroke left of the pads' wedge added up, Finger 1 reached its
    # stretch ever sooner, and the rotation reversed at its reach until stuck in the 15th
    # stroke. The stroke's mean wedge is now held to the second stroke's.
    suite = Path(__file__).parents[2] / "experiments" / "campaigns" / "recentre" / "long46t.json"
    case = {c.id: c for c in load_suite(suite).cases}["long46-circle-033"]
    row = run_case(case.model_dump_json(), ("rolling.cycles=30",))
    assert row["status"] != "crashed", row["traceback"]
    rolls_every_stroke(row)
    assert row["success"], (row["failure"], row["message"])
