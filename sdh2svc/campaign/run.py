"""Run a campaign: every case of a suite, one fast simulated run each, judged from the truth.

Each case is one independent run through the full byte path — :func:`run_once` in fast mode on
a virtual clock, the emulators, drivers, controller and recorder a real hand uses — with the
case's object and configuration keys (:meth:`Case.overrides`). What the controller believed is
compared with what the simulated world did (:func:`judge`).

Cases run in a local process pool (``workers``), in this process (``workers=1``) or on a Ray
cluster (``ray_address``), always through the same function, :func:`run_case`. Every finished
case is appended at once to ``OUT/cases.jsonl`` (flushed and fsync'd): running the same
campaign on the same ``OUT`` again skips every case already there. ``OUT/results.parquet`` is
written from that file at the end (:mod:`sdh2svc.campaign.results`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import multiprocessing
import os
import shutil
import socket
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from sdh2svc.campaign.case import CASE_KEYS, Case, Suite, wrap_deg
from sdh2svc.config import ConfigError, Settings, clip, load_config
from sdh2svc.control.observer import BaseObserver, Event, EventKind
from sdh2svc.provenance import code_version
from sdh2svc.workers import stop_pool, worker_init

CASES_FILE = "cases.jsonl"
CAMPAIGN_FILE = "campaign.json"
RESULTS_FILE = "results.parquet"

# What success means (judge()): thesis §4's targets, as the reproduction report checks them.
MIN_HALF_STROKE_DEG = 1.0  # true rotation of the object in every half stroke
F_BAND = (0.25, 2.5)  # × Fd: every rolling iteration's true grip after the grasp
CLUSTER_HINT = "pip install 'sdh2svc[cluster]'"


class CampaignError(Exception):
    """A campaign that cannot run or go on; ``status`` is the CLI's exit status for it."""

    def __init__(self, status: int, message: str) -> None:
        super().__init__(message)
        self.status = status


# --- suites ---------------------------------------------------------------------------------


def suite_digest(suite: Suite) -> str:
    return hashlib.sha256(suite.to_json().encode()).hexdigest()[:16]


# --- one case -------------------------------------------------------------------------------


def _workdir(root: str) -> Path:
    """This process's scratch directory for run databases under ``root``."""
    path = Path(root) / f"worker-{os.getpid()}"
    path.mkdir(parents=True, exist_ok=True)
    return path


def case_settings(case: Case, overrides: Sequence[str], config_path: str | None,
                  db_path: Path | None = None, base: Mapping[str, Any] | None = None,
                  ) -> Any:  # fmt: skip
    """The configuration of one case: the campaign's ``--set`` values, then the case's keys.
    ``base``: the campaign's effective configuration (its file, environment and ``--set``
    values in it already; ``overrides`` and ``config_path`` are then not read again), so a
    worker on another machine runs what the campaign recorded, not what its own node says."""
    at = [] if db_path is None else [f"storage.db_path={json.dumps(str(db_path))}"]
    if base is not None:
        keys = case.overrides(base["sim"]["sensor"]["gain_vs_library"])
        return load_config(overrides=[*keys, *at], use_env=False, base=base)
    gain = load_config(config_path, overrides).sim.sensor.gain_vs_library
    return load_config(config_path, [*overrides, *case.overrides(gain), *at])


