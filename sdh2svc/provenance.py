"""Which sdh2svc made a record: its version, the digest of its source and, from a git checkout,
``git describe``. Recorded with every run and every campaign, so that results of two versions
are never mistaken for one another's."""

from __future__ import annotations

import contextlib
import functools
import hashlib
import subprocess
from pathlib import Path
from typing import Any

from sdh2svc import __version__

PACKAGE = Path(__file__).resolve().parent


def source_digest(root: Path | None = None) -> str:
    """SHA-256 of the package's own files (its code and the data it loads: the recognition
    model, the configuration, the suites), path by path: two trees that would run a case
    differently differ here, where ``git describe --dirty`` reads the same for any two edits.
    ``root``: the package's folder (default: this one)."""
    root = root or PACKAGE
    h = hashlib.sha256()
    for path in sorted(root.rglob("*")):
        if path.is_file() and path.suffix in (".py", ".json", ".toml"):
            h.update(path.relative_to(root).as_posix().encode() + b"\0")
            h.update(hashlib.sha256(path.read_bytes()).digest())
    return h.hexdigest()


def code_version() -> dict[str, Any]:
    """sdh2svc's version, the digest of its source (:func:`source_digest`) and, from a git
    checkout, ``git describe`` (else None). Worked out once per process (≈ 25 ms: a run's
    start pays it once): the code a process runs is the code it loaded."""
    return dict(_code_version())


@functools.cache
def _code_version() -> dict[str, Any]:
    describe = None
    with contextlib.suppress(OSError, subprocess.SubprocessError):
        r = subprocess.run(["git", "describe", "--always", "--dirty", "--tags"], cwd=PACKAGE,
                           capture_output=True, text=True, timeout=10, check=False)  # fmt: skip
        if r.returncode == 0:
            describe = r.stdout.strip() or None
    return {"version": __version__, "git_describe": describe, "source": source_digest()}
