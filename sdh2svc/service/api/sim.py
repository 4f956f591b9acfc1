"""The simulated object (404 on a real hand: the object is whatever it holds)."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field

from sdh2svc.service.api.deps import Auth, St
from sdh2svc.service.api.errors import READ, WRITE, responses
from sdh2svc.service.hand_service import parse_object_request

router = APIRouter()


class ObjectRequest(BaseModel):
    model_config = ConfigDict(extra="forbid")

    name: str | None = Field(
        None, max_length=64, description="a preset: rubber, egg, cylinder, stick62 …"
    )
    spec: dict[str, Any] | None = Field(None, description="an object definition (kind, sizes …)")


@router.get("/api/sim/object", responses=responses(*READ, 404))
async def get_object(st: St) -> dict[str, Any]:
    return st.object_info()


@router.put("/api/sim/object", dependencies=[Auth], responses=responses(*WRITE, 404, 409, 422))
async def put_object(st: St, req: ObjectRequest) -> dict[str, Any]:
    st.object_info()  # 404 first when not in simulation
    return st.set_object(parse_object_request(req.name, req.spec))
