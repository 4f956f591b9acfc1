"""The REST/WebSocket API and the dashboard's files (docs/api.md is the contract).

Reads of the run database happen on worker threads with their own connection, so a large export
never takes time from the control loop; everything that touches the hand goes through the
:class:`~sdh2svc.service.hand_service.HandService` on the event loop. Before any route, the
:class:`~sdh2svc.service.guard.Guard` decides which requests get in at all (Host, Origin, content
type, body size); the token is checked per route (``Auth``), and not for the e-stop.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import secrets
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import Body, Depends, FastAPI, Query, Request, WebSocket, WebSocketDisconnect
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from sdh2svc import __version__
from sdh2svc.config import Settings, clip, error_key, error_message
from sdh2svc.connect import Where
from sdh2svc.control.params import RollingParams
from sdh2svc.service.guard import Guard
from sdh2svc.service.hand_service import HandService, ServiceError, parse_object_request
from sdh2svc.service.hub import Client, TelemetryHub, clean_json, encode
from sdh2svc.service.store import RunStore

log = logging.getLogger(__name__)

SQL_INT_MAX = 2**63 - 1  # SQLite's largest integer: run ids, sample offsets
DOCS_ASSETS = "/docs-assets"  # Swagger UI and ReDoc, served from the fastapi-offline package


def docs_assets_dir() -> Path:
    """Swagger UI's and ReDoc's files, packaged (no CDN: the lab PC may be offline)."""
    return Path(str(resources.files("fastapi_offline") / "static"))


def web_dir() -> Path:
    """The dashboard's files: packaged (wheel) or the repository's ``web/``."""
    packaged = resources.files("sdh2svc") / "_web"
    if packaged.is_dir():
        return Path(str(packaged))
    return Path(__file__).resolve().parent.parent.parent / "web"


@dataclass
class Services:
    """What one app instance owns (``app.state.services``)."""

    cfg: Settings
    hub: TelemetryHub
    station: HandService
    viewer: Any = None  # a Viewer or ViewerProcess (sdh2svc.service.viewer*), when on

    @property
    def viewer_url(self) -> str | None:
        return self.viewer.url if self.viewer is not None else None


class RunRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    params: dict[str, Any] | None = Field(None, description="rolling parameters for this run")
    object: Annotated[str, Field(max_length=64)] | dict[str, Any] | None = Field(
        None, description="in simulation: a preset name or an object spec"
    )


class ObjectRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(
        None, max_length=64, description="a preset: rubber, egg, cylinder, stick62 …"
    )
    spec: dict[str, Any] | None = Field(None, description="an object definition (kind, sizes …)")


class ErrorBody(BaseModel):
    """Every error: a sentence a person can act on, and one line per problem."""

    error: str
    details: list[str]


_WHY = {
    400: "the Host header names another site (without a token: service.allowed_hosts), or a "
    "malformed request",
    401: "missing or wrong bearer token (when service.token is set)",
    403: "cross-origin request from a web page (without a token: service.allowed_origins)",
    404: "no such run, or not in simulation",
    409: "conflicts with the hand's state (a run is running, none is, the hand is opening, the "
    "e-stop is latched)",
    413: "request body larger than service.max_body_kb",
    415: "a request that changes something must say Content-Type: application/json",
    422: "invalid values: one line per bad field, naming the field and its allowed range",
    503: "the hand's links are not up",
}
_READ = (400,)  # every route: the Host rule
_WRITE = (400, 401, 403, 413, 415)  # every mutating route but POST /api/estop
# A mutating route without a body: an empty JSON object, or nothing, with the JSON content type
# (so that Swagger UI's "Try it out" sends the content type the guard asks for)
_EMPTY_BODY = {"requestBody": {"required": False, "content": {"application/json": {
    "schema": {"type": "object", "properties": {}, "additionalProperties": False}}}}}  # fmt: skip


def _responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    return {c: {"model": ErrorBody, "description": _WHY[c]} for c in sorted(set(codes))}


def _error(status: int, message: str, details: list[str] | None = None) -> JSONResponse:
    # the last guard against echoing a long value back (the handlers clip what they quote)
    body = {"error": clip(message, 400), "details": [clip(d, 400) for d in details or []][:50]}
    return JSONResponse(body, status_code=status)


async def open_services(cfg: Settings, where: Where, *, viewer: bool | None = None) -> Services:
    """Open the hand (real, or simulated in this process) and the 3-D view."""
    hub = TelemetryHub(send_timeout_s=cfg.service.send_timeout_s)
    station = HandService(cfg, hub, where)
    services = Services(cfg, hub, station)
    try:
        await station.start()
        if cfg.service.viewer if viewer is None else viewer:
            services.viewer = await _start_viewer(cfg, station, hub)
    except BaseException:
        await close_services(services)
        raise
    return services


async def close_services(services: Services) -> None:
    """Motion first (the station stops the run and releases), then the rest; idempotent."""
    await services.station.close()
    if services.viewer is not None:
        with contextlib.suppress(Exception):
            await services.viewer.stop()
        services.viewer = None


def create_app(services: Services) -> FastAPI:
    """The service's app on opened services; its shutdown closes them (motion first)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        try:
            yield
        finally:
            await close_services(services)

    app = FastAPI(
        title="sdh2svc", version=__version__, lifespan=lifespan,
        description="Tactile in-hand rolling on a SCHUNK SDH2 hand (docs/api.md).",
        docs_url=None, redoc_url=None,
    )  # fmt: skip
    app.state.services = services
    sc = services.cfg.service
    app.add_middleware(Guard, token=sc.token, host=sc.host, allowed_hosts=sc.allowed_hosts,
                       allowed_origins=sc.allowed_origins, max_body_kb=sc.max_body_kb)  # fmt: skip
    _install_errors(app)
    _install_docs(app)
    _install_routes(app, services.cfg)
    static = web_dir()
    if static.is_dir():
        app.mount("/web", StaticFiles(directory=static), name="web")
    return app


