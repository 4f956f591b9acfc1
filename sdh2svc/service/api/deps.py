"""What the routers depend on: the app's :class:`Services` (``app.state.services``), taken
per request through FastAPI dependencies, and the bearer-token check."""

from __future__ import annotations

import json
import re
import secrets
from dataclasses import dataclass, field
from types import UnionType
from typing import Annotated, Any, Union, get_args, get_origin

from fastapi import Depends
from fastapi import Path as PathParam
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from pydantic import BeforeValidator
from pydantic_core import PydanticCustomError
from starlette.requests import HTTPConnection, Request

from sdh2svc.config import Settings
from sdh2svc.service.guard import ESTOP_PATH
from sdh2svc.service.hand_service import HandService, ServiceError
from sdh2svc.service.hub import TelemetryHub
from sdh2svc.service.reads import ReadPool

READ_ROUTES = "sdh2svc.service.api.runs"  # where the read processes' functions are
SQL_INT_MAX = 2**63 - 1  # SQLite's largest integer: run ids, sample offsets


@dataclass
class Services:
    """What one app instance owns (``app.state.services``)."""

    cfg: Settings
    hub: TelemetryHub
    station: HandService
    viewer: Any = None  # a Viewer or ViewerProcess (sdh2svc.service.viewer*), when on
    foxglove: Any = None  # the live Foxglove view (sdh2svc.service.foxglove_live), when on
    # the run database's reads for the API (sdh2svc.service.reads), the read routes' module
    # imported once by the processes' server
    reads: ReadPool = field(default_factory=lambda: ReadPool(preload=(READ_ROUTES,)))

    @property
    def viewer_url(self) -> str | None:
        return self.viewer.url if self.viewer is not None else None


# The dependencies are coroutines: FastAPI runs a plain function in a worker thread, a thread
# hop per request for an attribute read (and, on the fast mode's virtual clock, a wait the
# clock jumps over: a request's answer then depended on the machine's speed).


def _services(conn: HTTPConnection) -> Services:
    return conn.app.state.services  # type: ignore[no-any-return]


async def services(conn: HTTPConnection) -> Services:
    """The app's services, for a request or a WebSocket."""
    return _services(conn)


async def station(conn: HTTPConnection) -> HandService:
    return _services(conn).station


async def settings(conn: HTTPConnection) -> Settings:
    return _services(conn).cfg


async def authorised(request: HTTPConnection) -> None:
    token = _services(request).cfg.service.token
    if not token:
        return
    scheme, _, given = request.headers.get("authorization", "").strip().partition(" ")
    # the scheme's name is case-insensitive (RFC 9110 §11.1), the token is not
    if scheme.lower() != "bearer" or not secrets.compare_digest(given.strip().encode(),
                                                                token.encode()):  # fmt: skip
        raise ServiceError(401, "missing or wrong bearer token: send 'Authorization: "
                           "Bearer <token>' (the service's SDH2SVC_SERVICE__TOKEN)")  # fmt: skip


async def no_body(request: Request) -> None:
    """A command that takes no body takes nothing, or ``{}``: any other body is a 422, so that
    a mistaken one (a speed for *Open hand*, garbage for the release) is never silently
    ignored. (The stops take any body: stopping is never refused.)"""
    raw = await request.body()
    if not raw.strip():
        return
    try:
        value = json.loads(raw)
    except ValueError:  # (also a UnicodeDecodeError)
        value = None
    if value != {}:
        raise ServiceError(422, "invalid request", ["body: this command takes no body: send "
                                                    "nothing, or {}"])  # fmt: skip


async def known_query(conn: HTTPConnection) -> None:
    """An API request or a telemetry socket names only query parameters its route takes, each
    once unless the route takes a list: FastAPI ignores the others, so a misspelt one
    (``?ofset=100``, ``POST /api/runs?cycles=1``, ``/ws/telemetry?tactil=0``) would do the
    default silently, and keeps the last of a repeated one (``?limit=5&limit=500``: 500). (The
    app's dependency, for every route; a socket's handshake is refused with a 422 as for a bad
    value.)"""
    route, path = conn.scope.get("route"), conn.url.path
    http = conn.scope["type"] == "http" and path.startswith("/api/")
    if route is None or not (http or path.startswith("/ws/")):
        return
    if http and path.rstrip("/") == ESTOP_PATH:  # stopping always works (a pendant's ?source=)
        return
    fields = _query_fields(getattr(route, "dependant", None))
    errors = _unknown(conn, fields) + _repeated(conn, fields)
    if not errors:
        return
    # worded as any bad query value is, on a route and on a socket's handshake alike
    raise (RequestValidationError if http else WebSocketRequestValidationError)(errors)


def _unknown(conn: HTTPConnection, fields: dict[str, Any]) -> list[dict[str, Any]]:
    why = f"no such query parameter here (this one takes: {', '.join(sorted(fields)) or 'none'})"
    unknown = sorted(set(conn.query_params) - set(fields))
    return [{"type": "extra_forbidden", "loc": ("query", k), "msg": why,
             "input": conn.query_params[k]} for k in unknown]  # fmt: skip


def _repeated(conn: HTTPConnection, fields: dict[str, Any]) -> list[dict[str, Any]]:
    errors = []
    for name in sorted(set(conn.query_params) & set(fields)):
        given = conn.query_params.getlist(name)
        if len(given) > 1 and not _takes_list(fields[name]):
            why = f"given {len(given)} times; it takes one value"
            errors.append({"type": "repeated", "loc": ("query", name), "msg": why, "input": given})
    return errors


def _takes_list(field: Any) -> bool:
    """A query parameter declared as a list, whose every value FastAPI reads (none is yet)."""
    tp = field.field_info.annotation
    members = get_args(tp) if get_origin(tp) in (Union, UnionType) else (tp,)
    return any((get_origin(m) or m) in (list, set, frozenset, tuple) for m in members)


def _query_fields(dependant: Any) -> dict[str, Any]:
    """The query parameters of a route and its dependencies, by name."""
    if dependant is None:
        return {}
    fields = {p.alias: p for p in dependant.query_params}
    for sub in dependant.dependencies:
        fields |= _query_fields(sub)
    return fields


Svc = Annotated[Services, Depends(services)]
St = Annotated[HandService, Depends(station)]
Cfg = Annotated[Settings, Depends(settings)]
Auth = Depends(authorised)
NoBody = Depends(no_body)  # after Auth: 401 comes before the body's validation


def _digits(v: object) -> object:
    """An integer in a path or query is written in decimal digits: int() would also read
    '1_0' as 10 and ' +1' as 1, another number than the one a caller meant to write."""
    if isinstance(v, str) and not re.fullmatch(r"[0-9]+", v):
        raise PydanticCustomError("digits", "must be a whole number written in digits 0-9")
    return v


Digits = BeforeValidator(_digits)  # after Query()/Path(): their ranges stay in the schema
RunId = Annotated[
    int, PathParam(ge=1, le=SQL_INT_MAX, description="a run's id (GET /api/runs)"), Digits
]
