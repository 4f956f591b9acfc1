"""A run's export through the API is written by a read worker to a file of its own and streamed
from it: never whole in the service's process, which runs the control loop (a long run's MCAP is
gigabytes: passed back as bytes it tripled there and stalled the loop long enough to lose the
tactile line), and no file is left behind."""

from __future__ import annotations

import asyncio
import io
import os
import tempfile
from pathlib import Path

import pytest
from mcap_check import read
from test_store import _samples

from sdh2svc.config import Settings, load_config
from sdh2svc.service.api.runs import _answer, _export_body
from sdh2svc.service.reads import READ_NICE, Payload, ReadPool
from sdh2svc.service.store import Recorder, RunStore


@pytest.mark.parametrize("format", ["csv", "mcap"])
def test_an_export_is_streamed_from_a_file_that_goes_once_opened(
    cfg: Settings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, format: str
) -> None:
    db = tmp_path / "runs.sqlite"
    store = RunStore(db)
    run_id = store.create_run({})
    rec = Recorder(db, run_id, flush_s=0.01)
    for s in _samples(cfg, 40):
        rec.sample(s)
    rec.close()
    store.finish_run(run_id, "completed", {"status": "completed"})
    expected = io.BytesIO()
    if format == "csv":
        text = io.StringIO()
        store.export_csv(run_id, text)
        expected.write(text.getvalue().encode())
    store.close()
    spool = tmp_path / "spool"
    spool.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(spool))
    settings = load_config(overrides=[f"storage.db_path='{db}'"], use_env=False)

    payload = _export_body(settings, run_id, format)  # (what a read worker does)
    assert payload.content == b"" and payload.path is not None
    assert Path(payload.path).parent == spool and Path(payload.path).stat().st_size > 0
    response = _answer(payload)
    assert list(spool.iterdir()) == []  # unlinked at once: nothing left if the client goes

    async def body() -> bytes:
        return b"".join([bytes(c) async for c in response.body_iterator])  # type: ignore[attr-defined]

    got = asyncio.run(body())
    assert int(response.headers["content-length"]) == len(got)
    if format == "csv":
        assert got == expected.getvalue()
    else:  # a whole MCAP file, every message valid
        assert len(read(got).messages["/samples"]) == 40


def _worker_standing() -> Payload:
    """In a read worker: how the kernel ranks it for an out-of-memory kill, and its priority."""
    oom = Path("/proc/self/oom_score_adj").read_text().strip()
    return Payload(f"{oom} {os.nice(0)}".encode())


def test_a_read_worker_is_the_first_an_out_of_memory_machine_ends() -> None:
    """An MCAP export of a run of thousands of strokes takes gigabytes in its read worker; out
    of memory, the kernel ended the largest process, which could be the service driving the
    hand. The read workers now go first, and run below the service's CPU priority."""
    pool = ReadPool(workers=1)

    async def ask() -> bytes:
        return (await pool(_worker_standing)).content

    try:
        oom, nice = asyncio.run(ask()).decode().split()
    finally:
        pool.close()
    assert int(oom) == 1000 and int(nice) >= os.nice(0) + READ_NICE
