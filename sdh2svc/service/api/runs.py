"""Runs: starting and stopping one on the hand, reading the recorded ones (samples, tactile
frames, the simulation's truth, exports), and showing one recorded iteration in the 3-D view
(the dashboard's replay).

Reads of the run database run in the service's read processes (:mod:`sdh2svc.service.reads`:
a read in a thread of the service shares the GIL with the control loop), each with its own
connection, and make their JSON there (:func:`json_body`: FastAPI would encode a returned dict
or model on the event loop, the control loop's thread). The replay's one iteration is read on a
worker thread (``asyncio.to_thread``)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import io
import json
import os
import sqlite3
import tempfile
from collections.abc import AsyncIterator, Iterator
from typing import Annotated, Any, Literal, NamedTuple

from fastapi import APIRouter, Body, Query
from fastapi.responses import Response, StreamingResponse
from pydantic import BaseModel, ConfigDict, Field
from pydantic.json_schema import SkipJsonSchema

from sdh2svc.config import ConfigError, Settings
from sdh2svc.model.base import clean_json
from sdh2svc.model.hand import matrix_shapes
from sdh2svc.service.api.body import JsonRoute, not_null
from sdh2svc.service.api.deps import SQL_INT_MAX, Auth, Digits, NoBody, RunId, St, Svc
from sdh2svc.service.api.errors import EMPTY_BODY, READ, WRITE, responses
from sdh2svc.service.hand_service import ServiceError, parse_object_request
from sdh2svc.service.reads import Payload
from sdh2svc.service.replay_feed import Recorded, recorded_iteration
from sdh2svc.service.store import RunBusy, RunStore, StoreError, recorded_settings
from sdh2svc.service.telemetry import estimate_outline

router = APIRouter(route_class=JsonRoute)


class RunRequest(BaseModel):
    """What the run is to use: each key may be left out (not sent as null)."""

    model_config = ConfigDict(extra="forbid")

    params: Annotated[dict[str, Any] | SkipJsonSchema[None], not_null("an object", dict)] = Field(
        None, description="rolling parameters for this run (left out: those in force)"
    )
    object: Annotated[
        Annotated[str, Field(max_length=64)] | dict[str, Any] | SkipJsonSchema[None],
        not_null("a preset name or an object spec", str, dict),
    ] = Field(None, description="in simulation: a preset name or an object spec")


_EXPORT_RESPONSES: dict[int | str, dict[str, Any]] = {
    200: {
        "description": "the run as a file download",
        "content": {
            "text/csv": {"schema": {"type": "string"}},
            "application/octet-stream": {"schema": {"type": "string", "format": "binary"}},
        },
    },
    **responses(*READ, 404, 409, 422, 503),
}


@router.post("/api/runs", status_code=201, dependencies=[Auth],
             responses=responses(*WRITE, 409, 422, 503))  # fmt: skip
async def start_run(
    st: St, req: Annotated[RunRequest, Body(default_factory=RunRequest)]
) -> dict[str, Any]:
    """Start a run; no body, or ``{}``, for the parameters in force and the current object."""
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


def _dumps(value: Any) -> bytes:
    # as FastAPI's JSONResponse writes it (NaN and infinity, which JSON lacks, as null)
    try:
        text = json.dumps(value, ensure_ascii=False, allow_nan=False, separators=(",", ":"))
    except ValueError:
        text = json.dumps(clean_json(value), ensure_ascii=False, allow_nan=False,
                          separators=(",", ":"))  # fmt: skip
    return text.encode()


def json_body(value: Any) -> Payload:
    """``value`` as a JSON answer, as FastAPI would write it (a model: by its aliases)."""
    if isinstance(value, BaseModel):
        value = value.model_dump(mode="json", by_alias=True)
    return Payload(_dumps(value))


EXPORT_CHUNK_B = 1 << 20  # an export streamed from its file this many bytes at a time


def _answer(body: Payload) -> Response:
    if body.path is None:
        return Response(body.content, media_type=body.media_type, headers=body.headers)
    # a file a worker wrote: streamed from it, never whole in this process (a long run's MCAP
    # is gigabytes: passed back as bytes, it tripled in the service's memory and stalled the
    # event loop — the control loop's — long enough to lose the tactile line). Unlinked at
    # once: the open file is read to its end, and nothing is left if the client goes away
    fh = open(body.path, "rb")  # noqa: SIM115 (closed by the stream)
    os.unlink(body.path)
    size = os.fstat(fh.fileno()).st_size

    async def chunks() -> AsyncIterator[bytes]:
        try:
            while chunk := await asyncio.to_thread(fh.read, EXPORT_CHUNK_B):
                yield chunk
        finally:
            fh.close()

    headers = {**body.headers, "Content-Length": str(size)}
    return StreamingResponse(chunks(), media_type=body.media_type, headers=headers)


BEFORE = "only runs of lower ids (the next page: the last id of this one)"
RUNS_PAGE = 100  # runs per page of GET /api/runs by default (a run's entry is ≈ 3.5 kB)


def _list_body(cfg: Settings, limit: int, before: int | None) -> Payload:
    with _store(cfg) as store:
        runs, total = store.run_page(limit + 1, before)  # one more: is there a next page?
    body = json_body(runs[:limit])
    body.headers["X-Total-Count"] = str(total)
    if len(runs) > limit:
        last = runs[limit - 1]["id"]
        body.headers["Link"] = f'</api/runs?before={last}&limit={limit}>; rel="next"'
    return body


@router.get("/api/runs", response_model=list[dict[str, Any]], responses=responses(*READ, 422, 503))
async def list_runs(
    svc: Svc,
    limit: Annotated[int, Query(ge=1, le=1000, description="runs on the page"), Digits] = RUNS_PAGE,
    before: Annotated[int | None, Query(ge=1, le=SQL_INT_MAX, description=BEFORE), Digits] = None,
) -> Response:
    """The recorded runs, newest first, ``limit`` at a time; the header ``X-Total-Count`` says
    how many the database holds, ``Link: <…>; rel="next"`` where the next page is."""
    return _answer(await svc.reads(_list_body, svc.cfg, limit, before))


@router.delete("/api/runs/{run_id}", dependencies=[Auth, NoBody],
               responses=responses(*WRITE, 404, 409, 422, 503),
               openapi_extra=EMPTY_BODY)  # fmt: skip
async def delete_run(svc: Svc, run_id: RunId) -> Response:
    """Delete a recorded run with everything recorded with it; 409 while it is being
    recorded."""
    return _answer(await svc.reads(_delete_run, svc.cfg, run_id))


def _delete_run(cfg: Settings, run_id: int) -> Payload:
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        try:
            if not store.delete_runs([run_id]):
                raise ServiceError(404, f"no run {run_id} (GET /api/runs lists them)")
        except RunBusy as e:
            raise ServiceError(409, str(e)) from None
        except sqlite3.OperationalError as e:
            raise ServiceError(503, f"run {run_id} was not deleted: {e}") from None
    return json_body({"deleted": run_id})


class RecognitionSummary(BaseModel):
    """What the recognition made of the run's object, from the tactile frames and joint angles
    only (``control.recognition.Recognizer.summary``); null when it had no estimate."""

    model_config = ConfigDict(extra="allow")

    object_class: str | None = Field(
        None, description="box | polygon | ellipse | circle | stick; null: undecided"
    )
    confidence: float | None = Field(None, description="in object_class, 0…1; null: undecided")
    size_a_mm: float | None = Field(
        None, description="circle radius; ellipse semi-axis a; the box's side held between the "
        "pads; stick length; polygon circumradius, mm",
    )  # fmt: skip
    size_b_mm: float | None = Field(
        None, description="ellipse semi-axis b (from the narrowest width seen and the product a·b "
        "the curved contacts' radii give); stick diameter; null for a box or a polygon "
        "(not measured), mm",
    )  # fmt: skip
    rotation_deg: float | None = Field(
        None,
        description="the object's rotation since the grasp at the run's end (rolling "
        "kinematics), deg",
    )
    rotation_range_deg: float | None = Field(
        None, description="how far the object turned over the run, its largest rotation less "
        "its smallest (rolling kinematics; compare truth.rotation_range_deg in simulation), deg",
    )  # fmt: skip
    contacts: dict[str, float] | None = Field(
        None, description="the share of contact iterations labelled flat, edge and curved"
    )
    failed: dict[str, Any] | None = Field(
        None, description="the recognition failed mid-run: {iteration, message}; the fields "
        "above are what it had estimated until then (absent: it did not fail)",
    )  # fmt: skip


class RunSummary(BaseModel):
    """A finished run's summary (as ``sdh2svc run --json`` prints it); among its fields:"""

    model_config = ConfigDict(extra="allow")

    status: str = Field(description="completed | stopped | faulted | dropped | e-stopped")
    strokes: int | None = Field(None, description="back-and-forth strokes completed")
    iterations: int | None = Field(None, description="rolling iterations")
    recognition: RecognitionSummary | None = Field(
        None, description="the recognition's estimate of the object (null: none)"
    )
    truth: dict[str, Any] | None = Field(
        None, description="in simulation, the truth as the run let go (never seen by the run)"
    )


