"""What a campaign refuses before it runs or writes anything, and how it resumes: a folder that
is not its own, a suite that would write elsewhere or cannot be judged, a --set a case would
override, a resume under another configuration; crashed cases run again. The cases are stand-ins
(no simulation): what is checked is the campaign's bookkeeping."""

from __future__ import annotations

import json
import os
import socket
from pathlib import Path
from typing import Any

import pytest
from pydantic import ValidationError

from sdh2svc.campaign import run as camp
from sdh2svc.campaign.case import Case, Suite, load_suite
from sdh2svc.campaign.results import read_results
from sdh2svc.cli import main
from sdh2svc.config import ConfigError
from sdh2svc.provenance import code_version, source_digest
from sdh2svc.sim.objects import get_object

WIDTH = {"egg": 53.0, "rubber": 60.5}


def suite(*seeds: int, name: str = "guards", obj: str = "rubber") -> Suite:
    return Suite(name=name, cases=tuple(
        Case(id=f"{obj}-{s}", family="thesis", object=get_object(obj), height_mm=125.0,
             seed=s, true_width_mm=WIDTH[obj])
        for s in seeds
    ))  # fmt: skip


def stopped(case_json: str, *args: Any) -> dict[str, Any]:
    """A stand-in for run_case: every case recorded as run (no simulation)."""
    case = Case.model_validate_json(case_json)
    return camp.finish_row({**camp.case_columns(case), "status": "completed"})


def run(s: Suite, out: Path, fn: Any = stopped, **kw: Any) -> camp.Outcome:
    return camp.run_campaign(s, out, workers=1, progress=False, case_fn=fn, **kw)


def test_a_folder_of_other_files_is_never_written_into(tmp_path: Path) -> None:
    """Not even its `.work`: a campaign's scratch folder is its own, made and removed by it."""
    out = tmp_path / "mine"
    (out / ".work").mkdir(parents=True)
    (out / ".work" / "draft.tex").write_text("precious")
    (out / "results.parquet").write_text("my own")
    with pytest.raises(camp.CampaignError, match="is not empty and holds no campaign"):
        run(suite(1), out)
    assert (out / ".work" / "draft.tex").read_text() == "precious"
    assert (out / "results.parquet").read_text() == "my own"
    assert sorted(p.name for p in out.iterdir()) == [".work", "results.parquet"]
    # a campaign.json that cannot be read is no campaign to resume either
    bad = tmp_path / "bad"
    bad.mkdir()
    (bad / camp.CAMPAIGN_FILE).write_text("{torn")
    (bad / camp.CASES_FILE).write_text('{"id": "foo", "success": true}\n')
    with pytest.raises(camp.CampaignError, match="cannot be read"):
        run(suite(1), bad)
    assert (bad / camp.CAMPAIGN_FILE).read_text() == "{torn"
    # an empty folder is fine, and the campaign leaves no scratch behind
    empty = tmp_path / "empty"
    empty.mkdir()
    assert run(suite(1, 2), empty).ran == 2
    assert not [p for p in empty.iterdir() if p.name.startswith(".work")]
    # a file is no folder
    (tmp_path / "afile").write_text("")
    with pytest.raises(camp.CampaignError, match="not a directory"):
        run(suite(1), tmp_path / "afile")


def test_a_resume_under_another_configuration_is_refused(tmp_path: Path) -> None:
    """The same --set is not enough: the same effective configuration, whatever file or
    variable gave it (a resume with k = 3 over cases run with k = 2 mixed both silently)."""
    out = tmp_path / "out"
    run(suite(1, 2), out, overrides=["rolling.cycles=1"])
    k3 = tmp_path / "k3.toml"
    k3.write_text("[rolling]\nk = 3.0\n")
    with pytest.raises(camp.CampaignError, match=r"config differs: rolling\.k: 2\.0 there, 3\.0"):
        run(suite(1, 2), out, overrides=["rolling.cycles=1"], config_path=str(k3))
    # the same configuration again resumes (nothing left to run), however its --set is spelt
    assert run(suite(1, 2), out, overrides=["rolling.cycles=1"]).ran == 0
    assert run(suite(1, 2), out, overrides=["rolling.cycles = 1", "rolling.k=2"]).ran == 0


