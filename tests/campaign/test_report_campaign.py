"""Campaign reports and comparisons, from recorded rows (no runs), and judge()."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

from sdh2svc.campaign import run as camp
from sdh2svc.campaign.case import Case
from sdh2svc.campaign.results import write_results
from sdh2svc.cli import main
from sdh2svc.sim.objects import Box, Circle, Material


def case(i: int, family: str) -> Case:
    mat = Material(friction=0.3 + 0.1 * (i % 5))
    size = 40.0 + i
    obj: Box | Circle = Circle(diameter_mm=size, depth_mm=10.0, material=mat)
    if family == "box":
        obj = Box(width_mm=size, height_mm=20.0, depth_mm=10.0, material=mat)
    return Case.model_validate({
        "id": f"{family}-{i}", "family": family, "object": obj.model_dump(),
        "height_mm": 100.0 + 3 * i, "seed": i, "true_width_mm": size,
        "sensor": {"gain_factor": 0.6 + 0.05 * i},
    })  # fmt: skip


def good(c: Case, **kw: Any) -> dict[str, Any]:
    row = camp.case_columns(c)
    row.update(status="completed", strokes=3, cycles=3, iterations=900, fd=2.0, f_min=0.9,
               f_max=3.0, f_mean=2.0, half_stroke_rotation_deg=[5.0, 4.0, 5.0, 4.0, 5.0, 4.0],
               lambda_at_grasp_mm=c.true_width_mm - 1.0, lambda_error_mm=-1.0,
               mean_stroke_rotation_deg=9.0, wall_s=12.0, sim_s=50.0)  # fmt: skip
    row.update(kw)
    return camp.finish_row(row)


def write(out: Path, rows: list[dict[str, Any]], judge: dict[str, Any] | None = None) -> None:
    out.mkdir(parents=True)
    with (out / camp.CASES_FILE).open("w") as fh:
        for r in rows:
            fh.write(json.dumps(r) + "\n")
    info = {
        "suite": "synthetic",
        "overrides": [],
        "code": {"version": "0.1.0"},
        "generator_seed": 7,
        **({"judge": judge} if judge is not None else {}),
    }
    (out / camp.CAMPAIGN_FILE).write_text(json.dumps(info))


def test_judge_names_the_first_failure() -> None:
    c = case(1, "box")
    assert camp.judge(good(c)) == (True, "")
    assert good(c, status="crashed")["failure"] == "crashed"
    assert good(c, status="dropped", dropped=True)["failure"] == "dropped"
    assert good(c, status="faulted", fault="stuck")["failure"] == "faulted: stuck"
    assert good(c, status="stopped")["failure"] == "stopped"
    assert good(c, strokes=2)["failure"] == "too few strokes"
    assert good(c, half_stroke_rotation_deg=[5.0] * 5 + [0.9])["failure"] == "half stroke < 1°"
    assert good(c, half_stroke_rotation_deg=[5.0] * 5)["failure"] == "half stroke < 1°"
    assert good(c, f_min=0.49)["failure"] == "F below band"
    low = good(c, f_min=0.5)
    assert low["success"] and low["f_in_band"]
    assert good(c, f_max=5.01)["failure"] == "F above band"
    assert good(c, f_max=5.0)["success"]


def test_the_band_is_judged_on_the_true_grip_and_a_drop_on_the_truth() -> None:
    c = case(1, "box")
    # the controller's F in band; the true grip (a pad reading low) not: the truth decides
    high = good(c, true_f_min=1.5, true_f_max=5.2, true_f_mean=3.0)
    assert high["failure"] == "F above band" and high["f_in_band"] is False
    assert good(c, f_min=0.1, true_f_min=0.6, true_f_max=4.0)["success"]
    assert good(c, true_f_min=0.4, true_f_max=3.0)["failure"] == "F below band"
    # the controller lost both contacts; the object is still where the fixture holds it
    lost = good(c, status="dropped", fault="dropped", dropped=False)
    assert lost["failure"] == "faulted: dropped"


def test_the_true_grip_is_in_fds_units_through_the_calibration() -> None:
    from sdh2svc.config import load_config

    cfg = load_config(use_env=False)
    calib, pitch = cfg.calibration, cfg.tactile.texel_pitch_mm
    # 1 N spread evenly over 16 cells of 3.4 mm: each reads 1/(16 · 3.4²) N/mm² of physical
    # pressure, i.e. that / physical_pressure_per_count counts; the controller sums the counts'
    # library pressure and multiplies by its reference area
    counts = 1.0 / (16 * pitch**2) / calib.physical_pressure_per_count_n_per_mm2
    f = 16 * counts * calib.pressure_per_count_n_per_mm2 * calib.force_reference_area_mm2
    assert calib.force_per_newton(pitch) == pytest.approx(f, rel=1e-12)
    assert calib.force_per_newton(pitch) == pytest.approx(0.80, abs=0.005)  # Fd = 2: ≈ 2.5 N
    library = calib.model_copy(update={"force_reference_area_mm2": 0.0})
    assert library.force_per_newton(pitch) is None
    # … so a campaign with the library's force judges the band on the controller's F, and says so
    from sdh2svc.campaign.case import Suite

    suite = Suite(name="s", cases=(case(1, "box"),))
    assert camp.campaign_info(suite, [], None)["judge"]["f_band_on"] == "true grip"
    lib = camp.campaign_info(suite, ["calibration.force_reference_area_mm2=0"], None)
    assert lib["judge"]["f_band_on"] == "the controller's F"


def test_results_parquet_keeps_one_row_per_case_in_the_suite_order(tmp_path: Path) -> None:
    cases = [case(i, "box") for i in range(3)]
    rows = [good(cases[2]), good(cases[0], status="stopped"), good(cases[0])]  # re-run: last wins
    write(tmp_path / "a", rows)
    from sdh2svc.campaign.case import Suite

    write_results(tmp_path / "a", suite=Suite(name="s", cases=tuple(cases)))
    table = pq.read_table(tmp_path / "a" / camp.RESULTS_FILE)
    assert table.column("id").to_pylist() == ["box-0", "box-2"]
    assert table.column("success").to_pylist() == [True, True]


def test_report_writes_markdown_and_plots(tmp_path: Path) -> None:
    rows = [good(case(i, "box")) for i in range(6)]
    rows += [good(case(i, "circle"), status="faulted", fault="stuck") for i in range(4)]
    rows += [good(case(9, "circle"), status="crashed", traceback="Traceback …\nValueError: x")]
    write(tmp_path / "a", rows)
    assert main(["campaign", "report", str(tmp_path / "a")]) == 0
    md = (tmp_path / "a" / "report.md").read_text()
    # a crashed case is no result: counted apart, in no rate
    assert "**1 case crashed: no result, left out of every rate below**" in md
    assert "**Success overall: 6/10 (60 %)**" in md
    # Wilson's interval for 6 of 10 is 31.267–83.182 %, rounded outwards
    assert "success rate over everything the suite's generator draws: 31.2–83.2 % " in md
    assert "| box | 6 | 6/6 (100 %) |" in md and "| circle | 4 | 0/4 (0 %) |" in md
    assert "| faulted: stuck | 4 |" in md and "| crashed |" not in md
    assert "* **without a drop**: 10/10 (100 %)" in md
    assert "ValueError: x" in md
    assert "judged on the controller's F." in md  # a campaign whose judge says no other
    for name in ("success_by_family", "map_width_friction", "map_height_size",
                 "map_gain_family", "failure_reasons", "dist_lambda_error", "dist_force",
                 "dist_rotation"):  # fmt: skip
        assert (tmp_path / "a" / "plots" / f"{name}.png").stat().st_size > 1000
        assert f"plots/{name}.png" in md
    assert pq.read_table(tmp_path / "a" / camp.RESULTS_FILE).num_rows == 11


def test_compare_shows_what_got_better_and_worse(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cs = [case(i, "box") for i in range(4)]
    write(tmp_path / "a", [good(cs[0]), good(cs[1], f_min=0.1), good(cs[2]),
                           good(cs[3], strokes=1)])  # fmt: skip
    write(tmp_path / "b", [good(cs[0]), good(cs[1]), good(cs[2], status="dropped",
                                                          dropped=True),
                           good(cs[3], f_max=9.0)])  # fmt: skip
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    text, said = capsys.readouterr()
    assert said == f"written to {tmp_path / 'b' / 'compare.md'}\n"  # where the file went
    assert "| **all** | 2/4 (50 %) | 2/4 (50 %) |" in text
    assert "## Better in B (failed in A, succeeded in B): 1" in text
    assert "| box-1 | box | F below band | success |" in text
    assert "## Worse in B (succeeded in A, failed in B): 1" in text
    assert "| box-2 | box | success | dropped |" in text
    assert "| box-3 | box | too few strokes | F above band |" in text
    assert "B better on 1, worse on 1." in text and "p = 1.000, not significant" in text
    assert (tmp_path / "b" / "compare.md").read_text() == text


def test_compare_says_when_the_two_were_judged_by_different_rules(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cs = [case(i, "box") for i in range(2)]
    rule = {"min_half_stroke_deg": 1.0, "f_band_x_fd": [0.25, 2.5]}
    write(tmp_path / "a", [good(c) for c in cs], judge=rule)
    write(tmp_path / "b", [good(c) for c in cs], judge={**rule, "f_band_on": "true grip"})
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b")]) == 0
    text = capsys.readouterr().out
    assert "**The two were judged by different rules**" in text
    assert "the F band on the controller's F in A, on true grip in B" in text
    write(tmp_path / "c", [good(c) for c in cs], judge={**rule, "f_band_on": "true grip"})
    assert main(["campaign", "compare", str(tmp_path / "b"), str(tmp_path / "c")]) == 0
    assert "different rules" not in capsys.readouterr().out
    # a campaign from before the rule was named judged the band on the controller's F, too
    write(tmp_path / "d", [good(c) for c in cs], judge={**rule, "f_band_on": "the controller's F"})
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "d")]) == 0
    assert "different rules" not in capsys.readouterr().out


def test_compare_writes_nothing_into_its_inputs_and_pairs_no_crash(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A reference campaign may be read-only (or must stay as committed); a crashed case has
    no verdict to be better or worse than."""
    cs = [case(i, "box") for i in range(3)]
    write(tmp_path / "a", [good(cs[0]), good(cs[1]), good(cs[2])])
    write(tmp_path / "b", [good(cs[0], status="crashed", traceback="x"), good(cs[1], f_min=0.1),
                           good(cs[2])])  # fmt: skip
    before = {p: p.stat().st_mtime_ns for d in "ab" for p in (tmp_path / d).iterdir()}
    out = tmp_path / "c.md"
    assert main(["campaign", "compare", str(tmp_path / "a"), str(tmp_path / "b"), "-o",
                 str(out)]) == 0  # fmt: skip
    text = capsys.readouterr().out
    assert {p: p.stat().st_mtime_ns for d in "ab" for p in (tmp_path / d).iterdir()} == before
    assert "**1 of them crashed in A or B: no verdict, not compared** (e.g. box-0;" in text
    assert "| **all** | 3/3 (100 %) | 1/2 (50 %) |" in text  # the crash in no rate
    assert "## Worse in B (succeeded in A, failed in B): 1" in text
    assert "| box-1 | box | success | F below band |" in text
    assert "| box-0 |" not in text
    assert out.read_text() == text