class TruthProbe(BaseObserver):
    """Watches a run beside it (:class:`~sdh2svc.control.observer.RunObserver`): the simulated
    object's true angle ψ and the true grip force at the grasp and at every iteration, and
    where the half strokes end."""

    def __init__(self) -> None:
        self.bench: Any = None  # the simulated hand's bench (sdh2svc.connect.Bench)
        self.psi_grasp: float | None = None
        self.psi: list[tuple[int, float]] = []  # (iteration, ψ rad) of every rolling iteration
        # the iterations that reversed, and whether each ended a half stroke (the runner's count
        # rose: Finger 2 travelled min_half_stroke_deg since the reversal before and the
        # object turned by the controller's own estimate, control/rolling.py)
        self.reversals: list[tuple[int | None, bool]] = []
        self._half_strokes = 0
        # the true grip (N): the mean of the two distal pads' true normal forces, as the
        # controller's F is the mean of F1 and F2 — at the grasp and at every rolling iteration
        self.grasp_grip_n: float | None = None
        self.grip_n: list[float] = []
        # the largest true grip from the first touch to the run's end (N): the grasp's closing
        # too, which can press beyond its grip at the grasped event (and between iterations)
        self.grip_peak_n: float | None = None
        self.grasp_F: float | None = None
        # the distance between the true contact points on the object at the first iteration:
        # the object's width where the pads really touch it
        self.contact_width_mm: float | None = None
        self.fault: str = ""
        self.end_t: float | None = None

    def __call__(self, bench: Any) -> TruthProbe:
        self.bench = bench
        return self

    def _psi(self) -> float:
        """ψ as the physics last stepped: reading it steps nothing (``bench.object_pose``), so
        a campaign's runs stay bit for bit those of ``sdh2svc run --fast``."""
        return float(self.bench.object_pose()[2])

    def event(self, e: Event) -> None:
        kind, detail = e.kind, e.detail
        if kind is EventKind.GRASPED and self.bench is not None:
            self.psi_grasp, self.grasp_grip_n = self._psi(), self._grip_n()
            self.grasp_F = float(detail.get("F", 0.0))  # the controller's, for the library's force
        elif kind is EventKind.REVERSAL:
            n = int(detail.get("half_strokes", self._half_strokes))
            self.reversals.append((e.iteration, n > self._half_strokes))
            self._half_strokes = n
        elif kind is EventKind.FAULT:
            self.fault = str(detail.get("fault", ""))
        elif kind is EventKind.END:
            self.end_t = e.t
            if self.bench is not None:
                self.grip_peak_n = self.bench.object_now().grip_peak_n

    def _grip_n(self) -> float:
        """The true grip as the physics last stepped (N; steps nothing, as :meth:`_psi`)."""
        forces = {c.surface: c.normal_force_n for c in self.bench.contacts_now()}
        return float(forces.get("distal1", 0.0) + forces.get("distal2", 0.0)) / 2.0

    def sample(self, sample: Any) -> None:
        if self.bench is not None:
            self.psi.append((sample.iteration, self._psi()))
            self.grip_n.append(self._grip_n())
            if self.contact_width_mm is None:
                self.contact_width_mm = _contact_width(self.bench.contacts_now())

    def half_strokes_deg(self) -> list[float]:
        """How far the object truly turned in every half stroke (degrees): the largest
        excursion of ψ from its angle where the half stroke began (the grasp, or the reversal
        before), up to the reversal that ends it. The largest, not the net: an object may turn
        and come part of the way back within one half stroke (the egg does, ≈ 15° and back) —
        it did turn. Only the reversals the runner counted end a half stroke (Finger 2
        travelled far enough since the one before, and the object turned by the controller's
        own estimate); the unfinished last half stroke (the run ended) is not counted."""
        if self.psi_grasp is None:
            return []
        out: list[float] = []
        start, k = self.psi_grasp, 0
        peak = 0.0
        for end, counted in self.reversals:
            while k < len(self.psi) and (end is None or self.psi[k][0] <= end):
                peak = max(peak, abs(wrap_deg(math.degrees(self.psi[k][1] - start))))
                k += 1
            if counted:
                out.append(peak)
                start, peak = (self.psi[k - 1][1] if k else start), 0.0
        return out


def _contact_width(contacts: Sequence[Any]) -> float | None:
    """The distance between the two distal pads' true contact points, in the object's frame."""
    pts = {c.surface: c.object_point for c in contacts}
    a, b = pts.get("distal1"), pts.get("distal2")
    return None if a is None or b is None else math.dist(a, b)


def case_columns(case: Case) -> dict[str, Any]:
    """The case's own parameters, as columns to group results by."""
    obj = case.object
    return {
        "id": case.id, "family": case.family, "object_kind": obj.kind,
        "object_name": obj.name, "size_mm": float(obj.size_mm), "depth_mm": float(obj.depth_mm),
        "friction": float(obj.material.friction), "mass_g": float(obj.material.mass_g),
        "true_width_mm": case.true_width_mm, "height_mm": case.height_mm,
        "angle_deg": case.angle_deg, "seed": case.seed,
        "gain_factor": case.sensor.gain_factor,
        "dead_texels": len(case.sensor.dead_texels),
        "spec": case.model_dump_json(),
    }  # fmt: skip


def run_case(case_json: str, overrides: Sequence[str] = (), config_path: str | None = None,
             workdir: str | None = None, base: Mapping[str, Any] | None = None,
             ) -> dict[str, Any]:  # fmt: skip
    """Run one case and return its judged row; never raises for the case's own failure: an
    exception becomes a row with status ``crashed`` and its traceback. The run database goes
    to a per-process directory under ``workdir`` (else a temporary one) and is deleted after.
    ``base``: the campaign's effective configuration (:func:`case_settings`)."""
    from sdh2svc.connect import Simulated
    from sdh2svc.service.headless import run_once
    from sdh2svc.sim.clock import run_fast

    t0 = time.perf_counter()
    case = Case.model_validate_json(case_json)
    row = case_columns(case)
    with contextlib.ExitStack() as stack:
        if workdir is None:  # e.g. on a Ray node: a directory of the case's own
            workdir = stack.enter_context(tempfile.TemporaryDirectory(prefix="sdh2svc-case-"))
        db = _workdir(workdir) / f"case-{case.id}.sqlite"
        try:
            cfg = case_settings(case, overrides, config_path, db, base)
            probe = TruthProbe()
            where = Simulated(obj=case.object, fast=True)
            summary = run_fast(run_once(cfg, where, observer=probe))
            row.update(measure(summary, probe, cfg, case))
        except Exception:
            row.update(status="crashed", traceback=traceback.format_exc())
        finally:
            for suffix in ("", "-wal", "-shm", "-journal"):
                with contextlib.suppress(OSError):
                    os.unlink(f"{db}{suffix}")
    row["wall_s"] = time.perf_counter() - t0
    return finish_row(row)


