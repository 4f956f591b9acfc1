"""The simulated hand's surroundings: its object, a person's press on a pad (404 on a real hand:
the object is whatever it holds, its pads are pressed by hand)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter
from pydantic import BaseModel, ConfigDict, Field
from pydantic.json_schema import SkipJsonSchema

from sdh2svc.service.api.body import JsonRoute, not_null
from sdh2svc.service.api.deps import Auth, NoBody, St
from sdh2svc.service.api.errors import EMPTY_BODY, READ, WRITE, responses
from sdh2svc.service.hand_service import parse_object_request
from sdh2svc.sim.press import Press

router = APIRouter(route_class=JsonRoute)


class ObjectRequest(BaseModel):
    """A preset by its name, or an object spec: one of the keys, the other left out (not sent
    as null)."""

    model_config = ConfigDict(extra="forbid")

    name: Annotated[str | SkipJsonSchema[None], not_null("a preset name", str)] = Field(
        None, max_length=64, description="a preset: rubber, egg, cylinder, stick62 …"
    )
    spec: Annotated[dict[str, Any] | SkipJsonSchema[None], not_null("an object spec", dict)] = (
        Field(None, description="an object definition (kind, sizes …)")
    )


@router.get("/api/sim/object", responses=responses(*READ, 404))
async def get_object(st: St) -> dict[str, Any]:
    return st.object_info()


@router.put("/api/sim/object", dependencies=[Auth], responses=responses(*WRITE, 404, 409, 422))
async def put_object(st: St, req: ObjectRequest) -> dict[str, Any]:
    st.object_info()  # 404 first when not in simulation
    return st.set_object(parse_object_request(req.name, req.spec))


@router.post(
    "/api/sim/press", status_code=202, dependencies=[Auth], responses=responses(*WRITE, 404, 422)
)
async def press(st: St, req: Press) -> dict[str, Any]:
    """Press a pad as a person would, starting now: matrix ``pad``, centre (``x_mm`` across from
    column 0, ``y_mm`` along from row 0), ``force_n`` over a disc of ``radius_mm`` for
    ``duration_s``. Answers the accepted press; the next tactile frames read it."""
    return st.press(req)


@router.delete(
    "/api/sim/press",
    dependencies=[Auth, NoBody],
    responses=responses(*WRITE, 404, 422),
    openapi_extra=EMPTY_BODY,
)
async def release(st: St) -> dict[str, int]:
    """Lift every press that is on now (a person takes the finger away)."""
    return st.release_presses()