@pytest.mark.parametrize(
    "key",
    [
        "sim.object_height_mm=100",
        "sim.seed=7",
        "sim.object_angle_deg=10",
        "sim.sensor.noise_counts=1",
    ],
)
def test_a_set_of_what_each_case_sets_is_refused(key: str, tmp_path: Path) -> None:
    """The case's value would win without a word while the campaign recorded the --set."""
    with pytest.raises(camp.CampaignError, match="is set by each case"):
        run(suite(1), tmp_path / "out", overrides=[key])
    assert not (tmp_path / "out").exists()
    # the nominal gain the cases scale is the campaign's to set
    assert run(suite(1), tmp_path / "ok", overrides=["sim.sensor.gain_vs_library=0.06"]).ran == 1


@pytest.mark.parametrize("key", ['sim.object="rubber"', 'storage.db_path="/tmp/x.sqlite"'])
def test_a_set_of_what_the_campaign_sets_for_every_case_is_refused(
    key: str, tmp_path: Path
) -> None:
    """Each case runs its own object, recorded in its own database: a --set of either was
    recorded as in effect and changed nothing."""
    with pytest.raises(camp.CampaignError, match="whatever it is set to"):
        run(suite(1), tmp_path / "out", overrides=[key])
    assert not (tmp_path / "out").exists()
    if key.startswith("sim.object"):  # from a file too (the database's path may come from one)
        toml = tmp_path / "obj.toml"
        toml.write_text('[sim]\nobject = "rubber"\n')
        with pytest.raises(camp.CampaignError, match="from --config or the environment"):
            run(suite(1), tmp_path / "out", config_path=str(toml))


def test_a_crashed_case_runs_again_on_resume(tmp_path: Path) -> None:
    """A crash is no result: the resume runs the case again and its new row decides."""
    calls: list[str] = []

    def crashing(case_json: str, *args: Any) -> dict[str, Any]:
        case = Case.model_validate_json(case_json)
        calls.append(case.id)
        if case.seed == 2 and calls.count(case.id) == 1:
            return camp.crashed_row(case, "Traceback: a transient failure")
        return stopped(case_json)

    out = tmp_path / "out"
    first = run(suite(1, 2), out, fn=crashing)
    assert (first.crashed, first.ran) == (1, 2)
    again = run(suite(1, 2), out, fn=crashing)
    assert calls == ["rubber-1", "rubber-2", "rubber-2"]
    assert (again.ran, again.skipped, again.crashed) == (1, 1, 0)
    rows, _ = read_results(out)
    assert [r["status"] for r in rows] == ["completed", "completed"]


def test_suites_that_cannot_be_run_or_judged_are_refused(tmp_path: Path) -> None:
    """A name that is a path (the campaign's folder would be written elsewhere), no cases, a
    seed Parquet cannot hold, a stated width that is not the object's, an object wider than
    the open fingers, NaN, a file that is not UTF-8, a directory."""
    data = json.loads(suite(1).to_json())

    def refused(change: dict[str, Any], case_change: dict[str, Any], fragment: str) -> None:
        d = json.loads(json.dumps(data))
        d.update(change)
        if case_change:
            d["cases"][0].update(case_change)
        path = tmp_path / "s.json"
        path.write_text(json.dumps(d))
        with pytest.raises(ConfigError) as ei:
            load_suite(path)
        assert fragment in str(ei.value), str(ei.value)

    refused({"name": "../../escape"}, {}, "name = '../../escape'")
    refused({"name": ""}, {}, "name = ''")
    refused({"cases": []}, {}, "cases")
    refused({}, {"seed": 2**70}, "cases.0.seed")
    refused({}, {"true_width_mm": 150.0}, "true_width_mm is 150 but the object is 60.500 mm")
    refused({}, {"height_mm": float("nan")}, "finite number")
    wide = get_object("stick119").model_copy(update={"length_mm": 140.0}).model_dump()
    refused({}, {"object": wide, "true_width_mm": 140.0}, "the open fingers take at most 122.5")
    # a number written as a string is a mistake in the file, not a seed or a height
    refused({}, {"seed": "3"}, "cases.0.seed = '3'")
    refused({}, {"height_mm": "124.5"}, "cases.0.height_mm = '124.5'")
    # the family names the object's kind: the rubber (a box with rounded corners) is no circle
    refused({}, {"family": "circle"}, "family 'circle' but the object is a box with rounded")
    refused({}, {"family": "box"}, "family 'box' but the object is a box with rounded corners")
    latin1 = tmp_path / "latin1.json"
    latin1.write_bytes(b'{"name": "b\xe4d", "cases": []}')
    with pytest.raises(ConfigError, match="not a JSON suite file"):
        load_suite(latin1)
    with pytest.raises(ValidationError):
        Suite(name="a/b", cases=suite(1).cases)