def measure(summary: Mapping[str, Any], probe: TruthProbe, cfg: Any, case: Case) -> dict[str, Any]:
    """What a run did, from its summary and the truth sampled along the way."""
    truth = summary.get("truth") or {}
    force = summary.get("force") or {}
    halves = probe.half_strokes_deg()
    lam = summary.get("lambda_initial_mm")
    cycles = cfg.rolling.cycles
    strokes_deg = [halves[i] + halves[i + 1] for i in range(0, len(halves) - 1, 2)]
    true_f = true_forces(probe, cfg, force.get("max"))
    return {
        "status": summary["status"], "message": summary.get("message", ""),
        "fault": probe.fault, "strokes": summary.get("strokes", 0), "cycles": cycles,
        "iterations": summary.get("iterations", 0),
        "half_strokes": len(halves),
        "half_strokes_turned": sum(h >= MIN_HALF_STROKE_DEG for h in halves),
        "half_stroke_rotation_deg": halves,
        "min_half_stroke_deg": min(halves) if halves else None,
        "mean_stroke_rotation_deg": sum(strokes_deg) / len(strokes_deg) if strokes_deg else None,
        "dropped": bool(truth.get("dropped", False)), "slips": int(truth.get("slips", 0)),
        "rotation_range_deg": truth.get("rotation_range_deg"),
        "lambda_at_grasp_mm": lam,
        "true_contact_width_mm": probe.contact_width_mm,
        "lambda_error_mm": (lam - probe.contact_width_mm
                            if lam is not None and probe.contact_width_mm is not None else None),
        "lambda_error_placement_mm": lam - case.true_width_mm if lam is not None else None,
        "fd": cfg.rolling.grasp_force, "f_min": force.get("min"), "f_max": force.get("max"),
        "f_mean": force.get("mean"), **true_f,
        "sensor_gain": cfg.sim.sensor.gain_vs_library,
        "sim_s": probe.end_t,
    }  # fmt: skip


def true_grip_scale(cfg: Settings) -> float | None:
    """Fd's units per newton of true grip (:meth:`TactileCalibration.force_per_newton`); None
    with the library's force, when the band is judged on the controller's own F."""
    return cfg.calibration.force_per_newton(cfg.tactile.texel_pitch_mm)


def true_forces(probe: TruthProbe, cfg: Any, read_max: float | None) -> dict[str, float | None]:
    """The true grip in Fd's units (:meth:`TactileCalibration.force_per_newton`: what pads
    reading exactly as the calibration says would give): its least, largest and mean over the
    rolling iterations, and its peak over the whole grip (every physics step from the first
    touch to the run's end: the grasp's closing too). With the library's force
    (``calibration.force_reference_area_mm2 = 0``), which no force alone determines, the three
    are None and the band and the peak the controller's own F's (``read_max``: the most it
    read while rolling)."""
    k = true_grip_scale(cfg)
    if k is None:
        read = [f for f in (read_max, probe.grasp_F) if f is not None]
        return {"true_f_min": None, "true_f_max": None, "true_f_mean": None,
                "peak_force": max(read) if read else None}  # fmt: skip
    f = [k * n for n in probe.grip_n]
    held = [k * n for n in (probe.grasp_grip_n, probe.grip_peak_n) if n is not None]
    return {
        "true_f_min": min(f) if f else None, "true_f_max": max(f) if f else None,
        "true_f_mean": sum(f) / len(f) if f else None,
        "peak_force": max(f + held) if f or held else None,
    }  # fmt: skip


COLUMNS_DEFAULTS: dict[str, Any] = {
    "status": "crashed", "message": "", "fault": "", "strokes": 0, "cycles": None,
    "iterations": 0, "half_strokes": 0, "half_strokes_turned": 0,
    "half_stroke_rotation_deg": [], "min_half_stroke_deg": None,
    "mean_stroke_rotation_deg": None, "dropped": False, "slips": 0,
    "rotation_range_deg": None, "lambda_at_grasp_mm": None, "lambda_error_mm": None,
    "true_contact_width_mm": None, "lambda_error_placement_mm": None,
    "fd": None, "f_min": None, "f_max": None, "f_mean": None, "true_f_min": None,
    "true_f_max": None, "true_f_mean": None, "peak_force": None,
    "sensor_gain": None, "sim_s": None, "wall_s": None, "traceback": "",
}  # fmt: skip


def finish_row(row: dict[str, Any]) -> dict[str, Any]:
    """Every column present, then the verdict."""
    for key, value in COLUMNS_DEFAULTS.items():
        row.setdefault(key, list(value) if isinstance(value, list) else value)
    row["f_in_band"] = f_in_band(row)
    row["success"], row["failure"] = judge(row)
    return row


def judged_forces(row: Mapping[str, Any]) -> tuple[float | None, float | None]:
    """The least and largest grip the band judges: the true one (``true_f_*``), else — with the
    library's force, or in a campaign recorded before the truth was — the controller's F."""
    if row.get("true_f_min") is not None and row.get("true_f_max") is not None:
        return row["true_f_min"], row["true_f_max"]
    return row.get("f_min"), row.get("f_max")


