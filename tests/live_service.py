"""Start ``sdh2svc serve`` as a subprocess and wait for its URLs — for tests, benchmarks and
lab scripts that want a service of their own (free ports, their own database).

It runs the same command a person types and reads the one JSON line ``--json`` announces.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from sdh2svc.client import AsyncClient, Client, RunRef, Unavailable

START_TIMEOUT_S = 90.0


async def start_run(
    c: AsyncClient,
    params: Mapping[str, Any] | None = None,
    obj: str | Mapping[str, Any] | None = None,
) -> RunRef:
    """``c.start_run`` for a run the test needs started: a service starved of CPU for a moment
    (the other worker's load) can find its real-time tactile stream 0.3 s late and refuse the
    run 503 "sends no frames"; that answer — only that one, at most twice — is waited out (the
    status shows the line up again) and the run asked for again. Where the refusal is what a
    test checks, it calls ``c.start_run`` itself."""
    for attempt in range(3):
        try:
            return await c.start_run(params, obj)
        except Unavailable as e:
            if "sends no frames" not in str(e) or attempt == 2:
                raise
            await c.wait_status(lambda st: st["hand"]["connected"]["tactile"], 30.0)
    raise AssertionError("unreachable")


@dataclass
class LiveService:
    proc: subprocess.Popen[str]
    url: str
    viewer_url: str | None
    token: str | None
    db_path: Path
    log: list[str] = field(default_factory=list)
    readers: list[threading.Thread] = field(default_factory=list)
    announced: dict[str, Any] = field(default_factory=dict)  # serve --json's line

    @property
    def ws_url(self) -> str:
        """The telemetry WebSocket's URL, for tests that speak the protocol raw."""
        return self.url.replace("http://", "ws://", 1) + "/ws/telemetry"

    def headers(self) -> dict[str, str]:
        """The token's header, for raw HTTP requests."""
        return {"Authorization": f"Bearer {self.token}"} if self.token else {}

    def client(self) -> AsyncClient:
        """The service's :class:`~sdh2svc.client.AsyncClient`, with its token."""
        return AsyncClient(self.url, token=self.token)

    def sync_client(self) -> Client:
        """The service's blocking :class:`~sdh2svc.client.Client`, with its token."""
        return Client(self.url, token=self.token)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 60.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        for t in self.readers:  # EOF once the process is gone
            t.join(5.0)
        for stream in (self.proc.stdout, self.proc.stderr):
            if stream is not None:
                stream.close()
        return self.proc.returncode


# The simulated hand starts in the pre-shape: the first run's move there from the straight
# fingers takes 5.5 s of real time, in which these tests look at nothing (the move is tested on
# the virtual clock: tests/control, tests/service/test_faults_by_phase.py)
AT_PRESHAPE = ("--set", "sim.start_deg=[90.0, -30.0, 30.0, -90.0, 0.0, -30.0, 30.0]")
# For tests about something else than the grasp (tests/control and test_motion_safety.py are
# about it): the fingers approach at 6 °/s instead of 2 and close on the egg at most at 9 °/s
# instead of 3 (0.2–0.3° per frame period, under a third of safety.max_step_deg), so a run
# reaches its rolling in ≈ 9 s of real time instead of ≈ 17 (in fast mode the egg's grip peaks
# at 1.7 × Fd)
FAST_GRASP = ("--set", "run.grasp_max_velocity_deg_s=9.0", "--set", "run.grasp_gain_deg_s=5.0",
              "--set", "run.grasp_approach_velocity_deg_s=6.0")  # fmt: skip


def service_command(
    db_path: Path, *, viewer: bool, extra: Sequence[str] = (), sim: bool = True
) -> list[str]:
    """``sdh2svc serve --sim`` on free ports with the database at ``db_path`` (``sim=False``:
    without ``--sim``; give the hand's ``--dsa``/``--sdh`` in ``extra``). The simulated hand
    starts in the pre-shape (:data:`AT_PRESHAPE`)."""
    cmd = [sys.executable, "-m", "sdh2svc", "serve", "--json", "--port", "0",
           "--set", f"storage.db_path={json.dumps(str(db_path))}"]  # fmt: skip
    cmd += ["--sim", *AT_PRESHAPE] if sim else []
    cmd += ["--viser-port", "0"] if viewer else ["--no-viewer"]
    return cmd + list(extra)


def start_service(
    tmp: Path,
    *,
    viewer: bool = True,
    extra: Sequence[str] = (),
    env: dict[str, str] | None = None,
    token: str | None = None,
    sim: bool = True,
    wait_hand: bool = True,
) -> LiveService:
    """Start the service and wait for its announcement line (the URLs) — and, on a real hand
    (``sim=False``), for both its lines to be up (the service opens them in the background),
    unless ``wait_hand`` is False."""
    db = tmp / "runs.sqlite"
    full_env = {**os.environ, **(env or {})}
    if token:
        full_env["SDH2SVC_SERVICE__TOKEN"] = token
    proc = subprocess.Popen(
        service_command(db, viewer=viewer, extra=extra, sim=sim), stdout=subprocess.PIPE,
        stderr=subprocess.PIPE, text=True, env=full_env, cwd=tmp,
    )  # fmt: skip
    log: list[str] = []
    err = threading.Thread(target=_collect, args=(proc.stderr, log), daemon=True)
    err.start()
    line = _read_line(proc, START_TIMEOUT_S)
    try:
        info = json.loads(line) if line else None
    except ValueError:
        info = None
    if info is None:  # never leave a half-started service behind
        proc.kill()
        proc.wait()
        err.join(5.0)
        for stream in (proc.stdout, proc.stderr):
            stream.close()  # type: ignore[union-attr]
        raise RuntimeError(f"the service did not start ({line!r}):\n" + "".join(log))
    out = threading.Thread(target=_collect, args=(proc.stdout, log), daemon=True)
    out.start()
    svc = LiveService(proc, info["url"], info["viewer_url"], token, db, log, [err, out], info)
    if not sim and wait_hand:
        with svc.sync_client() as c:
            c.wait_status(lambda st: all(st["hand"]["connected"].values()), START_TIMEOUT_S)
    return svc


def _collect(stream: object, out: list[str]) -> None:
    with contextlib.suppress(ValueError):
        for line in stream:  # type: ignore[attr-defined]
            out.append(line)


def _read_line(proc: subprocess.Popen[str], timeout: float) -> str:
    """The announcement: the first stdout line that is a JSON object ("" if none in time)."""
    result: list[str] = []

    def read() -> None:
        for line in proc.stdout:  # type: ignore[union-attr]
            if line.startswith("{"):
                result.append(line)
                return

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    reader.join(timeout)
    return result[0] if result else ""
