"""`sdh2svc campaign run smoke`, as a user types it: every case runs through the full byte path
on two worker processes and is judged; none crashes."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pyarrow.parquet as pq

from sdh2svc.campaign.case import load_suite


def test_the_smoke_campaign_runs_and_judges_every_case(tmp_path: Path) -> None:
    out = tmp_path / "smoke"
    r = subprocess.run([sys.executable, "-m", "sdh2svc", "campaign", "run", "smoke",
                        "--workers", "2", "--out", str(out)],
                       capture_output=True, text=True, timeout=600, cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    rows = pq.read_table(out / "results.parquet").to_pylist()
    assert sorted(row["id"] for row in rows) == sorted(c.id for c in load_suite("smoke").cases)
    assert not [row["id"] for row in rows if row["status"] == "crashed"]
    assert all(row["success"] == (row["failure"] == "") for row in rows)
    assert any(row["success"] for row in rows)
    r = subprocess.run([sys.executable, "-m", "sdh2svc", "campaign", "report", str(out)],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Success overall" in (out / "report.md").read_text()
