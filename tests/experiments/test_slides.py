"""experiments.recognition.slides: an edge contact travelling along its pad, on hand-built
traces."""

from __future__ import annotations

from typing import Any

from experiments.recognition.slides import edge_slides, summary
from sdh2svc.control.recognition import ContactKind

EDGE, FLAT, CURVED = ContactKind.EDGE, ContactKind.FLAT, ContactKind.CURVED


def test_a_pivoting_edge_does_not_fire_and_a_travelling_one_does() -> None:
    pivot = [20.0 + 0.02 * j for j in range(12)]  # the rubber's wrap: hundredths a step
    assert edge_slides([EDGE] * 12, pivot) == []
    slide = [20.0] * 4 + [20.0 - 0.3 * j for j in range(1, 9)]  # 0.3 mm a step from 4 on
    got = edge_slides([EDGE] * 12, slide)
    # the first window whose ends lie more than 1 mm apart: 2..7 (1.2 mm; 1..6 is 0.9 mm)
    assert got == list(range(7, 12))


def test_only_an_edge_the_whole_window_long_counts() -> None:
    slide = [20.0 - 0.4 * j for j in range(12)]
    assert edge_slides([CURVED] * 12, slide) == []  # a curve rolls along its pad
    kinds = [EDGE] * 12
    kinds[7] = FLAT
    assert edge_slides(kinds, slide) == [5, 6]  # every window holding iteration 7 is out
    x3: list[float | None] = list(slide)
    x3[0] = None  # no contact: that window's start is unknown
    assert edge_slides([EDGE] * 12, x3)[0] == 6


def test_the_summary_counts_runs_by_whether_they_slid() -> None:
    def pad(
        slid: int, first: int | None, lean: float | None, fires: list[int], inside: int
    ) -> dict[str, Any]:
        return {"slid_iterations": slid, "first_slide": first, "lean_at_first_slide_deg": lean,
                "fires": fires, "fires_in_a_slide": inside}  # fmt: skip

    quiet = pad(0, None, None, [], 0)
    rows = [
        {"friction_angle_deg": 18.0, "pads": [pad(9, 30, 19.0, [33, 34], 2), quiet],
         "moves": {"edge sliding": [0.3, 0.2], "edge holding": [0.01]}},
        {"friction_angle_deg": 20.0, "pads": [quiet, pad(3, 12, 19.5, [], 0)],
         "moves": {"edge holding": [0.03]}},
        {"friction_angle_deg": 30.0, "pads": [quiet, pad(0, None, None, [50], 0)], "moves": {}},
        {"friction_angle_deg": 30.0, "pads": [quiet, quiet], "moves": {}},
    ]  # fmt: skip
    got = summary(rows)
    assert got["runs"] == 4 and got["runs_that_slid"] == 2
    assert got["lean_at_first_slide_minus_friction_angle_deg"] == {
        "mean": 0.25, "min": -0.5, "max": 1.0,
    }  # fmt: skip
    assert got["edge_slides_fired_in_runs_that_slid"] == 1
    assert got["edge_slides_fired_in_runs_that_never_slid"] == 1
    assert got["fires"] == 3 and got["fires_outside_a_slide"] == 1
    moves = got["moves"]
    assert list(moves) == ["edge holding", "edge sliding"]  # pooled over the runs
    assert moves["edge holding"]["n"] == 2 and abs(moves["edge holding"]["median"] - 0.02) < 1e-12
    assert abs(moves["edge sliding"]["median"] - 0.25) < 1e-12
