"""The telemetry hub: one publisher (the service), many readers (WebSocket clients, the 3-D view).

``publish`` runs on the control loop's path (a tactile frame arrives, the runner records its
iteration), so it only appends the message to a pending list. Everything else — the listeners
(the 3-D view), encoding each message once, filling the per-client queues and waking the client
senders — happens in :meth:`TelemetryHub.flush`, scheduled for when the loop has time: right after
a ``sample`` (the iteration's joint command is out; the next frame is a frame period away), or,
when no run iteration follows, after a short hold. The runner's next step never queues behind
telemetry that a frame's arrival set off.

Each client has a bounded queue and its own sender task with a send timeout: a slow or stalled
client loses its oldest messages (counted) and, past the timeout, its connection — never the
loop's time or another client's messages.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from sdh2svc.model.base import clean_json
from sdh2svc.service.telemetry import AnyMessage, Dropped, encode, kind_of

__all__ = ["Client", "Listener", "TelemetryHub", "cancel", "clean_json", "encode"]

log = logging.getLogger(__name__)

Listener = Callable[[AnyMessage], None]
Send = Callable[[str], Awaitable[None]]

HOLD_S = 0.012  # no run iteration under way: deliver this long after the first pending message
SAMPLE_WAIT_S = 0.030  # samples flowing (rolling): wait this long at most for the iteration's end
ROLLING_GAP_S = 0.2  # a sample this recently: a run is rolling, the next sample will come


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
    """Fan-out of telemetry messages (:mod:`sdh2svc.service.telemetry`; during the transition
    also their JSON form as dicts) to clients and listeners."""

    def __init__(self, *, send_timeout_s: float = 2.0) -> None:
        self.send_timeout_s = send_timeout_s
        self.clients: set[Client] = set()
        self._listeners: list[Listener] = []
        self._pending: list[AnyMessage] = []
        self._flush_at: asyncio.Handle | None = None
        self._last_sample = -math.inf
        self.published = 0
        self.disconnected_slow = 0

    def add_listener(self, listener: Listener) -> None:
        """In-process readers (the 3-D view); called with the message as published, at flush
        time; must return quickly."""
        self._listeners.append(listener)

    @property
    def has_listeners(self) -> bool:
        return bool(self._listeners)

    def publish(self, msg: AnyMessage) -> None:
        """Queue ``msg`` for delivery: O(1) here, the work is done by :meth:`flush`."""
        self.published += 1
        self._pending.append(msg)
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError:  # no event loop (scripts, tests): deliver at once
            self.flush()
            return
        now = loop.time()
        if kind_of(msg) == "sample":  # the end of an iteration: the loop is free now
            self._last_sample = now
            self._schedule(loop, None)
        elif self._flush_at is None:
            rolling = now - self._last_sample < ROLLING_GAP_S
            self._schedule(loop, SAMPLE_WAIT_S if rolling else HOLD_S)

    def _schedule(self, loop: asyncio.AbstractEventLoop, delay: float | None) -> None:
        if delay is None:
            if isinstance(self._flush_at, asyncio.TimerHandle):
                self._flush_at.cancel()
            elif self._flush_at is not None:
                return  # already due on the next loop turn
            self._flush_at = loop.call_soon(self.flush)
        else:
            self._flush_at = loop.call_later(delay, self.flush)

    def flush(self) -> None:
        """Deliver the pending messages: listeners, one encoding each, the client queues."""
        if self._flush_at is not None:
            self._flush_at.cancel()
            self._flush_at = None
        pending, self._pending = self._pending, []
        for msg in pending:
            self._deliver(msg)

    def _deliver(self, msg: AnyMessage) -> None:
        for listener in self._listeners:
            try:
                listener(msg)
            except Exception:  # a broken view must not break the telemetry of others
                log.exception("telemetry listener failed")
        kind = kind_of(msg)
        takers = [c for c in self.clients if c.wants(kind)]
        if takers:
            text = encode(msg)
            for c in takers:
                c.put(text)

    async def serve(self, client: Client, send: Send) -> str | None:
        """Send ``client`` its messages until the connection fails or stalls past the timeout;
        returns why a stalled client is cut off (None: the connection failed).

        One timeout context for the client's life, re-armed per message (``asyncio.wait_for``
        would create a task for every message: thousands a second with 20 clients)."""
        self.clients.add(client)
        loop = asyncio.get_running_loop()
        try:
            async with asyncio.timeout(None) as deadline:
                while True:
                    await client._wake.wait()
                    client._wake.clear()
                    while client.queue:
                        deadline.reschedule(loop.time() + self.send_timeout_s)
                        if client.dropped != client._reported_drops:
                            client._reported_drops = client.dropped
                            await send(encode(Dropped(client.dropped)))
                            client.sent += 1
                        await send(client.queue.popleft())
                        client.sent += 1
                    deadline.reschedule(None)  # idle is not stalled
        except TimeoutError:
            self.disconnected_slow += 1
            log.warning("telemetry client stalled for %.1f s: disconnected (dropped %d)",
                        self.send_timeout_s, client.dropped)  # fmt: skip
            return (f"too slow: took no message for {self.send_timeout_s:g} s "
                    f"({client.dropped} dropped)")  # fmt: skip
        finally:
            self.clients.discard(client)
        return None

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