class RunDetail(BaseModel):
    """One recorded run."""

    model_config = ConfigDict(extra="allow")

    id: int
    started_at: str
    ended_at: str | None
    status: str = Field(description="running, a run's end status, or interrupted")
    iterations: int
    meta: dict[str, Any] = Field(description="parameters, object, the hand's description")
    summary: RunSummary | None = Field(description="null while running")
    events: list[dict[str, Any]] = Field(description="{t, iteration, kind, detail}, in order")


_RUN_RESPONSES = {
    200: {"model": RunDetail, "description": "the run"},
    **responses(*READ, 404, 422, 503),
}


def _run_body(cfg: Settings, run_id: int) -> Payload:
    with _store(cfg) as store:
        return json_body(_run_or_404(store, run_id, events=True))


@router.get("/api/runs/{run_id}", response_model=dict[str, Any], responses=_RUN_RESPONSES)
async def get_run(svc: Svc, run_id: RunId) -> Response:
    """One run: its metadata, summary (with the recognition's estimate) and events."""
    return _answer(await svc.reads(_run_body, svc.cfg, run_id))


MAX_OUTLINES = 100  # samples per page with their outlines (each costs milliseconds to make)
MAX_EVERY = 10_000
EVERY_DOC = (
    "only one iteration in this many, counted from the run's first sample's (the same "
    "iterations of samples, frames and truth): a long run at a resolution a page can hold"
)
Every = Annotated[int, Query(ge=1, le=MAX_EVERY, description=EVERY_DOC), Digits]
OUTLINE_DOC = (
    "with each sample its `estimate_outline`: the object as the recognition reconstructed it, "
    "[[y, z], …] mm in frame 0 (empty while no class is known), as in the live `sample` "
    f"message; `limit` then at most {MAX_OUTLINES}"
)


