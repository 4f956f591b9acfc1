"""Every error as one body (a sentence a person can act on, one line per problem), the handlers
that produce it, and the documentation of each status the routes may answer."""

from __future__ import annotations

from typing import Any

from fastapi import FastAPI, Request, WebSocket
from fastapi.exceptions import RequestValidationError, WebSocketRequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel
from starlette.exceptions import HTTPException as StarletteHTTPException

from sdh2svc.config import clip, error_key, error_message, model_keys, shown, unknown_key
from sdh2svc.service.api.body import UNREADABLE, BodyRefused
from sdh2svc.service.guard import error_content
from sdh2svc.service.hand_service import ServiceError


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
    "e-stop is latched or came during its release, the 3-D view is off), or a run this version "
    "cannot read or that is being recorded",
    413: "request body larger than service.max_body_kb",
    415: "a request that changes something must say Content-Type: application/json",
    422: "invalid values: one line per bad field, naming the field and its allowed range (also "
    "null for an object, a body's key or a query parameter given twice)",
    503: "the hand's links are not up, the run database cannot be read or did not take a write "
    "(another program holding it locked), or the service is shutting down",
}


def _line(err: Any, msg: str) -> str:
    """``query.limit = 0: Input should be greater than or equal to 1``: the field, the value as
    given (a scalar, clipped; a missing one or a whole object is not quoted), the message."""
    value = err.get("input")
    quoted = err["type"] != "missing" and isinstance(value, (str, int, float, bool))
    return f"{error_key(err['loc'])}{f' = {shown(value)}' if quoted else ''}: {msg}"


def _where_it_breaks(err: Any, text: Any) -> str:
    """``Expecting value at character 12 (line 2, column 3)``: the JSON error and where (its
    message alone does not say; FastAPI keeps the character in the error's location)."""
    why = str((err.get("ctx") or {}).get("error") or "JSON decode error")
    pos = err["loc"][-1] if len(err["loc"]) > 1 else None
    if not isinstance(pos, int):
        return clip(why)
    where = f"{why} at character {pos}"
    if isinstance(text, str) and 0 <= pos <= len(text):
        line, column = text.count("\n", 0, pos) + 1, pos - text.rfind("\n", 0, pos)
        where += f" (line {line}, column {column})"
    return clip(where)


_UNPARSED = "There was an error parsing the body"  # FastAPI's detail, not a JSONDecodeError
READ = (400, 422)  # every route: the Host rule; an unknown or repeated query parameter
WRITE = (*READ, 401, 403, 413, 415)  # every mutating route but POST /api/estop
# A mutating route without a body: an empty JSON object, or nothing, with the JSON content type
# (so that Swagger UI's "Try it out" sends the content type the guard asks for)
EMPTY_BODY: dict[str, Any] = {
    "requestBody": {
        "required": False,
        "content": {
            "application/json": {
                "schema": {"type": "object", "properties": {}, "additionalProperties": False}
            }
        },
    }
}


def responses(*codes: int) -> dict[int | str, dict[str, Any]]:
    """The OpenAPI ``responses`` of a route that may answer ``codes``."""
    return {c: {"model": ErrorBody, "description": _WHY[c]} for c in sorted(set(codes))}


def error(status: int, message: str, details: list[str] | None = None) -> JSONResponse:
    return JSONResponse(error_content(message, details or []), status_code=status)


def _body_keys(request: Request) -> list[str] | None:
    """The top-level keys of the route's JSON body model (None if it has none)."""
    field = getattr(request.scope.get("route"), "body_field", None)
    return model_keys(getattr(getattr(field, "field_info", None), "annotation", None))


def install_errors(app: FastAPI) -> None:
    @app.exception_handler(ServiceError)
    async def _service_error(_: Request, e: ServiceError) -> JSONResponse:
        return error(e.status, e.message, e.details)

    @app.exception_handler(BodyRefused)
    async def _body_refused(_: Request, e: BodyRefused) -> JSONResponse:
        return error(e.status_code, str(e.detail), e.details)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, e: RequestValidationError) -> JSONResponse:
        errors = e.errors()
        if bad_json := [err for err in errors if err["type"] == "json_invalid"]:
            return error(400, "the body is not JSON", [_where_it_breaks(bad_json[0], e.body)])
        lines = []
        for err in errors:
            msg, loc = error_message(err), tuple(err["loc"])
            if err["type"] == "extra_forbidden" and len(loc) == 2 and loc[0] == "body":
                msg = unknown_key(_body_keys(request))  # (a query's says what it takes)
            lines.append(_line(err, msg))
        return error(422, "invalid request", lines)

    @app.exception_handler(WebSocketRequestValidationError)
    async def _ws_validation(ws: WebSocket, e: WebSocketRequestValidationError) -> None:
        # a bad query value refuses the handshake like a bad REST value: a 422 naming it (not
        # the bare 403 a close before accept makes, which reads as an Origin problem)
        lines = [_line(err, error_message(err)) for err in e.errors()]
        if "websocket.http.response" in ws.scope.get("extensions", {}):
            await ws.send_denial_response(error(422, "invalid request", lines))
        else:
            reason = clip("invalid request: " + "; ".join(lines), 100).encode()[:120]
            await ws.close(code=1008, reason=reason.decode(errors="ignore"))

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, e: StarletteHTTPException) -> JSONResponse:
        if e.status_code == 400 and e.detail == _UNPARSED:  # (body.decode names the cause)
            return error(400, f"{UNREADABLE}: text that is not UTF-8, a number of over 4300 "
                         "digits, or arrays and objects nested too deep")  # fmt: skip
        said = f"{request.method} {clip(request.url.path, 80)}"
        if e.status_code == 405:  # the router's: the path is a route, not for this method
            allow = (e.headers or {}).get("Allow", "")
            answer = error(405, f"{said}: this route takes {allow or 'other methods'}")
            if allow:
                answer.headers["Allow"] = allow  # (RFC 9110: a 405 says which it takes)
            return answer
        if e.status_code == 404 and e.detail == "Not Found":  # the router's: no such route
            return error(404, f"{said}: no such route (the API's routes: /docs)")
        return error(e.status_code, str(e.detail))
