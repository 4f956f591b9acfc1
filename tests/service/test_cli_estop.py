"""`sdh2svc estop --latch` beside a running service: it e-stops that service through its API
when the service keeps its runs in the same database, and leaves a service on another database
alone (found by a safety audit: the command latched the disk only, said the hand was not
stopped, and the service went on, its status unaware of the latch a restart would find)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from urllib.parse import urlsplit

from sdh2svc.cli import Exit
from sdh2svc.service.store import RunStore
from tests.live_service import start_service
from tests.service.test_retention import another_process_open


def estop_latch(db: Path, port: int) -> subprocess.CompletedProcess[str]:
    """`sdh2svc estop --latch` with this database and service port."""
    return subprocess.run(
        [sys.executable, "-m", "sdh2svc", "estop", "--latch",
         "--set", f"storage.db_path={json.dumps(str(db))}", "--set", f"service.port={port}"],
        capture_output=True, text=True, timeout=60, check=False,
    )  # fmt: skip


def test_estop_latch_stops_the_service_that_keeps_its_runs_there(tmp_path: Path) -> None:
    svc = start_service(tmp_path, viewer=False)
    try:
        port = urlsplit(svc.url).port
        assert port is not None
        # another database, held open as a service would hold it: that service is not this one
        other = tmp_path / "other" / "runs.sqlite"
        other.parent.mkdir()
        store = RunStore(other)
        try:
            assert store.create_run({"test": True}) == 1
        finally:
            store.close()
        with another_process_open(other):
            r = estop_latch(other, port)
        assert r.returncode == Exit.FAILED and "the hand was NOT stopped" in r.stderr, r
        assert "keeps its runs in another database" in r.stderr, r
        with svc.sync_client() as c:
            assert c.status()["estopped"] is False  # left alone

        # a database nobody has open, the service on another: said NOT stopped, exit 1
        alone = tmp_path / "alone" / "runs.sqlite"
        alone.parent.mkdir()
        r = estop_latch(alone, port)
        assert r.returncode == Exit.FAILED, r
        lines = r.stderr.splitlines()
        assert all(line.startswith("sdh2svc estop: ") for line in lines), r
        assert (f"sdh2svc estop: the service at http://127.0.0.1:{port} keeps its runs in another "
                "database") in r.stderr, r  # fmt: skip
        assert "it was NOT stopped" in r.stderr, r
        with svc.sync_client() as c:
            assert c.status()["estopped"] is False  # left alone

        r = estop_latch(svc.db_path, port)
        assert r.returncode == Exit.OK, r
        assert f"the service at http://127.0.0.1:{port}, which keeps its runs in this " in r.stdout
        assert "e-stopped the hand" in r.stdout and not r.stderr, r
        with svc.sync_client() as c:
            status = c.status()
            assert status["estopped"] is True and status["estop"] is not None, status
            assert c.release_estop()["estopped"] is False
            assert c.status()["estop"] is None  # released on disk too: the service's own latch
    finally:
        assert svc.stop() == 0, "".join(svc.log)
