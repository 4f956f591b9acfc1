"""The rolling parameters (in force, their schema, a patch) and the effective configuration."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body

from sdh2svc.control.safety import params_schema as safety_params_schema
from sdh2svc.service.api.body import JsonRoute
from sdh2svc.service.api.deps import Auth, Cfg, St
from sdh2svc.service.api.errors import READ, WRITE, responses

router = APIRouter(route_class=JsonRoute)


@router.get("/api/params", responses=responses(*READ))
async def get_params(st: St) -> dict[str, Any]:
    return st.params_in_force.model_dump()


@router.get("/api/params/schema", responses=responses(*READ))
def params_schema(cfg: Cfg) -> dict[str, Any]:
    """The parameters' JSON schema, with the ranges this configuration's safety limits allow."""
    return safety_params_schema(cfg.safety, cfg.rolling)


@router.patch("/api/params", dependencies=[Auth], responses=responses(*WRITE, 422))
async def patch_params(st: St, patch: Annotated[dict[str, Any], Body()]) -> dict[str, Any]:
    return st.patch_params(patch).model_dump()


@router.get("/api/config", responses=responses(*READ))
async def config(cfg: Cfg, st: St) -> dict[str, Any]:
    """The effective configuration (hand geometry, axis and matrix maps, limits, safety),
    without the token: the rolling parameters in force and the lines in use (the simulated
    hand's, or --dsa/--sdh), not those the service started with."""
    data = cfg.model_dump(mode="json")
    data["service"]["token"] = "***" if cfg.service.token else ""
    data["rolling"] = st.params_in_force.model_dump(mode="json")
    if st.dsa_url and st.sdh_url:
        data["links"].update(dsa_url=st.dsa_url, sdh_url=st.sdh_url)
    return data