def f_in_band(row: Mapping[str, Any]) -> bool | None:
    """Every rolling iteration's true grip within [0.25, 2.5] × Fd (None: no rolling
    iteration)."""
    (lo, hi), fd = judged_forces(row), row.get("fd")
    if lo is None or hi is None or fd is None:
        return None
    return bool(F_BAND[0] * fd <= lo and hi <= F_BAND[1] * fd)


def judge(row: Mapping[str, Any]) -> tuple[bool, str]:
    """Success, or the first reason it failed — the one definition of a successful case.

    A case succeeds when, by the simulation's ground truth:

    1. the run did not crash and completed (``status == "completed"``) all its strokes
       (``strokes >= cycles``, 3 by default);
    2. the object was never dropped;
    3. every half stroke (grasp or reversal to the next reversal that ended a move) turned the
       object by at least ``MIN_HALF_STROKE_DEG`` (1°) of true rotation — the largest
       excursion of its true angle ψ from where the half stroke began
       (:meth:`TruthProbe.half_strokes_deg`) — and there were ``2 × cycles`` of them;
    4. at every rolling iteration after the grasp the true grip — the mean of the two distal
       pads' true normal forces, in Fd's units through the calibration
       (:func:`true_forces`) — lay within ``F_BAND`` (0.25…2.5) × Fd. The controller's own F
       reads the pads, whose gain a campaign varies ×0.5–1.5: holding its F at Fd is no proof
       of a sane grip.

    The failure reason is the first of: ``crashed``, ``dropped`` (by the truth: the object
    left the hand and its fixture), ``faulted: FAULT`` (``faulted: dropped``: the controller
    lost both contacts, the object maybe still in its fixture), the status (``stopped`` …),
    ``too few strokes``, ``half stroke < 1°``, ``no force recorded``, ``F below band``,
    ``F above band``.
    """
    status = row.get("status")
    if status == "crashed":
        return False, "crashed"
    if row.get("dropped"):
        return False, "dropped"
    if status in ("faulted", "dropped"):
        return False, f"faulted: {row.get('fault') or status}"
    if status != "completed":
        return False, str(status)
    cycles = row.get("cycles") or 0
    if (row.get("strokes") or 0) < cycles:
        return False, "too few strokes"
    halves = row.get("half_stroke_rotation_deg") or []
    if len(halves) < 2 * cycles or any(h < MIN_HALF_STROKE_DEG for h in halves):
        return False, f"half stroke < {MIN_HALF_STROKE_DEG:g}°"
    fd, (lo, hi) = row.get("fd"), judged_forces(row)
    if fd is None or lo is None or hi is None:
        return False, "no force recorded"
    if lo < F_BAND[0] * fd:
        return False, "F below band"
    if hi > F_BAND[1] * fd:
        return False, "F above band"
    return True, ""


def crashed_row(case: Case, tb: str) -> dict[str, Any]:
    """The row of a case whose worker failed outside :func:`run_case` (e.g. it died)."""
    row = case_columns(case)
    row.update(status="crashed", traceback=tb)
    return finish_row(row)


# --- the campaign ---------------------------------------------------------------------------


@dataclass
class Outcome:
    total: int
    skipped: int  # already in cases.jsonl
    ran: int
    succeeded: int  # of every case recorded
    crashed: int
    wall_s: float
    results: Path | None


def read_rows(out: Path) -> list[dict[str, Any]]:
    """Every row of ``OUT/cases.jsonl``; a torn last line (a crash mid-write), or any line
    that is not a case's result (:func:`_is_result`), is dropped."""
    path = out / CASES_FILE
    if not path.exists():
        return []
    rows = []
    with path.open("rb") as fh:
        for line in fh:
            try:
                row = json.loads(line)
            except ValueError:
                continue
            if _is_result(row):
                rows.append(row)
    return rows


def _is_result(row: Any) -> bool:
    """A case's row as :func:`finish_row` writes it (an id, a verdict and a status): anything
    else in the file (a line from another program, a hand edit) is no result."""
    return (isinstance(row, dict) and isinstance(row.get("id"), str)
            and isinstance(row.get("success"), bool)
            and isinstance(row.get("status"), str))  # fmt: skip


def _repair_tail(path: Path) -> None:
    """Cut a torn last line, so that the next append starts on a line of its own."""
    if not path.exists():
        return
    data = path.read_bytes()
    if data and not data.endswith(b"\n"):
        cut = data.rfind(b"\n") + 1
        with path.open("r+b") as fh:
            fh.truncate(cut)


class Appender:
    """Appends one row per line to ``cases.jsonl``, on disk before it returns."""

    def __init__(self, path: Path) -> None:
        _repair_tail(path)
        self.fh = path.open("a", encoding="utf-8")

    def __call__(self, row: Mapping[str, Any]) -> None:
        self.fh.write(json.dumps(row, ensure_ascii=False, allow_nan=True) + "\n")
        self.fh.flush()
        os.fsync(self.fh.fileno())

    def close(self) -> None:
        self.fh.close()