def test_a_folder_named_like_a_packaged_suite_does_not_hide_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`cd campaigns; campaign run smoke` (where smoke/ is the smoke campaign's folder)."""
    (tmp_path / "smoke").mkdir()
    monkeypatch.chdir(tmp_path)
    assert load_suite("smoke").name == "smoke"
    with pytest.raises(ConfigError, match="is a directory, not a suite file"):
        load_suite("./smoke")


def test_report_and_compare_take_only_their_own_arguments(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    out = tmp_path / "a"
    run(suite(1), out)
    for args, fragment in (
        (["compare", str(out)], "compare needs two campaign folders"),
        (["report", str(out), str(out)], "report takes one campaign folder"),
        (["report", str(out), "--set", "rolling.k=3"], "--set: options of campaign run"),
        (["compare", str(out), str(out), "--workers", "2"], "--workers: options of campaign run"),
        (["report", str(out), "-o", str(tmp_path / "r.md")], "-o/--output goes with compare"),
        (["run", "smoke", "-o", str(tmp_path / "r")], "-o/--output goes with compare"),
    ):
        assert main(["campaign", *args]) == 2, args
        assert fragment in capsys.readouterr().err


def test_compare_pairs_a_case_only_with_the_same_case(tmp_path: Path) -> None:
    """The packaged suites share ids (box-000 …) for different objects: same id, other spec,
    another case — not paired, and said so."""
    from sdh2svc.campaign.report import compare

    run(suite(1, 2, name="one"), tmp_path / "a")
    run(suite(1, 2, name="two", obj="egg"), tmp_path / "b")  # other objects
    b_rows = [json.loads(x) for x in (tmp_path / "b" / camp.CASES_FILE).read_text().splitlines()]
    a_rows = [json.loads(x) for x in (tmp_path / "a" / camp.CASES_FILE).read_text().splitlines()]
    for r in b_rows:  # the same ids as A's, other objects
        r["id"] = r["id"].replace("egg", "rubber")
    (tmp_path / "b" / camp.CASES_FILE).write_text("".join(json.dumps(r) + "\n" for r in b_rows))
    text = compare(tmp_path / "a", tmp_path / "b")
    assert "0 cases in both" in text
    assert "2 cases share an id but not their spec" in text and "The suites differ" in text
    assert a_rows[0]["spec"] != b_rows[0]["spec"]


def test_report_skips_lines_that_are_no_case_results(tmp_path: Path) -> None:
    from sdh2svc.campaign.report import load

    out = tmp_path / "a"
    run(suite(1), out)
    with (out / camp.CASES_FILE).open("a") as fh:
        fh.write('{"id": "foo", "success": true}\n[1, 2]\n{"id": 3}\n')
    rows, _ = load(out)
    assert [r["id"] for r in rows] == ["rubber-1"]


def test_a_ray_address_where_nothing_listens_is_refused_at_once(tmp_path: Path) -> None:
    """Ray would retry HOST:PORT for many minutes; nothing is written before it answers."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(
        camp.CampaignError, match=f"cannot reach the Ray cluster at 127.0.0.1:{port}"
    ):
        camp.run_campaign(suite(1), tmp_path / "o", ray_address=f"127.0.0.1:{port}",
                          progress=False)  # fmt: skip
    assert not (tmp_path / "o").exists()


def test_a_resume_with_nothing_left_starts_no_ray(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`--ray local` on a finished campaign started a Ray instance (7 s) to run nothing."""
    out = tmp_path / "out"
    run(suite(1), out)

    def no_ray(*args: Any) -> None:
        raise AssertionError("Ray started with nothing to run")

    monkeypatch.setattr(camp, "_run_ray", no_ray)
    res = camp.run_campaign(suite(1), out, ray_address="local", progress=False)
    assert (res.ran, res.skipped) == (0, 1)


def test_a_resume_under_other_code_or_another_judge_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two edits of one commit both read `git describe` `…-dirty`: the source's digest tells
    them apart; and a verdict judged by other rules is not mixed with these either."""
    out = tmp_path / "out"
    run(suite(1, 2), out)
    with monkeypatch.context() as m:
        m.setattr(camp, "code_version", lambda: {**code_version(), "source": "0" * 64})
        with pytest.raises(camp.CampaignError, match="another sdh2svc made") as other:
            run(suite(1, 2), out)
        assert "source 000000000000) now" in str(other.value)
    with monkeypatch.context() as m:
        m.setattr(camp, "MIN_HALF_STROKE_DEG", 90.0)
        with pytest.raises(camp.CampaignError, match="judge differs"):
            run(suite(1, 2), out)
    assert run(suite(1, 2), out).ran == 0  # as it was: resumed
    # the checkout gone -dirty meanwhile (the campaign's own folder in it), the same source
    same = {**camp.code_version(), "git_describe": "abc1234-dirty"}
    with monkeypatch.context() as m:
        m.setattr(camp, "code_version", lambda: same)
        assert run(suite(1, 2), out).ran == 0


def test_the_source_digest_changes_with_any_edit_of_the_package(tmp_path: Path) -> None:
    import shutil

    pkg = tmp_path / "sdh2svc"
    shutil.copytree(Path(camp.__file__).parents[1], pkg,
                    ignore=shutil.ignore_patterns("__pycache__"))  # fmt: skip
    before = source_digest(pkg)
    assert before == source_digest()  # the same files, the same digest
    (pkg / "__pycache__").mkdir()
    (pkg / "__pycache__" / "x.pyc").write_bytes(b"compiled")
    assert source_digest(pkg) == before  # what Python caches is no source
    model = pkg / "control" / "recognition_model.json"
    model.write_text(model.read_text() + " ")
    assert source_digest(pkg) != before


@pytest.mark.parametrize("how", ["table", "config", "env"])
def test_a_case_key_changed_by_any_layer_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, how: str
) -> None:
    """Not only `--set sim.seed=3`: a table, a file or a variable that sets what every case
    sets would be overridden by the case without a word, and recorded as if in effect."""
    kw: dict[str, Any] = {}
    if how == "table":
        kw["overrides"] = ["sim.sensor={creep_gain=0.5}"]
    elif how == "config":
        (tmp_path / "c.toml").write_text("[sim]\nobject_angle_deg = 45.0\n")
        kw["config_path"] = str(tmp_path / "c.toml")
    else:
        monkeypatch.setenv("SDH2SVC_SIM__SEED", "3")
    key = {"table": "sim.sensor.creep_gain", "config": "sim.object_angle_deg",
           "env": "sim.seed"}[how]  # fmt: skip
    with pytest.raises(camp.CampaignError, match=f"{key} = .*is set by each case"):
        run(suite(1), tmp_path / "o", **kw)
    assert not (tmp_path / "o").exists()
    monkeypatch.delenv("SDH2SVC_SIM__SEED", raising=False)
    # the nominal gain the cases scale may be set, in any form
    assert run(suite(1), tmp_path / "ok", overrides=["sim.sensor={gain_vs_library=10.0}"]).ran == 1


def test_one_folder_one_running_campaign_and_a_killed_runs_scratch_is_removed(
    tmp_path: Path,
) -> None:
    import fcntl

    out = tmp_path / "o"
    run(suite(1, 2), out)
    cases = out / camp.CASES_FILE
    cases.write_text(cases.read_text().splitlines(keepends=True)[0])  # as if cut short
    with (out / camp.LOCK_FILE).open("a+") as fh:  # as a campaign running there holds it
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        with pytest.raises(camp.CampaignError, match=f"another campaign is running in {out}"):
            run(suite(1, 2), out)
    assert [r["id"] for r in camp.read_rows(out)] == ["rubber-1"]
    (out / ".work-killed").mkdir()  # a SIGKILLed run's scratch, its run database in it
    (out / ".work-killed" / "case-rubber-2.sqlite").write_text("")
    assert run(suite(1, 2), out).ran == 1
    assert not [p for p in out.iterdir() if p.name.startswith(".work")]
    assert not (out / camp.LOCK_FILE).exists()  # removed, still locked, as the campaign ended


def locked_elsewhere(case_json: str, *args: Any) -> dict[str, Any]:
    """:func:`stopped`, after checking that the folder's lock file is held (by the campaign)."""
    import fcntl

    out = Path(os.environ["GUARDS_OUT"])
    with (out / camp.LOCK_FILE).open("a+") as fh, pytest.raises(BlockingIOError):
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    return stopped(case_json, *args)


def test_a_lock_file_removed_before_it_was_taken_is_taken_anew(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A campaign that opens the lock file just as the one before it ends and removes it must
    not run on a lock nobody else can see: it takes the lock again on the file at the path."""
    import fcntl

    out = tmp_path / "o"
    out.mkdir()
    monkeypatch.setenv("GUARDS_OUT", str(out))
    real, calls = fcntl.flock, []

    def flock(fh: Any, op: int) -> None:
        calls.append(op)
        if len(calls) == 1:  # the run before ends between this run's open and its flock
            (out / camp.LOCK_FILE).unlink()
        real(fh, op)

    monkeypatch.setattr(fcntl, "flock", flock)
    assert run(suite(1), out, locked_elsewhere).ran == 1
    assert len(calls) == 3  # the lock taken twice, then the case's check that it is held
    assert not (out / camp.LOCK_FILE).exists()


def test_progress_to_a_log_is_plain_lines(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Not a terminal (captured here, as a file or a pipe would be): one line per 5 % of the
    cases, not a bar redrawn with carriage returns."""
    camp.run_campaign(suite(*range(1, 41)), tmp_path / "o", workers=1, case_fn=stopped)
    err = capsys.readouterr().err
    assert "\r" not in err
    lines = err.splitlines()
    assert len(lines) == 20
    assert lines[0].startswith("2/40 cases, success 0 %, about ") and lines[0].endswith(" left")
    assert lines[-1].startswith("40/40 cases")


def test_the_running_rate_leaves_a_crashed_case_out(capsys: pytest.CaptureFixture[str]) -> None:
    """As the report's: a crash is no result (the same command runs it again)."""
    bar = camp._progress(4, 1, 1, enabled=True)  # one case already there, a success
    for success, judged in ((False, True), (False, False), (True, True)):
        bar.update(success, judged=judged)
    assert capsys.readouterr().err.splitlines()[-1].startswith("4/4 cases, success 67 %, ")


def test_an_invalid_case_is_named_without_a_second_complaint_about_the_list(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = json.loads(suite(1).to_json())
    data["cases"][0]["object"]["material"]["friction"] = 7.5
    (tmp_path / "s.json").write_text(json.dumps(data))
    assert main(["campaign", "run", str(tmp_path / "s.json"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "friction = 7.5" in err and "allowed: 0.0 < friction ≤ 3.0" in err
    assert "at least 1 item" not in err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize(
    ("args", "fragment"),
    [
        (["--config", "/nonexistent.toml"], "--config: options of campaign run, not of generate"),
        (["--set", "rolling.k=3"], "--set: options of campaign run, not of generate"),
        (["--workers", "0"], "--workers: options of campaign run"),
    ],
)
def test_generate_refuses_the_options_of_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], fragment: str
) -> None:
    out = tmp_path / "g.json"
    cmd = ["campaign", "generate", "g", "--seed", "1", "--cases", "1", "-o", str(out), *args]
    assert main(cmd) == 2
    assert fragment in capsys.readouterr().err
    assert not out.exists()


def test_a_seed_beyond_64_bits_and_a_ray_address_without_a_port_are_usage_errors(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    big = str(2**64)
    cmd = ["campaign", "generate", "g", "--seed", big, "--cases", "1", "-o", str(tmp_path / "g")]
    assert main(cmd) == 2
    assert f"--seed {big}: 0 to {2**63 - 1}" in capsys.readouterr().err
    with pytest.raises(camp.CampaignError, match="--ray nohost: give auto, local, HOST:PORT"):
        run(suite(1), tmp_path / "o", ray_address="nohost")
    assert not (tmp_path / "o").exists()


def test_a_suite_name_too_long_for_its_case_ids_is_a_usage_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a 53-character name: the ids NAME-polygon-001 are 65; it ended as "a bug" (exit 70)
    out = tmp_path / "g.json"
    cmd = ["campaign", "generate", "a" * 53, "--seed", "1", "--cases", "2", "-o", str(out)]
    assert main(cmd) == 2
    assert "at most 52 characters for 2 cases" in capsys.readouterr().err
    assert not out.exists()


def test_a_report_older_than_the_results_a_run_made_is_said(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A campaign resumed after its report was written: report.md and the plots stayed as
    they were, out of date, without a word (CLI audit)."""
    out, path = tmp_path / "o", tmp_path / "s.json"
    s = suite(1)
    s.dump(path)
    run(s, out)
    (out / "report.md").write_text("3 of 10 cases recorded")
    os.utime(out / "report.md", (0, 0))
    assert main(["campaign", "run", str(path), "--out", str(out), "--quiet"]) == 0  # nothing left
    err = capsys.readouterr().err
    assert f"{out / 'report.md'} is older than these results" in err, err
    assert main(["campaign", "report", str(out)]) == 0
    capsys.readouterr()
    assert main(["campaign", "run", str(path), "--out", str(out), "--quiet"]) == 0
    assert "older than these results" not in capsys.readouterr().err
