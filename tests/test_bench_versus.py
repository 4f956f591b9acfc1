"""`python -m bench.versus` refuses what is no revision with one line, not a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_a_revision_that_does_not_exist_is_named() -> None:
    out = subprocess.run([sys.executable, "-m", "bench.versus", "no-such-rev", "--cases", "1",
                          "--rounds", "1"], cwd=ROOT, capture_output=True, text=True,
                         timeout=120, check=False)  # fmt: skip
    assert out.returncode == 1
    assert out.stderr.strip() == f"python -m bench.versus: 'no-such-rev' is no revision of {ROOT}"