def campaign_info(suite: Suite, overrides: Sequence[str], config_path: str | None,
                  ) -> dict[str, Any]:  # fmt: skip
    cfg = load_config(config_path, overrides)
    return {
        "suite": suite.name, "suite_version": suite.version, "suite_digest": suite_digest(suite),
        "generator_seed": suite.generator_seed, "cases": len(suite.cases),
        "overrides": list(overrides), "config_file": config_path,
        "code": code_version(), "config": cfg.model_dump(mode="json"),
        "judge": {"min_half_stroke_deg": MIN_HALF_STROKE_DEG, "f_band_x_fd": list(F_BAND),
                  "f_band_on": ("true grip" if true_grip_scale(cfg) is not None
                                else "the controller's F")},
    }  # fmt: skip


def _check_same(out: Path, info: Mapping[str, Any]) -> None:
    """``out`` is new, empty, or holds this same campaign (to resume): the same suite, the same
    ``--set`` values, the same effective configuration (whatever the file, the environment or
    ``--set`` it came from) and the same code. Anything else is refused before a byte is
    written: a folder of other files is never written into, and results of two
    configurations or two code versions are never mixed in one campaign."""
    if not out.exists():
        return
    if not out.is_dir():
        raise CampaignError(2, f"--out {out}: not a directory")
    path = out / CAMPAIGN_FILE
    if not path.exists():
        if any(p.name != LOCK_FILE and not p.name.startswith(".work-") for p in out.iterdir()):
            raise CampaignError(2, f"{out} is not empty and holds no campaign ({CAMPAIGN_FILE}): "
                                "give a new or empty --out")  # fmt: skip
        return
    try:
        old = json.loads(path.read_text())
        if not isinstance(old, dict):
            raise ValueError("not a JSON object")
    except (OSError, ValueError) as e:
        raise CampaignError(2, f"{path} cannot be read ({e}): is {out} a campaign? "
                            "give another --out") from None  # fmt: skip
    # (not the --set text: the same values in another order or spelling are the same campaign,
    # and the effective configuration they make is compared)
    old_code, code = old.get("code"), info["code"]
    old_code = old_code if isinstance(old_code, dict) else {}
    if not _same_code(old_code, code):  # (first: another version's keys differ anyway)
        raise CampaignError(2, f"{out} holds a campaign another sdh2svc made ({_code(old_code)} "
                            f"there, {_code(code)} now): results of two versions are never "
                            "mixed; finish it with that version, or use another --out")  # fmt: skip
    for key in ("suite_digest", "config", "judge"):
        if old.get(key) != info[key]:
            shown = (f"{clip(repr(old.get(key)))} there, {clip(repr(info[key]))} now"
                     if key != "config" else _config_change(old.get(key), info[key]))  # fmt: skip
            raise CampaignError(2, f"{out} holds another campaign ({key} differs: {shown}); "
                                "resume it as it was run, or use another --out")  # fmt: skip


def _same_code(a: Mapping[str, Any], b: Mapping[str, Any]) -> bool:
    """The same code: the same version and source digest (a checkout gone ``-dirty`` meanwhile,
    e.g. by the campaign's own folder in it, is the same code); without a digest, all of it."""
    if a.get("source") and b.get("source"):
        return (a.get("version"), a.get("source")) == (b.get("version"), b.get("source"))
    return dict(a) == dict(b)


def _code(code: Mapping[str, Any]) -> str:
    """``sdh2svc 0.1.0 (1b32b3b, source 3f9b875b8b66)``: a version as :func:`code_version`
    records it (the source's digest tells two edits of one commit apart)."""
    source = str(code.get("source") or "")[:12] or "unknown"
    return (f"sdh2svc {code.get('version')} ({code.get('git_describe') or 'no git'}, source "
            f"{source})")  # fmt: skip


def _config_change(old: Any, new: Mapping[str, Any]) -> str:
    """The first configuration keys whose values differ, ``rolling.k: 2.0 there, 3.0 now``."""

    def flat(d: Any, prefix: str = "") -> dict[str, Any]:
        if not isinstance(d, Mapping):
            return {prefix.rstrip("."): d}
        out: dict[str, Any] = {}
        for k, v in d.items():
            out.update(flat(v, f"{prefix}{k}."))
        return out

    a, b = flat(old or {}), flat(new)
    keys = [k for k in sorted(a.keys() | b.keys()) if a.get(k) != b.get(k)]
    shown = "; ".join(f"{k}: {clip(repr(a.get(k)))} there, {clip(repr(b.get(k)))} now"
                      for k in keys[:3])  # fmt: skip
    return shown + (f"; and {len(keys) - 3} more" if len(keys) > 3 else "")


# Keys a campaign sets for every case itself: a --set of one would be recorded, and ignored.
RUN_KEYS = {
    "sim.object": "each case runs its own object (the suite's)",
    "storage.db_path": "each case records its run in a database of its own",
}


