"""The telemetry hub: one publisher (the service), many readers (WebSocket clients, the 3-D view).

``publish`` runs on the control loop's path, so it only encodes once and appends to bounded
per-client queues; each client has its own sender task with a send timeout. A slow or stalled
client loses its oldest messages (counted) and, past the timeout, its connection — never the
loop's time or another client's messages.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import math
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

log = logging.getLogger(__name__)

Listener = Callable[[dict[str, Any]], None]
Send = Callable[[str], Awaitable[None]]


def clean_json(obj: Any) -> Any:
    """JSON has no NaN or infinity: send null (the dashboard treats it as a gap)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: clean_json(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [clean_json(v) for v in obj]
    return obj


def encode(msg: dict[str, Any]) -> str:
    try:
        return json.dumps(msg, allow_nan=False, separators=(",", ":"))
    except ValueError:
        return json.dumps(clean_json(msg), allow_nan=False, separators=(",", ":"))


@dataclass(eq=False)
class Client:
    """One WebSocket reader: what it wants and what it has lost."""

    max_queue: int = 256
    decimate: int = 1  # every n-th sample
    tactile: bool = True
    queue: deque[str] = field(init=False)
    dropped: int = 0
    sent: int = 0
    _samples_seen: int = 0
    _wake: asyncio.Event = field(default_factory=asyncio.Event)
    _reported_drops: int = 0

    def __post_init__(self) -> None:
        self.queue = deque(maxlen=self.max_queue)

    def wants(self, kind: str) -> bool:
        if kind == "tactile":
            return self.tactile
        if kind == "sample":
            self._samples_seen += 1
            return (self._samples_seen - 1) % self.decimate == 0
        return True

    def put(self, text: str) -> None:
        if len(self.queue) == self.queue.maxlen:
            self.dropped += 1  # deque drops the oldest on append
        self.queue.append(text)
        self._wake.set()


class TelemetryHub:
    """Fan-out of telemetry messages (dicts with a ``type``, docs/api.md) to clients, listeners."""

    def __init__(self, *, send_timeout_s: float = 2.0) -> None:
        self.send_timeout_s = send_timeout_s
        self.clients: set[Client] = set()
        self._listeners: list[Listener] = []
        self.published = 0
        self.disconnected_slow = 0

    def add_listener(self, listener: Listener) -> None:
        """In-process readers (the 3-D view); called with the dict, must return quickly."""
        self._listeners.append(listener)

    @property
    def has_listeners(self) -> bool:
        return bool(self._listeners)

    def publish(self, msg: dict[str, Any]) -> None:
        self.published += 1
        for listener in self._listeners:
            try:
                listener(msg)
            except Exception:  # a broken view must not break the control loop
                log.exception("telemetry listener failed")
        kind = msg["type"]
        takers = [c for c in self.clients if c.wants(kind)]
        if takers:
            text = encode(msg)
            for c in takers:
                c.put(text)

    async def serve(self, client: Client, send: Send) -> None:
        """Send ``client`` its messages until the connection fails or stalls past the timeout."""
        self.clients.add(client)
        try:
            while True:
                await client._wake.wait()
                client._wake.clear()
                while client.queue:
                    text = client.queue.popleft()
                    if client.dropped != client._reported_drops:
                        client._reported_drops = client.dropped
                        notice = encode({"type": "dropped", "count": client.dropped})
                        if not await self._send(client, send, notice):
                            return
                    if not await self._send(client, send, text):
                        return
        finally:
            self.clients.discard(client)

    async def _send(self, client: Client, send: Send, text: str) -> bool:
        try:
            await asyncio.wait_for(send(text), self.send_timeout_s)
        except TimeoutError:
            self.disconnected_slow += 1
            log.warning("telemetry client stalled for %.1f s: disconnected (dropped %d)",
                        self.send_timeout_s, client.dropped)  # fmt: skip
            return False
        client.sent += 1
        return True

    def stats(self) -> dict[str, Any]:
        return {
            "clients": len(self.clients),
            "dropped": sum(c.dropped for c in self.clients),
            "disconnected_slow": self.disconnected_slow,
        }


async def cancel(task: asyncio.Task[Any] | None) -> None:
    if task is not None and not task.done():
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError, Exception):
            await task
