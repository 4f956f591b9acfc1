"""The hand: its status, and opening it."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from fastapi.responses import JSONResponse

from sdh2svc.model.base import clean_json
from sdh2svc.service.api.body import JsonRoute
from sdh2svc.service.api.deps import Auth, NoBody, St
from sdh2svc.service.api.errors import EMPTY_BODY, READ, WRITE, responses

router = APIRouter(route_class=JsonRoute)


@router.get("/api/status", responses=responses(*READ))
async def status(st: St) -> JSONResponse:
    return JSONResponse(clean_json(st.status()))


@router.post("/api/hand/open", status_code=202, dependencies=[Auth, NoBody],
             responses=responses(*WRITE, 409, 422, 503), openapi_extra=EMPTY_BODY)  # fmt: skip
async def open_hand(st: St) -> dict[str, Any]:
    """Open the fingers to the pre-shape pose, releasing what they hold; answers at once
    (follow ``status.hand.opening``)."""
    return await st.open_hand()