@router.get("/api/runs/{run_id}/samples", response_model=dict[str, Any],
            responses=responses(*READ, 404, 422, 503))  # fmt: skip
async def samples(
    svc: Svc,
    run_id: RunId,
    first: Annotated[
        int, Query(alias="from", ge=0, le=SQL_INT_MAX, description="the first iteration"), Digits
    ] = 0,
    offset: Annotated[int, Query(ge=0, le=SQL_INT_MAX), Digits] = 0,
    limit: Annotated[
        int | None, Query(ge=1, le=10_000, description=f"1000; {MAX_OUTLINES} with outline"), Digits
    ] = None,
    every: Every = 1,
    outline: Annotated[bool, Query(description=OUTLINE_DOC)] = False,
) -> Response:
    """The run's samples in iteration order from iteration `from` on, `offset` of them skipped,
    `limit` at most; follow `next` (a `from`) for the rest."""
    if limit is None:
        limit = MAX_OUTLINES if outline else 1000
    if outline and limit > MAX_OUTLINES:
        raise ServiceError(422, "invalid request", [f"limit: at most {MAX_OUTLINES} with outline"])
    page = SampleQuery(first, offset, limit, every)
    return _answer(await svc.reads(_samples_body, svc.cfg, run_id, page, outline))


class SampleQuery(NamedTuple):
    first: int
    offset: int
    limit: int
    every: int


