"""The e-stop: latching it (no token, no Origin or content-type rule: stopping always works,
sdh2svc.service.guard) and releasing it (with the token)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter

from sdh2svc.service.api.body import JsonRoute
from sdh2svc.service.api.deps import Auth, NoBody, St
from sdh2svc.service.api.errors import EMPTY_BODY, WRITE, responses

router = APIRouter(route_class=JsonRoute)


@router.post("/api/estop", responses=responses(400, 413, 503), openapi_extra=EMPTY_BODY)
@router.post("/api/estop/", include_in_schema=False)  # answered, not redirected: stop now
async def estop(st: St) -> dict[str, Any]:
    return await st.estop()


@router.post("/api/estop/release", dependencies=[Auth, NoBody],
             responses=responses(*WRITE, 409, 422, 503),
             openapi_extra=EMPTY_BODY)  # fmt: skip
async def release(st: St) -> dict[str, Any]:
    return await st.release_estop()
