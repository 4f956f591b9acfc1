"""The Dockerfile, executed without a container engine (none runs here): its COPY and RUN steps
into a fresh directory and virtual environment, then its CMD with its ENV, then its HEALTHCHECK.
"""

from __future__ import annotations

import json
import os
import shlex
import shutil
import signal
import socket
import subprocess
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent


@dataclass
class Dockerfile:
    workdir: str = "/"
    copies: list[tuple[list[str], str]] = field(default_factory=list)
    runs: list[str] = field(default_factory=list)
    env: dict[str, str] = field(default_factory=dict)
    cmd: list[str] = field(default_factory=list)
    healthcheck: list[str] = field(default_factory=list)


def parse_dockerfile(text: str) -> Dockerfile:
    """The instructions this project's Dockerfile uses (continuation lines joined)."""
    d = Dockerfile()
    logical = text.replace("\\\n", " ")
    for raw in logical.splitlines():
        line = raw.strip()
        if not line or line.startswith("#"):
            continue
        op, _, rest = line.partition(" ")
        op = op.upper()
        if op == "WORKDIR":
            d.workdir = rest.strip()
        elif op == "COPY":
            *srcs, dst = shlex.split(rest)
            d.copies.append((srcs, dst))
        elif op == "RUN":
            d.runs.append(rest.strip())
        elif op == "ENV":
            d.env.update(dict(kv.split("=", 1) for kv in shlex.split(rest)))
        elif op == "CMD":
            d.cmd = json.loads(rest)
        elif op == "HEALTHCHECK":
            d.healthcheck = json.loads(rest[rest.index("CMD") + 3 :])
        elif op not in {"FROM", "VOLUME", "EXPOSE"}:
            raise AssertionError(f"unexpected Dockerfile instruction {op}")
    return d


def _free_ports(n: int) -> list[int]:
    """``n`` distinct free ports (held open together while chosen: one at a time, the system
    may hand out the same port twice)."""
    socks = [socket.socket() for _ in range(n)]
    try:
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]
    finally:
        for s in socks:
            s.close()


def test_dockerfile_steps_match_the_readme() -> None:
    d = parse_dockerfile((ROOT / "Dockerfile").read_text())
    readme = (ROOT / "README.md").read_text()
    assert d.runs and all(run in readme for run in d.runs), "README must show the same install"
    assert d.cmd[-3:] == ["sdh2svc", "serve", "--sim"] or d.cmd[-2:] == ["serve", "--sim"]
    assert d.env["SDH2SVC_SERVICE__HOST"] == "0.0.0.0"
    assert d.healthcheck[-1] == "health"


@pytest.mark.timeout(900)
def test_dockerfile_command_starts_the_service_from_a_fresh_venv(tmp_path: Path) -> None:
    d = parse_dockerfile((ROOT / "Dockerfile").read_text())
    app = tmp_path / "app"
    app.mkdir()
    for srcs, dst in d.copies:  # COPY into the WORKDIR
        target = app / dst
        for src in srcs:
            path = ROOT / src
            if path.is_dir():
                shutil.copytree(path, target, ignore=shutil.ignore_patterns("__pycache__"))
            else:
                target.mkdir(parents=True, exist_ok=True)
                shutil.copy(path, target / path.name)
    env = {k: v for k, v in os.environ.items() if not k.startswith(("SDH2SVC_", "VIRTUAL_ENV"))}
    env["PATH"] = os.defpath + ":" + os.environ.get("PATH", "")
    for run in d.runs:
        proc = subprocess.run(["bash", "-c", run], cwd=app, env=env, capture_output=True,
                              text=True, timeout=800)  # fmt: skip
        assert proc.returncode == 0, f"RUN {run}\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}"

    http_port, viser_port = _free_ports(2)
    run_env = {**env, **d.env, "SDH2SVC_STORAGE__DB_PATH": str(tmp_path / "data" / "runs.sqlite"),
               "SDH2SVC_SERVICE__PORT": str(http_port),
               "SDH2SVC_SERVICE__VISER_PORT": str(viser_port)}  # fmt: skip

    # without a token the exposed service refuses to start, and says why
    refused = subprocess.run(d.cmd, cwd=app, env=run_env, capture_output=True, text=True,
                             timeout=120)  # fmt: skip
    assert refused.returncode == 2 and "SDH2SVC_SERVICE__TOKEN" in refused.stderr

    run_env["SDH2SVC_SERVICE__TOKEN"] = "container-token"
    proc = subprocess.Popen(d.cmd, cwd=app, env=run_env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)  # fmt: skip
    try:
        deadline = time.monotonic() + 120
        health = None
        while time.monotonic() < deadline and proc.poll() is None:
            health = subprocess.run(d.healthcheck, cwd=app, env=run_env, capture_output=True,
                                    text=True, timeout=30)  # fmt: skip
            if health.returncode == 0:
                break
            time.sleep(1.0)
        if proc.poll() is not None:
            raise AssertionError("the service exited:\n" + (proc.stdout.read() if proc.stdout
                                                            else ""))  # fmt: skip
        assert health is not None and health.returncode == 0, health and health.stderr
        port = run_env["SDH2SVC_SERVICE__PORT"]
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as page:
            assert b"<html" in page.read().lower()  # the dashboard, from the installed package
        # it is the installed copy that runs, not the repository
        site = subprocess.run([str(app / ".venv/bin/python"), "-c",
                               "import sdh2svc, sys; print(sdh2svc.__file__)"],
                              capture_output=True, text=True, cwd=tmp_path)  # fmt: skip
        assert str(app / ".venv") in site.stdout
    finally:
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0, out[-3000:]
    assert "hand closed" in out