def viewer_host(cfg: Settings) -> str:
    """Where the 3-D view listens: loopback unless a token is set (see _start_viewer)."""
    return cfg.service.host if cfg.service.token else "127.0.0.1"


async def _start_viewer(cfg: Settings, station: HandService, hub: TelemetryHub) -> Any:
    """The 3-D view, in a process of its own unless ``service.viewer_process`` is off.

    The view cannot authenticate a browser. Without a token it is a control panel for whoever
    sits at this machine: bound to loopback only (and its WebSocket refuses other sites'
    pages: viewer.start_viser). With a token it listens where the service does, read-only:
    only its E-STOP acts (stopping is always allowed); the rest is the dashboard's, with the
    token."""
    if cfg.service.viewer_process:
        from sdh2svc.service.viewer_proc import ViewerProcess as View
    else:
        from sdh2svc.service.viewer import Viewer as View  # type: ignore[assignment]

    v = View(cfg, host=viewer_host(cfg), port=cfg.service.viser_port,
             on_command=station.command, read_only=bool(cfg.service.token),
             max_hz=cfg.service.viewer_max_hz)  # fmt: skip
    await v.start()
    hub.add_listener(v.handle)
    log.info("3-D view at %s", v.url)
    return v


def _install_errors(app: FastAPI) -> None:
    @app.exception_handler(ServiceError)
    async def _service_error(_: Request, e: ServiceError) -> JSONResponse:
        return _error(e.status, e.message, e.details)

    @app.exception_handler(RequestValidationError)
    async def _validation(_: Request, e: RequestValidationError) -> JSONResponse:
        # never the input itself: only its place and a message, each clipped
        lines = [f"{error_key(err['loc'])}: {error_message(err)}" for err in e.errors()]
        return _error(422, "invalid request", lines)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, e: StarletteHTTPException) -> JSONResponse:
        return _error(e.status_code, str(e.detail))


def _install_docs(app: FastAPI) -> None:
    """``/docs`` (Swagger UI) and ``/redoc`` from packaged files: nothing loads from elsewhere."""
    app.mount(DOCS_ASSETS, StaticFiles(directory=docs_assets_dir()), name="docs-assets")
    favicon = f"{DOCS_ASSETS}/favicon.png"

    @app.get("/docs", include_in_schema=False)
    def swagger() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url="/openapi.json", title="sdh2svc API",
            swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css", swagger_favicon_url=favicon,
            swagger_ui_parameters={"validatorUrl": None},  # no badge from validator.swagger.io
        )  # fmt: skip

    @app.get("/redoc", include_in_schema=False)
    def redoc() -> HTMLResponse:
        return get_redoc_html(openapi_url="/openapi.json", title="sdh2svc API",
                              redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
                              redoc_favicon_url=favicon, with_google_fonts=False)  # fmt: skip


