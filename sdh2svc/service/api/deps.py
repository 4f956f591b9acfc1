"""What the routers depend on: the app's :class:`Services` (``app.state.services``), taken
per request through FastAPI dependencies, and the bearer-token check."""

from __future__ import annotations

import secrets
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends
from fastapi import Path as PathParam
from starlette.requests import HTTPConnection

from sdh2svc.config import Settings
from sdh2svc.service.hand_service import HandService, ServiceError
from sdh2svc.service.hub import TelemetryHub

SQL_INT_MAX = 2**63 - 1  # SQLite's largest integer: run ids, sample offsets


@dataclass
class Services:
    """What one app instance owns (``app.state.services``)."""

    cfg: Settings
    hub: TelemetryHub
    station: HandService
    viewer: Any = None  # a Viewer or ViewerProcess (sdh2svc.service.viewer*), when on
    foxglove: Any = None  # the live Foxglove view (sdh2svc.service.foxglove_live), when on

    @property
    def viewer_url(self) -> str | None:
        return self.viewer.url if self.viewer is not None else None


def services(conn: HTTPConnection) -> Services:
    """The app's services, for a request or a WebSocket."""
    return conn.app.state.services  # type: ignore[no-any-return]


def station(conn: HTTPConnection) -> HandService:
    return services(conn).station


def settings(conn: HTTPConnection) -> Settings:
    return services(conn).cfg


def authorised(request: HTTPConnection) -> None:
    token = services(request).cfg.service.token
    if not token:
        return
    given = request.headers.get("authorization", "")
    if not secrets.compare_digest(given.encode(), f"Bearer {token}".encode()):
        raise ServiceError(401, "missing or wrong bearer token: send 'Authorization: "
                           "Bearer <token>' (the service's SDH2SVC_SERVICE__TOKEN)")  # fmt: skip


Svc = Annotated[Services, Depends(services)]
St = Annotated[HandService, Depends(station)]
Cfg = Annotated[Settings, Depends(settings)]
Auth = Depends(authorised)
RunId = Annotated[int, PathParam(ge=1, le=SQL_INT_MAX, description="a run's id (GET /api/runs)")]
