"""The live API against its own OpenAPI document, with schemathesis: no server error, and no
status code or content type that the document does not list, whatever the request.

Schemathesis's CLI runs in a subprocess against a real ``sdh2svc serve --sim`` (its own, on free
ports, so that the runs it starts and the parameters it changes touch no other test), in its
deterministic mode with a bounded number of examples per operation.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import httpx

from tests.live_service import start_service

CHECKS = "not_a_server_error,status_code_conformance,content_type_conformance"
MAX_EXAMPLES = 6  # per operation and phase: ≈ 300 requests, ≈ 15 s on a quiet 2-core machine


def test_api_conforms_to_its_openapi(tmp_path: Path) -> None:
    svc = start_service(tmp_path, viewer=False)
    try:
        cmd = [sys.executable, "-m", "schemathesis.cli", "run", f"{svc.url}/openapi.json",
               "--checks", CHECKS, "--max-examples", str(MAX_EXAMPLES),
               "--generation-deterministic", "--workers", "1", "--no-color",
               "--request-timeout", "30", "--suppress-health-check", "all"]  # fmt: skip
        with httpx.Client(base_url=svc.url, timeout=30) as c:
            out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp_path)
            report = out.stdout[-6000:] + out.stderr[-2000:]
            assert out.returncode == 0, report
            assert "passed" in out.stdout, report
            # whatever it started is stopped: the e-stop needs nothing, then it is released
            assert c.post("/api/estop").status_code == 200
            assert c.post("/api/estop/release", json={}).status_code == 200
            status = c.get("/api/status").json()
            assert status["run"] is None or status["run"]["status"] != "running"
            assert status["hand"]["connected"] == {"joints": True, "tactile": True}
    finally:
        code = svc.stop()
    assert code == 0, "the service did not shut down cleanly:\n" + "".join(svc.log)