def _samples_body(cfg: Settings, run_id: int, ask: SampleQuery, outline: bool) -> Payload:
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        rows = store.samples(run_id, ask.offset, ask.limit + 1, ask.first, ask.every)
        more = rows[ask.limit]["iteration"] if len(rows) > ask.limit else None
        rows = rows[: ask.limit]
        if outline:  # as the live `sample` message carries it
            for row in rows:
                row["estimate_outline"] = estimate_outline(row).tolist()
        page = {
            "run_id": run_id, "from": ask.first, "offset": ask.offset, "limit": ask.limit,
            "every": ask.every, "total": store.sample_count(run_id), "next": more, "samples": rows,
        }  # fmt: skip
        return json_body(page)


FRAME_ENCODING = "base64-u16le"


class RecordedFrame(BaseModel):
    """One iteration's tactile frame."""

    iteration: int = Field(description="the rolling iteration it was used in (count)")
    t: float = Field(description="time since the run started, s (the iteration's sample's t)")
    timestamp_ms: int = Field(description="the DSACON32m controller's clock, ms")
    texels: str = Field(
        description="raw counts (0…4095), base64 of little-endian uint16: the matrices of "
        "`shapes` one after the other, each row-major (row 0 at the fingertip's side)"
    )


class FramePage(BaseModel):
    """A page of a run's tactile frames, in iteration order."""

    model_config = ConfigDict(populate_by_name=True)

    run_id: int
    from_: int = Field(alias="from", description="the first iteration asked for")
    to: int | None = Field(description="the last iteration asked for (null: to the end)")
    limit: int = Field(description="frames per page at most")
    every: int = Field(description="one iteration in this many")
    total: int = Field(description="the run's frames linked to an iteration")
    next: int | None = Field(
        description="`from` of the next page; null: this page reaches `to` or the end"
    )
    encoding: Literal["base64-u16le"] = Field(description="how `texels` is written")
    shapes: list[tuple[int, int]] = Field(
        description="(rows, columns) of each tactile matrix, in matrix index order"
    )
    frames: list[RecordedFrame]


@router.get("/api/runs/{run_id}/frames", response_model=FramePage,
            responses=responses(*READ, 404, 409, 422, 503))  # fmt: skip
async def frames(
    svc: Svc,
    run_id: RunId,
    first: Annotated[int, Query(alias="from", ge=0, le=SQL_INT_MAX), Digits] = 0,
    to: Annotated[int | None, Query(ge=0, le=SQL_INT_MAX), Digits] = None,
    limit: Annotated[int, Query(ge=1, le=2000), Digits] = 500,
    every: Every = 1,
) -> Response:
    """The run's tactile frames of iterations `from`…`to`, `limit` at most; follow `next` for
    the rest. Frames recorded without an iteration are not listed."""
    if to is not None and to < first:
        raise ServiceError(422, "invalid request", [f"to: must be at least from ({first})"])
    return _answer(await svc.reads(_frames_body, svc.cfg, run_id, first, to, limit, every))


def _frames_body(
    cfg: Settings, run_id: int, first: int, to: int | None, limit: int, every: int
) -> Payload:
    last = SQL_INT_MAX if to is None else to
    with _store(cfg) as store:
        cfg = _as_recorded(_run_or_404(store, run_id), cfg)  # its matrices, however split now
        rows = store.frames_from(run_id, first, last, limit + 1, every)
        page = [
            RecordedFrame(iteration=it, t=t, timestamp_ms=ts,
                          texels=base64.b64encode(texels).decode("ascii"))
            for it, t, ts, texels in rows[:limit]
        ]  # fmt: skip
        return json_body(FramePage(
            run_id=run_id, from_=first, to=to, limit=limit, every=every,
            total=store.framed_count(run_id),
            next=rows[limit][0] if len(rows) > limit else None, encoding=FRAME_ENCODING,
            shapes=list(matrix_shapes(cfg.tactile, cfg.axes)), frames=page,
        ))  # fmt: skip