def check_overrides(overrides: Sequence[str], config_path: str | None = None) -> None:
    """No key each case sets itself (Case.overrides: where the object is placed, the seed, the
    sensor's variation) changed by ``--set``, ``--config`` or the environment: the case's value
    would win without a word, while the campaign recorded the change as in effect.
    ``sim.sensor.gain_vs_library`` is the nominal gain every case's ``gain_factor`` scales:
    that one may be set. Nor the keys the campaign decides itself (:data:`RUN_KEYS`)."""
    for text in overrides:
        key = text.partition("=")[0].strip()
        if key in RUN_KEYS:
            raise CampaignError(2, f"--set {clip(text)}: {RUN_KEYS[key]}, whatever it is "
                                "set to")  # fmt: skip
        if key in CASE_KEYS:
            raise CampaignError(2, f"--set {clip(text)}: {key} is set by each case (its "
                                "placement, seed or sensor); change it in the suite's "
                                "cases")  # fmt: skip
    given = load_config(config_path, overrides).model_dump(mode="json")
    default = load_config(use_env=False).model_dump(mode="json")
    for key in sorted(CASE_KEYS):
        a, b = given, default
        for part in key.split("."):
            a, b = a[part], b[part]
        if a != b:
            raise CampaignError(2, f"{key} = {clip(repr(a))} (from --set, --config or the "
                                "environment): it is set by each case (its placement, seed "
                                "or sensor); change it in the suite's cases")  # fmt: skip
    if given["sim"]["object"] != default["sim"]["object"]:  # (storage.db_path: the Dockerfile's)
        raise CampaignError(2, f"sim.object = {clip(repr(given['sim']['object']))} (from "
                            f"--config or the environment): {RUN_KEYS['sim.object']}; leave it "
                            "out of the campaign's configuration")  # fmt: skip


RAY_CONNECT_S = 10.0


def _check_ray_address(address: str) -> None:
    """A ``HOST:PORT`` (no ``ray://``) must answer a TCP connect within RAY_CONNECT_S: Ray itself
    retries an address where nothing listens for many minutes, logging as it goes."""
    if address in ("auto", "local") or "://" in address:
        return
    host, _, port = address.rpartition(":")
    if not port.isdigit() or not 0 < int(port) < 65536:
        raise CampaignError(2, f"--ray {clip(address)}: give auto, local, HOST:PORT or "
                            "ray://HOST:PORT")  # fmt: skip
    try:
        with socket.create_connection((host or "127.0.0.1", int(port)), timeout=RAY_CONNECT_S):
            pass
    except (OSError, ValueError) as e:
        why = e.strerror if isinstance(e, OSError) and e.strerror else str(e) or type(e).__name__
        raise CampaignError(4, f"cannot reach the Ray cluster at {address}: {why}") from None


def validate_cases(suite: Suite, overrides: Sequence[str], config_path: str | None) -> None:
    """Every case's configuration, validated before anything runs (ConfigError naming it)."""
    gain = load_config(config_path, overrides).sim.sensor.gain_vs_library
    for case in suite.cases:
        try:
            load_config(config_path, [*overrides, *case.overrides(gain)])
        except ConfigError as e:
            problems = list(e.problems)
            if any("gain_vs_library" in p for p in problems):
                problems.append(
                    f"(the case's sensor gain: the nominal sim.sensor.gain_vs_library "
                    f"{gain!r} × its gain_factor {case.sensor.gain_factor!r})"
                )
            raise ConfigError(problems, f"case {case.id}") from None


def run_campaign(
    suite: Suite,
    out: str | Path,
    *,
    workers: int | None = None,
    ray_address: str | None = None,
    overrides: Sequence[str] = (),
    config_path: str | None = None,
    progress: bool = True,
    case_fn: Callable[..., dict[str, Any]] | None = None,
) -> Outcome:
    """Run every case of ``suite`` not yet in ``OUT/cases.jsonl``; write ``results.parquet``.

    ``workers=1`` runs the cases in this process, more in a process pool (forkserver);
    ``ray_address`` on a Ray cluster: ``auto`` (the one this machine belongs to), ``ray://…``,
    or ``local`` (start one here); ignored once Ray is initialised in this process.
    ``case_fn`` replaces :func:`run_case` (tests; in a pool it must be picklable by name).
    """
    t0 = time.perf_counter()
    out = Path(out)
    overrides = list(overrides)
    info = campaign_info(suite, overrides, config_path)  # --set values are checked here
    check_overrides(overrides, config_path)
    validate_cases(suite, overrides, config_path)
    if ray_address is not None:
        _check_ray_address(ray_address)
        if not out.exists():  # a new campaign: joined before its folder is made (a cluster
            _ray_connect(ray_address)  # that is not there left a folder of no case behind)
    _check_same(out, info)
    with contextlib.ExitStack() as lock:
        try:
            out.mkdir(parents=True, exist_ok=True)
            lock.enter_context(_lock(out))
        except OSError as e:
            raise CampaignError(4, f"cannot write to {out}: {e.strerror or e}") from None
        _check_same(out, info)  # again, now that no other run can be writing it
        try:
            for stale in out.glob(".work-*"):  # a killed run's, never removed
                shutil.rmtree(stale, ignore_errors=True)
            text = json.dumps(info, indent=1, ensure_ascii=False) + "\n"
            (out / CAMPAIGN_FILE).write_text(text)
            appender = Appender(out / CASES_FILE)
            work = tempfile.mkdtemp(prefix=".work-", dir=out)  # its own: removed at the end
        except OSError as e:
            raise CampaignError(4, f"cannot write to {out}: {e.strerror or e}") from None
        return _run_todo(suite, out, info, t0, appender, work, workers=workers,
                         ray_address=ray_address, overrides=overrides, config_path=config_path,
                         progress=progress, case_fn=case_fn)  # fmt: skip


