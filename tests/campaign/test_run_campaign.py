"""Campaign runs: tiny suites of short fast-mode runs through the full byte path."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pyarrow.parquet as pq
import pytest

import sdh2svc.service.headless as headless
from sdh2svc.campaign import run as camp
from sdh2svc.campaign.case import Case, Suite, load_suite
from sdh2svc.campaign.generate import GENERATED, generate_cases
from sdh2svc.campaign.results import METADATA_KEY
from sdh2svc.cli import main
from sdh2svc.connect import Simulated
from sdh2svc.sim.objects import get_object

ONE_STROKE = ["rolling.cycles=1"]  # a few seconds per case
WIDTH = {"egg": 53.0, "rubber": 60.5}  # along y0 at angle 0: the egg's long axis, the rubber's
# what a case did, without its wall time
JUDGED = ("status", "success", "failure", "strokes", "iterations", "half_stroke_rotation_deg",
          "dropped", "slips", "lambda_at_grasp_mm", "f_min", "f_max", "peak_force",
          "sim_s")  # fmt: skip


def tiny_suite(*cases: tuple[str, int], name: str = "tiny") -> Suite:
    return Suite(name=name, cases=tuple(
        Case(id=f"{obj}-{seed}", family="thesis", object=get_object(obj), height_mm=125.0,
             seed=seed, true_width_mm=WIDTH[obj])
        for obj, seed in cases
    ))  # fmt: skip


THREE = (("egg", 1), ("rubber", 1), ("rubber", 2))


def lines(out: Path) -> list[dict[str, Any]]:
    return camp.read_rows(out)


@pytest.fixture(scope="module")
def one_worker(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("one") / "out"
    camp.run_campaign(tiny_suite(*THREE), out, workers=1, overrides=ONE_STROKE, progress=False)
    return out


def test_a_campaign_writes_parquet_with_every_case_judged(one_worker: Path) -> None:
    table = pq.read_table(one_worker / camp.RESULTS_FILE)
    assert table.num_rows == 3
    for col in ("id", "family", "success", "failure", "status", "strokes",
                "half_stroke_rotation_deg", "dropped", "slips", "lambda_error_mm", "f_in_band",
                "peak_force", "iterations", "wall_s", "spec", "friction", "size_mm",
                "height_mm", "gain_factor", "traceback"):  # fmt: skip
        assert col in table.column_names
    rows = {r["id"]: r for r in table.to_pylist()}
    assert set(rows) == {"egg-1", "rubber-1", "rubber-2"}
    for r in rows.values():
        assert r["status"] == "completed" and r["strokes"] == 1 and not r["dropped"]
        assert len(r["half_stroke_rotation_deg"]) == 2
        assert abs(r["lambda_error_mm"]) < 3.0
        assert Case.model_validate_json(r["spec"]).id == r["id"]
        assert (r["success"], r["failure"]) == camp.judge(r)
    # every one turns ≥ 1° every half stroke — the egg ≈ 15° and most of the way back within
    # one (its largest excursion counts, not the net: see TruthProbe.half_strokes_deg)
    assert all(r["success"] for r in rows.values()), rows
    assert max(rows["egg-1"]["half_stroke_rotation_deg"]) > 10.0
    info = json.loads(table.schema.metadata[METADATA_KEY])
    assert info["suite"] == "tiny" and info["overrides"] == ONE_STROKE
    assert info["code"]["version"] and info["config"]["rolling"]["cycles"] == 1
    assert json.loads((one_worker / camp.CAMPAIGN_FILE).read_text())["suite_digest"]
    assert not (one_worker / ".work").exists()


def test_two_workers_give_the_same_results_as_one(one_worker: Path, tmp_path: Path) -> None:
    out = tmp_path / "two"
    res = camp.run_campaign(tiny_suite(*THREE), out, workers=2, overrides=ONE_STROKE,
                            progress=False)  # fmt: skip
    assert (res.ran, res.skipped) == (3, 0)
    one = {r["id"]: r for r in pq.read_table(one_worker / camp.RESULTS_FILE).to_pylist()}
    two = {r["id"]: r for r in pq.read_table(out / camp.RESULTS_FILE).to_pylist()}
    assert one.keys() == two.keys()
    for i in one:
        assert {k: one[i][k] for k in JUDGED} == {k: two[i][k] for k in JUDGED}, i


def _default_sigint() -> None:
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def counting(calls: list[str]) -> Any:
    def fn(case_json: str, *args: Any) -> dict[str, Any]:
        calls.append(json.loads(case_json)["id"])
        return camp.run_case(case_json, *args)

    return fn


def test_a_rerun_runs_only_the_cases_missing_from_cases_jsonl(one_worker: Path,
                                                              tmp_path: Path) -> None:  # fmt: skip
    out = tmp_path / "resumed"
    out.mkdir()
    for name in (camp.CASES_FILE, camp.CAMPAIGN_FILE):
        (out / name).write_bytes((one_worker / name).read_bytes())
    kept = (one_worker / camp.CASES_FILE).read_text().splitlines(keepends=True)
    assert len(kept) == 3
    (out / camp.CASES_FILE).write_text(kept[0] + kept[2][: len(kept[2]) // 2])  # a torn line
    calls: list[str] = []
    res = camp.run_campaign(tiny_suite(*THREE), out, workers=1, overrides=ONE_STROKE,
                            progress=False, case_fn=counting(calls))  # fmt: skip
    first = json.loads(kept[0])["id"]
    assert sorted(calls) == sorted({"egg-1", "rubber-1", "rubber-2"} - {first})
    assert (res.skipped, res.ran) == (1, 2)
    ids = [r["id"] for r in lines(out)]
    assert sorted(ids) == ["egg-1", "rubber-1", "rubber-2"]  # each once, the torn line gone
    calls.clear()
    res = camp.run_campaign(tiny_suite(*THREE), out, workers=1, overrides=ONE_STROKE,
                            progress=False, case_fn=counting(calls))  # fmt: skip
    assert calls == [] and res.ran == 0 and res.skipped == 3
    assert pq.read_table(out / camp.RESULTS_FILE).num_rows == 3


def test_another_campaign_in_the_same_directory_is_refused(one_worker: Path) -> None:
    with pytest.raises(camp.CampaignError, match="another campaign"):
        camp.run_campaign(tiny_suite(*THREE), one_worker, workers=1,
                          overrides=["rolling.cycles=2"], progress=False)  # fmt: skip


def _wait_for_line(path: Path, proc: subprocess.Popen[bytes], deadline_s: float) -> None:
    """Until ``path`` holds a whole line (polling the file, not sleeping a fixed time)."""
    end = time.monotonic() + deadline_s
    while time.monotonic() < end:
        if path.exists() and b"\n" in path.read_bytes():
            return
        if proc.poll() is not None:
            pytest.fail(f"the campaign ended before any case: {proc.stderr.read()!r}")  # type: ignore[union-attr]
        time.sleep(0.02)
    pytest.fail("no case finished in time")


def _descendants(pid: int) -> set[int]:
    """The processes below ``pid`` now (from /proc): a pool's forkserver and its workers."""
    children: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:
            continue
        children.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    out, todo = set(), [pid]
    while todo:
        for c in children.get(todo.pop(), []):
            out.add(c)
            todo.append(c)
    return out


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0]
    except OSError:
        return False
    return state != "Z"


