"""The REST/WebSocket API and the dashboard's files (docs/api.md is the contract).

Reads of the run database happen on worker threads with their own connection, so a large export
never takes time from the control loop; everything that touches the hand goes through the
:class:`~sdh2svc.service.station.Station` on the event loop.
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
from fastapi.exceptions import RequestValidationError
from fastapi.responses import FileResponse, JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from sdh2svc import __version__
from sdh2svc.config import Settings
from sdh2svc.control.params import RollingParams
from sdh2svc.service.hub import Client, TelemetryHub, clean_json, encode
from sdh2svc.service.station import ServiceError, Station, parse_object_request
from sdh2svc.service.store import RunStore

log = logging.getLogger(__name__)


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
    station: Station
    viewer: Any = None  # a Viewer or ViewerProcess (sdh2svc.service.viewer*), when on

    @property
    def viewer_url(self) -> str | None:
        return self.viewer.url if self.viewer is not None else None


class RunRequest(BaseModel):
    params: dict[str, Any] | None = Field(None, description="rolling parameters for this run")
    object: str | dict[str, Any] | None = Field(
        None, description="in simulation: a preset name or an object spec"
    )


class ObjectRequest(BaseModel):
    name: str | None = Field(None, description="a preset: rubber, egg, cylinder, stick62 …")
    spec: dict[str, Any] | None = Field(None, description="an object definition (kind, sizes …)")


def _error(status: int, message: str, details: list[str] | None = None) -> JSONResponse:
    return JSONResponse({"error": message, "details": details or []}, status_code=status)


async def open_services(
    cfg: Settings,
    *,
    sim: bool,
    dsa_url: str | None = None,
    sdh_url: str | None = None,
    obj: Any = None,
    viewer: bool | None = None,
) -> Services:
    """Open the hand (both links, or the embedded simulated hand) and the 3-D view."""
    hub = TelemetryHub(send_timeout_s=cfg.service.send_timeout_s)
    station = Station(cfg, hub, sim=sim, dsa_url=dsa_url, sdh_url=sdh_url, obj=obj)
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
    )  # fmt: skip
    app.state.services = services
    _install_errors(app)
    _install_routes(app, services.cfg)
    static = web_dir()
    if static.is_dir():
        app.mount("/web", StaticFiles(directory=static), name="web")
    return app


async def _start_viewer(cfg: Settings, station: Station, hub: TelemetryHub) -> Any:
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

    token = bool(cfg.service.token)
    v = View(cfg, host=cfg.service.host if token else "127.0.0.1", port=cfg.service.viser_port,
             on_command=station.command, read_only=token,
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
        lines = [f"{'.'.join(str(p) for p in err['loc'])}: {err['msg']}" for err in e.errors()]
        return _error(422, "invalid request", lines)

    @app.exception_handler(StarletteHTTPException)
    async def _http(_: Request, e: StarletteHTTPException) -> JSONResponse:
        return _error(e.status_code, str(e.detail))


def _services(request: Request) -> Services:
    return request.app.state.services  # type: ignore[no-any-return]


def _station(request: Request) -> Station:
    return _services(request).station


def _authorised(request: Request) -> None:
    token = _services(request).cfg.service.token
    if not token:
        return
    given = request.headers.get("authorization", "")
    if not secrets.compare_digest(given.encode(), f"Bearer {token}".encode()):
        raise ServiceError(401, "missing or wrong bearer token: send 'Authorization: "
                           "Bearer <token>' (the service's SDH2SVC_SERVICE__TOKEN)")  # fmt: skip


St = Annotated[Station, Depends(_station)]
Auth = Depends(_authorised)


def _install_routes(app: FastAPI, cfg: Settings) -> None:
    @app.get("/", include_in_schema=False)
    def index() -> FileResponse:
        page = web_dir() / "index.html"
        if not page.is_file():
            raise ServiceError(404, f"the dashboard is not installed ({page} missing)")
        return FileResponse(page)

    @app.get("/api/status")
    async def status(st: St) -> JSONResponse:
        return JSONResponse(clean_json(st.status()))

    @app.get("/api/params")
    async def get_params(st: St) -> dict[str, Any]:
        return st.params_in_force.model_dump()

    @app.get("/api/params/schema")
    def params_schema() -> dict[str, Any]:
        return RollingParams.model_json_schema()

    @app.patch("/api/params", dependencies=[Auth])
    async def patch_params(st: St, patch: Annotated[dict[str, Any], Body()]) -> dict[str, Any]:
        return st.patch_params(patch).model_dump()

    @app.post("/api/runs", status_code=201, dependencies=[Auth])
    async def start_run(st: St, req: Annotated[RunRequest | None, Body()] = None) -> dict[str, Any]:
        req = req or RunRequest()
        obj = None
        if req.object is not None:
            if not st.sim:
                raise ServiceError(422, "an object can only be chosen in simulation")
            name, spec = (req.object, None) if isinstance(req.object, str) else (None, req.object)
            obj = parse_object_request(name, spec)
        return st.start_run(req.params, obj)

    @app.post("/api/runs/stop", status_code=202, dependencies=[Auth])
    async def stop_run(st: St) -> dict[str, Any]:
        return st.stop_run()

    @app.get("/api/runs")
    def list_runs() -> list[dict[str, Any]]:
        with _store(cfg) as store:
            return clean_json(store.runs())  # type: ignore[no-any-return]

    @app.get("/api/runs/{run_id}")
    def get_run(run_id: int) -> dict[str, Any]:
        with _store(cfg) as store:
            run = _run_or_404(store, run_id)
            run["events"] = store.events(run_id)
            return clean_json(run)  # type: ignore[no-any-return]

    @app.get("/api/runs/{run_id}/samples")
    def samples(
        run_id: int,
        offset: Annotated[int, Query(ge=0)] = 0,
        limit: Annotated[int, Query(ge=1, le=10_000)] = 1000,
    ) -> dict[str, Any]:
        with _store(cfg) as store:
            _run_or_404(store, run_id)
            return clean_json({  # type: ignore[no-any-return]
                "run_id": run_id, "offset": offset, "limit": limit,
                "total": store.sample_count(run_id),
                "samples": store.samples(run_id, offset, limit),
            })  # fmt: skip

    @app.get("/api/runs/{run_id}/export")
    def export(run_id: int, format: Literal["csv", "mcap"] = "csv") -> Response:
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

    @app.post("/api/estop", dependencies=[Auth])
    async def estop(st: St) -> dict[str, Any]:
        return await st.estop()

    @app.post("/api/estop/release", dependencies=[Auth])
    async def release(st: St) -> dict[str, Any]:
        return await st.release_estop()

    @app.get("/api/sim/object")
    async def get_object(st: St) -> dict[str, Any]:
        return st.object_info()

    @app.put("/api/sim/object", dependencies=[Auth])
    async def put_object(st: St, req: ObjectRequest) -> dict[str, Any]:
        st.object_info()  # 404 first when not in simulation
        return st.set_object(parse_object_request(req.name, req.spec))

    @app.get("/api/viewer")
    async def viewer(request: Request) -> dict[str, Any]:
        url = _services(request).viewer_url
        if url is not None and cfg.service.host in ("0.0.0.0", "::"):
            # bound to every interface: reachable at whatever host the caller used
            port = url.rsplit(":", 1)[1]
            url = f"{request.url.scheme}://{request.url.hostname}:{port}"
        return {"url": url}

    @app.get("/api/config")
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