LOCK_FILE = ".lock"


@contextlib.contextmanager
def _lock(out: Path) -> Iterator[None]:
    """An exclusive lock on ``OUT`` for as long as the campaign runs there (held by an open
    file, so a killed run holds none): a second run on the same folder would run every case
    again beside the first, and each would be recorded twice. The file is removed while still
    locked when the campaign ends; a run that finds it replaced or gone once it holds the lock
    (the one before removed it meanwhile) takes the lock again on the file that is there now."""
    path = out / LOCK_FILE
    try:
        import fcntl
    except ImportError:  # (Windows: no lock)
        yield
        return
    while True:
        fh = path.open("a+")
        try:
            fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            fh.close()
            raise CampaignError(2, f"another campaign is running in {out}: wait for it to "
                                "end, or use another --out") from None  # fmt: skip
        try:
            same = os.stat(path).st_ino == os.fstat(fh.fileno()).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        fh.close()
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            path.unlink()
        fh.close()


def _run_todo(suite: Suite, out: Path, info: Mapping[str, Any], t0: float, appender: Appender,
              work: str, *, workers: int | None, ray_address: str | None,
              overrides: list[str], config_path: str | None, progress: bool,
              case_fn: Callable[..., dict[str, Any]] | None) -> Outcome:  # fmt: skip
    """The cases of ``suite`` not yet in ``OUT/cases.jsonl``, run and recorded (see
    :func:`run_campaign`)."""
    from sdh2svc.campaign.results import write_results

    # the last row of each case decides; a crashed case runs again (a crash is no result)
    last = {r["id"]: r for r in read_rows(out)}
    ids = {c.id for c in suite.cases}
    done = {i for i, r in last.items() if i in ids and r.get("status") != "crashed"}
    todo = [c for c in suite.cases if c.id not in done]
    succeeded = sum(1 for i in done if last[i].get("success"))
    crashed = 0
    bar = _progress(len(suite.cases), len(done), succeeded, enabled=progress)

    def record(row: dict[str, Any]) -> None:
        nonlocal succeeded, crashed
        appender(row)
        succeeded += bool(row.get("success"))
        crashed += row.get("status") == "crashed"
        bar.update(bool(row.get("success")), judged=row.get("status") != "crashed")

    try:
        if ray_address is not None and todo:  # (nothing left to run starts no Ray)
            _run_ray(todo, overrides, config_path, info["config"], ray_address, record)
        elif (workers or os.cpu_count() or 1) <= 1 or len(todo) <= 1:
            fn = case_fn or run_case
            for case in todo:
                record(fn(case.model_dump_json(), overrides, config_path, work, info["config"]))
        else:
            args = (overrides, config_path, work, info["config"])
            _run_pool(todo, args, workers or os.cpu_count() or 1, record, case_fn or run_case)
    except KeyboardInterrupt:
        appender.close()
        with contextlib.suppress(Exception):  # what has finished, in Parquet too
            write_results(out, suite=suite, info=info)
        raise
    finally:
        appender.close()
        bar.close()
        shutil.rmtree(work, ignore_errors=True)
    results = write_results(out, suite=suite, info=info)
    return Outcome(total=len(suite.cases), skipped=len(done), ran=len(todo),
                   succeeded=succeeded, crashed=crashed, wall_s=time.perf_counter() - t0,
                   results=results)  # fmt: skip


class _Progress:
    """A progress line on stderr: cases done, ETA (tqdm) and the running success rate. To a
    file or a pipe (a log), a plain line at every 5 % of the cases instead of a redrawn one."""

    def __init__(self, total: int, done: int, succeeded: int, enabled: bool) -> None:
        # the rate is over the judged cases, as the report's (a crash is no result); the cases
        # already there are judged ones (a crashed one runs again)
        self.done, self.judged, self.succeeded, self.bar = done, done, succeeded, None
        self.total, self.log = total, enabled and not sys.stderr.isatty()
        self.t0, self.first = time.monotonic(), done
        if enabled and not self.log:
            from tqdm import tqdm

            self.bar = tqdm(total=total, initial=done, file=sys.stderr, unit="case",
                            dynamic_ncols=True, smoothing=0.1)  # fmt: skip
            self._postfix()

    def _rate(self) -> str:
        return f"{100 * self.succeeded / self.judged:.0f} %" if self.judged else "–"

    def _postfix(self) -> None:
        if self.bar is not None and self.done:
            self.bar.set_postfix_str(f"success {self._rate()}")

    def update(self, success: bool, *, judged: bool = True) -> None:
        self.done += 1
        self.judged += judged
        self.succeeded += success
        if self.bar is not None:
            self.bar.update(1)
            self._postfix()
        step = max(1, math.ceil(self.total / 20))
        if self.log and (self.done % step == 0 or self.done == self.total):
            ran = self.done - self.first
            left = (time.monotonic() - self.t0) / ran * (self.total - self.done)
            eta = f"{left:.0f} s" if left < 90 else f"{left / 60:.0f} min"
            print(f"{self.done}/{self.total} cases, success {self._rate()}, about {eta} left",
                  file=sys.stderr, flush=True)  # fmt: skip

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _progress(total: int, done: int, succeeded: int, *, enabled: bool) -> _Progress:
    return _Progress(total, done, succeeded, enabled)


