"""Telemetry's ways out: the WebSocket (``/ws/telemetry``) and where the 3-D view is served."""

from __future__ import annotations

import asyncio
import contextlib
from typing import Annotated, Any

from fastapi import APIRouter, Query, Request, WebSocket, WebSocketDisconnect

from sdh2svc.service.api.body import JsonRoute
from sdh2svc.service.api.deps import Digits, Svc
from sdh2svc.service.api.errors import READ, responses
from sdh2svc.service.hub import Client
from sdh2svc.service.telemetry import Hello, encode

router = APIRouter(route_class=JsonRoute)


@router.get("/api/viewer", responses=responses(*READ))
async def viewer(request: Request, svc: Svc) -> dict[str, Any]:
    url = svc.viewer_url
    if url is not None and svc.cfg.service.host in ("0.0.0.0", "::"):
        # bound to every interface: reachable at whatever host the caller used
        port = url.rsplit(":", 1)[1]
        url = f"{request.url.scheme}://{request.url.hostname}:{port}"
    return {"url": url}


@router.websocket("/ws/telemetry")
async def telemetry(
    ws: WebSocket,
    svc: Svc,
    decimate: Annotated[int, Query(ge=1, le=1000), Digits] = 1,
    tactile: Annotated[int, Query(ge=0, le=1), Digits] = 1,
    max_queue: Annotated[int, Query(ge=1, le=100_000), Digits] = 0,
) -> None:
    await ws.accept()
    client = Client(max_queue=max_queue or svc.cfg.service.telemetry_queue,
                    decimate=decimate, tactile=bool(tactile))  # fmt: skip
    client.put(encode(Hello(svc.station.status())))
    sender = asyncio.create_task(svc.hub.serve(client, ws.send_text))
    receiver = asyncio.create_task(_drain(ws))
    slow: str | None = None
    try:
        await asyncio.wait({sender, receiver}, return_when=asyncio.FIRST_COMPLETED)
        if sender.done() and not sender.cancelled() and sender.exception() is None:
            slow = sender.result()
    finally:
        for task in (sender, receiver):
            task.cancel()
            with contextlib.suppress(BaseException):
                await task
        with contextlib.suppress(Exception):
            # a client cut off for being slow is told so (docs/api.md), not closed as normal
            await (ws.close() if slow is None else ws.close(SLOW_CLOSE, slow[:MAX_REASON]))


SLOW_CLOSE = 1008  # the close code for a client cut off because it took no message in time
MAX_REASON = 120  # a close reason's length at most (RFC 6455: 123 bytes of UTF-8)


async def _drain(ws: WebSocket) -> None:
    """Read (and ignore) what the client sends, to notice when it goes away."""
    with contextlib.suppress(WebSocketDisconnect):
        while True:
            msg = await ws.receive()
            if msg["type"] == "websocket.disconnect":
                return
