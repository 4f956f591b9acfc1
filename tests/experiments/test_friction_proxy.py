"""experiments.friction_proxy: the probed run is the campaign's run, and its rows and report say
what the measured and the true leans were."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

import sdh2svc.control.runner as runner
from experiments.friction_proxy import COLUMNS, main, probe_case, report, stalls
from sdh2svc.campaign.case import load_suite
from sdh2svc.campaign.run import run_case


@pytest.fixture(scope="module")
def probed() -> tuple[dict, dict]:
    case = load_suite("smoke").cases[0].model_copy(deep=True)
    cj = case.model_dump_json()
    over = ("rolling.cycles=1",)
    return probe_case(cj, over), run_case(cj, over)


def test_the_probed_run_is_the_campaigns(probed: tuple[dict, dict]) -> None:
    res, row = probed
    assert (res["status"], res["success"], res["failure"]) == (
        row["status"], row["success"], row["failure"])  # fmt: skip
    assert len(res["rows"]) == row["iterations"]  # one row per rolling iteration, none added
    assert runner.step.__module__ == "sdh2svc.control.rolling"  # the runner's step restored


def test_its_rows_hold_both_leans_of_both_contacts(probed: tuple[dict, dict]) -> None:
    res, _ = probed
    col = {c: i for i, c in enumerate(COLUMNS)}
    rows = res["rows"]
    assert [r[col["iteration"]] for r in rows] == list(range(len(rows)))
    both = [r for r in rows if r[col["lean_A"]] is not None and r[col["true_A"]] is not None]
    assert len(both) > 0.9 * len(rows)
    # the measured lean tracks the true one (within a few degrees: the pads are 3.4 mm cells)
    err = [abs(r[col["lean_A"]] - r[col["true_A"]]) for r in both]
    assert sorted(err)[len(err) // 2] < 2.0
    assert all(0.0 <= r[col["true_A"]] <= math.degrees(math.atan(2.0)) for r in both)
    assert all(r[col["alpha"]] >= 22.0 - 1e-9 for r in rows)


def test_the_report_states_the_figures(probed: tuple[dict, dict], tmp_path: Path) -> None:
    res, _ = probed
    out = tmp_path / "probe.jsonl"
    out.write_text(json.dumps(res) + "\n")
    text = report([out])
    assert text.startswith("1 runs")
    assert "| every rolling contact-iteration |" in text
    col = {c: i for i, c in enumerate(COLUMNS)}
    n = sum(r[col[f"lean_{x}"]] is not None and r[col[f"true_{x}"]] is not None
            for r in res["rows"] for x in "AB")  # fmt: skip
    assert f"n = {n} |" in text.splitlines()[4]  # every contact-iteration with both leans


def test_bad_input_is_refused_with_a_message(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A bad --set, an unknown suite and a file that is not a probe's output: exit 2 and one
    line naming the problem, before any run starts."""
    out = tmp_path / "out.jsonl"
    assert main(["run", "smoke", str(out), "--set", "rolling.nope=1"]) == 2
    assert "rolling.nope" in capsys.readouterr().err and not out.exists()
    assert main(["run", "nosuch", str(out)]) == 2
    assert "no suite 'nosuch'" in capsys.readouterr().err
    other = tmp_path / "other.jsonl"
    other.write_text('{"id": "x"}\n')
    assert main(["report", str(other)]) == 2
    assert "not the output of `friction_proxy run`" in capsys.readouterr().err


def _rows(leans: list[float], plan_ahead: float, slipping: bool) -> list[list[object]]:
    """Rows in which contact A leans as given, each plan asking ``plan_ahead`` more."""
    return [[i, lean, 5.0, lean + plan_ahead, 5.0, lean, 5.0, slipping, False, 22.0, None]
            for i, lean in enumerate(leans)]  # fmt: skip


def test_a_stalled_lean_is_told_from_one_that_follows_its_plan() -> None:
    """Stalled: pushed 0.5° an iteration, the lean held at 19°; it slid or it held (the rule
    cannot tell which, so both are found, with the truth beside them). Following the plan, or
    stalled below 16°, or across a reversal: not found."""
    stalled = _rows([19.0] * 8, 0.5, True)
    found = stalls(stalled)
    assert [(k, x) for k, x, _ in found] == [(6, "A"), (7, "A")] and all(s for *_, s in found)
    assert all(not s for *_, s in stalls(_rows([19.0] * 8, 0.5, False)))
    assert stalls(_rows([19.0 + 0.1 * i for i in range(8)], 0.5, True)) == []  # follows
    assert stalls(_rows([12.0] * 8, 0.5, True)) == []  # below the lowest friction angle
    assert stalls(_rows([19.0] * 8, 0.2, True)) == []  # plans asking too little
    reversed_ = _rows([19.0] * 8, 0.5, True)
    reversed_[3][COLUMNS.index("reversal")] = "cone_A"
    assert stalls(reversed_) == []