def _run_pool(todo: Sequence[Case], args: tuple[Any, ...], workers: int,
              record: Callable[[dict[str, Any]], None],
              fn: Callable[..., dict[str, Any]] = run_case) -> None:  # fmt: skip
    """The cases on a pool of ``workers`` processes. A worker that dies (killed, out of memory,
    a crash in C) breaks the pool: the cases it was running are then run again one at a time,
    each in a pool of its own, and a case that kills its worker alone is recorded as crashed."""
    queue: Iterator[Case] = iter(todo)
    while True:
        lost = _pool_round(queue, args, min(workers, len(todo)), record, fn)
        if not lost:
            return
        for case in lost:  # each alone: only the guilty one breaks its pool
            if _pool_round(iter([case]), args, 1, record, fn):
                why = "(killed, out of memory, or a crash outside Python)"
                record(crashed_row(case, f"the worker process running case {case.id} died {why}"))


def _pool_round(queue: Iterator[Case], args: tuple[Any, ...], workers: int,
                record: Callable[[dict[str, Any]], None],
                fn: Callable[..., dict[str, Any]]) -> list[Case]:  # fmt: skip
    """Run cases from ``queue`` until it is empty or the pool breaks; the cases lost then."""
    ctx = multiprocessing.get_context("forkserver" if sys.platform != "win32" else "spawn")
    # a worker leaves Ctrl-C to the campaign, which keeps every finished case and stops them
    pool = ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=worker_init,
                               initargs=(os.getpid(),))  # fmt: skip
    pending: dict[Future[dict[str, Any]], Case] = {}
    lost: list[Case] = []

    def submit(case: Case) -> None:
        try:
            pending[pool.submit(fn, case.model_dump_json(), *args)] = case
        except BrokenProcessPool:  # a worker died since the last look: not this case's doing
            lost.append(case)

    try:
        # keep each worker busy with one case and one queued: Ctrl-C then cancels the rest
        for case in _take(queue, 2 * workers):
            submit(case)
        while pending:
            finished, _ = wait(pending, return_when=FIRST_COMPLETED)
            for fut in finished:
                case = pending.pop(fut)
                try:
                    row = fut.result()
                except BrokenProcessPool:
                    lost.append(case)
                    continue
                except Exception:
                    row = crashed_row(case, traceback.format_exc())
                record(row)
                if not lost:
                    for nxt in _take(queue, 1):
                        submit(nxt)
    except BaseException:
        stop_pool(pool)  # (their cases are not recorded)
        raise
    pool.shutdown(wait=True)
    return lost


def _take(it: Iterator[Case], n: int) -> list[Case]:
    out = []
    for _ in range(n):
        try:
            out.append(next(it))
        except StopIteration:
            break
    return out


RAY_HINT = (
    "`ray start --head` starts one on this machine, RAY_ADDRESS names another; or give "
    "--ray local for a Ray of the campaign's own, --ray ray://HOST:PORT, or --workers N"
)


def _ray_connect(address: str) -> Any:
    """Ray, joined to the cluster at ``address`` (once per process)."""
    try:
        import ray
    except ImportError:
        raise CampaignError(2, f"--ray needs Ray: {CLUSTER_HINT}") from None
    if not ray.is_initialized():
        try:  # "local": a Ray of its own on this machine
            ray.init(address=None if address == "local" else address, log_to_driver=False)
        except ConnectionError:  # (Ray's own advice names options sdh2svc does not have)
            raise CampaignError(4, f"cannot reach the Ray cluster at {address}: no cluster "
                                f"answered ({RAY_HINT})") from None  # fmt: skip
        except Exception as e:  # a bad address …
            raise CampaignError(4, f"cannot reach the Ray cluster at {address}: "
                                f"{type(e).__name__}: {e}") from None  # fmt: skip
    return ray


def _run_ray(todo: Sequence[Case], overrides: Sequence[str], config_path: str | None,
             base: Mapping[str, Any], address: str,
             record: Callable[[dict[str, Any]], None]) -> None:  # fmt: skip
    ray = _ray_connect(address)
    remote = ray.remote(num_cpus=1, max_retries=0)(run_case)
    args = (list(overrides), config_path, None, dict(base))
    refs = {remote.remote(c.model_dump_json(), *args): c for c in todo}
    try:
        while refs:
            ready, _ = ray.wait(list(refs), num_returns=1)
            for ref in ready:
                case = refs.pop(ref)
                try:
                    row = ray.get(ref)
                except Exception:
                    row = crashed_row(case, traceback.format_exc())
                record(row)
    except BaseException:
        for ref in refs:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)
        raise
