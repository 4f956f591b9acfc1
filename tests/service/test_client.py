"""sdh2svc.client against a real ``sdh2svc serve --sim`` with a token: every call once, its
refusals, and telemetry during a one-cycle run."""

from __future__ import annotations

import csv
import functools
import io
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from sdh2svc.client import (
    ApiError,
    AsyncClient,
    AsyncTelemetry,
    Client,
    Conflict,
    InvalidRequest,
    NotFound,
    Unauthorized,
    _raise_for,
)
from tests.live_service import LiveService, start_service
from tests.service.conftest import LONG_RUNS

TOKEN = "s3cret"
RUN_TIMEOUT_S = 120.0


@pytest.fixture(scope="module")
def svc(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveService]:
    s = start_service(tmp_path_factory.mktemp("client"), viewer=False, extra=LONG_RUNS, token=TOKEN)
    try:
        yield s
    finally:
        assert s.stop() == 0, "".join(s.log)


def test_an_error_without_the_service_body() -> None:
    """A proxy's or a crashed worker's answer still raises, with what it said."""
    request = httpx.Request("GET", "http://127.0.0.1:1/api/status")
    with pytest.raises(ApiError) as raised:
        _raise_for(httpx.Response(502, text="Bad Gateway", request=request))
    assert type(raised.value) is ApiError and raised.value.status == 502
    assert raised.value.details == ["Bad Gateway"] and "502" in str(raised.value)
    body = {"error": "no run 7 (GET /api/runs lists them)", "details": []}
    with pytest.raises(NotFound, match="no run 7"):
        _raise_for(httpx.Response(404, json=body, request=request))


def test_calls_and_refusals(svc: LiveService) -> None:
    with Client(svc.url, token=TOKEN) as c:
        st = c.status()
        assert st["sim"] is True and st["auth_required"] is True
        assert c.params()["k"] == 2.0
        assert "k" in c.params_schema()["properties"]
        assert c.config()["service"]["token"] == "***"
        assert c.sim_object()["presets"]
        assert c.set_sim_object(name="egg")["object"]["name"] == "egg"

        assert c.patch_params({"k": 3.0})["k"] == 3.0
        with pytest.raises(InvalidRequest) as bad:
            c.patch_params({"k": 0.5})
        assert bad.value.status == 422 and bad.value.error == "invalid rolling parameters"
        assert any(d.startswith("k = 0.5") for d in bad.value.details)
        assert c.patch_params({"k": 2.0})["k"] == 2.0

        with pytest.raises(Conflict) as none:
            c.stop_run()
        assert none.value.status == 409 and none.value.error == "no run is running"
        with pytest.raises(NotFound) as missing:
            c.run(9999)
        assert missing.value.status == 404 and "no run 9999" in str(missing.value)

        assert c.estop()["estopped"] is True
        with pytest.raises(Conflict):
            c.start_run()
        assert c.release_estop() == {"estopped": False}

    with Client(svc.url) as anonymous:  # reading needs no token; commanding does
        assert anonymous.status()["estopped"] is False
        patch = functools.partial(anonymous.patch_params, {"k": 3.0})
        for command in (patch, anonymous.start_run, anonymous.release_estop, anonymous.open_hand):
            with pytest.raises(Unauthorized) as refused:
                command()
            assert refused.value.status == 401 and "bearer token" in refused.value.error
        assert anonymous.estop()["estopped"] is True  # stopping always works
    with Client(svc.url, token=TOKEN) as c:
        c.release_estop()


async def test_run_observed_and_read_back(svc: LiveService, tmp_path: Path) -> None:
    async with AsyncClient(svc.url, token=TOKEN) as c:
        async with c.telemetry(tactile=False) as tm:
            run_id = None
            async for msg in tm:
                if msg["type"] == "hello":
                    assert msg["status"]["sim"] is True
                    run_id = (await c.start_run({"cycles": 1}, "egg"))["run_id"]
                elif msg["type"] == "sample" and msg["run_id"] == run_id:
                    assert msg["sample"]["iteration"] >= 0
                    break
        assert run_id is not None
        with pytest.raises(Conflict):
            await c.start_run()
        end = await c.wait_run(run_id, timeout=RUN_TIMEOUT_S)
        assert end["status"] == "completed", end

        assert (await c.runs())[0]["id"] == run_id
        run = await c.run(run_id)
        assert run["status"] == "completed" and run["iterations"] > 0
        kinds = [e["kind"] for e in await c.events(run_id)]
        assert {"start", "grasped", "end"} <= set(kinds), kinds

        page = await c.samples(run_id, offset=1, limit=2)
        assert page["total"] == run["iterations"] and len(page["samples"]) == 2
        every = [s async for s in c.iter_samples(run_id, page=100)]
        assert len(every) == page["total"] and every[1:3] == page["samples"]

        text = (await c.export_bytes(run_id, "csv")).decode()
        assert len(list(csv.DictReader(io.StringIO(text)))) == page["total"]
        path = await c.export(run_id, tmp_path / "run.mcap")
        assert path.read_bytes()[:5] == b"\x89MCAP"
        with pytest.raises(NotFound):
            await c.export_bytes(9999, "mcap")

        async with c.telemetry(tactile=False) as tm:  # Open hand: its events, then idle
            assert (await c.open_hand()) == {"state": "opening"}
            kinds = [m["kind"] async for m in _until_event(tm, "opened")]
            assert kinds[-2:] == ["open", "opened"]
        assert (await c.status())["hand"]["opening"] is False

    with Client(svc.url, token=TOKEN) as sync:  # the same from the blocking client
        csv_path = sync.export(run_id, tmp_path / "run.csv")
        assert csv_path.read_bytes().decode() == text
        assert list(sync.iter_samples(run_id, page=50)) == every
        messages = sync.telemetry(tactile=False)
        hello = next(messages)
        messages.close()
        assert hello["type"] == "hello" and "links" in hello["status"]


async def _until_event(tm: AsyncTelemetry, kind: str) -> AsyncIterator[dict[str, Any]]:
    """The events telemetry brings, up to the first of ``kind``."""
    async for msg in tm:
        if msg["type"] == "event":
            yield msg
            if msg["kind"] == kind:
                return