def test_the_familys_lambda_error_is_its_median(tmp_path: Path) -> None:
    # two boxes, −1 and −2 mm: the median is −1.5 (it read the upper of the middle two)
    rows = [good(case(1, "box"), lambda_error_mm=-1.0), good(case(2, "box"), lambda_error_mm=-2.0)]
    write(tmp_path / "a", rows)
    assert main(["campaign", "report", str(tmp_path / "a")]) == 0
    md = (tmp_path / "a" / "report.md").read_text()
    assert any(line.startswith("| box | 2 |") and "| -1.50 |" in line for line in md.splitlines())


def test_report_on_a_directory_without_a_campaign_is_not_found(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["campaign", "report", str(tmp_path)]) == 3
    assert "no campaign in" in capsys.readouterr().err


def test_a_folder_that_only_looks_like_a_campaign_is_refused_untouched(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    (tmp_path / "cases.jsonl").write_text("hello world\n")
    for action in (["report", str(tmp_path)], ["compare", str(tmp_path), str(tmp_path)]):
        assert main(["campaign", *action]) == 3
        assert "no campaign in" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cases.jsonl"]  # nothing written
    (tmp_path / "campaign.json").write_text("{}")
    (tmp_path / "cases.jsonl").write_text("hello world\n5\n[1]\n")
    assert main(["campaign", "report", str(tmp_path)]) == 2
    assert "no case's result in it" in capsys.readouterr().err


@pytest.mark.parametrize("broken", ["results.parquet", "campaign.json"])
def test_a_campaign_file_that_cannot_be_read_is_refused_naming_the_campaign(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], broken: str
) -> None:
    out = tmp_path / "camp"
    write(out, [good(case(i, "box")) for i in range(2)])
    assert main(["campaign", "report", str(out)]) == 0  # readable: a report
    capsys.readouterr()
    (out / broken).write_bytes(b"\x00junk")
    if broken == "results.parquet":
        (out / "cases.jsonl").unlink()  # only the Parquet file left to read
    assert main(["campaign", "report", str(out)]) == 2
    err = capsys.readouterr().err
    assert "cannot read the campaign in" in err and str(out) in err and "Traceback" not in err