class RecordedTruth(BaseModel):
    """One iteration's truth in simulation: the object as the physics last stepped."""

    iteration: int = Field(description="the rolling iteration (count)")
    t: float | None = Field(description="time since the run started, s (the sample's t)")
    y: float = Field(description="the object's centre, frame 0's y, mm")
    z: float = Field(description="the object's centre, frame 0's z, mm")
    psi: float = Field(description="the object's angle ψ, rad")
    held: bool = Field(description="held by the fingers")
    dropped: bool = Field(description="dropped")
    in_fixture: bool = Field(description="still held by the fixture")
    slips: int = Field(description="slip onsets so far (count)")


class RecordedOutline(BaseModel):
    """The run's object: its outline in its own frame (placed at an iteration's y, z, ψ:
    x' = y + x·cos ψ − y·sin ψ, and so on, as the live `sim` message's outline)."""

    object: str
    size_mm: float
    points: list[tuple[float, float]] = Field(description="the outline, object frame, mm")


class TruthPage(BaseModel):
    """A page of a run's truth (simulation only: a real hand's run has none), in iteration
    order."""

    model_config = ConfigDict(populate_by_name=True)

    run_id: int
    from_: int = Field(alias="from", description="the first iteration asked for")
    limit: int = Field(description="iterations per page at most")
    every: int = Field(description="one iteration in this many")
    total: int = Field(description="the run's iterations with truth")
    next: int | None = Field(description="`from` of the next page; null: this page is the last")
    outline: RecordedOutline | None = Field(description="the object; null: no truth recorded")
    truth: list[RecordedTruth]


@router.get("/api/runs/{run_id}/truth", response_model=TruthPage,
            responses=responses(*READ, 404, 422, 503))  # fmt: skip
async def truth(
    svc: Svc,
    run_id: RunId,
    first: Annotated[int, Query(alias="from", ge=0, le=SQL_INT_MAX), Digits] = 0,
    limit: Annotated[int, Query(ge=1, le=10000), Digits] = 2000,
    every: Every = 1,
) -> Response:
    """In simulation, the object's true pose and state at each iteration from `from` on,
    `limit` at most, and its outline; follow `next` for the rest."""
    return _answer(await svc.reads(_truth_body, svc.cfg, run_id, first, limit, every))


def _truth_body(cfg: Settings, run_id: int, first: int, limit: int, every: int) -> Payload:
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        rows = store.truth(run_id, first, limit + 1, every)
        outline = store.outline(run_id)
        return json_body(TruthPage(
            run_id=run_id, from_=first, limit=limit, every=every,
            total=store.truth_count(run_id),
            next=rows[limit]["iteration"] if len(rows) > limit else None,
            outline=None if outline is None else RecordedOutline(**outline),
            truth=[RecordedTruth(**r) for r in rows[:limit]],
        ))  # fmt: skip


class ReplayAt(BaseModel):
    """Which recorded iteration the 3-D view is to show."""

    model_config = ConfigDict(extra="forbid", strict=True)  # "1" and true are no ids

    run_id: int = Field(ge=1, le=SQL_INT_MAX, description="a run's id (GET /api/runs)")
    iteration: int = Field(ge=0, le=SQL_INT_MAX, description="an iteration of that run")


class ReplayShown(BaseModel):
    """What the 3-D view shows: a recorded iteration, or (``replay`` null) the live hand."""

    replay: dict[str, Any] | None = Field(
        description="run_id, iteration and t (s since the run started) of the iteration shown"
    )
    live_again_in_s: float | None = Field(
        description="without a newer PUT the view goes live again after this long"
    )


@router.put("/api/viewer/replay", response_model=ReplayShown, dependencies=[Auth],
            responses=responses(*WRITE, 404, 409, 422, 503))  # fmt: skip