def _services(request: Request) -> Services:
    return request.app.state.services  # type: ignore[no-any-return]


def _station(request: Request) -> HandService:
    return _services(request).station


def _authorised(request: Request) -> None:
    token = _services(request).cfg.service.token
    if not token:
        return
    given = request.headers.get("authorization", "")
    if not secrets.compare_digest(given.encode(), f"Bearer {token}".encode()):
        raise ServiceError(401, "missing or wrong bearer token: send 'Authorization: "
                           "Bearer <token>' (the service's SDH2SVC_SERVICE__TOKEN)")  # fmt: skip


St = Annotated[HandService, Depends(_station)]
Auth = Depends(_authorised)
RunId = Annotated[int, PathParam(ge=1, le=SQL_INT_MAX, description="a run's id (GET /api/runs)")]


def _install_routes(app: FastAPI, cfg: Settings) -> None:
    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        page = web_dir() / "index.html"
        if not page.is_file():
            raise ServiceError(404, f"the dashboard is not installed ({page} missing)")
        return FileResponse(page)

    @app.get("/api/status", responses=_responses(*_READ))
    async def status(st: St) -> JSONResponse:
        return JSONResponse(clean_json(st.status()))

    @app.get("/api/params", responses=_responses(*_READ))
    async def get_params(st: St) -> dict[str, Any]:
        return st.params_in_force.model_dump()

    @app.get("/api/params/schema", responses=_responses(*_READ))
    def params_schema() -> dict[str, Any]:
        return RollingParams.model_json_schema()

    @app.patch("/api/params", dependencies=[Auth], responses=_responses(*_WRITE, 422))
    async def patch_params(st: St, patch: Annotated[dict[str, Any], Body()]) -> dict[str, Any]:
        return st.patch_params(patch).model_dump()

    @app.post("/api/runs", status_code=201, dependencies=[Auth],
              responses=_responses(*_WRITE, 409, 422, 503))  # fmt: skip
    async def start_run(st: St, req: Annotated[RunRequest | None, Body()] = None) -> dict[str, Any]:
        req = req or RunRequest()
        obj = None
        if req.object is not None:
            if st.bench is None:
                raise ServiceError(422, "an object can only be chosen in simulation")
            name, spec = (req.object, None) if isinstance(req.object, str) else (None, req.object)
            obj = parse_object_request(name, spec)
        return st.start_run(req.params, obj)

    @app.post("/api/runs/stop", status_code=202, dependencies=[Auth],
              responses=_responses(*_WRITE, 409), openapi_extra=_EMPTY_BODY)  # fmt: skip
    async def stop_run(st: St) -> dict[str, Any]:
        return st.stop_run()

    @app.get("/api/runs", responses=_responses(*_READ))
    def list_runs() -> list[dict[str, Any]]:
        with _store(cfg) as store:
            return clean_json(store.runs())  # type: ignore[no-any-return]

    @app.get("/api/runs/{run_id}", responses=_responses(*_READ, 404, 422))
    def get_run(run_id: RunId) -> dict[str, Any]:
        with _store(cfg) as store:
            run = _run_or_404(store, run_id)
            run["events"] = store.events(run_id)
            return clean_json(run)  # type: ignore[no-any-return]

    @app.get("/api/runs/{run_id}/samples", responses=_responses(*_READ, 404, 422))
    def samples(
        run_id: RunId,
        offset: Annotated[int, Query(ge=0, le=SQL_INT_MAX)] = 0,
        limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
    ) -> dict[str, Any]:
        with _store(cfg) as store:
            _run_or_404(store, run_id)
            return clean_json({  # type: ignore[no-any-return]
                "run_id": run_id, "offset": offset, "limit": limit,
                "total": store.sample_count(run_id),
                "samples": store.samples(run_id, offset, limit),
            })  # fmt: skip

    @app.get("/api/runs/{run_id}/export", response_class=Response,
             responses={200: {"description": "the run as a file download", "content": {
                 "text/csv": {"schema": {"type": "string"}},
                 "application/octet-stream": {"schema": {"type": "string",
                                                         "format": "binary"}}}},
                        **_responses(*_READ, 404, 422)})  # fmt: skip
    def export(run_id: RunId, format: Literal["csv", "mcap"] = "csv") -> Response:
        with _store(cfg) as store:
            _run_or_404(store, run_id)
            name = f"run-{run_id}.{format}"
            headers = {"Content-Disposition": f'attachment; filename="{name}"'}
            if format == "csv":
                text = io.StringIO()
                store.export_csv(run_id, text)
                return Response(text.getvalue(), media_type="text/csv", headers=headers)
            data = io.BytesIO()
            store.export_mcap(run_id, data)
            return Response(data.getvalue(), media_type="application/octet-stream",
                            headers=headers)  # fmt: skip

    # no token, no Origin or content-type rule (sdh2svc.service.guard): stopping always works
    @app.post("/api/estop", responses=_responses(400, 413, 503), openapi_extra=_EMPTY_BODY)
    async def estop(st: St) -> dict[str, Any]:
        return await st.estop()

    @app.post("/api/estop/release", dependencies=[Auth], responses=_responses(*_WRITE, 503),
              openapi_extra=_EMPTY_BODY)  # fmt: skip
    async def release(st: St) -> dict[str, Any]:
        return await st.release_estop()

    @app.post("/api/hand/open", status_code=202, dependencies=[Auth],
              responses=_responses(*_WRITE, 409, 503), openapi_extra=_EMPTY_BODY)  # fmt: skip
    async def open_hand(st: St) -> dict[str, Any]:
        """Open the fingers to the pre-shape pose, releasing what they hold; answers at once
        (follow ``status.hand.opening``)."""
        return await st.open_hand()

    @app.get("/api/sim/object", responses=_responses(*_READ, 404))
    async def get_object(st: St) -> dict[str, Any]:
        return st.object_info()

    @app.put("/api/sim/object", dependencies=[Auth],
             responses=_responses(*_WRITE, 404, 409, 422))  # fmt: skip
    async def put_object(st: St, req: ObjectRequest) -> dict[str, Any]:
        st.object_info()  # 404 first when not in simulation
        return st.set_object(parse_object_request(req.name, req.spec))

    @app.get("/api/viewer", responses=_responses(*_READ))
    async def viewer(request: Request) -> dict[str, Any]:
        url = _services(request).viewer_url
        if url is not None and cfg.service.host in ("0.0.0.0", "::"):
            # bound to every interface: reachable at whatever host the caller used
            port = url.rsplit(":", 1)[1]
            url = f"{request.url.scheme}://{request.url.hostname}:{port}"
        return {"url": url}

    @app.get("/api/config", responses=_responses(*_READ))
    async def config() -> dict[str, Any]:
        """The effective configuration (hand geometry, axis and matrix maps, limits, safety),
        without the token."""
        data = cfg.model_dump(mode="json")
        data["service"]["token"] = "***" if cfg.service.token else ""
        return data  # type: ignore[no-any-return]

    @app.websocket("/ws/telemetry")
    async def telemetry(
        ws: WebSocket,
        decimate: Annotated[int, Query(ge=1, le=1000)] = 1,
        tactile: Annotated[int, Query(ge=0, le=1)] = 1,
        max_queue: Annotated[int, Query(ge=1, le=100_000)] = 0,
    ) -> None:
        svc: Services = ws.app.state.services
        await ws.accept()
        client = Client(max_queue=max_queue or cfg.service.telemetry_queue,
                        decimate=decimate, tactile=bool(tactile))  # fmt: skip
        client.put(encode({"type": "hello", "status": svc.station.status()}))
        sender = asyncio.create_task(svc.hub.serve(client, ws.send_text))
        receiver = asyncio.create_task(_drain(ws))
        try:
            await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in (sender, receiver):
                task.cancel()
                with contextlib.suppress(BaseException):
                    await task
            with contextlib.suppress(Exception):
                await ws.close()


async def _drain(ws: WebSocket) -> None:
    """Read (and ignore) what the client sends, to notice when it goes away."""
    with contextlib.suppress(WebSocketDisconnect):
        while True:
            msg = await ws.receive()
            if msg["type"] == "websocket.disconnect":
                return


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