def _all_gone(pids: set[int], deadline_s: float) -> bool:
    """Whether every one of ``pids`` has ended within ``deadline_s`` (a deadline to give up,
    not a measure of speed)."""
    end = time.monotonic() + deadline_s
    while any(_alive(p) for p in pids) and time.monotonic() < end:
        time.sleep(0.05)
    return not [p for p in pids if _alive(p)]


def _resume_runs_only_the_rest(suite: Suite, out: Path, done: list[str]) -> camp.Outcome:
    """The same campaign again (its cases recorded as run, not simulated): it runs exactly the
    cases not in ``done``."""
    calls: list[str] = []

    def recorded(case_json: str, *args: Any) -> dict[str, Any]:  # the resume, not the runs
        calls.append(json.loads(case_json)["id"])
        case = Case.model_validate_json(case_json)
        return camp.finish_row({**camp.case_columns(case), "status": "completed"})

    res = camp.run_campaign(suite, out, workers=1, overrides=ONE_STROKE, progress=False,
                            case_fn=recorded)  # fmt: skip
    assert sorted(calls) == sorted({c.id for c in suite.cases} - set(done))
    assert res.ran == len(suite.cases) - len(done)
    return res


def test_sigterm_reaches_a_case_running_here_as_ctrl_c_does() -> None:
    """SIGTERM is sent on as SIGINT, to asyncio's handler while a case runs in this process: it
    cancels the case's task, which ends before the interrupt leaves the loop. Raised as a bare
    KeyboardInterrupt at any point, it could land inside the loop's own bookkeeping, and the
    campaign then hung (4 of 60 timed SIGTERMs); a bare one leaves the loop first and the task
    is cancelled only as the loop closes."""
    import asyncio

    from sdh2svc.cli import _interrupt

    order: list[str] = []

    async def case() -> None:
        try:
            os.kill(os.getpid(), signal.SIGTERM)
            await asyncio.sleep(10.0)
        except asyncio.CancelledError:
            order.append("cancelled")
            raise

    term = signal.signal(signal.SIGTERM, _interrupt)
    sigint = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with asyncio.Runner() as runner:
            try:
                runner.run(case())
            except KeyboardInterrupt:
                order.append("interrupted")
    finally:
        signal.signal(signal.SIGTERM, term)
        signal.signal(signal.SIGINT, sigint)
    assert order == ["cancelled", "interrupted"]


