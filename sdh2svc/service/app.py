"""The service's app: opens the services and assembles the API's rooms (docs/api.md is the
contract; the routers are in :mod:`sdh2svc.service.api`).

Everything that touches the hand goes through the
:class:`~sdh2svc.service.hand_service.HandService` on the event loop. Before any route, the
:class:`~sdh2svc.service.guard.Guard` decides which requests get in at all (Host, Origin, content
type, body size); the token is checked per route
(``Auth``), and not for the e-stop.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI

from sdh2svc import __version__
from sdh2svc.config import Settings
from sdh2svc.connect import Where
from sdh2svc.service.api import dashboard, estop, hand, params, runs, sim, telemetry
from sdh2svc.service.api.dashboard import docs_assets_dir, web_dir
from sdh2svc.service.api.deps import Services, known_query
from sdh2svc.service.api.errors import install_errors
from sdh2svc.service.foxglove_live import FoxgloveLive
from sdh2svc.service.guard import Guard
from sdh2svc.service.hand_service import HandService
from sdh2svc.service.hub import TelemetryHub

__all__ = ["Services", "close_services", "create_app", "docs_assets_dir", "open_services",
           "viewer_host", "web_dir"]  # fmt: skip

log = logging.getLogger(__name__)

# The rooms, in the order their routes are matched and documented.
ROUTERS = (dashboard.router, hand.router, params.router, runs.router, estop.router,
           sim.router, telemetry.router)  # fmt: skip


async def open_services(cfg: Settings, where: Where, *, viewer: bool | None = None) -> Services:
    """Open the hand (real, or simulated in this process) and the 3-D view."""
    hub = TelemetryHub(send_timeout_s=cfg.service.send_timeout_s)
    station = HandService(cfg, hub, where)
    services = Services(cfg, hub, station)
    try:
        await station.start()
        if cfg.service.viewer if viewer is None else viewer:
            services.viewer = await _start_viewer(cfg, station, hub)
            station.view_served = lambda: services.viewer_url is not None
        if cfg.service.foxglove_port:
            services.foxglove = _start_foxglove(cfg, hub)
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
    if services.foxglove is not None:
        services.foxglove.stop()
        services.foxglove = None
    services.reads.close()


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
        docs_url=None, redoc_url=None, dependencies=[Depends(known_query)],
    )  # fmt: skip
    app.state.services = services
    sc = services.cfg.service
    app.add_middleware(Guard, token=sc.token, host=sc.host, allowed_hosts=sc.allowed_hosts,
                       allowed_origins=sc.allowed_origins, max_body_kb=sc.max_body_kb)  # fmt: skip
    install_errors(app)
    dashboard.mount_files(app)
    for router in ROUTERS:
        app.include_router(router)
    return app


def viewer_host(cfg: Settings) -> str:
    """Where the 3-D view (and the live Foxglove view) listens: loopback unless a token is set
    (see _start_viewer)."""
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


def _start_foxglove(cfg: Settings, hub: TelemetryHub) -> FoxgloveLive:
    """The live Foxglove view (read-only), bound like the 3-D view: loopback without a token."""
    sc = cfg.service
    fox = FoxgloveLive(cfg, host=viewer_host(cfg), port=sc.foxglove_port, max_hz=sc.viewer_max_hz)
    fox.start()
    hub.add_listener(fox.handle)
    log.info("Foxglove live view at %s", fox.url)
    return fox