async def show_replay(svc: Svc, at: ReplayAt) -> ReplayShown:
    """Show a recorded iteration in the 3-D view (its pose, contacts, cones and pads) instead of
    the live hand: the dashboard's replay scrubber sends where it is. The view stays on it until
    DELETE, or a minute without a newer one."""
    view = _viewer(svc)

    def read() -> Recorded | None:
        with _store(svc.cfg) as store:
            _run_or_404(store, at.run_id)
            try:  # drawn as the run recorded its configuration
                return recorded_iteration(store, svc.cfg, at.run_id, at.iteration)
            except ConfigError as e:
                raise ServiceError(409, _unreadable(at.run_id, e)) from None

    rec = await asyncio.to_thread(read)
    if rec is None:
        raise ServiceError(404, f"run {at.run_id} has no iteration {at.iteration}")
    view.replay.show(rec)
    return ReplayShown(replay=clean_json(rec.where()), live_again_in_s=view.replay.ttl_s)


@router.delete("/api/viewer/replay", response_model=ReplayShown, dependencies=[Auth, NoBody],
               responses=responses(*WRITE, 409, 422), openapi_extra=EMPTY_BODY)  # fmt: skip
async def end_replay(svc: Svc) -> ReplayShown:
    """The 3-D view shows the live hand again."""
    _viewer(svc).replay.end()
    return ReplayShown(replay=None, live_again_in_s=None)


def _viewer(svc: Any) -> Any:
    if svc.viewer is None:
        raise ServiceError(409, "the 3-D view is off on this service (started with --no-viewer)")
    return svc.viewer


@router.get("/api/runs/{run_id}/export", response_class=Response, responses=_EXPORT_RESPONSES)
async def export(svc: Svc, run_id: RunId, format: Literal["csv", "mcap"] = "csv") -> Response:
    return _answer(await svc.reads(_export_body, svc.cfg, run_id, format))


def _export_body(cfg: Settings, run_id: int, format: str) -> Payload:
    """The export written to a file of its own, which the service streams (:func:`_answer`)."""
    with _store(cfg) as store:
        _run_or_404(store, run_id)
        headers = {"Content-Disposition": f'attachment; filename="run-{run_id}.{format}"'}
        fd, path = tempfile.mkstemp(prefix="sdh2svc-export-", suffix=f".{format}")
        try:
            with open(fd, "wb") as out:
                if format == "csv":
                    text = io.TextIOWrapper(out, encoding="utf-8", newline="")
                    store.export_csv(run_id, text)
                    text.flush()
                    text.detach()  # (``out`` closes the file)
                else:
                    store.export_mcap(run_id, out, cfg)
        except ConfigError as e:  # recorded by a version whose configuration this one refuses
            os.unlink(path)
            raise ServiceError(409, f"run {run_id} cannot be drawn by this version: {e}") from None
        except BaseException:
            os.unlink(path)
            raise
    media = "text/csv; charset=utf-8" if format == "csv" else "application/octet-stream"
    return Payload(b"", media, headers, path=path)


@contextlib.contextmanager
def _store(cfg: Settings) -> Iterator[RunStore]:
    """A connection of this read's own (SQLite WAL: readers never block the recorder)."""
    try:
        store = RunStore(cfg.storage.db_path, create=False,
                         busy_timeout_s=cfg.storage.busy_timeout_s)  # fmt: skip
    except StoreError as e:
        raise ServiceError(503, f"the run database cannot be read: {e}") from None
    try:
        yield store
    finally:
        store.close()


def _run_or_404(store: RunStore, run_id: int, *, events: bool = False) -> dict[str, Any]:
    run = store.record(run_id) if events else store.run(run_id)
    if run is None:
        raise ServiceError(404, f"no run {run_id} (GET /api/runs lists them)")
    return run


def _as_recorded(run: dict[str, Any], cfg: Settings) -> Settings:
    """The configuration ``run`` was recorded with; 409 if this version cannot read it."""
    try:
        return recorded_settings(run, cfg)
    except ConfigError as e:
        raise ServiceError(409, _unreadable(run["id"], e)) from None


def _unreadable(run_id: int, e: ConfigError) -> str:
    return f"run {run_id} cannot be read by this version: {e}"
