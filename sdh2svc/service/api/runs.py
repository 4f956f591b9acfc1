"""Runs: starting and stopping one on the hand, and reading the recorded ones.

Reads of the run database happen on worker threads (sync routes) with their own connection, so
a large export never takes time from the control loop."""

from __future__ import annotations

import contextlib
import io
from collections.abc import Iterator
from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Query
from fastapi.responses import Response
from pydantic import BaseModel, ConfigDict, Field

from sdh2svc.config import Settings
from sdh2svc.service.api.deps import SQL_INT_MAX, Auth, Cfg, RunId, St
from sdh2svc.service.api.errors import EMPTY_BODY, READ, WRITE, responses
from sdh2svc.service.hand_service import ServiceError, parse_object_request
from sdh2svc.service.store import RunStore
from sdh2svc.service.telemetry import clean_json

router = APIRouter()


class RunRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    params: dict[str, Any] | None = Field(None, description="rolling parameters for this run")
    object: Annotated[str, Field(max_length=64)] | dict[str, Any] | None = Field(
        None, description="in simulation: a preset name or an object spec"
    )


_EXPORT_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the run as a file download",
        "content": {
            "text/csv": {"schema": {"type": "string"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    },
    **responses(*READ, 404, 422),
}


@router.post("/api/runs", status_code=201, dependencies=[Auth],
             responses=responses(*WRITE, 409, 422, 503))  # fmt: skip
async def start_run(st: St, req: Annotated[RunRequest | None, Body()] = None) -> dict[str, Any]:
    req = req or RunRequest(params=None, object=None)
    obj = None
    if req.object is not None:
        if st.bench is None:
            raise ServiceError(422, "an object can only be chosen in simulation")
        name, spec = (req.object, None) if isinstance(req.object, str) else (None, req.object)
        obj = parse_object_request(name, spec)
    return st.start_run(req.params, obj)


@router.post("/api/runs/stop", status_code=202, dependencies=[Auth],
             responses=responses(*WRITE, 409), openapi_extra=EMPTY_BODY)  # fmt: skip
async def stop_run(st: St) -> dict[str, Any]:
    return st.stop_run()


@router.get("/api/runs", responses=responses(*READ))
def list_runs(cfg: Cfg) -> list[dict[str, Any]]:
    with _store(cfg) as store:
        return clean_json(store.runs())  # type: ignore[no-any-return]


@router.get("/api/runs/{run_id}", responses=responses(*READ, 404, 422))
def get_run(cfg: Cfg, run_id: RunId) -> dict[str, Any]:
    with _store(cfg) as store:
        run = _run_or_404(store, run_id)
        run["events"] = store.events(run_id)
        return clean_json(run)  # type: ignore[no-any-return]


@router.get("/api/runs/{run_id}/samples", responses=responses(*READ, 404, 422))
def samples(
    cfg: Cfg,
    run_id: RunId,
    offset: Annotated[int, Query(ge=0, le=SQL_INT_MAX)] = 0,
    limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
) -> dict[str, Any]:
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        page = {
            "run_id": run_id, "offset": offset, "limit": limit,
            "total": store.sample_count(run_id), "samples": store.samples(run_id, offset, limit),
        }  # fmt: skip
        return clean_json(page)  # type: ignore[no-any-return]


@router.get("/api/runs/{run_id}/export", response_class=Response, responses=_EXPORT_RESPONSES)
def export(cfg: Cfg, run_id: RunId, format: Literal["csv", "mcap"] = "csv") -> Response:
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        headers = {"Content-Disposition": f'attachment; filename="run-{run_id}.{format}"'}
        if format == "csv":
            text = io.StringIO()
            store.export_csv(run_id, text)
            return Response(text.getvalue(), media_type="text/csv", headers=headers)
        data = io.BytesIO()
        store.export_mcap(run_id, data, cfg)
        return Response(data.getvalue(), media_type="application/octet-stream", headers=headers)


@contextlib.contextmanager
def _store(cfg: Settings) -> Iterator[RunStore]:
    """A connection of this worker thread's own (SQLite WAL: readers never block the recorder)."""
    store = RunStore(cfg.storage.db_path)
    try:
        yield store
    finally:
        store.close()


def _run_or_404(store: RunStore, run_id: int) -> dict[str, Any]:
    run = store.run(run_id)
    if run is None:
        raise ServiceError(404, f"no run {run_id} (GET /api/runs lists them)")
    return run