# the pool: a single process is the simpler case; SIGTERM (`kill`) stops it as Ctrl-C does
@pytest.mark.parametrize(("workers", "sig"), [(2, signal.SIGINT), (2, signal.SIGTERM)])
def test_ctrl_c_keeps_every_finished_case_and_a_rerun_completes(
    tmp_path: Path, workers: int, sig: int
) -> None:
    # far more cases than can finish between the first one's line and the signal (a few ms)
    n = 24
    suite = tiny_suite(*(("rubber", seed) for seed in range(1, n + 1)))
    suite.dump(tmp_path / "s.json")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "sdh2svc", "campaign", "run", str(tmp_path / "s.json"),
           "--out", str(out), "--workers", str(workers), "--quiet",
           "--set", ONE_STROKE[0]]  # fmt: skip
    # a Ctrl-C as a terminal sends it, whatever this process does with SIGINT (an ignored
    # signal is inherited, and a local Ray instance started by another test may ignore it)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            env={**os.environ, "PYTHONUNBUFFERED": "1"},
                            preexec_fn=_default_sigint)  # fmt: skip
    try:
        _wait_for_line(out / camp.CASES_FILE, proc, 240)
        below = _descendants(proc.pid)
        assert below, "no pool processes"
        proc.send_signal(sig)
        assert proc.wait(timeout=60) == 130, proc.stderr.read()  # type: ignore[union-attr]
        err = proc.stderr.read().decode()  # type: ignore[union-attr]
        assert "interrupted; every finished case is in" in err, err
        # no worker outlives the campaign (a SIGTERM used to orphan them, running)
        assert _all_gone(below, 30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stdout.close()  # type: ignore[union-attr]
        proc.stderr.close()  # type: ignore[union-attr]
    done = [r["id"] for r in lines(out)]
    assert 1 <= len(done) < n and len(set(done)) == len(done)
    assert sorted(pq.read_table(out / camp.RESULTS_FILE).column("id").to_pylist()) == sorted(done)
    assert all(r["status"] == "completed" for r in lines(out))
    _resume_runs_only_the_rest(suite, out, done)
    assert sorted(r["id"] for r in lines(out)) == sorted(c.id for c in suite.cases)


def test_a_killed_campaign_leaves_no_process_behind_and_its_rerun_completes(
    tmp_path: Path,
) -> None:
    """SIGKILL (no chance to stop the pool): the workers see their campaign gone and end;
    nothing they were running is recorded, and the same command finishes the campaign."""
    n = 24
    suite = tiny_suite(*(("rubber", seed) for seed in range(1, n + 1)))
    suite.dump(tmp_path / "s.json")
    out = tmp_path / "out"
    cmd = [sys.executable, "-m", "sdh2svc", "campaign", "run", str(tmp_path / "s.json"),
           "--out", str(out), "--workers", "2", "--quiet", "--set", ONE_STROKE[0]]  # fmt: skip
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    try:
        _wait_for_line(out / camp.CASES_FILE, proc, 240)
        below = _descendants(proc.pid)
        assert below, "no pool processes"
        proc.kill()
        proc.wait(timeout=60)
        assert _all_gone(below, 60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        proc.stderr.close()  # type: ignore[union-attr]
    done = [r["id"] for r in lines(out)]
    assert 1 <= len(done) < n and len(set(done)) == len(done)
    assert [p.name for p in out.glob(".work-*")]  # the killed run's scratch is still there
    _resume_runs_only_the_rest(suite, out, done)
    assert not list(out.glob(".work-*"))


def test_a_crashing_case_is_recorded_with_its_traceback_and_the_rest_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    real = headless.run_once

    async def run_once(cfg: Any, where: Any, **kw: Any) -> dict[str, Any]:
        if cfg.sim.seed == 2:
            raise RuntimeError("the world fell over")
        return await real(cfg, where, **kw)

    monkeypatch.setattr(headless, "run_once", run_once)
    out = tmp_path / "out"
    res = camp.run_campaign(tiny_suite(("rubber", 2), ("rubber", 1)), out, workers=1,
                            overrides=ONE_STROKE, progress=False)  # fmt: skip
    assert (res.ran, res.crashed, res.succeeded) == (2, 1, 1)
    rows = {r["id"]: r for r in pq.read_table(out / camp.RESULTS_FILE).to_pylist()}
    bad = rows["rubber-2"]
    assert (bad["status"], bad["success"], bad["failure"]) == ("crashed", False, "crashed")
    assert "RuntimeError: the world fell over" in bad["traceback"]
    assert "Traceback" in bad["traceback"]
    assert rows["rubber-1"]["status"] == "completed" and rows["rubber-1"]["traceback"] == ""


def test_a_bad_suite_is_refused_before_anything_runs(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    data = json.loads(tiny_suite(("rubber", 1), ("egg", 1)).to_json())
    data["cases"][1]["height_mm"] = 30.0
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(data))
    out = tmp_path / "out"
    assert main(["campaign", "run", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith("sdh2svc campaign: invalid suite")
    assert "cases.1.height_mm = 30.0" in err and "allowed" in err and "60" in err
    assert not out.exists()
    # a --set value out of its range, too
    tiny_suite(("rubber", 1)).dump(path)
    assert main(["campaign", "run", str(path), "--out", str(out), "--set", "rolling.k=0"]) == 2
    assert "rolling.k" in capsys.readouterr().err
    assert not out.exists()
    assert main(["campaign", "run", "no-such-suite", "--out", str(out)]) == 3
    assert "no suite 'no-such-suite'" in capsys.readouterr().err


def test_without_ray_the_cluster_option_says_what_to_install(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray → ImportError
    path = tmp_path / "s.json"
    tiny_suite(("rubber", 1)).dump(path)
    assert main(["campaign", "run", str(path), "--out", str(tmp_path / "o"), "--ray",
                 "auto", "--quiet"]) == 2  # fmt: skip
    err = capsys.readouterr().err.strip()
    assert err == "sdh2svc campaign: --ray needs Ray: pip install 'sdh2svc[cluster]'"


def test_on_a_local_ray_the_results_are_those_of_the_process_pool(
    one_worker: Path, tmp_path: Path
) -> None:
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'sdh2svc[cluster]'"
                              "): the --ray path is not tested here")  # fmt: skip
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    try:
        out = tmp_path / "ray"
        res = camp.run_campaign(tiny_suite(*THREE), out, ray_address="auto",
                                overrides=ONE_STROKE, progress=False)  # fmt: skip
    finally:
        ray.shutdown()
    assert res.ran == 3
    one = {r["id"]: r for r in pq.read_table(one_worker / camp.RESULTS_FILE).to_pylist()}
    got = {r["id"]: r for r in pq.read_table(out / camp.RESULTS_FILE).to_pylist()}
    for i in one:
        assert {k: one[i][k] for k in JUDGED} == {k: got[i][k] for k in JUDGED}, i


def test_watching_the_truth_leaves_the_run_as_it_is_unwatched(one_worker: Path,
                                                              tmp_path: Path) -> None:  # fmt: skip
    """The probe reads ψ without stepping the physics: a case's run is the plain run's."""
    from sdh2svc.sim.clock import run_fast

    row = next(r for r in lines(one_worker) if r["id"] == "egg-1")
    case = Case.model_validate_json(row["spec"])
    cfg = camp.case_settings(case, ONE_STROKE, None, tmp_path / "runs.sqlite")
    plain = run_fast(headless.run_once(cfg, Simulated(obj=case.object, fast=True)))
    assert (plain["iterations"], plain["force"]["max"], plain["lambda_initial_mm"],
            plain["truth"]["slips"]) == (row["iterations"], row["f_max"],
                                          row["lambda_at_grasp_mm"], row["slips"])  # fmt: skip
    assert plain["truth"]["rotation_range_deg"] == row["rotation_range_deg"]


def test_no_ray_cluster_at_the_address_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install 'sdh2svc[cluster]'"
                              "): the --ray path is not tested here")  # fmt: skip
    assert not ray.is_initialized()
    # "auto" finds no cluster, whatever else runs on this machine (Ray looks for any running
    # GCS process, e.g. one still shutting down after the local-Ray test)
    from ray._private import services

    def no_gcs() -> list[str]:
        return []

    no_gcs.cache_clear = lambda: None  # type: ignore[attr-defined]  # (Ray clears its cache)
    monkeypatch.setattr(services, "find_gcs_addresses", no_gcs)
    monkeypatch.setattr(services, "find_bootstrap_address", lambda temp_dir: None)
    path = tmp_path / "s.json"
    tiny_suite(("rubber", 1)).dump(path)
    args = ["campaign", "run", str(path), "--out", str(tmp_path / "o"), "--quiet"]
    env_before = os.environ.pop("RAY_ADDRESS", None)
    try:
        assert main([*args, "--ray", "auto"]) == 4
    finally:
        if env_before is not None:
            os.environ["RAY_ADDRESS"] = env_before
    err = capsys.readouterr().err
    assert err.startswith("sdh2svc campaign: cannot reach the Ray cluster at auto: ")
    # sdh2svc's options, not Ray's; and no folder of no case left to refuse another suite
    # (CLI audit)
    assert "--ray local" in err and "--address" not in err, err
    assert not (tmp_path / "o").exists()
    assert err.count("\n") == 1
    assert camp.read_rows(tmp_path / "o") == []


def fake_case(case_json: str, *args: Any) -> dict[str, Any]:
    """A stand-in for run_case in pool workers: dies or raises for some cases."""
    case = Case.model_validate_json(case_json)
    if case.seed == 3:
        os._exit(9)  # the worker dies as if killed
    if case.seed == 4:
        raise ValueError("not caught in the worker")
    return camp.finish_row({**camp.case_columns(case), "status": "stopped"})


def test_a_dead_worker_or_an_exception_in_it_is_a_crashed_case_and_the_rest_run(
    tmp_path: Path,
) -> None:
    suite = tiny_suite(*(("rubber", seed) for seed in range(1, 7)))
    out = tmp_path / "out"
    res = camp.run_campaign(suite, out, workers=2, overrides=ONE_STROKE, progress=False,
                            case_fn=fake_case)  # fmt: skip
    rows = {r["id"]: r for r in lines(out)}
    assert len(lines(out)) == 6 and res.ran == 6 and res.crashed == 2
    assert rows["rubber-3"]["status"] == "crashed"
    assert "worker process running case rubber-3 died" in rows["rubber-3"]["traceback"]
    assert rows["rubber-4"]["status"] == "crashed"
    assert "ValueError: not caught in the worker" in rows["rubber-4"]["traceback"]
    assert all(rows[f"rubber-{i}"]["status"] == "stopped" for i in (1, 2, 5, 6))


def test_generate_writes_a_new_suite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """`campaign generate NAME --seed S --cases N`: the seed's cases under the suite's name, a
    file `campaign run` loads as it loads any suite; never rewritten; bad input refused (2)."""
    out = tmp_path / "held.json"
    args = ["campaign", "generate", "held", "--seed", "77", "--cases", "7", "-o", str(out)]
    assert main(args) == 0
    suite = load_suite(out)
    assert suite.name == "held" and suite.generator_seed == 77
    assert suite.cases == tuple(generate_cases(77, 7, prefix="held-"))
    assert {c.family for c in suite.cases} == set(GENERATED)  # every family, taking turns
    text = out.read_text()
    assert main(args) == 2 and out.read_text() == text  # never rewritten
    assert "exists" in capsys.readouterr().err
    again = tmp_path / "again.json"
    assert main([*args[:-1], str(again)]) == 0 and again.read_text() == text  # bit for bit
    for bad in (["generate", "a b", "--seed", "1", "--cases", "3"],
                ["generate", "x", "--cases", "3"],
                ["generate", "x", "--seed", "1", "--cases", "0"],
                ["generate", "x", "--seed", "1", "--cases", "10001"],
                ["generate", "x", "--seed", "-1", "--cases", "3"],
                ["run", "smoke", "--seed", "1"]):  # fmt: skip
        assert main(["campaign", *bad, "-o", str(tmp_path / "bad.json")]) == 2, bad
    assert not (tmp_path / "bad.json").exists()


def test_a_worker_runs_the_configuration_the_campaign_recorded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Workers start from the campaign's effective configuration (what `campaign.json`
    records), not from their own node's environment and files: the same settings as the
    driver's, whatever a Ray node's `SDH2SVC_*` variables or missing `--config` file say."""
    conf = tmp_path / "lab.toml"
    conf.write_text("[rolling]\nk = 3.0\n")
    suite = load_suite("smoke")
    info = camp.campaign_info(suite, ONE_STROKE, str(conf))
    for case in suite.cases[:6]:
        made = camp.case_settings(case, ONE_STROKE, str(conf), tmp_path / "r.sqlite")
        shipped = camp.case_settings(case, [], None, tmp_path / "r.sqlite", info["config"])
        assert shipped.model_dump() == made.model_dump(), case.id
    conf.unlink()  # a node without the file, with variables of its own
    monkeypatch.setenv("SDH2SVC_ROLLING__K", "1.5")
    monkeypatch.setenv("SDH2SVC_ROLLING__CYCLES", "4")
    cfg = camp.case_settings(suite.cases[0], [], None, None, info["config"])
    assert (cfg.rolling.k, cfg.rolling.cycles) == (3.0, 1)
