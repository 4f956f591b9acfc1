"""The command line, run as a user runs it (a subprocess of the installed entry point)."""

from __future__ import annotations

import json
import subprocess
import sys


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "sdh2svc", *args], capture_output=True, text=True, timeout=60
    )


def test_demo_json_gives_the_mirror_pose_values() -> None:
    r = run("demo", "--json")
    assert r.returncode == 0, r.stderr
    out = json.loads(r.stdout)
    assert round(out["Lambda_mm"], 2) == 82.20
    assert round(out["omega_A_deg"], 2) == round(out["omega_B_deg"], 2) == 91.39
    assert out["inside_cone"] is True


def test_demo_reports_leaving_the_cone() -> None:
    r = run("demo", "--json", "--phi2", "10", "--phi3", "60")
    assert json.loads(r.stdout)["inside_cone"] is False


def test_bad_override_exits_2_with_a_readable_message() -> None:
    r = run("config", "--set", "rolling.k=0")
    assert r.returncode == 2
    assert "rolling.k = 0" in r.stderr and "1.0 < k ≤ 10.0" in r.stderr
    assert "Traceback" not in r.stderr


def test_config_prints_effective_values() -> None:
    r = run("config", "--set", "rolling.cycles=9")
    assert r.returncode == 0
    assert json.loads(r.stdout)["rolling"]["cycles"] == 9