def test_a_percentage_is_rounded_but_never_up_across_a_target() -> None:
    from sdh2svc.campaign.report import percent

    assert percent(341, 360) == "94.7 %"  # not "95 %"
    assert percent(359, 360) == "99.7 %" and percent(360, 360) == "100 %"
    assert percent(1, 2) == "50 %" and percent(0, 7) == "0 %"
    # rounded, not cut (71.6 % and 46.6 %: user audit), but never up onto a whole number
    assert percent(43, 60) == "71.7 %" and percent(28, 60) == "46.7 %"
    assert percent(1899, 2000) == "94.9 %" and percent(1901, 2000) == "95.1 %"
    assert percent(2001, 2100) == "95.3 %" and percent(1, 3) == "33.3 %"


def wilson(k: int, n: int, z: float = 1.959963984540054) -> tuple[float, float]:
    """Wilson's score interval, written out (the report takes it from scipy)."""
    p, d = k / n, 1 + z * z / n
    centre = (p + z * z / (2 * n)) / d
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
    return centre - half, centre + half


@pytest.mark.parametrize(("k", "n"), [(349, 360), (6, 11), (0, 20), (20, 20), (423, 450)])
def test_the_success_interval_is_wilsons(k: int, n: int) -> None:
    from sdh2svc.campaign.report import interval

    assert interval(k, n) == pytest.approx(wilson(k, n), abs=1e-12)


def test_an_interval_is_rounded_outwards() -> None:
    from sdh2svc.campaign.report import span

    assert span(0.94612, 0.98285) == "94.6–98.3 %"  # not 98.2
    assert span(0.95, 0.99) == "95.0–99.0 %"  # exact tenths stay
    assert span(0.0, 1.0) == "0.0–100.0 %"


def test_the_paired_test_is_mcnemars_exact() -> None:
    from sdh2svc.campaign.report import paired_p

    # two-sided: twice the chance of 4 or fewer of 17 changes going B's way, 2·3214 / 2¹⁷
    assert paired_p(4, 13) == pytest.approx(2 * 3214 / 2**17, rel=1e-12)
    assert paired_p(13, 4) == paired_p(4, 13)
    assert paired_p(0, 6) == pytest.approx(2 / 2**6, rel=1e-12)
    assert paired_p(1, 1) == 1.0 and paired_p(0, 0) == 1.0
