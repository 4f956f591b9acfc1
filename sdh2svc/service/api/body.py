"""JSON request bodies, read strictly: what FastAPI and pydantic would read as something else is
a 422 naming it (docs/api.md, *Errors*).

* A key given twice, at any depth: ``json.loads`` keeps the last one silently, so that
  ``{"grasp_force": 1, "grasp_force": 40}`` grasped at 40.
* A body of ``null``: FastAPI reads it as no body, so that ``POST /api/runs``, whose body is
  optional, started a run with the defaults.
* ``null`` for an optional key (:func:`not_null`): pydantic reads it as the key left out, so
  that ``{"params": null}`` started a run with the parameters in force.

Every API router reads its routes' bodies through :class:`JsonRoute`; a route without a body
(the stops, the commands that take none) never decodes one."""

from __future__ import annotations

import asyncio
import json
import re
from collections.abc import Callable, Coroutine
from typing import Any

from fastapi import Request, Response
from fastapi.routing import APIRoute
from pydantic import BeforeValidator
from pydantic_core import PydanticCustomError
from starlette.exceptions import HTTPException

from sdh2svc.config import clip, error_key

# A larger body is decoded on a worker thread: the object hook runs Python per object, and the
# event loop is the control loop's (1 MB of small objects held it ≈ 100 ms inline, ≈ 15 ms at
# most from a thread, which hands the GIL back at each switch interval).
THREAD_ABOVE_B = 64 * 1024


class BodyRefused(HTTPException):
    """A body refused while FastAPI reads it, where it passes on an HTTPException only (any
    other error there is its 400 "There was an error parsing the body", which cannot say
    why)."""

    def __init__(
        self, details: list[str], status: int = 422, message: str = "invalid request"
    ) -> None:
        super().__init__(status, message)
        self.details = details


UNREADABLE = "the body is no JSON this service can read"
_DIGITS = re.compile(r"value has (\d+) digits")


class _Repeated(dict[str, Any]):
    """A decoded object in which some key came more than once (the last value kept)."""

    def __init__(self, pairs: list[tuple[str, Any]]) -> None:
        super().__init__(pairs)
        counts: dict[str, int] = {}
        for key, _ in pairs:
            counts[key] = counts.get(key, 0) + 1
        self.repeated = [k for k, n in counts.items() if n > 1]


def decode(raw: bytes) -> Any:
    """``raw`` as JSON (its errors as ``json.loads``'s); :class:`BodyRefused` if it is null or
    an object in it repeats a key."""
    repeated = False

    def pairs(items: list[tuple[str, Any]]) -> dict[str, Any]:
        nonlocal repeated
        obj = dict(items)
        if len(obj) == len(items):
            return obj
        repeated = True
        return _Repeated(items)

    try:
        value = json.loads(raw, object_pairs_hook=pairs)
    except json.JSONDecodeError:
        raise  # FastAPI's "not JSON", with where it breaks (errors.py)
    except (ValueError, RecursionError) as e:
        why, detail = _unreadable(e)
        raise BodyRefused([detail], 400, f"{UNREADABLE}: {why}" if why else UNREADABLE) from None
    if value is None:
        raise BodyRefused(["body: must be a JSON object, not null"])
    if repeated:
        raise BodyRefused(_repeated_lines(value))
    return value


def _unreadable(e: ValueError | RecursionError) -> tuple[str, str]:
    """Why ``json.loads`` gave up on a body for a reason other than its syntax, and the detail."""
    if isinstance(e, UnicodeDecodeError):
        byte = e.object[e.start : e.start + 1].hex()
        return "not UTF-8", f"byte {e.start} (0x{byte}) is not {e.encoding.upper()}"
    if isinstance(e, RecursionError):
        return "nested too deep", "arrays and objects nested deeper than the decoder goes"
    if digits := _DIGITS.search(str(e)):  # Python's limit on an integer's digits
        return "a number of over 4300 digits", f"a number of {digits[1]} digits"
    return "", clip(str(e))


def _repeated_lines(value: Any) -> list[str]:
    """``body.params.k: …`` for each repeated key, in the body's order (a loop, not recursion:
    the body may be nested as deep as ``json.loads`` reads)."""
    lines: list[str] = []
    stack: list[tuple[tuple[int | str, ...], Any]] = [(("body",), value)]
    while stack:
        loc, v = stack.pop()
        if isinstance(v, _Repeated):
            lines += [f"{error_key((*loc, k))}: the key is given more than once (JSON would "
                      "silently keep the last)" for k in v.repeated]  # fmt: skip
        items = v.items() if isinstance(v, dict) else enumerate(v) if isinstance(v, list) else ()
        stack += reversed([((*loc, k), child) for k, child in items])
    return lines


class JsonRequest(Request):
    """A request whose ``json()`` (FastAPI's one read of a route's body) is :func:`decode`."""

    async def json(self) -> Any:
        raw = await self.body()
        return await asyncio.to_thread(decode, raw) if len(raw) > THREAD_ABOVE_B else decode(raw)


class JsonRoute(APIRoute):
    """An API route whose JSON body is read by :func:`decode`."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handle = super().get_route_handler()

        async def strict(request: Request) -> Response:
            return await handle(JsonRequest(request.scope, request.receive))

        return strict


def not_null(what: str, *takes: type) -> BeforeValidator:
    """An optional key's validator: a null is refused as not ``what`` the key takes (pydantic
    would read it as the key left out), and so is a value of none of the JSON types ``takes``
    (one line, not one per branch of a union in pydantic's own names). Its default, the key
    left out, is not validated."""

    def refuse(value: object) -> object:
        if value is None:
            raise PydanticCustomError(
                "not_null", f"must be {what}, not null (leave the key out for its default)"
            )
        if takes and (isinstance(value, bool) or not isinstance(value, takes)):
            raise PydanticCustomError("wrong_type", f"must be {what}, not {_kind(value)}")
        return value

    return BeforeValidator(refuse)


def _kind(value: object) -> str:
    """What a JSON value is, in JSON's words."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, float)):
        return "a number"
    if isinstance(value, str):
        return "a string"
    if isinstance(value, list):
        return "an array"
    return "an object" if isinstance(value, dict) else type(value).__name__
